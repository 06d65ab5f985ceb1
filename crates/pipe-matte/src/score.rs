//! Per-pixel object/background decision against the background plate.
//!
//! For image pixel `I` and plate pixel `B` (RGB, 0..=255):
//!
//! * **changed**: `max_c |I_c - B_c| > T`, `T = max(change_threshold, 4σ)`; unchanged pixels
//!   are background. `σ` is the image's noise against its plate: the robust standard
//!   deviation (1.4826 × median absolute deviation) of the signed differences `I_c − B_c`
//!   over all pixels and channels, which the background dominates. A render against a plate
//!   of the same sampler seed has `σ = 0`; a camera's frames against a separately shot plate
//!   do not.
//! * **shadow-like**: with the offset log-ratio `l_c = ln((I_c + k) / (B_c + k))`,
//!   `max_c l_c - min_c l_c < shadow_max_spread + s` (all channels scaled by the same factor,
//!   i.e. the plate's hue is kept) and `mean_c l_c < shadow_max_log_gain + s` (the pixel got
//!   darker, not brighter). `s = 2 max_c σ_c`, with `σ_c = (σ/√2) √((I_c + k)⁻² + (B_c + k)⁻²)`
//!   the noise of `l_c` when image and plate share the difference's noise: in a dark shadow a few
//!   levels of noise move the ratios far. With noise (`σ > 0`) the test reads the pixel's 3×3
//!   block means (noise `σ/3`). The offset `k` keeps the ratio of near-black pixels finite.
//! * **object** = changed and not shadow-like ([`Class`]).
//! * **block change**: a pixel unchanged by the first test is changed too when, in some
//!   channel, both its own signed difference and its 3×3 block's mean signed difference exceed
//!   `T_b = max(block_change_threshold, 4σ/3)` with the same sign; its shadow test then runs
//!   on the block's mean colours (noise `σ/3`). Noise falls three times in the block's mean; an
//!   object a few levels off the plate over a whole block does not, and a background pixel
//!   beside the object's outline, unchanged itself, is not taken by its neighbours' change.

use rayon::prelude::*;

use crate::params::MatteParams;
use crate::view::RgbImageView;

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
    /// No change beyond the noise (module doc).
    Unchanged,
    /// Changed, but every channel dimmed by a similar factor: a shadow, or an object of
    /// the plate's hue.
    ShadowLike,
    /// Changed otherwise.
    Object,
}

/// The thresholds of one image against its plate (see the module doc).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Thresholds {
    /// `T`, 8-bit levels.
    change: f32,
    /// `T_b`, 8-bit levels.
    block: f32,
    /// `σ`, 8-bit levels.
    noise: f32,
    /// The log-ratio offset `k`.
    offset: f32,
}

impl Thresholds {
    fn new(noise: f32, params: &MatteParams) -> Self {
        let offset = if params.ratio_offset.is_finite() && params.ratio_offset > 0.0 {
            params.ratio_offset
        } else {
            f32::MIN_POSITIVE
        };
        let change = f32::from(params.change_threshold).max(4.0 * noise);
        let block = if params.block_change_threshold < params.change_threshold {
            f32::from(params.block_change_threshold).max(4.0 * noise / 3.0)
        } else {
            f32::INFINITY
        };
        Self {
            change,
            block,
            noise,
            offset,
        }
    }
}

/// `σ` of the module doc: 1.4826 × the median absolute deviation of the signed differences
/// `I_c − B_c` over all pixels and channels (exact, from their histogram).
pub(crate) fn noise_sigma(img: &[u8], pl: &[u8]) -> f32 {
    let mut hist = [0u64; 511];
    for (&i, &b) in img.iter().zip(pl) {
        hist[usize::from(i) + 255 - usize::from(b)] += 1;
    }
    let n: u64 = hist.iter().sum();
    if n == 0 {
        return 0.0;
    }
    let quantile = |h: &[u64], rank: u64| -> usize {
        let mut acc = 0;
        h.iter()
            .position(|&c| {
                acc += c;
                acc > rank
            })
            .unwrap_or(h.len() - 1)
    };
    let median = quantile(&hist, n / 2) as i64;
    let mut dev = [0u64; 511];
    for (v, &c) in hist.iter().enumerate() {
        dev[(v as i64 - median).unsigned_abs() as usize] += c;
    }
    1.4826 * quantile(&dev, n / 2) as f32
}

