//! Ground witnesses: do the other views see the ground behind a pixel dimmed as this view sees
//! it?
//!
//! A shadow lies on the ground and dims it by a factor that does not depend on the viewpoint
//! (a diffuse floor), so every view with a clear line of sight to a shadowed ground point sees
//! the same dimming `s = (I + k) / (B + k)` there. A pixel of view `a` that shows an object in
//! front of the ground does not: its dimming is the object's colour over the plate's. For
//! pixel `p`, take the ground points `X_n` of the pixels `n` of its 3×3 block (those not already
//! proven object) and, in every other view `b` that sees `X_p` with no voxel of the hull in
//! between (an occluded witness proves nothing), compare
//! `mean_n |ln s_a(n) − ln s_b(X_n)|` (mean over the block, `ln s` averaged over the channels)
//! with a tolerance `witness_tolerance + witness_noise_factor · spread_b` (`spread_b`: the mean
//! absolute deviation of `ln s_b` over the block, so a noisy dark shadow does not disagree with
//! itself): below it `b` agrees (shadow), above it disagrees. The block compares the
//! dimming's texture, not one value: an object of the shadow's own tone still carries its own
//! texture, while a shadow's dimming is smooth and the plate's texture cancels in the ratio.

use glam::DVec3;

use crate::hull::Hull;
use crate::multiview::View;
use crate::params::MultiViewParams;

/// Counts of the other views that see the ground behind a pixel dimmed the same way, and
/// otherwise.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Witnesses {
    /// Unoccluded views whose dimming agrees.
    pub agree: usize,
    /// Unoccluded views whose dimming differs.
    pub disagree: usize,
}

/// Mean over the channels of `ln((I_c + k) / (B_c + k))` at continuous pixel `(u, v)` of `view`
/// (nearest pixel), if inside the image.
fn log_dimming(view: &View<'_>, u: f64, v: f64, k: f32) -> Option<f32> {
    let (w, h) = (view.image.width(), view.image.height());
    if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
        return None;
    }
    let p = 3 * (v as usize * w + u as usize);
    let (i, b) = (view.image.data(), view.plate.data());
    Some(
        (0..3)
            .map(|c| ((f32::from(i[p + c]) + k) / (f32::from(b[p + c]) + k)).ln())
            .sum::<f32>()
            / 3.0,
    )
}

/// The witnesses of pixel `i` of view `a` (see the module doc): `proven` marks view `a`'s
/// pixels already proven object (left out of the block), `hull` is what may occlude the ground;
/// the ratio offset `k` and the tolerances are `p`'s.
pub(crate) fn witnesses(
    a: usize,
    i: usize,
    views: &[View<'_>],
    proven: &[bool],
    hull: &Hull,
    p: &MultiViewParams,
) -> Witnesses {
    let k = p.view.ratio_offset.max(f32::MIN_POSITIVE);
    let cam = &views[a].camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (x0, y0) = (i % w, i / w);
    let mut out = Witnesses::default();
    if x0 == 0 || y0 == 0 || x0 + 1 >= w || y0 + 1 >= h {
        return out;
    }
    let Some(centre) = cam.ground_point(x0 as f64 + 0.5, y0 as f64 + 0.5) else {
        return out;
    };
    let mut block: Vec<(DVec3, f32)> = Vec::with_capacity(9);
    for y in y0 - 1..=y0 + 1 {
        for x in x0 - 1..=x0 + 1 {
            if proven[y * w + x] {
                continue;
            }
            let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
            let (Some(g), Some(l)) = (cam.ground_point(u, v), log_dimming(&views[a], u, v, k))
            else {
                return out;
            };
            block.push((g, l));
        }
    }
    for (b, vb) in views.iter().enumerate() {
        if b == a || vb.camera.project(centre).is_none() {
            continue;
        }
        // An occluded witness proves nothing; stop short of the ground point, on which the
        // object may rest.
        if hull.blocks(vb.camera.centre_world, centre, 1.5 * hull.voxel) {
            continue;
        }
        let theirs: Option<Vec<f32>> = block
            .iter()
            .map(|(g, _)| {
                vb.camera
                    .project(*g)
                    .and_then(|(u, v, _)| log_dimming(vb, u, v, k))
            })
            .collect();
        let Some(theirs) = theirs else {
            continue;
        };
        let n = block.len() as f32;
        let difference = block
            .iter()
            .zip(&theirs)
            .map(|((_, l), lb)| (lb - l).abs())
            .sum::<f32>()
            / n;
        let mean = theirs.iter().sum::<f32>() / n;
        let spread = theirs.iter().map(|lb| (lb - mean).abs()).sum::<f32>() / n;
        if difference <= p.witness_tolerance + p.witness_noise_factor * spread {
            out.agree += 1;
        } else {
            out.disagree += 1;
        }
    }
    out
}
