//! Real spherical harmonics up to degree 3 in the 3DGS / gsplat basis and sign convention.
//!
//! `rgb = max(0, Σ_k Y_k(d)·sh_k + 0.5)` with `d` the unit vector from the camera centre to
//! the Gaussian mean (or `Rᵀ·d` for SH turned with a deformation's rotation `R`,
//! [`rotate_dir`]). Coefficients from Sloan, "Stupid SH tricks" (as used by 3DGS).

use crate::real::Real;

const C0: f64 = 0.282_094_791_773_878_14;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Basis values `Y_0..Y_{(deg+1)²-1}` at the unit direction `d`; unused entries are 0.
#[inline]
pub fn basis<T: Real>(degree: u32, d: [T; 3]) -> [T; 16] {
    let f = T::from_f64;
    let [x, y, z] = d;
    let mut out = [T::ZERO; 16];
    out[0] = f(C0);
    if degree >= 1 {
        out[1] = -f(C1) * y;
        out[2] = f(C1) * z;
        out[3] = -f(C1) * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        out[4] = f(C2[0]) * x * y;
        out[5] = f(C2[1]) * y * z;
        out[6] = f(C2[2]) * (f(2.0) * zz - xx - yy);
        out[7] = f(C2[3]) * x * z;
        out[8] = f(C2[4]) * (xx - yy);
        if degree >= 3 {
            out[9] = f(C3[0]) * y * (f(3.0) * xx - yy);
            out[10] = f(C3[1]) * x * y * z;
            out[11] = f(C3[2]) * y * (f(4.0) * zz - xx - yy);
            out[12] = f(C3[3]) * z * (f(2.0) * zz - f(3.0) * xx - f(3.0) * yy);
            out[13] = f(C3[4]) * x * (f(4.0) * zz - xx - yy);
            out[14] = f(C3[5]) * z * (xx - yy);
            out[15] = f(C3[6]) * x * (xx - f(3.0) * yy);
        }
    }
    out
}

/// `Σ_k w_k ∇_d Y_k(d)`, the gradient w.r.t. `d` treated as a free 3-vector (the caller
/// chains through the normalisation `d = v/|v|`).
#[inline]
pub fn basis_vjp<T: Real>(degree: u32, d: [T; 3], w: &[T; 16]) -> [T; 3] {
    let f = T::from_f64;
    let [x, y, z] = d;
    let mut g = [T::ZERO; 3];
    if degree == 0 {
        return g;
    }
    g[1] += -f(C1) * w[1];
    g[2] += f(C1) * w[2];
    g[0] += -f(C1) * w[3];
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        // Y4 = c·xy
        g[0] += f(C2[0]) * y * w[4];
        g[1] += f(C2[0]) * x * w[4];
        // Y5 = c·yz
        g[1] += f(C2[1]) * z * w[5];
        g[2] += f(C2[1]) * y * w[5];
        // Y6 = c·(2z² - x² - y²)
        g[0] += f(-2.0 * C2[2]) * x * w[6];
        g[1] += f(-2.0 * C2[2]) * y * w[6];
        g[2] += f(4.0 * C2[2]) * z * w[6];
        // Y7 = c·xz
        g[0] += f(C2[3]) * z * w[7];
        g[2] += f(C2[3]) * x * w[7];
        // Y8 = c·(x² - y²)
        g[0] += f(2.0 * C2[4]) * x * w[8];
        g[1] += f(-2.0 * C2[4]) * y * w[8];
        if degree >= 3 {
            // Y9 = c·y(3x² - y²)
            g[0] += f(6.0 * C3[0]) * x * y * w[9];
            g[1] += f(3.0 * C3[0]) * (xx - yy) * w[9];
            // Y10 = c·xyz
            g[0] += f(C3[1]) * y * z * w[10];
            g[1] += f(C3[1]) * x * z * w[10];
            g[2] += f(C3[1]) * x * y * w[10];
            // Y11 = c·y(4z² - x² - y²)
            g[0] += f(-2.0 * C3[2]) * x * y * w[11];
            g[1] += f(C3[2]) * (f(4.0) * zz - xx - f(3.0) * yy) * w[11];
            g[2] += f(8.0 * C3[2]) * y * z * w[11];
            // Y12 = c·z(2z² - 3x² - 3y²)
            g[0] += f(-6.0 * C3[3]) * x * z * w[12];
            g[1] += f(-6.0 * C3[3]) * y * z * w[12];
            g[2] += f(3.0 * C3[3]) * (f(2.0) * zz - xx - yy) * w[12];
            // Y13 = c·x(4z² - x² - y²)
            g[0] += f(C3[4]) * (f(4.0) * zz - f(3.0) * xx - yy) * w[13];
            g[1] += f(-2.0 * C3[4]) * x * y * w[13];
            g[2] += f(8.0 * C3[4]) * x * z * w[13];
            // Y14 = c·z(x² - y²)
            g[0] += f(2.0 * C3[5]) * x * z * w[14];
            g[1] += f(-2.0 * C3[5]) * y * z * w[14];
            g[2] += f(C3[5]) * (xx - yy) * w[14];
            // Y15 = c·x(x² - 3y²)
            g[0] += f(3.0 * C3[6]) * (xx - yy) * w[15];
            g[1] += f(-6.0 * C3[6]) * x * y * w[15];
        }
    }
    g
}

