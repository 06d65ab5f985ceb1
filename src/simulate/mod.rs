//! `pipe simulate PARTICLES.ply --material SIM.yaml --frames N --out DIR`: run the MPM
//! simulator forward from a particle cloud and write every frame.
//!
//! 1. [`load_spec`] reads and validates `SIM.yaml` ([`spec`]: material family and its
//!    parameters, initial velocity, gravity, frame time, boundaries, forces, substeps);
//! 2. the particles are read from any point-cloud or 3DGS PLY (`x y z`);
//! 3. [`setup::setup`] resolves the defaults: particle spacing (hash-grid density, see
//!    [`crate::scene::neighbors::particle_spacing`]), `grid_dx = 2·spacing`, `particle_volume = spacing³`,
//!    and the grid (following the particles unless the file declares a `domain`); a
//!    surface-like cloud (3DGS splats)
//!    gets `grid_dx` from its size instead and is filled with particles inside ([`fill`]);
//! 4. the family picks one monomorphised `pipe_mpm::Simulator`; every frame takes the
//!    substeps the stability limit needs at its start (recomputed from the largest speed), or
//!    the file's fixed `substeps`, which must respect the looser limit of a fixed step (CFL
//!    number 0.5 instead of the automatic 0.3, `pipe_mpm::StepLimits`) unless
//!    `allow_unstable: true`;
//! 5. [`output`] writes `frame_NNNN.ply` per frame (frame 0 = input), `particles.arrow` and
//!    `summary.json`, each atomically; the summary is written last.
//!
//! The particle count never changes: without `domain` the grid follows the particles and
//! nothing but the declared boundaries acts on them; with one, particles that reach its edge
//! are held there by the walls and counted per frame (`held`, `contacts`). Fillers are
//! simulated after the input particles and never written.

pub mod fill;
pub mod output;
pub mod setup;
pub mod skin;
pub mod spec;

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Boundaries, BoundaryKind, Constitutive, Domain, Material, ModelVisitor, MpmError, SimConfig,
    Simulator, StableStep, State, StepLimits, Stepper, speed_bound, stable_step_at_speed,
};

use output::{FrameOut, ToWriter};
pub use output::{FrameStats, Summary, Timing, Trajectories};
pub use spec::{SimSpec, load_spec};

use crate::io::ply::{self, PlyError};
use crate::pipeline::progress::Progress;
use crate::pipeline::spec::SpecError;
use crate::pipeline::yaml::Position;
use crate::scene::deform::deform;
use crate::scene::gaussians::Gaussians;
use crate::scene::table::TableError;
use fill::Splat;
use setup::Setup;
use spec::fmt_num;

