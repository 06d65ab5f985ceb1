//! Stage `warmup`: static 3DGS optimisation of the canonical Gaussians on the first frame(s)
//! (Kerbl et al. 2023): Adam on positions, log-scales, rotations, opacity logits and SH, the loss
//! λ·L1 + (1 − λ)·D-SSIM against the white-composited object images, adaptive density control
//! and opacity resets. Writes the canonical `gaussians.arrow`, `metrics.arrow` (training curve,
//! held-out PSNR/SSIM) and `renders/` (test views next to ground truth).

pub mod adam;
pub mod density;
mod gt_mask;

use std::path::Path;

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use schemas::{Backdrop, WarmupParams};
use serde_json::{Value, json};

use self::adam::AdamConfig;
use self::density::{DensifyConfig, DensityStats, GroupStates};
use crate::io::image::{self, Rgb8};
use crate::pipeline::spec::{Preset, SceneSpec};
use crate::pipeline::stage::{
    InputFile, MetricRow, ParamError, StageContext, StageError, TypedStage,
};
use crate::scene::camera::Camera;
use crate::scene::frames::{FrameRow, Frames, Role};
use crate::scene::gaussians::Gaussians;
use crate::scene::splat;
use crate::scene::table::{self, Table};

/// Parameters of `warmup` (kept in their own module so the stage reads top-down).
pub mod schemas {
    use schemars::JsonSchema;
    use serde::{Deserialize, Serialize};

    /// Parameters of `warmup`.
    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
    #[serde(deny_unknown_fields)]
    pub struct WarmupParams {
        /// Frames whose images are fitted (the canonical state).
        #[serde(default = "frames")]
        pub frames: Vec<u16>,
        /// Passes over all training images of those frames.
        #[serde(default = "epochs")]
        pub epochs: u32,
        /// Weight of L1 in λ·L1 + (1 − λ)·D-SSIM.
        #[serde(default = "lambda")]
        pub lambda: f64,
        /// Position learning rate at the start, × scene extent (3DGS: 1.6e-4).
        #[serde(default = "lr_position")]
        pub lr_position: f32,
        /// Position learning rate at the end (exponential decay), × scene extent.
        #[serde(default = "lr_position_final")]
        pub lr_position_final: f32,
        /// Learning rate of the SH DC term (higher orders use 1/20 of it).
        #[serde(default = "lr_sh")]
        pub lr_sh: f32,
        /// Learning rate of opacity logits.
        #[serde(default = "lr_opacity")]
        pub lr_opacity: f32,
        /// Learning rate of log-scales.
        #[serde(default = "lr_scale")]
        pub lr_scale: f32,
        /// Learning rate of quaternions.
        #[serde(default = "lr_rotation")]
        pub lr_rotation: f32,
        /// Densify from this fraction of the iterations...
        #[serde(default = "densify_from")]
        pub densify_from: f32,
        /// ...until this fraction.
        #[serde(default = "densify_until")]
        pub densify_until: f32,
        /// Iterations between densification steps.
        #[serde(default = "densify_every")]
        pub densify_every: u32,
        /// Mean NDC gradient threshold of densification (3DGS: 2e-4).
        #[serde(default = "grad_threshold")]
        pub grad_threshold: f32,
        /// Iterations between opacity resets (0 = never).
        #[serde(default = "opacity_reset_every")]
        pub opacity_reset_every: u32,
        /// Upper bound on the number of Gaussians.
        #[serde(default = "max_gaussians")]
        pub max_gaussians: u32,
        /// Weight of the silhouette term mean |α − mask| (the object is opaque inside its
        /// mask and absent outside); 0 disables it.
        #[serde(default = "alpha_weight")]
        pub alpha_weight: f64,
        /// What the Gaussians are composited over in training: the camera's background
        /// plate (default; the capture itself, consistent at the object's anti-aliased edge),
        /// a random colour per iteration, or the ingest background colour.
        #[serde(default)]
        pub background: Backdrop,
        /// Seed of the view order and of splits.
        #[serde(default)]
        pub seed: u64,
    }

