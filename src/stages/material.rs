//! Stage `material`: the object's material from every frame (paper §3.2), by gradient descent
//! through the renderer and the MPM simulation, with the canonical Gaussians and the initial
//! velocity (`velocity`) held.
//!
//! Only the parameters of the scene's declared family are learned (`learn:` narrows or widens
//! the set among them), each in the optimiser's coordinates of [`crate::physics::params`] (log10
//! of moduli, stresses and viscosities; ν and the friction angle through bounded maps). The
//! global model (`model: global`) is one value per parameter; `model: field` then refines it
//! into a per-particle E (and optionally ν) field ([`crate::stages::material_field`]);
//! `model: auto` (the default) keeps the field only when it wins on held-out views
//! ([`crate::stages::material_select`]). Each epoch simulates the sequence from frame 0; with `truncate: frame` (the
//! default, as the seed method) every frame's gradient stops at the previous frame's state and
//! Adam steps after every frame (online truncated back-propagation through time); with
//! `truncate: none` the gradient runs through the whole rollout and Adam steps once an epoch.
//!
//! Writes `material.json`, `scene.sim.yaml` (a simulation file `pipe simulate` takes as it is),
//! `particles.arrow` (frame 0: position, mass, volume, E, ν, v0 per particle) and
//! `metrics.arrow` (the loss and every learned value per epoch); checkpoints every epoch.

use std::collections::BTreeMap;

use glam::DVec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::physics::adam::{Adam, AdamConfig, decayed};
use crate::physics::descent::{Iteration, LineSearch, Probe, probe};
use crate::physics::fit::{FitError, Inputs, PrecisionParam};
use crate::physics::material_field::{FieldSettings, colour_of, percentiles, write_weights};
use crate::physics::object::{Resolution, sim_yaml};
use crate::physics::params::{MaterialValues, Param};
use crate::physics::profile::{ParamProfile, ViewLosses};
use crate::physics::rollout::{
    FrameGradient, NextMaterial, Rollout, RolloutError, Truncate, Wants, Work, is_fluid,
};
use crate::physics::views::{LossWeights, ViewsLoss};
use crate::pipeline::spec::{Preset, SceneSpec};
use crate::pipeline::stage::{MetricRow, ParamError, StageContext, StageError, TypedStage};
use crate::stages::material_select::{
    AutoSettings, Candidate, ModelSelection, PartsScore, choose, field_wins,
    median_replaces_global, split_views,
};
use crate::stages::velocity::{VelocityResult, check_family_guess, check_guess};

/// How the material varies over the object.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MaterialModel {
    /// The global model, then a field from it kept only when it lowers the loss on training
    /// views it was not fitted on by more than `auto.margin`
    /// ([`crate::stages::material_select`]); `material.json`'s `model` is the one kept.
    #[default]
    Auto,
    /// One value per parameter: a homogeneous object needs no more.
    Global,
    /// The global fit first, then per-particle E and ν from a triplane + MLP field over the
    /// rest positions, started at the global values (seed paper §3.2, eq. 8; the `field:`
    /// block); the family's other parameters stay global.
    Field,
}

/// How the parameters are stepped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// Quasi-Newton (BFGS) descent with a backtracking line search on the loss over every frame
    /// ([`crate::physics::descent`]): each epoch one gradient and the forward rollouts of its
    /// trials; stops early once no step above `lr_final` lowers the loss.
    #[default]
    LineSearch,
    /// Adam with an exponentially decaying step: after every frame with `truncate: frame`
    /// (online, as the seed method), once an epoch with `truncate: none`.
    Adam,
}

/// Parameters of `material`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MaterialParams {
    /// How the material varies over the object.
    #[serde(default)]
    pub model: MaterialModel,
    /// The parameters learned, among the family's (default: the family's usual set: E and ν
    /// of a solid, also the yield stress of plasticine, ... the viscosity μ and bulk modulus κ
    /// of a Newtonian fluid, the friction angle of sand).
    #[serde(default)]
    pub learn: Option<Vec<Param>>,
    /// The start of each parameter of the family (SI units, degrees; default the family's
    /// guess: E = 1e5 Pa, ν = 0.3, ...); parameters not learned keep it.
    #[serde(default)]
    pub guess: BTreeMap<Param, f64>,
    /// Gradient evaluations (each a rollout over the frames and its adjoint).
    #[serde(default = "epochs")]
    pub epochs: u32,
    /// How the parameters are stepped.
    #[serde(default)]
    pub optimizer: Optimizer,
    /// The first step in the optimiser's coordinates (0.5 = ×3.2 on a modulus): the line
    /// search's first trial (it grows to 1 and shrinks as the loss asks), Adam's rate at the
    /// start (decaying to `lr_final`).
    #[serde(default = "lr")]
    pub lr: f64,
    /// The line search's smallest step (convergence), Adam's rate at the end.
    #[serde(default = "lr_final")]
    pub lr_final: f64,
    /// Compass probes (decades) where the line search finds no lower loss: each learned
    /// modulus, yield stress and viscosity moved alone by this many decades down (and up when
    /// down does not lower the loss), then by half as many, and the descent goes on from the
    /// lowest probe that lowers the loss (0: stop there). A
    /// plasticine whose E is far above its yield stress moves as a rigid–plastic body: the
    /// loss no longer depends on E, and a gradient cannot leave that plateau.
    #[serde(default = "probe_decades")]
    pub probe: f64,
    /// How far back a frame's loss is differentiated.
    #[serde(default)]
    pub truncate: Truncate,
    /// Last frame fitted (default: every frame).
    #[serde(default)]
    pub frames: Option<u16>,
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
    /// The stage's simulation work budget, in billions of particle-substeps
    /// ([`crate::physics::rollout::Work`]: each substep simulated counts the particles once,
    /// each substep reversed once more): no epoch, of the global fit or of the field, starts
    /// past it, and the stage keeps what it has learned and says so. It bounds the stage's
    /// time on any scene (the particles follow the object's size, the substeps the material's
    /// stiffness) and reads no clock, so a run stops at the same epoch on every machine.
    /// Unset: no limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget: Option<f64>,
    /// Start the rollouts where the body's free flight ends (the learned rigid motion in closed
    /// form before it: [`crate::physics::free_flight::FreeFrames`]); `false` simulates every
    /// frame from frame 0.
    #[serde(default = "closed_form")]
    pub closed_form: bool,
    /// Precision of the simulation and its adjoint.
    #[serde(default)]
    pub precision: PrecisionParam,
    /// Weight of L1 in `λ·L1 + (1 − λ)·D-SSIM`.
    #[serde(default = "lambda")]
    pub lambda: f64,
    /// Weight of the silhouette term `mean|α − mask|`.
    #[serde(default = "alpha_weight")]
    pub alpha_weight: f64,
    /// Gradients longer than this (optimiser coordinates) are scaled down to it.
    #[serde(default = "grad_clip")]
    pub grad_clip: f64,
    /// The field of `model: field` and `model: auto` (ignored by `model: global`).
    #[serde(default)]
    pub field: FieldSettings,
    /// How `model: auto` decides.
    #[serde(default)]
    pub auto: AutoSettings,
    /// How closely the frames pin each learned parameter, measured after the fit
    /// ([`crate::physics::profile`]: each parameter moved alone by growing steps, scored on
    /// the training views; `material.json` `profile`).
    #[serde(default)]
    pub profile: crate::physics::profile::ProfileParams,
}

