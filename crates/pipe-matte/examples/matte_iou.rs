//! Mattes every frame of a PAC-NeRF-layout scene against its camera's plate and prints
//! IoU against the ground-truth masks.
//!
//! ```text
//! cargo run -p pipe-matte --release --example matte_iou -- <scene_dir> [--downscale N] [--set field=value]...
//! ```
//!
//! Reads `<scene_dir>/data/r_<cam>_<frame>.png`, plates `r_<cam>_-1.png` and
//! `<scene_dir>/gt/masks/m_<cam>_<frame>.png` (binarised at 128). `--downscale N`
//! box-averages image, plate and GT alpha over NxN blocks first. `--set` overrides one
//! `MatteParams` field (e.g. `--set max_hole_area=8`) for tuning.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use pipe_matte::{Mask, MatteParams, RgbImageView, iou, matte};

/// Reads a PNG as `(bytes, width, height)` with `channels` = 3 (RGB) or 1 (luma).
fn load(path: &Path, channels: usize) -> Result<(Vec<u8>, usize, usize), String> {
    let img = image::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data = if channels == 3 {
        img.into_rgb8().into_raw()
    } else {
        img.into_luma8().into_raw()
    };
    Ok((data, w, h))
}

/// Box-averages `n`x`n` blocks (rounded), cropping any remainder.
fn downscale(data: &[u8], w: usize, h: usize, ch: usize, n: usize) -> (Vec<u8>, usize, usize) {
    if n <= 1 {
        return (data.to_vec(), w, h);
    }
    let (ow, oh) = (w / n, h / n);
    let area = (n * n) as u32;
    let mut out = Vec::with_capacity(ow * oh * ch);
    for y in 0..oh {
        for x in 0..ow {
            for c in 0..ch {
                let mut s = 0u32;
                for dy in 0..n {
                    for dx in 0..n {
                        s += u32::from(data[((y * n + dy) * w + x * n + dx) * ch + c]);
                    }
                }
                out.push(u8::try_from((s + area / 2) / area).unwrap_or(u8::MAX));
            }
        }
    }
    (out, ow, oh)
}

/// Applies one `field=value` override to `params`.
fn set_param(params: &mut MatteParams, kv: &str) -> Result<(), String> {
    let (key, value) = kv
        .split_once('=')
        .ok_or_else(|| format!("--set expects field=value, got {kv:?}"))?;
    let bad = |e: &dyn std::fmt::Display| format!("--set {kv}: {e}");
    match key {
        "change_threshold" => params.change_threshold = value.parse().map_err(|e| bad(&e))?,
        "ratio_offset" => params.ratio_offset = value.parse().map_err(|e| bad(&e))?,
        "shadow_max_spread" => params.shadow_max_spread = value.parse().map_err(|e| bad(&e))?,
        "shadow_max_log_gain" => params.shadow_max_log_gain = value.parse().map_err(|e| bad(&e))?,
        "majority_filter" => params.majority_filter = value.parse().map_err(|e| bad(&e))?,
        "min_component_area" => params.min_component_area = value.parse().map_err(|e| bad(&e))?,
        "max_hole_area" => params.max_hole_area = value.parse().map_err(|e| bad(&e))?,
        "boundary_change_threshold" => {
            params.boundary_change_threshold = value.parse().map_err(|e| bad(&e))?;
        }
        _ => return Err(format!("--set: unknown MatteParams field {key:?}")),
    }
    Ok(())
}

fn run(scene: &Path, n: usize, params: &MatteParams) -> Result<(), String> {
    let data = scene.join("data");
    let mut rows: Vec<(f64, usize, usize)> = Vec::new();
    let mut elapsed = Duration::ZERO;
    for cam in 0.. {
        let plate_path = data.join(format!("r_{cam}_-1.png"));
        if !plate_path.exists() {
            break;
        }
        let (p, w, h) = load(&plate_path, 3)?;
        let (p, pw, ph) = downscale(&p, w, h, 3, n);
        let plate = RgbImageView::new(&p, pw, ph).map_err(|e| e.to_string())?;
        // Frames need not be contiguous (the composite fixtures keep a few).
        for frame in 0..1000 {
            let img_path = data.join(format!("r_{cam}_{frame}.png"));
            if !img_path.exists() {
                continue;
            }
            let (i, w, h) = load(&img_path, 3)?;
            let (i, iw, ih) = downscale(&i, w, h, 3, n);
            let (g, gw, gh) = load(&scene.join(format!("gt/masks/m_{cam}_{frame}.png")), 1)?;
            let (g, gw, gh) = downscale(&g, gw, gh, 1, n);
            let gt = Mask::from_threshold(gw, gh, &g, 128).map_err(|e| e.to_string())?;
            let image = RgbImageView::new(&i, iw, ih).map_err(|e| e.to_string())?;
            let t0 = Instant::now();
            let mask = matte(&image, &plate, params).map_err(|e| e.to_string())?;
            elapsed += t0.elapsed();
            rows.push((iou(&mask, &gt), cam, frame));
        }
    }
    if rows.is_empty() {
        return Err(format!("no frames found under {}", data.display()));
    }
    let mean = rows.iter().map(|r| r.0).sum::<f64>() / rows.len() as f64;
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let name = scene.file_name().unwrap_or_default().to_string_lossy();
    let worst: Vec<String> = rows
        .iter()
        .take(5)
        .map(|(v, c, f)| format!("(cam {c}, frame {f}) {v:.4}"))
        .collect();
    let mut out = std::io::stdout().lock();
    // A closed stdout (e.g. piped into `head`) is not an error worth reporting.
    let _ = writeln!(
        out,
        "{name} downscale={n}: {} images, mean IoU {mean:.4}, min IoU {:.4}, {:.2} ms/image",
        rows.len(),
        rows[0].0,
        elapsed.as_secs_f64() * 1e3 / rows.len() as f64
    );
    let _ = writeln!(out, "  worst: {}", worst.join(", "));
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let mut scene: Option<PathBuf> = None;
    let mut n = 1usize;
    let mut params = MatteParams::default();
    while let Some(a) = args.next() {
        if a == "--set" {
            let kv = args.next().unwrap_or_default();
            if let Err(e) = set_param(&mut params, &kv) {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        } else if a == "--downscale" {
            match args.next().and_then(|v| v.parse().ok()) {
                Some(v) if v >= 1 => n = v,
                _ => {
                    eprintln!("--downscale needs a positive integer");
                    return ExitCode::FAILURE;
                }
            }
        } else {
            scene = Some(PathBuf::from(a));
        }
    }
    let Some(scene) = scene else {
        eprintln!("usage: matte_iou <scene_dir> [--downscale N] [--set field=value]...");
        return ExitCode::FAILURE;
    };
    match run(&scene, n, &params) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
