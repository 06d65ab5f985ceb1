//! What `pipe simulate` writes into its output folder, every file atomically, on a writer
//! thread of its own while the next frame simulates:
//!
//! - `frame_0000.ply` … `frame_{frames-1}.ply`: positions (m) as binary little-endian
//!   `float x y z`; frame 0 is the input state (particles outside a given `domain` moved to
//!   its edge, as the run warns);
//! - `splats_0000.ply` … (with `--splats`, for a 3DGS input): the input's splats moved and
//!   deformed with their particles ([`crate::scene::deform`]), in the input's 3DGS layout;
//! - `particles.arrow`: the [`Trajectories`] table, one row per particle per frame;
//! - `summary.json`: the [`Summary`].

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::Receiver;

use arrow_array::{Float32Array, RecordBatch, UInt16Array, UInt32Array};
use arrow_schema::{DataType, Field, Schema};
use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::SimulateError;
use super::spec::{BoxSpec, MaterialSpec, short_number};
use crate::io::ply;
use crate::scene::gaussians::Gaussians;
use crate::scene::table::{self, Table, TableError, column};

/// The `particles` table (`particles.arrow`, Arrow IPC file, one record batch per frame, written
/// as the run goes: [`Trajectories::frame_batch`]), rows ordered by frame then particle:
///
/// | column | type | meaning |
/// |---|---|---|
/// | `frame` | UInt16 | output frame, 0 = input state |
/// | `id` | UInt32 | particle = vertex index in the input PLY |
/// | `x`, `y`, `z` | Float32 | position (m) |
/// | `vx`, `vy`, `vz` | Float32 | velocity (m/s) |
///
/// The contract is `schemas/particles.arrow.json`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Trajectories {
    /// Frame of each row.
    pub frame: Vec<u16>,
    /// Particle of each row.
    pub id: Vec<u32>,
    /// Positions (m).
    pub x: Vec<[f32; 3]>,
    /// Velocities (m/s).
    pub v: Vec<[f32; 3]>,
}

impl Trajectories {
    /// The record batch of one frame: one row per particle, in order, from its positions (m)
    /// and velocities (m/s).
    pub fn frame_batch(frame: u16, x: &[[f32; 3]], v: &[[f32; 3]]) -> RecordBatch {
        Self::batch(
            UInt16Array::from_iter_values(std::iter::repeat_n(frame, x.len())),
            UInt32Array::from_iter_values(0..x.len() as u32),
            x,
            v,
        )
    }

    /// The record batch of these columns.
    fn batch(frame: UInt16Array, id: UInt32Array, x: &[[f32; 3]], v: &[[f32; 3]]) -> RecordBatch {
        let comp = |src: &[[f32; 3]], a: usize| -> Arc<dyn arrow_array::Array> {
            Arc::new(Float32Array::from_iter_values(src.iter().map(|p| p[a])))
        };
        RecordBatch::try_new(
            Arc::new(Self::schema()),
            vec![
                Arc::new(frame),
                Arc::new(id),
                comp(x, 0),
                comp(x, 1),
                comp(x, 2),
                comp(v, 0),
                comp(v, 1),
                comp(v, 2),
            ],
        )
        .expect("columns match the schema")
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.frame.len()
    }

    /// `true` without rows.
    pub fn is_empty(&self) -> bool {
        self.frame.is_empty()
    }

    /// Positions of one frame, in particle order.
    pub fn positions(&self, frame: u16) -> Vec<[f32; 3]> {
        self.frame
            .iter()
            .zip(&self.x)
            .filter(|(f, _)| **f == frame)
            .map(|(_, x)| *x)
            .collect()
    }
}

impl Table for Trajectories {
    const NAME: &'static str = "particles";
    const VERSION: u32 = 1;
    const FORMAT: &'static str = "Arrow IPC file, one record batch per frame";

    fn schema() -> Schema {
        let f32col = |n: &str| Field::new(n, DataType::Float32, false);
        Schema::new(vec![
            Field::new("frame", DataType::UInt16, false),
            Field::new("id", DataType::UInt32, false),
            f32col("x"),
            f32col("y"),
            f32col("z"),
            f32col("vx"),
            f32col("vy"),
            f32col("vz"),
        ])
        .with_metadata(
            [
                ("schema_version".to_string(), Self::VERSION.to_string()),
                (
                    "units".to_string(),
                    "x y z: m; vx vy vz: m/s; frame 0 = input state; id = input PLY vertex index"
                        .to_string(),
                ),
            ]
            .into_iter()
            .collect::<std::collections::HashMap<String, String>>(),
        )
    }

    fn to_batch(&self) -> RecordBatch {
        Self::batch(
            UInt16Array::from(self.frame.clone()),
            UInt32Array::from(self.id.clone()),
            &self.x,
            &self.v,
        )
    }