fn epochs() -> u32 {
    10
}
fn lr() -> f64 {
    0.5
}
fn lr_final() -> f64 {
    0.005
}
fn cells() -> f64 {
    24.0
}
fn closed_form() -> bool {
    true
}
fn probe_decades() -> f64 {
    1.0
}
/// A probe is taken when it lowers the loss by more than this fraction (the stall rule's).
const PROBE_GAIN: f64 = 1e-3;
fn lambda() -> f64 {
    crate::scene::targets::DEFAULT_LAMBDA
}
fn alpha_weight() -> f64 {
    0.1
}
fn grad_clip() -> f64 {
    1.0
}

/// What an interrupted run resumes from.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Checkpoint {
    /// Epochs done.
    epoch: u32,
    /// The learned parameters, in the optimiser's coordinates (order of `learned`).
    u: Vec<f64>,
    adam: Adam,
    search: LineSearch,
    /// The line search has converged.
    converged: bool,
    /// Particle-substeps simulated so far (`budget`).
    #[serde(default)]
    work: u64,
}

/// `material.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaterialResult {
    /// The family.
    pub family: String,
    /// The model of the result: `global` or `field` (`model: auto` says which it kept).
    pub model: MaterialModel,
    /// Young's modulus E (Pa), Poisson's ratio ν, yield stress (Pa), viscosity (Pa s: the
    /// plastic flow's η, or a fluid's μ), bulk modulus κ (Pa), friction angle (degrees);
    /// `null` where the family has none.
    pub youngs_modulus: Option<f64>,
    pub poisson_ratio: Option<f64>,
    pub yield_stress: Option<f64>,
    pub viscosity: Option<f64>,
    pub bulk_modulus: Option<f64>,
    pub friction_angle_deg: Option<f64>,
    /// The parameters learned (the others stayed at their guess).
    pub learned: Vec<Param>,
    /// Where they started.
    pub guess: BTreeMap<Param, f64>,
    /// The initial velocity (m/s) from `velocity`: the mean, and the rigid motion.
    pub initial_velocity: [f64; 3],
    pub angular_velocity: [f64; 3],
    /// Density (kg/m³).
    pub density: f64,
    /// Loss over the frames (sum of the frames' mean view losses) at the guess and at the
    /// result, from a rollout at each.
    pub loss_guess: f64,
    pub loss_final: f64,
    /// Mean PSNR (dB) of the training views over the frames at the result.
    pub train_psnr_final: f64,
    /// Frames fitted (`1..=frames`), epochs, simulated particles (Gaussians and fillers),
    /// Gaussians among them, floaters dropped, grid cell (m), substeps of each frame at the
    /// result.
    pub frames: u16,
    pub epochs: u32,
    pub particles: usize,
    pub gaussians: usize,
    pub floaters: usize,
    pub grid_dx: f64,
    pub substeps: Vec<usize>,
    /// `model: field`: how E and ν vary over the particles (the values above are then the
    /// medians), the colour map of `field_E.ply`, the weights' table.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldSummary>,
    /// `model: auto`: the two models' held-out losses and which was kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection: Option<ModelSelection>,
    /// How closely the frames pin each learned parameter of the global fit (before a field):
    /// the moves tried on each side of it, their loss rise and the training cameras'
    /// agreement, and the values that bound it ([`crate::physics::profile`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub profile: Vec<ParamProfile>,
}

/// The learned field in `material.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldSummary {
    /// 5th, 50th and 95th percentiles of the particles' log10 E (E in Pa) and ν.
    pub log10_youngs_modulus_p05_p50_p95: [f64; 3],
    pub poisson_ratio_p05_p50_p95: [f64; 3],
    /// `field_E.ply`: each Gaussian coloured by its log10 E, blue at `colour_map_log10_e[0]`,
    /// green midway, red at `colour_map_log10_e[1]` (the 5th to 95th percentile, at least a
    /// decade about the median).
    pub colour_map_log10_e: [f64; 2],
    /// Loss over the frames at the global fit the field started from.
    pub loss_global: f64,
    /// Weights of the triplane and the MLP (`field.material.arrow`), and their count.
    pub weights_table: String,
    pub weights: usize,
    /// The field's values grouped into parts (`profile.field_parts`), each with the profile
    /// of its E moved alone: how closely the frames hold each part.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parts: Option<FieldParts>,
}

/// A kept field's parts (natural breaks of its `log10 E`, [`crate::physics::field_parts`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldParts {
    /// The field's `log10 E` (E in Pa) between consecutive parts, ascending.
    pub thresholds: Vec<f64>,
    /// The parts, softest first.
    pub parts: Vec<FieldPart>,
}

/// One part of a kept field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldPart {
    /// Its share of the body's volume, and its particles.
    pub volume_share: f64,
    pub particles: usize,
    /// The volume-weighted median of its particles' E (Pa).
    pub youngs_modulus_median: f64,
    /// Every particle of the part has its E scaled alone by the profile's steps (decades);
    /// `value` and the bounds are the part's median E so moved.
    pub profile: ParamProfile,
}

/// The `material` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct MaterialStage;