    /// What rendered Gaussians are composited over when fitting (see [`WarmupParams::background`]).
    #[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
    #[serde(rename_all = "snake_case")]
    pub enum Backdrop {
        /// The camera's background plate: the target is the capture inside the object mask
        /// and the plate outside it (the object's shadow is not modelled).
        #[default]
        Plate,
        /// A uniformly random colour per iteration, so no Gaussian can stand in for the
        /// background.
        Random,
        /// The ingest background colour (white by default).
        White,
    }

    fn alpha_weight() -> f64 {
        0.1
    }

    fn frames() -> Vec<u16> {
        vec![0]
    }
    fn epochs() -> u32 {
        200
    }
    fn lambda() -> f64 {
        crate::scene::targets::DEFAULT_LAMBDA
    }
    fn lr_position() -> f32 {
        1.6e-4
    }
    fn lr_position_final() -> f32 {
        1.6e-6
    }
    fn lr_sh() -> f32 {
        2.5e-3
    }
    fn lr_opacity() -> f32 {
        0.05
    }
    fn lr_scale() -> f32 {
        5e-3
    }
    fn lr_rotation() -> f32 {
        1e-3
    }
    fn densify_from() -> f32 {
        0.1
    }
    fn densify_until() -> f32 {
        0.6
    }
    fn densify_every() -> u32 {
        100
    }
    fn grad_threshold() -> f32 {
        2e-4
    }
    fn opacity_reset_every() -> u32 {
        3000
    }
    fn max_gaussians() -> u32 {
        200_000
    }
}

/// Problems specific to warmup.
#[derive(Debug, thiserror::Error)]
pub enum WarmupError {
    /// Reading an upstream table failed.
    #[error(transparent)]
    Table(#[from] table::TableError),
    /// Reading or writing an image failed.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// The rasterizer refused its input.
    #[error("rendering view {view} frame {frame}: {source}")]
    Render {
        /// Camera.
        view: u16,
        /// Frame.
        frame: u16,
        /// Why.
        source: pipe_render::RenderError,
    },
    /// The loss refused its input.
    #[error("loss: {0}")]
    Loss(#[from] pipe_loss::LossError),
    /// A non-finite value appeared.
    #[error(
        "non-finite {quantity} at epoch {epoch}, iteration {iteration} (view {view}, frame {frame}); lower stages.warmup.lr_position or lr_scale and re-run"
    )]
    NonFinite {
        /// What became NaN/Inf.
        quantity: &'static str,
        /// Epoch (0-based).
        epoch: u32,
        /// Iteration (1-based).
        iteration: u32,
        /// Camera.
        view: u16,
        /// Frame.
        frame: u16,
    },
    /// The inputs cannot be trained on.
    #[error("{0}")]
    Invalid(String),
}

/// The `warmup` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Warmup;

/// A training or test image in memory.
struct Target {
    row: FrameRow,
    camera: pipe_render::Camera<f32>,
    /// The object composited over the ingest background colour, RGB in [0, 1].
    pixels: Vec<f32>,
    /// Object mask in [0, 1].
    mask: Vec<f32>,
    /// The camera's background plate, RGB in [0, 1], when the capture has one.
    plate: Option<Vec<f32>>,
}

impl Target {
    /// The capture with everything outside the object mask replaced by `backdrop`
    /// (3 values per pixel): `m·image + (1 − m)·backdrop`.
    fn over(&self, backdrop: &[f32]) -> Vec<f32> {
        self.pixels
            .chunks_exact(3)
            .zip(&self.mask)
            .zip(backdrop.chunks_exact(3))
            .flat_map(|((px, m), b)| [0, 1, 2].map(|c| m * px[c] + (1.0 - m) * b[c]))
            .collect()
    }
}

fn to_unit(v: &[u8]) -> Vec<f32> {
    v.iter().map(|v| f32::from(*v) / 255.0).collect()
}