    fn from_batch(b: &RecordBatch, _path: &Path) -> Result<Self, TableError> {
        let f = |n: &str| column::<Float32Array>(b, n).values().to_vec();
        let zip3 = |a: Vec<f32>, b: Vec<f32>, c: Vec<f32>| -> Vec<[f32; 3]> {
            a.into_iter()
                .zip(b)
                .zip(c)
                .map(|((x, y), z)| [x, y, z])
                .collect()
        };
        Ok(Self {
            frame: column::<UInt16Array>(b, "frame").values().to_vec(),
            id: column::<UInt32Array>(b, "id").values().to_vec(),
            x: zip3(f("x"), f("y"), f("z")),
            v: zip3(f("vx"), f("vy"), f("vz")),
        })
    }
}

/// What happened in one simulated frame (from frame − 1 to frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameStats {
    /// The frame reached (1-based; frame 0 is the input).
    pub frame: u32,
    /// Substeps taken.
    pub substeps: usize,
    /// Substep (s).
    pub dt_s: f64,
    /// Why this many: `"user"` (the file's `substeps`) or the binding stability limit
    /// (`"elastic wave (CFL)"`, `"viscous"`).
    pub substeps_reason: String,
    /// The binding stability limit at the frame's start.
    pub binding_limit: String,
    /// The step automatic substeps take under that limit (s; CFL number 0.3 for the wave
    /// limit).
    pub stable_dt_s: f64,
    /// The largest step a fixed `substeps` may take (s; CFL number 0.5, or the viscous limit).
    pub max_fixed_dt_s: f64,
    /// CFL number of this frame's substep: `dt · (speed bound + wave speed) / dx` (automatic
    /// substeps ≤ 0.3; PAC-NeRF's 200 per frame are 0.17–0.43 on its scenes).
    pub cfl_number: f64,
    /// Largest particle speed at the frame's start (m/s).
    pub max_speed_m_s: f64,
    /// The speed the limits hold for (m/s): each particle's speed at the frame's start plus
    /// what the frame's forces and impulses can add to it (`max_speed_m_s` when none act).
    pub speed_bound_m_s: f64,
    /// `dt_s` exceeds `max_fixed_dt_s` (only possible with `allow_unstable`).
    pub unstable: bool,
    /// Particle-substeps in which a particle was held at the domain walls.
    pub held: usize,
    /// Most particles held in a single substep.
    pub max_held: usize,
    /// The box (m) of the grid nodes the frame's substeps stored: a following grid's windows
    /// together, or the fixed grid.
    #[serde(default)]
    pub grid: Option<BoxSpec>,
    /// Per boundary of `boundaries` (same order, the domain walls last when there is a
    /// domain), the particles it acted on in this frame: those whose stencil reached a node it
    /// treats in some substep.
    #[serde(default)]
    pub contacts: Vec<usize>,
}

