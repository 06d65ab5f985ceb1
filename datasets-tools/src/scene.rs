//! `datasets-tools scene DST --family F ...`: a generated PAC-NeRF-layout scene of one
//! homogeneous object of any material family the pipeline learns (elastic, elastic_fcr,
//! plasticine, non_newtonian, newtonian, sand), so every family can be run from images to a
//! scored result with a known truth.
//!
//! The object (a `bar`, `ball` or `blob`: a union of four overlapping balls) is a lattice of
//! particles dropped with an initial velocity onto the sticky ground y = 0 and simulated by
//! `pipe simulate`'s own path (`pipe::simulate::run`, f64, the grid following the particles,
//! substeps from the stability limit) with the simulation file written to `gt/scene.sim.yaml`.
//! Each frame is ray-traced as the surface of the body the particles stand for (each one's
//! cube of the lattice, following its local deformation: `two_material::surface`),
//! Lambert-shaded and textured by the rest position (the two-material scene's renderer and
//! cameras: not the Gaussian rasterizer being fitted); `--sphere-radius` draws a sphere per
//! particle instead, as this generator did before.
//!
//! Written: `all_data.json`, `data/r_<cam>_<frame>.png` and plates `r_<cam>_-1.png`,
//! `gt/masks/m_<cam>_<frame>.png`, `gt/particles/<frame>.ply`, `gt/particles_rest.ply`,
//! `gt/scene.sim.yaml` and `gt/params.json` (PAC-NeRF's keys: `E`, `nu`, `yield_stress`,
//! `plastic_viscosity_eta` / `mu`, `kappa`, `friction_angle_deg`, `v0`, `rho`, …). The output
//! is a function of the arguments only.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::DVec3;
use pipe::io::{pacnerf, ply};
use pipe::pipeline::progress::{Mode, Reporter};
use serde_json::json;

use crate::two_material::cameras::Ring;
use crate::two_material::render::Look;
use crate::two_material::{Drawing, FOV_X_DEG, FRAME_DT, bar::albedo, render_frames, to_f32};

/// The object's shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Shape {
    /// A box of `--extent`.
    Bar,
    /// An ellipsoid inscribed in `--extent`.
    Ball,
    /// Four overlapping balls inside `--extent`: a lumpy body with concave creases.
    Blob,
}

/// `datasets-tools scene` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Destination folder (created; it must not exist or be empty).
    pub dst: PathBuf,
    /// Material family, as the pipeline names it: elastic, elastic_fcr, plasticine,
    /// non_newtonian, newtonian, sand.
    #[arg(long)]
    pub family: String,
    /// Young's modulus (Pa): solids, plasticine, non_newtonian, sand.
    #[arg(long)]
    pub youngs_modulus: Option<f64>,
    /// Poisson's ratio.
    #[arg(long)]
    pub poisson_ratio: Option<f64>,
    /// Yield stress (Pa): plasticine, non_newtonian.
    #[arg(long)]
    pub yield_stress: Option<f64>,
    /// Viscosity (Pa·s): non_newtonian's plastic viscosity, newtonian's μ.
    #[arg(long)]
    pub viscosity: Option<f64>,
    /// Bulk modulus (Pa): newtonian.
    #[arg(long)]
    pub bulk_modulus: Option<f64>,
    /// Friction angle (degrees): sand.
    #[arg(long)]
    pub friction_angle_deg: Option<f64>,
    /// Density (kg/m³).
    #[arg(long, default_value_t = 1000.0)]
    pub density: f64,
    /// The object's shape.
    #[arg(long, value_enum, default_value_t = Shape::Ball)]
    pub shape: Shape,
    /// The shape's box x,y,z (m).
    #[arg(long, value_delimiter = ',', default_values_t = [0.3, 0.3, 0.3], allow_negative_numbers = true)]
    pub extent: Vec<f64>,
    /// Particle spacing (m); the MPM cell is twice it (8 particles per cell, as PAC-NeRF).
    #[arg(long, default_value_t = 0.015)]
    pub spacing: f64,
    /// Height of the object's lowest particle cell above the ground at frame 0 (m).
    #[arg(long, default_value_t = 0.2)]
    pub drop_height: f64,
    /// Initial velocity x,y,z (m/s).
    #[arg(long, value_delimiter = ',', default_values_t = [0.2, -0.8, 0.1], allow_negative_numbers = true)]
    pub v0: Vec<f64>,
    /// Initial angular velocity x,y,z (rad/s) about the centre of mass: a tumbling throw
    /// (`--v0` is then the centre of mass's velocity).
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0, 0.0], allow_negative_numbers = true)]
    pub spin: Vec<f64>,
    /// Image width and height (pixels).
    #[arg(long, default_value_t = 100)]
    pub size: u32,
    /// Frames (frame 0 is the object at rest, at the drop height).
    #[arg(long, default_value_t = 14)]
    pub frames: u32,
    /// Cameras on the ring.
    #[arg(long, default_value_t = 11)]
    pub views: u16,
    /// Draw each particle as a sphere of this radius, in lattice spacings (0.5–1.5), instead
    /// of the body the particles stand for (the default; spheres of 0.75, this generator's
    /// drawing before, show a body a quarter spacing thicker on every side).
    #[arg(long)]
    pub sphere_radius: Option<f64>,
    /// Samples per pixel along each axis.
    #[arg(long, default_value_t = 3)]
    pub supersample: u32,
}