impl TypedStage for MaterialStage {
    type Params = MaterialParams;
    const KIND: &'static str = "material";
    const VERSION: u32 = 20;
    const DESCRIPTION: &'static str = "Learn the material's parameters from every frame (gradient descent through the renderer and the MPM simulation)";
    const UPSTREAM: &'static [&'static str] = &["ingest", "warmup", "velocity"];

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![("particles_material", 1)]
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            // A field's fit starts on a plateau (the global fit) and may take twice as many
            // epochs to leave it: on the generated two-material bar, 20 epochs found the split
            // for two of four warm-up seeds (held out −20 % and −50 % for the others), 40 for
            // all four (−82 % to −86 %). A fit that stops improving stops early.
            Preset::Draft => {
                json!({"model": "global", "epochs": 5, "cells": 16, "field": {"epochs": 40}})
            }
            // The budget: ~35 min of the costliest particle-substeps measured (plasticine,
            // 3.5e6 a second on 2 cores with its renders; a Newtonian fluid's are 3.4× cheaper).
            Preset::Standard => json!({
                "epochs": 10, "cells": 24, "budget": 7.0, "field": {"epochs": 40}
            }),
            Preset::Paper => json!({
                "epochs": 200, "cells": 48, "precision": "f64", "field": {"epochs": 200}
            }),
        }
    }

    fn scene_key(&self, scene: &SceneSpec) -> Value {
        scene.physics_key()
    }

    fn validate(&self, p: &MaterialParams) -> Result<(), ParamError> {
        let bad = |path: &str, message: String| {
            Err(ParamError {
                path: path.into(),
                message,
            })
        };
        if p.epochs == 0 {
            return bad("epochs", "must be at least 1".into());
        }
        for (name, v) in [("lr", p.lr), ("lr_final", p.lr_final), ("probe", p.probe)] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, format!("must be finite and >= 0, found {v}"));
            }
        }
        if let Some((field, message)) = p.profile.invalid() {
            return bad(&format!("profile.{field}"), message);
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
        if p.grad_clip.is_nan() || p.grad_clip <= 0.0 {
            return bad("grad_clip", format!("must be > 0, found {}", p.grad_clip));
        }
        if p.frames == Some(0) {
            return bad("frames", "must be at least 1".into());
        }
        if let Err((name, why)) = p.auto.check() {
            return bad(name, why);
        }
        if let Err(why) = Work::check_budget(p.budget) {
            return bad("budget", why);
        }
        if p.model != MaterialModel::Global {
            if let Err(e) = p.field.config(2).validate() {
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
            if p.field.parts > crate::physics::material_field::MAX_PARTS {
                return bad(
                    "field.parts",
                    format!(
                        "must be at most {} (0 or 1: no parts), found {}",
                        crate::physics::material_field::MAX_PARTS,
                        p.field.parts
                    ),
                );
            }
            if p.field.parts_epochs == Some(0) {
                return bad("field.parts_epochs", "must be at least 1".into());
            }
        }
        if let Some(l) = &p.learn
            && l.is_empty()
        {
            return bad(
                "learn",
                "names no parameter; leave it out for the family's set".into(),
            );
        }
        check_guess(&p.guess)
    }

    fn run(&self, p: &MaterialParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let inputs = Inputs::load(ctx)?;
        let velocity: VelocityResult = {
            let path = ctx.upstream("velocity")?.dir.join("velocity.json");
            crate::io::read_json(&path).map_err(StageError::failed)?
        };
        let family = inputs.family;
        let last = p.frames.unwrap_or(u16::MAX).min(inputs.last_frame());
        if last == 0 {
            return Err(StageError::failed(FitError::Invalid(
                "the capture has no frame after frame 0".into(),
            )));
        }
        let guess = MaterialValues::guess(family, ctx.scene.density, &p.guess);
        check_family_guess(&guess, &p.guess, ctx.name)?;
        let learned: Vec<Param> = match &p.learn {
            None => Param::learned_by_default(family).to_vec(),
            Some(l) => {
                for q in l {
                    if guess.get(*q).is_none() {
                        return Err(StageError::failed(FitError::Invalid(format!(
                            "stages.{}.learn: the scene's family `{}` has no parameter `{}` (it has {})",
                            ctx.name,
                            crate::simulate::spec::family_name(family),
                            q.name(),
                            Param::of_family(family)
                                .iter()
                                .map(|p| p.name())
                                .collect::<Vec<_>>()
                                .join(", ")
                        ))));
                    }
                    if !q.encodable(guess.get(*q).unwrap_or(0.0)) {
                        return Err(StageError::failed(FitError::Invalid(format!(
                            "stages.{}.learn names `{}`, whose guess {} cannot be learned (set `guess.{}` > 0)",
                            ctx.name,
                            q.name(),
                            guess.get(*q).unwrap_or(0.0),
                            q.name()
                        ))));
                    }
                }
                let mut l = l.clone();
                l.sort();
                l.dedup();
                l
            }
        };
        if p.model == MaterialModel::Field {
            // Before any rollout: a field asked for that cannot apply is refused at once.
            crate::stages::material_field::outputs(family, &learned, &p.field.vary, ctx.name)?;
        }
        let object = inputs.object(ctx, &guess, Resolution::of(p.cells, p.dx))?;
        let v0 = velocity.velocities(&object, &ctx.upstream("velocity")?.dir)?;
        let targets = inputs.train_targets(last)?;
        let weights = LossWeights {
            lambda: p.lambda,
            alpha_weight: p.alpha_weight,
        };
        let mut loss = ViewsLoss::new(
            &object,
            is_fluid(family),
            &targets,
            weights,
            inputs.background,
        );
        ctx.progress.log(&format!(
            "material: {} ({} floaters dropped), {:.2} kg, dx {:.4} m, frames 1..={last}, {} views; learning {}",
            object.particle_summary(),
            object.floaters,
            object.mass(),
            object.body.setup.dx,
            targets.len(),
            learned.iter().map(|p| p.name()).collect::<Vec<_>>().join(", ")
        ));

        let values_of = |u: &[f64]| -> MaterialValues {
            let mut m = guess.clone();
            for (q, u) in learned.iter().zip(u) {
                m.values.insert(*q, q.decode(*u));
            }
            m
        };
        let mut u: Vec<f64> = learned
            .iter()
            .map(|q| q.encode(guess.get(*q).unwrap_or(1.0)))
            .collect();
        let mut adam = Adam::new(learned.len());
        let mut search = LineSearch::new(p.lr, p.lr_final, 1.0);
        let mut converged = false;
        let mut first_epoch = 0;
        let interrupt = ctx.interrupt_flag();
        let mut work_done = 0;
        if let Some(ck) = ctx.resume::<Checkpoint>()
            && ck.u.len() == learned.len()
        {
            (first_epoch, u, adam, search, converged, work_done) =
                (ck.epoch, ck.u, ck.adam, ck.search, ck.converged, ck.work);
        }
        let work = Work::starting_at(work_done);
        let cfg = AdamConfig {
            clip: p.grad_clip,
            ..Default::default()
        };
        let precision = p.precision.mpm();
        // While the body is in free flight its material plays no part: the rollouts start where
        // the flight ends (the learned rigid motion in closed form; not with a velocity field,
        // whose residual deforms the body).
        let free = free_frames(p, &velocity, &object, last, is_fluid(family));
        match &free {
            Some(f) if f.frames() >= last => ctx.progress.warn(&format!(
                "material: the body is in free flight over every frame fitted (1..={last}): they say nothing of its material, which stays at the guess; fit frames after it lands (`frames`), or set `closed_form: false` to fit what the simulation's numerics show of it"
            )),
            Some(f) => ctx.progress.log(&format!(
                "material: the body is in free flight until frame {}: the rollouts start there (frames 1..={} in closed form)",
                f.frames(),
                f.frames()
            )),
            None => {}
        }
        // Every rollout of the stage: the guess's, the others by `..base`.
        let base = Rollout {
            object: &object,
            material: &guess,
            v0: &v0,
            frames: last,
            precision,
            interrupt: Some(interrupt),
            moduli: None,
            free: free.as_ref(),
            work: Some(&work),
        };
        let fail = |epoch: u32, e: RolloutError| -> StageError {
            match e {
                RolloutError::Interrupted => StageError::Interrupted,
                e => StageError::failed(FitError::Training {
                    epoch,
                    message: format!(
                        "{e}; try a smaller `lr`, `precision: f64`, more `cells` or a guess closer to the material"
                    ),
                }),
            }
        };
        // Adam steps over the whole descent (per frame with truncate: frame).
        let steps_per_epoch = match p.truncate {
            Truncate::Frame => u32::from(last),
            Truncate::None => 1,
        };
        let total_steps = (p.epochs * steps_per_epoch).max(2);
        ctx.progress.start("epoch", u64::from(p.epochs));
        ctx.progress.inc(u64::from(first_epoch));
        let grad_u = |u: &[f64], grad: &BTreeMap<Param, f64>| -> Result<Vec<f64>, String> {
            let g: Vec<f64> = learned
                .iter()
                .zip(u)
                .map(|(q, u)| grad.get(q).copied().unwrap_or(0.0) * q.dvalue_du(*u))
                .collect();
            match learned.iter().zip(&g).find(|(_, v)| !v.is_finite()) {
                Some((q, v)) => Err(format!("non-finite gradient of `{}` ({v})", q.name())),
                None => Ok(g),
            }
        };
        let started = std::time::Instant::now();
        for epoch in first_epoch..p.epochs {
            ctx.check_interrupted()?;
            if converged {
                break;
            }
            if let Some(note) = budget_spent(p, &work, "the global fit", epoch) {
                ctx.progress.log(&note);
                break;
            }
            let values = values_of(&u);
            let rollout = Rollout {
                material: &values,
                ..base
            };
            let step = |u: &mut Vec<f64>,
                        adam: &mut Adam,
                        grad: &BTreeMap<Param, f64>|
             -> Result<(), String> {
                let g = grad_u(u, grad)?;
                let progress = f64::from(adam.t) / f64::from(total_steps - 1);
                let lr = decayed(p.lr, p.lr_final, progress);
                adam.step(&cfg, u, &g, &vec![lr; g.len()]);
                Ok(())
            };
            let mut taken = None;
            let mut full_gradient = false;
            let mut probes = 0;
            // The training PSNR at the epoch's start (the trials after it render other points).
            let mut start_psnr = None;
            let out = match (p.optimizer, p.truncate) {
                (Optimizer::LineSearch, truncate) => {
                    let gradient_of = |out: &crate::physics::rollout::Outcome| {
                        grad_u(&u, out.material.as_ref().expect("a gradient")).map_err(|message| {
                            fail(
                                epoch,
                                RolloutError::Loss {
                                    frame: last,
                                    message,
                                },
                            )
                        })
                    };
                    let out = rollout
                        .run(&mut loss, Wants::Material(truncate))
                        .map_err(|e| fail(epoch, e))?;
                    start_psnr = Some(loss.mean_psnr());
                    let g = gradient_of(&out)?;
                    // A trial above `up_to` is rejected whatever it is: its rollout stops there.
                    let trial_loss = |trial: &[f64], up_to: f64, loss: &mut ViewsLoss<'_>| {
                        let v = values_of(trial);
                        Rollout {
                            material: &v,
                            ..rollout
                        }
                        .run(loss, Wants::LossUpTo(up_to))
                        .map(|o| o.loss())
                    };
                    let before = search.clone();
                    let mut it = search
                        .iterate(&u, out.loss(), &g, |t, up_to| trial_loss(t, up_to, &mut loss))
                        .map_err(|e| fail(epoch, e))?;
                    if it.step == 0.0 && truncate == Truncate::Frame {
                        // The truncated gradient is not the loss's own: when no step along it
                        // lowers the loss, the whole rollout's gradient decides (one more
                        // rollout with its adjoint). On a generated two-material bar the
                        // truncated gradient at E = 1e5 Pa pointed stiffer while the loss fell
                        // softer, and the descent never left its guess.
                        let full = rollout
                            .run(&mut loss, Wants::Material(Truncate::None))
                            .map_err(|e| fail(epoch, e))?;
                        let g = gradient_of(&full)?;
                        search = before;
                        it = search
                            .iterate(&u, full.loss(), &g, |t, up_to| trial_loss(t, up_to, &mut loss))
                            .map_err(|e| fail(epoch, e))?;
                        full_gradient = true;
                    }
                    if it.step == 0.0 && p.probe > 0.0 {
                        let axes: Vec<usize> = learned
                            .iter()
                            .enumerate()
                            .filter(|(_, q)| q.log_scaled())
                            .map(|(k, _)| k)
                            .collect();
                        // Compass search: the probe's length, then half of it.
                        for size in [p.probe, 0.5 * p.probe] {
                            let Probe { best, evaluated } = probe(
                                &u,
                                it.loss,
                                &axes,
                                size,
                                PROBE_GAIN,
                                |t, up_to| trial_loss(t, up_to, &mut loss),
                            )
                            .map_err(|e| fail(epoch, e))?;
                            probes += evaluated;
                            let Some((at, l)) = best else { continue };
                            ctx.progress.log(&format!(
                                "    no step lowered the loss {:.5}; a probe {size} decade(s) away did: {:.5} at {}",
                                it.loss,
                                l,
                                learned
                                    .iter()
                                    .zip(&at)
                                    .map(|(q, u)| format!("{} {:.4e}", q.name(), q.decode(*u)))
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ));
                            it = Iteration {
                                u: at,
                                loss: l,
                                step: size,
                                trials: it.trials + probes,
                            };
                            // A new start: the curvature and step lengths learned on the
                            // plateau do not hold there.
                            search = LineSearch::new(p.lr, p.lr_final, 1.0);
                            break;
                        }
                    }
                    converged = search.converged();
                    u = it.u.clone();
                    taken = Some(it);
                    Ok(out)
                }
                (Optimizer::Adam, Truncate::Frame) => {
                    let mut on_frame = |frame: u16, grad: FrameGradient<'_>| {
                        step(&mut u, &mut adam, grad.values)
                            .map_err(|message| RolloutError::Loss { frame, message })?;
                        Ok(Some(NextMaterial {
                            values: values_of(&u),
                            moduli: None,
                        }))
                    };
                    rollout.run_online(&mut loss, &mut on_frame)
                }
                (Optimizer::Adam, Truncate::None) => rollout
                    .run(&mut loss, Wants::Material(Truncate::None))
                    .and_then(|o| {
                        let grad = o.material.clone().unwrap_or_default();
                        step(&mut u, &mut adam, &grad).map_err(|message| RolloutError::Loss {
                            frame: last,
                            message,
                        })?;
                        Ok(o)
                    }),
            }
            .map_err(|e| fail(epoch, e))?;
            let l = out.loss();
            let psnr = start_psnr.unwrap_or_else(|| loss.mean_psnr());
            // The values at the end of the epoch.
            let now = values_of(&u);
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
            metric("train_psnr", psnr);
            metric("substeps", out.substeps.iter().sum::<usize>() as f64);
            if let Some(it) = &taken {
                metric("full_gradient", f64::from(u8::from(full_gradient)));
                metric("probes", probes as f64);
                metric("step", it.step);
                metric("trials", it.trials as f64);
                metric("loss_after_step", it.loss);
            }
            for (q, v) in &now.values {
                metric(q.name(), *v);
            }
            ctx.progress.message(&format!(
                "loss {l:.5}  {}",
                learned
                    .iter()
                    .map(|q| format!("{} {:.4e}", q.name(), now.get(*q).unwrap_or(0.0)))
                    .collect::<Vec<_>>()
                    .join("  ")
            ));
            ctx.progress.inc(1);
            ctx.checkpoint(
                &format!("epoch {}", epoch + 1),
                &Checkpoint {
                    epoch: epoch + 1,
                    u: u.clone(),
                    adam: adam.clone(),
                    search: search.clone(),
                    converged,
                    work: work.done(),
                },
            )?;
        }

        let mut global = values_of(&u);
        let global_s = started.elapsed().as_secs_f64();
        // The losses of a material, from a clean rollout.
        let eval = |values: &MaterialValues,
                    moduli: Option<&crate::physics::rollout::Moduli>,
                    loss: &mut ViewsLoss<'_>| {
            Rollout {
                material: values,
                moduli,
                ..base
            }
            .run(loss, Wants::Loss)
            .map_err(|e| fail(p.epochs, e))
        };
        // A field starts where the descent ended: the profile's moves below improve the global
        // model a field must beat, not the field's start (on the generated two-material bar a
        // start moved a decade by them left the stiff half 0.47 decades off, against 0.2).
        let field_start = global.clone();
        // How closely the frames pin each parameter of the global fit; where a move of a
        // modulus, yield stress or viscosity lowers the loss with the cameras agreeing, the fit
        // goes on from there.
        let profile = if p.profile.enabled {
            profile_and_polish(p, ctx, &learned, &mut global, &work, |m| {
                eval(m, None, &mut loss)?;
                Ok(loss.view_loss.clone())
            })?
        } else {
            Vec::new()
        };
        // The profile's wall time (s), after the global phase's.
        let profile_s = started.elapsed().as_secs_f64() - global_s;
        let field_applies =
            crate::stages::material_field::outputs(family, &learned, &p.field.vary, ctx.name);
        let (fitted, selection) = match p.model {
            MaterialModel::Global => (None, None),
            MaterialModel::Field => (
                Some(crate::stages::material_field::fit(
                    p,
                    ctx,
                    Rollout {
                        material: &field_start,
                        ..base
                    },
                    &mut loss,
                    &learned,
                )?),
                None,
            ),
            MaterialModel::Auto => {
                let (held, fit_views) = split_views(&targets, &p.auto, ctx.name)?;
                // The field sees the fit views' frames 1..=fit_last; everything else decides.
                let held_frames = p.auto.held_out_frames(last);
                let fit_last = last.saturating_sub(held_frames);
                if fit_last == 0 {
                    return Err(StageError::failed(FitError::Invalid(format!(
                        "stages.{}.auto.held_out_frames = {held_frames} leaves no frame of 1..={last} to fit the field on",
                        ctx.name
                    ))));
                }
                let fitted_on = |t: &&crate::scene::targets::Target| {
                    !held.contains(&t.row.view) && t.row.frame <= fit_last
                };
                let mut selection = ModelSelection::simpler(
                    "global",
                    held.clone(),
                    fit_views.clone(),
                    p.auto.margin,
                    fit_last,
                );
                match field_applies {
                    Err(e) => {
                        selection.reason = format!("no field applies: {e}");
                        (None, Some(selection))
                    }
                    Ok(_) if work.spent(p.budget).is_some() => {
                        selection.reason =
                            "the global fit spent the work budget (`budget`): no field was fitted"
                                .into();
                        ctx.progress
                            .log(&format!("material auto: {}", selection.reason));
                        (None, Some(selection))
                    }
                    Ok(_) => {
                        let mut held_loss = ViewsLoss::new(
                            &object,
                            is_fluid(family),
                            targets.iter().filter(|t| !fitted_on(t)),
                            weights,
                            inputs.background,
                        );
                        let mut fit_loss = ViewsLoss::new(
                            &object,
                            is_fluid(family),
                            targets.iter().filter(fitted_on),
                            weights,
                            inputs.background,
                        );
                        ctx.progress.log(&format!(
                            "material auto: the field is fitted on views {fit_views:?} of frames 1..={fit_last} and compared with the global fit on the rest (views {held:?}, and frames after {fit_last})"
                        ));
                        let f = crate::stages::material_field::fit(
                            p,
                            ctx,
                            Rollout {
                                material: &field_start,
                                frames: fit_last,
                                ..base
                            },
                            &mut fit_loss,
                            &learned,
                        )?;
                        let lg = eval(&global, None, &mut held_loss)?.loss();
                        let lf = eval(&f.values, Some(&f.moduli), &mut held_loss)?.loss();
                        // One material at the field's median: the field phase also goes on
                        // descending, so a global fit its epochs left short makes any field
                        // look better; a single E where the field ended may do as well.
                        let at_median = at_field_median(&f);
                        let lm = eval(&at_median, None, &mut held_loss)?.loss();
                        selection.loss_global_held_out = Some(lg);
                        selection.loss_field_held_out = Some(lf);
                        selection.loss_global_at_field_median_held_out = Some(lm);
                        // The simpler model the field must beat: the lower of the two.
                        let (simple, simpler, simple_values) = if lm < lg {
                            (lm, "global model at the field's median", &at_median)
                        } else {
                            (lg, "global model", &global)
                        };
                        // A field that wins is grouped into parts, each one material
                        // (`field.parts`): the simplest non-uniform models, tried first.
                        let mut fits = Vec::new();
                        if p.field.parts >= 2 && field_wins(simple, lf, p.auto.margin) {
                            let epochs = p.field.parts_epochs.unwrap_or(p.epochs);
                            for k in 2..=p.field.parts {
                                let Some(pf) = crate::stages::material_parts::fit(
                                    p,
                                    ctx,
                                    Rollout {
                                        frames: fit_last,
                                        ..base
                                    },
                                    &mut fit_loss,
                                    &learned,
                                    &f,
                                    k,
                                    epochs,
                                )?
                                else {
                                    continue;
                                };
                                let l = eval(&pf.values, Some(&pf.moduli), &mut held_loss)?.loss();
                                fits.push((format!("the {k}-part model"), pf, l));
                            }
                        }
                        fits.push(("the field".to_string(), f, lf));
                        // Those that win are scored again on the object rebuilt on another
                        // grid (`auto.regrid`): a gain that mostly vanishes with a new
                        // discretisation is not the object's.
                        let winning: Vec<usize> = (0..fits.len())
                            .filter(|&i| field_wins(simple, fits[i].2, p.auto.margin))
                            .collect();
                        let mut regrid: Vec<Option<f64>> = vec![None; fits.len()];
                        let mut simple2 = None;
                        if !winning.is_empty() && p.auto.regrid != 1.0 {
                            let dx = p.auto.regrid * object.body.setup.dx;
                            ctx.progress.log(&format!(
                                "material auto: held out, the {simpler} {simple:.5}, {}; scoring {} again on a grid of {dx:.4} m cells",
                                fits.iter()
                                    .map(|(n, _, l)| format!("{n} {l:.5}"))
                                    .collect::<Vec<_>>()
                                    .join(", "),
                                winning
                                    .iter()
                                    .map(|&i| fits[i].0.as_str())
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ));
                            let scored: Vec<&crate::stages::material_field::FieldFit> =
                                winning.iter().map(|&i| &fits[i].1).collect();
                            let (ls2, l2) = OtherGrid {
                                inputs: &inputs,
                                velocity: &velocity,
                                guess: &guess,
                                template: base,
                            }
                            .held_out_losses(
                                p,
                                ctx,
                                dx,
                                targets.iter().filter(|t| !fitted_on(t)),
                                simple_values,
                                &scored,
                            )?;
                            for (&i, l) in winning.iter().zip(l2) {
                                regrid[i] = Some(l);
                            }
                            simple2 = Some(ls2);
                            selection.regrid_dx_m = Some(dx);
                            selection.loss_simple_regrid_held_out = Some(ls2);
                            selection.loss_field_regrid_held_out = regrid[fits.len() - 1];
                        }
                        selection.parts = fits[..fits.len() - 1]
                            .iter()
                            .zip(&regrid)
                            .map(|((_, pf, l), l2)| {
                                let parts = pf.field.parts.clone().unwrap_or_default();
                                PartsScore {
                                    parts: parts.len(),
                                    thresholds: parts.thresholds,
                                    log10_e: parts.log10_e,
                                    loss_held_out: *l,
                                    loss_regrid_held_out: *l2,
                                }
                            })
                            .collect();
                        let candidates: Vec<Candidate> = fits
                            .iter()
                            .zip(&regrid)
                            .map(|((name, _, l), l2)| Candidate {
                                name: name.clone(),
                                held_out: *l,
                                regrid: *l2,
                            })
                            .collect();
                        let (chosen, reason) = choose(
                            simple,
                            simple2,
                            &candidates,
                            p.auto.margin,
                            p.auto.regrid_keep,
                            simpler,
                        );
                        selection.reason = reason;
                        let wins = chosen.is_some();
                        let kept = chosen.map(|i| fits.swap_remove(i));
                        if !wins && median_replaces_global(lg, lm, p.auto.margin) {
                            global = at_median;
                            selection.reason = format!(
                                "{}; one material at the field's median kept: its held-out loss {lm:.5} is more than {:.1} % below the global fit's {lg:.5}",
                                selection.reason,
                                100.0 * p.auto.margin
                            );
                        }
                        ctx.progress
                            .log(&format!("material auto: {}", selection.reason));
                        match kept {
                            Some((_, f, _)) => {
                                selection.kept = if f.field.parts.is_some() {
                                    "parts"
                                } else {
                                    "field"
                                }
                                .into();
                                (Some(f), Some(selection))
                            }
                            None => (None, Some(selection)),
                        }
                    }
                }
            }
        };
        // How closely the frames hold each part of a kept field.
        let field_parts = match &fitted {
            Some(f) if p.profile.enabled && p.profile.field_parts >= 2 => {
                profile_field_parts(p, ctx, f, &object.body.material.volume, |m, moduli| {
                    eval(m, Some(moduli), &mut loss)?;
                    Ok(loss.view_loss.clone())
                })?
            }
            _ => None,
        };
        // Wall time of each phase (s; the global one from this run's first epoch on).
        for (metric, value) in [
            ("wall_s_global", global_s),
            ("wall_s_profile", profile_s),
            (
                "wall_s_field",
                started.elapsed().as_secs_f64() - global_s - profile_s,
            ),
            ("work_particle_substeps", work.done() as f64),
        ] {
            ctx.metric(MetricRow::of_stage(metric, value));
        }
        let result = fitted
            .as_ref()
            .map_or_else(|| global.clone(), |f| f.values.clone());
        let moduli = fitted.as_ref().map(|f| &f.moduli);
        let loss_guess = eval(&guess, None, &mut loss)?.loss();
        let loss_global = match &fitted {
            Some(_) => Some(eval(&global, None, &mut loss)?.loss()),
            None => None,
        };
        let final_out = eval(&result, moduli, &mut loss)?;
        let psnr = loss.mean_psnr();
        for (metric, value) in [
            ("loss_guess", loss_guess),
            ("loss_final", final_out.loss()),
            ("train_psnr_final", psnr),
        ] {
            ctx.metric(MetricRow::of_stage(metric, value));
        }
        let spec = result.spec();
        let field = match (&fitted, loss_global) {
            (Some(f), Some(loss_global)) => {
                let log_e: Vec<f64> = f.moduli.e.iter().map(|e| e.log10()).collect();
                let pe = percentiles(&log_e);
                let pn = percentiles(&f.moduli.nu);
                // p5..p95, widened to a decade about the median when narrower (a homogeneous
                // object shows as one colour, not as noise stretched over the whole map).
                let map = if pe[2] - pe[0] >= 1.0 {
                    [pe[0], pe[2]]
                } else {
                    [pe[1] - 0.5, pe[1] + 0.5]
                };
                write_weights(&ctx.out_dir.join("field.material.arrow"), &f.field)
                    .map_err(StageError::failed)?;
                let mut g = object.gaussians.clone();
                let per = 3 * (usize::from(g.sh_degree) + 1).pow(2);
                // Each Gaussian shows its carrier particle's E.
                for (i, &c) in object.skin().carrier().iter().enumerate() {
                    let rgb = colour_of(log_e[c as usize], map[0], map[1]);
                    let sh = &mut g.sh[i * per..(i + 1) * per];
                    sh.fill(0.0);
                    for c in 0..3 {
                        sh[c] = (rgb[c] as f32 - 0.5) / crate::stages::init::SH_C0;
                    }
                }
                crate::io::ply::write_gaussians(&ctx.out_dir.join("field_E.ply"), &g)
                    .map_err(StageError::failed)?;
                Some(FieldSummary {
                    log10_youngs_modulus_p05_p50_p95: pe,
                    poisson_ratio_p05_p50_p95: pn,
                    colour_map_log10_e: map,
                    loss_global,
                    weights_table: "field.material.arrow".into(),
                    weights: f.field.field.param_count(),
                    parts: field_parts,
                })
            }
            _ => None,
        };
        let median = |i: usize, global: Option<f64>| {
            field.as_ref().map_or(global, |f| {
                Some(if i == 0 {
                    10f64.powf(f.log10_youngs_modulus_p05_p50_p95[1])
                } else {
                    f.poisson_ratio_p05_p50_p95[1]
                })
            })
        };
        let out = MaterialResult {
            family: crate::simulate::spec::family_name(family).into(),
            model: if fitted.is_some() {
                MaterialModel::Field
            } else {
                MaterialModel::Global
            },
            youngs_modulus: median(0, spec.youngs_modulus),
            poisson_ratio: median(1, spec.poisson_ratio),
            yield_stress: spec.yield_stress,
            viscosity: spec.viscosity,
            bulk_modulus: spec.bulk_modulus,
            friction_angle_deg: spec.friction_angle_deg,
            learned: learned.clone(),
            guess: guess.values.clone(),
            initial_velocity: velocity.initial_velocity,
            angular_velocity: velocity.angular_velocity,
            density: ctx.scene.density,
            loss_guess,
            loss_final: final_out.loss(),
            train_psnr_final: psnr,
            frames: last,
            epochs: p.epochs,
            particles: object.particles(),
            gaussians: object.rendered(),
            floaters: object.floaters,
            grid_dx: object.body.setup.dx,
            substeps: final_out.substeps.clone(),
            field,
            selection,
            profile,
        };
        crate::io::write_json(&ctx.out_dir.join("material.json"), &out)
            .map_err(StageError::failed)?;
        // The rigid part of the learned motion, as the rollouts start it; a velocity field's
        // residual is not in the file.
        let motion = velocity.rigid(&object);
        let residual_note = if velocity.model == crate::stages::velocity::VelocityModel::Field {
            "# The learned velocity field's residual is not in this file (particles.arrow has\n\
             # every particle's initial velocity): pipe simulate starts from its rigid part.\n"
        } else {
            ""
        };
        let sim = sim_yaml(
            &spec,
            &motion,
            ctx.scene,
            inputs.frame_dt,
            object.body.setup.dx,
            None,
            inputs.splat_filter(),
        );
        std::fs::write(
            ctx.out_dir.join("scene.sim.yaml"),
            format!(
                "# Learned by stage `{}` of {} (family {}); simulate the fitted Gaussians with\n\
                 #   pipe export FILE --stage warmup --format ply --out object.ply\n\
                 #   pipe simulate object.ply --material scene.sim.yaml --frames {} --out sim --splats\n{residual_note}{sim}",
                ctx.name,
                ctx.scene.path.display(),
                out.family,
                u32::from(last) + 1
            ),
        )
        .map_err(StageError::failed)?;
        crate::physics::particles::write(
            &ctx.out_dir.join("particles.arrow"),
            &object,
            &result,
            moduli,
            &v0,
        )
        .map_err(StageError::failed)?;
        ctx.progress.log(&report(&out, ctx.scene));
        Ok(())
    }
}