/// `summary.json`: what was simulated, how, and what came out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// `pipe` version.
    pub pipe_version: String,
    /// Input PLY.
    pub particles_file: String,
    /// Simulation file.
    pub sim_file: String,
    /// Material as resolved from the file.
    pub material: MaterialSpec,
    /// Output frames written (including frame 0).
    pub frames: u32,
    /// Time between frames (s).
    pub frame_dt_s: f64,
    /// Simulated time (s): `(frames − 1) · frame_dt`.
    pub simulated_time_s: f64,
    /// Particles read.
    pub particles_in: usize,
    /// Particles in every written frame (always equal to `particles_in`).
    pub particles_out: usize,
    /// Simulation particles that carry them: `particles_in`, or fewer when `merge_splats`
    /// let the splats of one voxel ride one particle.
    pub carrier_particles: usize,
    /// Measured particle spacing (m; cube root of the volume per particle), when a default
    /// needed it.
    pub spacing_m: Option<f64>,
    /// Median nearest-neighbour distance (m), when measured.
    pub median_nn_distance_m: Option<f64>,
    /// Grid cell size (m).
    pub dx_m: f64,
    /// `"file"`, `"2 x spacing"` or, for a surface-like cloud, `"largest extent / 32 ..."`.
    pub dx_source: String,
    /// Volume of one particle (m³; the mean when the filling measured each particle's).
    pub particle_volume_m3: f64,
    /// `"file"`, `"spacing^3"` or `"the surface layer's voxels / particles"`.
    pub particle_volume_source: String,
    /// Mass of one particle (kg) = density · volume (the mean, as the volume).
    pub particle_mass_kg: f64,
    /// Total mass (kg), fillers included.
    pub total_mass_kg: f64,
    /// What the interior filling did (see `pipe::simulate::fill`).
    pub fill: String,
    /// Particles added inside a closed surface: simulated, not written.
    pub fill_particles: usize,
    /// Volume of a whole filler particle, the filling's voxel (m³; 0 without fillers); those
    /// next to the surface have half of it.
    pub fill_particle_volume_m3: f64,
    /// The file's domain (m), whose walls hold the particles that reach it; `null` when the
    /// grid follows the particles (see `frame_stats[].grid`).
    pub domain: Option<BoxSpec>,
    /// How the grid was chosen.
    pub domain_source: String,
    /// Grid nodes per axis of a fixed domain (plus the simulator's margin); `null` when the
    /// grid follows the particles.
    pub grid_nodes: Option<[usize; 3]>,
    /// Boundaries in the order applied.
    pub boundaries: Vec<String>,
    /// External forces and impulses.
    pub forces: usize,
    /// Gravity (m/s²).
    pub gravity: [f64; 3],
    /// Initial velocity (m/s): of every particle, or of `spin_centre` when the body spins.
    pub initial_velocity: [f64; 3],
    /// Initial angular velocity (rad/s) about `spin_centre`.
    #[serde(default)]
    pub angular_velocity: [f64; 3],
    /// The point the body spins about (m): the file's `spin_centre`, or the centre of mass.
    #[serde(default)]
    pub spin_centre: [f64; 3],
    /// Substeps over the whole run.
    pub substeps_total: usize,
    /// Per simulated frame.
    pub frame_stats: Vec<FrameStats>,
    /// Particle-substeps held at the walls over the whole run.
    pub held_total: usize,
    /// Things the user should know (automatic choices that may be wrong, unstable steps).
    pub warnings: Vec<String>,
    /// Whether `splats_NNNN.ply` were written (`--splats`).
    #[serde(default)]
    pub splats: bool,
    /// Floating-point precision of the simulation (`f64` or `f32`).
    #[serde(default)]
    pub precision: String,
    /// Wall-clock time of the whole command (s).
    pub wall_time_s: f64,
    /// Where the wall-clock time went (s).
    #[serde(default)]
    pub timing_s: Timing,
}

/// The command's wall-clock time by part (s).
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
pub struct Timing {
    /// Reading the inputs, measuring the spacing, filling, loading and sorting the particles
    /// in the simulator: everything before the first substep.
    pub setup: f64,
    /// The substeps alone (the simulator's kernels), over all frames.
    pub substeps: f64,
    /// The rest: reading back each frame's state and handing it to the writer thread, the
    /// stability check of each frame, waiting for the writer at the end (the frame PLYs and
    /// `particles.arrow` are written while the next frame simulates) and the summary.
    pub output: f64,
}

impl Summary {
    /// What the grid did: the walls' holds of a fixed domain, or how far a following grid
    /// spread.
    fn grid_line(&self) -> String {
        match self.domain {
            Some(_) => format!(
                "{} particle-substeps held at the domain walls",
                self.held_total
            ),
            None => {
                let widest = self
                    .frame_stats
                    .iter()
                    .filter_map(|f| f.grid)
                    .map(|g| std::array::from_fn::<f64, 3, _>(|a| g.max[a] - g.min[a]))
                    .fold([0.0f64; 3], |m, e| std::array::from_fn(|a| m[a].max(e[a])));
                format!(
                    "grid following the particles (widest {} x {} x {} m)",
                    short_number(widest[0]),
                    short_number(widest[1]),
                    short_number(widest[2])
                )
            }
        }
    }

    /// A few lines for the terminal: what ran, how many substeps and why, what was written.
    pub fn report(&self, out: &Path) -> String {
        let reasons: std::collections::BTreeSet<&str> = self
            .frame_stats
            .iter()
            .map(|f| f.substeps_reason.as_str())
            .collect();
        let (lo, hi) = self.frame_stats.iter().fold((usize::MAX, 0), |(a, b), f| {
            (a.min(f.substeps), b.max(f.substeps))
        });
        let (cfl_lo, cfl_hi) = self
            .frame_stats
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), f| {
                (a.min(f.cfl_number), b.max(f.cfl_number))
            });
        let steps = if self.frame_stats.is_empty() {
            "no substeps (frame 0 only)".to_string()
        } else {
            format!(
                "{} substeps ({lo}-{hi} per frame, set by: {}; CFL number {cfl_lo:.2}-{cfl_hi:.2})",
                self.substeps_total,
                reasons.into_iter().collect::<Vec<_>>().join(", ")
            )
        };
        let mut text = format!(
            "simulated {} frame(s) of {} ({}) in {:.1} s: {steps}; dx {} m, particle \
             volume {} m^3, {}\nwrote {} frame PLYs{}, \
             particles.arrow and summary.json to {}",
            self.frames.saturating_sub(1),
            if self.carrier_particles == self.particles_out {
                format!("{} particles", self.particles_out)
            } else {
                format!(
                    "{} splats riding {} particles",
                    self.particles_out, self.carrier_particles
                )
            },
            super::spec::family_name(self.material.family),
            self.wall_time_s,
            short_number(self.dx_m),
            short_number(self.particle_volume_m3),
            self.grid_line(),
            self.frames,
            if self.splats {
                format!(" and {} splat PLYs", self.frames)
            } else {
                String::new()
            },
            out.display()
        );
        for w in &self.warnings {
            text.push_str(&format!("\nwarning: {w}"));
        }
        text
    }
}

