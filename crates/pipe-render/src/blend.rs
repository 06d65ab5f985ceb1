//! Per-tile alpha blending, forward and backward (3DGS `renderCUDA` and its backward).
//!
//! Within a tile the splats are visited in depth order and each one updates only the pixels
//! inside a conservative ellipse around it (the `α >= 1/255` ellipse, widened; see
//! [`Splat::row_span`]), row by row in batches of [`LANES`] pixels evaluated branch-free,
//! while the per-pixel running state (transmittance, colour, ...) lives in small per-tile
//! arrays. Per pixel this performs the same floating-point operations, in the same order, as
//! the per-pixel loop of the reference; it only skips pixels a splat cannot reach. Forward
//! and backward share [`hits`], so they take bit-identical skip decisions.
//!
//! For `f32` on x86-64 CPUs with AVX-512 or AVX2+FMA (detected at run time), the tiles go to
//! the explicit vector kernels of `crate::simd` instead: same rules and per-pixel order,
//! rounding aside (fused multiply-adds); `f64` and other CPUs use the portable loops here.

// Lane loops index several fixed-size arrays in lock step so that they vectorise.
#![allow(clippy::needless_range_loop)]

use crate::real::Real;
use crate::splat::{ALPHA_MAX, LANES, Splat, T_MIN, hits};

/// Calls `f::<8>` then `f::<4>` over the columns `[lx0, lx1)`: full batches of [`LANES`],
/// and a tail of at most 4 lanes in a narrower batch.
macro_rules! for_batches {
    ($lx0:expr, $lx1:expr, |$lxb:ident, $n:ident| $wide:block, $narrow:block) => {{
        let mut $lxb = $lx0;
        while $lxb < $lx1 {
            let $n = $lx1 - $lxb;
            if $n > LANES / 2 {
                $wide
                $lxb += LANES;
            } else {
                $narrow
                $lxb += LANES / 2;
            }
        }
    }};
}

/// A tile's pixel rectangle `[x0, x1) × [y0, y1)` in global pixel coordinates.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TileRect {
    pub x0: usize,
    pub x1: usize,
    pub y0: usize,
    pub y1: usize,
}

impl TileRect {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    pub fn n_pixels(&self) -> usize {
        self.width() * (self.y1 - self.y0)
    }
}

/// Row stride of the per-tile state arrays: a batch of [`LANES`] starting at any column of
/// the tile stays in bounds; lanes past the row span are masked off.
pub(crate) const STRIDE: usize = crate::camera::TILE as usize + LANES;
const TILE_ROWS: usize = crate::camera::TILE as usize;

fn lanes<X, const N: usize>(v: &mut [X], o: usize) -> &mut [X; N] {
    (&mut v[o..o + N]).try_into().expect("N-long slice")
}

/// Forward per-pixel state of one tile, structure of arrays, row stride [`STRIDE`].
#[derive(Debug, Clone, Default)]
pub(crate) struct TileForward<T> {
    /// Transmittance.
    pub t: Vec<T>,
    /// Accumulated colour (without background).
    pub rgb: [Vec<T>; 3],
    /// Accumulated `Σ w_i z_i`.
    pub z: Vec<T>,
    /// Blended splats (i32: signed lane compares are native in SSE2).
    pub count: Vec<i32>,
    /// 1 + list position of the last blended splat.
    pub last: Vec<i32>,
    /// 1 once the pixel stopped (T would fall below 1e-4), else 0 (i32 like the lanes).
    pub done: Vec<i32>,
}

impl<T: Real> TileForward<T> {
    pub fn reset(&mut self) {
        let n = TILE_ROWS * STRIDE;
        let fill = |v: &mut Vec<T>, x: T| {
            v.clear();
            v.resize(n, x);
        };
        fill(&mut self.t, T::ONE);
        self.rgb.iter_mut().for_each(|v| fill(v, T::ZERO));
        fill(&mut self.z, T::ZERO);
        self.count.clear();
        self.count.resize(n, 0);
        self.last.clear();
        self.last.resize(n, 0);
        self.done.clear();
        self.done.resize(n, 0);
    }
}

