//! Stage `velocity`: the object's initial velocity from the first frames (paper §3.2), by
//! gradient descent through the renderer and the MPM simulation, the material held at a
//! guess of its family (in free flight it barely matters).
//!
//! The descent starts from the velocity of the masks' visual hulls over those frames
//! ([`crate::physics::track`], `init: hull`), then a quasi-Newton descent with a line search
//! ([`crate::physics::descent`]) steps the translation (`model: translation`, 3 numbers) or the
//! rigid motion (`model: rigid`, linear and angular velocity about the centre of mass, 6
//! numbers; the angular one measured as the speed it gives at the object's radius) on the
//! image loss of the training views of frames `1..frames` (frame 0 is the canonical state),
//! back-propagated through every frame to the initial velocity. Writes `velocity.json` and `metrics.arrow` (the loss and the learned values
//! per epoch); checkpoints every epoch, so an interrupted run resumes.

use std::collections::BTreeMap;

use glam::DVec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::physics::descent::LineSearch;
use crate::physics::fit::{FitError, Inputs, PrecisionParam, RigidVelocity};
use crate::physics::free_flight;
use crate::physics::material_field::percentiles;
use crate::physics::object::{Object, Resolution};
use crate::physics::params::{MaterialValues, Param};
use crate::physics::rollout::{Rollout, RolloutError, Wants, Work, is_fluid};
use crate::physics::step_search::{StepSearch, lerp, stalled};
use crate::physics::track;
use crate::physics::velocity_field::{
    VelocityField, VelocityFieldSettings, WEIGHTS_FILE, initial_velocities, write_weights,
};
use crate::physics::views::{LossWeights, ViewsLoss};
use crate::pipeline::spec::{Preset, SceneSpec};
use crate::pipeline::stage::{MetricRow, ParamError, StageContext, StageError, TypedStage};
use crate::stages::material_select::{
    AutoSettings, ModelSelection, decide, decide_again, split_views,
};
use pipe_field::{AdamConfig as FieldAdamConfig, FieldAdam, LrSchedule};

/// The velocity field learned.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum VelocityModel {
    /// The rigid motion, then a field from it kept only when it lowers the loss on training
    /// views it was not fitted on by more than `auto.margin` (as the material's `auto`);
    /// `velocity.json`'s `model` is the one kept.
    #[default]
    Auto,
    /// One velocity for every particle (3 numbers).
    Translation,
    /// Linear and angular velocity about the centre of mass (6 numbers): a thrown or dropped
    /// object.
    Rigid,
    /// The rigid motion plus a triplane + MLP residual per particle (the `field:` block;
    /// [`crate::physics::velocity_field`]).
    Field,
}

/// Where the descent starts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum VelocityInit {
    /// The velocity of the masks' visual hulls over the frames (a least-squares fit of a
    /// ballistic path).
    #[default]
    Hull,
    /// At rest.
    Zero,
}

/// Parameters of `velocity`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct VelocityParams {
    /// Frames `0..frames` are used (the loss is taken at frames `1..frames`).
    #[serde(default = "frames")]
    pub frames: u16,
    /// The velocity field.
    #[serde(default)]
    pub model: VelocityModel,
    /// Where the descent starts.
    #[serde(default)]
    pub init: VelocityInit,
    /// When the masks' hulls show the object in free flight over every frame fitted (with
    /// `init: hull`), fit the rigid or translational motion in closed form
    /// ([`crate::physics::free_flight`]: the body turns and falls as a rigid body, so the fit
    /// costs the renders only, no simulation); `false` simulates it as the other frames are.
    #[serde(default = "closed_form")]
    pub closed_form: bool,
    /// With a rigid motion in closed form, probe spins about x, y and z before the descent
    /// (each axis in turn, from the best so far: ±5°, 10°, 20°, 40° per frame interval) and
    /// start from the one that fits best: a body turning about an axis its silhouette does not
    /// show (a ball, a ring, a disc about its axis) shows its spin only in its texture, whose
    /// loss a descent from rest does not cross.
    #[serde(default = "probe_spin")]
    pub probe_spin: bool,
    /// The stage's simulation work budget, in billions of particle-substeps (as
    /// `material.budget`): no epoch, of the rigid fit or of the field, starts past it. Unset:
    /// no limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget: Option<f64>,
    /// Gradient evaluations (each a rollout over the frames and its adjoint); the descent stops
    /// earlier once it has converged.
    #[serde(default = "epochs")]
    pub epochs: u32,
    /// The line search's first step (m/s; the angular velocity's step is the speed it gives
    /// at the object's radius).
    #[serde(default = "lr")]
    pub lr: f64,
    /// The smallest step (m/s): below it the descent has converged.
    #[serde(default = "lr_final")]
    pub lr_final: f64,
    /// The material held during the fit: values of the scene family's parameters
    /// (`E`, `nu`, `yield_stress`, `viscosity`, `bulk_modulus`, `friction_angle`; SI units,
    /// degrees), each defaulting to the family's guess (E = 1e5 Pa, ν = 0.3, ...).
    #[serde(default)]
    pub guess: BTreeMap<Param, f64>,
    /// Grid cells across the object's largest extent.
    #[serde(default = "cells")]
    pub cells: f64,
    /// Grid cell (m), whatever the object's size; when set it replaces `cells`. The
    /// parameters of plastic and viscous materials are those of the simulation at its cell
    /// (MLS-MPM is not grid-converged at these resolutions): to compare with another
    /// simulator's values, or to reuse the learned ones there, set the cell it uses
    /// (the sample scenes were made at 0.02 m).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dx: Option<f64>,
    /// Precision of the simulation and its adjoint.
    #[serde(default)]
    pub precision: PrecisionParam,
    /// Weight of L1 in `λ·L1 + (1 − λ)·D-SSIM`.
    #[serde(default = "lambda")]
    pub lambda: f64,
    /// Weight of the silhouette term `mean|α − mask|`.
    #[serde(default = "alpha_weight")]
    pub alpha_weight: f64,
    /// The field of `model: field` and `model: auto`.
    #[serde(default)]
    pub field: VelocityFieldSettings,
    /// How `model: auto` decides.
    #[serde(default)]
    pub auto: AutoSettings,
}

