//! Stage `evaluate`: re-simulates the learned scene from frame 0 (the canonical Gaussians,
//! `velocity`'s initial velocity, `material`'s material: the same rollout the stages trained
//! on, on `pipe simulate`'s body) and scores it against the capture in every view and frame.
//!
//! Each view is rendered over black and composited over its camera's plate, and compared with
//! the capture inside the ingested mask and the plate outside (as `warmup` scores). Per (view,
//! frame, split) `metrics.arrow` holds `psnr`, `ssim`, `psnr_mask` (inside the object's mask)
//! and `mask_iou` (rendered alpha > ½ against the mask). Where the scene folder has ground
//! truth (`gt/params.json`, `gt/particles/<f>.ply`), the parameter errors and the per-frame
//! mean Chamfer distance between the simulated and the true particles are added.
//! `evaluation.json` summarises; `renders/` holds a PNG per view and frame, alpha and depth
//! as EXR, and an animated GIF per rendered view (captured | ours | 4× error).

use std::collections::BTreeMap;
use std::path::Path;

use glam::DVec3;
use pipe_mpm::{State, StateGrad};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::io::image::{self, Rgb8};
use crate::physics::appearance::{self, ColourFit, MotionRecorder};
use crate::physics::fit::{FitError, Inputs, PrecisionParam};
use crate::physics::material_field::read_moduli;
use crate::physics::material_truth::MaterialTruthErrors;
use crate::physics::object::{Object, Resolution};
use crate::physics::params::{MaterialValues, Param};
use crate::physics::pose::Pose;
use crate::physics::rollout::{FrameLoss, Moduli, Rollout, RolloutError, Wants, is_fluid};
use crate::pipeline::spec::{Preset, SceneSpec};
use crate::pipeline::stage::{
    InputFile, MetricRow, ParamError, StageContext, StageError, TypedStage,
};
use crate::scene::frames::{FrameRow, Role};
use crate::scene::gaussians::Gaussians;
use crate::scene::shading::Relight;
use crate::scene::table::Table;
use crate::scene::targets::{self, Target, composite};
use crate::stages::material::{MaterialModel, MaterialResult};
use crate::stages::velocity::VelocityResult;

/// Which views are rendered to files (all views are scored).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ViewSet {
    /// The held-out views (`scene.test_views`).
    #[default]
    Test,
    /// Every view.
    All,
}

/// Parameters of `evaluate`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EvaluateParams {
    /// Views whose renders are written (PNG, EXR, GIF); every view is scored.
    #[serde(default)]
    pub views: ViewSet,
    /// Write the renders (PNG per view and frame, alpha and depth EXR, a GIF per view).
    #[serde(default = "yes")]
    pub renders: bool,
    /// Precision of the re-simulation.
    #[serde(default)]
    pub precision: PrecisionParam,
    /// Milliseconds per GIF frame.
    #[serde(default = "gif_ms")]
    pub gif_ms: u32,
    /// Re-light the deformed Gaussians: the irradiance of each surface normal, fitted to the
    /// shading the warm-up baked into the colours, stays in the world when the body turns or
    /// flattens ([`crate::scene::shading`]; solids only).
    #[serde(default = "yes")]
    pub relight: bool,
    /// Passes over the training images of every frame in which the canonical Gaussians'
    /// colours (SH, nothing of the geometry) are refitted along the learned motion before
    /// scoring ([`crate::physics::appearance`]): the warm-up saw frame 0 only, in which the
    /// cameras barely see the side the object rests on. 0 keeps the warm-up's colours.
    /// Presets: draft 10, standard 20, paper 40.
    #[serde(default = "colour_epochs")]
    pub colour_epochs: u32,
    /// Adam's rate of the DC colour coefficients at the start of the refit (the higher orders
    /// take a twentieth; both decay to a tenth over the refit).
    #[serde(default = "colour_lr")]
    pub colour_lr: f32,
}

fn colour_epochs() -> u32 {
    20
}
fn colour_lr() -> f32 {
    0.005
}
fn yes() -> bool {
    true
}
fn gif_ms() -> u32 {
    150
}

/// The scores of one view in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ViewScore {
    /// Camera.
    pub view: u16,
    /// Frame.
    pub frame: u16,
    /// Whether the view was held out of training.
    pub test: bool,
    /// PSNR (dB) and SSIM of the composite over the plate against the capture.
    pub psnr: f64,
    pub ssim: f64,
    /// PSNR (dB) inside the object's mask.
    pub psnr_mask: f64,
    /// IoU of the rendered alpha (> ½) against the mask.
    pub mask_iou: f64,
}

