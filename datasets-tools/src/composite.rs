//! `datasets-tools composite`: a matting test scene made from a real capture's cameras,
//! plates and object silhouettes, with an adversarial texture and a cast shadow.
//!
//! For every selected frame and camera of SRC (which must hold `gt/masks/` and
//! `gt/particles/<frame>.ply`):
//! 1. the object's silhouette is SRC's ground-truth alpha `a`;
//! 2. its colour at a pixel is the [`Texture`] at the rest position (frame 0) of the nearest
//!    visible particle (particles splatted into a depth buffer), times Lambert shading
//!    `0.7 + 0.45·max(0, n·(−L))`, plus ±3 levels of per-pixel noise (path-tracer grain);
//! 3. the background is the camera's plate times the [`GroundShadow`] of the frame's particles
//!    along the light `L`, looked up where the pixel's ray meets the ground y = 0;
//! 4. `I = a·object + (1 − a)·background`, then everything is box-filtered by `factor`.
//!
//! The scene is written in the PAC-NeRF layout (`all_data.json`, `data/`, `gt/masks/`) with
//! `gt/composite.json` recording how it was made.

use std::fs;
use std::path::Path;

use anyhow::{Context, Result, bail};
use glam::DVec3;
use pipe::io::{image as pimage, pacnerf, ply};
use pipe::scene::camera::Camera;
use serde_json::{Value, json};

use crate::resample::{box_filter_luma, box_filter_rgb};
use crate::shadow::{GroundShadow, ShadowParams};
use crate::texture::{self, Texture};

/// What to make.
#[derive(Debug, Clone)]
pub struct CompositeArgs<'a> {
    /// Source scene (cameras, plates, gt/masks, gt/particles).
    pub src: &'a Path,
    /// Destination folder.
    pub dst: &'a Path,
    /// The object's texture.
    pub texture: Texture,
    /// Light direction of travel.
    pub light: DVec3,
    /// Frames to make.
    pub frames: &'a [i32],
    /// Cameras to keep (all when empty).
    pub views: &'a [u16],
    /// Box-filter factor of the output.
    pub factor: u32,
}

/// Shadow of the sample scenes: full shadow dims the floor to ~exp(−1.1) ≈ 0.33.
fn shadow_params(light: DVec3) -> ShadowParams {
    ShadowParams {
        light,
        core: 0.008,
        penumbra_base: 0.004,
        penumbra_slope: 0.04,
        floor_factor: 0.33,
        cell: 0.003,
    }
}

fn to_dvec(p: &[f32; 3]) -> DVec3 {
    DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
}

fn read_particles(src: &Path, frame: i32) -> Result<Vec<DVec3>> {
    let path = src.join(format!("gt/particles/{frame}.ply"));
    let cloud = ply::read_points(&path)?;
    Ok(cloud.positions.iter().map(to_dvec).collect())
}

/// Median plate colour of the floor near the object (pixels whose ray meets the ground
/// within 1 m of the origin), over all cameras.
fn floor_colour(plates: &[(Camera, pimage::Rgb8)]) -> Result<[f64; 3]> {
    let mut ch: [Vec<u8>; 3] = Default::default();
    for (cam, plate) in plates {
        for y in 0..plate.height {
            for x in 0..plate.width {
                let near = cam
                    .ground_point(f64::from(x) + 0.5, f64::from(y) + 0.5)
                    .is_some_and(|g| g.x.hypot(g.z) < 1.0);
                if near {
                    let p = ((y * plate.width + x) * 3) as usize;
                    for (c, values) in ch.iter_mut().enumerate() {
                        values.push(plate.data[p + c]);
                    }
                }
            }
        }
    }
    if ch[0].is_empty() {
        bail!("no camera sees the ground near the origin");
    }
    Ok(ch.map(|mut v| {
        v.sort_unstable();
        f64::from(v[v.len() / 2])
    }))
}