/// Why `pipe simulate` failed. Every message names the file, key or value at fault.
#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    /// The simulation file is unreadable or invalid (file, line:column, key, value, hint).
    #[error(transparent)]
    Spec(SpecError),
    /// The particle PLY cannot be read, or an output PLY cannot be written.
    #[error(transparent)]
    Ply(#[from] PlyError),
    /// The particle PLY holds no vertex.
    #[error("{path}: no particles: the `vertex` element has 0 records")]
    NoParticles {
        /// The PLY.
        path: PathBuf,
    },
    /// More particles than the output table can index.
    #[error("{path}: {count} particles; at most {} are supported", u32::MAX)]
    TooManyParticles {
        /// The PLY.
        path: PathBuf,
        /// Its vertex count.
        count: usize,
    },
    /// `--splats` on a PLY that is not a 3DGS one.
    #[error("{path}: --splats needs a 3DGS PLY (x y z, f_dc_*, opacity, scale_*, rot_*): {source}")]
    NotSplats {
        /// The PLY.
        path: PathBuf,
        /// What is missing.
        source: Box<PlyError>,
    },
    /// A bad `--frames` value.
    #[error("--frames {frames}: {reason}")]
    Frames {
        /// The value given.
        frames: u32,
        /// What is wrong.
        reason: &'static str,
    },
    /// The particle spacing cannot be measured (a default needs it).
    #[error("{path}: {message}")]
    Spacing {
        /// The PLY.
        path: PathBuf,
        /// What is wrong and what to set instead.
        message: String,
    },
    /// The file's fixed `substeps` breaks the stability limit (and `allow_unstable` is off).
    #[error(
        "{file}: `substeps` = {substeps}{at} is above the {limit} stability limit at frame {frame}: \
         dt = frame_dt / substeps = {dt:.3e} s (CFL number {cfl_number:.2}) > {max_dt:.3e} s, the \
         largest step a fixed count may take; at least {needed} substeps per frame are needed \
         (leave `substeps` out to choose them automatically, raise it, or set \
         `allow_unstable: true`)",
        at = position.map(|p| format!(" at line {p}")).unwrap_or_default()
    )]
    UnstableSubsteps {
        /// The simulation file.
        file: PathBuf,
        /// Where `substeps` is.
        position: Option<Position>,
        /// The fixed count.
        substeps: u32,
        /// Frame about to be simulated (1-based).
        frame: u32,
        /// `frame_dt / substeps` (s).
        dt: f64,
        /// The binding limit (`"elastic wave (CFL)"`, `"viscous"`).
        limit: &'static str,
        /// The largest step a fixed count may take under it (s).
        max_dt: f64,
        /// CFL number of `dt` (`pipe_mpm::StableStep::cfl_number`).
        cfl_number: f64,
        /// Substeps per frame the limit needs.
        needed: usize,
    },
    /// The automatic substeps of a frame would exceed [`MAX_SUBSTEPS_PER_FRAME`].
    #[error(
        "frame {frame} would need {needed:.3e} substeps (the {limit} limit at speeds up to \
         {speed:.3e} m/s allows dt = {dt:.3e} s), more than the {MAX_SUBSTEPS_PER_FRAME} a frame \
         may take: {cause}"
    )]
    TooManySubsteps {
        /// What most likely asks for them: a force or impulse, a `frame_dt` too long from the
        /// start, or a run that diverged.
        cause: String,
        /// Frame about to be simulated (1-based).
        frame: u32,
        /// Substeps the limit asks for.
        needed: f64,
        /// The binding limit.
        limit: &'static str,
        /// Its step (s).
        dt: f64,
        /// The speed bound it holds for (m/s).
        speed: f64,
    },
    /// With a fixed substep count, particles move more than a cell per substep: the run has
    /// diverged (even with `allow_unstable`).
    #[error(
        "the run diverged by frame {frame}: particles move at up to {speed:.3e} m/s, \
         {cells:.3e} grid cells per substep (MPM needs well under one); `substeps` is too small \
         for this material (leave it out to choose the substeps automatically)"
    )]
    Diverged {
        /// Frame about to be simulated (1-based).
        frame: u32,
        /// Largest particle speed (m/s).
        speed: f64,
        /// Cells it crosses per substep.
        cells: f64,
    },
    /// The simulator refused the settings or diverged.
    #[error("{context}: {source}")]
    Simulation {
        /// Where (`setting up the simulator`, `frame 3 (120 substeps of 3.5e-4 s)`).
        context: String,
        /// The simulator's error.
        source: MpmError,
    },
    /// A file-system failure on an output.
    #[error("{path}: cannot {action}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// What was attempted.
        action: &'static str,
        /// OS error.
        source: std::io::Error,
    },
    /// `particles.arrow` cannot be written.
    #[error(transparent)]
    Table(#[from] TableError),
}

/// Simulates `frames` output frames (frame 0 = the input state) of the particles in
/// `particles` with the settings of `sim_file`, writing them to `out` (created if needed).
pub fn run(
    particles: &Path,
    sim_file: &Path,
    frames: u32,
    out: &Path,
    progress: &dyn Progress,
) -> Result<Summary, SimulateError> {
    run_with(
        particles,
        sim_file,
        frames,
        out,
        progress,
        Options::default(),
    )
}

/// What `pipe simulate` writes besides the positions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Options {
    /// Also write `splats_NNNN.ply`: the input 3DGS splats carried by the motion
    /// ([`crate::scene::deform`]).
    pub splats: bool,
    /// Floating-point precision of the simulation (`f64` by default; `f32` runs about twice as
    /// fast, as the peer simulators do).
    pub precision: pipe_mpm::Precision,
}

