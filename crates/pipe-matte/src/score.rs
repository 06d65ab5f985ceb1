//! Per-pixel object/background decision against the background plate.
//!
//! For image pixel `I` and plate pixel `B` (RGB, 0..=255):
//!
//! * **changed**: `max_c |I_c - B_c| > change_threshold`; unchanged pixels are background.
//! * **shadow-like**: with the offset log-ratio `l_c = ln((I_c + k) / (B_c + k))`,
//!   `max_c l_c - min_c l_c < shadow_max_spread` (all channels scaled by the same factor,
//!   i.e. the plate's hue is kept) and `mean_c l_c < shadow_max_log_gain` (the pixel got
//!   darker, not brighter). The offset `k` keeps the ratio of near-black pixels finite.
//! * **object** = changed and not shadow-like.

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

/// Decides one pixel; `lut` is [`log_table`] of `params.ratio_offset`.
fn is_object(i: &[u8], b: &[u8], lut: &[f32; 256], params: &MatteParams) -> bool {
    if change(i, b) <= params.change_threshold {
        return false;
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
    let shadow = hi - lo < params.shadow_max_spread && sum / 3.0 < params.shadow_max_log_gain;
    !shadow
}

/// Raw per-pixel object decisions and change magnitudes (row-major, before any
/// clean-up).
///
/// `image` and `plate` must have the same dimensions (checked by [`crate::matte`]).
pub(crate) fn classify(
    image: &RgbImageView<'_>,
    plate: &RgbImageView<'_>,
    params: &MatteParams,
) -> (Vec<bool>, Vec<u8>) {
    let (w, h) = (image.width(), image.height());
    let mut object = vec![false; w * h];
    let mut strength = vec![0u8; w * h];
    if w == 0 || h == 0 {
        return (object, strength);
    }
    let lut = log_table(params.ratio_offset);
    let (img, pl) = (image.data(), plate.data());
    object
        .par_chunks_mut(w)
        .zip(strength.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (obj_row, str_row))| {
            let base = y * w * 3;
            for (x, (o, s)) in obj_row.iter_mut().zip(str_row).enumerate() {
                let p = base + 3 * x;
                let (i, b) = (&img[p..p + 3], &pl[p..p + 3]);
                *s = change(i, b);
                *o = is_object(i, b, &lut, params);
            }
        });
    (object, strength)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(i: [u8; 3], b: [u8; 3]) -> bool {
        let p = MatteParams::default();
        is_object(&i, &b, &log_table(p.ratio_offset), &p)
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
        assert!(!is_object(&[0, 0, 0], &[0, 0, 0], &lut, &p));
    }
}