/// Blends splat `s` into the `N` pixels at state offset `o` (row centre `py`, first pixel
/// centre `px0`, `n` valid lanes); returns how many pixels stopped (T < 1e-4).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn forward_batch<T: Real, const N: usize>(
    s: &Splat<T>,
    st: &mut TileForward<T>,
    o: usize,
    px0: T,
    py: T,
    n: usize,
    next: i32,
    t_min: T,
) -> usize {
    let h = hits::<T, N>(s, px0, py, n);
    if h.alpha.iter().all(|&a| a == T::ZERO) {
        return 0;
    }
    let t = lanes::<T, N>(&mut st.t, o);
    let done = lanes::<i32, N>(&mut st.done, o);
    let count = lanes::<i32, N>(&mut st.count, o);
    let last = lanes::<i32, N>(&mut st.last, o);
    let mut w = [T::ZERO; N];
    let mut stops = 0i32;
    for l in 0..N {
        let alpha = h.alpha[l];
        let keep = (alpha != T::ZERO) & (done[l] == 0);
        let test_t = t[l] * (T::ONE - alpha);
        let stop = keep & (test_t < t_min);
        let blend = keep & !stop;
        w[l] = if blend { alpha * t[l] } else { T::ZERO };
        t[l] = if blend { test_t } else { t[l] };
        count[l] += blend as i32;
        last[l] = if blend { next } else { last[l] };
        done[l] |= stop as i32;
        stops += stop as i32;
    }
    for (c, acc) in st.rgb.iter_mut().enumerate() {
        let acc = lanes::<T, N>(acc, o);
        for l in 0..N {
            acc[l] += s.col[c] * w[l];
        }
    }
    let z = lanes::<T, N>(&mut st.z, o);
    for l in 0..N {
        z[l] += s.z * w[l];
    }
    stops as usize
}

/// Front-to-back blend of one tile into `st` (pixel `(lx, ly)` at `ly·STRIDE + lx`): the
/// AVX-512 or AVX2 kernel for `f32` where the CPU has one, else [`forward_tile_portable`].
pub(crate) fn forward_tile<T: Real>(splats: &[Splat<T>], r: TileRect, st: &mut TileForward<T>) {
    #[cfg(target_arch = "x86_64")]
    if let Some(st32) = (st as &mut dyn std::any::Any).downcast_mut::<TileForward<f32>>()
        && let Some(k) = crate::simd::kernel()
    {
        return crate::simd::forward_tile(k, splats, r, st32);
    }
    forward_tile_portable(splats, r, st);
}

/// [`forward_tile`] with the lane loops left to the compiler (any `T`, any CPU).
pub(crate) fn forward_tile_portable<T: Real>(
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileForward<T>,
) {
    debug_assert!(r.x1 > r.x0 && r.y1 > r.y0 && r.width() <= TILE_ROWS && r.y1 - r.y0 <= TILE_ROWS);
    debug_assert!(splats.len() < i32::MAX as usize);
    st.reset();
    let n_pix = r.n_pixels();
    let mut n_done = 0;
    let t_min = T::from_f64(T_MIN);
    for (pos, s) in splats.iter().enumerate() {
        let Some((ly0, ly1)) = s.local_rows(r.y0, r.y1) else {
            continue;
        };
        let next = pos as i32 + 1;
        for ly in ly0..ly1 {
            let Some((lx0, lx1)) = s.row_span(r.y0 + ly, r.x0, r.x1) else {
                continue;
            };
            let py = T::from_f64((r.y0 + ly) as f64 + 0.5);
            let o = ly * STRIDE;
            let px0 = r.x0 as f64 + 0.5;
            for_batches!(
                lx0,
                lx1,
                |lxb, n| {
                    n_done += forward_batch::<T, LANES>(
                        s,
                        st,
                        o + lxb,
                        T::from_f64(px0 + lxb as f64),
                        py,
                        n,
                        next,
                        t_min,
                    );
                },
                {
                    n_done += forward_batch::<T, { LANES / 2 }>(
                        s,
                        st,
                        o + lxb,
                        T::from_f64(px0 + lxb as f64),
                        py,
                        n,
                        next,
                        t_min,
                    );
                }
            );
        }
        if n_done == n_pix {
            break;
        }
    }
}