/// [`run`] with [`Options`].
pub fn run_with(
    particles: &Path,
    sim_file: &Path,
    frames: u32,
    out: &Path,
    progress: &dyn Progress,
    options: Options,
) -> Result<Summary, SimulateError> {
    let started = Instant::now();
    if frames == 0 {
        return Err(SimulateError::Frames {
            frames,
            reason: "at least 1 frame (frame 0 is the input state)",
        });
    }
    if frames > u32::from(u16::MAX) + 1 {
        return Err(SimulateError::Frames {
            frames,
            reason: "at most 65536 frames (the `frame` column of particles.arrow is UInt16)",
        });
    }
    let spec = load_spec(sim_file)?;
    let cloud = ply::read_points(particles)?;
    let n = cloud.positions.len();
    if n == 0 {
        return Err(SimulateError::NoParticles {
            path: particles.to_path_buf(),
        });
    }
    if n > u32::MAX as usize {
        return Err(SimulateError::TooManyParticles {
            path: particles.to_path_buf(),
            count: n,
        });
    }
    let x0: Vec<DVec3> = cloud
        .positions
        .iter()
        .map(|p| DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
        .collect();
    // The 3DGS splats, read once: for the interior filling, and written with `--splats`.
    let gaussians = match ply::read_gaussians(particles) {
        Ok(g) => Some(g),
        Err(source @ PlyError::MissingProperty { .. }) if options.splats => {
            return Err(SimulateError::NotSplats {
                path: particles.to_path_buf(),
                source: Box::new(source),
            });
        }
        Err(PlyError::MissingProperty { .. }) => None,
        Err(e) => return Err(e.into()),
    };
    let splats = gaussians
        .as_ref()
        .map_or_else(Vec::new, |g| fill_splats(g, n, spec.splat_filter));
    let gaussians = gaussians.filter(|_| options.splats);
    let body = Body::new(&spec, particles, x0, &splats, frames)?;
    for w in &body.setup.warnings {
        progress.warn(w);
    }
    let setup = body.setup.clone();
    let carriers = body.n_input;
    let body_spin_centre = body.spin_centre.to_array();
    let job = Job {
        spec: &spec,
        body,
        frames,
        out,
        progress,
        gaussians: gaussians.as_ref(),
        precision: options.precision,
        started,
    };
    let done = spec.material.mpm_family().visit(job)?;

    let mut warnings = setup.warnings.clone();
    warnings.extend(done.warnings);
    let substeps_total = done.stats.iter().map(|s| s.substeps).sum();
    let held_total = done.stats.iter().map(|s| s.held).sum();
    let wall = started.elapsed().as_secs_f64();
    let mass = spec.material.density * setup.particle_volume;
    let total_mass = spec.material.density
        * (setup
            .input_volumes
            .as_ref()
            .map_or(setup.particle_volume * n as f64, |v| v.iter().sum())
            + setup.fill_volumes.iter().sum::<f64>());
    let summary = Summary {
        pipe_version: env!("CARGO_PKG_VERSION").to_string(),
        particles_file: particles.display().to_string(),
        sim_file: sim_file.display().to_string(),
        material: spec.material.clone(),
        frames,
        frame_dt_s: spec.frame_dt,
        simulated_time_s: f64::from(frames - 1) * spec.frame_dt,
        particles_in: n,
        particles_out: done.particles_out,
        carrier_particles: carriers,
        spacing_m: setup.spacing.map(|s| s.spacing),
        median_nn_distance_m: setup.spacing.map(|s| s.median_nn),
        dx_m: setup.dx,
        dx_source: setup.dx_source.clone(),
        particle_volume_m3: setup.particle_volume,
        particle_volume_source: setup.volume_source.clone(),
        particle_mass_kg: mass,
        total_mass_kg: total_mass,
        fill: setup.fill_source.clone(),
        fill_particles: setup.fill.len(),
        fill_particle_volume_m3: setup.fill_volume,
        domain: setup.domain.map(|d| spec::BoxSpec {
            min: d.lo.to_array(),
            max: d.hi.to_array(),
        }),
        domain_source: setup.domain_source.clone(),
        grid_nodes: setup.domain.map(|d| setup::grid_nodes(&d, setup.dx)),
        boundaries: setup::describe_boundaries(&spec.boundaries, setup.domain.is_some()),
        forces: setup.forces.len(),
        gravity: spec.gravity,
        initial_velocity: spec.initial_velocity,
        angular_velocity: spec.angular_velocity,
        spin_centre: body_spin_centre,
        substeps_total,
        frame_stats: done.stats,
        held_total,
        warnings,
        splats: options.splats,
        precision: match options.precision {
            pipe_mpm::Precision::F64 => "f64",
            pipe_mpm::Precision::F32 => "f32",
        }
        .to_string(),
        wall_time_s: wall,
        timing_s: Timing {
            setup: done.setup_s,
            substeps: done.substeps_s,
            output: (wall - done.setup_s - done.substeps_s).max(0.0),
        },
    };
    output::write_summary(out, &summary)?;
    Ok(summary)
}

/// A particle cloud made ready to simulate: the settings [`setup::setup`] resolved, the state
/// (the input particles, then the fillers of a closed surface, all at the file's initial
/// velocity) and the per-particle material. `pipe simulate` and the physics stages build
/// their bodies here.
#[derive(Debug, Clone)]
pub struct Body {
    /// Resolved settings.
    pub setup: Setup,
    /// The initial state: input particles first, fillers after.
    pub state: State,
    /// The file's material per particle (fillers have their own volume and mass).
    pub material: Material,
    /// Input particles (the first ones of `state`): the inputs, or the particles that carry
    /// them when splats were merged.
    pub n_input: usize,
    /// How the input points ride the first `n_input` particles (identity unless
    /// `merge_splats` merged them).
    pub skin: skin::Skin,
    /// The point the initial spin turns about (m): the file's `spin_centre`, or the centre
    /// of mass.
    pub spin_centre: DVec3,
}

impl Body {
    /// The body of the particles `x0` (m, read from `source`, with their 3DGS `splats` when
    /// they are splats) under `spec`, simulated for `frames` frames.
    pub fn new(
        spec: &SimSpec,
        source: &Path,
        x0: Vec<DVec3>,
        splats: &[Splat],
        frames: u32,
    ) -> Result<Self, SimulateError> {
        let mut setup = setup::setup(spec, source, (&x0, splats), frames)?;
        let (x0, skin) = match setup.carriers.take() {
            Some((carriers, skin)) => (carriers, skin),
            None => {
                let n = x0.len();
                (x0, skin::Skin::identity(n))
            }
        };
        let n = x0.len();
        let n_all = n + setup.fill.len();
        let mut material = spec
            .material
            .material(n_all, setup.particle_volume)
            .map_err(|source| SimulateError::Simulation {
                context: format!("material from {}", spec.file.display()),
                source,
            })?;
        // The volumes the filling measured: each input particle's, then the fillers'.
        if let Some(v) = &setup.input_volumes {
            material.volume[..n].copy_from_slice(v);
        }
        material.volume[n..].copy_from_slice(&setup.fill_volumes);
        for (m, v) in material.mass.iter_mut().zip(&material.volume) {
            *m = spec.material.density * v;
        }
        let mut x_all = x0;
        x_all.extend_from_slice(&setup.fill);
        let mut body = Self {
            setup,
            state: State::at_rest(x_all),
            material,
            n_input: n,
            skin,
            spin_centre: DVec3::ZERO,
        };
        body.spin_centre = spec
            .spin_centre
            .map_or_else(|| body.centre_of_mass(), DVec3::from_array);
        let (v0, w, c) = (
            DVec3::from_array(spec.initial_velocity),
            DVec3::from_array(spec.angular_velocity),
            body.spin_centre,
        );
        // The rigid motion; APIC's affine velocity `C` starts at 0, as PAC-NeRF's, the stages'
        // and the generated scenes' (so a turning body spins slower than ω on a coarse grid:
        // `simulate::a_spinning_block_turns_about_its_centre_of_mass`).
        let Body { state, .. } = &mut body;
        for (v, x) in state.v.iter_mut().zip(&state.x) {
            *v = v0 + w.cross(*x - c);
        }
        Ok(body)
    }

    /// The mass-weighted mean position of the simulated particles (m), at the initial state.
    pub fn centre_of_mass(&self) -> DVec3 {
        let m = &self.material.mass;
        let total: f64 = m.iter().sum();
        self.state
            .x
            .iter()
            .zip(m)
            .map(|(x, m)| *x * *m)
            .sum::<DVec3>()
            / total
    }

    /// The input points at `state`: their positions (m), velocities (m/s) and the deformation
    /// gradients their splats take ([`splat_deformation`]); through the skin when splats were
    /// merged (each point at its carrier's `x + A d`, with its carrier's velocity and `F`).
    pub fn input_pose<'s>(
        &self,
        family: crate::pipeline::spec::MaterialFamily,
        state: &'s State,
    ) -> InputPose<'s> {
        let n = self.n_input;
        let a = splat_deformation(family, &state.f[..n]);
        let v = self.skin.gather(&state.v);
        if self.skin.is_identity() {
            return InputPose {
                x: Cow::Borrowed(&state.x[..n]),
                v,
                f: a,
            };
        }
        InputPose {
            x: Cow::Owned(self.skin.positions(&state.x[..n], &a)),
            v,
            f: Cow::Owned(self.skin.gather(&a).into_owned()),
        }
    }

    /// The simulator settings of this body under `spec`: its grid (following the particles,
    /// or the file's domain with walls), gravity, colliders and forces, in `precision`; the
    /// substep is the frame's, until [`frame_step`] sets it.
    pub fn config(&self, spec: &SimSpec, precision: pipe_mpm::Precision) -> SimConfig {
        let setup = &self.setup;
        let mut cfg = match setup.domain {
            Some(domain) => SimConfig::new(domain, setup.dx, spec.frame_dt),
            None => {
                let mut c = SimConfig::following(setup.dx, spec.frame_dt);
                c.domain = Domain::Follow {
                    max_nodes: setup::FOLLOW_NODES,
                };
                c
            }
        };
        cfg.gravity = DVec3::from_array(spec.gravity);
        cfg.margin = setup::GRID_MARGIN;
        cfg.boundaries = Boundaries {
            colliders: setup.colliders.clone(),
            walls: setup.domain.map(|_| BoundaryKind::Separate),
        };
        cfg.forces = setup.forces.clone();
        cfg.precision = precision;
        cfg
    }
}

