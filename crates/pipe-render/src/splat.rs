//! A visible Gaussian as the blend sees it: its conic, opacity, colour, the conservative
//! pixel region it can reach, and its alpha at a batch of pixel centres (3DGS `renderCUDA`
//! inner loop: `power = -½ dᵀ Σ'⁻¹ d`, `α = min(0.99, o·e^power)`, skip `α < 1/255`).

use crate::real::Real;

/// Largest alpha of one splat (3DGS clamp).
pub const ALPHA_MAX: f64 = 0.99;
/// Splats with a smaller alpha at a pixel are skipped.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Blending stops before a splat that would take the transmittance below this.
pub const T_MIN: f64 = 1e-4;

/// A visible Gaussian as the blend sees it, gathered per tile in depth order.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Splat<T> {
    pub mx: T,
    pub my: T,
    /// Conic `[[a, b], [b, c]]`.
    pub a: T,
    pub b: T,
    pub c: T,
    pub o: T,
    /// Conservative lower bound on `power` below which `alpha < 1/255` for sure
    /// (`ln(1/(255·o))` minus a margin far above rounding), so `exp` can be skipped.
    pub pmin: T,
    pub col: [T; 3],
    pub z: T,
    /// Pixel rows (global, half-open) outside which `power < pmin`: `[y0, y1]`.
    pub rows: [i64; 2],
    /// Row-interval coefficients of the widened ellipse (see [`Splat::row_span`]):
    /// centre `mx + slope·dy`, half-width² `k1·dy² + k2`.
    pub slope: f64,
    pub k1: f64,
    pub k2: f64,
}

impl<T: Real> Splat<T> {
    /// `cov` is the 2D covariance `[a, b, c]` whose inverse is `conic`.
    #[inline]
    pub fn new(mean2d: [T; 2], conic: [T; 3], cov: [T; 3], o: T, col: [T; 3], z: T) -> Self {
        let pmin = if o > T::ZERO {
            (T::ONE / (T::from_f64(255.0) * o)).ln() - T::from_f64(1e-3)
        } else {
            T::from_f64(f64::INFINITY)
        };
        // power >= pmin  <=>  dᵀ Q d <= r2 = -2·pmin (Q = conic), whose extent along y is
        // sqrt(r2·Σ_yy). Widened by 10% in r2 and 0.1 px against rounding of `power`.
        let r2m = -2.2 * pmin.to_f64();
        let (a, b, c) = (conic[0].to_f64(), conic[1].to_f64(), conic[2].to_f64());
        let mut out = Self {
            mx: mean2d[0],
            my: mean2d[1],
            a: conic[0],
            b: conic[1],
            c: conic[2],
            o,
            pmin,
            col,
            z,
            rows: [0; 2],
            slope: 0.0,
            k1: 0.0,
            k2: -1.0,
        };
        if r2m > 0.0 && a > 0.0 {
            let ey = (r2m * cov[2].to_f64()).sqrt() + 0.1;
            let my = mean2d[1].to_f64();
            // pixel centre j + 0.5 within [my - ey, my + ey]
            out.rows = [
                ceil_i64(my - ey - 0.5),
                floor_i64(my + ey - 0.5).saturating_add(1),
            ];
            // A dx² + 2B dx dy + C dy² <= r2m at fixed dy:
            // dx in -B dy/A ± sqrt((B² - AC) dy² + A r2m)/A
            out.slope = b / a;
            out.k1 = (b * b - a * c) / (a * a);
            out.k2 = r2m / a;
            if !(out.slope.is_finite() && out.k1.is_finite() && out.k2.is_finite()) {
                // degenerate (e.g. an underflowing conic of a huge Gaussian): whole rows
                (out.slope, out.k1, out.k2) = (0.0, 0.0, f64::INFINITY);
            }
        }
        out
    }

    /// Tile-local rows `[ly0, ly1)` of the tile rows `[y0, y1)` the splat may reach.
    #[inline]
    pub fn local_rows(&self, y0: usize, y1: usize) -> Option<(usize, usize)> {
        let l = self.rows[0].max(y0 as i64);
        let h = self.rows[1].min(y1 as i64);
        (l < h).then(|| ((l as usize) - y0, (h as usize) - y0))
    }