/// How closely the frames pin each parameter of the global fit `global`
/// ([`crate::physics::profile`]); where a move of a modulus, yield stress or viscosity
/// lowers the loss with the cameras agreeing, the fit goes on from there and is profiled
/// again (at most `profile.rounds` times, the move's rollout reused as the new fit's), then
/// takes each parameter's parabola vertex that lowers the loss. `eval` scores a material on
/// the fit's views and returns each (frame, view)'s loss.
fn profile_and_polish(
    p: &MaterialParams,
    ctx: &mut StageContext<'_>,
    learned: &[Param],
    global: &mut MaterialValues,
    work: &Work,
    mut eval: impl FnMut(&MaterialValues) -> Result<ViewLosses, StageError>,
) -> Result<Vec<ParamProfile>, StageError> {
    use crate::physics::profile::{best_better, paired, profile, vertex};
    let mut rounds = 0;
    let names = learned
        .iter()
        .map(|q| q.name())
        .collect::<Vec<_>>()
        .join(", ");
    // The losses of the points this round scored: the next round's fit is one of them.
    let mut seen: Vec<(Vec<f64>, ViewLosses)> = Vec::new();
    let (prof, fit) = loop {
        let at: Vec<f64> = learned
            .iter()
            .map(|q| global.get(*q).unwrap_or(0.0))
            .collect();
        seen.retain(|(v, _)| *v == at);
        ctx.progress.log(&format!(
            "material profile: each of {names} moved alone about the fit, on the training views (cameras agree at t >= {})",
            p.profile.t_min
        ));
        let from = global.clone();
        let (prof, fit) = profile(
            &p.profile,
            learned,
            &at,
            |values| {
                if let Some((_, l)) = seen.iter().find(|(v, _)| v == values) {
                    return Ok(l.clone());
                }
                let mut m = from.clone();
                for (q, v) in learned.iter().zip(values) {
                    m.values.insert(*q, *v);
                }
                let l = eval(&m)?;
                seen.push((values.to_vec(), l.clone()));
                Ok(l)
            },
            |line| ctx.progress.log(&format!("    {line}")),
        )?;
        if let Some(note) = budget_spent(p, work, "the profile", p.epochs) {
            ctx.progress.log(&note);
            break (prof, None);
        }
        // Only the axes of `probe`: a modulus, yield stress or viscosity can sit on a plateau
        // the descent cannot leave (a plasticine far above its yield stress moves as a
        // rigid–plastic body); ν and the friction angle have none, and where the frames hold
        // them weakly the loss follows the model's mismatch (the sample torus's ν, −0.05 for
        // 1.3 % of loss, away from the truth).
        match best_better(&prof, |k| learned[k].log_scaled()) {
            Some((k, value, rise)) if rounds < p.profile.rounds => {
                rounds += 1;
                global.values.insert(learned[k], value);
                ctx.progress.log(&format!(
                    "material profile: {} {value:.4e} lowers the loss by {:.2} % with the cameras agreeing: the fit goes on from there (round {rounds} of at most {})",
                    learned[k].name(),
                    -rise,
                    p.profile.rounds
                ));
            }
            _ => break (prof, Some(fit)),
        }
    };
    // The vertex of the parabola through each bracketed minimum, one parameter at a time
    // (taken together they interact: E and the yield stress of a plasticine).
    let mut vertices = 0u32;
    if let Some(mut fit) = fit.filter(|_| p.profile.rounds > 0) {
        for (q, pr) in learned.iter().zip(&prof) {
            let Some(v) = vertex(pr, *q) else { continue };
            let mut m = global.clone();
            m.values.insert(*q, v);
            let at = eval(&m)?;
            let (rise, t) = paired(&fit, &at);
            let taken = rise < 0.0;
            ctx.progress.log(&format!(
                "material profile: the parabola's vertex {} {v:.4e} {} the loss by {:.3} % (cameras t = {t:.2}): {}",
                q.name(),
                if taken { "lowers" } else { "raises" },
                rise.abs(),
                if taken { "taken" } else { "not taken" }
            ));
            if taken {
                *global = m;
                fit = at;
                vertices += 1;
            }
        }
    }
    for (metric, value) in [
        ("profile_moves", f64::from(rounds)),
        ("profile_vertices_taken", f64::from(vertices)),
    ] {
        ctx.metric(MetricRow::of_stage(metric, value));
    }
    Ok(prof)
}