/// The input points of a [`Body`] at a state ([`Body::input_pose`]).
#[derive(Debug, Clone)]
pub struct InputPose<'s> {
    /// Positions (m).
    pub x: Cow<'s, [DVec3]>,
    /// Velocities (m/s).
    pub v: Cow<'s, [DVec3]>,
    /// The deformation gradients their splats take.
    pub f: Cow<'s, [DMat3]>,
}

/// The splats of a 3DGS PLY's `n` Gaussians (`scale_*`, `rot_*`, `opacity` beside `x y z`),
/// through the rasterizer's filter `filter` (m), for the interior filling. Records that make
/// no splat (a zero rotation) are skipped.
fn fill_splats(g: &Gaussians, n: usize, filter: f64) -> Vec<Splat> {
    debug_assert_eq!(g.len(), n);
    let f = |v: [f32; 3]| v.map(f64::from);
    (0..g.len())
        .filter_map(|i| {
            Splat::from_3dgs(
                DVec3::from_array(f(g.position[i])),
                f(g.log_scale[i]),
                g.rotation[i].map(f64::from),
                f64::from(g.opacity_logit[i]),
            )
            .map(|s| s.filtered(filter))
        })
        .collect()
}

/// The deformation gradients the splats follow: the particles' `F`, except for the Newtonian
/// fluid, whose `F` holds only the volume ratio (`diag(J, 1, 1)`): its splats swell or shrink
/// evenly, `J^(1/3) I`.
pub fn splat_deformation(
    family: crate::pipeline::spec::MaterialFamily,
    f: &[DMat3],
) -> std::borrow::Cow<'_, [DMat3]> {
    match family {
        crate::pipeline::spec::MaterialFamily::Newtonian => f
            .iter()
            .map(|f| DMat3::from_diagonal(DVec3::splat(f.x_axis.x.max(0.0).cbrt())))
            .collect(),
        _ => f.into(),
    }
}