fn closed_form() -> bool {
    true
}
fn probe_spin() -> bool {
    true
}
fn converged_default() -> bool {
    true
}
fn frames() -> u16 {
    4
}
fn epochs() -> u32 {
    30
}
fn lr() -> f64 {
    0.05
}
fn lr_final() -> f64 {
    0.0005
}
fn cells() -> f64 {
    24.0
}
fn lambda() -> f64 {
    crate::scene::targets::DEFAULT_LAMBDA
}
fn alpha_weight() -> f64 {
    0.1
}

/// What an interrupted run resumes from.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Checkpoint {
    /// Epochs done.
    epoch: u32,
    /// The learned values, in the optimiser's order.
    x: Vec<f64>,
    search: LineSearch,
    converged: bool,
    /// Where the descent started.
    start: Vec<f64>,
    /// Particle-substeps simulated so far (`budget`).
    #[serde(default)]
    work: u64,
}

/// The `velocity` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Velocity;

/// `velocity.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VelocityResult {
    /// `translation`, `rigid` or `field` (the rigid motion plus the residual field in
    /// `field.velocity.arrow`; `model: auto` says which it kept).
    pub model: VelocityModel,
    /// Linear velocity of the centre of mass (m/s).
    pub linear_velocity: [f64; 3],
    /// Angular velocity (rad/s; zero for a translation).
    pub angular_velocity: [f64; 3],
    /// The centre of mass (m) the rotation is about.
    pub centre_of_mass: [f64; 3],
    /// The particles' mass-weighted mean velocity (m/s): what a simulation file's
    /// `initial_velocity` takes.
    pub initial_velocity: [f64; 3],
    /// Where the descent started (m/s), and its angular velocity (rad/s; the hulls' turn, or
    /// zero).
    pub start_velocity: [f64; 3],
    #[serde(default)]
    pub start_angular_velocity: [f64; 3],
    /// How the start was found.
    pub init: VelocityInit,
    /// Whether the descent converged (or stalled) before `epochs` ran out.
    #[serde(default = "converged_default")]
    pub converged: bool,
    /// Frames used (`0..frames`).
    pub frames: u16,
    /// Loss at the start and at the learned velocity.
    pub loss_start: f64,
    pub loss_final: f64,
    /// The material held during the fit.
    pub material: MaterialValues,
    /// Simulated particles (Gaussians and fillers), Gaussians among them, and Gaussians
    /// dropped as floaters.
    pub particles: usize,
    pub gaussians: usize,
    pub floaters: usize,
    /// `model: field`: the residual's speeds and the loss of the rigid motion it refined.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<VelocityFieldSummary>,
    /// `model: auto`: the two models' held-out losses and which was kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection: Option<ModelSelection>,
}

/// The learned velocity field in `velocity.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VelocityFieldSummary {
    /// 5th, 50th and 95th percentiles of the residual's speed over the particles (m/s).
    pub residual_speed_p05_p50_p95: [f64; 3],
    /// Loss at the rigid motion the field started from.
    pub loss_rigid: f64,
    /// The weights' table and their count.
    pub weights_table: String,
    pub weights: usize,
}

impl VelocityResult {
    /// The learned rigid motion about `object`'s own centre of mass (without a field's
    /// residual).
    pub fn rigid(&self, object: &crate::physics::object::Object) -> RigidVelocity {
        RigidVelocity {
            linear: self.linear_velocity,
            angular: self.angular_velocity,
            centre: object.centre_of_mass().to_array(),
        }
    }

    /// The initial velocity of every particle of `object` (m/s) as learned (about `object`'s
    /// own centre of mass), the field's residual included; `dir` is the `velocity` entry.
    ///
    /// # Errors
    /// An unreadable field, named.
    pub fn velocities(
        &self,
        object: &crate::physics::object::Object,
        dir: &std::path::Path,
    ) -> Result<Vec<DVec3>, StageError> {
        let rigid = self.rigid(object);
        let field = (self.model == VelocityModel::Field).then(|| dir.join(WEIGHTS_FILE));
        initial_velocities(object, &rigid, field.as_deref())
            .map_err(|e| StageError::failed(FitError::Invalid(e)))
    }
}