    /// Tile-local columns `[lx0, lx1)` of row `y` (global) inside the widened ellipse
    /// `A dx² + 2B dx dy + C dy² <= r2m` (plus 0.1 px), clipped to the tile columns `[x0, x1)`.
    #[inline]
    pub fn row_span(&self, y: usize, x0: usize, x1: usize) -> Option<(usize, usize)> {
        let dy = self.my.to_f64() - (y as f64 + 0.5);
        let h2 = self.k1 * dy * dy + self.k2;
        if h2.is_nan() || h2 < 0.0 {
            return None;
        }
        let half = h2.sqrt() + 0.1;
        // dx = mx - px, so px in mx + slope·dy ± half; pixel centre px = i + 0.5
        let centre = self.mx.to_f64() + self.slope * dy - 0.5;
        let l = ceil_i64(centre - half).max(x0 as i64);
        let h = (floor_i64(centre + half).saturating_add(1)).min(x1 as i64);
        (l < h).then(|| ((l as usize) - x0, (h as usize) - x0))
    }
}

/// `floor(v)` as an integer without a libm call (saturating, NaN -> 0).
#[inline(always)]
fn floor_i64(v: f64) -> i64 {
    let i = v as i64;
    if (i as f64) > v {
        i.saturating_sub(1)
    } else {
        i
    }
}

/// `ceil(v)` as an integer without a libm call (saturating, NaN -> 0).
#[inline(always)]
fn ceil_i64(v: f64) -> i64 {
    let i = v as i64;
    if (i as f64) < v {
        i.saturating_add(1)
    } else {
        i
    }
}

/// Pixels per batch along a row: the alpha of a batch is computed branch-free so that it
/// vectorises; the stateful per-pixel update stays scalar.
pub(crate) const LANES: usize = 8;

/// A splat evaluated at `N` consecutive pixel centres of one row.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hits<T, const N: usize> {
    /// `min(0.99, o·e^power)`, or 0 where the pixel is skipped (`power > 0`, `power < pmin`
    /// or `alpha < 1/255`); a kept alpha is >= 1/255, so 0 is unambiguous.
    pub alpha: [T; N],
    /// `o·exp(power)` before the 0.99 clamp.
    pub raw: [T; N],
    /// `exp(power)`.
    pub gauss: [T; N],
    /// `mx - px`.
    pub dx: [T; N],
}

/// `dx = mx - px`, `power = -½(a dx² + c dy²) - b dx dy`, `alpha = min(0.99, o e^power)` at
/// the pixel centres `px0 + l` (l < N) of the row with centre `py`; lanes `l >= n` are
/// skipped. Forward and backward both use this, so they take bit-identical skip decisions.
#[inline(always)]
pub(crate) fn hits<T: Real, const N: usize>(s: &Splat<T>, px0: T, py: T, n: usize) -> Hits<T, N> {
    let dy = s.my - py;
    let cdy2 = s.c * dy * dy;
    let mut h = Hits {
        alpha: [T::ZERO; N],
        raw: [T::ZERO; N],
        gauss: [T::ZERO; N],
        dx: [T::ZERO; N],
    };
    let (amax, amin) = (T::from_f64(ALPHA_MAX), T::from_f64(ALPHA_MIN));
    for l in 0..N {
        let dx = s.mx - (px0 + T::from_f64(l as f64));
        let power = T::from_f64(-0.5) * (s.a * dx * dx + cdy2) - s.b * dx * dy;
        let gauss = power.exp_fast();
        let raw = s.o * gauss;
        let alpha = raw.min(amax);
        let skip = (power > T::ZERO) | (power < s.pmin) | (alpha < amin) | (l >= n);
        h.alpha[l] = if skip { T::ZERO } else { alpha };
        h.raw[l] = raw;
        h.gauss[l] = gauss;
        h.dx[l] = dx;
    }
    h
}