/// The substeps of frame `frame` (1-based) about to start from `state` with material `mat`,
/// or the refusal: the file's fixed `substeps`, or those the stability limit needs. The limits hold for the
/// particles' speed at the frame's start plus what this frame's forces and impulses can add
/// ([`pipe_mpm::speed_bound`]).
pub fn frame_step<M: Constitutive>(
    spec: &SimSpec,
    body: &Body,
    mat: &Material,
    sim: &Simulator<M>,
    state: &State,
    frame: u32,
) -> Result<FrameStep, SimulateError> {
    let frame_dt = spec.frame_dt;
    let t0 = f64::from(frame - 1) * frame_dt;
    let max_speed = state.v.iter().map(|v| v.length()).fold(0.0, f64::max);
    let speed = speed_bound(&state.v, &mat.mass, &body.setup.forces, t0, t0 + frame_dt);
    let stable = stable_step_at_speed(
        sim.model(),
        mat,
        speed,
        body.setup.dx,
        StepLimits::default(),
    );
    let Some(user) = spec.substeps else {
        let n = stable.substeps_per_frame(frame_dt);
        if n > MAX_SUBSTEPS_PER_FRAME {
            let cause = if speed > max_speed * (1.0 + 1e-9) + 1e-12 {
                "a force or impulse is too strong for this material (see `forces`)".into()
            } else if frame == 1 {
                format!(
                    "`frame_dt` = {} s in {} is too long for this material, grid and \
                     initial speed: a frame may last at most {} s",
                    spec::fmt_num(frame_dt),
                    spec.file.display(),
                    spec::short_number(MAX_SUBSTEPS_PER_FRAME as f64 * stable.dt())
                )
            } else {
                "the run has diverged".into()
            };
            return Err(SimulateError::TooManySubsteps {
                cause,
                frame,
                needed: (frame_dt / stable.dt()).ceil(),
                limit: stable.limit(),
                dt: stable.dt(),
                speed,
            });
        }
        // A synthetic capture's own step (`prefer_substeps`) where a fixed count may take it.
        let (n, reason) = match spec.prefer_substeps {
            Some(p) if preferred_step_is_stable(&stable, frame_dt, p, max_speed, body.setup.dx) => {
                (p as usize, "prefer_substeps")
            }
            _ => (n, stable.limit()),
        };
        return Ok(FrameStep {
            substeps: n,
            reason,
            stable,
            max_speed,
            speed,
            unstable: false,
        });
    };
    let dt = frame_dt / f64::from(user);
    // Only a fixed count can get here (automatic steps keep speed · dt ≤ 0.3 dx).
    if max_speed * dt > body.setup.dx {
        return Err(SimulateError::Diverged {
            frame,
            speed: max_speed,
            cells: max_speed * dt / body.setup.dx,
        });
    }
    match stable.check(dt) {
        Ok(()) => Ok(FrameStep {
            substeps: user as usize,
            reason: "user",
            stable,
            max_speed,
            speed,
            unstable: false,
        }),
        Err(MpmError::StepTooLarge { limit, max_dt, .. }) => {
            if spec.allow_unstable {
                Ok(FrameStep {
                    substeps: user as usize,
                    reason: "user",
                    stable,
                    max_speed,
                    speed,
                    unstable: true,
                })
            } else {
                Err(SimulateError::UnstableSubsteps {
                    file: spec.file.clone(),
                    position: spec.position("substeps"),
                    substeps: user,
                    frame,
                    dt,
                    limit,
                    max_dt,
                    cfl_number: stable.cfl_number(dt),
                    needed: stable.fixed_substeps_needed(frame_dt),
                })
            }
        }
        Err(source) => Err(SimulateError::Simulation {
            context: format!("frame {frame}"),
            source,
        }),
    }
}

