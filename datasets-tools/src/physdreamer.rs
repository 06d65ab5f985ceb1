//! `datasets-tools physdreamer DST`: a generated scene in the PhysDreamer layout (issue 25), as
//! `pipe`'s `scene.dataset: physdreamer` reads it (`pipe::io::physdreamer`).
//!
//! A potted plant in miniature: a static pot (0.12 × 0.10 × 0.12 m) with a leaf standing on it
//! (a thin upright plate, 0.03 × 0.21 × 0.09 m, the moving part), and a stone beside the pot
//! (0.06 × 0.04 × 0.06 m: clutter, not the object). The "trained" 3DGS is made, not trained:
//! one isotropic Gaussian (σ = 0.6 of the spacing, opacity 0.95, SH degree 0) at the centre of
//! every cell of a 1 cm lattice filling each box, coloured per part with bands (the leaf's
//! across its height, so its bending shows). The videos show the leaf swaying: a point at
//! height `h` above the pot is moved along x by `A·sin(2π·t/T)·(h/L)²` (`L` the leaf's height,
//! `T` the clip's length), rendered with `pipe`'s rasterizer over a uniform backdrop.
//!
//! Written:
//! - `point_cloud.ply`: the Gaussians (3DGS PLY);
//! - `clean_object_points.ply`: the centres of the pot's and the leaf's Gaussians (a subset
//!   of the Gaussians: the reader selects exactly them);
//! - `moving_part_points.ply`: the leaf sampled on another, coarser lattice (1.5 cm, offset,
//!   inset 1.5 cm from the pot's top), so the reader's tolerance is what selects the leaf;
//! - `transforms_train.json`: `camera_angle_x`, `w`, `h`, `fps` and a ring of cameras; the
//!   last one has no video (PhysDreamer lists more cameras than it has videos for);
//! - `videos/<camera>/NNNNN.png` and `masks/<camera>/NNNNN.png` (the object's visible
//!   coverage ≥ ½: the pot and the leaf, not the stone).
//!
//! Before anything is written the parts are selected as `pipe` selects them and compared with
//! the construction: exactly the leaf moves, exactly the pot and the leaf are the object. The
//! output is a function of the arguments only (bit-identical across runs and thread counts).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::DVec3;
use pipe::io::{image as pimage, physdreamer, ply};
use pipe::scene::camera::Camera;
use pipe::scene::gaussians::Gaussians;
use serde_json::json;

use crate::two_material::cameras::Ring;

/// Lattice spacing of the Gaussians (m).
const SPACING: f64 = 0.01;
/// Spacing of the moving part's selection points (m).
const MOVING_SPACING: f64 = 0.015;
/// Horizontal field of view (degrees).
const FOV_X_DEG: f64 = 40.0;
/// 0th-order SH constant.
const SH_C0: f64 = 0.282_094_791_773_878_1;
/// The backdrop of the videos (RGB in [0, 1]).
const BACKDROP: [f32; 3] = [0.86, 0.89, 0.93];

/// The parts: (name, lower corner, upper corner) in metres.
const POT: ([f64; 3], [f64; 3]) = ([-0.06, 0.0, -0.06], [0.06, 0.10, 0.06]);
const LEAF: ([f64; 3], [f64; 3]) = ([-0.015, 0.10, -0.045], [0.015, 0.31, 0.045]);
const STONE: ([f64; 3], [f64; 3]) = ([0.12, 0.0, -0.03], [0.18, 0.04, 0.03]);

/// `datasets-tools physdreamer` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Destination folder (created; it must not exist or be empty).
    pub dst: PathBuf,
    /// Image width and height (pixels).
    #[arg(long, default_value_t = 80)]
    pub size: u32,
    /// Frames per video.
    #[arg(long, default_value_t = 6)]
    pub frames: u32,
    /// Cameras with a video (one more camera is listed without one).
    #[arg(long, default_value_t = 4)]
    pub views: u16,
    /// Frames per second (`fps` in transforms_train.json).
    #[arg(long, default_value_t = 24.0)]
    pub fps: f64,
    /// Sway of the leaf's top along x (m).
    #[arg(long, default_value_t = 0.04, allow_negative_numbers = true)]
    pub amplitude: f64,
}

