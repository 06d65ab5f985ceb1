//! `datasets-tools two-material DST`: a generated PAC-NeRF-layout scene of an object made of
//! two materials (issue 23's check of material fields).
//!
//! A bar (default 0.6 × 0.15 × 0.15 m, long axis along x) of particles on a cubic lattice
//! ([`bar`]), its half at rest `x < 0` with Young's modulus `E_soft` and the other half
//! `E_stiff = ratio · E_soft` (same ν and density), is dropped with an initial velocity onto
//! the sticky ground y = 0 and simulated by `pipe_mpm`'s neo-Hookean MPM with per-particle
//! moduli ([`simulate`]). Each frame is drawn by a ray tracer that is not the Gaussian
//! rasterizer being fitted ([`render`]: the surface of the body the particles stand for,
//! [`surface`], Lambert-shaded and coloured by a texture of the rest position that is the same
//! on both halves, over a tiled floor and a round wall, no shadow; `--sphere-radius` draws a
//! sphere per particle instead) from a ring of cameras ([`cameras`]).
//!
//! Written (PAC-NeRF's layout, as `pipe`'s `scene.dataset: pacnerf` reads it):
//! `all_data.json`; `data/r_<cam>_-1.png` (plates: the backdrop alone) and
//! `data/r_<cam>_<frame>.png`; `gt/masks/m_<cam>_<frame>.png` (the body's coverage, 8-bit);
//! `gt/particles/<frame>.ply` (positions, float32); `gt/particles_rest_color.ply` (frame 0
//! with each particle's colour); `gt/material_particles.ply` (frame 0 with each particle's `E`
//! and `nu`, the per-particle truth `evaluate` scores a material field against);
//! `gt/params.json` (the truth: `E_soft`, `E_stiff`, `split_x`,
//! `nu`, `v0`, `rho`, …, and `E` = the geometric mean `sqrt(E_soft · E_stiff)`, which is what
//! the pipeline's error report compares a single learned E with).
//!
//! The output is a function of the arguments only: bit-identical across runs and thread
//! counts (the MPM is deterministic for any thread count; each sample of the renderer depends
//! on its own ray only).

pub(crate) mod bar;
pub(crate) mod cameras;
mod deformation;
pub(crate) mod render;
mod simulate;
pub(crate) mod surface;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use glam::DVec3;
use pipe::io::{image as pimage, pacnerf, ply};
use pipe::scene::camera::Camera;
use serde_json::json;

use bar::Bar;
use cameras::Ring;
use deformation::Deformation;
use render::Look;

/// PAC-NeRF's frame time (s): 24 frames per second.
pub const FRAME_DT: f64 = 1.0 / 24.0;

/// Horizontal field of view of the cameras (degrees), as the sample scenes.
pub(crate) const FOV_X_DEG: f64 = 40.0;