/// `evaluation.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Mean over the test views and frames (every frame, 0 included).
    pub test_psnr_mean: Option<f64>,
    pub test_ssim_mean: Option<f64>,
    /// Test-view mean at frame 0 and at the last frame.
    pub test_psnr_first_frame: Option<f64>,
    pub test_psnr_last_frame: Option<f64>,
    /// Mean over the training views and frames.
    pub train_psnr_mean: Option<f64>,
    pub train_ssim_mean: Option<f64>,
    /// Test-view mean PSNR inside the mask and mask IoU.
    pub test_psnr_mask_mean: Option<f64>,
    pub test_mask_iou_mean: Option<f64>,
    /// Mean PSNR (dB) of the test views at each frame.
    pub test_psnr_per_frame: Vec<f64>,
    /// With `relight: true` (solids): the share of the Gaussians' baked log-luminance their
    /// rest normals explain (the fitted irradiance's hold on the colours); `null` when the
    /// renders were not re-lit.
    #[serde(default)]
    pub relight_explained: Option<f64>,
    /// The colour refit along the learned motion (`colour_epochs` > 0), else `null`.
    #[serde(default)]
    pub colour_refit: Option<ColourRefit>,
    /// The learned parameters (`material.json`'s, and the initial velocity, m/s).
    pub learned: BTreeMap<String, f64>,
    pub initial_velocity: [f64; 3],
    /// The learned angular velocity about the centre of mass (rad/s).
    #[serde(default)]
    pub angular_velocity: [f64; 3],
    /// The scene's ground truth, when it has one (same names; v0 in m/s, the angular velocity
    /// in rad/s when `gt/params.json` gives `angular_velocity`).
    pub ground_truth: Option<BTreeMap<String, f64>>,
    pub ground_truth_v0: Option<[f64; 3]>,
    #[serde(default)]
    pub ground_truth_angular_velocity: Option<[f64; 3]>,
    /// Errors against it: `|log10 learned − log10 truth|` for moduli, stresses and
    /// viscosities, absolute differences for ν and the friction angle, `|v0 − v0_true|` (m/s),
    /// `|ω − ω_true|` (rad/s).
    pub errors: Option<BTreeMap<String, f64>>,
    /// Mean Chamfer distance (m) between simulated and true particles, per frame and at the
    /// last frame.
    pub chamfer_per_frame_m: Vec<f64>,
    pub chamfer_last_frame_m: Option<f64>,
    /// Mean distance (m) between each simulated particle and the true particle nearest to it
    /// at frame 0, per frame and at the last frame: the true particles are numbered alike in
    /// every frame, so this follows material points, where Chamfer sees only the shape (a
    /// torus spinning about its axis, or a texture sliding over an unchanged outline, keep
    /// their Chamfer distance). Empty when the truth's particle count changes between frames.
    #[serde(default)]
    pub tracking_per_frame_m: Vec<f64>,
    #[serde(default)]
    pub tracking_last_frame_m: Option<f64>,
    /// The learned E and ν particle by particle (a field's, or the global values everywhere)
    /// against the scene's per-particle truth (`gt/material_particles.ply`), per part when it
    /// has few distinct values.
    #[serde(default)]
    pub material_truth: Option<MaterialTruthErrors>,
    /// Wall time (s) of every stage that made these results, and of this one.
    pub stage_wall_s: BTreeMap<String, f64>,
    /// Frames evaluated (`0..=frames`), test views.
    pub frames: u16,
    pub test_views: Vec<u16>,
}

/// What the colour refit did (`evaluation.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ColourRefit {
    /// Whether the refitted colours were kept: they lowered the loss of the training views
    /// held out of a first refit of half the passes (else the warm-up's colours are scored).
    pub kept: bool,
    /// The training views held out of the deciding refit, and their mean image loss at the
    /// warm-up's colours and at the refitted ones (`null` with fewer than two training views:
    /// then the refit is kept undecided).
    pub held_out_views: Vec<u16>,
    pub held_out_loss_before: Option<f64>,
    pub held_out_loss_after: Option<f64>,
    /// Passes made, and training images (views × frames) per pass of the final refit.
    pub epochs: u32,
    pub images: usize,
    /// Mean training image loss (`λ·L1 + (1 − λ)·D-SSIM`) in the final refit's first and last
    /// pass.
    pub loss_first_epoch: f64,
    pub loss_last_epoch: f64,
    /// Wall time (s) of the refits and their rollout.
    pub wall_s: f64,
}

/// The `evaluate` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Evaluate;