impl Args {
    fn check(&self) -> Result<()> {
        if !(16..=1024).contains(&self.size) {
            bail!("--size {}: must be from 16 to 1024 pixels", self.size);
        }
        if !(1..=500).contains(&self.frames) {
            bail!("--frames {}: must be from 1 to 500", self.frames);
        }
        if !(1..=100).contains(&self.views) {
            bail!("--views {}: must be from 1 to 100", self.views);
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            bail!("--fps {}: must be a finite number > 0", self.fps);
        }
        if !(self.amplitude.is_finite() && self.amplitude.abs() <= 0.1) {
            bail!("--amplitude {}: must be within ±0.1 m", self.amplitude);
        }
        Ok(())
    }
}

/// Which part a Gaussian belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Part {
    Pot,
    Leaf,
    Stone,
}

/// Centres of the cells of side `a` filling the box `lo..hi` (whose sides are multiples of `a`).
fn lattice(lo: DVec3, hi: DVec3, a: f64) -> Vec<DVec3> {
    let n = ((hi - lo) / a).round().as_ivec3();
    let mut out = Vec::with_capacity((n.x * n.y * n.z).max(0) as usize);
    for j in 0..n.y {
        for i in 0..n.x {
            for k in 0..n.z {
                out.push(lo + (DVec3::new(f64::from(i), f64::from(j), f64::from(k)) + 0.5) * a);
            }
        }
    }
    out
}

fn corner(c: [f64; 3]) -> DVec3 {
    DVec3::from_array(c)
}

/// Colour (RGB in [0, 1]) of a Gaussian of `part` at `x`.
fn colour(part: Part, x: DVec3) -> [f64; 3] {
    let band = |h: f64| ((h / 0.03).floor() as i64).rem_euclid(2) == 0;
    match part {
        Part::Pot => match band(x.y) {
            true => [0.72, 0.38, 0.22],
            false => [0.60, 0.30, 0.17],
        },
        Part::Leaf => match band(x.y - LEAF.0[1]) {
            true => [0.22, 0.58, 0.20],
            false => [0.78, 0.80, 0.25],
        },
        Part::Stone => [0.45, 0.46, 0.50],
    }
}

/// The scene's Gaussians and the part of each.
fn gaussians() -> (Gaussians, Vec<Part>) {
    let mut centres = Vec::new();
    let mut parts = Vec::new();
    for (part, (lo, hi)) in [(Part::Pot, POT), (Part::Leaf, LEAF), (Part::Stone, STONE)] {
        let x = lattice(corner(lo), corner(hi), SPACING);
        parts.extend(std::iter::repeat_n(part, x.len()));
        centres.extend(x);
    }
    let n = centres.len();
    let opacity: f64 = 0.95;
    let g = Gaussians {
        sh_degree: 0,
        id: (0..n as u32).collect(),
        position: centres.iter().map(|x| x.as_vec3().to_array()).collect(),
        log_scale: vec![[(0.6 * SPACING).ln() as f32; 3]; n],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
        opacity_logit: vec![(opacity / (1.0 - opacity)).ln() as f32; n],
        sh: centres
            .iter()
            .zip(&parts)
            .flat_map(|(x, p)| colour(*p, *x).map(|c| ((c - 0.5) / SH_C0) as f32))
            .collect(),
        simulated: vec![true; n],
    };
    (g, parts)
}

/// The moving part's selection: the leaf on a coarser lattice, inset from the pot.
fn moving_points() -> Vec<DVec3> {
    let (lo, hi) = (corner(LEAF.0), corner(LEAF.1));
    let inset = DVec3::new(0.0, MOVING_SPACING, 0.0);
    lattice(lo + inset, hi, MOVING_SPACING)
}

/// The Gaussians of frame `frame`: the leaf swayed.
fn swayed(g: &Gaussians, parts: &[Part], args: &Args, frame: u32) -> Gaussians {
    let t = f64::from(frame) / f64::from(args.frames);
    let height = LEAF.1[1] - LEAF.0[1];
    let shift = args.amplitude * (2.0 * std::f64::consts::PI * t).sin();
    let mut out = g.clone();
    for (p, part) in out.position.iter_mut().zip(parts) {
        if *part == Part::Leaf {
            let h = (f64::from(p[1]) - LEAF.0[1]) / height;
            p[0] = (f64::from(p[0]) + shift * h * h) as f32;
        }
    }
    out
}