/// Index of the nearest particle seen at each pixel (splats of radius 1.2 cm), then
/// propagated to the object pixels the splats miss (nearest filled pixel, 4-neighbour order).
fn visible_particles(cam: &Camera, points: &[DVec3], alpha: &[u8]) -> Vec<Option<usize>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut depth = vec![f64::INFINITY; w * h];
    let mut index: Vec<Option<usize>> = vec![None; w * h];
    for (i, p) in points.iter().enumerate() {
        let Some((u, v, z)) = cam.project(*p) else {
            continue;
        };
        let r = cam.fx * 0.012 / z;
        let (x0, x1) = ((u - r).floor().max(0.0), (u + r).ceil().min(w as f64 - 1.0));
        let (y0, y1) = ((v - r).floor().max(0.0), (v + r).ceil().min(h as f64 - 1.0));
        if x0 > x1 || y0 > y1 {
            continue;
        }
        for y in y0 as usize..=y1 as usize {
            for x in x0 as usize..=x1 as usize {
                let (dx, dy) = (x as f64 + 0.5 - u, y as f64 + 0.5 - v);
                if dx * dx + dy * dy <= r * r && z < depth[y * w + x] {
                    depth[y * w + x] = z;
                    index[y * w + x] = Some(i);
                }
            }
        }
    }
    let mut queue: std::collections::VecDeque<usize> =
        (0..w * h).filter(|&p| index[p].is_some()).collect();
    while let Some(p) = queue.pop_front() {
        let (x, y) = (p % w, p / w);
        let mut push = |q: usize| {
            if index[q].is_none() && alpha[q] > 0 {
                index[q] = index[p];
                queue.push_back(q);
            }
        };
        if x > 0 {
            push(p - 1);
        }
        if x + 1 < w {
            push(p + 1);
        }
        if y > 0 {
            push(p - w);
        }
        if y + 1 < h {
            push(p + w);
        }
    }
    index
}

/// One composite image at the source resolution.
#[allow(clippy::too_many_arguments)]
fn compose(
    cam: &Camera,
    plate: &pimage::Rgb8,
    alpha: &[u8],
    points: &[DVec3],
    rest: &[DVec3],
    normals: &[DVec3],
    shadow: &GroundShadow,
    args: &CompositeArgs<'_>,
    floor: [f64; 3],
    (view, frame): (u16, i32),
) -> Result<image::RgbImage> {
    let (w, h) = (plate.width, plate.height);
    let seen = visible_particles(cam, points, alpha);
    let light = args.light.normalize();
    let mut out = image::RgbImage::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let p = (y * w + x) as usize;
            let noise = |c: usize, amp: f64| amp * texture::pixel_noise(view, frame, x, y, c);
            let factor = cam
                .ground_point(f64::from(x) + 0.5, f64::from(y) + 0.5)
                .map_or(1.0, |g| shadow.factor(g.x, g.z));
            let bg: [f64; 3] = std::array::from_fn(|c| {
                let v = f64::from(plate.data[3 * p + c]) * factor;
                if factor < 0.995 { v + noise(c, 3.0) } else { v }
            });
            let a = f64::from(alpha[p]) / 255.0;
            let rgb: [f64; 3] = match seen[p] {
                Some(i) if a > 0.0 => {
                    let shade = 0.7 + 0.45 * normals[i].dot(-light).max(0.0);
                    let albedo = args.texture.albedo(rest[i], floor);
                    std::array::from_fn(|c| {
                        a * (albedo[c] * shade + noise(c + 3, 3.0)) + (1.0 - a) * bg[c]
                    })
                }
                Some(_) => bg,
                None if a > 0.0 => bail!(
                    "camera {view} frame {frame}: the object's silhouette has no particle in view"
                ),
                None => bg,
            };
            out.put_pixel(
                x,
                y,
                image::Rgb(rgb.map(|v| v.round().clamp(0.0, 255.0) as u8)),
            );
        }
    }
    Ok(out)
}