impl TypedStage for Velocity {
    type Params = VelocityParams;
    const KIND: &'static str = "velocity";
    const VERSION: u32 = 17;
    const DESCRIPTION: &'static str = "Learn the initial velocity from the first frames (gradient descent through the renderer and the MPM simulation)";
    const UPSTREAM: &'static [&'static str] = &["ingest", "warmup"];

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        Vec::new()
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            Preset::Draft => {
                json!({"model": "rigid", "epochs": 12, "cells": 16, "field": {"epochs": 12}})
            }
            // The budget: ~6 min of a field's particle-substeps (1.9e7 a second on 2 cores with
            // the renders, the sample droplet's); the rigid fit is mostly in closed form.
            Preset::Standard => json!({
                "epochs": 30, "cells": 24, "budget": 7.0, "field": {"epochs": 30}
            }),
            Preset::Paper => json!({
                "epochs": 100, "cells": 32, "precision": "f64", "field": {"epochs": 100}
            }),
        }
    }

    fn scene_key(&self, scene: &SceneSpec) -> Value {
        scene.physics_key()
    }

    fn validate(&self, p: &VelocityParams) -> Result<(), ParamError> {
        let bad = |path: &str, message: String| {
            Err(ParamError {
                path: path.into(),
                message,
            })
        };
        if p.frames < 2 {
            return bad(
                "frames",
                format!("needs at least 2 frames, found {}", p.frames),
            );
        }
        if p.epochs == 0 {
            return bad("epochs", "must be at least 1".into());
        }
        for (name, v) in [("lr", p.lr), ("lr_final", p.lr_final)] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, format!("must be finite and >= 0, found {v}"));
            }
        }
        if let Err((field, message)) = Resolution::check(p.cells, p.dx) {
            return bad(field, message);
        }
        if !(0.0..=1.0).contains(&p.lambda) {
            return bad("lambda", format!("must be in [0, 1], found {}", p.lambda));
        }
        if !(p.alpha_weight.is_finite() && p.alpha_weight >= 0.0) {
            return bad(
                "alpha_weight",
                format!("must be >= 0, found {}", p.alpha_weight),
            );
        }
        if let Err((name, why)) = p.auto.check() {
            return bad(name, why);
        }
        if let Err(why) = Work::check_budget(p.budget) {
            return bad("budget", why);
        }
        if matches!(p.model, VelocityModel::Field | VelocityModel::Auto) {
            if let Err(e) = p.field.config().validate() {
                return bad("field", e.to_string());
            }
            for (name, v) in [
                ("field.lr", p.field.lr),
                ("field.lr_final", p.field.lr_final),
            ] {
                if !(v.is_finite() && v > 0.0) {
                    return bad(name, format!("must be finite and > 0, found {v}"));
                }
            }
            if p.field.epochs == Some(0) {
                return bad("field.epochs", "must be at least 1".into());
            }
        }
        check_guess(&p.guess)
    }

    fn run(&self, p: &VelocityParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let inputs = Inputs::load(ctx)?;
        let mut last = p.frames.saturating_sub(1).min(inputs.last_frame());
        if last == 0 {
            return Err(StageError::failed(FitError::Invalid(format!(
                "stages.{}.frames = {}: the capture has no frame after frame 0",
                ctx.name, p.frames
            ))));
        }
        // The first estimate, from the masks' hulls, over the frames still in free flight: a
        // fast object that lands within the stage's frames leaves the ballistic path, and the
        // frames after that say how it landed (the material, unknown here), not how it was
        // thrown; the fit below stops there too.
        let g = DVec3::from_array(ctx.scene.gravity);
        let mut in_free_flight = false;
        let (start_v, start_w) = match p.init {
            VelocityInit::Zero => (DVec3::ZERO, None),
            VelocityInit::Hull => {
                let frames: Vec<u16> = (0..=last).collect();
                let (samples, voxel) =
                    track::hull_samples(&inputs.ingest_dir, &inputs.frames.rows, &frames)
                        .map_err(StageError::failed)?;
                let centres: Vec<(f64, DVec3)> =
                    samples.iter().map(|s| (s.time_s, s.centre)).collect();
                let k = track::free_flight(&centres, g, 2.0 * voxel);
                if k >= 2 && k < centres.len() {
                    let free = (k - 1) as u16;
                    ctx.progress.log(&format!(
                        "velocity: the object leaves free flight after frame {free} (its hull's centre is off the ballistic path of frames 0..={free} by more than two voxels, {:.1} mm): fitting frames 1..={free}",
                        2e3 * voxel
                    ));
                    last = last.min(free.max(1));
                }
                in_free_flight = k >= 2 && usize::from(last) < k;
                (
                    track::fit_velocity(&centres[..k], g).unwrap_or(DVec3::ZERO),
                    track::fit_angular_velocity(&samples[..k]),
                )
            }
        };
        let material = MaterialValues::guess(inputs.family, ctx.scene.density, &p.guess);
        check_family_guess(&material, &p.guess, ctx.name)?;
        let object = inputs.object(ctx, &material, Resolution::of(p.cells, p.dx))?;
        let centre = object.centre_of_mass().to_array();
        let spins = !matches!(p.model, VelocityModel::Translation);
        let start_motion = RigidVelocity {
            linear: start_v.to_array(),
            angular: start_w.filter(|_| spins).unwrap_or(DVec3::ZERO).to_array(),
            centre,
        };
        let targets = inputs.train_targets(last)?;
        let weights = LossWeights {
            lambda: p.lambda,
            alpha_weight: p.alpha_weight,
        };
        let fluid = is_fluid(inputs.family);
        let mut loss = ViewsLoss::new(&object, fluid, &targets, weights, inputs.background);
        let closed = p.closed_form
            && in_free_flight
            && free_flight::touches_nothing(&object, &start_motion, last);
        ctx.progress.log(&format!(
            "velocity: {} ({} floaters dropped), {:.2} kg, frames 1..={last}, {} views{}",
            object.particle_summary(),
            object.floaters,
            object.mass(),
            targets.len(),
            if closed {
                "; in free flight: the rigid motion in closed form"
            } else {
                ""
            }
        ));

        let dims = match p.model {
            VelocityModel::Translation => 3,
            VelocityModel::Rigid | VelocityModel::Field | VelocityModel::Auto => 6,
        };
        let mut x: Vec<f64> = start_v.to_array().to_vec();
        x.resize(dims, 0.0);
        let mut search = LineSearch::new(p.lr, p.lr_final, 20.0 * p.lr);
        let mut converged = false;
        let mut first_epoch = 0;
        let mut start: Vec<f64> = x.clone();
        let interrupt = ctx.interrupt_flag();
        let mut work_done = 0;
        if let Some(ck) = ctx.resume::<Checkpoint>()
            && ck.x.len() == dims
        {
            (first_epoch, x, search, converged, start, work_done) =
                (ck.epoch, ck.x, ck.search, ck.converged, ck.start, ck.work);
        }
        let work = Work::starting_at(work_done);
        // The angular velocity's coordinates are the speed (m/s) it gives at the object's
        // radius, comparable with the linear velocity's.
        let c = DVec3::from_array(centre);
        let radius = object
            .body
            .state
            .x
            .iter()
            .map(|x| (*x - c).length())
            .fold(0.0, f64::max)
            .max(1e-6);
        let rigid = |x: &[f64]| RigidVelocity {
            linear: [x[0], x[1], x[2]],
            angular: if x.len() == 6 {
                [x[3] / radius, x[4] / radius, x[5] / radius]
            } else {
                [0.0; 3]
            },
            centre,
        };
        let precision = p.precision.mpm();
        let sim = Simulated {
            object: &object,
            material: &material,
            last,
            precision,
            interrupt,
            work: &work,
        };
        let fail = |epoch: u32, e: RolloutError| -> StageError {
            match e {
                RolloutError::Interrupted => StageError::Interrupted,
                e => StageError::failed(FitError::Training {
                    epoch,
                    message: format!("{e}; try a smaller `lr`, `precision: f64` or more `cells`"),
                }),
            }
        };
        // The loss of a rigid motion: in closed form in free flight, else simulated.
        let rigid_loss =
            |x: &[f64], up_to: f64, loss: &mut ViewsLoss<'_>| -> Result<f64, RolloutError> {
                if closed {
                    free_flight::run(&object, &rigid(x), last, fluid, loss, false).map(|(l, _)| l)
                } else {
                    sim.loss(&rigid(x).field(&object), loss, Some(up_to))
                }
            };
        // The hulls' turn (`track::fit_angular_velocity`) is a second start, kept when it fits
        // the frames better than no spin: a tumbling throw turns by tens of degrees over the
        // fitted frames, and a descent from rest takes three times the epochs to find it.
        // The loss at `start`, once a start search has computed it.
        let mut start_loss = None;
        if dims == 6
            && first_epoch == 0
            && let Some(w) = start_w
        {
            let mut spun = x.clone();
            spun[3..].copy_from_slice(&(w * radius).to_array());
            let still = rigid_loss(&x, f64::INFINITY, &mut loss).map_err(|e| fail(0, e))?;
            let turned = rigid_loss(&spun, f64::INFINITY, &mut loss).map_err(|e| fail(0, e))?;
            let keep = turned < still;
            start_loss = Some(turned.min(still));
            ctx.progress.log(&format!(
                "velocity: the hulls turn at [{:.2}, {:.2}, {:.2}] rad/s: loss {turned:.5} against {still:.5} without spin; {}",
                w.x,
                w.y,
                w.z,
                if keep {
                    "the descent starts there"
                } else {
                    "the descent starts without spin"
                }
            ));
            if keep {
                x = spun;
                start = x.clone();
            }
        }
        if dims == 6 && first_epoch == 0 && closed && p.probe_spin {
            let from = match start_loss {
                Some(l) => l,
                None => rigid_loss(&x, f64::INFINITY, &mut loss).map_err(|e| fail(0, e))?,
            };
            let (probed, best) = probe_spins(&x, from, radius, inputs.frame_dt, |trial| {
                rigid_loss(trial, f64::INFINITY, &mut loss).map_err(|e| fail(0, e))
            })?;
            start_loss = Some(best);
            if best < from {
                let w = rigid(&probed).angular;
                ctx.progress.log(&format!(
                    "velocity: probing spins about x, y and z: [{:.2}, {:.2}, {:.2}] rad/s fits best (loss {best:.5} against {from:.5}); the descent starts there",
                    w[0], w[1], w[2]
                ));
                x = probed;
                start = x.clone();
            }
        }
        ctx.progress.start("epoch", u64::from(p.epochs));
        ctx.progress.inc(u64::from(first_epoch));
        // The loss after each epoch's step: three epochs that gain less than 0.1 % end the fit.
        let mut losses: Vec<f64> = Vec::new();
        for epoch in first_epoch..p.epochs {
            ctx.check_interrupted()?;
            if converged {
                break;
            }
            if let Some(note) = work.spent(p.budget) {
                ctx.progress.log(&format!(
                    "velocity: {note}: the descent stops after {epoch} epoch(s)"
                ));
                break;
            }
            let field = rigid(&x);
            let v0 = field.field(&object);
            let rollout = sim.rollout(&v0);
            let (l, (gv, gw)) = if closed {
                let (l, g) = free_flight::run(&object, &field, last, fluid, &mut loss, true)
                    .map_err(|e| fail(epoch, e))?;
                (l, g.expect("a gradient was asked for"))
            } else {
                let out = rollout
                    .run(&mut loss, Wants::Velocity)
                    .map_err(|e| fail(epoch, e))?;
                let gp = out.v0.as_ref().expect("a velocity rollout gives ∂L/∂v0");
                (out.loss(), field.gradient(&object, gp))
            };
            let mut grad: Vec<f64> = gv.to_array().to_vec();
            if dims == 6 {
                grad.extend((gw / radius).to_array());
            }
            if grad.iter().any(|v| !v.is_finite()) {
                return Err(StageError::failed(FitError::Training {
                    epoch,
                    message: "non-finite gradient of the initial velocity".into(),
                }));
            }
            let mut metric = |name: &str, value: f64| {
                ctx.metric(MetricRow {
                    epoch: Some(epoch),
                    view: None,
                    frame: None,
                    metric: name.into(),
                    value,
                })
            };
            metric("loss", l);
            for (k, name) in ["vx", "vy", "vz"].iter().enumerate() {
                metric(name, x[k]);
            }
            for (k, name) in ["wx", "wy", "wz"].iter().enumerate() {
                metric(name, field.angular[k]);
            }
            let it = search
                .iterate(&x, l, &grad, |trial, up_to| {
                    rigid_loss(trial, up_to, &mut loss)
                })
                .map_err(|e| fail(epoch, e))?;
            metric("step", it.step);
            metric("trials", it.trials as f64);
            x = it.u;
            losses.push(it.loss.min(l));
            converged = search.converged() || stalled(&losses);
            ctx.progress.message(&format!(
                "loss {l:.5}  v [{:.4}, {:.4}, {:.4}] m/s",
                x[0], x[1], x[2]
            ));
            ctx.progress.inc(1);
            ctx.checkpoint(
                &format!("epoch {}", epoch + 1),
                &Checkpoint {
                    epoch: epoch + 1,
                    x: x.clone(),
                    search: search.clone(),
                    converged,
                    start: start.clone(),
                    work: work.done(),
                },
            )?;
        }
        // A descent cut short by `epochs` while the loss still falls leaves a velocity the
        // material stage then has to explain: say so.
        let n = losses.len();
        let cut_short = !converged && first_epoch + n as u32 == p.epochs && n >= 2;
        if cut_short {
            let k = n.min(4);
            let (then, now) = (losses[n - k], losses[n - 1]);
            ctx.progress.warn(&format!(
                "velocity: the descent had not converged after {} epochs (the loss still fell {:.1} % over the last {}); raise stages.{}.epochs",
                p.epochs,
                100.0 * (then - now) / then.abs().max(f64::MIN_POSITIVE),
                k - 1,
                ctx.name
            ));
        }
        if closed && !free_flight::touches_nothing(&object, &rigid(&x), last) {
            ctx.progress.warn(&format!(
                "velocity: the learned motion comes within two grid cells of a boundary by frame {last}, which the closed form does not see; set stages.{}.closed_form: false to simulate it",
                ctx.name
            ));
        }
        // The loss at the start and at the learned velocity.
        let eval = |x: &[f64], loss: &mut ViewsLoss<'_>| -> Result<f64, StageError> {
            rigid_loss(x, f64::INFINITY, loss).map_err(|e| fail(p.epochs, e))
        };
        let loss_start = match start_loss {
            Some(l) => l,
            None => eval(&start, &mut loss)?,
        };
        let loss_rigid = eval(&x, &mut loss)?;
        let field = rigid(&x);
        let fit_field = |ctx: &mut StageContext<'_>, loss: &mut ViewsLoss<'_>| {
            fit_velocity_field(
                &p.field,
                p.epochs,
                p.budget,
                ctx,
                &Frozen {
                    sim,
                    base: field.field(&object),
                },
                loss,
            )
        };
        let base_model = match p.model {
            VelocityModel::Translation => VelocityModel::Translation,
            _ => VelocityModel::Rigid,
        };
        let (learned_field, selection) = match p.model {
            VelocityModel::Translation | VelocityModel::Rigid => (None, None),
            VelocityModel::Field => (Some(fit_field(ctx, &mut loss)?), None),
            VelocityModel::Auto if work.spent(p.budget).is_some() => {
                let reason = "the rigid fit spent the work budget (`budget`): no field was fitted"
                    .to_string();
                ctx.progress.log(&format!("velocity auto: {reason}"));
                let (held, fit_views) = split_views(&targets, &p.auto, ctx.name)?;
                let selection = ModelSelection {
                    reason,
                    ..ModelSelection::simpler("rigid", held, fit_views, p.auto.margin, last)
                };
                (None, Some(selection))
            }
            VelocityModel::Auto => {
                let (held, fit_views) = split_views(&targets, &p.auto, ctx.name)?;
                let mut held_loss = ViewsLoss::new(
                    &object,
                    fluid,
                    targets.iter().filter(|t| held.contains(&t.row.view)),
                    weights,
                    inputs.background,
                );
                let mut fit_loss = ViewsLoss::new(
                    &object,
                    fluid,
                    targets.iter().filter(|t| !held.contains(&t.row.view)),
                    weights,
                    inputs.background,
                );
                ctx.progress.log(&format!(
                    "velocity auto: the field is fitted on views {fit_views:?} and compared with the rigid motion on views {held:?}"
                ));
                let f = fit_field(ctx, &mut fit_loss)?;
                // Both simulated, so the comparison is between the two motions only.
                let lg = sim
                    .loss(&field.field(&object), &mut held_loss, None)
                    .map_err(|e| fail(p.epochs, e))?;
                let lf = sim
                    .loss(&f.1, &mut held_loss, None)
                    .map_err(|e| fail(p.epochs, e))?;
                let (mut wins, mut reason) =
                    decide(lg, lf, p.auto.margin, "rigid motion", "the field");
                let mut regrid = None;
                if wins && p.auto.regrid != 1.0 {
                    // The same object on another grid (`auto.regrid`), the field read at its
                    // particles' rest positions: a gain that depends on the discretisation is
                    // not the object's.
                    let dx = p.auto.regrid * object.body.setup.dx;
                    ctx.progress.log(&format!(
                        "velocity auto: {reason}; scoring both again on a grid of {dx:.4} m cells"
                    ));
                    let other = inputs.object(ctx, &material, Resolution::Dx(dx))?;
                    let rigid_other = RigidVelocity {
                        centre: other.centre_of_mass().to_array(),
                        ..field
                    };
                    let residual = VelocityField {
                        field: f.0.field.clone(),
                        points: other.body.state.x.iter().map(|x| x.to_array()).collect(),
                    }
                    .residual()
                    .map_err(|e| {
                        fail(
                            p.epochs,
                            RolloutError::Loss {
                                frame: 0,
                                message: format!("velocity field on the second grid: {e}"),
                            },
                        )
                    })?;
                    let v_rigid = rigid_other.field(&other);
                    let v_field: Vec<DVec3> = v_rigid
                        .iter()
                        .zip(&residual)
                        .map(|(v, r)| *v + *r)
                        .collect();
                    let mut held_other = ViewsLoss::new(
                        &other,
                        fluid,
                        targets.iter().filter(|t| held.contains(&t.row.view)),
                        weights,
                        inputs.background,
                    );
                    let sim_other = Simulated {
                        object: &other,
                        ..sim
                    };
                    let lg2 = sim_other
                        .loss(&v_rigid, &mut held_other, None)
                        .map_err(|e| fail(p.epochs, e))?;
                    let lf2 = sim_other
                        .loss(&v_field, &mut held_other, None)
                        .map_err(|e| fail(p.epochs, e))?;
                    let (wins2, reason2) = decide_again(
                        (lg, lf),
                        (lg2, lf2),
                        p.auto.margin,
                        p.auto.regrid_keep,
                        "rigid motion",
                        "the field",
                    );
                    wins = wins2;
                    reason = format!("{reason}; on a grid of {dx:.4} m cells: {reason2}");
                    regrid = Some((dx, lg2, lf2));
                }
                ctx.progress.log(&format!("velocity auto: {reason}"));
                let selection = ModelSelection {
                    kept: if wins { "field" } else { "rigid" }.into(),
                    reason,
                    loss_global_held_out: Some(lg),
                    loss_field_held_out: Some(lf),
                    regrid_dx_m: regrid.map(|r| r.0),
                    loss_simple_regrid_held_out: regrid.map(|r| r.1),
                    loss_field_regrid_held_out: regrid.map(|r| r.2),
                    ..ModelSelection::simpler("rigid", held, fit_views, p.auto.margin, last)
                };
                (wins.then_some(f), Some(selection))
            }
        };
        let (model, v0, summary) = match &learned_field {
            None => (base_model, field.field(&object), None),
            Some((vf, v0)) => {
                write_weights(&ctx.out_dir.join(WEIGHTS_FILE), vf).map_err(StageError::failed)?;
                let speeds: Vec<f64> = v0
                    .iter()
                    .zip(field.field(&object))
                    .map(|(v, r)| (*v - r).length())
                    .collect();
                (
                    VelocityModel::Field,
                    v0.clone(),
                    Some(VelocityFieldSummary {
                        residual_speed_p05_p50_p95: percentiles(&speeds),
                        loss_rigid,
                        weights_table: WEIGHTS_FILE.into(),
                        weights: vf.field.param_count(),
                    }),
                )
            }
        };
        let loss_final = if learned_field.is_none() {
            loss_rigid
        } else {
            sim.loss(&v0, &mut loss, None)
                .map_err(|e| fail(p.epochs, e))?
        };
        let mass = &object.body.material.mass;
        let mean_v =
            v0.iter().zip(mass).map(|(v, m)| *v * *m).sum::<DVec3>() / mass.iter().sum::<f64>();
        let result = VelocityResult {
            model,
            linear_velocity: field.linear,
            angular_velocity: field.angular,
            centre_of_mass: centre,
            initial_velocity: mean_v.to_array(),
            start_velocity: [start[0], start[1], start[2]],
            start_angular_velocity: if dims == 6 {
                [start[3] / radius, start[4] / radius, start[5] / radius]
            } else {
                [0.0; 3]
            },
            init: p.init,
            converged: !cut_short,
            frames: p.frames,
            loss_start,
            loss_final,
            material,
            particles: object.particles(),
            gaussians: object.rendered(),
            floaters: object.floaters,
            field: summary,
            selection,
        };
        for (metric, value) in [
            ("loss_start", loss_start),
            ("loss_final", loss_final),
            ("work_particle_substeps", work.done() as f64),
        ] {
            ctx.metric(MetricRow::of_stage(metric, value));
        }
        let truth = crate::physics::fit::ground_truth(ctx.scene)
            .and_then(|gt| serde_json::from_value::<[f64; 3]>(gt["v0"].clone()).ok());
        let v = result.initial_velocity;
        ctx.progress.log(&format!(
            "learned initial velocity [{:.4}, {:.4}, {:.4}] m/s{} (started at [{:.4}, {:.4}, {:.4}]), angular [{:.3}, {:.3}, {:.3}] rad/s; loss {loss_start:.5} -> {loss_final:.5}",
            v[0],
            v[1],
            v[2],
            truth
                .map(|t| format!(" (ground truth [{}, {}, {}])", t[0], t[1], t[2]))
                .unwrap_or_default(),
            start[0],
            start[1],
            start[2],
            result.angular_velocity[0],
            result.angular_velocity[1],
            result.angular_velocity[2],
        ));
        crate::io::write_json(&ctx.out_dir.join("velocity.json"), &result)
            .map_err(StageError::failed)?;
        Ok(())
    }
}

