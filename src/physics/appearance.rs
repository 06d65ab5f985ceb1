//! The canonical Gaussians' colours refitted along the learned motion.
//!
//! The warm-up learns the colours from frame 0 alone, where the capture's cameras (all above
//! the ground) barely see the side the object rests on or faces away with; once the learned
//! motion turns the body, that side shows with the colours of a side no camera saw. With the
//! motion fixed (the rollout's pose of every Gaussian at every frame), the colours — SH
//! coefficients, nothing of the geometry — are fitted to the training views of every frame by
//! Adam on the stages' image loss (`λ·L1 + (1 − λ)·D-SSIM` over the plate), one image per step
//! in frame-then-view order, as the warm-up fits frame 0. Re-lighting, when on, is applied
//! inside the fit (a Gaussian's colour at frame `f` is its gain `k_f` times its albedo: the
//! gradient of the albedo's coefficients is `k_f` times theirs), so that the albedo absorbs
//! what the shading model does not and no more.

use pipe_mpm::{State, StateGrad};

use super::object::Object;
use super::pose::Pose;
use super::rollout::{FrameLoss, RolloutError};
use crate::scene::gaussians::{Gaussians, sh_coeffs};
use crate::scene::shading::{Relight, relit_sh};
use crate::scene::splat::render_gaussians_sh;
use crate::scene::targets::{Target, over_black, view_loss};
use crate::stages::warmup::adam::{AdamConfig, AdamState};

/// How the colours are refitted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourFit {
    /// Passes over every training image of every frame.
    pub epochs: u32,
    /// Adam's rate of the DC coefficients (the higher orders take a twentieth, as 3DGS).
    pub lr: f32,
    /// `λ` of `λ·L1 + (1 − λ)·D-SSIM`.
    pub lambda: f64,
}

/// One frame of the motion: the Gaussians' pose and, when re-lit, their colour gains.
#[derive(Debug, Clone)]
pub struct PosedFrame {
    /// Frame index.
    pub frame: u16,
    /// The rendered Gaussians at this frame.
    pub pose: Pose<f32>,
    /// Re-lighting gain per Gaussian (empty: none).
    pub gains: Vec<f32>,
}

/// Records the pose of the object's Gaussians at every frame a rollout reaches.
#[derive(Debug)]
pub struct MotionRecorder<'a> {
    object: &'a Object,
    fluid: bool,
    shading: Option<&'a Relight>,
    /// The frames recorded, in rollout order.
    pub frames: Vec<PosedFrame>,
}

impl<'a> MotionRecorder<'a> {
    /// A recorder for `object` (`fluid`: a Newtonian fluid's pose), re-lit by `shading`.
    pub fn new(object: &'a Object, fluid: bool, shading: Option<&'a Relight>) -> Self {
        Self {
            object,
            fluid,
            shading,
            frames: Vec::new(),
        }
    }

    /// Records `state` as frame `frame`.
    pub fn record(&mut self, frame: u16, state: &State) {
        let gains = self
            .shading
            .map_or_else(Vec::new, |r| r.gains(&self.object.gaussian_f(&state.f)));
        self.frames.push(PosedFrame {
            frame,
            pose: Pose::of(state, self.object.skin(), self.fluid),
            gains,
        });
    }
}

impl FrameLoss for MotionRecorder<'_> {
    fn frame(
        &mut self,
        frame: u16,
        state: &State,
        _grad: Option<&mut StateGrad>,
    ) -> Result<f64, RolloutError> {
        self.record(frame, state);
        Ok(0.0)
    }
}

/// What the refit did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColourFitReport {
    /// Mean image loss over the training images in each epoch (each image scored at the
    /// colours it was rendered with).
    pub epoch_loss: Vec<f64>,
    /// Images fitted per epoch.
    pub images: usize,
}

