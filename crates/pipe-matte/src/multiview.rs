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
//!    concavities, e.g. a torus's hole seen through).
//!
//! Measured (`examples/matte_scene.rs`, README; mean/min IoU, composites at the sample scenes'
//! 200²): the sample scenes' IoU rises by 0.003–0.007, a dark object over grout lines of its
//! own grey reaches 0.985/0.974 (0.978/0.890 single-view), an object in the floor's shadow tones
//! 0.967/0.922 (0.016/0.0 single-view). A flattened blob of the shadow's tones lying on its own
//! shadow is not solved (0.44/0.02 at 100²): its masks' low agreement is what `ingest` warns
//! about.

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::Pinhole;
use crate::error::MatteError;
use crate::hull::{self, Hull, MaskedView};
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
    /// Per view, IoU of its mask with the reprojection of the hull of all masks, in [0, 1].
    pub agreement: Vec<f64>,
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
    let agreement = agreement(&cameras, &masks, params);
    Ok(FrameMatte { masks, agreement })
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
    if cameras.len() < 2 {
        return vec![1.0; cameras.len()];
    }
    let masked: Vec<MaskedView<'_>> = cameras
        .iter()
        .zip(masks)
        .map(|(c, m)| MaskedView {
            camera: *c,
            mask: m.data(),
        })
        .collect();
    let votes = hull::votes(&masked, p.hull_grid, p.hull_max_misses);
    cameras
        .iter()
        .zip(masks)
        .enumerate()
        .map(|(a, (c, m))| {
            if (c.width as usize, c.height as usize) != (m.width(), m.height()) {
                return 0.0;
            }
            let bits = votes.without(a, p.hull_max_misses).reproject(c);
            iou(m, &Mask::from_bits(m.width(), m.height(), &bits))
        })
        .collect()
}
