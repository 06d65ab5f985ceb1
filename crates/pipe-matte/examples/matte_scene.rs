//! Mattes every frame of a PAC-NeRF-layout scene with all its views together
//! ([`pipe_matte::matte_frame`]) and prints IoU against the ground-truth masks and the
//! multi-view agreement and consistency (of the matte's masks and of the true ones).
//!
//! ```text
//! cargo run -p pipe-matte --release --example matte_scene -- <scene_dir> [--single] [--dump DIR] [--set field=value]...
//! ```
//!
//! `--single` mattes each image alone ([`pipe_matte::matte`]) for comparison; `--dump DIR`
//! writes each mask as `DIR/m_<cam>_<frame>.png`; `--set` overrides one `MultiViewParams`
//! field (`change_threshold`, `block_change_threshold`, `ground_min_change`, `ground_lit_views`, `photo_rounds`, `support_views`,
//! `photo_tolerance`, `hull_grid`, `hull_max_misses`, and the graph cut's `cut_rounds`,
//! `cut_smoothness`, `cut_evidence_cost`, `cut_shadow_cost`, `cut_agree_cost`, `cut_pull`,
//! `witness_tolerance`, `witness_noise_factor`, `witness_min_disagree`, `witness_min_height`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use glam::{DMat3, DVec3};
use pipe_matte::{
    Mask, MultiViewParams, Pinhole, RgbImageView, View, agreement_and_consistency, iou, matte,
    matte_frame,
};

struct Entry {
    cam: usize,
    frame: i64,
    camera: Pinhole,
    path: PathBuf,
}

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

/// Cameras of `all_data.json`, OpenGL c2w converted to OpenCV axes.
fn entries(scene: &Path) -> Result<Vec<Entry>, String> {
    let path = scene.join("all_data.json");
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for e in json.as_array().ok_or("all_data.json is not a list")? {
        let file = e["file_path"].as_str().ok_or("file_path")?;
        let stem = file.rsplit('/').next().unwrap_or_default();
        let stem = stem.trim_start_matches("r_").trim_end_matches(".png");
        let (c, f) = stem.split_once('_').ok_or("file name")?;
        let m = |r: usize, c: usize| e["c2w"][r][c].as_f64().unwrap_or(f64::NAN);
        let k = |r: usize, c: usize| e["intrinsic"][r][c].as_f64().unwrap_or(f64::NAN);
        let col = |c: usize, s: f64| DVec3::new(s * m(0, c), s * m(1, c), s * m(2, c));
        let path = scene.join(file.trim_start_matches("./"));
        let (_, w, h) = load(&path, 3)?;
        out.push(Entry {
            cam: c.parse().map_err(|_| "camera index")?,
            frame: f.parse().map_err(|_| "frame index")?,
            camera: Pinhole {
                world_from_camera_rot: DMat3::from_cols(col(0, 1.0), col(1, -1.0), col(2, -1.0)),
                centre_world: DVec3::new(m(0, 3), m(1, 3), m(2, 3)),
                fx: k(0, 0),
                fy: k(1, 1),
                cx: k(0, 2),
                cy: k(1, 2),
                width: w as u32,
                height: h as u32,
            },
            path,
        });
    }
    Ok(out)
}

