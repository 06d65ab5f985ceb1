//! What the `velocity` and `material` stages share: their inputs (the `ingest` frames, the
//! canonical Gaussians, the frame interval), their settings common to both, the object, and
//! the initial velocity field of a rigid motion.

use std::path::PathBuf;

use glam::DVec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::object::{Object, ObjectSettings, Resolution};
use super::params::MaterialValues;
use crate::pipeline::spec::{MaterialFamily, SceneSpec};
use crate::pipeline::stage::{StageContext, StageError};
use crate::scene::frames::{FrameRow, Frames, Role};
use crate::scene::gaussians::Gaussians;
use crate::scene::table;
use crate::scene::targets::{self, Target};

/// A problem a physics stage reports.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The inputs cannot be used.
    #[error("{0}")]
    Invalid(String),
    /// A value went NaN/Inf or the simulation failed during training.
    #[error("epoch {epoch}: {message}")]
    Training {
        /// Epoch (0-based).
        epoch: u32,
        /// What, where (frame, substep, quantity) and what to try.
        message: String,
    },
}

/// Floating-point precision of a stage's simulation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PrecisionParam {
    /// Single precision, as the peer simulators: about twice as fast.
    #[default]
    F32,
    /// Double precision.
    F64,
}

impl PrecisionParam {
    /// The simulator's precision.
    pub fn mpm(self) -> pipe_mpm::Precision {
        match self {
            PrecisionParam::F32 => pipe_mpm::Precision::F32,
            PrecisionParam::F64 => pipe_mpm::Precision::F64,
        }
    }
}

/// The inputs of a physics stage.
#[derive(Debug)]
pub struct Inputs {
    /// The `ingest` entry.
    pub ingest_dir: PathBuf,
    /// Its frames.
    pub frames: Frames,
    /// The background colour images were composited on.
    pub background: [f32; 3],
    /// The canonical Gaussians (`warmup`).
    pub gaussians: Gaussians,
    /// Time between frames (s), from the frames' times.
    pub frame_dt: f64,
    /// The scene's material family.
    pub family: MaterialFamily,
}

fn invalid(message: String) -> StageError {
    StageError::failed(FitError::Invalid(message))
}

impl Inputs {
    /// Reads the upstream `ingest` and `warmup` entries of `ctx`.
    pub fn load(ctx: &StageContext<'_>) -> Result<Self, StageError> {
        let ingest = ctx.upstream("ingest")?.clone();
        let background: [f32; 3] =
            serde_json::from_value(ingest.manifest.key_material.params["background"].clone())
                .unwrap_or([1.0, 1.0, 1.0]);
        let frames: Frames =
            table::read(&ingest.dir.join("frames.arrow")).map_err(StageError::failed)?;
        let gaussians: Gaussians =
            table::read(&ctx.upstream("warmup")?.dir.join("gaussians.arrow"))
                .map_err(StageError::failed)?;
        if gaussians.is_empty() {
            return Err(invalid("warmup produced no Gaussians".into()));
        }
        let family = ctx.scene.material.ok_or_else(|| {
            invalid(format!(
                "stage `{}` needs the scene's material family: add `material:` (elastic, \
                 elastic_fcr, plasticine, non_newtonian, newtonian or sand) to the `scene:` \
                 section",
                ctx.name
            ))
        })?;
        let frame_dt = frame_interval(&frames.rows)?;
        Ok(Self {
            ingest_dir: ingest.dir,
            frames,
            background,
            gaussians,
            frame_dt,
            family,
        })
    }

    /// The last frame index.
    pub fn last_frame(&self) -> u16 {
        self.frames.rows.iter().map(|r| r.frame).max().unwrap_or(0)
    }

    /// The training targets of frames `1..=last` (frame 0 is the canonical state).
    pub fn train_targets(&self, last: u16) -> Result<Vec<Target>, StageError> {
        let rows: Vec<&FrameRow> = self
            .frames
            .rows
            .iter()
            .filter(|r| r.role == Role::Train && r.frame >= 1 && r.frame <= last)
            .collect();
        targets::load(&self.ingest_dir, &rows).map_err(StageError::failed)
    }

