//! SSIM (Wang et al. 2004) with an 11×11 Gaussian window (σ = 1.5), accumulated in f64.
//!
//! Per channel: `μx = G*x`, `μy = G*y`, `σx² = G*x² - μx²`, `σy² = G*y² - μy²`,
//! `σxy = G*(xy) - μxμy`, `S = (2μxμy + C1)(2σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2))`,
//! `C1 = 0.01²`, `C2 = 0.03²` (data range 1).
//! - 3DGS convention ([`ssim`], the training loss): zero padding ('same' conv2d), mean of `S`
//!   over all `3·H·W` values; [`ssim_grad`] gives `d SSIM / d a` by the chain rule through the
//!   five filtered maps (the zero-padded Gaussian filter is its own adjoint).
//! - scikit-image convention ([`ssim_skimage`], for reports): reflect padding, a 5-pixel
//!   border dropped, mean over the interior, then over the channels.

use rayon::prelude::*;

use crate::error::LossError;
use crate::image::{Image, same_size};
use crate::window::{Padding, RADIUS, filter};

/// `(K1·L)²` with K1 = 0.01, L = 1.
pub const C1: f64 = 1e-4;
/// `(K2·L)²` with K2 = 0.03, L = 1.
pub const C2: f64 = 9e-4;

/// Filtered moments of one channel.
struct Moments {
    mx: Vec<f64>,
    my: Vec<f64>,
    ex2: Vec<f64>,
    ey2: Vec<f64>,
    exy: Vec<f64>,
}

fn moments(x: &[f64], y: &[f64], w: usize, h: usize, pad: Padding) -> Moments {
    let sq = |v: &[f64]| v.iter().map(|a| a * a).collect::<Vec<_>>();
    let xy: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    Moments {
        mx: filter(x, w, h, pad),
        my: filter(y, w, h, pad),
        ex2: filter(&sq(x), w, h, pad),
        ey2: filter(&sq(y), w, h, pad),
        exy: filter(&xy, w, h, pad),
    }
}

/// The SSIM terms at one pixel.
#[derive(Debug, Clone, Copy)]
struct Terms {
    num1: f64,
    num2: f64,
    den1: f64,
    den2: f64,
}

impl Terms {
    #[inline]
    fn at(m: &Moments, p: usize) -> Self {
        let (mx, my) = (m.mx[p], m.my[p]);
        let sx = m.ex2[p] - mx * mx;
        let sy = m.ey2[p] - my * my;
        let sxy = m.exy[p] - mx * my;
        Self {
            num1: 2.0 * mx * my + C1,
            num2: 2.0 * sxy + C2,
            den1: mx * mx + my * my + C1,
            den2: sx + sy + C2,
        }
    }
    #[inline]
    fn s(&self) -> f64 {
        (self.num1 * self.num2) / (self.den1 * self.den2)
    }
}

fn channel_map(a: &Image<'_>, b: &Image<'_>, c: usize, pad: Padding) -> (Moments, Vec<f64>) {
    let (w, h) = (a.width(), a.height());
    let m = moments(&a.plane(c), &b.plane(c), w, h, pad);
    let map = (0..w * h).map(|p| Terms::at(&m, p).s()).collect();
    (m, map)
}

/// Per-pixel SSIM map of the 3DGS formula, `[H][W][3]` like the inputs.
pub fn ssim_map(a: Image<'_>, b: Image<'_>) -> Result<Vec<f64>, LossError> {
    same_size(&a, &b)?;
    let maps: Vec<Vec<f64>> = (0..3)
        .into_par_iter()
        .map(|c| channel_map(&a, &b, c, Padding::Zero).1)
        .collect();
    let n = a.width() * a.height();
    Ok((0..n * 3).map(|i| maps[i % 3][i / 3]).collect())
}

/// SSIM in the 3DGS convention (zero padding, mean over all values).
pub fn ssim(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    same_size(&a, &b)?;
    let sums: Vec<f64> = (0..3)
        .into_par_iter()
        .map(|c| channel_map(&a, &b, c, Padding::Zero).1.iter().sum::<f64>())
        .collect();
    Ok(sums.iter().sum::<f64>() / (3 * a.width() * a.height()) as f64)
}