/// Writes the composite scene.
pub fn composite(args: &CompositeArgs<'_>) -> Result<()> {
    if args.factor == 0 {
        bail!("--factor must be at least 1");
    }
    if args.light.y >= 0.0 || !args.light.is_finite() {
        bail!(
            "--light {}: must be finite and point down (y < 0)",
            args.light
        );
    }
    let scene = pacnerf::read_scene(args.src)?;
    let views: Vec<u16> = scene
        .plates
        .keys()
        .copied()
        .filter(|v| args.views.is_empty() || args.views.contains(v))
        .collect();
    if views.is_empty() {
        bail!(
            "none of the cameras {:?} is in {}",
            args.views,
            args.src.display()
        );
    }
    let mut plates = Vec::new();
    for v in &views {
        let img = &scene.plates[v];
        let plate = pimage::read_rgb8(&img.path)?;
        let cam = Camera::new(
            &img.world_from_camera,
            img.intrinsics,
            plate.width,
            plate.height,
        );
        plates.push((cam, plate));
    }
    let floor = floor_colour(&plates)?;
    let rest = read_particles(args.src, 0)?;
    fs::create_dir_all(args.dst.join("data"))?;
    fs::create_dir_all(args.dst.join("gt/masks"))?;
    for &frame in args.frames {
        let points = read_particles(args.src, frame)?;
        if points.len() != rest.len() {
            bail!(
                "{}: {} particles, but frame 0 has {}",
                args.src.join(format!("gt/particles/{frame}.ply")).display(),
                points.len(),
                rest.len()
            );
        }
        let normals = texture::normals(&points, 0.025);
        let shadow = GroundShadow::cast(&points, &shadow_params(args.light));
        for (v, (cam, plate)) in views.iter().zip(&plates) {
            let mask_path = args.src.join(format!("gt/masks/m_{v}_{frame}.png"));
            let (mw, mh, alpha) = pimage::read_gray8(&mask_path)?;
            if (mw, mh) != (plate.width, plate.height) {
                bail!(
                    "{}: {mw}×{mh}, but the plate is {}×{}",
                    mask_path.display(),
                    plate.width,
                    plate.height
                );
            }
            let img = compose(
                cam,
                plate,
                &alpha,
                &points,
                &rest,
                &normals,
                &shadow,
                args,
                floor,
                (*v, frame),
            )?;
            let rel = format!("data/r_{v}_{frame}.png");
            box_filter_rgb(&img, args.factor)
                .save(args.dst.join(&rel))
                .with_context(|| format!("writing {}", args.dst.join(&rel).display()))?;
            let gt = image::GrayImage::from_raw(mw, mh, alpha).context("mask size")?;
            box_filter_luma(&gt, args.factor)
                .save(args.dst.join(format!("gt/masks/m_{v}_{frame}.png")))?;
        }
    }
    for (v, (_, plate)) in views.iter().zip(&plates) {
        let img = image::RgbImage::from_raw(plate.width, plate.height, plate.data.clone())
            .context("plate size")?;
        box_filter_rgb(&img, args.factor).save(args.dst.join(format!("data/r_{v}_-1.png")))?;
    }
    write_cameras(args, &views)?;
    let about = json!({
        "made_by": "datasets-tools composite",
        "source": args.src.file_name().map(|n| n.to_string_lossy().to_string()),
        "texture": format!("{:?}", args.texture),
        "light_direction": [args.light.x, args.light.y, args.light.z],
        "shadow": format!("{:?}", shadow_params(args.light)),
        "floor_colour": floor,
        "frames": args.frames,
        "views": views,
        "factor": args.factor,
    });
    fs::write(
        args.dst.join("gt/composite.json"),
        serde_json::to_string_pretty(&about)?,
    )?;
    println!(
        "wrote {} images of {} cameras to {}",
        views.len() * args.frames.len(),
        views.len(),
        args.dst.display()
    );
    Ok(())
}

/// `all_data.json` of the kept cameras and frames, intrinsics divided by the factor.
fn write_cameras(args: &CompositeArgs<'_>, views: &[u16]) -> Result<()> {
    let json_path = args.src.join("all_data.json");
    let entries: Vec<Value> = serde_json::from_slice(
        &fs::read(&json_path).with_context(|| format!("reading {}", json_path.display()))?,
    )
    .with_context(|| format!("parsing {}", json_path.display()))?;
    let mut kept = Vec::new();
    for e in entries {
        let file = e["file_path"].as_str().context("entry without file_path")?;
        let Some((v, f)) = crate::parse_name(file) else {
            bail!("{}: unexpected file name {file}", json_path.display());
        };
        let keep = u16::try_from(v).is_ok_and(|v| views.contains(&v))
            && (f < 0 || args.frames.iter().any(|x| i64::from(*x) == f));
        if keep {
            kept.push(crate::scale_intrinsics(e, args.factor)?);
        }
    }
    fs::write(
        args.dst.join("all_data.json"),
        serde_json::to_string_pretty(&kept)?,
    )?;
    Ok(())
}
