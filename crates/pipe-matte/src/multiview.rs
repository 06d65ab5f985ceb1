//! Matting all views of one frame together: the object is where the views agree in 3D.
//!
//! 1. Each view is classified against its plate (`score.rs`): unchanged, shadow-like, object.
//! 2. Ground test: a shadow lies on the ground y = 0 and darkens it for every camera. For a
//!    shadow-like pixel of view A, take the ground point X its ray meets; if another view sees
//!    X unchanged (its 3×3 neighbourhood around X's projection all unchanged), X is lit, so
//!    the pixel's darkening is not a shadow on X: something between camera A and X — the
//!    object — was seen. Such pixels become object.
//!    Reach test (`reach.rs`): a shadow-like pixel whose ray meets the hull of the other views'
//!    changed pixels `witness_min_height` voxels above the ground, and whose ground point lies
//!    out of reach of the object's shadow (farther from every column of the hull of all changed
//!    pixels than its height times `tan(shadow_max_zenith_deg)`), is object: the dark object
//!    against distant floor that no other camera sees.
//! 3. Photo-consistency (`photo_rounds` rounds): for a pixel still ambiguous (shadow-like and
//!    not proven, or unchanged: an object the colour of the plate behind it), take the point
//!    `P` where its ray first meets the visual hull of the *other* views' changed pixels. If
//!    at least `support_views` other views see at `P` a pixel already proven object, of the
//!    same colour within `photo_tolerance` levels per channel, the pixel is object: the object
//!    is there and looks the same from both sides. (A shadow or the floor seen through a hole
//!    is not: the views that see an object at `P` see it in another colour, and the views that
//!    see `P`'s colour see floor, not proven object.)
//! 4. Each view's mask is cleaned up as in the single-view [`crate::matte`]; with
//!    `cut_rounds > 0` a graph cut per view then refines the masks (`refine.rs`).
//! 5. Agreement: per view, the visual hull of the other views' masks (a voxel may miss
//!    `hull_max_misses` of them) is projected into the view; `agreement` is the IoU of the
//!    view's mask with it. A mask torn in half scores low; the ground-truth masks of the sample
//!    scenes score 0.77 and more, mean 0.92–0.94 (the other views cannot see this view's
//!    concavities, e.g. a torus's hole seen through), but with three or four cameras as little
//!    as 0.4: [`consistency`] divides it by what consistent masks reach in the same layout.
//!
//! Measured (`examples/matte_scene.rs`, README; mean/min IoU, composites at the sample scenes'
//! 200²): the sample scenes' IoU rises by 0.003–0.007, a dark object over grout lines of its
//! own grey reaches 0.985/0.973 (0.980/0.901 single-view), an object in the floor's shadow tones
//! 0.968/0.930 (0.016/0.0 single-view). A flattened blob of the shadow's tones lying on its own
//! shadow (0.42/0.02 at 100²) and an object of the floor's own hue and brightness (0.76/0.49 at
//! 100²) are not solved: their masks' low consistency is what `ingest` warns about.

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::Pinhole;
use crate::error::MatteError;
use crate::hull::{self, Hull, MaskedView, Votes};
use crate::mask::{Mask, iou};
use crate::params::MultiViewParams;
use crate::reach::ShadowReach;
use crate::refine::Proofs;
use crate::score::{self, Class, Evidence};
use crate::view::RgbImageView;

/// One camera's image of the frame, its background plate and its calibration.
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    /// The camera (image size included).
    pub camera: Pinhole,
    /// The frame's image.
    pub image: RgbImageView<'a>,
    /// The camera's empty background plate.
    pub plate: RgbImageView<'a>,
}

/// The masks of one frame and how far each agrees with the others.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMatte {
    /// One mask per view, in the order given.
    pub masks: Vec<Mask>,
    /// Per view, IoU of its mask with the reprojection of the hull of the other views'
    /// masks ([`agreement`]), in [0, 1].
    pub agreement: Vec<f64>,
    /// Per view, that agreement against what consistent masks reach in this camera layout
    /// ([`consistency`]), in [0, 1].
    pub consistency: Vec<f64>,
}