/// SSIM in the 3DGS convention and its gradient w.r.t. `a` (`[H][W][3]`, f32).
pub fn ssim_grad(a: Image<'_>, b: Image<'_>) -> Result<(f64, Vec<f32>), LossError> {
    same_size(&a, &b)?;
    let (w, h) = (a.width(), a.height());
    let n_all = (3 * w * h) as f64;
    let per_channel: Vec<(f64, Vec<f64>)> = (0..3)
        .into_par_iter()
        .map(|c| {
            let x = a.plane(c);
            let y = b.plane(c);
            let m = moments(&x, &y, w, h, Padding::Zero);
            // dS/dμx, dS/d(G*x²), dS/d(G*xy) per pixel
            let mut g_mu = vec![0.0; w * h];
            let mut g_ex2 = vec![0.0; w * h];
            let mut g_exy = vec![0.0; w * h];
            let mut sum = 0.0;
            for p in 0..w * h {
                let t = Terms::at(&m, p);
                let s = t.s();
                sum += s;
                let inv = 1.0 / (t.den1 * t.den2);
                let (mx, my) = (m.mx[p], m.my[p]);
                // num1 = 2μxμy + C1, num2 = 2(exy - μxμy) + C2,
                // den1 = μx² + μy² + C1, den2 = ex2 - μx² + ey2 - μy² + C2
                g_mu[p] = 2.0 * my * (t.num2 - t.num1) * inv - 2.0 * mx * s / t.den1
                    + 2.0 * mx * s / t.den2;
                g_ex2[p] = -s / t.den2;
                g_exy[p] = 2.0 * t.num1 * inv;
            }
            let f_mu = filter(&g_mu, w, h, Padding::Zero);
            let f_ex2 = filter(&g_ex2, w, h, Padding::Zero);
            let f_exy = filter(&g_exy, w, h, Padding::Zero);
            let grad = (0..w * h)
                .map(|q| (f_mu[q] + 2.0 * x[q] * f_ex2[q] + y[q] * f_exy[q]) / n_all)
                .collect();
            (sum, grad)
        })
        .collect();
    let value = per_channel.iter().map(|(s, _)| s).sum::<f64>() / n_all;
    let grad = (0..3 * w * h)
        .map(|i| per_channel[i % 3].1[i / 3] as f32)
        .collect();
    Ok((value, grad))
}

/// D-SSIM = 1 - SSIM (3DGS convention) and its gradient w.r.t. `a`.
pub fn dssim_grad(a: Image<'_>, b: Image<'_>) -> Result<(f64, Vec<f32>), LossError> {
    let (s, g) = ssim_grad(a, b)?;
    Ok((1.0 - s, g.into_iter().map(|v| -v).collect()))
}

/// SSIM in the scikit-image convention (`structural_similarity(gaussian_weights=True,
/// sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)`): reflect
/// padding, mean over the interior `[5:H-5, 5:W-5]` per channel, then over channels.
/// Needs images of at least 11×11 pixels.
pub fn ssim_skimage(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    same_size(&a, &b)?;
    let (w, h) = (a.width(), a.height());
    let min = 2 * RADIUS + 1;
    for (field, v) in [("width", w), ("height", h)] {
        if v < min {
            return Err(LossError::Value {
                field,
                value: v as f64,
                reason: "must be >= 11 pixels for the scikit-image SSIM (11-tap window)",
            });
        }
    }
    let means: Vec<f64> = (0..3)
        .into_par_iter()
        .map(|c| {
            let (_, map) = channel_map(&a, &b, c, Padding::Reflect);
            let mut sum = 0.0;
            for y in RADIUS..h - RADIUS {
                sum += map[y * w + RADIUS..y * w + w - RADIUS].iter().sum::<f64>();
            }
            sum / ((w - 2 * RADIUS) * (h - 2 * RADIUS)) as f64
        })
        .collect();
    Ok(means.iter().sum::<f64>() / 3.0)
}