/// Everything the monomorphised run needs.
struct Job<'a> {
    spec: &'a SimSpec,
    /// The particles, their settings and material (its state is taken when the run starts).
    body: Body,
    frames: u32,
    out: &'a Path,
    progress: &'a dyn Progress,
    /// The input's 3DGS splats, written moved and deformed with every frame (`--splats`).
    gaussians: Option<&'a Gaussians>,
    precision: pipe_mpm::Precision,
    /// When the command started.
    started: Instant,
}

/// Most automatic substeps a frame may take (beyond it the run has diverged, or a force is far
/// too strong for the material: a frame would take hours).
pub const MAX_SUBSTEPS_PER_FRAME: usize = 1_000_000;

/// How a frame is stepped.
#[derive(Debug, Clone, Copy)]
pub struct FrameStep {
    /// Substeps it takes.
    pub substeps: usize,
    /// Why: `"user"`, `"prefer_substeps"` or the binding limit of the automatic count.
    pub reason: &'static str,
    /// The stability limits at the frame's start.
    pub stable: StableStep,
    /// Largest particle speed at the frame's start (m/s).
    pub max_speed: f64,
    /// The speed bound they hold for (m/s).
    pub speed: f64,
    /// The fixed count is above the limit (`allow_unstable`).
    pub unstable: bool,
}

/// Whether `substeps` a frame of `frame_dt` (s) keep within the limits of a user-fixed count
/// (CFL number ≤ 0.5, the viscous limit, and no particle crossing a cell of `dx` m at
/// `max_speed` m/s in a substep).
fn preferred_step_is_stable(
    stable: &StableStep,
    frame_dt: f64,
    substeps: u32,
    max_speed: f64,
    dx: f64,
) -> bool {
    let dt = frame_dt / f64::from(substeps);
    stable.check(dt).is_ok() && max_speed * dt <= dx
}

/// What the run produced.
struct Done {
    /// Particles in every written frame.
    particles_out: usize,
    stats: Vec<FrameStats>,
    warnings: Vec<String>,
    /// Time from the command's start to the first substep (s).
    setup_s: f64,
    /// Time inside the substeps (s).
    substeps_s: f64,
}

impl ModelVisitor for Job<'_> {
    type Output = Result<Done, SimulateError>;

    fn visit<M: Constitutive + Clone + 'static>(self, model: M) -> Self::Output {
        self.simulate(model)
    }
}