/// Turns per frame interval (degrees) the spin probes try about each axis, both ways.
const PROBE_DEGREES: [f64; 4] = [5.0, 10.0, 20.0, 40.0];

/// Least relative fall of the loss for a spin probe to move the start: a ball without texture
/// looks the same whatever its spin, and a spin taken on a rounding difference would roll it
/// once it lands.
const PROBE_GAIN: f64 = 0.02;

/// Coordinate probes of the angular velocity: for x, y and z in turn, from the best point so
/// far, the spins that turn the body by [`PROBE_DEGREES`] per frame interval `frame_dt` (s)
/// either way are added to `x` (the rigid motion's optimiser coordinates: linear velocity,
/// then the angular one times `radius`), and the lowest `loss` is kept when it is at least
/// [`PROBE_GAIN`] below the best so far. Returns the best point and its loss (`x` and `from`
/// when nothing fits better).
fn probe_spins<E>(
    x: &[f64],
    from: f64,
    radius: f64,
    frame_dt: f64,
    mut loss: impl FnMut(&[f64]) -> Result<f64, E>,
) -> Result<(Vec<f64>, f64), E> {
    let (mut best, mut best_loss) = (x.to_vec(), from);
    for axis in 0..3 {
        let (base, base_loss) = (best.clone(), best_loss);
        for degrees in PROBE_DEGREES {
            for sign in [-1.0, 1.0] {
                let mut trial = base.clone();
                trial[3 + axis] += sign * degrees.to_radians() / frame_dt * radius;
                let l = loss(&trial)?;
                if l < best_loss && l < base_loss * (1.0 - PROBE_GAIN) {
                    (best, best_loss) = (trial, l);
                }
            }
        }
    }
    Ok((best, best_loss))
}