impl TypedStage for Evaluate {
    type Params = EvaluateParams;
    const KIND: &'static str = "evaluate";
    const VERSION: u32 = 9;
    const DESCRIPTION: &'static str = "Re-simulate the learned scene and score it in every view and frame (PSNR, SSIM, mask IoU; parameter and Chamfer errors against ground truth)";
    const UPSTREAM: &'static [&'static str] = &["ingest", "init", "warmup", "velocity", "material"];

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![(Gaussians::NAME, Gaussians::VERSION)]
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            Preset::Draft => json!({"colour_epochs": 10}),
            Preset::Standard => json!({"colour_epochs": 20}),
            Preset::Paper => json!({"colour_epochs": 40}),
        }
    }

    fn scene_key(&self, scene: &SceneSpec) -> Value {
        let mut key = scene.physics_key();
        key["test_views"] = json!(scene.test_views);
        key
    }

    fn validate(&self, p: &EvaluateParams) -> Result<(), ParamError> {
        if p.gif_ms == 0 || p.gif_ms > 10_000 {
            return Err(ParamError {
                path: "gif_ms".into(),
                message: format!("must be in 1..=10000, found {}", p.gif_ms),
            });
        }
        if !(p.colour_lr.is_finite() && p.colour_lr > 0.0 && p.colour_lr <= 1.0) {
            return Err(ParamError {
                path: "colour_lr".into(),
                message: format!("must be in (0, 1], found {}", p.colour_lr),
            });
        }
        Ok(())
    }

    fn inputs(&self, _p: &EvaluateParams, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError> {
        // The ground truth, when the scene folder has it.
        let mut out = Vec::new();
        let params = scene.path.join("gt/params.json");
        if params.is_file() {
            out.push(InputFile {
                logical_name: "gt/params.json".into(),
                path: params,
            });
        }
        let truth = scene.path.join(crate::physics::material_truth::TRUTH_FILE);
        if truth.is_file() {
            out.push(InputFile {
                logical_name: crate::physics::material_truth::TRUTH_FILE.into(),
                path: truth,
            });
        }
        let dir = scene.path.join("gt/particles");
        if let Ok(rd) = std::fs::read_dir(&dir) {
            let mut names: Vec<String> = rd
                .flatten()
                .filter_map(|e| e.file_name().into_string().ok())
                .filter(|n| {
                    n.ends_with(".ply") && n.trim_end_matches(".ply").parse::<u16>().is_ok()
                })
                .collect();
            names.sort();
            for n in names {
                out.push(InputFile {
                    logical_name: format!("gt/particles/{n}"),
                    path: dir.join(&n),
                });
            }
        }
        Ok(out)
    }

    fn run(&self, p: &EvaluateParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let started = std::time::Instant::now();
        let inputs = Inputs::load(ctx)?;
        let velocity: VelocityResult =
            crate::io::read_json(&ctx.upstream("velocity")?.dir.join("velocity.json"))
                .map_err(StageError::failed)?;
        let learned: MaterialResult =
            crate::io::read_json(&ctx.upstream("material")?.dir.join("material.json"))
                .map_err(StageError::failed)?;
        let family = inputs.family;
        let mut values = MaterialValues::guess(family, ctx.scene.density, &BTreeMap::new());
        for (q, v) in [
            (Param::E, learned.youngs_modulus),
            (Param::Nu, learned.poisson_ratio),
            (Param::YieldStress, learned.yield_stress),
            (Param::Viscosity, learned.viscosity),
            (Param::BulkModulus, learned.bulk_modulus),
            (Param::FrictionAngle, learned.friction_angle_deg),
        ] {
            if let (Some(v), true) = (v, values.get(q).is_some()) {
                values.values.insert(q, v);
            }
        }
        let grid = material_grid(ctx)?;
        let object = inputs.object(ctx, &values, grid)?;
        let v0 = velocity.velocities(&object, &ctx.upstream("velocity")?.dir)?;
        // A field is a function of the rest position: asked at this object's particles.
        let rest: Vec<[f64; 3]> = object.body.state.x.iter().map(|x| x.to_array()).collect();
        let moduli = match learned.model {
            MaterialModel::Field => Some(
                read_moduli(
                    &ctx.upstream("material")?.dir.join("field.material.arrow"),
                    rest,
                    &values,
                )
                .map_err(|e| StageError::failed(FitError::Invalid(e)))?,
            ),
            MaterialModel::Global | MaterialModel::Auto => None,
        };
        let truth_errors = match (&moduli, is_fluid(family)) {
            (_, true) => None,
            (Some(m), false) => Some(m.clone()),
            (None, false) => Some(Moduli {
                e: vec![values.get(Param::E).unwrap_or(f64::NAN); object.particles()],
                nu: vec![values.get(Param::Nu).unwrap_or(f64::NAN); object.particles()],
            }),
        }
        .map(|m| {
            crate::physics::material_truth::errors(
                &ctx.scene
                    .path
                    .join(crate::physics::material_truth::TRUTH_FILE),
                &object.body.state.x,
                &m,
            )
        })
        .transpose()
        .map_err(|e| StageError::failed(FitError::Invalid(e)))?
        .flatten();
        let last = inputs.last_frame();
        let all_rows: Vec<&FrameRow> = inputs.frames.rows.iter().collect();
        let targets = targets::load(&inputs.ingest_dir, &all_rows).map_err(StageError::failed)?;
        let written: Vec<u16> = match p.views {
            ViewSet::Test => ctx.scene.test_views.clone(),
            ViewSet::All => {
                let mut v: Vec<u16> = targets.iter().map(|t| t.row.view).collect();
                v.sort_unstable();
                v.dedup();
                v
            }
        };
        let gt_dir = ctx.scene.path.join("gt/particles");
        let out_dir = ctx.out_dir.to_path_buf();
        if p.renders {
            for sub in ["renders", "renders/alpha", "renders/depth"] {
                std::fs::create_dir_all(out_dir.join(sub)).map_err(StageError::failed)?;
            }
        }
        let shading = if p.relight && !is_fluid(family) {
            object.relight()
        } else {
            None
        };
        if let Some(r) = &shading {
            ctx.progress.log(&format!(
                "evaluate: re-lighting the deformed Gaussians (normals explain {:.0} % of the baked log-luminance)",
                100.0 * r.shading.explained
            ));
        }
        let interrupt = ctx.interrupt_flag();
        let rollout = Rollout {
            object: &object,
            material: &values,
            v0: &v0,
            frames: last,
            precision: p.precision.mpm(),
            interrupt: Some(interrupt),
            moduli: moduli.as_ref(),
            // Re-simulated from frame 0, as `pipe simulate` does.
            free: None,
            work: None,
        };
        let mut gaussians = std::borrow::Cow::Borrowed(&object.gaussians);
        let colour_refit = if p.colour_epochs > 0 {
            let (sh, refit) = refit_colours(
                ctx,
                shading.as_ref(),
                &targets,
                &rollout,
                p,
                inputs.background,
            )?;
            if let Some(sh) = sh {
                gaussians.to_mut().sh = sh;
                write_refitted(&inputs.gaussians, &gaussians, ctx.out_dir)?;
            }
            Some(refit)
        } else {
            None
        };
        let mut eval = Scorer {
            object: &object,
            gaussians: &gaussians,
            shading: shading.as_ref(),
            fluid: is_fluid(family),
            targets: &targets,
            background: inputs.background,
            written: &written,
            out_dir: &out_dir,
            renders: p.renders,
            scores: Vec::new(),
            chamfer: Vec::new(),
            tracking: Tracking::default(),
            gt_dir: &gt_dir,
            gif: BTreeMap::new(),
        };
        ctx.progress.log(&format!(
            "evaluate: re-simulating frames 1..={last} ({} particles), scoring {} views",
            object.particles(),
            {
                let mut v: Vec<u16> = targets.iter().map(|t| t.row.view).collect();
                v.sort_unstable();
                v.dedup();
                v.len()
            }
        ));
        eval.frame(0, &rollout.initial_state(), None)
            .map_err(train_error)?;
        rollout.run(&mut eval, Wants::Loss).map_err(train_error)?;
        if p.renders {
            for (view, frames) in &eval.gif {
                crate::io::video::write_gif(
                    &out_dir.join(format!("renders/v{view}.gif")),
                    frames,
                    p.gif_ms,
                )
                .map_err(StageError::failed)?;
            }
        }
        let scores = eval.scores.clone();
        let chamfer = eval.chamfer.clone();
        let tracking = eval.tracking.per_frame.clone();
        for s in &scores {
            for (metric, value) in [
                ("psnr", s.psnr),
                ("ssim", s.ssim),
                ("psnr_mask", s.psnr_mask),
                ("mask_iou", s.mask_iou),
            ] {
                ctx.metric(MetricRow {
                    epoch: None,
                    view: Some(s.view),
                    frame: Some(s.frame),
                    metric: format!("{}_{metric}", if s.test { "test" } else { "train" }),
                    value,
                });
            }
        }
        for (name, values) in [("chamfer_m", &chamfer), ("tracking_m", &tracking)] {
            for (f, c) in values.iter().enumerate() {
                ctx.metric(MetricRow {
                    epoch: None,
                    view: None,
                    frame: Some(f as u16),
                    metric: name.into(),
                    value: *c,
                });
            }
        }
        let mean = |it: &mut dyn Iterator<Item = f64>| {
            let v: Vec<f64> = it.collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        let test = |s: &&ViewScore| s.test;
        let train = |s: &&ViewScore| !s.test;
        let per_frame: Vec<f64> = (0..=last)
            .filter_map(|f| {
                mean(
                    &mut scores
                        .iter()
                        .filter(test)
                        .filter(|s| s.frame == f)
                        .map(|s| s.psnr),
                )
            })
            .collect();
        let mut learned_map = BTreeMap::new();
        for (name, v) in [
            ("E", learned.youngs_modulus),
            ("nu", learned.poisson_ratio),
            ("yield_stress", learned.yield_stress),
            ("viscosity", learned.viscosity),
            ("bulk_modulus", learned.bulk_modulus),
            ("friction_angle", learned.friction_angle_deg),
        ] {
            if let Some(v) = v {
                learned_map.insert(name.to_string(), v);
            }
        }
        let Truth {
            values: truth,
            v0: truth_v0,
            angular: truth_w,
        } = ground_truth(ctx.scene, &learned.family);
        let errors = truth.as_ref().map(|t| {
            let mut e = BTreeMap::new();
            for (name, l) in &learned_map {
                if let Some(t) = t.get(name) {
                    let err = match name.as_str() {
                        "nu" | "friction_angle" => (l - t).abs(),
                        _ if *t > 0.0 && *l > 0.0 => (l.log10() - t.log10()).abs(),
                        _ => (l - t).abs(),
                    };
                    e.insert(name.clone(), err);
                }
            }
            if let Some(tv) = truth_v0 {
                e.insert(
                    "v0_m_s".into(),
                    (DVec3::from_array(velocity.initial_velocity) - DVec3::from_array(tv)).length(),
                );
            }
            if let Some(tw) = truth_w {
                e.insert(
                    "angular_velocity_rad_s".into(),
                    (DVec3::from_array(velocity.angular_velocity) - DVec3::from_array(tw)).length(),
                );
            }
            e
        });
        let mut stage_wall_s = BTreeMap::new();
        for (name, u) in ctx.upstream.iter() {
            stage_wall_s.insert(name.clone(), u.manifest.wall_s);
        }
        stage_wall_s.insert(ctx.name.to_string(), started.elapsed().as_secs_f64());
        let result = Evaluation {
            test_psnr_mean: mean(&mut scores.iter().filter(test).map(|s| s.psnr)),
            test_ssim_mean: mean(&mut scores.iter().filter(test).map(|s| s.ssim)),
            test_psnr_first_frame: per_frame.first().copied(),
            test_psnr_last_frame: per_frame.last().copied(),
            train_psnr_mean: mean(&mut scores.iter().filter(train).map(|s| s.psnr)),
            train_ssim_mean: mean(&mut scores.iter().filter(train).map(|s| s.ssim)),
            test_psnr_mask_mean: mean(&mut scores.iter().filter(test).map(|s| s.psnr_mask)),
            test_mask_iou_mean: mean(&mut scores.iter().filter(test).map(|s| s.mask_iou)),
            test_psnr_per_frame: per_frame,
            relight_explained: shading.as_ref().map(|r| r.shading.explained),
            colour_refit,
            learned: learned_map,
            initial_velocity: velocity.initial_velocity,
            angular_velocity: velocity.angular_velocity,
            ground_truth: truth,
            ground_truth_v0: truth_v0,
            ground_truth_angular_velocity: truth_w,
            errors,
            chamfer_last_frame_m: chamfer.last().copied().filter(|c| c.is_finite()),
            chamfer_per_frame_m: chamfer,
            tracking_last_frame_m: tracking.last().copied().filter(|c| c.is_finite()),
            tracking_per_frame_m: tracking,
            material_truth: truth_errors,
            stage_wall_s,
            frames: last,
            test_views: ctx.scene.test_views.clone(),
        };
        for (metric, value) in [
            ("test_psnr_mean", result.test_psnr_mean),
            ("test_ssim_mean", result.test_ssim_mean),
            ("train_psnr_mean", result.train_psnr_mean),
            ("chamfer_last_frame_m", result.chamfer_last_frame_m),
            ("tracking_last_frame_m", result.tracking_last_frame_m),
        ] {
            if let Some(value) = value {
                ctx.metric(MetricRow::of_stage(metric, value));
            }
        }
        if let Some(errors) = &result.errors {
            for (name, value) in errors {
                ctx.metric(MetricRow {
                    epoch: None,
                    view: None,
                    frame: None,
                    metric: format!("error_{name}"),
                    value: *value,
                });
            }
        }
        if let Some(t) = &result.material_truth {
            let mut rows = vec![(
                "error_field_log10_E_abs_median".to_string(),
                t.log10_youngs_modulus_abs_median,
            )];
            for (k, part) in t.parts.iter().enumerate() {
                rows.push((
                    format!("error_part{k}_log10_E"),
                    part.log10_youngs_modulus_error,
                ));
            }
            for (metric, value) in rows {
                ctx.metric(MetricRow {
                    epoch: None,
                    view: None,
                    frame: None,
                    metric,
                    value,
                });
            }
        }
        ctx.progress.log(&summary(&result));
        crate::io::write_json(&out_dir.join("evaluation.json"), &result)
            .map_err(StageError::failed)?;
        Ok(())
    }
}

/// Writes `gaussians.arrow`: the warm-up's Gaussians (`all`, floaters included) with the
/// colours of the simulated ones (`refitted`, matched by id) replaced: what `edit` renders.
fn write_refitted(all: &Gaussians, refitted: &Gaussians, out: &Path) -> Result<(), StageError> {
    let per = 3 * crate::scene::gaussians::sh_coeffs(all.sh_degree);
    let row: BTreeMap<u32, usize> = refitted
        .id
        .iter()
        .enumerate()
        .map(|(i, id)| (*id, i))
        .collect();
    let mut g = all.clone();
    for (k, id) in all.id.iter().enumerate() {
        if let Some(&i) = row.get(id) {
            g.sh[k * per..(k + 1) * per].copy_from_slice(&refitted.sh[i * per..(i + 1) * per]);
        }
    }
    crate::scene::table::write(&out.join(GAUSSIANS_FILE), &g).map_err(StageError::failed)
}

/// The refitted canonical Gaussians `evaluate` writes when it keeps the colour refit.
pub const GAUSSIANS_FILE: &str = "gaussians.arrow";

/// Refits the canonical colours along the learned motion (a rollout recording every frame's
/// pose), first on the training views but a held-out few (half the passes); when that lowers
/// the held-out views' loss, again on every training view, whose colours are returned (else `None`: the
/// warm-up's colours stay). Logs and records the loss per pass.
fn refit_colours(
    ctx: &mut StageContext<'_>,
    shading: Option<&Relight>,
    targets: &[Target],
    rollout: &Rollout<'_>,
    p: &EvaluateParams,
    background: [f32; 3],
) -> Result<(Option<Vec<f32>>, ColourRefit), StageError> {
    let started = std::time::Instant::now();
    let object = rollout.object;
    let mut motion = MotionRecorder::new(object, is_fluid(rollout.material.family), shading);
    motion.record(0, &rollout.initial_state());
    rollout.run(&mut motion, Wants::Loss).map_err(train_error)?;
    let fail = |e: String| StageError::failed(FitError::Invalid(e));
    let fit = ColourFit {
        epochs: p.colour_epochs,
        lr: p.colour_lr,
        lambda: targets::DEFAULT_LAMBDA,
    };
    let g = &object.gaussians;
    let train: Vec<&Target> = targets
        .iter()
        .filter(|t| t.row.role == Role::Train)
        .collect();
    let mut views: Vec<u16> = train.iter().map(|t| t.row.view).collect();
    views.sort_unstable();
    views.dedup();
    let held = crate::stages::material_select::held_out_views(&views, None).unwrap_or_default();
    let (mut before, mut after) = (None, None);
    if !held.is_empty() {
        let (out, fitted): (Vec<&Target>, Vec<&Target>) =
            train.iter().partition(|t| held.contains(&t.row.view));
        // Half the passes decide (the sign of the held-out change is what is asked).
        let trial = ColourFit {
            epochs: fit.epochs.div_ceil(2),
            ..fit
        };
        let (sh, _) = appearance::refit_colours(g, &motion.frames, &fitted, background, &trial)
            .map_err(fail)?;
        before = appearance::mean_loss(g, &g.sh, &motion.frames, &out, background, fit.lambda)
            .map_err(fail)?;
        after = appearance::mean_loss(g, &sh, &motion.frames, &out, background, fit.lambda)
            .map_err(fail)?;
    }
    let kept = match (before, after) {
        (Some(b), Some(a)) => a < b,
        _ => true,
    };
    let (sh, report) = if kept {
        let (sh, report) =
            appearance::refit_colours(g, &motion.frames, &train, background, &fit).map_err(fail)?;
        (Some(sh), report)
    } else {
        (None, appearance::ColourFitReport::default())
    };
    for (epoch, loss) in report.epoch_loss.iter().enumerate() {
        ctx.metric(MetricRow {
            epoch: Some(epoch as u32),
            view: None,
            frame: None,
            metric: "colour_loss".into(),
            value: *loss,
        });
    }
    let refit = ColourRefit {
        kept,
        held_out_views: held,
        held_out_loss_before: before,
        held_out_loss_after: after,
        epochs: if kept { p.colour_epochs } else { 0 },
        images: report.images,
        loss_first_epoch: report.epoch_loss.first().copied().unwrap_or(f64::NAN),
        loss_last_epoch: report.epoch_loss.last().copied().unwrap_or(f64::NAN),
        wall_s: started.elapsed().as_secs_f64(),
    };
    let judged = match (before, after) {
        (Some(b), Some(a)) => format!(
            "held-out views {:?}: loss {b:.4} -> {a:.4} ({:+.1} %)",
            refit.held_out_views,
            100.0 * (a / b - 1.0)
        ),
        _ => "fewer than two training views: kept undecided".into(),
    };
    ctx.progress.log(&if kept {
        format!(
            "evaluate: colours refitted along the learned motion ({judged}; {} passes over {} training images, loss {:.4} -> {:.4}; {:.1} s)",
            refit.epochs, refit.images, refit.loss_first_epoch, refit.loss_last_epoch, refit.wall_s
        )
    } else {
        format!(
            "evaluate: the warm-up's colours kept: a refit along the learned motion did not predict the held-out views better ({judged}; {:.1} s)",
            refit.wall_s
        )
    });
    Ok((sh, refit))
}

/// The grid the `material` stage simulated with (its resolved parameters).
fn material_grid(ctx: &StageContext<'_>) -> Result<Resolution, StageError> {
    let m = ctx.upstream("material")?;
    Resolution::from_params(&m.manifest.key_material.params).ok_or_else(|| {
        StageError::failed(FitError::Invalid(
            "the `material` entry has no `cells` parameter".into(),
        ))
    })
}

fn train_error(e: RolloutError) -> StageError {
    match e {
        RolloutError::Interrupted => StageError::Interrupted,
        e => StageError::failed(FitError::Training {
            epoch: 0,
            message: format!("re-simulating the learned scene: {e}"),
        }),
    }
}

/// What `gt/params.json` says, when the scene has one.
#[derive(Default)]
struct Truth {
    /// The parameters under this project's names.
    values: Option<BTreeMap<String, f64>>,
    /// `v0` (m/s).
    v0: Option<[f64; 3]>,
    /// `angular_velocity` (rad/s), when given.
    angular: Option<[f64; 3]>,
}

/// `gt/params.json`'s parameters under this project's names, its `v0` and, when it gives
/// one, its `angular_velocity`.
fn ground_truth(scene: &SceneSpec, family: &str) -> Truth {
    let Some(gt) = crate::physics::fit::ground_truth(scene) else {
        return Truth::default();
    };
    let mut t = BTreeMap::new();
    let pick = |key: &str| gt[key].as_f64();
    for (name, key) in [
        ("E", "E"),
        ("nu", "nu"),
        ("yield_stress", "yield_stress"),
        ("bulk_modulus", "kappa"),
        ("friction_angle", "friction_angle_deg"),
    ] {
        if let Some(v) = pick(key) {
            t.insert(name.to_string(), v);
        }
    }
    let visc = if family == "newtonian" {
        pick("mu")
    } else {
        pick("plastic_viscosity_eta").or_else(|| pick("viscosity_eta"))
    };
    if let Some(v) = visc {
        t.insert("viscosity".to_string(), v);
    }
    let v0 = serde_json::from_value::<[f64; 3]>(gt["v0"].clone()).ok();
    let angular = serde_json::from_value::<[f64; 3]>(gt["angular_velocity"].clone()).ok();
    Truth {
        values: Some(t),
        v0,
        angular,
    }
}

fn summary(e: &Evaluation) -> String {
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
    let mut s = format!(
        "test PSNR {} dB (frame 0 {}, last {}), SSIM {}; train PSNR {} dB",
        f(e.test_psnr_mean),
        f(e.test_psnr_first_frame),
        f(e.test_psnr_last_frame),
        e.test_ssim_mean
            .map_or("-".to_string(), |v| format!("{v:.4}")),
        f(e.train_psnr_mean)
    );
    if let Some(c) = e.chamfer_last_frame_m {
        s.push_str(&format!("; Chamfer at the last frame {:.2} mm", c * 1e3));
    }
    if let Some(c) = e.tracking_last_frame_m {
        s.push_str(&format!(", material points {:.2} mm off", c * 1e3));
    }
    if let Some(err) = &e.errors {
        let parts: Vec<String> = err.iter().map(|(k, v)| format!("{k} {v:.3}")).collect();
        s.push_str(&format!("; errors: {}", parts.join(", ")));
    }
    if let Some(t) = &e.material_truth {
        s.push_str(&format!(
            "; per particle: |log10 E error| median {:.3}",
            t.log10_youngs_modulus_abs_median
        ));
        for p in &t.parts {
            s.push_str(&format!(
                "; part E {:.3e} Pa ({} particles): median {:.3e} Pa (log10 error {:.3})",
                p.youngs_modulus_truth,
                p.particles,
                10f64.powf(p.log10_youngs_modulus_median),
                p.log10_youngs_modulus_error
            ));
        }
    }
    s
}

/// Renders and scores every view of a frame as the rollout reaches it.
struct Scorer<'a> {
    object: &'a Object,
    /// Its Gaussians as rendered (the canonical ones, their colours refitted when they were).
    gaussians: &'a Gaussians,
    /// The re-lighting, when on.
    shading: Option<&'a Relight>,
    fluid: bool,
    targets: &'a [Target],
    background: [f32; 3],
    written: &'a [u16],
    out_dir: &'a Path,
    renders: bool,
    scores: Vec<ViewScore>,
    chamfer: Vec<f64>,
    tracking: Tracking,
    gt_dir: &'a Path,
    /// Per written view, the GIF frames (captured | ours | error).
    gif: BTreeMap<u16, Vec<Rgb8>>,
}