/// Mattes all views of one frame (see the module doc). Deterministic whatever the thread
/// count.
///
/// # Errors
/// [`MatteError::SizeMismatch`] if an image and its plate differ in size, and
/// [`MatteError::CameraSize`] if a camera's size is not its image's.
pub fn matte_frame(views: &[View<'_>], params: &MultiViewParams) -> Result<FrameMatte, MatteError> {
    for (i, v) in views.iter().enumerate() {
        let (w, h) = (v.image.width(), v.image.height());
        if (w, h) != (v.plate.width(), v.plate.height()) {
            return Err(MatteError::SizeMismatch {
                image_width: w,
                image_height: h,
                plate_width: v.plate.width(),
                plate_height: v.plate.height(),
            });
        }
        if (v.camera.width as usize, v.camera.height as usize) != (w, h) {
            return Err(MatteError::CameraSize {
                view: i,
                camera_width: v.camera.width as usize,
                camera_height: v.camera.height as usize,
                image_width: w,
                image_height: h,
            });
        }
    }
    let evidence: Vec<Evidence> = views
        .par_iter()
        .map(|v| score::classify(&v.image, &v.plate, &params.view))
        .collect();
    let definite: Vec<Vec<bool>> = (0..views.len())
        .into_par_iter()
        .map(|a| ground_test(a, views, &evidence, params))
        .collect();

    let changed: Vec<Vec<u8>> = evidence
        .iter()
        .zip(views)
        .map(|(e, v)| {
            let bits: Vec<bool> = e.class.iter().map(|c| *c != Class::Unchanged).collect();
            let bits = crate::morphology::majority3(&bits, v.image.width(), v.image.height());
            bits.iter().map(|b| if *b { 255 } else { 0 }).collect()
        })
        .collect();
    let masked: Vec<MaskedView<'_>> = views
        .iter()
        .zip(&changed)
        .map(|(v, m)| MaskedView {
            camera: v.camera,
            mask: m,
        })
        .collect();
    let votes = hull::votes(&masked, params.hull_grid, 0);
    let others: Vec<Hull> = (0..views.len())
        .into_par_iter()
        .map(|a| votes.without(a, 0))
        .collect();
    let raised: Vec<Vec<bool>> = (0..views.len())
        .into_par_iter()
        .map(|a| raised_pixels(&views[a].camera, &evidence[a], &others[a], params))
        .collect();
    let reach = ShadowReach::new(&votes.within(0), params.shadow_max_zenith_deg);
    let definite: Vec<Vec<bool>> = definite
        .into_par_iter()
        .enumerate()
        .map(|(a, mut bits)| {
            reach_test(&views[a].camera, &raised[a], &reach, &mut bits);
            bits
        })
        .collect();
    let settled = definite.clone();
    let mut definite = definite;
    for _ in 0..params.photo_rounds {
        definite = (0..views.len())
            .into_par_iter()
            .map(|a| {
                let mut bits = definite[a].clone();
                photo_test(a, views, &definite, &others[a], &mut bits, params);
                bits
            })
            .collect();
    }
    let masks: Vec<Mask> = definite
        .par_iter()
        .enumerate()
        .map(|(a, bits)| {
            let (w, h) = (views[a].image.width(), views[a].image.height());
            crate::clean_up(bits.clone(), &evidence[a].strength, w, h, &params.view)
        })
        .collect();
    let proofs: Vec<Proofs<'_>> = (0..views.len())
        .map(|a| Proofs {
            proven: &definite[a],
            settled: &settled[a],
            raised: &raised[a],
        })
        .collect();
    let masks = crate::refine::refine(views, &evidence, &proofs, masks, params);
    let cameras: Vec<Pinhole> = views.iter().map(|v| v.camera).collect();
    let (agreement, consistency) = agreement_and_consistency(&cameras, &masks, params);
    Ok(FrameMatte {
        masks,
        agreement,
        consistency,
    })
}

/// Per pixel of a view seen by `cam`: whether it is shadow-like and its ray meets `others`
/// (the hull of the other views' changed pixels) at least `witness_min_height` voxels above the
/// ground: an object may stand there (a contact shadow's ray meets that hull lower). The reach
/// test and the witnesses ask it; computed once per frame.
fn raised_pixels(cam: &Pinhole, e: &Evidence, others: &Hull, p: &MultiViewParams) -> Vec<bool> {
    let w = cam.width as usize;
    let min_height = p.witness_min_height * others.voxel;
    e.class
        .iter()
        .enumerate()
        .map(|(i, c)| {
            *c == Class::ShadowLike
                && others
                    .front(cam, ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5))
                    .is_some_and(|q| q.y >= min_height)
        })
        .collect()
}