/// What every rollout of the stage holds fixed: the object, its guessed material, the frames
/// and how they are simulated.
#[derive(Clone, Copy)]
struct Simulated<'a> {
    object: &'a Object,
    material: &'a MaterialValues,
    last: u16,
    precision: pipe_mpm::Precision,
    interrupt: &'a std::sync::atomic::AtomicBool,
    /// Counts the simulation work (`budget`).
    work: &'a Work,
}

impl<'a> Simulated<'a> {
    /// The rollout of frames `1..=last` from initial velocities `v0` (m/s).
    fn rollout<'b>(&self, v0: &'b [DVec3]) -> Rollout<'b>
    where
        'a: 'b,
    {
        Rollout {
            object: self.object,
            material: self.material,
            v0,
            frames: self.last,
            precision: self.precision,
            interrupt: Some(self.interrupt),
            moduli: None,
            free: None,
            work: Some(self.work),
        }
    }

    /// The loss of initial velocities `v0`; with `up_to`, the rollout may stop once its loss
    /// exceeds it, returning a partial loss above it ([`Wants::LossUpTo`]).
    fn loss(
        &self,
        v0: &[DVec3],
        loss: &mut ViewsLoss<'_>,
        up_to: Option<f64>,
    ) -> Result<f64, RolloutError> {
        self.rollout(v0)
            .run(loss, up_to.map_or(Wants::Loss, Wants::LossUpTo))
            .map(|o| o.loss())
    }
}