impl Job<'_> {
    fn simulate<M: Constitutive + Clone + 'static>(
        mut self,
        model: M,
    ) -> Result<Done, SimulateError> {
        let mut state = std::mem::replace(&mut self.body.state, State::at_rest(Vec::new()));
        let spec = self.spec;
        let sim = simulator(model, spec, &self.body, self.precision)?;
        let mut stepper = stepper(&sim, spec, &self.body, &mut state, self.frames)?;

        let removed = output::prepare_dir(self.out, self.frames, self.gaussians.is_some())?;
        if !removed.is_empty() {
            self.progress.log(&format!(
                "removed {} stale frame file(s) of an earlier run from {}",
                removed.len(),
                self.out.display()
            ));
        }
        // Only the input points are written; the fillers follow them unseen.
        let (gaussians, family, body) = (self.gaussians, spec.material.family, &self.body);
        // The frames are written on a thread of their own, while the next one simulates
        // ([`output::write_frames`]); one frame waits at most.
        std::thread::scope(|scope| {
            let (tx, rx) = std::sync::mpsc::sync_channel::<ToWriter>(1);
            let out_dir = self.out;
            let writer = scope.spawn(move || output::write_frames(out_dir, rx));
            let join = |w: std::thread::ScopedJoinHandle<'_, Result<(), SimulateError>>| {
                w.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            };
            let mut send = |frame: u32, state: &State, _: Option<&FrameStats>| {
                let p = body.input_pose(family, state);
                let splats = gaussians.map(|g| match frame {
                    0 => g.clone(),
                    _ => deform(g, &p.x, &p.f),
                });
                let out = FrameOut::new(frame, &p.x, &p.v, splats);
                Ok(tx.send(ToWriter::Frame(Box::new(out))).is_ok())
            };
            let run = run_frames(
                Frames {
                    spec,
                    body: &self.body,
                    sim: &sim,
                    count: self.frames,
                    progress: self.progress,
                    deformation: gaussians.is_some(),
                },
                &mut stepper,
                &mut state,
                &mut send,
            );
            let finish = matches!(run, Ok(Some(_))) && tx.send(ToWriter::Finish).is_ok();
            drop(tx);
            let written = join(writer);
            match run? {
                Some(run) if finish => written.map(|()| Done {
                    particles_out: self.body.skin.len(),
                    stats: run.stats,
                    warnings: run.warnings,
                    setup_s: run
                        .first_substep
                        .saturating_duration_since(self.started)
                        .as_secs_f64(),
                    substeps_s: run.substeps_s,
                }),
                _ => Err(written.err().unwrap_or_else(|| SimulateError::Io {
                    path: out_dir.to_path_buf(),
                    action: "write the frames",
                    source: std::io::Error::other("the frame writer stopped"),
                })),
            }
        })
    }
}

/// The simulator of `body` under `spec` in `precision`, with `model` (the family's).
pub fn simulator<M: Constitutive>(
    model: M,
    spec: &SimSpec,
    body: &Body,
    precision: pipe_mpm::Precision,
) -> Result<Simulator<M>, SimulateError> {
    let setup = &body.setup;
    Simulator::new(model, body.config(spec, precision)).map_err(|source| setup_error(setup, source))
}

fn setup_error(setup: &Setup, source: MpmError) -> SimulateError {
    SimulateError::Simulation {
        context: format!(
            "setting up the simulator (dx {} m, {})",
            fmt_num(setup.dx),
            match setup.domain {
                Some(d) => format!("domain {:?} to {:?} m", d.lo.to_array(), d.hi.to_array()),
                None => "grid following the particles".to_string(),
            }
        ),
        source,
    }
}

/// `state` (every particle of `body`) loaded into `sim`'s engine, validated and held in the
/// domain, its boundary contacts counted; refuses a fixed substep count above the stability
/// limit of the first frame before anything is written.
pub fn stepper<'s, M: Constitutive>(
    sim: &'s Simulator<M>,
    spec: &SimSpec,
    body: &Body,
    state: &mut State,
    frames: u32,
) -> Result<Stepper<'s, M>, SimulateError> {
    let mut stepper = sim
        .stepper(state, &body.material)
        .map_err(|source| setup_error(&body.setup, source))?;
    stepper.watch_contacts();
    if frames > 1 {
        frame_step(spec, body, &body.material, sim, state, 1)?;
    }
    Ok(stepper)
}

/// What [`run_frames`] simulates.
pub struct Frames<'a, M: Constitutive> {
    /// The simulation file (frame time, substeps).
    pub spec: &'a SimSpec,
    /// The body (its settings, forces and material).
    pub body: &'a Body,
    /// Its simulator.
    pub sim: &'a Simulator<M>,
    /// Frames, frame 0 (the initial state) included.
    pub count: u32,
    /// Progress reporting.
    pub progress: &'a dyn Progress,
    /// Whether each frame's state needs `C` and `F` too (splats), or only `x` and `v`.
    pub deformation: bool,
}

impl<M: Constitutive> std::fmt::Debug for Frames<'_, M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frames")
            .field("count", &self.count)
            .field("deformation", &self.deformation)
            .finish_non_exhaustive()
    }
}

/// What [`run_frames`] measured.
#[derive(Debug, Clone)]
pub struct Stepped {
    /// Per frame `1..count`: substeps, limits, contacts per boundary.
    pub stats: Vec<FrameStats>,
    /// Things the user should know (domain walls acting, unstable fixed steps).
    pub warnings: Vec<String>,
    /// Time inside the substeps (s).
    pub substeps_s: f64,
    /// When the first substep started (after frame 0 was handed over).
    pub first_substep: Instant,
}

/// A frame's consumer in [`run_frames`]: the frame (0 = the initial state), the whole state
/// (every particle: the input ones, then the fillers) and, after frame 0, its statistics.
/// `Ok(false)` stops the run without an error of its own (the consumer's follows).
pub type FrameSink<'a> =
    dyn FnMut(u32, &State, Option<&FrameStats>) -> Result<bool, SimulateError> + 'a;