/// Refits the SH coefficients of the Gaussians `g` (returned, `[gaussian][coeff][channel]`)
/// to the `targets` (training images; those of frames not in `motion` are skipped), each frame
/// posed as `motion` has it. Adam, one image per step in the order frames × targets; the DC
/// rate `fit.lr` (the higher orders a twentieth) decays exponentially to a tenth over the fit.
/// Deterministic whatever the thread count (the rasterizer's backward is).
///
/// # Errors
/// A message naming the frame and view where rendering failed or where the loss or the
/// colours' gradient was not finite.
pub fn refit_colours(
    g: &Gaussians,
    motion: &[PosedFrame],
    targets: &[&Target],
    backdrop: [f32; 3],
    fit: &ColourFit,
) -> Result<(Vec<f32>, ColourFitReport), String> {
    let per = 3 * sh_coeffs(g.sh_degree);
    let mut sh = g.sh.clone();
    let mut report = ColourFitReport::default();
    let images: Vec<(&PosedFrame, &Target, Vec<f32>)> = motion
        .iter()
        .flat_map(|m| {
            targets
                .iter()
                .filter(move |t| t.row.frame == m.frame)
                .map(move |t| (m, *t, t.backdrop(backdrop).into_owned()))
        })
        .collect();
    report.images = images.len();
    if images.is_empty() || fit.epochs == 0 {
        return Ok((sh, report));
    }
    let mut adam = AdamState::new(per, g.len());
    let cfg = AdamConfig::default();
    let steps = images.len() as f64 * f64::from(fit.epochs);
    let mut step = 0u32;
    for _ in 0..fit.epochs {
        let mut total = 0.0;
        for (m, target, plate) in &images {
            let (loss, grad) = image_loss(g, &sh, m, target, plate, fit.lambda, true)?;
            let grad = grad.expect("asked for");
            total += loss;
            let lr = fit.lr * 0.1f32.powf((f64::from(step) / steps) as f32);
            step += 1;
            adam.step(&cfg, step, &mut sh, &grad, |j| {
                if j < 3 { lr } else { lr / 20.0 }
            });
        }
        report.epoch_loss.push(total / images.len() as f64);
    }
    Ok((sh, report))
}

/// Mean image loss of the colours `sh` over the `targets` of the frames in `motion` (`None`
/// when no target is of those frames): how a refit is judged on views it did not fit.
///
/// # Errors
/// As [`refit_colours`].
pub fn mean_loss(
    g: &Gaussians,
    sh: &[f32],
    motion: &[PosedFrame],
    targets: &[&Target],
    backdrop: [f32; 3],
    lambda: f64,
) -> Result<Option<f64>, String> {
    let (mut total, mut n) = (0.0, 0usize);
    for m in motion {
        for t in targets.iter().filter(|t| t.row.frame == m.frame) {
            let plate = t.backdrop(backdrop);
            total += image_loss(g, sh, m, t, &plate, lambda, false)?.0;
            n += 1;
        }
    }
    Ok((n > 0).then(|| total / n as f64))
}

