//! `datasets-tools`: make and reshape scenes in the PAC-NeRF layout.
//!
//! `datasets-tools downscale SRC DST --factor 2 [--frames 0,4,8] [--views 0,1,2]` writes a
//! smaller copy of a scene: every image and plate box-filtered by `factor`, the intrinsics
//! scaled to match (fx/f, fy/f, cx/f, cy/f), ground-truth masks box-filtered into soft alpha,
//! `gt/params.json` copied. The repo's test and demo scene was made this way.
//!
//! `datasets-tools composite SRC DST --texture shadow-greys|greys-crimson|dark-grey|floor-tone --frames 0,5,9,13`
//! writes a matting test scene: SRC's cameras, plates and object silhouettes, the object
//! re-textured adversarially and its shadow cast on the plates ([`composite`]).
//!
//! `datasets-tools two-material DST [--size 100] [--frames 14] [--views 11] [--ratio 30] ...`
//! writes a generated scene of a bar whose halves differ in Young's modulus, simulated with
//! per-particle materials and ray-traced as the body its particles stand for ([`two_material`]).
//!
//! `datasets-tools physdreamer DST [--size 80] [--frames 6] [--views 4] ...` writes a generated
//! scene in the PhysDreamer layout: a pot, a swaying leaf on it (the moving part) and a stone
//! beside it (clutter), as Gaussians with the selection points and videos ([`physdreamer`]).
//!
//! `datasets-tools scene DST --family sand --youngs-modulus 2e5 --poisson-ratio 0.3
//! --friction-angle-deg 30 [--shape ball|bar|blob] ...` writes a generated scene of one
//! homogeneous object of any material family, with its truth ([`scene`]).

mod composite;
mod physdreamer;
mod resample;
mod scene;
mod shadow;
mod texture;
mod two_material;

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use glam::DVec3;
use serde_json::Value;

use resample::{box_filter_luma, box_filter_rgb};

#[derive(Debug, Parser)]
#[command(
    name = "datasets-tools",
    about = "Make and reshape scenes in the PAC-NeRF and PhysDreamer layouts"
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
    /// Write a matting test scene: SRC's cameras, plates and silhouettes (gt/masks), the
    /// object re-textured and its shadow cast along --light (needs gt/particles/<frame>.ply).
    Composite {
        /// Source scene folder (holds all_data.json, gt/masks and gt/particles).
        src: PathBuf,
        /// Destination folder (created).
        dst: PathBuf,
        /// The object's texture.
        #[arg(long, value_enum)]
        texture: texture::Texture,
        /// Frames to make (comma-separated).
        #[arg(long, value_delimiter = ',', required = true)]
        frames: Vec<i32>,
        /// Keep only these cameras (comma-separated; all when absent).
        #[arg(long, value_delimiter = ',')]
        views: Vec<u16>,
        /// The light's direction of travel x,y,z (y < 0).
        #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0.3, -1.0, 0.2], allow_negative_numbers = true)]
        light: Vec<f64>,
        /// Integer box-filter factor of the output.
        #[arg(long, default_value_t = 2)]
        factor: u32,
    },
    /// Write a generated scene: a bar whose halves differ in Young's modulus (--ratio),
    /// simulated with per-particle materials and ray-traced as the body its particles stand
    /// for, with its ground truth (gt/params.json, gt/particles, gt/masks).
    TwoMaterial(two_material::Args),
    /// Write a generated scene in the PhysDreamer layout: a static pot, a swaying leaf on it
    /// (the moving part) and a stone beside it (clutter) as a 3DGS `point_cloud.ply`, with
    /// `clean_object_points.ply`, `moving_part_points.ply`, `transforms_train.json`, and a
    /// video and masks per camera.
    Physdreamer(physdreamer::Args),
    /// Write a generated scene of one homogeneous object of any material family (bar, ball or
    /// blob), dropped onto the ground, simulated by `pipe simulate`'s path and ray-traced as
    /// the body its particles stand for, with its ground truth (gt/params.json, gt/particles, gt/masks,
    /// gt/scene.sim.yaml).
    Scene(scene::Args),
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
        Command::Composite {
            src,
            dst,
            texture,
            frames,
            views,
            light,
            factor,
        } => composite::composite(&composite::CompositeArgs {
            src: &src,
            dst: &dst,
            texture,
            light: DVec3::new(light[0], light[1], light[2]),
            frames: &frames,
            views: &views,
            factor,
        }),
        Command::TwoMaterial(args) => two_material::run(&args),
        Command::Physdreamer(args) => physdreamer::run(&args),
        Command::Scene(args) => scene::run(&args),
    }
}

/// `(camera, frame)` of a `./data/r_<camera>_<frame>.png` name.
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
        e = scale_intrinsics(e, factor)?;
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

/// An `all_data.json` entry with its intrinsics divided by `factor` (fx, fy, cx, cy).
fn scale_intrinsics(mut e: Value, factor: u32) -> Result<Value> {
    let k = e["intrinsic"].as_array_mut().context("intrinsic")?;
    for (r, c) in [(0, 0), (0, 2), (1, 1), (1, 2)] {
        let v = k[r][c].as_f64().context("intrinsic value")?;
        k[r][c] = serde_json::json!(v / f64::from(factor));
    }
    Ok(e)
}

/// Runs `write` to fill `dst`, which must not exist or be empty; a `write` that fails leaves
/// the folder as it found it (only what the run made is removed).
pub(crate) fn into_empty_folder(dst: &Path, write: impl FnOnce() -> Result<()>) -> Result<()> {
    let existed = dst.exists();
    if existed
        && fs::read_dir(dst)
            .with_context(|| format!("reading {}", dst.display()))?
            .next()
            .is_some()
    {
        bail!(
            "{}: exists and is not empty; remove it or choose another folder",
            dst.display()
        );
    }
    let written = write();
    if written.is_err() {
        let _ = if existed {
            fs::read_dir(dst).map(|entries| {
                for e in entries.flatten() {
                    let p = e.path();
                    let _ = if p.is_dir() {
                        fs::remove_dir_all(&p)
                    } else {
                        fs::remove_file(&p)
                    };
                }
            })
        } else {
            fs::remove_dir_all(dst)
        };
    }
    written
}