/// What the velocity field's fit holds fixed.
struct Frozen<'a> {
    sim: Simulated<'a>,
    /// The rigid motion of every particle (m/s).
    base: Vec<DVec3>,
}

/// The residual field from zero (the rigid motion `fixed.base`): Adam's direction on the
/// gradient through every frame, its length searched on the loss ([`StepSearch`]).
fn fit_velocity_field(
    settings: &VelocityFieldSettings,
    stage_epochs: u32,
    budget: Option<f64>,
    ctx: &mut StageContext<'_>,
    fixed: &Frozen<'_>,
    loss: &mut ViewsLoss<'_>,
) -> Result<(VelocityField, Vec<DVec3>), StageError> {
    let training = |epoch: u32, message: String| {
        StageError::failed(FitError::Training {
            epoch,
            message: format!("velocity field: {message}"),
        })
    };
    let points: Vec<[f64; 3]> = fixed
        .sim
        .object
        .body
        .state
        .x
        .iter()
        .map(|x| x.to_array())
        .collect();
    let mut vf = VelocityField::zero(settings, points).map_err(|e| {
        StageError::failed(FitError::Invalid(format!("stages.{}.field: {e}", ctx.name)))
    })?;
    let epochs = settings.epochs.unwrap_or(stage_epochs);
    let schedule = LrSchedule::exponential(settings.lr, settings.lr_final, epochs.max(2));
    let mut adam = FieldAdam::new(&vf.field, schedule, schedule, FieldAdamConfig::default())
        .map_err(|e| {
            StageError::failed(FitError::Invalid(format!("stages.{}.field: {e}", ctx.name)))
        })?;
    let v0_of = |vf: &VelocityField| -> Option<Vec<DVec3>> {
        let r = vf.residual().ok()?;
        Some(fixed.base.iter().zip(r).map(|(b, r)| *b + r).collect())
    };
    let mut search = StepSearch::default();
    let mut v0 = fixed.base.clone();
    ctx.progress.log(&format!(
        "velocity field: {}² planes × {} channels, MLP {}×{}, {} weights, {epochs} epochs from the rigid motion",
        settings.resolution,
        settings.channels,
        settings.layers,
        settings.hidden,
        vf.field.param_count()
    ));
    ctx.progress.start("field epoch", u64::from(epochs));
    let mut losses = Vec::new();
    for epoch in 0..epochs {
        ctx.check_interrupted()?;
        if let Some(note) = fixed.sim.work.spent(budget) {
            ctx.progress.log(&format!(
                "velocity: {note}: the field stops after {epoch} epoch(s)"
            ));
            break;
        }
        let out = fixed
            .sim
            .rollout(&v0)
            .run(loss, Wants::Velocity)
            .map_err(|e| match e {
                RolloutError::Interrupted => StageError::Interrupted,
                e => training(epoch, e.to_string()),
            })?;
        let g = out.v0.as_ref().expect("a velocity rollout gives ∂L/∂v0");
        let mut grad = vf.backward(g).map_err(|e| training(epoch, e.to_string()))?;
        vf.field
            .tv_backward(&mut grad)
            .map_err(|e| training(epoch, e.to_string()))?;
        let before = vf.field.to_flat();
        adam.step(&mut vf.field, &grad)
            .map_err(|e| training(epoch, e.to_string()))?;
        let stepped = vf.field.to_flat();
        // A trial above the loss so far is rejected whatever it is (`StepSearch::run`).
        let loss0 = out.loss();
        let found = search.run(loss0, |t| {
            vf.field
                .set_flat(&lerp(&before, &stepped, t))
                .map_err(|e| training(epoch, e.to_string()))?;
            let Some(trial) = v0_of(&vf) else {
                return Ok(None);
            };
            match fixed.sim.loss(&trial, loss, Some(loss0)) {
                Ok(l) => Ok(Some(l)),
                Err(RolloutError::Interrupted) => Err(StageError::Interrupted),
                Err(_) => Ok(None),
            }
        })?;
        let t = found.map_or(0.0, |(t, _)| t);
        vf.field
            .set_flat(&lerp(&before, &stepped, t))
            .map_err(|e| training(epoch, e.to_string()))?;
        v0 = v0_of(&vf).ok_or_else(|| training(epoch, "non-finite residual".into()))?;
        let speeds: Vec<f64> = v0
            .iter()
            .zip(&fixed.base)
            .map(|(v, b)| (*v - *b).length())
            .collect();
        let [_, s50, s95] = percentiles(&speeds);
        let mut metric = |name: &str, value: f64| {
            ctx.metric(MetricRow {
                epoch: Some(epoch),
                view: None,
                frame: None,
                metric: name.into(),
                value,
            })
        };
        metric("field_loss", out.loss());
        metric("field_residual_speed_p50", s50);
        metric("field_residual_speed_p95", s95);
        metric("field_step_scale", search.scale);
        if let Some((_, l)) = found {
            metric("field_loss_after_step", l);
        }
        ctx.progress.message(&format!(
            "loss {:.5}  residual speed p50/p95 {s50:.4}/{s95:.4} m/s",
            out.loss()
        ));
        ctx.progress.inc(1);
        losses.push(found.map_or(out.loss(), |(_, l)| l));
        if stalled(&losses) {
            ctx.progress.log(&crate::physics::step_search::stall_note(
                "velocity field",
                epoch + 1,
                epochs,
            ));
            break;
        }
    }
    Ok((vf, v0))
}