/// Backward per-pixel inputs and running state of one tile, row stride [`STRIDE`].
#[derive(Debug, Clone, Default)]
pub(crate) struct TileBackward<T> {
    /// `dL/dC` per channel.
    pub dc: [Vec<T>; 3],
    /// `dL/d alpha_out · T_final`.
    pub da_tn: Vec<T>,
    /// Running `T_i`, starts at `T_final`.
    pub t: Vec<T>,
    /// Running `S_i = Σ_{j>i} c_j α_j T_j + T_final·bg` per channel.
    pub acc: [Vec<T>; 3],
    /// 1 + list position of the last blended splat (0 for padding lanes).
    pub last: Vec<i32>,
}

impl<T: Real> TileBackward<T> {
    /// Clears to the padded size; the caller then sets every pixel of the tile.
    pub fn reset(&mut self) {
        let n = TILE_ROWS * STRIDE;
        let fill = |v: &mut Vec<T>| {
            v.clear();
            v.resize(n, T::ZERO);
        };
        self.dc.iter_mut().chain(self.acc.iter_mut()).for_each(fill);
        fill(&mut self.da_tn);
        fill(&mut self.t);
        self.last.clear();
        self.last.resize(n, 0);
    }
}

/// Gradient of one splat's blend inputs (before the per-Gaussian reduction).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SplatGrad<T> {
    pub mean2d: [T; 2],
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
}

/// Backward of splat `s` (list position `pos`) over the `N` pixels at state offset `o`,
/// accumulating its gradients into the first `N` lanes of `acc`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn backward_batch<T: Real, const N: usize>(
    s: &Splat<T>,
    st: &mut TileBackward<T>,
    o: usize,
    px0: T,
    py: T,
    n: usize,
    pos: i32,
    acc: &mut [[T; LANES]; 9],
) {
    let h = hits::<T, N>(s, px0, py, n);
    let last = lanes::<i32, N>(&mut st.last, o);
    // non-short-circuit `&` and selects keep the lane loops branch-free (vectorised)
    let mut a = [T::ZERO; N];
    let mut geo = [T::ZERO; N];
    for l in 0..N {
        let m = (h.alpha[l] != T::ZERO) & (pos < last[l]);
        a[l] = if m { h.alpha[l] } else { T::ZERO };
        geo[l] = if m & (h.raw[l] <= T::from_f64(ALPHA_MAX)) {
            T::ONE
        } else {
            T::ZERO
        };
    }
    if a.iter().all(|&v| v == T::ZERO) {
        return;
    }
    let dy = s.my - py;
    let half = T::from_f64(0.5);
    // T_i = T_{i+1}/(1 - α_i); masked lanes have α = 0: T unchanged, w = 0
    let mut inv = [T::ZERO; N];
    let mut w = [T::ZERO; N];
    let t = lanes::<T, N>(&mut st.t, o);
    for l in 0..N {
        inv[l] = T::ONE / (T::ONE - a[l]);
        t[l] *= inv[l];
        w[l] = a[l] * t[l];
    }
    // dC/dα_i = c_i T_i - S_i/(1 - α_i); d(1 - T_N)/dα_i = T_N/(1 - α_i)
    let mut g_alpha = [T::ZERO; N];
    let da = lanes::<T, N>(&mut st.da_tn, o);
    for l in 0..N {
        g_alpha[l] = da[l] * inv[l];
    }
    for c in 0..3 {
        let dc = lanes::<T, N>(&mut st.dc[c], o);
        let sacc = lanes::<T, N>(&mut st.acc[c], o);
        for l in 0..N {
            acc[c][l] += dc[l] * w[l];
            g_alpha[l] += dc[l] * (s.col[c] * t[l] - sacc[l] * inv[l]);
            sacc[l] += s.col[c] * w[l];
        }
    }
    // through α = o·exp(power); zero where masked or clamped at 0.99
    for l in 0..N {
        let ga = g_alpha[l] * geo[l];
        acc[3][l] += h.gauss[l] * ga;
        let g_pow = h.raw[l] * ga;
        let dx = h.dx[l];
        acc[4][l] -= g_pow * (s.a * dx + s.b * dy);
        acc[5][l] -= g_pow * (s.c * dy + s.b * dx);
        acc[6][l] -= half * g_pow * dx * dx;
        acc[7][l] -= g_pow * dx * dy;
        acc[8][l] -= half * g_pow * dy * dy;
    }
}

