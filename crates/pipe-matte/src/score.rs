//! Per-pixel object/background decision against the background plate.
//!
//! For image pixel `I` and plate pixel `B` (RGB, 0..=255):
//!
//! * **changed**: `max_c |I_c - B_c| > change_threshold`; unchanged pixels are background.
//! * **shadow-like**: with the offset log-ratio `l_c = ln((I_c + k) / (B_c + k))`,
//!   `max_c l_c - min_c l_c < shadow_max_spread` (all channels scaled by the same factor,
//!   i.e. the plate's hue is kept) and `mean_c l_c < shadow_max_log_gain` (the pixel got
//!   darker, not brighter). The offset `k` keeps the ratio of near-black pixels finite.
//! * **object** = changed and not shadow-like ([`Class`]).

use rayon::prelude::*;

use crate::params::MatteParams;
use crate::view::RgbImageView;

/// `ln(v + k)` for every 8-bit value `v`.
fn log_table(offset: f32) -> [f32; 256] {
    let k = if offset.is_finite() && offset > 0.0 {
        offset
    } else {
        // `ln(0)` would make every ratio with a black channel infinite; fall back to the
        // smallest offset that keeps the table finite.
        f32::MIN_POSITIVE
    };
    std::array::from_fn(|v| (v as f32 + k).ln())
}

/// Change magnitude `max_c |I_c - B_c|` of one pixel.
fn change(i: &[u8], b: &[u8]) -> u8 {
    i.iter()
        .zip(b)
        .map(|(&x, &y)| x.abs_diff(y))
        .max()
        .unwrap_or(0)
}

/// What a pixel's change against the plate looks like.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Class {
    /// `max_c |I_c - B_c| <= change_threshold`.
    Unchanged,
    /// Changed, but every channel dimmed by a similar factor: a shadow, or an object of
    /// the plate's hue.
    ShadowLike,
    /// Changed otherwise.
    Object,
}

/// Classifies one pixel; `lut` is [`log_table`] of `params.ratio_offset`.
fn classify_pixel(i: &[u8], b: &[u8], lut: &[f32; 256], params: &MatteParams) -> Class {
    if change(i, b) <= params.change_threshold {
        return Class::Unchanged;
    }
    let mut lo = f32::INFINITY;
    let mut hi = f32::NEG_INFINITY;
    let mut sum = 0.0f32;
    for (&x, &y) in i.iter().zip(b) {
        let l = lut[usize::from(x)] - lut[usize::from(y)];
        lo = lo.min(l);
        hi = hi.max(l);
        sum += l;
    }
    if hi - lo < params.shadow_max_spread && sum / 3.0 < params.shadow_max_log_gain {
        Class::ShadowLike
    } else {
        Class::Object
    }
}

/// Per-pixel evidence of one view (row-major, before any clean-up).
#[derive(Debug, Clone)]
pub(crate) struct Evidence {
    /// Each pixel's class.
    pub class: Vec<Class>,
    /// Change magnitude `max_c |I_c - B_c|`.
    pub strength: Vec<u8>,
}

impl Evidence {
    /// The object decision of the single-view test: changed and not shadow-like.
    pub fn object_bits(&self) -> Vec<bool> {
        self.class.iter().map(|c| *c == Class::Object).collect()
    }
}

/// Classifies every pixel of `image` against `plate`.
///
/// `image` and `plate` must have the same dimensions (checked by the callers).
pub(crate) fn classify(
    image: &RgbImageView<'_>,
    plate: &RgbImageView<'_>,
    params: &MatteParams,
) -> Evidence {
    let (w, h) = (image.width(), image.height());
    let mut class = vec![Class::Unchanged; w * h];
    let mut strength = vec![0u8; w * h];
    if w == 0 || h == 0 {
        return Evidence { class, strength };
    }
    let lut = log_table(params.ratio_offset);
    let (img, pl) = (image.data(), plate.data());
    class
        .par_chunks_mut(w)
        .zip(strength.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (cls_row, str_row))| {
            let base = y * w * 3;
            for (x, (o, s)) in cls_row.iter_mut().zip(str_row).enumerate() {
                let p = base + 3 * x;
                let (i, b) = (&img[p..p + 3], &pl[p..p + 3]);
                *s = change(i, b);
                *o = classify_pixel(i, b, &lut, params);
            }
        });
    Evidence { class, strength }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(i: [u8; 3], b: [u8; 3]) -> bool {
        let p = MatteParams::default();
        classify_pixel(&i, &b, &log_table(p.ratio_offset), &p) == Class::Object
    }

    #[test]
    fn unchanged_pixel_is_background() {
        assert!(!one([120, 100, 80], [120, 100, 80]));
        assert!(!one([120, 100, 80], [125, 95, 85]));
    }

    #[test]
    fn uniformly_darkened_pixel_is_shadow() {
        assert!(!one([60, 50, 40], [120, 100, 80]));
        assert!(!one([12, 10, 8], [120, 100, 80]));
    }

    #[test]
    fn hue_change_is_object() {
        assert!(one([200, 40, 30], [120, 100, 80]));
        assert!(one([40, 80, 200], [120, 100, 80]));
    }

    #[test]
    fn brightening_is_object() {
        assert!(one([240, 200, 160], [120, 100, 80]));
    }

    #[test]
    fn degenerate_offset_does_not_produce_nan_decisions() {
        let p = MatteParams {
            ratio_offset: 0.0,
            ..MatteParams::default()
        };
        let lut = log_table(p.ratio_offset);
        assert!(lut.iter().all(|v| v.is_finite()));
        assert_eq!(
            classify_pixel(&[0, 0, 0], &[0, 0, 0], &lut, &p),
            Class::Unchanged
        );
    }
}