fn run(
    scene: &Path,
    single: bool,
    dump: Option<&Path>,
    params: &MultiViewParams,
) -> Result<(), String> {
    let all = entries(scene)?;
    let plates: BTreeMap<usize, (Vec<u8>, usize, usize)> = all
        .iter()
        .filter(|e| e.frame < 0)
        .map(|e| load(&e.path, 3).map(|p| (e.cam, p)))
        .collect::<Result<_, _>>()?;
    let mut frames: BTreeMap<i64, Vec<&Entry>> = BTreeMap::new();
    for e in all.iter().filter(|e| e.frame >= 0) {
        frames.entry(e.frame).or_default().push(e);
    }
    let mut rows: Vec<(f64, usize, i64)> = Vec::new();
    let mut agreements: Vec<(f64, usize, i64)> = Vec::new();
    let mut gt_agreements: Vec<(f64, usize, i64)> = Vec::new();
    let mut consistencies: Vec<(f64, usize, i64)> = Vec::new();
    let mut gt_consistencies: Vec<(f64, usize, i64)> = Vec::new();
    let mut matte_seconds = 0.0;
    for (frame, list) in &frames {
        let images: Vec<(Vec<u8>, usize, usize)> = list
            .iter()
            .map(|e| load(&e.path, 3))
            .collect::<Result<_, _>>()?;
        let views: Vec<View<'_>> = list
            .iter()
            .zip(&images)
            .map(|(e, (d, w, h))| {
                let (p, pw, ph) = &plates[&e.cam];
                Ok(View {
                    camera: e.camera,
                    image: RgbImageView::new(d, *w, *h).map_err(|e| e.to_string())?,
                    plate: RgbImageView::new(p, *pw, *ph).map_err(|e| e.to_string())?,
                })
            })
            .collect::<Result<_, String>>()?;
        let (masks, agree, consistent) = if single {
            let m: Vec<Mask> = views
                .iter()
                .map(|v| matte(&v.image, &v.plate, &params.view).map_err(|e| e.to_string()))
                .collect::<Result<_, _>>()?;
            (m, vec![f64::NAN; views.len()], vec![f64::NAN; views.len()])
        } else {
            let start = std::time::Instant::now();
            let r = matte_frame(&views, params).map_err(|e| e.to_string())?;
            matte_seconds += start.elapsed().as_secs_f64();
            (r.masks, r.agreement, r.consistency)
        };
        let gts: Vec<Mask> = list
            .iter()
            .map(|e| {
                let (g, gw, gh) =
                    load(&scene.join(format!("gt/masks/m_{}_{frame}.png", e.cam)), 1)?;
                Mask::from_threshold(gw, gh, &g, 128).map_err(|e| e.to_string())
            })
            .collect::<Result<_, _>>()?;
        let cameras: Vec<Pinhole> = list.iter().map(|e| e.camera).collect();
        let (gt_agree, gt_consistent) = agreement_and_consistency(&cameras, &gts, params);
        for ((a, c), e) in gt_agree.iter().zip(&gt_consistent).zip(list) {
            gt_agreements.push((*a, e.cam, *frame));
            gt_consistencies.push((*c, e.cam, *frame));
        }
        for (c, e) in consistent.iter().zip(list) {
            consistencies.push((*c, e.cam, *frame));
        }
        for (((e, m), a), gt) in list.iter().zip(&masks).zip(&agree).zip(&gts) {
            rows.push((iou(m, gt), e.cam, *frame));
            agreements.push((*a, e.cam, *frame));
            if let Some(dir) = dump {
                let out = dir.join(format!("m_{}_{frame}.png", e.cam));
                image::GrayImage::from_raw(m.width() as u32, m.height() as u32, m.data().to_vec())
                    .ok_or("mask size")?
                    .save(&out)
                    .map_err(|e| format!("{}: {e}", out.display()))?;
            }
        }
    }
    let mean = rows.iter().map(|r| r.0).sum::<f64>() / rows.len().max(1) as f64;
    let per_frame: Vec<String> = frames
        .keys()
        .map(|f| {
            let v: Vec<f64> = rows.iter().filter(|r| r.2 == *f).map(|r| r.0).collect();
            format!("{f}: {:.3}", v.iter().sum::<f64>() / v.len().max(1) as f64)
        })
        .collect();
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    agreements.sort_by(|a, b| a.0.total_cmp(&b.0));
    gt_agreements.sort_by(|a, b| a.0.total_cmp(&b.0));
    consistencies.sort_by(|a, b| a.0.total_cmp(&b.0));
    gt_consistencies.sort_by(|a, b| a.0.total_cmp(&b.0));
    let name = scene.file_name().unwrap_or_default().to_string_lossy();
    let fmt = |v: &[(f64, usize, i64)]| {
        v.iter()
            .take(5)
            .map(|(v, c, f)| format!("(cam {c}, frame {f}) {v:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "{name} {}: {} images, mean IoU {mean:.4}, min IoU {:.4}",
        if single { "single-view" } else { "multi-view" },
        rows.len(),
        rows.first().map_or(f64::NAN, |r| r.0)
    );
    println!("  worst IoU: {}", fmt(&rows));
    println!("  mean IoU per frame: {}", per_frame.join(", "));
    if !single {
        println!(
            "  matte_frame: {:.3} s per frame ({} frames)",
            matte_seconds / frames.len().max(1) as f64,
            frames.len()
        );
        let amean = agreements.iter().map(|r| r.0).sum::<f64>() / agreements.len().max(1) as f64;
        println!("  agreement mean {amean:.4}; lowest: {}", fmt(&agreements));
        let cmean =
            consistencies.iter().map(|r| r.0).sum::<f64>() / consistencies.len().max(1) as f64;
        println!(
            "  consistency mean {cmean:.4}; lowest: {}",
            fmt(&consistencies)
        );
    }
    let gmean = gt_agreements.iter().map(|r| r.0).sum::<f64>() / gt_agreements.len().max(1) as f64;
    println!(
        "  ground truth's agreement mean {gmean:.4}; lowest: {}",
        fmt(&gt_agreements)
    );
    let gcmean =
        gt_consistencies.iter().map(|r| r.0).sum::<f64>() / gt_consistencies.len().max(1) as f64;
    println!(
        "  ground truth's consistency mean {gcmean:.4}; lowest: {}",
        fmt(&gt_consistencies)
    );
    Ok(())
}

fn set(params: &mut MultiViewParams, kv: &str) -> Result<(), String> {
    let (k, v) = kv.split_once('=').ok_or("--set expects field=value")?;
    let bad = |e: &dyn std::fmt::Display| format!("--set {kv}: {e}");
    match k {
        "change_threshold" => params.view.change_threshold = v.parse().map_err(|e| bad(&e))?,
        "block_change_threshold" => {
            params.view.block_change_threshold = v.parse().map_err(|e| bad(&e))?
        }
        "ground_min_change" => params.ground_min_change = v.parse().map_err(|e| bad(&e))?,
        "ground_lit_views" => params.ground_lit_views = v.parse().map_err(|e| bad(&e))?,
        "photo_rounds" => params.photo_rounds = v.parse().map_err(|e| bad(&e))?,
        "support_views" => params.support_views = v.parse().map_err(|e| bad(&e))?,
        "photo_tolerance" => params.photo_tolerance = v.parse().map_err(|e| bad(&e))?,
        "hull_grid" => params.hull_grid = v.parse().map_err(|e| bad(&e))?,
        "hull_max_misses" => params.hull_max_misses = v.parse().map_err(|e| bad(&e))?,
        "consistency_threshold" => params.consistency_threshold = v.parse().map_err(|e| bad(&e))?,
        "cut_rounds" => params.cut_rounds = v.parse().map_err(|e| bad(&e))?,
        "cut_smoothness" => params.cut_smoothness = v.parse().map_err(|e| bad(&e))?,
        "cut_evidence_cost" => params.cut_evidence_cost = v.parse().map_err(|e| bad(&e))?,
        "cut_shadow_cost" => params.cut_shadow_cost = v.parse().map_err(|e| bad(&e))?,
        "cut_agree_cost" => params.cut_agree_cost = v.parse().map_err(|e| bad(&e))?,
        "cut_pull" => params.cut_pull = v.parse().map_err(|e| bad(&e))?,
        "texture_radius" => params.texture_radius = v.parse().map_err(|e| bad(&e))?,
        "texture_min_plate_variance" => {
            params.texture_min_plate_variance = v.parse().map_err(|e| bad(&e))?
        }
        "texture_split" => params.texture_split = v.parse().map_err(|e| bad(&e))?,
        "texture_scale" => params.texture_scale = v.parse().map_err(|e| bad(&e))?,
        "shadow_max_zenith_deg" => params.shadow_max_zenith_deg = v.parse().map_err(|e| bad(&e))?,
        "cut_texture_cost" => params.cut_texture_cost = v.parse().map_err(|e| bad(&e))?,
        "witness_tolerance" => params.witness_tolerance = v.parse().map_err(|e| bad(&e))?,
        "witness_noise_factor" => params.witness_noise_factor = v.parse().map_err(|e| bad(&e))?,
        "witness_min_disagree" => params.witness_min_disagree = v.parse().map_err(|e| bad(&e))?,
        "witness_min_height" => params.witness_min_height = v.parse().map_err(|e| bad(&e))?,
        _ => return Err(format!("unknown field {k:?}")),
    }
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let (mut scene, mut single, mut dump) = (None, false, None);
    let mut params = MultiViewParams::default();
    while let Some(a) = args.next() {
        let r = match a.as_str() {
            "--single" => {
                single = true;
                Ok(())
            }
            "--dump" => {
                dump = args.next().map(PathBuf::from);
                Ok(())
            }
            "--set" => set(&mut params, &args.next().unwrap_or_default()),
            _ => {
                scene = Some(PathBuf::from(a));
                Ok(())
            }
        };
        if let Err(e) = r {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    }
    let Some(scene) = scene else {
        eprintln!("usage: matte_scene <scene_dir> [--single] [--dump DIR] [--set field=value]...");
        return ExitCode::FAILURE;
    };
    if let Some(d) = &dump {
        let _ = std::fs::create_dir_all(d);
    }
    match run(&scene, single, dump.as_deref(), &params) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