/// Simulates frames `1..count` of `state` (kept in `stepper`), each with the substeps its
/// stability limit needs ([`frame_step`]: the speed bound includes the frame's forces and
/// impulses), handing every frame, 0 included, to `sink`. `None` when the sink stopped. The
/// one frame loop of `pipe simulate` and the `edit` stage: a NaN or Inf stops it with the
/// engine's error (substep, quantity, particle), particles held at the walls are counted,
/// never dropped.
pub fn run_frames<M: Constitutive>(
    run: Frames<'_, M>,
    stepper: &mut Stepper<'_, M>,
    state: &mut State,
    sink: &mut FrameSink<'_>,
) -> Result<Option<Stepped>, SimulateError> {
    let Frames {
        spec,
        body,
        sim,
        count,
        progress,
        deformation,
    } = run;
    if !sink(0, state, None)? {
        return Ok(None);
    }
    let mut stats = Vec::new();
    let mut warnings = Vec::new();
    let first_substep = Instant::now();
    let mut substeps_s = 0.0;
    progress.start("simulate", u64::from(count.saturating_sub(1)));
    for frame in 1..count {
        let FrameStep {
            substeps: n_sub,
            reason,
            stable,
            max_speed,
            speed,
            unstable,
        } = frame_step(spec, body, &body.material, sim, state, frame)?;
        let dt = spec.frame_dt / n_sub as f64;
        if unstable {
            let w = format!(
                "frame {frame}: `substeps` = {n_sub} gives dt = {dt:.3e} s (CFL number \
                 {:.2}), above the largest step a fixed count may take, {:.3e} s \
                 (allow_unstable)",
                stable.cfl_number(dt),
                stable.max_fixed_dt()
            );
            progress.warn(&w);
            warnings.push(w);
        }
        let t0 = f64::from(frame - 1) * spec.frame_dt;
        let stepping = Instant::now();
        let rep = stepper.advance(t0, dt, n_sub);
        substeps_s += stepping.elapsed().as_secs_f64();
        let rep = rep.map_err(|source| {
            if let MpmError::Diverged { speed, cells, .. } = source {
                return SimulateError::Diverged {
                    frame,
                    speed,
                    cells,
                };
            }
            let why = if unstable {
                " (the substep is above the stability limit: allow_unstable)"
            } else {
                ""
            };
            SimulateError::Simulation {
                context: format!(
                    "frame {frame} ({n_sub} substeps of {dt:.3e} s from t = {t0:.4} s){why}"
                ),
                source,
            }
        })?;
        // The next frame's substeps need the velocities; splats need `F` too.
        let read = if deformation {
            stepper.read(state)
        } else {
            stepper.read_motion(state)
        };
        read.map_err(|source| SimulateError::Simulation {
            context: format!("frame {frame}: reading the state"),
            source,
        })?;
        // Fillers count too: a boundary acts on the whole object.
        let contacts = stepper.take_contacts();
        let walls = body
            .setup
            .domain
            .map_or(0, |_| contacts.last().copied().unwrap_or(0));
        if walls > 0 {
            let w = format!(
                "frame {frame}: the domain walls acted on {walls} particle(s): the motion \
                 differs from one without walls; enlarge `domain` or leave it out (the grid \
                 then follows the particles)"
            );
            progress.warn(&w);
            warnings.push(w);
        }
        progress.message(&format!(
            "frame {frame}: {n_sub} substeps ({reason}), held {}",
            rep.held
        ));
        progress.inc(1);
        let frame_stats = FrameStats {
            frame,
            substeps: n_sub,
            dt_s: dt,
            substeps_reason: reason.to_string(),
            binding_limit: stable.limit().to_string(),
            stable_dt_s: stable.dt(),
            max_fixed_dt_s: stable.max_fixed_dt(),
            cfl_number: stable.cfl_number(dt),
            max_speed_m_s: max_speed,
            speed_bound_m_s: speed,
            unstable,
            held: rep.held,
            max_held: rep.max_held,
            grid: stepper.grid_span().map(|g| spec::BoxSpec {
                min: g.lo.to_array(),
                max: g.hi.to_array(),
            }),
            contacts: if body.setup.domain.is_some() {
                contacts
            } else {
                contacts[..contacts.len().saturating_sub(1)].to_vec()
            },
        };
        let go_on = sink(frame, state, Some(&frame_stats))?;
        stats.push(frame_stats);
        if !go_on {
            return Ok(None);
        }
    }
    Ok(Some(Stepped {
        stats,
        warnings,
        substeps_s,
        first_substep,
    }))
}