impl Args {
    fn check(&self) -> Result<()> {
        for (name, v) in [
            ("extent", &self.extent),
            ("v0", &self.v0),
            ("spin", &self.spin),
        ] {
            if v.len() != 3 || v.iter().any(|x| !x.is_finite()) {
                bail!("--{name} {v:?}: expected three finite values x,y,z");
            }
        }
        if self.extent.iter().any(|e| *e < 2.0 * self.spacing) {
            bail!(
                "--extent {:?} with --spacing {}: at least two particles across every axis",
                self.extent,
                self.spacing
            );
        }
        if !(self.spacing.is_finite() && self.spacing > 0.0) {
            bail!("--spacing {}: must be > 0 (m)", self.spacing);
        }
        if !(self.drop_height.is_finite() && self.drop_height >= 0.0) {
            bail!("--drop-height {}: must be ≥ 0 (m)", self.drop_height);
        }
        if !(8..=4096).contains(&self.size) || !(2..=1000).contains(&self.frames) {
            bail!(
                "--size {} / --frames {}: from 8 to 4096 pixels, 2 to 1000 frames",
                self.size,
                self.frames
            );
        }
        if self.views < 2 || !(1..=8).contains(&self.supersample) {
            bail!(
                "--views {} / --supersample {}: at least 2 cameras, 1 to 8 samples",
                self.views,
                self.supersample
            );
        }
        if let Some(r) = self.sphere_radius
            && !(0.5..=1.5).contains(&r)
        {
            bail!("--sphere-radius {r}: from 0.5 to 1.5 spacings");
        }
        Ok(())
    }

    fn drawing(&self) -> Drawing {
        Drawing::from_arg(self.sphere_radius, self.spacing)
    }

    fn extent(&self) -> DVec3 {
        DVec3::new(self.extent[0], self.extent[1], self.extent[2])
    }

    /// The simulation file (`pipe simulate`'s format; the pipeline's material names).
    fn sim_yaml(&self) -> String {
        let mut m = format!("  family: {}\n  density: {:e}\n", self.family, self.density);
        for (key, v) in [
            ("youngs_modulus", self.youngs_modulus),
            ("poisson_ratio", self.poisson_ratio),
            ("yield_stress", self.yield_stress),
            ("viscosity", self.viscosity),
            ("bulk_modulus", self.bulk_modulus),
            ("friction_angle_deg", self.friction_angle_deg),
        ] {
            if let Some(v) = v {
                m.push_str(&format!("  {key}: {v:e}\n"));
            }
        }
        format!(
            "# datasets-tools scene: the generated object's simulation (pipe simulate's format)\n\
             material:\n{m}initial_velocity: [{:e}, {:e}, {:e}]\n\
             angular_velocity: [{:e}, {:e}, {:e}]\n\
             gravity: [0, -9.8, 0]\n\
             particle_volume: {:e}\n\
             grid_dx: {:e}\n\
             frame_dt: {:e}\n\
             fill_interior: false\n\
             boundaries:\n  - {{kind: ground, y: 0.0, condition: sticky}}\n",
            self.v0[0],
            self.v0[1],
            self.v0[2],
            self.spin[0],
            self.spin[1],
            self.spin[2],
            self.spacing.powi(3),
            2.0 * self.spacing,
            FRAME_DT,
        )
    }
}

