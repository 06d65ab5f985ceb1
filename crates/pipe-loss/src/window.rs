//! The 11-tap Gaussian window (σ = 1.5) and separable filtering with zero or reflect padding.

use rayon::prelude::*;

/// Half-width of the window (11 taps).
pub const RADIUS: usize = 5;
/// Standard deviation of the window (pixels).
pub const SIGMA: f64 = 1.5;

/// Normalised 1D weights `exp(-x²/(2σ²))`, `x = -5..=5`.
pub fn weights() -> [f64; 2 * RADIUS + 1] {
    let mut w: [f64; 2 * RADIUS + 1] = std::array::from_fn(|i| {
        (-((i as f64 - RADIUS as f64).powi(2)) / (2.0 * SIGMA * SIGMA)).exp()
    });
    let s: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= s);
    w
}

/// Border handling of [`filter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Padding {
    /// Outside values are 0 (PyTorch `conv2d(padding=5)`, the 3DGS loss).
    Zero,
    /// Half-sample symmetric `d c b a | a b c d` (scipy `mode='reflect'`, scikit-image).
    Reflect,
}

/// Index `i` (possibly outside `0..n`) folded back by half-sample symmetric reflection.
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let period = 2 * n;
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - 1 - m }) as usize
}

/// Source index of tap position `j` (possibly outside `0..n`), or `None` for a zero tap.
#[inline]
fn source(j: isize, n: usize, pad: Padding) -> Option<usize> {
    if (0..n as isize).contains(&j) {
        Some(j as usize)
    } else if pad == Padding::Zero {
        None
    } else {
        Some(reflect(j, n))
    }
}

/// Horizontal pass of one row: `dst[i] = Σ_t w_t·src[i + t - R]` (taps in ascending order),
/// the interior as tap-major sweeps over contiguous ranges (vectorisable).
fn filter_row(src: &[f64], dst: &mut [f64], k: &[f64; 2 * RADIUS + 1], pad: Padding) {
    let n = src.len();
    let r = RADIUS as isize;
    let border = |i: usize| -> f64 {
        k.iter()
            .enumerate()
            .filter_map(|(t, &wk)| source(i as isize + t as isize - r, n, pad).map(|j| wk * src[j]))
            .sum()
    };
    if n > 2 * RADIUS {
        dst.fill(0.0);
        let interior = RADIUS..n - RADIUS;
        for (t, &wk) in k.iter().enumerate() {
            let s = &src[t..t + interior.len()];
            for (d, &v) in dst[interior.clone()].iter_mut().zip(s) {
                *d += wk * v;
            }
        }
        for i in (0..RADIUS).chain(n - RADIUS..n) {
            dst[i] = border(i);
        }
    } else {
        for (i, d) in dst.iter_mut().enumerate() {
            *d = border(i);
        }
    }
}

/// Separable 2D Gaussian filter of a `[h][w]` plane ('same' size): rows first, then columns
/// as weighted sums of whole rows. Parallel over rows; every output value is computed by one
/// task in a fixed order, so results do not depend on the thread count.
pub fn filter(src: &[f64], w: usize, h: usize, pad: Padding) -> Vec<f64> {
    debug_assert_eq!(src.len(), w * h);
    let k = weights();
    let r = RADIUS as isize;
    let mut tmp = vec![0.0; w * h];
    tmp.par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(trow, srow)| filter_row(srow, trow, &k, pad));
    let mut out = vec![0.0; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, orow)| {
        for (t, &wk) in k.iter().enumerate() {
            if let Some(sy) = source(y as isize + t as isize - r, h, pad) {
                for (o, &v) in orow.iter_mut().zip(&tmp[sy * w..(sy + 1) * w]) {
                    *o += wk * v;
                }
            }
        }
    });
    out
}
