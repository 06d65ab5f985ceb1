//! The image loss of a simulated frame: the object's Gaussians posed at the frame's state
//! ([`Pose`]), rendered from each of the frame's captured views and compared with the capture
//! ([`crate::scene::targets::view_loss`]: `λ·L1 + (1 − λ)·D-SSIM` over the camera's plate,
//! plus the silhouette term). The frame's loss is the mean over its views; its gradient goes
//! back through the rasterizer and the pose to the particles' `x` and `F`.

use std::collections::BTreeMap;

use pipe_mpm::{State, StateGrad};

use super::object::Object;
use super::pose::Pose;
use super::rollout::{FrameLoss, RolloutError};
use crate::scene::targets::{Target, view_loss};

/// The loss settings of a physics stage (those of `warmup`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossWeights {
    /// `λ` of `λ·L1 + (1 − λ)·D-SSIM`.
    pub lambda: f64,
    /// Weight of the silhouette term `mean|α − mask|`.
    pub alpha_weight: f64,
}

/// The views of each frame, and what their losses were.
pub struct ViewsLoss<'a> {
    object: &'a Object,
    fluid: bool,
    /// Targets by frame, each with its backdrop.
    by_frame: BTreeMap<u16, Vec<(&'a Target, Vec<f32>)>>,
    weights: LossWeights,
    opts: pipe_render::RenderOptions<f32>,
    /// Mean PSNR (dB) of each frame's views at the last evaluation.
    pub psnr: BTreeMap<u16, f64>,
    /// Loss of each (frame, view) at its last evaluation (a view's own loss, not divided by
    /// the frame's view count).
    pub view_loss: super::profile::ViewLosses,
}

impl std::fmt::Debug for ViewsLoss<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ViewsLoss")
            .field("frames", &self.by_frame.keys().collect::<Vec<_>>())
            .finish_non_exhaustive()
    }
}

impl<'a> ViewsLoss<'a> {
    /// The loss of `object` against `targets` (any frames; the background where a capture has
    /// no plate is `solid`).
    pub fn new<'t: 'a>(
        object: &'a Object,
        fluid: bool,
        targets: impl IntoIterator<Item = &'t Target>,
        weights: LossWeights,
        solid: [f32; 3],
    ) -> Self {
        let mut by_frame: BTreeMap<u16, Vec<(&'a Target, Vec<f32>)>> = BTreeMap::new();
        for t in targets {
            by_frame
                .entry(t.row.frame)
                .or_default()
                .push((t, t.backdrop(solid).into_owned()));
        }
        Self {
            object,
            fluid,
            by_frame,
            weights,
            opts: crate::scene::targets::over_black(),
            psnr: BTreeMap::new(),
            view_loss: BTreeMap::new(),
        }
    }

    /// Frames that have views.
    pub fn frames(&self) -> impl Iterator<Item = u16> + '_ {
        self.by_frame.keys().copied()
    }

    /// The mean over frames of [`Self::psnr`] (dB) at their last evaluation (0 before any).
    pub fn mean_psnr(&self) -> f64 {
        self.psnr.values().sum::<f64>() / self.psnr.len().max(1) as f64
    }
}

impl FrameLoss for ViewsLoss<'_> {
    /// `λ·L1 + (1 − λ)·(1 − SSIM)` and `mean|α − mask|` are each ≥ 0.
    fn non_negative(&self) -> bool {
        true
    }

    fn frame(
        &mut self,
        frame: u16,
        state: &State,
        mut grad: Option<&mut StateGrad>,
    ) -> Result<f64, RolloutError> {
        let Some(views) = self.by_frame.get(&frame) else {
            return Ok(0.0);
        };
        let fail = |message: String| RolloutError::Loss { frame, message };
        let pose = Pose::<f32>::of(state, self.object.skin(), self.fluid);
        let g = pose.apply(crate::scene::splat::render_gaussians(
            &self.object.gaussians,
        ));
        let n = views.len() as f64;
        let (mut loss, mut psnr) = (0.0, 0.0);
        for (target, backdrop) in views {
            let view = target.row.view;
            let out = pipe_render::render(&g, &target.camera, &self.opts)
                .map_err(|e| fail(format!("rendering view {view}: {e}")))?;
            let mut l = view_loss(
                &out,
                target,
                backdrop,
                self.weights.lambda,
                self.weights.alpha_weight,
            )
            .map_err(|e| fail(format!("view {view}: {e}")))?;
            if !l.loss.is_finite() {
                return Err(fail(format!("non-finite loss in view {view}")));
            }
            loss += l.loss / n;
            psnr += l.psnr / n;
            self.view_loss.insert((frame, view), l.loss);
            if let Some(grad) = grad.as_deref_mut() {
                // The frame's loss is the mean over its views.
                let s = (1.0 / n) as f32;
                l.d_image.iter_mut().flatten().for_each(|d| *d *= s);
                l.d_alpha.iter_mut().for_each(|d| *d *= s);
                let gr = pipe_render::backward(
                    &g,
                    &target.camera,
                    &self.opts,
                    &out,
                    &l.d_image,
                    Some(&l.d_alpha),
                )
                .map_err(|e| fail(format!("rendering view {view} backward: {e}")))?;
                if gr.means.as_flattened().iter().any(|v| !v.is_finite())
                    || gr.deformation.as_flattened().iter().any(|v| !v.is_finite())
                {
                    return Err(fail(format!(
                        "non-finite gradient of the Gaussians' positions or deformation in \
                         view {view}"
                    )));
                }
                pose.seed(self.object.skin(), &gr, grad);
            }
        }
        self.psnr.insert(frame, psnr);
        Ok(loss)
    }
}