/// The frames in closed form of `object`'s rollouts (`closed_form`; not with a velocity
/// field, whose residual deforms the body).
fn free_frames(
    p: &MaterialParams,
    velocity: &VelocityResult,
    object: &crate::physics::object::Object,
    last: u16,
    fluid: bool,
) -> Option<crate::physics::free_flight::FreeFrames> {
    (p.closed_form && velocity.model != crate::stages::velocity::VelocityModel::Field)
        .then(|| {
            crate::physics::free_flight::FreeFrames::of(
                object,
                &velocity.rigid(object),
                last,
                fluid,
            )
        })
        .flatten()
}

/// A kept field's values grouped into `profile.field_parts` parts, and each part's E moved
/// alone by the profile's steps ([`crate::physics::profile`]): `eval` scores per-particle
/// moduli on the fit's views and frames. `None` when the field does not split into that many
/// parts (a uniform field).
fn profile_field_parts(
    p: &MaterialParams,
    ctx: &mut StageContext<'_>,
    f: &crate::stages::material_field::FieldFit,
    volume: &[f64],
    mut eval: impl FnMut(
        &MaterialValues,
        &crate::physics::rollout::Moduli,
    ) -> Result<ViewLosses, StageError>,
) -> Result<Option<FieldParts>, StageError> {
    use crate::physics::field_parts::natural_breaks;
    let k = p.profile.field_parts;
    let log_e: Vec<f64> = f.moduli.e.iter().map(|e| e.log10()).collect();
    let Some(split) = natural_breaks(&log_e, volume, k) else {
        ctx.progress.log(&format!(
            "material profile: the field's E does not split into {k} parts: no part profiled"
        ));
        return Ok(None);
    };
    let part = split.assign(&f.moduli.e);
    let shares = split.shares(&part, volume);
    let median: Vec<f64> = split.log10_e.iter().map(|l| 10f64.powf(*l)).collect();
    ctx.progress.log(&format!(
        "material profile: the field in {k} parts (its log10 E cut at {}), each part's E moved alone on the training views",
        split.cuts_text()
    ));
    let learned = vec![Param::E; k];
    let (profiles, _) = crate::physics::profile::profile(
        &p.profile,
        &learned,
        &median,
        |values| {
            let mut moduli = f.moduli.clone();
            for (e, k) in moduli.e.iter_mut().zip(&part) {
                *e *= values[*k] / median[*k];
            }
            eval(&f.values, &moduli)
        },
        // Logged below, named by part.
        |_| {},
    )?;
    let parts = profiles
        .into_iter()
        .zip(&shares)
        .zip(&median)
        .enumerate()
        .map(|(i, ((mut profile, (share, n)), e))| {
            ctx.progress.log(&format!(
                "    part {} ({:.0} % of the volume, {n} particles): {}",
                i + 1,
                100.0 * share,
                profile.summary()
            ));
            profile.param = format!("E of part {} of {k}", i + 1);
            FieldPart {
                volume_share: *share,
                particles: *n,
                youngs_modulus_median: *e,
                profile,
            }
        })
        .collect();
    Ok(Some(FieldParts {
        thresholds: split.thresholds,
        parts,
    }))
}