/// The shadow test on mean colours `i`, `b` (0–255) whose noise is `noise` levels.
fn shadow_or_object(
    i: [f32; 3],
    b: [f32; 3],
    noise: f32,
    t: &Thresholds,
    p: &MatteParams,
) -> Class {
    let k = t.offset;
    let l = [0, 1, 2].map(|c| ((i[c] + k) / (b[c] + k)).ln());
    let lo = l.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = l.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mean = (l[0] + l[1] + l[2]) / 3.0;
    // Noise of each log-ratio, the difference's noise shared equally by image and plate.
    let half = noise * std::f32::consts::FRAC_1_SQRT_2;
    let slack = (0..3)
        .map(|c| 2.0 * half * ((i[c] + k).powi(-2) + (b[c] + k).powi(-2)).sqrt())
        .fold(0.0, f32::max);
    if hi - lo < p.shadow_max_spread + slack && mean < p.shadow_max_log_gain + slack {
        Class::ShadowLike
    } else {
        Class::Object
    }
}

/// Classifies pixel `(x, y)` of `img` against `pl` (interleaved RGB, `w × h`).
fn classify_pixel(
    img: &[u8],
    pl: &[u8],
    (w, h): (usize, usize),
    (x, y): (usize, usize),
    t: &Thresholds,
    p: &MatteParams,
) -> Class {
    let q = 3 * (y * w + x);
    let (i, b) = (&img[q..q + 3], &pl[q..q + 3]);
    let own = [0, 1, 2].map(|c| f32::from(i[c]) - f32::from(b[c]));
    let changed = own.iter().any(|d| d.abs() > t.change);
    if !changed && (!t.block.is_finite() || own.iter().all(|d| d.abs() <= t.block)) {
        return Class::Unchanged;
    }
    if changed && t.noise == 0.0 {
        let rgb = |v: &[u8]| [0, 1, 2].map(|c| f32::from(v[c]));
        return shadow_or_object(rgb(i), rgb(b), 0.0, t, p);
    }
    let (mi, mb, n) = block_means(img, pl, (w, h), (x, y));
    if changed {
        return shadow_or_object(mi, mb, t.noise / n.sqrt(), t, p);
    }
    let shared = (0..3).any(|c| {
        let mean = mi[c] - mb[c];
        own[c].abs() > t.block && mean.abs() > t.block && own[c].signum() == mean.signum()
    });
    if shared {
        shadow_or_object(mi, mb, t.noise / n.sqrt(), t, p)
    } else {
        Class::Unchanged
    }
}

