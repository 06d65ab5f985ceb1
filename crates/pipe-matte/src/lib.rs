//! Object matting against a per-camera background plate.
//!
//! Given a camera image `I` and that camera's empty background plate `B` (rendered with
//! the same sampler seed, so unchanged pixels are nearly identical), [`matte`] returns a
//! binary mask of the moving object. The difficulty is the object's shadow: it changes
//! the image too, but it only scales the plate's colour by a similar factor in every
//! channel, while the object replaces the colour. Pipeline (thresholds in
//! [`MatteParams`]):
//!
//! 1. per pixel (`score.rs`): object iff `max_c |I_c - B_c| > change_threshold` (or a change
//!    its 3×3 block shares, `block_change_threshold`; both rise with the image's noise against
//!    its plate) and not shadow-like, where shadow-like means the log-ratios
//!    `l_c = ln((I_c + k) / (B_c + k))` have spread `max_c l_c - min_c l_c <
//!    shadow_max_spread` and mean `< shadow_max_log_gain` (widened by their noise);
//! 2. 3x3 majority vote (`morphology.rs`);
//! 3. drop object components smaller than `min_component_area`, fill enclosed holes of at
//!    most `max_hole_area` pixels (`components.rs`);
//! 4. peel outline pixels whose change is at most `boundary_change_threshold`: mostly
//!    uncovered anti-aliased edge pixels (`morphology.rs`).
//!
//! [`matte_frame`] mattes all cameras of one frame together (`multiview.rs`): the geometry of
//! the capture tells an object from its shadow on the ground, and from background of its own
//! colour, where one view's colours cannot; it also scores how far each mask agrees with the
//! other views ([`agreement`]), and how far that is from what consistent masks reach in the
//! same camera layout ([`consistency`]). [`carve`] is the visual-hull carving it shares with the
//! pipeline's `init` stage.

mod camera;
mod components;
mod cut;
mod error;
pub mod hull;
mod mask;
mod maxflow;
pub(crate) mod morphology;
mod multiview;
mod params;
mod reach;
mod refine;
mod score;
mod texture;
mod view;
mod witness;

pub use camera::Pinhole;
pub use error::MatteError;
pub use hull::{Hull, MaskedView, carve};
pub use mask::{Mask, iou};
pub use multiview::{
    FrameMatte, View, agreement, agreement_and_consistency, consistency, matte_frame,
};
pub use params::{MatteParams, MultiViewParams};
pub use view::RgbImageView;

/// Mattes the object out of `image` using the background `plate` of the same camera.
///
/// Deterministic; parallel over rows. An image identical to its plate gives an empty mask.
///
/// # Errors
/// [`MatteError::SizeMismatch`] if the two views differ in width or height.
pub fn matte(
    image: &RgbImageView<'_>,
    plate: &RgbImageView<'_>,
    params: &MatteParams,
) -> Result<Mask, MatteError> {
    let (w, h) = (image.width(), image.height());
    if (w, h) != (plate.width(), plate.height()) {
        return Err(MatteError::SizeMismatch {
            image_width: w,
            image_height: h,
            plate_width: plate.width(),
            plate_height: plate.height(),
        });
    }
    let evidence = score::classify(image, plate, params);
    Ok(clean_up(
        evidence.object_bits(),
        &evidence.strength,
        w,
        h,
        params,
    ))
}

/// Steps 2–4 of the pipeline: majority vote, small components and holes, boundary peel.
pub(crate) fn clean_up(
    mut bits: Vec<bool>,
    strength: &[u8],
    w: usize,
    h: usize,
    params: &MatteParams,
) -> Mask {
    if params.majority_filter {
        bits = morphology::majority3(&bits, w, h);
    }
    components::remove_small_components(&mut bits, w, h, params.min_component_area);
    components::fill_small_holes(&mut bits, w, h, params.max_hole_area);
    if params.boundary_change_threshold > params.change_threshold {
        bits =
            morphology::peel_weak_boundary(&bits, strength, w, h, params.boundary_change_threshold);
    }
    Mask::from_bits(w, h, &bits)
}