/// `datasets-tools two-material` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Destination folder (created; it must not exist or be empty).
    pub dst: PathBuf,
    /// Image width and height (pixels).
    #[arg(long, default_value_t = 100)]
    pub size: u32,
    /// Frames (frame 0 is the bar at rest, at the drop height).
    #[arg(long, default_value_t = 14)]
    pub frames: u32,
    /// Cameras on the ring.
    #[arg(long, default_value_t = 11)]
    pub views: u16,
    /// E_stiff / E_soft.
    #[arg(long, default_value_t = 30.0, allow_negative_numbers = true)]
    pub ratio: f64,
    /// Young's modulus of the soft half, the one at x < 0 (Pa).
    #[arg(long, default_value_t = 2.0e4, allow_negative_numbers = true)]
    pub e_soft: f64,
    /// Poisson's ratio of both halves.
    #[arg(long, default_value_t = 0.3, allow_negative_numbers = true)]
    pub nu: f64,
    /// Density of both halves (kg/m³).
    #[arg(long, default_value_t = 1000.0, allow_negative_numbers = true)]
    pub density: f64,
    /// The bar's size x,y,z (m).
    #[arg(long, value_delimiter = ',', default_values_t = [0.6, 0.15, 0.15], allow_negative_numbers = true)]
    pub bar: Vec<f64>,
    /// Particle spacing (m); the MPM cell is twice it (8 particles per cell, as PAC-NeRF).
    #[arg(long, default_value_t = 0.015, allow_negative_numbers = true)]
    pub spacing: f64,
    /// Height of the bar's lowest face above the ground at frame 0 (m).
    #[arg(long, default_value_t = 0.25, allow_negative_numbers = true)]
    pub drop_height: f64,
    /// Initial velocity x,y,z (m/s).
    #[arg(long, value_delimiter = ',', default_values_t = [0.3, -1.0, 0.0], allow_negative_numbers = true)]
    pub v0: Vec<f64>,
    /// Draw each particle as a sphere of this radius, in lattice spacings (0.5–1.5; ≥ ~0.6
    /// closes the surface), instead of the body the particles stand for (the default; spheres
    /// show a body a quarter spacing thicker on every side at 0.75: see `surface`).
    #[arg(long, allow_negative_numbers = true)]
    pub sphere_radius: Option<f64>,
    /// Samples per pixel along each axis (anti-aliasing and soft mask edges).
    #[arg(long, default_value_t = 3)]
    pub supersample: u32,
}

impl Args {
    fn check(&self) -> Result<()> {
        for (name, v) in [("bar", &self.bar), ("v0", &self.v0)] {
            if v.len() != 3 {
                bail!("--{name} {v:?}: expected three values x,y,z");
            }
        }
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(anyhow::anyhow!("--{name} {v}: must be a finite number > 0"))
            }
        };
        positive("ratio", self.ratio)?;
        positive("e-soft", self.e_soft)?;
        positive("density", self.density)?;
        positive("spacing", self.spacing)?;
        if !(self.nu.is_finite() && self.nu > -1.0 && self.nu < 0.5) {
            bail!("--nu {}: must be in (-1, 0.5)", self.nu);
        }
        if !(8..=4096).contains(&self.size) {
            bail!("--size {}: must be from 8 to 4096 pixels", self.size);
        }
        if !(1..=1000).contains(&self.frames) {
            bail!("--frames {}: must be from 1 to 1000", self.frames);
        }
        if self.views == 0 {
            bail!("--views 0: at least one camera");
        }
        if !(1..=8).contains(&self.supersample) {
            bail!("--supersample {}: must be from 1 to 8", self.supersample);
        }
        if let Some(r) = self.sphere_radius
            && !(0.5..=1.5).contains(&r)
        {
            bail!("--sphere-radius {r}: must be from 0.5 to 1.5 lattice spacings");
        }
        for (axis, s) in ["x", "y", "z"].iter().zip(&self.bar) {
            positive(&format!("bar ({axis})"), *s)?;
            if s / self.spacing < 2.0 || s / self.spacing > 400.0 {
                bail!(
                    "--bar {axis} = {s} m with --spacing {} m gives {:.1} particles across: \
                     must be from 2 to 400",
                    self.spacing,
                    s / self.spacing
                );
            }
        }
        if !(self.drop_height.is_finite() && self.drop_height >= self.spacing) {
            bail!(
                "--drop-height {}: must be at least one spacing ({} m) above the ground",
                self.drop_height,
                self.spacing
            );
        }
        if self.v0.iter().any(|v| !v.is_finite()) {
            bail!("--v0 {:?}: must be finite", self.v0);
        }
        Ok(())
    }

    fn size3(&self) -> DVec3 {
        DVec3::new(self.bar[0], self.bar[1], self.bar[2])
    }

    fn v0(&self) -> DVec3 {
        DVec3::new(self.v0[0], self.v0[1], self.v0[2])
    }
}