/// The same object on another grid (`auto.regrid`): rebuilt from the canonical Gaussians with
/// another cell, so its particles and their grid are drawn anew.
struct OtherGrid<'a> {
    inputs: &'a Inputs,
    velocity: &'a VelocityResult,
    guess: &'a MaterialValues,
    /// The stage's rollout (its frames, precision and interrupt are kept).
    template: Rollout<'a>,
}

impl OtherGrid<'_> {
    /// The held-out losses (`targets`) of `simple` and of each field of `fits` (read at the new
    /// particles' rest positions, with its parts when it has them) on the grid of cell `dx` (m).
    fn held_out_losses<'t>(
        &self,
        p: &MaterialParams,
        ctx: &StageContext<'_>,
        dx: f64,
        targets: impl IntoIterator<Item = &'t crate::scene::targets::Target>,
        simple: &MaterialValues,
        fits: &[&crate::stages::material_field::FieldFit],
    ) -> Result<(f64, Vec<f64>), StageError> {
        let object = self.inputs.object(ctx, self.guess, Resolution::Dx(dx))?;
        let v0 = self
            .velocity
            .velocities(&object, &ctx.upstream("velocity")?.dir)?;
        let last = self.template.frames;
        let free = free_frames(p, self.velocity, &object, last, is_fluid(self.guess.family));
        let points: Vec<[f64; 3]> = object.body.state.x.iter().map(|x| x.to_array()).collect();
        let mut held = ViewsLoss::new(
            &object,
            is_fluid(self.guess.family),
            targets,
            LossWeights {
                lambda: p.lambda,
                alpha_weight: p.alpha_weight,
            },
            self.inputs.background,
        );
        ctx.progress.log(&format!(
            "material auto: the second grid holds {}",
            object.particle_summary()
        ));
        let base = Rollout {
            object: &object,
            material: simple,
            v0: &v0,
            moduli: None,
            free: free.as_ref(),
            ..self.template
        };
        let mut run = |r: Rollout<'_>| {
            r.run(&mut held, Wants::Loss)
                .map(|o| o.loss())
                .map_err(|e| match e {
                    RolloutError::Interrupted => StageError::Interrupted,
                    e => StageError::failed(FitError::Training {
                        epoch: p.epochs,
                        message: format!("on the second grid (`auto.regrid`): {e}"),
                    }),
                })
        };
        let ls = run(base)?;
        let mut lf = Vec::with_capacity(fits.len());
        for f in fits {
            let moduli = f
                .field
                .moduli_at(&points, &f.values)
                .map_err(|e| StageError::failed(FitError::Invalid(format!("field: {e}"))))?;
            lf.push(run(Rollout {
                material: &f.values,
                moduli: Some(&moduli),
                ..base
            })?);
        }
        Ok((ls, lf))
    }
}