/// Step 2b: a raised pixel (see [`raised_pixels`]) not yet proven is object when the ground
/// point behind it is out of reach of the object's shadow (`reach.rs`).
fn reach_test(cam: &Pinhole, raised: &[bool], reach: &ShadowReach, bits: &mut [bool]) {
    let w = cam.width as usize;
    for (i, bit) in bits.iter_mut().enumerate() {
        if *bit || !raised[i] {
            continue;
        }
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        if cam.ground_point(u, v).is_some_and(|g| !reach.reaches(g)) {
            *bit = true;
        }
    }
}

/// RGB of pixel `(u, v)` (continuous; nearest pixel), if inside the image.
fn rgb_at(img: &RgbImageView<'_>, u: f64, v: f64) -> Option<[f32; 3]> {
    let (w, h) = (img.width(), img.height());
    (u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64).then(|| {
        let p = 3 * (v as usize * w + u as usize);
        let d = img.data();
        [d[p], d[p + 1], d[p + 2]].map(f32::from)
    })
}

/// Step 3 of the module doc: the pixels of view `a` its own evidence left ambiguous become
/// object when at least `support_views` other views see, where the pixel's ray first meets
/// `others` (the hull of the other views' changed pixels), a definite object pixel of the
/// same colour (within `photo_tolerance` levels per channel).
fn photo_test(
    a: usize,
    views: &[View<'_>],
    definite: &[Vec<bool>],
    others: &Hull,
    bits: &mut [bool],
    p: &MultiViewParams,
) {
    let view = &views[a];
    let cam = &view.camera;
    let w = cam.width as usize;
    let tolerance = f32::from(p.photo_tolerance);
    for (i, bit) in bits.iter_mut().enumerate() {
        if *bit {
            continue;
        }
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let Some(front) = others.front(cam, (u, v)) else {
            continue;
        };
        let colour = rgb_at(&view.image, u, v).expect("pixel inside");
        let support = views
            .iter()
            .zip(definite)
            .enumerate()
            .filter(|(b, _)| *b != a)
            .filter(|(_, (vb, db))| {
                let Some((qu, qv, _)) = vb.camera.project(front) else {
                    return false;
                };
                let Some(c) = rgb_at(&vb.image, qu, qv) else {
                    return false;
                };
                let q = qv as usize * vb.camera.width as usize + qu as usize;
                db[q] && (0..3).all(|k| (c[k] - colour[k]).abs() <= tolerance)
            })
            .count();
        *bit = support >= p.support_views;
    }
}

/// Whether all pixels of the 3×3 block around continuous position `(u, v)` are unchanged.
fn lit_at(e: &Evidence, w: usize, h: usize, u: f64, v: f64) -> bool {
    if !(u >= 1.0 && v >= 1.0 && u < (w - 1) as f64 && v < (h - 1) as f64) {
        return false;
    }
    let (x, y) = (u as usize, v as usize);
    (y - 1..=y + 1).all(|yy| (x - 1..=x + 1).all(|xx| e.class[yy * w + xx] == Class::Unchanged))
}

/// View `a`'s object bits after the ground test (step 2 of the module doc).
fn ground_test(
    a: usize,
    views: &[View<'_>],
    evidence: &[Evidence],
    p: &MultiViewParams,
) -> Vec<bool> {
    let e = &evidence[a];
    let cam = &views[a].camera;
    let w = cam.width as usize;
    let mut bits = e.object_bits();
    for (i, bit) in bits.iter_mut().enumerate() {
        if e.class[i] != Class::ShadowLike || e.strength[i] <= p.ground_min_change {
            continue;
        }
        let Some(x) = cam.ground_point((i % w) as f64 + 0.5, (i / w) as f64 + 0.5) else {
            continue;
        };
        *bit = lit_views(x, a, views, evidence) >= p.ground_lit_views;
    }
    bits
}

/// How many views other than `skip` see ground point `x` unchanged.
fn lit_views(x: DVec3, skip: usize, views: &[View<'_>], evidence: &[Evidence]) -> usize {
    views
        .iter()
        .zip(evidence)
        .enumerate()
        .filter(|(b, (v, e))| {
            *b != skip
                && v.camera.project(x).is_some_and(|(u, vv, _)| {
                    lit_at(e, v.camera.width as usize, v.camera.height as usize, u, vv)
                })
        })
        .count()
}

/// Step 4: per view, the IoU of its mask with the reprojection of the visual hull of the
/// other views' masks (carved at `hull_grid` voxels, a voxel may miss `hull_max_misses` of
/// them): how far the other views explain this view's mask. Works on any
/// masks (a matte's or ground truth); one view, or none, agrees with itself (1).
///
/// `cameras[i]` must have the size of `masks[i]` (a mismatch scores 0).
pub fn agreement(cameras: &[Pinhole], masks: &[Mask], p: &MultiViewParams) -> Vec<f64> {
    agreement_with(cameras, masks, p.hull_grid, p.hull_max_misses)
}

/// Each camera with its mask, as the hull carving takes them.
fn masked_views<'a>(cameras: &[Pinhole], masks: &'a [Mask]) -> Vec<MaskedView<'a>> {
    cameras
        .iter()
        .zip(masks)
        .map(|(c, m)| MaskedView {
            camera: *c,
            mask: m.data(),
        })
        .collect()
}

/// [`agreement`] with hulls carved at `grid` voxels in which a voxel may miss `misses` views.
fn agreement_with(cameras: &[Pinhole], masks: &[Mask], grid: usize, misses: usize) -> Vec<f64> {
    if cameras.len() < 2 {
        return vec![1.0; cameras.len()];
    }
    let votes = hull::votes(&masked_views(cameras, masks), grid, misses);
    agreement_from(&votes, cameras, masks, misses)
}

/// [`agreement`] from the views' `votes` (at least two views), a voxel missing `misses`.
fn agreement_from(votes: &Votes, cameras: &[Pinhole], masks: &[Mask], misses: usize) -> Vec<f64> {
    cameras
        .iter()
        .zip(masks)
        .enumerate()
        .map(|(a, (c, m))| {
            if (c.width as usize, c.height as usize) != (m.width(), m.height()) {
                return 0.0;
            }
            let bits = votes.without(a, misses).reproject(c);
            iou(m, &Mask::from_bits(m.width(), m.height(), &bits))
        })
        .collect()
}

/// [`agreement`] and [`consistency`] together, the hull's votes carved once for both when
/// `hull_max_misses` is 0 (the default).
pub fn agreement_and_consistency(
    cameras: &[Pinhole],
    masks: &[Mask],
    p: &MultiViewParams,
) -> (Vec<f64>, Vec<f64>) {
    let consistency = consistency_with(cameras, masks, p);
    let agreement = if p.hull_max_misses == 0 {
        consistency.raw
    } else {
        agreement(cameras, masks, p)
    };
    (agreement, consistency.scores)
}

/// Per view, how far its mask agrees with the other views' masks against how far consistent
/// masks can in this camera layout, in [0, 1]: the mask's [`agreement`] divided by the
/// agreement of the view's consistent mask, clamped to 1. The consistent masks are the
/// reprojections of the visual hull of all views' masks: they agree with each other as far as
/// the camera layout lets masks agree (with three or four cameras a hull is loose and a perfect
/// mask's agreement may be 0.4; with eleven around the object, 0.77 and more). A view whose
/// consistent mask agrees with nothing (an empty hull) scores 0.
///
/// One torn mask carves the hull of every other view and lowers them all. So when some view
/// scores below `consistency_threshold`, each view is left out in turn; if without one of
/// them all the others reach the threshold, the others get those scores and that view keeps
/// its own: it alone is named.
///
/// Measured (`examples/matte_scene.rs`): the matte's masks on the sample scenes and on subsets
/// of 3, 4 and 6 of torus-elastic's cameras score 0.95 and more.
pub fn consistency(cameras: &[Pinhole], masks: &[Mask], p: &MultiViewParams) -> Vec<f64> {
    consistency_with(cameras, masks, p).scores
}

/// What [`consistency_with`] gives: the scores, and the raw agreement of every view with
/// all the others (hulls carved with no misses).
struct Consistency {
    scores: Vec<f64>,
    raw: Vec<f64>,
}

/// [`consistency`], and the raw agreement it divides.
fn consistency_with(cameras: &[Pinhole], masks: &[Mask], p: &MultiViewParams) -> Consistency {
    let whole = consistency_of(cameras, masks, p);
    let t = p.consistency_threshold;
    if cameras.len() < 4 || whole.scores.iter().all(|c| *c >= t) {
        return whole;
    }
    let without = |a: usize| -> (Vec<Pinhole>, Vec<Mask>) {
        let keep = |i: &usize| *i != a;
        (
            (0..cameras.len())
                .filter(keep)
                .map(|i| cameras[i])
                .collect(),
            (0..masks.len())
                .filter(keep)
                .map(|i| masks[i].clone())
                .collect(),
        )
    };
    let best = (0..cameras.len())
        .into_par_iter()
        .map(|a| {
            let (c, m) = without(a);
            (a, consistency_of(&c, &m, p).scores)
        })
        .filter(|(_, rest)| rest.iter().all(|c| *c >= t))
        .max_by(|x, y| {
            let low = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
            low(&x.1).total_cmp(&low(&y.1)).then(y.0.cmp(&x.0))
        });
    let Some((culprit, rest)) = best else {
        return whole;
    };
    let mut rest = rest.into_iter();
    let scores = (0..cameras.len())
        .map(|i| {
            if i == culprit {
                whole.scores[i]
            } else {
                rest.next().expect("one score per other view")
            }
        })
        .collect();
    Consistency {
        scores,
        raw: whole.raw,
    }
}

/// [`consistency`] of all views together, without leaving any out. One carving of the views'
/// votes gives both the raw agreement and the hull of all masks.
fn consistency_of(cameras: &[Pinhole], masks: &[Mask], p: &MultiViewParams) -> Consistency {
    if cameras.len() < 2 {
        return Consistency {
            scores: vec![1.0; cameras.len()],
            raw: vec![1.0; cameras.len()],
        };
    }
    let votes = hull::votes(&masked_views(cameras, masks), p.hull_grid, 0);
    let raw = agreement_from(&votes, cameras, masks, 0);
    let hull = votes.within(0);
    let consistent: Vec<Mask> = cameras
        .iter()
        .zip(masks)
        .map(|(c, m)| {
            let bits = if (c.width as usize, c.height as usize) == (m.width(), m.height()) {
                hull.reproject(c)
            } else {
                vec![false; m.width() * m.height()]
            };
            Mask::from_bits(m.width(), m.height(), &bits)
        })
        .collect();
    let reachable = agreement_with(cameras, &consistent, p.hull_grid, 0);
    let scores = raw
        .iter()
        .zip(reachable)
        .map(|(a, r)| if r > 0.0 { (a / r).min(1.0) } else { 0.0 })
        .collect();
    Consistency { scores, raw }
}