/// The cameras: a ring around the point above the origin half-way up the drop, far enough
/// that a sphere holding the bar at rest and on the ground fills 75 % of the field of view.
fn ring(args: &Args) -> Ring {
    let s = args.size3();
    let top = args.drop_height + s.y;
    let radius = 0.5 * (s.x * s.x + top * top + s.z * s.z).sqrt();
    Ring {
        views: args.views,
        target: DVec3::new(0.0, 0.5 * top, 0.0),
        distance: radius / (0.75 * 0.5 * FOV_X_DEG.to_radians()).sin(),
        elevation_deg: 25.0,
        elevation_swing_deg: 5.0,
        azimuth0_deg: 15.0,
        fov_x_deg: FOV_X_DEG,
    }
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
    for sub in ["data", "gt/masks", "gt/particles"] {
        std::fs::create_dir_all(dst.join(sub))
            .with_context(|| format!("creating {}", dst.join(sub).display()))?;
    }
    let started = std::time::Instant::now();

    let bar = Bar::new(args.size3(), args.spacing, args.drop_height);
    let e_stiff = args.ratio * args.e_soft;
    let setting = simulate::Setting {
        rest: bar.rest.clone(),
        particle_volume: args.spacing.powi(3),
        dx: 2.0 * args.spacing,
        youngs_modulus: bar.youngs_moduli(args.e_soft, e_stiff),
        poisson_ratio: args.nu,
        density: args.density,
        v0: args.v0(),
        gravity: DVec3::new(0.0, -9.8, 0.0),
        frame_dt: FRAME_DT,
    };
    let traj = setting.run(args.frames)?;
    let simulated = started.elapsed().as_secs_f64();

    // Cameras: written, then read back as the pipeline reads them.
    let ring = ring(args);
    let all_data = dst.join("all_data.json");
    std::fs::write(
        &all_data,
        serde_json::to_string_pretty(&ring.all_data(args.size, args.frames, FRAME_DT))?,
    )
    .with_context(|| format!("writing {}", all_data.display()))?;
    let scene = pacnerf::read_scene(dst)?;

    let look = Look {
        ss: args.supersample,
        ..Look::default()
    };
    let albedo: Vec<[f64; 3]> = bar.rest.iter().map(|p| bar::albedo(*p)).collect();
    let drawing = Drawing::from_arg(args.sphere_radius, args.spacing);
    render_frames(
        dst,
        &scene,
        args.size,
        &bar.rest,
        args.spacing,
        &traj.frames,
        drawing,
        &look,
    )?;
    for (f, x) in traj.frames.iter().enumerate() {
        ply::write_points(&dst.join(format!("gt/particles/{f}.ply")), &to_f32(x), None)?;
    }
    let colours: Vec<[f32; 3]> = albedo
        .iter()
        .map(|a| a.map(|c| (c / 255.0) as f32))
        .collect();
    ply::write_points(
        &dst.join("gt/particles_rest_color.ply"),
        &to_f32(&bar.rest),
        Some(&colours),
    )?;
    let nu = vec![args.nu; bar.rest.len()];
    ply::write_point_scalars(
        &dst.join("gt/material_particles.ply"),
        &to_f32(&bar.rest),
        &[("E", &setting.youngs_modulus), ("nu", &nu)],
    )?;

    // Measured on the positions as written (float32), so the numbers are the files'.
    let written: Vec<Vec<DVec3>> = traj
        .frames
        .iter()
        .map(|x| {
            to_f32(x)
                .iter()
                .map(|p| DVec3::from_array(p.map(f64::from)))
                .collect()
        })
        .collect();
    let deformed = Deformation::of(&bar, &written);
    let params = params_json(args, &bar, &traj, &ring, &look, &deformed);
    let params_path = dst.join("gt/params.json");
    std::fs::write(&params_path, serde_json::to_string_pretty(&params)?)
        .with_context(|| format!("writing {}", params_path.display()))?;
    println!(
        "two-material bar: {} particles ({} soft at E {:e} Pa, {} stiff at E {:e} Pa), {} frames \
         ({} substeps), simulated in {simulated:.1} s",
        bar.rest.len(),
        bar.soft().iter().filter(|s| **s).count(),
        args.e_soft,
        bar.soft().iter().filter(|s| !**s).count(),
        e_stiff,
        args.frames,
        traj.substeps.iter().sum::<usize>(),
    );
    println!(
        "largest deformation over the frames, soft | stiff half: non-rigid residual {:.4} | \
         {:.4} (ratio {:.1}), edge strain (95th percentile) {:.4} | {:.4} (ratio {:.1})",
        deformed.residual[0],
        deformed.residual[1],
        deformed.residual[0] / deformed.residual[1],
        deformed.strain[0],
        deformed.strain[1],
        deformed.strain[0] / deformed.strain[1],
    );
    println!(
        "wrote {} images of {} cameras to {} in {:.1} s",
        scene.images.len(),
        scene.plates.len(),
        dst.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// How a frame's particles are drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Drawing {
    /// The body the particles stand for ([`surface::Surface`]: each particle's cube of side
    /// `spacing`, following the local deformation).
    Surface,
    /// A sphere of this radius (m) per particle (larger than the body: see [`surface`]).
    Spheres(f64),
}

impl Drawing {
    /// From a `--sphere-radius` in lattice spacings (none: the surface).
    pub(crate) fn from_arg(sphere_radius: Option<f64>, spacing: f64) -> Self {
        sphere_radius.map_or(Self::Surface, |r| Self::Spheres(r * spacing))
    }

    /// How far the drawing reaches beyond a particle's centre (m), at most.
    pub(crate) fn reach(&self, spacing: f64) -> f64 {
        match self {
            Self::Surface => spacing,
            Self::Spheres(r) => *r,
        }
    }

    /// For `gt/params.json`.
    pub(crate) fn describe(&self) -> String {
        match self {
            Self::Surface => "ray-traced surface of the particles' body (the level set 1/2 of \
                              their quadratic B-splines, following each particle's local \
                              deformation), Lambert shading, textured by the rest position; no \
                              shadows"
                .to_string(),
            Self::Spheres(r) => format!(
                "ray-traced spheres of radius {r} m, one per particle, Lambert shading; no shadows"
            ),
        }
    }
}

/// One frame's particles as they are drawn: their surface, or their centres and the spheres'
/// radius (m).
enum Framed<'a> {
    Surface(surface::Surface),
    Spheres(&'a [DVec3], f64),
}

/// Draws every image of `scene` (a PAC-NeRF scene just written to `dst`, `size`² pixels):
/// each camera's plate, then the body of `frames[f]` (particles whose lattice rest positions
/// are `rest`, spacing m, textured by [`bar::albedo`] of the rest position) over it as
/// `data/r_<cam>_<f>.png` with its coverage as `gt/masks/m_<cam>_<f>.png`. Refuses a frame
/// that leaves a camera's image.
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_frames(
    dst: &Path,
    scene: &pacnerf::PacnerfScene,
    size: u32,
    rest: &[DVec3],
    spacing: f64,
    frames: &[Vec<DVec3>],
    drawing: Drawing,
    look: &Look,
) -> Result<()> {
    let reach = drawing.reach(spacing);
    for img in &scene.images {
        let cam = Camera::new(&img.world_from_camera, img.intrinsics, size, size);
        check_in_view(
            &cam,
            &frames[img.frame as usize],
            reach,
            img.view,
            img.frame,
        )?;
    }
    let mut plates = std::collections::BTreeMap::new();
    for (view, plate_entry) in &scene.plates {
        let cam = Camera::new(
            &plate_entry.world_from_camera,
            plate_entry.intrinsics,
            size,
            size,
        );
        let plate = look.plate(&cam);
        write_rgb(&plate_entry.path, size, &look.resolve(&plate).rgb)?;
        plates.insert(*view, (cam, plate));
    }
    // The spheres' colours, one per particle (the surface evaluates the texture at each hit).
    let albedos: Vec<[f64; 3]> = match drawing {
        Drawing::Spheres(_) => rest.iter().map(|p| bar::albedo(*p)).collect(),
        Drawing::Surface => Vec::new(),
    };
    for (f, x) in frames.iter().enumerate() {
        let body = match drawing {
            Drawing::Surface => Framed::Surface(surface::Surface::new(rest, x, spacing)),
            Drawing::Spheres(radius) => Framed::Spheres(x, radius),
        };
        for img in scene.images.iter().filter(|i| i.frame as usize == f) {
            let Some((cam, plate)) = plates.get(&img.view) else {
                bail!("camera {} has frame {f} but no background plate", img.view);
            };
            let samples = match &body {
                Framed::Surface(surface) => look.surface(cam, plate, surface, bar::albedo),
                Framed::Spheres(x, r) => look.spheres(cam, plate, x, *r, &albedos),
            };
            let frame = look.resolve(&samples);
            write_rgb(&img.path, size, &frame.rgb)?;
            let mask = pacnerf::gt_mask_path(dst, img.view, img.frame);
            pimage::write_gray8(&mask, size, size, &frame.alpha)?;
        }
    }
    Ok(())
}

fn write_rgb(path: &Path, size: u32, rgb: &[u8]) -> Result<()> {
    pimage::write_rgb8(
        path,
        &pimage::Rgb8 {
            width: size,
            height: size,
            data: rgb.to_vec(),
        },
    )?;
    Ok(())
}

pub(crate) fn to_f32(x: &[DVec3]) -> Vec<[f32; 3]> {
    x.iter().map(|p| p.to_array().map(|v| v as f32)).collect()
}

/// Every sphere lies in front of the camera and inside its image.
fn check_in_view(cam: &Camera, x: &[DVec3], radius: f64, view: u16, frame: i32) -> Result<()> {
    for (i, p) in x.iter().enumerate() {
        let inside = cam.project(*p).is_some_and(|(u, v, z)| {
            let r = cam.fx * radius / z;
            z > radius
                && u - r >= 0.0
                && v - r >= 0.0
                && u + r <= f64::from(cam.width)
                && v + r <= f64::from(cam.height)
        });
        if !inside {
            bail!(
                "particle {i} at {p} (m) leaves camera {view}'s image at frame {frame}: the bar \
                 moves out of the cameras' view (a smaller --v0, --drop-height or --bar, or fewer \
                 --frames)"
            );
        }
    }
    Ok(())
}

/// `gt/params.json`, in the sample scenes' format plus the two halves' moduli.
fn params_json(
    args: &Args,
    bar: &Bar,
    traj: &simulate::Trajectory,
    ring: &Ring,
    look: &Look,
    deformed: &Deformation,
) -> serde_json::Value {
    let e_stiff = args.ratio * args.e_soft;
    let lame = |e: f64| {
        let (mu, lam) = pipe_mpm::lame(e, args.nu).expect("checked E and nu");
        json!({"lame_mu": mu, "lame_lambda": lam})
    };
    let n = bar.rest.len();
    let n_soft = bar.soft().iter().filter(|s| **s).count();
    let (lo, hi) = bar.bounds();
    let mut x_all = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for p in traj.frames.iter().flatten() {
        x_all = (x_all.0.min(*p), x_all.1.max(*p));
    }
    let mut out = json!({
        "scene": "two-material-bar",
        "description": format!(
            "bar {:?} m of two neo-Hookean halves (x < {} soft, E {:e} Pa; the rest stiff, \
             E {:e} Pa, {}x), dropped from {} m with v0 {:?} m/s onto the sticky ground",
            args.bar, bar.split_x, args.e_soft, e_stiff, args.ratio, args.drop_height, args.v0
        ),
        "made_by": "datasets-tools two-material",
        "simulator": "pipe_mpm (MLS-MPM, quadratic B-spline, APIC), neo-Hookean, f64, a Young's \
                      modulus per particle; grid following the particles; substeps per frame \
                      from the stability limit (CFL 0.3) at the frame's start",
        "material": "elasticity",
        "family": "elastic",
        "rho": args.density,
        "E": (args.e_soft * e_stiff).sqrt(),
        "E_note": "the geometric mean sqrt(E_soft * E_stiff): no single E is true here; the \
                   pipeline's error report compares a global E with it",
        "E_soft": args.e_soft,
        "E_stiff": e_stiff,
        "E_ratio": args.ratio,
        "split_axis": "x",
        "split_x": bar.split_x,
        "soft_side": "rest x < split_x",
        "nu": args.nu,
        "yield_stress": null,
        "plastic_viscosity_eta": null,
        "mu": null,
        "kappa": null,
        "friction_angle_deg": null,
        "friction_alpha": null,
        "viscosity_eta": null,
        "soft": lame(args.e_soft),
        "stiff": lame(e_stiff),
    });
    let more = json!({
        "v0": args.v0,
        "frame_dt": FRAME_DT,
        "n_frames": args.frames,
        "substeps": traj.substeps,
        "dx": 2.0 * args.spacing,
        "particles_per_cell": 8,
        "p_vol": args.spacing.powi(3),
        "p_mass": args.density * args.spacing.powi(3),
        "n_particles": n,
        "n_soft": n_soft,
        "n_stiff": n - n_soft,
        "gravity": [0.0, -9.8, 0.0],
        "boundary": {"ground": [[0, 0, 0], [0, 1, 0]], "type": "sticky (grid nodes with y <= 0 get v = 0)"},
    });
    if let (Some(out), serde_json::Value::Object(more)) = (out.as_object_mut(), more) {
        out.extend(more);
    }
    out["arguments"] = json!({
        "size": args.size, "frames": args.frames, "views": args.views, "ratio": args.ratio,
        "e_soft": args.e_soft, "nu": args.nu, "density": args.density, "bar": args.bar,
        "spacing": args.spacing, "drop_height": args.drop_height, "v0": args.v0,
        "sphere_radius": args.sphere_radius, "supersample": args.supersample,
    });
    out["domain"] = json!({
        "particle_bbox_all_frames": [x_all.0.to_array(), x_all.1.to_array()],
        "grid": "follows the particles",
    });
    out["shape"] = json!({
        "kind": "bar",
        "size": args.bar,
        "lattice": bar.counts,
        "spacing": args.spacing,
        "bbox_rest": [lo.to_array(), hi.to_array()],
        "lowest_y": args.drop_height,
        "center_xz": [0.0, 0.0],
    });
    out["texture"] = json!({
        "kind": "stripes of the rest position",
        "period_m": 0.085,
        "dir": [1.0, 0.45, 0.7],
        "colours": ["#e2702a", "#268e98"],
        "note": "phase wobbled by value noise (6 cm), brightness x0.85-1.15 (2.5 cm noise); the same on both halves",
    });
    out["deformation"] = deformation_json(deformed);
    out["render"] = render_json(args, ring, look);
    out
}

/// `gt/params.json`'s `deformation`: how much each half deformed.
fn deformation_json(deformed: &Deformation) -> serde_json::Value {
    json!({
        "max_non_rigid_residual": {"soft": deformed.residual[0], "stiff": deformed.residual[1]},
        "max_edge_strain_p95": {"soft": deformed.strain[0], "stiff": deformed.strain[1]},
        "frame_of_max_soft_residual": deformed.residual_frame,
        "note": "largest over the frames, per half: the RMS distance of its particles to the best rigid motion of its rest shape / the rest shape's RMS radius; the 95th percentile of | |x_i - x_j| / |X_i - X_j| - 1 | over its lattice edges",
    })
}

/// `gt/params.json`'s `render`: how the images were made.
fn render_json(args: &Args, ring: &Ring, look: &Look) -> serde_json::Value {
    json!({
        "renderer": format!(
            "datasets-tools two-material: {}",
            Drawing::from_arg(args.sphere_radius, args.spacing).describe()
        ),
        "W": args.size,
        "H": args.size,
        "supersample": args.supersample,
        "sphere_radius_m": args.sphere_radius.map(|r| r * args.spacing),
        "light_direction_to": look.to_light.to_array(),
        "ambient": look.ambient,
        "diffuse": look.diffuse,
        "backdrop": format!(
            "tiles of {} m on a {} m square mat on the ground y = 0, plain floor around it, a round wall of radius {} m",
            look.tile, 2.0 * look.mat_half, look.wall_radius
        ),
        "n_cameras": args.views,
        "fov_x_deg": ring.fov_x_deg,
        "camera_target": ring.target.to_array(),
        "camera_distance": ring.distance,
        "camera_layout": format!(
            "ring, azimuth {} + 360 k / n deg, elevation {} deg (even k) / {} deg (odd k)",
            ring.azimuth0_deg,
            ring.elevation_deg - ring.elevation_swing_deg,
            ring.elevation_deg + ring.elevation_swing_deg
        ),
        "convention": "c2w 3x4 OpenGL (camera looks down -z, +y up), K pixels, cx=W/2, cy=H/2",
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/two-material-bar")
    }

    /// The shipped scene's ground truth: its particles are the lattice its arguments describe,
    /// and the soft half deforms far more than the stiff one (measured: non-rigid residual
    /// 0.178 against 0.019, 9.5×; 95th-percentile edge strain 0.44 against 0.027, 16.5×).
    #[test]
    fn in_the_fixture_the_soft_half_deforms_more_than_the_stiff_half() {
        let params: serde_json::Value =
            serde_json::from_slice(&std::fs::read(fixture().join("gt/params.json")).unwrap())
                .unwrap();
        let a = &params["arguments"];
        let f = |v: &serde_json::Value| v.as_f64().unwrap();
        let size = DVec3::new(f(&a["bar"][0]), f(&a["bar"][1]), f(&a["bar"][2]));
        let bar = Bar::new(size, f(&a["spacing"]), f(&a["drop_height"]));
        assert_eq!(f(&params["split_x"]), bar.split_x);
        let n_frames = params["n_frames"].as_u64().unwrap() as usize;
        let frames: Vec<Vec<DVec3>> = (0..n_frames)
            .map(|k| {
                let cloud =
                    ply::read_points(&fixture().join(format!("gt/particles/{k}.ply"))).unwrap();
                assert_eq!(cloud.positions.len(), bar.rest.len(), "frame {k}");
                cloud
                    .positions
                    .iter()
                    .map(|p| DVec3::from_array(p.map(f64::from)))
                    .collect()
            })
            .collect();
        for (p, q) in frames[0].iter().zip(&bar.rest) {
            assert!((*p - *q).abs().max_element() < 1e-6, "{p} vs {q}");
        }
        let d = Deformation::of(&bar, &frames);
        assert!(d.residual.iter().chain(&d.strain).all(|v| v.is_finite()));
        assert!(d.residual[0] > 0.1, "{d:?}");
        assert!(d.residual[0] > 4.0 * d.residual[1], "{d:?}");
        assert!(d.strain[0] > 0.2, "{d:?}");
        assert!(d.strain[0] > 5.0 * d.strain[1], "{d:?}");
        // The file states what the frames hold.
        let stated = &params["deformation"];
        assert_eq!(f(&stated["max_non_rigid_residual"]["soft"]), d.residual[0]);
        assert_eq!(f(&stated["max_edge_strain_p95"]["stiff"]), d.strain[1]);
    }
}