/// Rest positions: the cell centres of a lattice of `spacing` over `extent` that lie in the
/// shape, lifted so the lowest cell's bottom is at `drop_height`, centred above the origin.
pub fn lattice(shape: Shape, extent: DVec3, spacing: f64, drop_height: f64) -> Vec<DVec3> {
    let n = (extent / spacing)
        .round()
        .as_uvec3()
        .max(glam::UVec3::splat(2));
    let size = n.as_dvec3() * spacing;
    let half = 0.5 * size;
    // Four balls of 0.32 of the box's smallest side, at the corners of a tilted tetrahedron.
    let lumps: [DVec3; 4] = [
        DVec3::new(-0.22, -0.18, -0.12),
        DVec3::new(0.2, -0.16, -0.16),
        DVec3::new(0.02, -0.14, 0.22),
        DVec3::new(0.0, 0.18, 0.0),
    ];
    let inside = |q: DVec3| -> bool {
        match shape {
            Shape::Bar => true,
            Shape::Ball => (q / half).length_squared() <= 1.0,
            Shape::Blob => lumps
                .iter()
                .any(|c| ((q - *c * size) / (0.32 * size)).length_squared() <= 1.0),
        }
    };
    let mut out = Vec::new();
    for k in 0..n.z {
        for j in 0..n.y {
            for i in 0..n.x {
                let q =
                    (DVec3::new(f64::from(i), f64::from(j), f64::from(k)) + 0.5) * spacing - half;
                if inside(q) {
                    out.push(q);
                }
            }
        }
    }
    let lowest = out.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
    let lift = drop_height + 0.5 * spacing - lowest;
    out.iter().map(|p| *p + DVec3::Y * lift).collect()
}

