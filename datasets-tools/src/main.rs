//! `datasets-tools`: reshape scenes in the PAC-NeRF layout.
//!
//! `datasets-tools downscale SRC DST --factor 2 [--frames 0,4,8] [--views 0,1,2]` writes a
//! smaller copy of a scene: every image and plate box-filtered by `factor`, the intrinsics
//! scaled to match (fx/f, fy/f, cx/f, cy/f), ground-truth masks box-filtered into soft alpha,
//! `gt/params.json` copied. The repo's test and demo scene was made this way.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use serde_json::Value;

#[derive(Debug, Parser)]
#[command(
    name = "datasets-tools",
    about = "Make and reshape scenes in the PAC-NeRF layout"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Write a down-scaled (and optionally frame/view-subset) copy of a PAC-NeRF scene.
    Downscale {
        /// Source scene folder (holds all_data.json).
        src: PathBuf,
        /// Destination folder (created).
        dst: PathBuf,
        /// Integer box-filter factor.
        #[arg(long, default_value_t = 2)]
        factor: u32,
        /// Keep only these frames (comma-separated); plates are always kept.
        #[arg(long, value_delimiter = ',')]
        frames: Vec<i64>,
        /// Keep only these cameras (comma-separated).
        #[arg(long, value_delimiter = ',')]
        views: Vec<i64>,
    },
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Downscale {
            src,
            dst,
            factor,
            frames,
            views,
        } => downscale(&src, &dst, factor, &frames, &views),
    }
}

fn parse_name(name: &str) -> Option<(i64, i64)> {
    let stem = name
        .rsplit('/')
        .next()?
        .strip_prefix("r_")?
        .strip_suffix(".png")?;
    let (a, b) = stem.split_once('_')?;
    Some((a.parse().ok()?, b.parse().ok()?))
}

fn downscale(src: &Path, dst: &Path, factor: u32, frames: &[i64], views: &[i64]) -> Result<()> {
    if factor == 0 {
        bail!("--factor must be at least 1");
    }
    let json_path = src.join("all_data.json");
    let entries: Vec<Value> = serde_json::from_slice(
        &fs::read(&json_path).with_context(|| format!("reading {}", json_path.display()))?,
    )
    .with_context(|| format!("parsing {}", json_path.display()))?;
    fs::create_dir_all(dst.join("data"))?;
    let mut kept = Vec::new();
    for mut e in entries {
        let file = e["file_path"]
            .as_str()
            .context("entry without file_path")?
            .to_string();
        let (view, frame) =
            parse_name(&file).with_context(|| format!("unexpected file name {file}"))?;
        if (!views.is_empty() && !views.contains(&view))
            || (frame >= 0 && !frames.is_empty() && !frames.contains(&frame))
        {
            continue;
        }
        let rel = file.trim_start_matches("./");
        let img = image::open(src.join(rel))
            .with_context(|| format!("reading {}", src.join(rel).display()))?
            .into_rgb8();
        let small = box_filter_rgb(&img, factor);
        small
            .save(dst.join(rel))
            .with_context(|| format!("writing {}", dst.join(rel).display()))?;
        let k = e["intrinsic"].as_array_mut().context("intrinsic")?;
        for (r, c) in [(0, 0), (0, 2), (1, 1), (1, 2)] {
            let v = k[r][c].as_f64().context("intrinsic value")?;
            k[r][c] = serde_json::json!(v / f64::from(factor));
        }
        if frame >= 0 {
            let m = src.join("gt/masks").join(format!("m_{view}_{frame}.png"));
            if m.exists() {
                fs::create_dir_all(dst.join("gt/masks"))?;
                let g = image::open(&m)?.into_luma8();
                box_filter_luma(&g, factor)
                    .save(dst.join("gt/masks").join(format!("m_{view}_{frame}.png")))?;
            }
        }
        kept.push(e);
    }
    if kept.is_empty() {
        bail!("no image matched --frames/--views");
    }
    fs::write(
        dst.join("all_data.json"),
        serde_json::to_string_pretty(&kept)?,
    )?;
    let params = src.join("gt/params.json");
    if params.exists() {
        fs::create_dir_all(dst.join("gt"))?;
        fs::copy(&params, dst.join("gt/params.json"))?;
    }
    println!("wrote {} images to {}", kept.len(), dst.display());
    Ok(())
}

fn box_filter_rgb(img: &image::RgbImage, f: u32) -> image::RgbImage {
    let (w, h) = (img.width() / f, img.height() / f);
    image::RgbImage::from_fn(w, h, |x, y| {
        let mut acc = [0u32; 3];
        for dy in 0..f {
            for dx in 0..f {
                let p = img.get_pixel(x * f + dx, y * f + dy);
                for c in 0..3 {
                    acc[c] += u32::from(p[c]);
                }
            }
        }
        let n = f * f;
        image::Rgb(acc.map(|a| ((a + n / 2) / n) as u8))
    })
}

fn box_filter_luma(img: &image::GrayImage, f: u32) -> image::GrayImage {
    let (w, h) = (img.width() / f, img.height() / f);
    image::GrayImage::from_fn(w, h, |x, y| {
        let mut acc = 0u32;
        for dy in 0..f {
            for dx in 0..f {
                acc += u32::from(img.get_pixel(x * f + dx, y * f + dy)[0]);
            }
        }
        let n = f * f;
        image::Luma([((acc + n / 2) / n) as u8])
    })
}