/// `DIR/frame_0007.ply`.
pub fn frame_path(dir: &Path, frame: u32) -> PathBuf {
    dir.join(format!("frame_{frame:04}.ply"))
}

/// `DIR/splats_0007.ply`.
pub fn splats_path(dir: &Path, frame: u32) -> PathBuf {
    dir.join(format!("splats_{frame:04}.ply"))
}

/// One output frame, as the simulating thread hands it to the writer: positions (m) and
/// velocities (m/s) in `f32`, as written, and the splats (`--splats`).
pub(crate) struct FrameOut {
    frame: u32,
    x: Vec<[f32; 3]>,
    v: Vec<[f32; 3]>,
    splats: Option<Gaussians>,
}

impl FrameOut {
    pub(crate) fn new(frame: u32, x: &[DVec3], v: &[DVec3], splats: Option<Gaussians>) -> Self {
        let f32s = |p: &[DVec3]| p.iter().map(|p| p.as_vec3().to_array()).collect();
        Self {
            frame,
            x: f32s(x),
            v: f32s(v),
            splats,
        }
    }
}

/// What the simulating thread sends the writer.
pub(crate) enum ToWriter {
    Frame(Box<FrameOut>),
    /// The run succeeded: finish `particles.arrow`.
    Finish,
}

/// The writer (a thread of its own, so that a frame's files are written while the next frame
/// simulates): each frame's `frame_NNNN.ply`, `splats_NNNN.ply` and rows of `particles.arrow`.
/// The table is finished on [`ToWriter::Finish`] only: a run that fails leaves none, and its
/// temporary file is removed. Stops at its first error.
pub(crate) fn write_frames(dir: &Path, frames: Receiver<ToWriter>) -> Result<(), SimulateError> {
    let mut table = table::Writer::<Trajectories>::create(&dir.join("particles.arrow"))?;
    for message in frames {
        match message {
            ToWriter::Frame(f) => {
                ply::write_points(&frame_path(dir, f.frame), &f.x, None)?;
                table.write(&Trajectories::frame_batch(f.frame as u16, &f.x, &f.v))?;
                if let Some(g) = &f.splats {
                    ply::write_gaussians(&splats_path(dir, f.frame), g)?;
                }
            }
            ToWriter::Finish => return Ok(table.finish()?),
        }
    }
    Ok(())
}

/// Creates `dir` and removes `frame_NNNN.ply` and `splats_NNNN.ply` files of an earlier,
/// longer run (frames ≥ `frames`; every `splats_NNNN.ply` unless `splats`), so the folder holds
/// exactly this run's frames. Returns the files removed.
pub fn prepare_dir(dir: &Path, frames: u32, splats: bool) -> Result<Vec<PathBuf>, SimulateError> {
    let io = |action: &'static str| {
        move |source| SimulateError::Io {
            path: dir.to_path_buf(),
            action,
            source,
        }
    };
    std::fs::create_dir_all(dir).map_err(io("create the output folder"))?;
    let mut removed = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io("list the output folder"))? {
        let entry = entry.map_err(io("list the output folder"))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let numbered = |prefix: &str| {
            name.strip_prefix(prefix)
                .and_then(|s| s.strip_suffix(".ply"))
                .filter(|d| d.len() >= 4 && d.bytes().all(|b| b.is_ascii_digit()))
                .and_then(|d| d.parse::<u64>().ok())
        };
        let stale = numbered("frame_").is_some_and(|k| k >= u64::from(frames))
            || numbered("splats_").is_some_and(|k| !splats || k >= u64::from(frames));
        if stale {
            std::fs::remove_file(entry.path()).map_err(|source| SimulateError::Io {
                path: entry.path(),
                action: "remove a stale frame",
                source,
            })?;
            removed.push(entry.path());
        }
    }
    Ok(removed)
}

/// Writes `summary.json` atomically.
pub fn write_summary(dir: &Path, summary: &Summary) -> Result<(), SimulateError> {
    let path = dir.join("summary.json");
    let text = serde_json::to_string_pretty(summary).expect("the summary serialises") + "\n";
    crate::pipeline::cache::write_atomic(&path, text.as_bytes()).map_err(|source| {
        SimulateError::Io {
            path,
            action: "write",
            source,
        }
    })
}