/// `guess:` values are finite, in their parameter's range.
pub(crate) fn check_guess(guess: &BTreeMap<Param, f64>) -> Result<(), ParamError> {
    for (p, v) in guess {
        // A plasticine viscosity of 0 is the family's default (no viscosity).
        if !(p.encodable(*v) || (*p == Param::Viscosity && *v == 0.0)) {
            return Err(ParamError {
                path: format!("guess.{}", p.name()),
                message: format!(
                    "{} = {v} is outside its range ({})",
                    p.name(),
                    match p {
                        Param::Nu => "0 < nu < 0.49",
                        Param::FrictionAngle => "0 < friction_angle < 80 degrees",
                        _ => "finite and > 0",
                    }
                ),
            });
        }
    }
    Ok(())
}

/// `guess:` names only parameters of the scene's family.
pub(crate) fn check_family_guess(
    material: &MaterialValues,
    guess: &BTreeMap<Param, f64>,
    stage: &str,
) -> Result<(), StageError> {
    for p in guess.keys() {
        if material.get(*p).is_none() {
            return Err(StageError::failed(FitError::Invalid(format!(
                "stages.{stage}.guess.{}: the scene's family `{}` has no such parameter (it has {})",
                p.name(),
                crate::simulate::spec::family_name(material.family),
                Param::of_family(material.family)
                    .iter()
                    .map(|p| p.name())
                    .collect::<Vec<_>>()
                    .join(", ")
            ))));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A loss flat far from its minimum (a texture's loss is: a turn past its stripes matches
    /// no better than none) at the spin (0, 8, 2) rad/s: from rest the gradient is nil, the
    /// probes land in the basin (y first, then z), and a loss with its minimum at rest keeps
    /// the start.
    #[test]
    fn spin_probes_find_a_turn_the_gradient_cannot_see() {
        let (radius, dt) = (0.15, 1.0 / 24.0);
        let target = DVec3::new(0.0, 8.0, 2.0);
        let loss = |target: DVec3| {
            move |x: &[f64]| -> Result<f64, ()> {
                let w = DVec3::new(x[3], x[4], x[5]) / radius;
                Ok(1.0 - (-(w - target).length_squared() / 9.0).exp())
            }
        };
        let start = [0.3, 0.0, 0.3, 0.0, 0.0, 0.0];
        let from = loss(target)(&start).unwrap();
        assert!(from > 0.999);
        let (x, best) = probe_spins(&start, from, radius, dt, loss(target)).unwrap();
        let w = DVec3::new(x[3], x[4], x[5]) / radius;
        assert!((w - target).length() < 0.5, "{w}");
        assert!(best < 0.05 && best.is_finite(), "{best}");
        assert_eq!(&x[..3], &start[..3]);
        let (x, best) = probe_spins(&start, 0.0, radius, dt, loss(DVec3::ZERO)).unwrap();
        assert_eq!((x.as_slice(), best), (&start[..], 0.0));
        // A spin that fits better by a rounding difference (a ball without texture) is not
        // taken.
        let flat = |x: &[f64]| -> Result<f64, ()> { Ok(0.5 - 1e-9 * x[4].abs()) };
        let (x, best) = probe_spins(&start, 0.5, radius, dt, flat).unwrap();
        assert_eq!((x.as_slice(), best), (&start[..], 0.5));
    }
}