/// Whether an epoch loop of `phase` stops before `epoch`: `Err` when the user
/// interrupted, `true` (and the reason logged) once the work budget is spent.
pub(crate) fn epoch_loop_stops(
    ctx: &StageContext<'_>,
    p: &MaterialParams,
    work: Option<&Work>,
    phase: &str,
    epoch: u32,
) -> Result<bool, StageError> {
    ctx.check_interrupted()?;
    match work.and_then(|w| budget_spent(p, w, phase, epoch)) {
        Some(note) => {
            ctx.progress.log(&note);
            Ok(true)
        }
        None => Ok(false),
    }
}

/// When `p.budget` is spent by the `work` done: the note the stage logs, naming the phase
/// that stops and the epochs it had done.
pub(crate) fn budget_spent(
    p: &MaterialParams,
    work: &Work,
    phase: &str,
    epochs_done: u32,
) -> Option<String> {
    work.spent(p.budget).map(|note| {
        format!(
            "material: {note}: {phase} stops after {epochs_done} epoch(s), with what it has learned"
        )
    })
}

/// The family's values of a fitted field with E (and ν) at the median of its particles'.
fn at_field_median(f: &crate::stages::material_field::FieldFit) -> MaterialValues {
    let log_e: Vec<f64> = f.moduli.e.iter().map(|e| e.log10()).collect();
    let mut m = f.values.clone();
    m.values
        .insert(Param::E, 10f64.powf(percentiles(&log_e)[1]));
    m.values.insert(Param::Nu, percentiles(&f.moduli.nu)[1]);
    m
}