/// Back-to-front backward of one tile; writes one gradient per splat into `out`: the
/// AVX-512 or AVX2 kernel for `f32` where the CPU has one, else [`backward_tile_portable`].
pub(crate) fn backward_tile<T: Real>(
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileBackward<T>,
    out: &mut [SplatGrad<T>],
) {
    #[cfg(target_arch = "x86_64")]
    if let Some(st32) = (st as &mut dyn std::any::Any).downcast_mut::<TileBackward<f32>>()
        && let Some(k) = crate::simd::kernel()
    {
        return crate::simd::backward_tile(k, splats, r, st32, out);
    }
    backward_tile_portable(splats, r, st, out);
}

/// [`backward_tile`] with the lane loops left to the compiler (any `T`, any CPU).
pub(crate) fn backward_tile_portable<T: Real>(
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileBackward<T>,
    out: &mut [SplatGrad<T>],
) {
    debug_assert_eq!(splats.len(), out.len());
    debug_assert!(splats.len() < i32::MAX as usize);
    // splats behind every pixel's last contributor get no gradient
    let max_last = st.last.iter().copied().max().unwrap_or(0).max(0) as usize;
    let end = max_last.min(splats.len());
    out[end..].fill(SplatGrad::default());
    for (pos, (s, g)) in splats[..end]
        .iter()
        .zip(out[..end].iter_mut())
        .enumerate()
        .rev()
    {
        let Some((ly0, ly1)) = s.local_rows(r.y0, r.y1) else {
            continue;
        };
        let pos = pos as i32;
        // per-lane partial sums (colour 0..3, opacity 3, mean2d 4..6, conic 6..9), reduced in
        // lane order at the end
        let mut acc = [[T::ZERO; LANES]; 9];
        for ly in ly0..ly1 {
            let Some((lx0, lx1)) = s.row_span(r.y0 + ly, r.x0, r.x1) else {
                continue;
            };
            let py = T::from_f64((r.y0 + ly) as f64 + 0.5);
            let o = ly * STRIDE;
            let px0 = r.x0 as f64 + 0.5;
            for_batches!(
                lx0,
                lx1,
                |lxb, n| {
                    backward_batch::<T, LANES>(
                        s,
                        st,
                        o + lxb,
                        T::from_f64(px0 + lxb as f64),
                        py,
                        n,
                        pos,
                        &mut acc,
                    );
                },
                {
                    backward_batch::<T, { LANES / 2 }>(
                        s,
                        st,
                        o + lxb,
                        T::from_f64(px0 + lxb as f64),
                        py,
                        n,
                        pos,
                        &mut acc,
                    );
                }
            );
        }
        let sum = |v: &[T; LANES]| v.iter().fold(T::ZERO, |a, &b| a + b);
        *g = SplatGrad {
            mean2d: [sum(&acc[4]), sum(&acc[5])],
            conic: [sum(&acc[6]), sum(&acc[7]), sum(&acc[8])],
            opacity: sum(&acc[3]),
            color: [sum(&acc[0]), sum(&acc[1]), sum(&acc[2])],
        };
    }
}