impl FrameLoss for Scorer<'_> {
    fn frame(
        &mut self,
        frame: u16,
        state: &State,
        _grad: Option<&mut StateGrad>,
    ) -> Result<f64, RolloutError> {
        let fail = |message: String| RolloutError::Loss { frame, message };
        let pose = Pose::<f32>::of(state, self.object.skin(), self.fluid);
        let relit = self.shading.map(|r| {
            r.sh(
                &self.gaussians.sh,
                self.gaussians.sh_degree,
                &self.object.gaussian_f(&state.f),
            )
        });
        let g = pose.apply(crate::scene::splat::render_gaussians_sh(
            self.gaussians,
            relit.as_deref().unwrap_or(&self.gaussians.sh),
        ));
        let opts = targets::over_black();
        for t in self.targets.iter().filter(|t| t.row.frame == frame) {
            let view = t.row.view;
            let (w, h) = t.size();
            let out = pipe_render::render(&g, &t.camera, &opts)
                .map_err(|e| fail(format!("rendering view {view}: {e}")))?;
            let backdrop = t.backdrop(self.background);
            let ours = composite(&out, &backdrop);
            let truth = t.over(&backdrop);
            let a =
                pipe_loss::Image::new("render", &ours, w, h).map_err(|e| fail(e.to_string()))?;
            let b =
                pipe_loss::Image::new("target", &truth, w, h).map_err(|e| fail(e.to_string()))?;
            let psnr = pipe_loss::psnr(a, b).map_err(|e| fail(e.to_string()))?;
            let ssim = pipe_loss::ssim(a, b).map_err(|e| fail(e.to_string()))?;
            let (mut se, mut n_in, mut inter, mut union) = (0.0f64, 0usize, 0usize, 0usize);
            for (i, m) in t.mask.iter().enumerate() {
                let (inside, drawn) = (*m > 0.5, out.alpha[i] > 0.5);
                inter += usize::from(inside && drawn);
                union += usize::from(inside || drawn);
                if inside {
                    n_in += 1;
                    for c in 0..3 {
                        let d = f64::from(ours[3 * i + c] - truth[3 * i + c]);
                        se += d * d;
                    }
                }
            }
            let psnr_mask = if n_in == 0 {
                f64::NAN
            } else {
                let mse = se / (3 * n_in) as f64;
                if mse == 0.0 {
                    f64::INFINITY
                } else {
                    -10.0 * mse.log10()
                }
            };
            let mask_iou = if union == 0 {
                1.0
            } else {
                inter as f64 / union as f64
            };
            let test = t.row.role == Role::Test;
            self.scores.push(ViewScore {
                view,
                frame,
                test,
                psnr,
                ssim,
                psnr_mask,
                mask_iou,
            });
            if self.renders && self.written.contains(&view) {
                let rgb = |px: &[f32]| Rgb8 {
                    width: w as u32,
                    height: h as u32,
                    data: px
                        .iter()
                        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                        .collect(),
                };
                let (ours8, truth8) = (rgb(&ours), rgb(&truth));
                let name = format!("v{view}_f{frame}");
                let err = |e: &dyn std::fmt::Display| fail(e.to_string());
                image::write_rgb8(&self.out_dir.join(format!("renders/{name}.png")), &ours8)
                    .map_err(|e| err(&e))?;
                crate::io::exr::write_channel(
                    &self.out_dir.join(format!("renders/alpha/{name}.exr")),
                    "A",
                    w as u32,
                    h as u32,
                    &out.alpha,
                )
                .map_err(|e| err(&e))?;
                crate::io::exr::write_depth(
                    &self.out_dir.join(format!("renders/depth/{name}.exr")),
                    w as u32,
                    h as u32,
                    &out.depth,
                )
                .map_err(|e| err(&e))?;
                self.gif.entry(view).or_default().push(image::compare_strip(
                    &truth8.data,
                    &ours8.data,
                    w,
                    h,
                ));
            }
        }
        // The ground truth's particles of this frame, when the scene has them.
        let gt = self.gt_dir.join(format!("{frame}.ply"));
        let truth: Option<Vec<DVec3>> = crate::io::ply::read_points(&gt).ok().map(|cloud| {
            cloud
                .positions
                .iter()
                .map(|p| DVec3::new(p[0].into(), p[1].into(), p[2].into()))
                .collect()
        });
        let chamfer = truth.as_ref().map_or(f64::NAN, |truth| {
            crate::scene::neighbors::mean_chamfer(&state.x, truth).unwrap_or(f64::NAN)
        });
        if gt.is_file() || !self.chamfer.is_empty() {
            self.chamfer.push(chamfer);
            self.tracking.frame(&state.x, truth.as_deref());
        }
        Ok(0.0)
    }
}