fn load_targets(dir: &Path, rows: &[&FrameRow]) -> Result<Vec<Target>, StageError> {
    rows.iter()
        .map(|r| {
            let img = image::read_rgb8(&dir.join(&r.image)).map_err(StageError::failed)?;
            let (_, _, mask) = image::read_gray8(&dir.join(&r.mask)).map_err(StageError::failed)?;
            let plate = match &r.plate {
                Some(rel) => {
                    let pl = image::read_rgb8(&dir.join(rel)).map_err(StageError::failed)?;
                    if (pl.width, pl.height) != (img.width, img.height) {
                        return Err(StageError::failed(WarmupError::Invalid(format!(
                            "{}: plate is {}×{}, image {} is {}×{}",
                            dir.join(rel).display(),
                            pl.width,
                            pl.height,
                            r.image,
                            img.width,
                            img.height
                        ))));
                    }
                    Some(to_unit(&pl.data))
                }
                None => None,
            };
            Ok(Target {
                row: (*r).clone(),
                camera: splat::render_camera(&Camera::from_row(r)),
                pixels: to_unit(&img.data),
                mask: to_unit(&mask),
                plate,
            })
        })
        .collect()
}

/// The rendered object (rendered over black) composited over a per-pixel backdrop:
/// `I = C + (1 − α)·B`.
fn composite(out: &pipe_render::Rendered<f32>, backdrop: &[f32]) -> Vec<f32> {
    out.image
        .iter()
        .zip(&out.alpha)
        .zip(backdrop.chunks_exact(3))
        .flat_map(|((c, a), b)| [0, 1, 2].map(|k| c[k] + (1.0 - a) * b[k]))
        .collect()
}

/// ∂L/∂α contributed by the backdrop term of [`composite`]: `−Σ_c ∂L/∂I_c · B_c`.
fn backdrop_alpha_grad(d_image: &[[f32; 3]], backdrop: &[f32]) -> impl Iterator<Item = f32> {
    d_image
        .iter()
        .zip(backdrop.chunks_exact(3))
        .map(|(d, b)| -(d[0] * b[0] + d[1] * b[1] + d[2] * b[2]))
}