/// Mean colours of image and plate over the 3×3 block around `(x, y)` (cut by the image's
/// border), and the block's pixel count.
fn block_means(
    img: &[u8],
    pl: &[u8],
    (w, h): (usize, usize),
    (x, y): (usize, usize),
) -> ([f32; 3], [f32; 3], f32) {
    let mut si = [0.0f32; 3];
    let mut sb = [0.0f32; 3];
    let mut n = 0.0f32;
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let r = 3 * (yy * w + xx);
            for c in 0..3 {
                si[c] += f32::from(img[r + c]);
                sb[c] += f32::from(pl[r + c]);
            }
            n += 1.0;
        }
    }
    (si.map(|v| v / n), sb.map(|v| v / n), n)
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
    let (img, pl) = (image.data(), plate.data());
    let t = Thresholds::new(noise_sigma(img, pl), params);
    class
        .par_chunks_mut(w)
        .zip(strength.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (cls_row, str_row))| {
            let base = y * w * 3;
            for (x, (o, s)) in cls_row.iter_mut().zip(str_row).enumerate() {
                let p = base + 3 * x;
                *s = change(&img[p..p + 3], &pl[p..p + 3]);
                *o = classify_pixel(img, pl, (w, h), (x, y), &t, params);
            }
        });
    Evidence { class, strength }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The class of a lone pixel `i` against plate pixel `b`, noise-free.
    fn class_of(i: [u8; 3], b: [u8; 3], p: &MatteParams) -> Class {
        classify_pixel(&i, &b, (1, 1), (0, 0), &Thresholds::new(0.0, p), p)
    }

    fn one(i: [u8; 3], b: [u8; 3]) -> bool {
        class_of(i, b, &MatteParams::default()) == Class::Object
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
        assert_eq!(class_of([0, 0, 0], [0, 0, 0], &p), Class::Unchanged);
        // Ratios of black against a colour stay finite: their spread is the plate's own.
        assert_eq!(class_of([0, 0, 0], [120, 100, 80], &p), Class::Object);
        assert_eq!(class_of([0, 0, 0], [100, 100, 100], &p), Class::ShadowLike);
    }

    /// A `w × h` image of one colour.
    fn flat(w: usize, h: usize, rgb: [u8; 3]) -> Vec<u8> {
        rgb.iter().copied().cycle().take(3 * w * h).collect()
    }

    fn classes(img: &[u8], pl: &[u8], w: usize, h: usize) -> Vec<Class> {
        let p = MatteParams::default();
        classify(
            &RgbImageView::new(img, w, h).unwrap(),
            &RgbImageView::new(pl, w, h).unwrap(),
            &p,
        )
        .class
    }

    #[test]
    fn a_block_a_few_levels_off_is_changed_and_a_lone_pixel_is_not() {
        let (w, h) = (9, 9);
        let plate = flat(w, h, [130, 115, 90]);
        let mut img = plate.clone();
        // A 5×5 object 10 levels off in red and blue (a hue change), within the per-pixel
        // threshold of 12.
        for y in 2..7 {
            for x in 2..7 {
                let q = 3 * (y * w + x);
                img[q] -= 10;
                img[q + 2] += 10;
            }
        }
        // A lone pixel 10 levels off far from it.
        img[0] += 10;
        let c = classes(&img, &plate, w, h);
        assert_eq!(c[4 * w + 4], Class::Object, "block centre");
        assert_ne!(
            c[4 * w + 2],
            Class::Unchanged,
            "block edge: six of its nine are object"
        );
        assert_eq!(c[0], Class::Unchanged, "lone pixel");
        assert_eq!(
            c[4 * w + 1],
            Class::Unchanged,
            "background beside the block"
        );
        // The same block dimmed in every channel alike is shadow-like, not object.
        let mut dim = plate.clone();
        for y in 2..7 {
            for x in 2..7 {
                for c in 0..3 {
                    dim[3 * (y * w + x) + c] -= 8;
                }
            }
        }
        assert_eq!(classes(&dim, &plate, w, h)[4 * w + 4], Class::ShadowLike);
    }

    #[test]
    fn noise_is_the_robust_spread_of_the_differences() {
        let plate = flat(10, 10, [100, 100, 100]);
        assert_eq!(noise_sigma(&plate, &plate), 0.0);
        // Differences −3, 0, +3 in equal thirds: median 0, median absolute deviation 3.
        let img: Vec<u8> = plate
            .iter()
            .enumerate()
            .map(|(i, v)| match i % 3 {
                0 => v - 3,
                1 => *v,
                _ => v + 3,
            })
            .collect();
        assert!((noise_sigma(&img, &plate) - 1.4826 * 3.0).abs() < 1e-4);
        // A few large changes (the object) do not move it.
        let mut with_object = img.clone();
        for v in with_object.iter_mut().take(60) {
            *v = 250;
        }
        assert!((noise_sigma(&with_object, &plate) - 1.4826 * 3.0).abs() < 1e-4);
        assert_eq!(noise_sigma(&[], &[]), 0.0);
    }

    #[test]
    fn noise_raises_the_change_threshold() {
        let p = MatteParams::default();
        let quiet = Thresholds::new(0.0, &p);
        let noisy = Thresholds::new(5.0, &p);
        // A lone changed pixel in the middle of a 3×3 plate.
        let plate = flat(3, 3, [130, 115, 90]);
        let mut img = plate.clone();
        img[12..15].copy_from_slice(&[148, 115, 72]);
        let at = |t: &Thresholds| classify_pixel(&img, &plate, (3, 3), (1, 1), t, &p);
        assert_eq!(at(&quiet), Class::Object);
        assert_eq!(
            at(&noisy),
            Class::Unchanged,
            "18 levels is within 4σ of noise 5"
        );
    }
}