/// RGB render (8-bit) of `g` over the backdrop, and the object's coverage (8-bit, 0/255 at ½).
fn render(g: &Gaussians, parts: &[Part], cam: &Camera) -> Result<(Vec<u8>, Vec<u8>)> {
    let rcam = pipe::scene::splat::render_camera(cam);
    let image = pipe_render::render(
        &pipe::scene::splat::render_gaussians(g),
        &rcam,
        &pipe_render::RenderOptions {
            background: BACKDROP,
            ..Default::default()
        },
    )?;
    // The object's visible coverage: the same Gaussians coloured 1 (object) or 0 (clutter)
    // over 0.
    let mut indicator = g.clone();
    for (c, part) in indicator.sh.chunks_exact_mut(3).zip(parts) {
        let v = if *part == Part::Stone { 0.0 } else { 1.0 };
        c.fill(((v - 0.5) / SH_C0) as f32);
    }
    let coverage = pipe_render::render(
        &pipe::scene::splat::render_gaussians(&indicator),
        &rcam,
        &pipe_render::RenderOptions::default(),
    )?;
    let mask = coverage
        .image
        .iter()
        .map(|p| if p[0] >= 0.5 { 255 } else { 0 })
        .collect();
    Ok((pipe::scene::splat::to_rgb8(&image.image), mask))
}

/// The ring of cameras: `views + 1` around the pot, a sphere of 0.22 m about the target
/// filling 95 % of the field of view.
fn ring(args: &Args) -> Ring {
    let target = DVec3::new(0.02, 0.14, 0.0);
    let radius = 0.22;
    Ring {
        views: args.views + 1,
        target,
        distance: radius / (0.95 * 0.5 * FOV_X_DEG.to_radians()).sin(),
        elevation_deg: 20.0,
        elevation_swing_deg: 5.0,
        azimuth0_deg: 60.0,
        fov_x_deg: FOV_X_DEG,
    }
}

/// Camera `k` of the ring for `size`² images: its OpenGL `c2w` in OpenCV axes (the y and z
/// columns negated), `f = (size/2) / tan(fov/2)`, the principal point at the centre.
fn ring_camera(ring: &Ring, k: u16, size: u32) -> Camera {
    let c2w = ring.c2w(k);
    let half = 0.5 * f64::from(size);
    let focal = half / (0.5 * FOV_X_DEG.to_radians()).tan();
    let mut w = [0.0; 12];
    for i in 0..3 {
        w[i * 4] = c2w[i][0];
        w[i * 4 + 1] = -c2w[i][1];
        w[i * 4 + 2] = -c2w[i][2];
        w[i * 4 + 3] = c2w[i][3];
    }
    Camera::new(&w, [focal, focal, half, half], size, size)
}

/// Camera `k`'s name (the stem of its image, naming its folders).
fn camera_name(k: u16) -> String {
    format!("frame_{k:05}")
}

/// Writes the scene into `args.dst`, which must not exist or be empty; a run that fails
/// leaves it as it found it.
pub fn run(args: &Args) -> Result<()> {
    args.check()?;
    crate::into_empty_folder(&args.dst, || write_scene(args))
}