/// The loss of one image with the albedo coefficients `sh` posed as `m` has it and, with
/// `gradient`, its gradient with respect to `sh`.
fn image_loss(
    g: &Gaussians,
    sh: &[f32],
    m: &PosedFrame,
    target: &Target,
    plate: &[f32],
    lambda: f64,
    gradient: bool,
) -> Result<(f64, Option<Vec<f32>>), String> {
    let (frame, view) = (m.frame, target.row.view);
    let fail = |what: String| format!("refitting the colours, frame {frame} view {view}: {what}");
    let per = 3 * sh_coeffs(g.sh_degree);
    let shown = (!m.gains.is_empty()).then(|| relit_sh(sh, g.sh_degree, &m.gains));
    let posed = m
        .pose
        .apply(render_gaussians_sh(g, shown.as_deref().unwrap_or(sh)));
    let opts = over_black();
    let out =
        pipe_render::render(&posed, &target.camera, &opts).map_err(|e| fail(e.to_string()))?;
    let l = view_loss(&out, target, plate, lambda, 0.0).map_err(|e| fail(e.to_string()))?;
    if !l.loss.is_finite() {
        return Err(fail(format!("the loss is {}", l.loss)));
    }
    if !gradient {
        return Ok((l.loss, None));
    }
    let gr = pipe_render::backward(&posed, &target.camera, &opts, &out, &l.d_image, None)
        .map_err(|e| fail(e.to_string()))?;
    let mut grad = gr.sh.as_flattened().to_vec();
    if grad.len() != sh.len() {
        return Err(fail(format!(
            "{} colour gradients for {}",
            grad.len(),
            sh.len()
        )));
    }
    // Shown = gain · albedo (+ a constant): the albedo's gradient is gain times.
    for (row, k) in grad.chunks_mut(per).zip(&m.gains) {
        row.iter_mut().for_each(|v| *v *= k);
    }
    if let Some(i) = grad.iter().position(|v| !v.is_finite()) {
        return Err(fail(format!(
            "non-finite colour gradient of Gaussian {}",
            i / per
        )));
    }
    Ok((l.loss, Some(grad)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::Camera;
    use crate::scene::frames::{FrameRow, Role};
    use crate::scene::splat::render_camera;
    use crate::scene::targets::composite;
    use glam::DVec3;
    use pipe_mpm::State;

    /// A camera at `eye` looking at the origin (OpenCV axes), 48×48 px.
    fn row(view: u16, frame: u16, eye: DVec3) -> FrameRow {
        let fwd = (-eye).normalize();
        let right = fwd.cross(DVec3::Y).normalize();
        let down = fwd.cross(right);
        let r = glam::DMat3::from_cols(right, down, fwd);
        let mut m = [0.0; 12];
        for i in 0..3 {
            for j in 0..3 {
                m[4 * i + j] = r.col(j)[i];
            }
            m[4 * i + 3] = eye[i];
        }
        FrameRow {
            view,
            frame,
            time_s: f64::from(frame) / 24.0,
            world_from_camera: m,
            fx: 60.0,
            fy: 60.0,
            cx: 24.0,
            cy: 24.0,
            width: 48,
            height: 48,
            image: String::new(),
            mask: String::new(),
            plate: None,
            role: Role::Train,
        }
    }

    /// Six round Gaussians on a ring (degree-0 SH: DC only), `albedo` giving their colours.
    fn ring(albedo: &[[f32; 3]]) -> Gaussians {
        let n = albedo.len();
        let position: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                let a = std::f32::consts::TAU * i as f32 / n as f32;
                [0.3 * a.cos(), 0.0, 0.3 * a.sin()]
            })
            .collect();
        Gaussians {
            sh_degree: 0,
            id: (0..n as u32).collect(),
            position,
            log_scale: vec![[(0.08f32).ln(); 3]; n],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacity_logit: vec![4.0; n],
            sh: albedo.iter().flatten().copied().collect(),
            simulated: vec![true; n],
        }
    }

    /// The ring turned by `turn` radians about y at frame `frame` (the gains per Gaussian).
    fn posed(g: &Gaussians, frame: u16, turn: f64, gains: Vec<f32>) -> PosedFrame {
        let q = glam::DMat3::from_rotation_y(turn);
        let x: Vec<DVec3> = g
            .position
            .iter()
            .map(|p| q * DVec3::new(p[0].into(), p[1].into(), p[2].into()))
            .collect();
        let mut s = State::at_rest(x);
        s.f.iter_mut().for_each(|f| *f = q);
        PosedFrame {
            frame,
            pose: Pose::of(&s, &crate::simulate::skin::Skin::identity(g.len()), false),
            gains,
        }
    }

    /// Targets rendered from the true colours (each frame's gains applied) by two cameras,
    /// over white, with a full mask (the target is then exactly what a render can match).
    fn targets(truth: &Gaussians, motion: &[PosedFrame]) -> Vec<Target> {
        let mut out = Vec::new();
        for m in motion {
            let sh = if m.gains.is_empty() {
                truth.sh.clone()
            } else {
                relit_sh(&truth.sh, 0, &m.gains)
            };
            let base = render_gaussians_sh(truth, &sh);
            for (view, eye) in [
                (0u16, DVec3::new(0.0, 0.6, 1.4)),
                (1, DVec3::new(1.2, 0.5, -0.6)),
            ] {
                let row = row(view, m.frame, eye);
                let camera = render_camera(&Camera::from_row(&row));
                let r = pipe_render::render(&m.pose.apply(base), &camera, &over_black()).unwrap();
                assert!(
                    r.alpha.iter().any(|a| *a > 0.5),
                    "view {view} sees the ring"
                );
                out.push(Target {
                    pixels: composite(&r, &[1.0; 3].repeat(48 * 48)),
                    mask: vec![1.0; 48 * 48],
                    plate: None,
                    camera,
                    row,
                });
            }
        }
        out
    }

    /// Colours of six Gaussians, the second half brighter.
    fn truth() -> Gaussians {
        ring(&[
            [0.8, -0.6, 0.1],
            [-0.9, 0.4, 0.6],
            [0.2, 0.9, -0.8],
            [1.1, 0.3, -0.2],
            [-0.4, -0.7, 0.9],
            [0.5, 0.5, 0.5],
        ])
    }

    #[test]
    fn the_albedo_gradient_matches_finite_differences_with_gains() {
        let truth = truth();
        let motion = [posed(&truth, 1, 0.7, vec![1.6, 0.6, 1.0, 1.3, 0.8, 1.1])];
        let t = targets(&truth, &motion);
        let start = ring(&[[0.1, 0.2, -0.1]; 6]);
        let plate = [1.0f32; 3].repeat(48 * 48);
        let loss =
            |sh: &[f32], gradient| image_loss(&start, sh, &motion[0], &t[0], &plate, 0.2, gradient);
        let (l0, grad) = loss(&start.sh, true).unwrap();
        let grad = grad.expect("asked for");
        assert!(l0.is_finite() && l0 > 1e-3, "{l0}");
        assert_eq!(grad.len(), start.sh.len());
        let h = 1e-2f32;
        let mut checked = 0;
        for k in 0..grad.len() {
            let mut up = start.sh.clone();
            up[k] += h;
            let mut down = start.sh.clone();
            down[k] -= h;
            let fd =
                (loss(&up, false).unwrap().0 - loss(&down, false).unwrap().0) / f64::from(2.0 * h);
            let an = f64::from(grad[k]);
            if fd.abs() > 1e-4 {
                checked += 1;
            }
            assert!(
                (fd - an).abs() <= 0.03 * fd.abs().max(an.abs()) + 2e-5,
                "coefficient {k}: finite differences {fd}, gradient {an}"
            );
        }
        assert!(checked >= 9, "only {checked} coefficients matter");
    }

    #[test]
    fn colours_are_recovered_from_frames_that_show_them_relit() {
        let truth = truth();
        // Frame 0 shows the ring's front only to view 0 (a Gaussian behind the others from
        // view 1 is seen later); frame 1 turns it a quarter and re-lights half of it.
        let motion = [
            posed(&truth, 0, 0.0, Vec::new()),
            posed(
                &truth,
                1,
                std::f64::consts::FRAC_PI_2,
                vec![1.5, 1.5, 1.5, 0.7, 0.7, 0.7],
            ),
        ];
        let t = targets(&truth, &motion);
        let refs: Vec<&Target> = t.iter().collect();
        let start = ring(&[[0.0; 3]; 6]);
        let fit = ColourFit {
            epochs: 150,
            lr: 0.05,
            lambda: 0.2,
        };
        let (sh, report) = refit_colours(&start, &motion, &refs, [1.0; 3], &fit).unwrap();
        assert_eq!(report.images, 4);
        assert_eq!(report.epoch_loss.len(), 150);
        let (first, last) = (report.epoch_loss[0], *report.epoch_loss.last().unwrap());
        assert!(last < 0.05 * first, "loss {first} -> {last}");
        for (i, (a, b)) in sh.chunks(3).zip(truth.sh.chunks(3)).enumerate() {
            for c in 0..3 {
                // Compare the colours (0.5 + C0·dc), clamped as the rasterizer clamps.
                let colour = |v: f32| (0.5 + 0.282_094_8 * v).clamp(0.0, 1.0);
                assert!(
                    (colour(a[c]) - colour(b[c])).abs() < 0.03,
                    "Gaussian {i} channel {c}: {} vs {}",
                    a[c],
                    b[c]
                );
            }
        }
        // The same on one thread.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let (sh1, _) =
            one.install(|| refit_colours(&start, &motion, &refs, [1.0; 3], &fit).unwrap());
        assert_eq!(sh, sh1);
    }

    #[test]
    fn nothing_to_fit_keeps_the_colours_and_a_non_finite_loss_is_named() {
        let truth = truth();
        let motion = [posed(&truth, 0, 0.0, Vec::new())];
        let t = targets(&truth, &motion);
        let refs: Vec<&Target> = t.iter().collect();
        let fit = ColourFit {
            epochs: 3,
            lr: 0.01,
            lambda: 0.2,
        };
        // No target of the motion's frames.
        let other = [posed(&truth, 5, 0.0, Vec::new())];
        let (sh, report) = refit_colours(&truth, &other, &refs, [1.0; 3], &fit).unwrap();
        assert_eq!((sh, report.images), (truth.sh.clone(), 0));
        assert_eq!(
            mean_loss(&truth, &truth.sh, &other, &refs, [1.0; 3], 0.2),
            Ok(None)
        );
        // The true colours score (almost) nothing on the views they were rendered for.
        let exact = mean_loss(&truth, &truth.sh, &motion, &refs, [1.0; 3], 0.2).unwrap();
        assert!(exact.is_some_and(|l| l < 1e-4), "{exact:?}");
        // A non-finite gain (a broken re-lighting) fails with the frame and view.
        let bad = posed(&truth, 0, 0.0, vec![1.0, 1.0, f32::NAN, 1.0, 1.0, 1.0]);
        let err = refit_colours(&truth, &[bad], &refs, [1.0; 3], &fit).unwrap_err();
        assert!(err.contains("frame 0 view 0"), "{err}");
    }
}