/// Unit view direction from `center` to `mean` and the distance; `([0;3], 0)` when they
/// coincide.
#[inline]
pub fn view_dir<T: Real>(mean: [T; 3], center: [T; 3]) -> ([T; 3], T) {
    let v = [
        mean[0] - center[0],
        mean[1] - center[1],
        mean[2] - center[2],
    ];
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > T::ZERO {
        (v.map(|c| c / n), n)
    } else {
        ([T::ZERO; 3], T::ZERO)
    }
}

/// Evaluates the colour. Returns the RGB and, per channel, whether the clamp at 0 was active.
#[inline]
pub fn eval<T: Real>(degree: u32, coeffs: &[[T; 3]], dir: [T; 3]) -> ([T; 3], [bool; 3]) {
    let y = basis(degree, dir);
    let mut raw = [T::from_f64(0.5); 3];
    for (k, c) in coeffs.iter().enumerate() {
        for ch in 0..3 {
            raw[ch] += y[k] * c[ch];
        }
    }
    let clamped = raw.map(|r| r < T::ZERO);
    (raw.map(|r| r.max(T::ZERO)), clamped)
}

/// `Rᵀ·d` for a row-major 3×3 `R` (`r[3·row + col]`): SH turned with `R` show towards `d`
/// what they showed towards `Rᵀ·d` (PhysGaussian §4.1).
#[inline]
pub fn rotate_dir<T: Real>(r: &[T; 9], d: [T; 3]) -> [T; 3] {
    std::array::from_fn(|i| r[i] * d[0] + r[3 + i] * d[1] + r[6 + i] * d[2])
}

/// Backward of [`eval`]: writes `dL/d coeffs` into `g_coeffs` and returns `dL/d mean` through
/// the view direction (`dist` is `|mean - center|`).
#[inline]
pub fn eval_vjp<T: Real>(
    degree: u32,
    coeffs: &[[T; 3]],
    dir: [T; 3],
    dist: T,
    clamped: [bool; 3],
    g_rgb: [T; 3],
    g_coeffs: &mut [[T; 3]],
) -> [T; 3] {
    let w = coeffs_vjp(degree, coeffs, dir, clamped, g_rgb, g_coeffs);
    if degree == 0 || dist <= T::ZERO {
        return [T::ZERO; 3];
    }
    let g_dir = basis_vjp(degree, dir, &w);
    normalize_vjp(dir, dist, g_dir)
}

/// Backward of [`eval`] at the turned direction `d' = Rᵀ·d` ([`rotate_dir`]), `(d, dist)` from
/// [`view_dir`]: writes `dL/d coeffs` into `g_coeffs` and returns `(dL/d mean, dL/dR)`, with
/// `dL/dR[j][i] = d_j·(dL/dd')_i` and `dL/dd = R·dL/dd'` chained through the normalisation.
#[inline]
pub fn eval_rotated_vjp<T: Real>(
    degree: u32,
    coeffs: &[[T; 3]],
    (dir, dist): ([T; 3], T),
    r: &[T; 9],
    clamped: [bool; 3],
    g_rgb: [T; 3],
    g_coeffs: &mut [[T; 3]],
) -> ([T; 3], [T; 9]) {
    let turned = rotate_dir(r, dir);
    let w = coeffs_vjp(degree, coeffs, turned, clamped, g_rgb, g_coeffs);
    if degree == 0 || dist <= T::ZERO {
        return ([T::ZERO; 3], [T::ZERO; 9]);
    }
    let g_turned = basis_vjp(degree, turned, &w);
    let g_r = std::array::from_fn(|e| dir[e / 3] * g_turned[e % 3]);
    let g_dir = std::array::from_fn(|j| {
        r[3 * j] * g_turned[0] + r[3 * j + 1] * g_turned[1] + r[3 * j + 2] * g_turned[2]
    });
    (normalize_vjp(dir, dist, g_dir), g_r)
}

/// Writes `dL/d coeffs = Y(dir)·g_raw` into `g_coeffs` and returns the per-basis weights
/// `w_k = Σ_ch coeffs_k·g_raw` that [`basis_vjp`] takes (`g_raw` is 0 on clamped channels).
#[inline]
fn coeffs_vjp<T: Real>(
    degree: u32,
    coeffs: &[[T; 3]],
    dir: [T; 3],
    clamped: [bool; 3],
    g_rgb: [T; 3],
    g_coeffs: &mut [[T; 3]],
) -> [T; 16] {
    let g_raw: [T; 3] = std::array::from_fn(|ch| if clamped[ch] { T::ZERO } else { g_rgb[ch] });
    let y = basis(degree, dir);
    let mut w = [T::ZERO; 16];
    for (k, (c, gc)) in coeffs.iter().zip(g_coeffs.iter_mut()).enumerate() {
        for ch in 0..3 {
            gc[ch] = y[k] * g_raw[ch];
            w[k] += c[ch] * g_raw[ch];
        }
    }
    w
}

/// `d = v/|v|`: `dL/dv = (g - d (d·g)) / |v|`.
#[inline]
fn normalize_vjp<T: Real>(dir: [T; 3], dist: T, g_dir: [T; 3]) -> [T; 3] {
    let dot = g_dir[0] * dir[0] + g_dir[1] * dir[1] + g_dir[2] * dir[2];
    std::array::from_fn(|i| (g_dir[i] - dir[i] * dot) / dist)
}