    /// The rasterizer's filter (m) in the images the canonical Gaussians were fitted to: the
    /// training views of frame 0.
    pub fn splat_filter(&self) -> f64 {
        let views: Vec<&FrameRow> = self
            .frames
            .rows
            .iter()
            .filter(|r| r.role == Role::Train && r.frame == 0)
            .collect();
        super::object::render_filter(&views, &self.gaussians)
    }

    /// The object at `material`, on a grid of resolution `grid`.
    pub fn object(
        &self,
        ctx: &StageContext<'_>,
        material: &MaterialValues,
        grid: Resolution,
    ) -> Result<Object, StageError> {
        let settings = ObjectSettings {
            scene: ctx.scene,
            frame_dt: self.frame_dt,
            grid,
            material: material.spec(),
            frames: u32::from(self.last_frame()) + 1,
            label: PathBuf::from(format!("stages.{}", ctx.name)),
            splat_filter: self.splat_filter(),
            anchor: None,
        };
        Object::build(&self.gaussians, &settings).map_err(StageError::failed)
    }
}

/// The time between frames (s): the frames' times must be evenly spaced.
pub fn frame_interval(rows: &[FrameRow]) -> Result<f64, StageError> {
    let mut times: Vec<(u16, f64)> = rows.iter().map(|r| (r.frame, r.time_s)).collect();
    times.sort_by_key(|t| t.0);
    times.dedup_by_key(|t| t.0);
    if times.len() < 2 {
        return Err(invalid(
            "the capture has a single frame: nothing moves to learn from".into(),
        ));
    }
    let (f0, t0) = times[0];
    let (f1, t1) = times[times.len() - 1];
    let dt = (t1 - t0) / f64::from(f1 - f0);
    if !(dt.is_finite() && dt > 0.0) {
        return Err(invalid(format!(
            "frames.arrow: the frames' times do not increase (frame {f0} at {t0} s, frame {f1} \
             at {t1} s)"
        )));
    }
    for &(f, t) in &times {
        let expected = t0 + f64::from(f - f0) * dt;
        if (t - expected).abs() > 1e-3 * dt + 1e-9 {
            return Err(invalid(format!(
                "frames.arrow: frame {f} is at {t} s, not {expected} s: the frames must be \
                 evenly spaced (all_data.json `time`)"
            )));
        }
    }
    Ok(dt)
}

/// An initial velocity field: a translation, or a rigid motion `v + ω × (x − c)` about the
/// centre of mass `c`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct RigidVelocity {
    /// Linear velocity of the centre of mass (m/s).
    pub linear: [f64; 3],
    /// Angular velocity (rad/s).
    pub angular: [f64; 3],
    /// The centre of mass (m) it turns about.
    pub centre: [f64; 3],
}

impl RigidVelocity {
    /// The velocity of every particle of `object` (m/s).
    pub fn field(&self, object: &Object) -> Vec<DVec3> {
        let (v, w, c) = (
            DVec3::from_array(self.linear),
            DVec3::from_array(self.angular),
            DVec3::from_array(self.centre),
        );
        object
            .body
            .state
            .x
            .iter()
            .map(|x| v + w.cross(*x - c))
            .collect()
    }

    /// `(∂L/∂v, ∂L/∂ω)` from `∂L/∂v_p` of every particle.
    pub fn gradient(&self, object: &Object, g: &[DVec3]) -> (DVec3, DVec3) {
        let c = DVec3::from_array(self.centre);
        let x = &object.body.state.x;
        let gv = g.iter().sum::<DVec3>();
        let gw = x
            .iter()
            .zip(g)
            .map(|(x, g)| (*x - c).cross(*g))
            .sum::<DVec3>();
        (gv, gw)
    }

    /// The mass-weighted mean velocity of `object`'s particles (m/s).
    pub fn mean(&self, object: &Object) -> DVec3 {
        let m = &object.body.material.mass;
        let total: f64 = m.iter().sum();
        self.field(object)
            .iter()
            .zip(m)
            .map(|(v, m)| *v * *m)
            .sum::<DVec3>()
            / total
    }
}

/// `gt/params.json` of the scene folder, when it has one (for messages only: no stage output
/// depends on it).
pub fn ground_truth(scene: &SceneSpec) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(scene.path.join("gt/params.json")).ok()?;
    serde_json::from_str(&text).ok()
}