/// The cameras: a ring around the object's path, far enough that a sphere holding every
/// frame's particles fills 75 % of the field of view.
fn ring(args: &Args, frames: &[Vec<DVec3>]) -> Ring {
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for p in frames.iter().flatten() {
        (lo, hi) = (lo.min(*p), hi.max(*p));
    }
    lo.y = 0.0;
    let pad = DVec3::splat(args.drawing().reach(args.spacing));
    let (lo, hi) = (lo - pad, hi + pad);
    let radius = 0.5 * (hi - lo).length();
    Ring {
        views: args.views,
        target: 0.5 * (lo + hi),
        distance: radius / (0.75 * 0.5 * FOV_X_DEG.to_radians()).sin(),
        elevation_deg: 30.0,
        elevation_swing_deg: 8.0,
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

fn write_scene(args: &Args) -> Result<()> {
    let dst = &args.dst;
    for sub in ["data", "gt/masks", "gt/particles"] {
        std::fs::create_dir_all(dst.join(sub))
            .with_context(|| format!("creating {}", dst.join(sub).display()))?;
    }
    let started = std::time::Instant::now();
    let rest = lattice(args.shape, args.extent(), args.spacing, args.drop_height);
    let rest_ply = dst.join("gt/particles_rest.ply");
    let colours: Vec<[f32; 3]> = rest
        .iter()
        .map(|p| albedo(*p).map(|c| (c / 255.0) as f32))
        .collect();
    ply::write_points(&rest_ply, &to_f32(&rest), Some(&colours))?;
    let sim_file = dst.join("gt/scene.sim.yaml");
    std::fs::write(&sim_file, args.sim_yaml())
        .with_context(|| format!("writing {}", sim_file.display()))?;

    // The motion, through `pipe simulate`'s own path, into a scratch folder.
    let scratch = dst.join(".simulate");
    let summary = pipe::simulate::run(
        &rest_ply,
        &sim_file,
        args.frames,
        &scratch,
        &Reporter::new(Mode::Quiet),
    )
    .with_context(|| {
        format!(
            "simulating {} (its material's keys come from the flags of the same name: \
             youngs_modulus from --youngs-modulus, poisson_ratio from --poisson-ratio, ...)",
            sim_file.display()
        )
    })?;
    let frames: Vec<Vec<DVec3>> = (0..args.frames)
        .map(|f| {
            let path = scratch.join(format!("frame_{f:04}.ply"));
            ply::read_points(&path)
                .with_context(|| format!("reading {}", path.display()))
                .map(|c| {
                    c.positions
                        .iter()
                        .map(|p| DVec3::from_array(p.map(f64::from)))
                        .collect()
                })
        })
        .collect::<Result<_>>()?;
    std::fs::remove_dir_all(&scratch).with_context(|| format!("removing {}", scratch.display()))?;
    for (f, x) in frames.iter().enumerate() {
        if x.len() != rest.len() {
            bail!("frame {f}: {} particles, not {}", x.len(), rest.len());
        }
        ply::write_points(&dst.join(format!("gt/particles/{f}.ply")), &to_f32(x), None)?;
    }
    let simulated = started.elapsed().as_secs_f64();

    let ring = ring(args, &frames);
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
    render_frames(
        dst,
        &scene,
        args.size,
        &rest,
        args.spacing,
        &frames,
        args.drawing(),
        &look,
    )?;
    let params = params_json(args, &rest, &frames, &summary, &ring);
    let path = dst.join("gt/params.json");
    std::fs::write(&path, serde_json::to_string_pretty(&params)?)
        .with_context(|| format!("writing {}", path.display()))?;
    let travel = frames
        .last()
        .map(|x| {
            let c = |x: &[DVec3]| x.iter().sum::<DVec3>() / x.len() as f64;
            (c(x) - c(&rest)).length()
        })
        .unwrap_or(0.0);
    println!(
        "{} {:?}: {} particles, {:.2} kg, {} frames ({} substeps, simulated in {simulated:.1} s); \
         centre of mass moved {travel:.3} m; wrote {} images of {} cameras to {} in {:.1} s",
        args.family,
        args.shape,
        rest.len(),
        summary.total_mass_kg,
        args.frames,
        summary.substeps_total,
        scene.images.len(),
        scene.plates.len(),
        dst.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `gt/params.json` in the sample scenes' format.
fn params_json(
    args: &Args,
    rest: &[DVec3],
    frames: &[Vec<DVec3>],
    summary: &pipe::simulate::Summary,
    ring: &Ring,
) -> serde_json::Value {
    let newtonian = args.family == "newtonian";
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for p in frames.iter().flatten() {
        (lo, hi) = (lo.min(*p), hi.max(*p));
    }
    json!({
        "scene": format!("generated-{}-{:?}", args.family, args.shape).to_lowercase(),
        "description": format!(
            "a {:?} {:?} m of {} dropped from {} m with v0 {:?} m/s and spin {:?} rad/s onto the sticky ground",
            args.shape, args.extent, args.family, args.drop_height, args.v0, args.spin
        ),
        "made_by": "datasets-tools scene",
        "simulator": "pipe simulate (pipe_mpm MLS-MPM, quadratic B-spline, APIC, f64; grid \
                      following the particles; substeps from the stability limit)",
        "family": args.family,
        "material": args.family,
        "rho": args.density,
        "E": args.youngs_modulus,
        "nu": args.poisson_ratio,
        "yield_stress": args.yield_stress,
        "plastic_viscosity_eta": if newtonian { None } else { args.viscosity },
        "mu": if newtonian { args.viscosity } else { None },
        "kappa": args.bulk_modulus,
        "friction_angle_deg": args.friction_angle_deg,
        "v0": args.v0,
        "angular_velocity": args.spin,
        "frame_dt": FRAME_DT,
        "n_frames": args.frames,
        "substeps": summary.frame_stats.iter().map(|s| s.substeps).collect::<Vec<_>>(),
        "dx": 2.0 * args.spacing,
        "particles_per_cell": 8,
        "p_vol": args.spacing.powi(3),
        "p_mass": args.density * args.spacing.powi(3),
        "n_particles": rest.len(),
        "gravity": [0.0, -9.8, 0.0],
        "boundary": {"ground": [[0, 0, 0], [0, 1, 0]], "type": "sticky (grid nodes with y <= 0 get v = 0)"},
        "domain": {"particle_bbox_all_frames": [lo.to_array(), hi.to_array()], "grid": "follows the particles"},
        "shape": {"kind": format!("{:?}", args.shape).to_lowercase(), "extent": args.extent, "spacing": args.spacing, "lowest_y": args.drop_height},
        "texture": {"kind": "stripes of the rest position (the two-material scene's)"},
        "arguments": {
            "size": args.size, "frames": args.frames, "views": args.views,
            "sphere_radius": args.sphere_radius, "supersample": args.supersample,
        },
        "render": {
            "renderer": format!("datasets-tools: {}", args.drawing().describe()),
            "W": args.size, "H": args.size, "n_cameras": args.views,
            "fov_x_deg": ring.fov_x_deg, "camera_target": ring.target.to_array(),
            "camera_distance": ring.distance,
            "convention": "c2w 3x4 OpenGL (camera looks down -z, +y up), K pixels, cx=W/2, cy=H/2",
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_fill_their_box_and_rest_at_the_drop_height() {
        let e = DVec3::new(0.3, 0.2, 0.3);
        let bar = lattice(Shape::Bar, e, 0.02, 0.1);
        let ball = lattice(Shape::Ball, e, 0.02, 0.1);
        let blob = lattice(Shape::Blob, e, 0.02, 0.1);
        assert_eq!(bar.len(), 15 * 10 * 15);
        // An ellipsoid holds π/6 of its box.
        let ratio = ball.len() as f64 / bar.len() as f64;
        assert!((ratio - std::f64::consts::PI / 6.0).abs() < 0.03, "{ratio}");
        assert!(
            blob.len() > bar.len() / 5 && blob.len() < bar.len(),
            "{}",
            blob.len()
        );
        for x in [&bar, &ball, &blob] {
            let lowest = x.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
            assert!((lowest - 0.11).abs() < 1e-12, "{lowest}");
        }
    }
}