/// [`run`] once `args.dst` is known to be free.
fn write_scene(args: &Args) -> Result<()> {
    let dst = &args.dst;
    let (g, parts) = gaussians();
    let object: Vec<[f32; 3]> = g
        .position
        .iter()
        .zip(&parts)
        .filter(|(_, p)| **p != Part::Stone)
        .map(|(x, _)| *x)
        .collect();
    let moving: Vec<[f32; 3]> = moving_points()
        .iter()
        .map(|x| x.as_vec3().to_array())
        .collect();
    check_selection(&g, &parts, &object, &moving)?;

    std::fs::create_dir_all(dst).with_context(|| format!("creating {}", dst.display()))?;
    ply::write_gaussians(&dst.join("point_cloud.ply"), &g)?;
    ply::write_points(&dst.join("clean_object_points.ply"), &object, None)?;
    ply::write_points(&dst.join("moving_part_points.ply"), &moving, None)?;
    let ring = ring(args);
    let frames: Vec<_> = (0..ring.views)
        .map(|k| {
            let c2w = ring.c2w(k);
            let mut m: Vec<Vec<f64>> = c2w.iter().map(|r| r.to_vec()).collect();
            m.push(vec![0.0, 0.0, 0.0, 1.0]);
            json!({"file_path": format!("./images/{}.png", camera_name(k)), "transform_matrix": m})
        })
        .collect();
    let transforms = json!({
        "camera_angle_x": FOV_X_DEG.to_radians(),
        "w": args.size,
        "h": args.size,
        "fps": args.fps,
        "frames": frames,
    });
    let path = dst.join("transforms_train.json");
    std::fs::write(&path, serde_json::to_string_pretty(&transforms)? + "\n")
        .with_context(|| format!("writing {}", path.display()))?;
    let cameras: Vec<Camera> = (0..args.views)
        .map(|k| ring_camera(&ring, k, args.size))
        .collect();
    for (k, cam) in cameras.iter().enumerate() {
        for sub in ["videos", "masks"] {
            let d = dst.join(sub).join(camera_name(k as u16));
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
        }
        for f in 0..args.frames {
            let (rgb, mask) = render(&swayed(&g, &parts, args, f), &parts, cam)?;
            let name = format!("{}/{f:05}.png", camera_name(k as u16));
            pimage::write_rgb8(
                &dst.join("videos").join(&name),
                &pimage::Rgb8 {
                    width: args.size,
                    height: args.size,
                    data: rgb,
                },
            )?;
            pimage::write_gray8(&dst.join("masks").join(&name), args.size, args.size, &mask)?;
        }
    }
    // Read back as the pipeline reads the scene: the cameras must be the ones drawn from.
    let scene = physdreamer::read_scene(dst)?;
    for img in &scene.capture.images {
        let read = Camera::new(&img.world_from_camera, img.intrinsics, args.size, args.size);
        let drawn = cameras[usize::from(img.view)];
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * (1.0 + a.abs());
        let m = |c: &Camera| {
            let r = c.world_from_camera_rot.to_cols_array();
            let mut v = r.to_vec();
            v.extend(c.centre_world.to_array());
            v.extend([c.fx, c.fy, c.cx, c.cy]);
            v
        };
        if !m(&read).iter().zip(m(&drawn)).all(|(a, b)| close(*a, b)) {
            bail!(
                "camera {} reads back differently from how it was drawn",
                img.view
            );
        }
    }
    println!(
        "physdreamer scene: {} Gaussians ({} pot, {} leaf: the moving part, {} stone: clutter), \
         {} cameras with {} frames of {}×{} px, 1 camera without a video",
        g.len(),
        parts.iter().filter(|p| **p == Part::Pot).count(),
        parts.iter().filter(|p| **p == Part::Leaf).count(),
        parts.iter().filter(|p| **p == Part::Stone).count(),
        args.views,
        args.frames,
        args.size,
        args.size
    );
    Ok(())
}

/// The selection files select exactly the leaf (moving) and the pot and leaf (object), as
/// `pipe` selects them from the values as written (float32).
fn check_selection(
    g: &Gaussians,
    parts: &[Part],
    object: &[[f32; 3]],
    moving: &[[f32; 3]],
) -> Result<()> {
    let d = |x: &[[f32; 3]]| -> Vec<DVec3> {
        x.iter()
            .map(|p| DVec3::from_array(p.map(f64::from)))
            .collect()
    };
    let sel = pipe::scene::parts::select(&d(&g.position), Some(&d(object)), Some(&d(moving)))?;
    for (i, part) in parts.iter().enumerate() {
        if sel.moving[i] != (*part == Part::Leaf) || sel.object[i] != (*part != Part::Stone) {
            bail!(
                "Gaussian {i} ({part:?} at {:?}) is selected as moving {} / object {}: the \
                 selection points do not select the parts",
                g.position[i],
                sel.moving[i],
                sel.object[i]
            );
        }
    }
    Ok(())
}