/// The tracking error ([`Evaluation::tracking_per_frame_m`]): each simulated particle paired
/// with the true particle nearest to it at the first frame scored.
#[derive(Debug, Default)]
struct Tracking {
    /// Simulated particle → true particle index, and the truth's particle count.
    pairs: Option<(Vec<usize>, usize)>,
    per_frame: Vec<f64>,
}

impl Tracking {
    /// Scores one frame (`NaN` without a truth, or when its count differs from the first's).
    fn frame(&mut self, ours: &[DVec3], truth: Option<&[DVec3]>) {
        let Some(truth) = truth.filter(|t| !t.is_empty() && !ours.is_empty()) else {
            self.per_frame.push(f64::NAN);
            return;
        };
        if self.pairs.is_none() && self.per_frame.is_empty() {
            self.pairs = pair_nearest(ours, truth).map(|p| (p, truth.len()));
        }
        let value = match &self.pairs {
            Some((pairs, n)) if *n == truth.len() && pairs.len() == ours.len() => {
                ours.iter()
                    .zip(pairs)
                    .map(|(x, &j)| x.distance(truth[j]))
                    .sum::<f64>()
                    / ours.len() as f64
            }
            _ => f64::NAN,
        };
        self.per_frame.push(value);
    }
}

/// For each point of `a`, the index of the nearest point of `b`.
fn pair_nearest(a: &[DVec3], b: &[DVec3]) -> Option<Vec<usize>> {
    let spacing = crate::scene::neighbors::median_nn_distance(b)?;
    let grid = crate::scene::neighbors::PointGrid::new(b, spacing.max(1e-6) * 2.0);
    a.iter()
        .map(|&q| grid.nearest(q, None).map(|(j, _)| j))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_colour_rate_out_of_range_is_refused_by_name() {
        let ok: EvaluateParams = serde_json::from_value(json!({})).unwrap();
        assert_eq!((ok.colour_epochs, ok.colour_lr), (20, 0.005));
        assert!(Evaluate.validate(&ok).is_ok());
        for bad in [-1.0f32, 0.0, f32::NAN, 2.0] {
            let p = EvaluateParams {
                colour_lr: bad,
                ..ok.clone()
            };
            let e = Evaluate.validate(&p).unwrap_err();
            assert_eq!(e.path, "colour_lr");
            assert!(e.message.contains(&bad.to_string()), "{}", e.message);
        }
    }

    fn ring(n: usize, turn: f64) -> Vec<DVec3> {
        (0..n)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / n as f64 + turn;
                DVec3::new(a.cos(), 0.5, a.sin())
            })
            .collect()
    }

    #[test]
    fn tracking_sees_a_spin_that_chamfer_cannot() {
        // A ring of 360 points turned by 10° about its axis: the same shape (Chamfer 0), but
        // every material point moved by 2 sin(5°) ≈ 0.174 m.
        let (rest, turned) = (ring(360, 0.0), ring(360, 10f64.to_radians()));
        let chamfer = crate::scene::neighbors::mean_chamfer(&turned, &turned).unwrap();
        assert!(chamfer < 1e-12);
        let mut t = Tracking::default();
        t.frame(&rest, Some(&rest));
        t.frame(&turned, Some(&turned));
        // Our particles stayed where they were while the truth turned.
        t.frame(&rest, Some(&turned));
        let expected = 2.0 * 5f64.to_radians().sin();
        assert!(
            t.per_frame[0] < 1e-12 && t.per_frame[1] < 1e-12,
            "{:?}",
            t.per_frame
        );
        assert!(
            (t.per_frame[2] - expected).abs() < 1e-9,
            "{:?}",
            t.per_frame
        );
        // A frame whose truth has another count cannot be paired, nor one without a truth.
        t.frame(&rest, Some(&ring(100, 0.0)));
        t.frame(&rest, None);
        assert!(t.per_frame[3].is_nan() && t.per_frame[4].is_nan());
        assert_eq!(t.per_frame.len(), 5);
    }
}