/// The learned values next to the scene's ground truth, when it has one.
fn report(out: &MaterialResult, scene: &SceneSpec) -> String {
    let gt = crate::physics::fit::ground_truth(scene);
    let truth = |key: &str| gt.as_ref().and_then(|g| g[key].as_f64());
    let mut parts = Vec::new();
    for (name, value, key, unit) in [
        ("E", out.youngs_modulus, "E", " Pa"),
        ("nu", out.poisson_ratio, "nu", ""),
        ("yield stress", out.yield_stress, "yield_stress", " Pa"),
        (
            "viscosity",
            out.viscosity,
            if out.family == "newtonian" {
                "mu"
            } else {
                "plastic_viscosity_eta"
            },
            " Pa s",
        ),
        ("bulk modulus", out.bulk_modulus, "kappa", " Pa"),
        (
            "friction angle",
            out.friction_angle_deg,
            "friction_angle_deg",
            " deg",
        ),
    ] {
        if let Some(v) = value {
            let t = truth(key)
                .map(|t| format!(" (ground truth {t:.4e})"))
                .unwrap_or_default();
            parts.push(format!("{name} {v:.4e}{unit}{t}"));
        }
    }
    let v = out.initial_velocity;
    let v_truth = gt
        .as_ref()
        .and_then(|g| serde_json::from_value::<[f64; 3]>(g["v0"].clone()).ok())
        .map(|t| format!(" (ground truth [{}, {}, {}])", t[0], t[1], t[2]))
        .unwrap_or_default();
    format!(
        "learned {} material: {}; initial velocity [{:.4}, {:.4}, {:.4}] m/s{v_truth}; loss {:.5} at the guess -> {:.5}",
        out.family,
        parts.join(", "),
        v[0],
        v[1],
        v[2],
        out.loss_guess,
        out.loss_final
    )
}

/// `∂`-free helper: the velocity field's mean, for tests.
#[allow(dead_code)]
fn mean(v: &[DVec3]) -> DVec3 {
    v.iter().sum::<DVec3>() / v.len().max(1) as f64
}