impl TypedStage for Warmup {
    type Params = WarmupParams;
    const KIND: &'static str = "warmup";
    const VERSION: u32 = 2;
    const DESCRIPTION: &'static str = "Fit the canonical 3D Gaussians to the first frame(s) (3DGS: Adam, L1 + D-SSIM, densification)";
    const UPSTREAM: &'static [&'static str] = &["ingest", "init"];

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![(Gaussians::NAME, Gaussians::VERSION)]
    }

    /// The captures and ground-truth masks of the fitted frames, when the scene has such
    /// masks: the views are also scored against them (`*_psnr_gtmask`).
    fn inputs(&self, p: &WarmupParams, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError> {
        let files = gt_mask::files(&p.frames, scene).map_err(StageError::failed)?;
        Ok(files
            .into_iter()
            .flat_map(|f| [f.capture, f.mask])
            .collect())
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            Preset::Draft => json!({"epochs": 100, "densify_every": 50, "max_gaussians": 30000}),
            Preset::Standard => json!({"epochs": 400, "densify_every": 100}),
            Preset::Paper => json!({"epochs": 3000, "densify_every": 100}),
        }
    }

    fn validate(&self, p: &WarmupParams) -> Result<(), ParamError> {
        let bad = |path: &str, message: String| {
            Err(ParamError {
                path: path.into(),
                message,
            })
        };
        if p.frames.is_empty() {
            return bad("frames", "needs at least one frame".into());
        }
        if p.epochs == 0 {
            return bad("epochs", "must be at least 1".into());
        }
        if !(0.0..=1.0).contains(&p.lambda) {
            return bad("lambda", format!("must be in [0, 1], found {}", p.lambda));
        }
        for (name, v) in [
            ("lr_position", p.lr_position),
            ("lr_position_final", p.lr_position_final),
            ("lr_sh", p.lr_sh),
            ("lr_opacity", p.lr_opacity),
            ("lr_scale", p.lr_scale),
            ("lr_rotation", p.lr_rotation),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, format!("must be finite and >= 0, found {v}"));
            }
        }
        if !(0.0..=1.0).contains(&p.densify_from)
            || !(p.densify_from..=1.0).contains(&p.densify_until)
        {
            return bad(
                "densify_until",
                format!(
                    "need 0 <= densify_from ({}) <= densify_until ({}) <= 1",
                    p.densify_from, p.densify_until
                ),
            );
        }
        if p.densify_every == 0 {
            return bad("densify_every", "must be at least 1".into());
        }
        Ok(())
    }

    fn run(&self, p: &WarmupParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let ingest = ctx.upstream("ingest")?.clone();
        let background: [f32; 3] =
            serde_json::from_value(ingest.manifest.key_material.params["background"].clone())
                .unwrap_or([1.0, 1.0, 1.0]);
        let frames: Frames =
            table::read(&ingest.dir.join("frames.arrow")).map_err(StageError::failed)?;
        let mut g: Gaussians = table::read(&ctx.upstream("init")?.dir.join("gaussians.arrow"))
            .map_err(StageError::failed)?;
        if g.is_empty() {
            return Err(StageError::failed(WarmupError::Invalid(
                "init produced no Gaussians".into(),
            )));
        }
        let pick = |role: Role| -> Vec<&FrameRow> {
            frames
                .rows
                .iter()
                .filter(|r| r.role == role && p.frames.contains(&r.frame))
                .collect()
        };
        let train = load_targets(&ingest.dir, &pick(Role::Train))?;
        let test = load_targets(&ingest.dir, &pick(Role::Test))?;
        if train.is_empty() {
            return Err(StageError::failed(WarmupError::Invalid(format!(
                "stages.warmup.frames {:?}: no training image (frames available: 0..{})",
                p.frames,
                frames.rows.iter().map(|r| r.frame).max().unwrap_or(0)
            ))));
        }

        // Scene extent as in 3DGS: radius of the camera centres around their mean, × 1.1.
        let centres: Vec<glam::DVec3> = train
            .iter()
            .map(|t| Camera::from_row(&t.row).centre_world)
            .collect();
        let mean = centres.iter().sum::<glam::DVec3>() / centres.len() as f64;
        let extent = (centres
            .iter()
            .map(|c| (*c - mean).length())
            .fold(0.0, f64::max)
            * 1.1)
            .max(1e-3) as f32;

        if p.background == Backdrop::Plate
            && let Some(t) = train.iter().chain(&test).find(|t| t.plate.is_none())
        {
            return Err(StageError::failed(WarmupError::Invalid(format!(
                "stages.warmup.background is `plate`, but camera {} of this capture has no background plate; use `random` or `white`",
                t.row.view
            ))));
        }
        // Gaussians are rendered over black and composited over a per-pixel backdrop.
        let opts = pipe_render::RenderOptions {
            background: [0.0; 3],
            ..Default::default()
        };
        let iters_per_epoch = train.len() as u32;
        let total = p.epochs * iters_per_epoch;
        let densify_from = (p.densify_from * total as f32) as u32;
        let densify_until = (p.densify_until * total as f32) as u32;
        let cfg = AdamConfig::default();
        let mut states = GroupStates::new(&g);
        let mut stats = DensityStats::new(g.len());
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(p.seed);
        let k = g.sh.len() / g.len();
        let (w, h) = (train[0].row.width as usize, train[0].row.height as usize);
        let mut order: Vec<usize> = (0..train.len()).collect();
        let mut t = 0u32;
        ctx.progress.start("epoch", u64::from(p.epochs));
        for epoch in 0..p.epochs {
            ctx.check_interrupted()?;
            order.shuffle(&mut rng);
            let (mut loss_sum, mut psnr_sum) = (0.0f64, 0.0f64);
            for &vi in &order {
                t += 1;
                let target = &train[vi];
                let (view, frame) = (target.row.view, target.row.frame);
                let nonfinite = |quantity| {
                    StageError::failed(WarmupError::NonFinite {
                        quantity,
                        epoch,
                        iteration: t,
                        view,
                        frame,
                    })
                };
                let rg = splat::render_gaussians(&g);
                let backdrop: Vec<f32> = match p.background {
                    Backdrop::Plate => target.plate.clone().expect("checked before training"),
                    Backdrop::Random => {
                        let c: [f32; 3] = [rng.random(), rng.random(), rng.random()];
                        c.repeat(w * h)
                    }
                    Backdrop::White => background.repeat(w * h),
                };
                let target_pixels = target.over(&backdrop);
                let out = pipe_render::render(&rg, &target.camera, &opts).map_err(|source| {
                    StageError::failed(WarmupError::Render {
                        view,
                        frame,
                        source,
                    })
                })?;
                let composited = composite(&out, &backdrop);
                let rendered = pipe_loss::Image::new("render", &composited, w, h)
                    .map_err(StageError::failed)?;
                let gt = pipe_loss::Image::new("target", &target_pixels, w, h)
                    .map_err(StageError::failed)?;
                let (mut loss, d_image) =
                    pipe_loss::l1_dssim(rendered, gt, p.lambda).map_err(StageError::failed)?;
                // Silhouette term: w·mean|α − mask|, gradient w·sign(α − mask)/n.
                let (d_image, _) = d_image.as_chunks::<3>();
                let mut d_alpha: Vec<f32> = backdrop_alpha_grad(d_image, &backdrop).collect();
                if p.alpha_weight > 0.0 {
                    let n = out.alpha.len() as f64;
                    let wgt = (p.alpha_weight / n) as f32;
                    loss += p.alpha_weight
                        * out
                            .alpha
                            .iter()
                            .zip(&target.mask)
                            .map(|(a, m)| f64::from((a - m).abs()))
                            .sum::<f64>()
                        / n;
                    for ((d, a), m) in d_alpha.iter_mut().zip(&out.alpha).zip(&target.mask) {
                        *d += wgt * (a - m).signum();
                    }
                }
                if !loss.is_finite() {
                    return Err(nonfinite("loss"));
                }
                loss_sum += loss;
                psnr_sum += pipe_loss::psnr(rendered, gt).map_err(StageError::failed)?;
                let grads = pipe_render::backward(
                    &rg,
                    &target.camera,
                    &opts,
                    &out,
                    d_image,
                    Some(&d_alpha),
                )
                .map_err(|source| {
                    StageError::failed(WarmupError::Render {
                        view,
                        frame,
                        source,
                    })
                })?;
                for (name, ok) in [
                    (
                        "gradient of positions",
                        grads.means.as_flattened().iter().all(|v| v.is_finite()),
                    ),
                    (
                        "gradient of log-scales",
                        grads
                            .log_scales
                            .as_flattened()
                            .iter()
                            .all(|v| v.is_finite()),
                    ),
                    (
                        "gradient of rotations",
                        grads.quats.as_flattened().iter().all(|v| v.is_finite()),
                    ),
                    (
                        "gradient of opacities",
                        grads.opacity_logits.iter().all(|v| v.is_finite()),
                    ),
                    (
                        "gradient of SH",
                        grads.sh.as_flattened().iter().all(|v| v.is_finite()),
                    ),
                ] {
                    if !ok {
                        return Err(nonfinite(name));
                    }
                }
                // Densification statistics.
                if t < densify_until {
                    let radius: Vec<f32> =
                        out.projected.iter().map(|pg| pg.radius as f32).collect();
                    stats.add(&grads.means2d, &radius, w as u32, h as u32);
                }
                // Adam steps.
                let progress = t as f32 / total.max(1) as f32;
                let lr_pos = p.lr_position
                    * (p.lr_position_final / p.lr_position.max(1e-30)).powf(progress)
                    * extent;
                let lr_pos = if p.lr_position == 0.0 { 0.0 } else { lr_pos };
                states.position.step(
                    &cfg,
                    t,
                    g.position.as_flattened_mut(),
                    grads.means.as_flattened(),
                    |_| lr_pos,
                );
                states.log_scale.step(
                    &cfg,
                    t,
                    g.log_scale.as_flattened_mut(),
                    grads.log_scales.as_flattened(),
                    |_| p.lr_scale,
                );
                states.rotation.step(
                    &cfg,
                    t,
                    g.rotation.as_flattened_mut(),
                    grads.quats.as_flattened(),
                    |_| p.lr_rotation,
                );
                states
                    .opacity
                    .step(&cfg, t, &mut g.opacity_logit, &grads.opacity_logits, |_| {
                        p.lr_opacity
                    });
                let lr_sh = p.lr_sh;
                states
                    .sh
                    .step(&cfg, t, &mut g.sh, grads.sh.as_flattened(), |j| {
                        if j < 3 { lr_sh } else { lr_sh / 20.0 }
                    });
                if g.position.as_flattened().iter().any(|v| !v.is_finite()) {
                    return Err(nonfinite("position after the Adam step"));
                }
                // Density control.
                if t >= densify_from && t < densify_until && t.is_multiple_of(p.densify_every) {
                    let dcfg = DensifyConfig {
                        grad_threshold: p.grad_threshold,
                        percent_dense: 0.01,
                        min_opacity: 0.005,
                        max_screen_radius: if t > p.opacity_reset_every && p.opacity_reset_every > 0
                        {
                            20.0
                        } else {
                            0.0
                        },
                        max_world_scale: 0.1,
                        extent,
                        max_gaussians: p.max_gaussians as usize,
                    };
                    density::densify(&mut g, &mut states, &stats, &dcfg, &mut rng);
                    stats = DensityStats::new(g.len());
                }
                if p.opacity_reset_every > 0
                    && t.is_multiple_of(p.opacity_reset_every)
                    && t < densify_until
                {
                    density::reset_opacity(&mut g, &mut states, 0.01);
                }
            }
            let n = f64::from(iters_per_epoch);
            ctx.progress.message(&format!(
                "loss {:.4}  psnr {:.2} dB  {} Gaussians",
                loss_sum / n,
                psnr_sum / n,
                g.len()
            ));
            ctx.progress.inc(1);
            for (metric, value) in [
                ("loss", loss_sum / n),
                ("train_psnr", psnr_sum / n),
                ("gaussians", g.len() as f64),
            ] {
                ctx.metric(MetricRow {
                    epoch: Some(epoch),
                    view: None,
                    frame: None,
                    metric: metric.into(),
                    value,
                });
            }
        }
        debug_assert_eq!(g.sh.len(), g.len() * k);

        // Held-out views (and the training views, for reference). The score compares the
        // render composited over the camera's plate with the capture (the object's shadow
        // excluded); `*_psnr_solid` compares the render on the ingest background colour with
        // the composited image; `*_psnr_gtmask` compares the same render with the capture
        // inside the ground-truth mask, where the scene has one (a matting error costs there).
        std::fs::create_dir_all(ctx.out_dir.join("renders")).map_err(StageError::failed)?;
        let rg = splat::render_gaussians(&g);
        let solid = background.repeat(w * h);
        let gt_files = gt_mask::files(&p.frames, ctx.scene).map_err(StageError::failed)?;
        let mut summary = Vec::new();
        for (set, targets) in [("test", &test), ("train", &train)] {
            let (mut psnr_sum, mut ssim_sum, mut solid_sum) = (0.0, 0.0, 0.0);
            let mut gtmask = Vec::new();
            for target in targets.iter() {
                let (view, frame) = (target.row.view, target.row.frame);
                let out = pipe_render::render(&rg, &target.camera, &opts).map_err(|source| {
                    StageError::failed(WarmupError::Render {
                        view,
                        frame,
                        source,
                    })
                })?;
                let backdrop = target.plate.as_deref().unwrap_or(&solid);
                let over = composite(&out, backdrop);
                let truth = target.over(backdrop);
                let on_solid = composite(&out, &solid);
                let img = |name, px| pipe_loss::Image::new(name, px, w, h);
                let (rendered, gt) = (
                    img("render", &over).map_err(StageError::failed)?,
                    img("target", &truth).map_err(StageError::failed)?,
                );
                let psnr = pipe_loss::psnr(rendered, gt).map_err(StageError::failed)?;
                let ssim = pipe_loss::ssim(rendered, gt).map_err(StageError::failed)?;
                let psnr_solid = pipe_loss::psnr(
                    img("render", &on_solid).map_err(StageError::failed)?,
                    img("target", &target.pixels).map_err(StageError::failed)?,
                )
                .map_err(StageError::failed)?;
                psnr_sum += psnr;
                ssim_sum += ssim;
                solid_sum += psnr_solid;
                let mut scores = vec![
                    (format!("{set}_psnr"), psnr),
                    (format!("{set}_ssim"), ssim),
                    (format!("{set}_psnr_solid"), psnr_solid),
                ];
                if let Some(f) = gt_files.iter().find(|f| (f.view, f.frame) == (view, frame)) {
                    let truth_gt = gt_mask::target(f, w as u32, h as u32, backdrop)
                        .map_err(|e| StageError::failed(WarmupError::Invalid(e)))?;
                    let psnr_gt = pipe_loss::psnr(
                        rendered,
                        img("target", &truth_gt).map_err(StageError::failed)?,
                    )
                    .map_err(StageError::failed)?;
                    gtmask.push(psnr_gt);
                    scores.push((format!("{set}_psnr_gtmask"), psnr_gt));
                }
                for (metric, value) in scores {
                    ctx.metric(MetricRow {
                        epoch: None,
                        view: Some(view),
                        frame: Some(frame),
                        metric,
                        value,
                    });
                }
                if set == "test" {
                    let rgb8 = |px: &[f32]| Rgb8 {
                        width: w as u32,
                        height: h as u32,
                        data: px
                            .iter()
                            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                            .collect(),
                    };
                    let (render, object) = (rgb8(&over), rgb8(&on_solid));
                    let side = image::compare_strip(&rgb8(&truth).data, &render.data, w, h);
                    for (name, picture) in [
                        (format!("test_v{view}_f{frame}.png"), &render),
                        (format!("object_v{view}_f{frame}.png"), &object),
                        (format!("compare_v{view}_f{frame}.png"), &side),
                    ] {
                        image::write_rgb8(&ctx.out_dir.join("renders").join(name), picture)
                            .map_err(StageError::failed)?;
                    }
                }
            }
            if !targets.is_empty() {
                let n = targets.len() as f64;
                let mut means = vec![
                    (format!("{set}_psnr_mean"), psnr_sum / n),
                    (format!("{set}_ssim_mean"), ssim_sum / n),
                    (format!("{set}_psnr_solid_mean"), solid_sum / n),
                ];
                let mut line = format!(
                    "{set} PSNR {:.2} dB, SSIM {:.4} over the plate, {:.2} dB on the solid background",
                    psnr_sum / n,
                    ssim_sum / n,
                    solid_sum / n
                );
                if !gtmask.is_empty() {
                    let mean = gtmask.iter().sum::<f64>() / gtmask.len() as f64;
                    means.push((format!("{set}_psnr_gtmask_mean"), mean));
                    line += &format!(", {mean:.2} dB against the ground-truth mask");
                    if gtmask.len() != targets.len() {
                        line += &format!(" ({} of them)", gtmask.len());
                    }
                }
                summary.push(format!("{line} ({} views)", targets.len()));
                for (metric, value) in means {
                    ctx.metric(MetricRow {
                        epoch: None,
                        view: None,
                        frame: None,
                        metric,
                        value,
                    });
                }
            }
        }
        ctx.progress
            .log(&format!("{} Gaussians; {}", g.len(), summary.join("; ")));
        table::write(&ctx.out_dir.join("gaussians.arrow"), &g).map_err(StageError::failed)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Means, log-scales, quaternions, opacity logits and RGB of a few Gaussians.
    type Scene = (
        Vec<[f32; 3]>,
        Vec<[f32; 3]>,
        Vec<[f32; 4]>,
        Vec<f32>,
        Vec<[f32; 3]>,
    );

    /// Three overlapping Gaussians in front of the camera below.
    fn scene() -> Scene {
        (
            vec![[0.0, 0.0, 3.0], [0.2, -0.1, 3.5], [-0.3, 0.2, 2.8]],
            vec![[-1.5, -1.8, -1.6], [-1.7, -1.4, -1.9], [-1.6, -1.6, -1.6]],
            vec![
                [1.0, 0.0, 0.0, 0.0],
                [0.9, 0.3, 0.1, 0.0],
                [0.8, 0.0, 0.5, 0.2],
            ],
            vec![0.5, 1.5, -0.2],
            vec![[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]],
        )
    }

    fn camera() -> pipe_render::Camera<f32> {
        let eye = |r: usize, c: usize| if r == c { 1.0 } else { 0.0 };
        pipe_render::Camera {
            camera_from_world_rotation: std::array::from_fn(|r| std::array::from_fn(|c| eye(r, c))),
            camera_from_world_translation: [0.0; 3],
            fx: 30.0,
            fy: 30.0,
            cx: 12.0,
            cy: 10.0,
            width: 24,
            height: 20,
            near: 0.01,
        }
    }

    /// `composite` and `backdrop_alpha_grad` against the renderer's own background term
    /// (tested there against finite differences): for a constant backdrop B, rendering over
    /// black and compositing must equal rendering over B, in value and in every gradient.
    #[test]
    fn backdrop_composite_and_its_alpha_gradient_match_the_renderer_background() {
        let (means, log_scales, quats, logits, rgb) = scene();
        let g = pipe_render::Gaussians {
            means: &means,
            scales: pipe_render::Scales::Log(&log_scales),
            quats: &quats,
            opacities: pipe_render::Opacities::Logit(&logits),
            colors: pipe_render::Colors::Rgb(&rgb),
            deformation: None,
        };
        let cam = camera();
        let b = [0.3f32, 0.6, 0.9];
        let n = (cam.width * cam.height) as usize;
        let backdrop = b.repeat(n);
        let black = pipe_render::RenderOptions {
            background: [0.0; 3],
            ..Default::default()
        };
        let over_b = pipe_render::RenderOptions {
            background: b,
            ..Default::default()
        };
        let out0 = pipe_render::render(&g, &cam, &black).unwrap();
        let out_b = pipe_render::render(&g, &cam, &over_b).unwrap();
        let ours = composite(&out0, &backdrop);
        for (x, y) in ours.iter().zip(out_b.image.as_flattened()) {
            assert!((x - y).abs() < 1e-6, "{x} vs {y}");
        }
        assert!(
            out0.alpha.iter().any(|a| *a > 0.5),
            "the Gaussians cover pixels"
        );
        let d_image: Vec<[f32; 3]> = (0..n)
            .map(|i| [0, 1, 2].map(|c| ((i * 7 + c * 3) % 11) as f32 / 11.0 - 0.5))
            .collect();
        let d_alpha: Vec<f32> = backdrop_alpha_grad(&d_image, &backdrop).collect();
        let ga = pipe_render::backward(&g, &cam, &black, &out0, &d_image, Some(&d_alpha)).unwrap();
        let gb = pipe_render::backward(&g, &cam, &over_b, &out_b, &d_image, None).unwrap();
        let close = |a: &[f32], b: &[f32], what: &str| {
            let scale = b.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() <= 1e-5 * scale, "{what}: {x} vs {y}");
            }
        };
        close(ga.means.as_flattened(), gb.means.as_flattened(), "means");
        close(
            ga.log_scales.as_flattened(),
            gb.log_scales.as_flattened(),
            "log-scales",
        );
        close(
            ga.quats.as_flattened(),
            gb.quats.as_flattened(),
            "quaternions",
        );
        close(&ga.opacity_logits, &gb.opacity_logits, "opacity logits");
        close(
            ga.colors.as_flattened(),
            gb.colors.as_flattened(),
            "colours",
        );
        assert!(
            gb.opacity_logits.iter().any(|v| v.abs() > 1e-4),
            "non-trivial gradients"
        );
    }

    #[test]
    fn the_target_is_the_capture_inside_the_mask_and_the_backdrop_outside() {
        let t = Target {
            row: FrameRow {
                view: 0,
                frame: 0,
                time_s: 0.0,
                world_from_camera: [0.0; 12],
                fx: 1.0,
                fy: 1.0,
                cx: 1.0,
                cy: 0.5,
                width: 2,
                height: 1,
                image: String::new(),
                mask: String::new(),
                plate: None,
                role: Role::Train,
            },
            camera: camera(),
            pixels: vec![0.1, 0.2, 0.3, 1.0, 1.0, 1.0],
            mask: vec![1.0, 0.0],
            plate: None,
        };
        assert_eq!(
            t.over(&[0.5, 0.5, 0.5, 0.4, 0.5, 0.6]),
            vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
        );
    }
}
