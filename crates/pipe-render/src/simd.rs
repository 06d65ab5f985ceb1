//! AVX2+FMA and AVX-512 kernels of the `f32` blend, selected at run time (see
//! [`crate::blend`]).
//!
//! They compute what the portable lane loops of [`crate::blend`] compute, on 8 (AVX2) or 16
//! (AVX-512) pixels per vector: the same skip rules, stop rule and per-pixel order of splats,
//! so only the rounding differs (fused multiply-adds, the exponential below). Forward and
//! backward evaluate a splat through the same [`hits`], so they keep taking identical skip
//! decisions.
//!
//! Layout: a tile row is cut into aligned halves of 8 columns (AVX2) or taken whole
//! (AVX-512), so every splat reads and writes the per-pixel state at the same offsets. Per
//! splat, [`row_masks`] picks the (row, half) batches that meet the widened `α >= 1/255`
//! ellipse of [`Splat::row_span`]; inside a batch the skip rules alone decide, so a pixel
//! is evaluated at most once per splat and nothing outside the ellipse is blended.
//!
//! The CPU features are checked once (`pulp` caches the answer) and the kernels run inside
//! `pulp`'s `vectorize`, which enables them for everything inlined into it: every helper
//! here is `#[inline(always)]` for that reason.

use std::arch::x86_64::{__m128, __m256, __m256i, __m512, __m512i};

use pulp::x86::{V3, V4};

use crate::blend::{STRIDE, SplatGrad, TileBackward, TileForward, TileRect};
use crate::real::Real;
use crate::splat::{ALPHA_MAX, ALPHA_MIN, Splat, T_MIN};

/// Tile side.
const TILE: usize = crate::camera::TILE as usize;
/// Length of the per-tile state arrays used here.
const STATE: usize = TILE * STRIDE;

/// The best vector kernel this CPU runs, if any.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Kernel {
    /// AVX2 + FMA, 8 lanes.
    Avx2(V3),
    /// AVX-512 (F, BW, CD, DQ, VL), 16 lanes.
    Avx512(V4),
}

/// The vector kernel for this CPU: AVX-512 if present, else AVX2+FMA, else none.
#[inline]
pub(crate) fn kernel() -> Option<Kernel> {
    V4::try_new()
        .map(Kernel::Avx512)
        .or_else(|| V3::try_new().map(Kernel::Avx2))
}

/// The lane operations the kernels need; `F` holds f32 lanes, `I` i32 lanes, `M` a lane mask.
trait Simd: Copy {
    /// Lanes per vector (8 or 16; a tile row is `16 / W` batches).
    const W: usize;
    type F: Copy;
    type I: Copy;
    type M: Copy;
    /// The AVX2 token (for the f64 row masks, 4 rows at a time).
    fn v3(self) -> V3;
    fn splat(self, x: f32) -> Self::F;
    fn splat_i(self, x: i32) -> Self::I;
    /// Lane `l` holds `l`.
    fn iota(self) -> Self::F;
    fn add(self, a: Self::F, b: Self::F) -> Self::F;
    fn sub(self, a: Self::F, b: Self::F) -> Self::F;
    fn mul(self, a: Self::F, b: Self::F) -> Self::F;
    fn div(self, a: Self::F, b: Self::F) -> Self::F;
    /// `min(a, b)`, `b` if either is NaN (as `f32::min` with a finite `b`).
    fn min(self, a: Self::F, b: Self::F) -> Self::F;
    fn max(self, a: Self::F, b: Self::F) -> Self::F;
    /// `a·b + c`, one rounding.
    fn fma(self, a: Self::F, b: Self::F, c: Self::F) -> Self::F;
    /// `c - a·b`, one rounding.
    fn fnma(self, a: Self::F, b: Self::F, c: Self::F) -> Self::F;
    /// `a·b - c`, one rounding.
    fn fms(self, a: Self::F, b: Self::F, c: Self::F) -> Self::F;
    /// `a < b` (false on NaN).
    fn lt(self, a: Self::F, b: Self::F) -> Self::M;
    /// `a <= b` (false on NaN).
    fn le(self, a: Self::F, b: Self::F) -> Self::M;
    /// `!(a > b)` (true on NaN).
    fn not_gt(self, a: Self::F, b: Self::F) -> Self::M;
    /// `!(a < b)` (true on NaN).
    fn not_lt(self, a: Self::F, b: Self::F) -> Self::M;
    fn and(self, a: Self::M, b: Self::M) -> Self::M;
    /// `!a & b`.
    fn andnot(self, a: Self::M, b: Self::M) -> Self::M;
    /// `a` in the lanes of `m`, 0 elsewhere.
    fn masked(self, m: Self::M, a: Self::F) -> Self::F;
    /// `m ? a : b` per lane.
    fn select(self, m: Self::M, a: Self::F, b: Self::F) -> Self::F;
    /// Bit `l` set iff lane `l` of `m` is.
    fn bits(self, m: Self::M) -> u32;
    /// Lanes `l < n`.
    fn first(self, n: usize) -> Self::M;
    /// `2^n` where `t = 1.5·2^23 + n` (integer `n` in `[-126, 127]`).
    fn pow2(self, t: Self::F) -> Self::F;
    /// Sum of the lanes in a fixed order.
    fn hsum(self, a: Self::F) -> f32;
    fn load(self, v: &[f32; STATE], o: usize) -> Self::F;
    fn store(self, v: &mut [f32; STATE], o: usize, x: Self::F);
    fn load_i(self, v: &[i32; STATE], o: usize) -> Self::I;
    fn store_i(self, v: &mut [i32; STATE], o: usize, x: Self::I);
    /// `a > b` on i32 lanes.
    fn gt_i(self, a: Self::I, b: Self::I) -> Self::M;
    /// Nonzero i32 lanes.
    fn nonzero_i(self, a: Self::I) -> Self::M;
    /// -1 in the lanes of `m`, 0 elsewhere.
    fn mask_i(self, m: Self::M) -> Self::I;
    /// `a + 1` in the lanes of `m`, `a` elsewhere.
    fn inc_i(self, a: Self::I, m: Self::M) -> Self::I;
    /// `m ? a : b` on i32 lanes.
    fn select_i(self, m: Self::M, a: Self::I, b: Self::I) -> Self::I;
}

/// `&v[o..o + N]` as an array (in bounds for the batch offsets here: see [`offset`]).
#[inline(always)]
fn at<X: Copy, const N: usize>(v: &[X; STATE], o: usize) -> [X; N] {
    v[o..o + N].try_into().expect("N lanes")
}

impl Simd for V3 {
    const W: usize = 8;
    type F = __m256;
    type I = __m256i;
    type M = __m256;
    #[inline(always)]
    fn v3(self) -> V3 {
        self
    }
    #[inline(always)]
    fn splat(self, x: f32) -> __m256 {
        self.avx._mm256_set1_ps(x)
    }
    #[inline(always)]
    fn splat_i(self, x: i32) -> __m256i {
        self.avx._mm256_set1_epi32(x)
    }
    #[inline(always)]
    fn iota(self) -> __m256 {
        self.avx
            ._mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)
    }
    #[inline(always)]
    fn add(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_add_ps(a, b)
    }
    #[inline(always)]
    fn sub(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_sub_ps(a, b)
    }
    #[inline(always)]
    fn mul(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_mul_ps(a, b)
    }
    #[inline(always)]
    fn div(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_div_ps(a, b)
    }
    #[inline(always)]
    fn min(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_min_ps(a, b)
    }
    #[inline(always)]
    fn max(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_max_ps(a, b)
    }
    #[inline(always)]
    fn fma(self, a: __m256, b: __m256, c: __m256) -> __m256 {
        self.fma._mm256_fmadd_ps(a, b, c)
    }
    #[inline(always)]
    fn fnma(self, a: __m256, b: __m256, c: __m256) -> __m256 {
        self.fma._mm256_fnmadd_ps(a, b, c)
    }
    #[inline(always)]
    fn fms(self, a: __m256, b: __m256, c: __m256) -> __m256 {
        self.fma._mm256_fmsub_ps(a, b, c)
    }
    #[inline(always)]
    fn lt(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_cmp_ps::<0x11>(a, b) // _CMP_LT_OQ
    }
    #[inline(always)]
    fn le(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_cmp_ps::<0x12>(a, b) // _CMP_LE_OQ
    }
    #[inline(always)]
    fn not_gt(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_cmp_ps::<0x1a>(a, b) // _CMP_NGT_UQ
    }
    #[inline(always)]
    fn not_lt(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_cmp_ps::<0x15>(a, b) // _CMP_NLT_UQ
    }
    #[inline(always)]
    fn and(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_and_ps(a, b)
    }
    #[inline(always)]
    fn andnot(self, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_andnot_ps(a, b)
    }
    #[inline(always)]
    fn masked(self, m: __m256, a: __m256) -> __m256 {
        self.avx._mm256_and_ps(m, a)
    }
    #[inline(always)]
    fn select(self, m: __m256, a: __m256, b: __m256) -> __m256 {
        self.avx._mm256_blendv_ps(b, a, m)
    }
    #[inline(always)]
    fn bits(self, m: __m256) -> u32 {
        self.avx._mm256_movemask_ps(m) as u32
    }
    #[inline(always)]
    fn first(self, n: usize) -> __m256 {
        let iota = self.avx._mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let n = self.splat_i(n.min(8) as i32);
        self.avx
            ._mm256_castsi256_ps(self.avx2._mm256_cmpgt_epi32(n, iota))
    }
    #[inline(always)]
    fn pow2(self, t: __m256) -> __m256 {
        // bits of t = bits of 1.5·2^23 + n; 2^n has exponent field n + 127
        let e = self.avx2._mm256_sub_epi32(
            self.avx._mm256_castps_si256(t),
            self.splat_i(12_582_912f32.to_bits() as i32 - 127),
        );
        self.avx
            ._mm256_castsi256_ps(self.avx2._mm256_slli_epi32::<23>(e))
    }
    #[inline(always)]
    fn hsum(self, x: __m256) -> f32 {
        let (avx, sse) = (self.avx, self.sse);
        let lo: __m128 = avx._mm256_castps256_ps128(x);
        let hi: __m128 = avx._mm256_extractf128_ps::<1>(x);
        let s4 = sse._mm_add_ps(lo, hi);
        let s2 = sse._mm_add_ps(s4, sse._mm_movehl_ps(s4, s4));
        let s1 = sse._mm_add_ss(s2, sse._mm_shuffle_ps::<0b01>(s2, s2));
        sse._mm_cvtss_f32(s1)
    }
    #[inline(always)]
    fn load(self, v: &[f32; STATE], o: usize) -> __m256 {
        pulp::cast(at::<f32, 8>(v, o))
    }
    #[inline(always)]
    fn store(self, v: &mut [f32; STATE], o: usize, x: __m256) {
        v[o..o + 8].copy_from_slice(&pulp::cast::<__m256, [f32; 8]>(x));
    }
    #[inline(always)]
    fn load_i(self, v: &[i32; STATE], o: usize) -> __m256i {
        pulp::cast(at::<i32, 8>(v, o))
    }
    #[inline(always)]
    fn store_i(self, v: &mut [i32; STATE], o: usize, x: __m256i) {
        v[o..o + 8].copy_from_slice(&pulp::cast::<__m256i, [i32; 8]>(x));
    }
    #[inline(always)]
    fn gt_i(self, a: __m256i, b: __m256i) -> __m256 {
        self.avx
            ._mm256_castsi256_ps(self.avx2._mm256_cmpgt_epi32(a, b))
    }
    #[inline(always)]
    fn nonzero_i(self, a: __m256i) -> __m256 {
        let z = self.avx2._mm256_cmpeq_epi32(a, self.splat_i(0));
        self.avx
            ._mm256_castsi256_ps(self.avx2._mm256_xor_si256(z, self.splat_i(-1)))
    }
    #[inline(always)]
    fn mask_i(self, m: __m256) -> __m256i {
        self.avx._mm256_castps_si256(m)
    }
    #[inline(always)]
    fn inc_i(self, a: __m256i, m: __m256) -> __m256i {
        self.avx2._mm256_sub_epi32(a, self.mask_i(m))
    }
    #[inline(always)]
    fn select_i(self, m: __m256, a: __m256i, b: __m256i) -> __m256i {
        self.avx2._mm256_blendv_epi8(b, a, self.mask_i(m))
    }
}

impl Simd for V4 {
    const W: usize = 16;
    type F = __m512;
    type I = __m512i;
    type M = u16;
    #[inline(always)]
    fn v3(self) -> V3 {
        *self
    }
    #[inline(always)]
    fn splat(self, x: f32) -> __m512 {
        self.avx512f._mm512_set1_ps(x)
    }
    #[inline(always)]
    fn splat_i(self, x: i32) -> __m512i {
        self.avx512f._mm512_set1_epi32(x)
    }
    #[inline(always)]
    fn iota(self) -> __m512 {
        pulp::cast(std::array::from_fn::<f32, 16, _>(|l| l as f32))
    }
    #[inline(always)]
    fn add(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_add_ps(a, b)
    }
    #[inline(always)]
    fn sub(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_sub_ps(a, b)
    }
    #[inline(always)]
    fn mul(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_mul_ps(a, b)
    }
    #[inline(always)]
    fn div(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_div_ps(a, b)
    }
    #[inline(always)]
    fn min(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_min_ps(a, b)
    }
    #[inline(always)]
    fn max(self, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_max_ps(a, b)
    }
    #[inline(always)]
    fn fma(self, a: __m512, b: __m512, c: __m512) -> __m512 {
        self.avx512f._mm512_fmadd_ps(a, b, c)
    }
    #[inline(always)]
    fn fnma(self, a: __m512, b: __m512, c: __m512) -> __m512 {
        self.avx512f._mm512_fnmadd_ps(a, b, c)
    }
    #[inline(always)]
    fn fms(self, a: __m512, b: __m512, c: __m512) -> __m512 {
        self.avx512f._mm512_fmsub_ps(a, b, c)
    }
    #[inline(always)]
    fn lt(self, a: __m512, b: __m512) -> u16 {
        self.avx512f._mm512_cmp_ps_mask::<0x11>(a, b)
    }
    #[inline(always)]
    fn le(self, a: __m512, b: __m512) -> u16 {
        self.avx512f._mm512_cmp_ps_mask::<0x12>(a, b)
    }
    #[inline(always)]
    fn not_gt(self, a: __m512, b: __m512) -> u16 {
        self.avx512f._mm512_cmp_ps_mask::<0x1a>(a, b)
    }
    #[inline(always)]
    fn not_lt(self, a: __m512, b: __m512) -> u16 {
        self.avx512f._mm512_cmp_ps_mask::<0x15>(a, b)
    }
    #[inline(always)]
    fn and(self, a: u16, b: u16) -> u16 {
        a & b
    }
    #[inline(always)]
    fn andnot(self, a: u16, b: u16) -> u16 {
        !a & b
    }
    #[inline(always)]
    fn masked(self, m: u16, a: __m512) -> __m512 {
        self.avx512f._mm512_maskz_mov_ps(m, a)
    }
    #[inline(always)]
    fn select(self, m: u16, a: __m512, b: __m512) -> __m512 {
        self.avx512f._mm512_mask_blend_ps(m, b, a)
    }
    #[inline(always)]
    fn bits(self, m: u16) -> u32 {
        m as u32
    }
    #[inline(always)]
    fn first(self, n: usize) -> u16 {
        ((1u32 << n.min(16)) - 1) as u16
    }
    #[inline(always)]
    fn pow2(self, t: __m512) -> __m512 {
        let f = self.avx512f;
        let e = f._mm512_sub_epi32(
            f._mm512_castps_si512(t),
            self.splat_i(12_582_912f32.to_bits() as i32 - 127),
        );
        f._mm512_castsi512_ps(f._mm512_slli_epi32::<23>(e))
    }
    #[inline(always)]
    fn hsum(self, x: __m512) -> f32 {
        let lo = self.avx512f._mm512_castps512_ps256(x);
        let hi = self.avx512dq._mm512_extractf32x8_ps::<1>(x);
        self.v3().hsum(self.v3().add(lo, hi))
    }
    #[inline(always)]
    fn load(self, v: &[f32; STATE], o: usize) -> __m512 {
        pulp::cast(at::<f32, 16>(v, o))
    }
    #[inline(always)]
    fn store(self, v: &mut [f32; STATE], o: usize, x: __m512) {
        v[o..o + 16].copy_from_slice(&pulp::cast::<__m512, [f32; 16]>(x));
    }
    #[inline(always)]
    fn load_i(self, v: &[i32; STATE], o: usize) -> __m512i {
        pulp::cast(at::<i32, 16>(v, o))
    }
    #[inline(always)]
    fn store_i(self, v: &mut [i32; STATE], o: usize, x: __m512i) {
        v[o..o + 16].copy_from_slice(&pulp::cast::<__m512i, [i32; 16]>(x));
    }
    #[inline(always)]
    fn gt_i(self, a: __m512i, b: __m512i) -> u16 {
        self.avx512f._mm512_cmpgt_epi32_mask(a, b)
    }
    #[inline(always)]
    fn nonzero_i(self, a: __m512i) -> u16 {
        self.avx512f._mm512_test_epi32_mask(a, a)
    }
    #[inline(always)]
    fn mask_i(self, m: u16) -> __m512i {
        self.avx512f._mm512_maskz_mov_epi32(m, self.splat_i(-1))
    }
    #[inline(always)]
    fn inc_i(self, a: __m512i, m: u16) -> __m512i {
        self.avx512f
            ._mm512_mask_sub_epi32(a, m, a, self.splat_i(-1))
    }
    #[inline(always)]
    fn select_i(self, m: u16, a: __m512i, b: __m512i) -> __m512i {
        self.avx512f._mm512_mask_blend_epi32(m, b, a)
    }
}

/// `f32` of a `T` that is `f32` (the identity; these kernels only run for `T = f32`).
#[inline(always)]
fn f32_of<T: Real>(x: T) -> f32 {
    x.to_f64() as f32
}

/// `e^x`: `x = n·ln2 + r` with `n = round(x·log2 e)` and `|r| <= ln2/2` (ln 2 split in two
/// parts, the first exact times `n`), `e^r` by its degree-7 Taylor polynomial (error < 6e-9
/// relative), `2^n` built in the exponent bits. `x` is clamped to `[-87, 88]`, so the result
/// is finite and normal: relative error < 2e-7 over the whole clamp range.
#[inline(always)]
fn exp<S: Simd>(v: S, x: S::F) -> S::F {
    // 1.5·2^23: adding it rounds to an integer held in the low mantissa bits.
    const MAGIC: f32 = 12_582_912.0;
    let x = v.min(v.max(x, v.splat(-87.0)), v.splat(88.0));
    let t = v.fma(x, v.splat(std::f32::consts::LOG2_E), v.splat(MAGIC));
    let n = v.sub(t, v.splat(MAGIC));
    let r = v.fma(n, v.splat(-0.693_359_4), x);
    let r = v.fma(n, v.splat(2.121_944_4e-4), r);
    let mut p = v.splat(1.0 / 5040.0);
    for k in [720.0, 120.0, 24.0, 6.0, 2.0, 1.0, 1.0] {
        p = v.fma(p, r, v.splat(1.0 / k));
    }
    v.mul(p, v.pow2(t))
}

/// A splat's scalars broadcast to all lanes.
#[derive(Clone, Copy)]
struct SplatV<F> {
    mx: F,
    a: F,
    b: F,
    c: F,
    o: F,
    pmin: F,
    col: [F; 3],
}

#[inline(always)]
fn splat_v<S: Simd, T: Real>(v: S, s: &Splat<T>) -> SplatV<S::F> {
    SplatV {
        mx: v.splat(f32_of(s.mx)),
        a: v.splat(f32_of(s.a)),
        b: v.splat(f32_of(s.b)),
        c: v.splat(f32_of(s.c)),
        o: v.splat(f32_of(s.o)),
        pmin: v.splat(f32_of(s.pmin)),
        col: s.col.map(|c| v.splat(f32_of(c))),
    }
}

/// Per tile row `ly` of one splat: `dy = my - py`, `c·dy²` and `b·dy` (`py` = row centre).
struct Rows {
    dy: [f32; TILE],
    cdy2: [f32; TILE],
    bdy: [f32; TILE],
}

#[inline(always)]
fn rows<T: Real>(v: V3, s: &Splat<T>, y0: usize) -> Rows {
    let mut out = Rows {
        dy: [0.0; TILE],
        cdy2: [0.0; TILE],
        bdy: [0.0; TILE],
    };
    let (my, b, c) = (
        v.splat(f32_of(s.my)),
        v.splat(f32_of(s.b)),
        v.splat(f32_of(s.c)),
    );
    for k in 0..2 {
        // py = y0 + ly + 0.5, exact in f32 (as in the portable path)
        let py = v.add(v.splat((y0 + 8 * k) as u32 as f32 + 0.5), v.iota());
        let dy = v.sub(my, py);
        let store = |a: &mut [f32; TILE], x: __m256| {
            a[8 * k..8 * k + 8].copy_from_slice(&pulp::cast::<__m256, [f32; 8]>(x));
        };
        store(&mut out.dy, dy);
        store(&mut out.cdy2, v.mul(v.mul(c, dy), dy));
        store(&mut out.bdy, v.mul(b, dy));
    }
    out
}

/// Per batch column (`NH = 16 / W` of them), bit masks of the tile rows in `[ly0, ly1)`
/// whose widened-ellipse span (as [`Splat::row_span`], evaluated 4 rows at a time in f64)
/// meets the batch's columns `[h·W, (h+1)·W)` of the tile.
#[inline(always)]
fn row_masks<T: Real>(
    v: V3,
    w: usize,
    s: &Splat<T>,
    r: TileRect,
    ly0: usize,
    ly1: usize,
) -> [u32; 2] {
    let (avx, fma) = (v.avx, v.fma);
    let (k1, k2) = (avx._mm256_set1_pd(s.k1), avx._mm256_set1_pd(s.k2));
    let slope = avx._mm256_set1_pd(s.slope);
    // dy = my - (y0 + ly + 0.5); tile-local span centre mx + slope·dy - 0.5 - x0
    let my = avx._mm256_set1_pd(s.my.to_f64() - r.y0 as f64 - 0.5);
    let cx = avx._mm256_set1_pd(s.mx.to_f64() - 0.5 - r.x0 as f64);
    let zero = avx._mm256_setzero_pd();
    let width = avx._mm256_set1_pd(r.width() as f64);
    let one = avx._mm256_set1_pd(1.0);
    let mut out = [0u32; 2];
    let mut g = ly0 & !3;
    while g < ly1 {
        let gf = g as f64;
        let ly = avx._mm256_setr_pd(gf, gf + 1.0, gf + 2.0, gf + 3.0);
        let dy = avx._mm256_sub_pd(my, ly);
        let h2 = fma._mm256_fmadd_pd(k1, avx._mm256_mul_pd(dy, dy), k2);
        let valid = avx._mm256_cmp_pd::<0x1d>(h2, zero); // _CMP_GE_OQ
        let half = avx._mm256_add_pd(avx._mm256_sqrt_pd(h2), avx._mm256_set1_pd(0.1));
        let centre = fma._mm256_fmadd_pd(slope, dy, cx);
        // columns [lo, hi) of the row inside the tile
        let lo = avx._mm256_ceil_pd(avx._mm256_sub_pd(centre, half));
        let hi = avx._mm256_add_pd(avx._mm256_floor_pd(avx._mm256_add_pd(centre, half)), one);
        let lo = avx._mm256_max_pd(lo, zero);
        let hi = avx._mm256_min_pd(hi, width);
        let ne = avx._mm256_and_pd(valid, avx._mm256_cmp_pd::<0x11>(lo, hi)); // _CMP_LT_OQ
        for (h, m) in out.iter_mut().enumerate().take(TILE / w) {
            let (b0, b1) = (
                avx._mm256_set1_pd((h * w) as f64),
                avx._mm256_set1_pd(((h + 1) * w) as f64),
            );
            let meets = avx._mm256_and_pd(
                avx._mm256_cmp_pd::<0x11>(lo, b1),
                avx._mm256_cmp_pd::<0x1e>(hi, b0), // _CMP_GT_OQ
            );
            *m |= (avx._mm256_movemask_pd(avx._mm256_and_pd(ne, meets)) as u32) << g;
        }
        g += 4;
    }
    let rows = ((1u32 << ly1) - 1) & !((1u32 << ly0) - 1);
    out.map(|m| m & rows)
}

/// A splat at the `W` pixel centres of a batch (see [`crate::splat::Hits`]); `keep` masks
/// the pixels not skipped, and `alpha` is 0 elsewhere.
#[derive(Clone, Copy)]
struct HitsV<F, M> {
    keep: M,
    alpha: F,
    raw: F,
    gauss: F,
    dx: F,
}

/// `dx = mx - px`, `power = -½(a dx² + c dy²) - b dx dy`, `alpha = min(0.99, o e^power)` at
/// the pixel centres `px`, skipping (as [`crate::splat::hits`]) `power > 0`,
/// `power < pmin`, `alpha < 1/255` and the lanes outside `lanes`.
#[inline(always)]
fn hits<S: Simd>(
    v: S,
    s: &SplatV<S::F>,
    cdy2: S::F,
    bdy: S::F,
    px: S::F,
    lanes: S::M,
) -> HitsV<S::F, S::M> {
    let dx = v.sub(s.mx, px);
    let q = v.fma(v.mul(s.a, dx), dx, cdy2);
    let power = v.fnma(bdy, dx, v.mul(v.splat(-0.5), q));
    let gauss = exp(v, power);
    let raw = v.mul(s.o, gauss);
    let alpha = v.min(raw, v.splat(ALPHA_MAX as f32));
    let keep = v.and(
        v.and(v.not_gt(power, v.splat(0.0)), v.not_lt(power, s.pmin)),
        v.and(v.not_lt(alpha, v.splat(ALPHA_MIN as f32)), lanes),
    );
    HitsV {
        keep,
        alpha: v.masked(keep, alpha),
        raw,
        gauss,
        dx,
    }
}

/// Pixel centres `px` of the batch columns of the tile, and their lane masks of the
/// columns inside the image.
#[inline(always)]
fn columns<S: Simd>(v: S, r: TileRect) -> [(S::F, S::M); 2] {
    let w = r.width();
    std::array::from_fn(|h| {
        let px = v.add(v.splat((r.x0 + h * S::W) as u32 as f32 + 0.5), v.iota());
        (px, v.first(w.saturating_sub(h * S::W)))
    })
}

/// The first [`STATE`] entries of a state array, as a fixed-size array.
#[inline(always)]
fn state<X>(v: &mut [X]) -> &mut [X; STATE] {
    (&mut v[..STATE]).try_into().expect("tile state")
}

/// Offset of the batch `h` (of width `w`) of tile row `ly`; at most `15·STRIDE + 16 - w`.
#[inline(always)]
fn offset(ly: u32, h: usize, w: usize) -> usize {
    (ly as usize & (TILE - 1)) * STRIDE + ((h * w) & (TILE - 1))
}

/// [`crate::blend::forward_tile`] for `f32` with vector kernel `k`.
pub(crate) fn forward_tile<T: Real>(
    k: Kernel,
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileForward<f32>,
) {
    struct Op<'a, S, T> {
        v: S,
        splats: &'a [Splat<T>],
        r: TileRect,
        st: &'a mut TileForward<f32>,
    }
    impl<S: Simd, T: Real> pulp::NullaryFnOnce for Op<'_, S, T> {
        type Output = ();
        #[inline(always)]
        fn call(self) {
            forward_impl(self.v, self.splats, self.r, self.st);
        }
    }
    match k {
        Kernel::Avx2(v) => v.vectorize(Op { v, splats, r, st }),
        Kernel::Avx512(v) => v.vectorize(Op { v, splats, r, st }),
    }
}

#[inline(always)]
fn forward_impl<S: Simd, T: Real>(
    v: S,
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileForward<f32>,
) {
    st.reset();
    let n_pix = r.n_pixels();
    let mut n_done = 0;
    let TileForward {
        t,
        rgb,
        z,
        count,
        last,
        done,
    } = st;
    let (t, z, count, last, done) = (state(t), state(z), state(count), state(last), state(done));
    let [r_acc, g_acc, b_acc] = rgb;
    let mut rgb = [state(r_acc), state(g_acc), state(b_acc)];
    let t_min = v.splat(T_MIN as f32);
    let cols = columns(v, r);
    for (pos, s) in splats.iter().enumerate() {
        let Some((ly0, ly1)) = s.local_rows(r.y0, r.y1) else {
            continue;
        };
        let masks = row_masks(v.v3(), S::W, s, r, ly0, ly1);
        if masks[0] | masks[1] == 0 {
            continue;
        }
        let sv = splat_v(v, s);
        let rows = rows(v.v3(), s, r.y0);
        let sz = v.splat(f32_of(s.z));
        let next = v.splat_i(pos as i32 + 1);
        for (h, mut m) in masks.into_iter().enumerate() {
            let (px, lanes) = cols[h];
            while m != 0 {
                let ly = m.trailing_zeros();
                m &= m - 1;
                let k = ly as usize & (TILE - 1);
                let hit = hits(
                    v,
                    &sv,
                    v.splat(rows.cdy2[k]),
                    v.splat(rows.bdy[k]),
                    px,
                    lanes,
                );
                if v.bits(hit.keep) == 0 {
                    continue;
                }
                let o = offset(ly, h, S::W);
                // keep = not skipped and not stopped; stop before T would fall below 1e-4
                let d = v.nonzero_i(v.load_i(done, o));
                let keep = v.andnot(d, hit.keep);
                let t0 = v.load(t, o);
                let test_t = v.mul(t0, v.sub(v.splat(1.0), hit.alpha));
                let stop = v.and(keep, v.lt(test_t, t_min));
                let blend = v.andnot(stop, keep);
                let (mb, ms) = (v.bits(blend), v.bits(stop));
                if ms != 0 {
                    let dn = v.load_i(done, o);
                    v.store_i(done, o, v.select_i(stop, v.splat_i(1), dn));
                    n_done += ms.count_ones() as usize;
                }
                if mb == 0 {
                    continue;
                }
                let w = v.masked(blend, v.mul(hit.alpha, t0));
                v.store(t, o, v.select(blend, test_t, t0));
                let cnt = v.inc_i(v.load_i(count, o), blend);
                v.store_i(count, o, cnt);
                let lst = v.select_i(blend, next, v.load_i(last, o));
                v.store_i(last, o, lst);
                for (acc, col) in rgb.iter_mut().zip(sv.col) {
                    let x = v.fma(col, w, v.load(acc, o));
                    v.store(acc, o, x);
                }
                let x = v.fma(sz, w, v.load(z, o));
                v.store(z, o, x);
            }
        }
        if n_done == n_pix {
            break;
        }
    }
}

/// [`crate::blend::backward_tile`] for `f32` with vector kernel `k`.
pub(crate) fn backward_tile<T: Real>(
    k: Kernel,
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileBackward<f32>,
    out: &mut [SplatGrad<T>],
) {
    struct Op<'a, S, T> {
        v: S,
        splats: &'a [Splat<T>],
        r: TileRect,
        st: &'a mut TileBackward<f32>,
        out: &'a mut [SplatGrad<T>],
    }
    impl<S: Simd, T: Real> pulp::NullaryFnOnce for Op<'_, S, T> {
        type Output = ();
        #[inline(always)]
        fn call(self) {
            backward_impl(self.v, self.splats, self.r, self.st, self.out);
        }
    }
    match k {
        Kernel::Avx2(v) => v.vectorize(Op {
            v,
            splats,
            r,
            st,
            out,
        }),
        Kernel::Avx512(v) => v.vectorize(Op {
            v,
            splats,
            r,
            st,
            out,
        }),
    }
}

#[inline(always)]
fn backward_impl<S: Simd, T: Real>(
    v: S,
    splats: &[Splat<T>],
    r: TileRect,
    st: &mut TileBackward<f32>,
    out: &mut [SplatGrad<T>],
) {
    // splats behind every pixel's last contributor get no gradient
    let max_last = st.last.iter().copied().max().unwrap_or(0).max(0) as usize;
    let end = max_last.min(splats.len());
    out[end..].fill(SplatGrad::default());
    let TileBackward {
        dc,
        da_tn,
        t,
        acc: s_acc,
        last,
    } = st;
    let (da_tn, t, last) = (state(da_tn), state(t), state(last));
    let [d0, d1, d2] = dc;
    let dc = [state(d0), state(d1), state(d2)];
    let [s0, s1, s2] = s_acc;
    let s_acc = [state(s0), state(s1), state(s2)];
    let one = v.splat(1.0);
    let cols = columns(v, r);
    for (pos, (s, g)) in splats[..end]
        .iter()
        .zip(out[..end].iter_mut())
        .enumerate()
        .rev()
    {
        let Some((ly0, ly1)) = s.local_rows(r.y0, r.y1) else {
            continue;
        };
        let masks = row_masks(v.v3(), S::W, s, r, ly0, ly1);
        if masks[0] | masks[1] == 0 {
            continue;
        }
        let sv = splat_v(v, s);
        let rows = rows(v.v3(), s, r.y0);
        let posv = v.splat_i(pos as i32);
        // per-lane partial sums: colour, opacity, then for the geometry (all negated, the
        // conic diagonal without its ½): g·(A dx + B dy), g·(C dy + B dx), g dx², g dx dy,
        // g dy² with g = dL/dpower
        let zero = v.splat(0.0);
        let mut acc_c = [zero; 3];
        let mut acc_o = zero;
        let mut acc_g = [zero; 5];
        for (h, mut m) in masks.into_iter().enumerate() {
            let (px, lanes) = cols[h];
            while m != 0 {
                let ly = m.trailing_zeros();
                m &= m - 1;
                let k = ly as usize & (TILE - 1);
                let bdy = v.splat(rows.bdy[k]);
                let hit = hits(v, &sv, v.splat(rows.cdy2[k]), bdy, px, lanes);
                if v.bits(hit.keep) == 0 {
                    continue;
                }
                let o = offset(ly, h, S::W);
                // blended by this pixel: not skipped and in front of its last contributor
                let m = v.and(hit.keep, v.gt_i(v.load_i(last, o), posv));
                if v.bits(m) == 0 {
                    continue;
                }
                let a = v.masked(m, hit.alpha);
                // T_i = T_{i+1}/(1 - α_i); masked lanes have α = 0: T unchanged, w = 0
                let inv = v.div(one, v.sub(one, a));
                let ti = v.mul(v.load(t, o), inv);
                v.store(t, o, ti);
                let w = v.mul(a, ti);
                // dC/dα_i = c_i T_i - S_i/(1 - α_i); d(1 - T_N)/dα_i = T_N/(1 - α_i)
                let mut g_alpha = v.mul(v.load(da_tn, o), inv);
                for c in 0..3 {
                    let d = v.load(dc[c], o);
                    let sa = v.load(s_acc[c], o);
                    acc_c[c] = v.fma(d, w, acc_c[c]);
                    g_alpha = v.fma(d, v.fms(sv.col[c], ti, v.mul(sa, inv)), g_alpha);
                    v.store(s_acc[c], o, v.fma(sv.col[c], w, sa));
                }
                // through α = o·exp(power); zero where masked or clamped at 0.99
                let geo = v.and(m, v.le(hit.raw, v.splat(ALPHA_MAX as f32)));
                let ga = v.masked(geo, g_alpha);
                acc_o = v.fma(hit.gauss, ga, acc_o);
                let gp = v.mul(hit.raw, ga);
                let gdx = v.mul(gp, hit.dx);
                let dy = v.splat(rows.dy[k]);
                acc_g[0] = v.fma(gp, v.fma(sv.a, hit.dx, bdy), acc_g[0]);
                acc_g[1] = v.fma(gp, v.fma(sv.b, hit.dx, v.mul(sv.c, dy)), acc_g[1]);
                acc_g[2] = v.fma(gdx, hit.dx, acc_g[2]);
                acc_g[3] = v.fma(gdx, dy, acc_g[3]);
                acc_g[4] = v.fma(gp, v.mul(dy, dy), acc_g[4]);
            }
        }
        let sum = |x: S::F| T::from_f64(v.hsum(x) as f64);
        let half = T::from_f64(0.5);
        *g = SplatGrad {
            mean2d: [-sum(acc_g[0]), -sum(acc_g[1])],
            conic: [-half * sum(acc_g[2]), -sum(acc_g[3]), -half * sum(acc_g[4])],
            opacity: sum(acc_o),
            color: acc_c.map(sum),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blend::{backward_tile_portable, forward_tile_portable};

    /// SplitMix64 uniform in `[lo, hi)`.
    struct Rng(u64);
    impl Rng {
        fn range(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            lo + (hi - lo) * ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// Splats around the tile `r`: round to needle-like (axis ratio up to 100, any angle),
    /// opacities up to 0.999 so that many pixels reach the `T < 1e-4` stop.
    fn splats(rng: &mut Rng, r: TileRect, n: usize) -> Vec<Splat<f32>> {
        (0..n)
            .map(|i| {
                let m = [
                    rng.range(r.x0 as f64 - 8.0, r.x1 as f64 + 8.0),
                    rng.range(r.y0 as f64 - 8.0, r.y1 as f64 + 8.0),
                ];
                let long = rng.range(0.3, 9.0);
                let short = long / rng.range(1.0, 100.0);
                let th = rng.range(0.0, std::f64::consts::PI);
                let (c, s) = (th.cos(), th.sin());
                let (l1, l2) = (long * long + 0.3, short * short + 0.3);
                let cov = [
                    c * c * l1 + s * s * l2,
                    c * s * (l1 - l2),
                    s * s * l1 + c * c * l2,
                ];
                let det = cov[0] * cov[2] - cov[1] * cov[1];
                let conic = [cov[2] / det, -cov[1] / det, cov[0] / det];
                let o = if i % 5 == 0 {
                    0.999
                } else {
                    rng.range(0.02, 0.95)
                };
                let f = |x: f64| x as f32;
                Splat::new(
                    m.map(f),
                    conic.map(f),
                    cov.map(f),
                    f(o),
                    [0; 3].map(|_| f(rng.range(0.0, 1.0))),
                    f(rng.range(1.0, 5.0)),
                )
            })
            .collect()
    }

    /// The AVX2 and AVX-512 kernels (those this CPU has) against the portable ones on the
    /// same splats, full and partial tiles: identical blend decisions (counts, last
    /// contributors), values and gradients equal up to rounding.
    #[test]
    fn vector_kernels_match_portable() {
        let kernels = [
            V3::try_new().map(Kernel::Avx2),
            V4::try_new().map(Kernel::Avx512),
        ];
        for k in kernels.into_iter().flatten() {
            matches_portable(k);
        }
    }

    fn matches_portable(simd: Kernel) {
        let mut rng = Rng(7);
        let mut blended = 0;
        for (case, (w, h, n)) in [(16, 16, 40), (16, 16, 400), (11, 13, 150), (1, 16, 60)]
            .into_iter()
            .enumerate()
        {
            let r = TileRect {
                x0: 32,
                x1: 32 + w,
                y0: 48,
                y1: 48 + h,
            };
            let sp = splats(&mut rng, r, n);
            let (mut fa, mut fb) = (TileForward::default(), TileForward::default());
            forward_tile(simd, &sp, r, &mut fa);
            forward_tile_portable(&sp, r, &mut fb);
            let mut ba = TileBackward::default();
            ba.reset();
            for ly in 0..h {
                for lx in 0..w {
                    let q = ly * STRIDE + lx;
                    assert_eq!(fa.count[q], fb.count[q], "case {case} count ({lx}, {ly})");
                    assert_eq!(fa.last[q], fb.last[q], "case {case} last ({lx}, {ly})");
                    assert!(
                        (fa.t[q] - fb.t[q]).abs() <= 1e-5,
                        "case {case} T ({lx}, {ly})"
                    );
                    for c in 0..3 {
                        assert!(
                            (fa.rgb[c][q] - fb.rgb[c][q]).abs() <= 1e-5,
                            "case {case} rgb"
                        );
                    }
                    assert!((fa.z[q] - fb.z[q]).abs() <= 1e-5 * 5.0, "case {case} depth");
                    blended += fa.count[q];
                    let tn = fb.t[q];
                    for c in 0..3 {
                        ba.dc[c][q] = rng.range(-1.0, 1.0) as f32;
                        ba.acc[c][q] = tn * 0.25;
                    }
                    ba.da_tn[q] = rng.range(-1.0, 1.0) as f32 * tn;
                    ba.t[q] = tn;
                    ba.last[q] = fb.last[q];
                }
            }
            let mut bb = ba.clone();
            let mut ga = vec![SplatGrad::default(); n];
            let mut gb = vec![SplatGrad::default(); n];
            backward_tile(simd, &sp, r, &mut ba, &mut ga);
            backward_tile_portable(&sp, r, &mut bb, &mut gb);
            let flat = |g: &SplatGrad<f32>| {
                let mut v = g.mean2d.to_vec();
                v.extend(g.conic);
                v.push(g.opacity);
                v.extend(g.color);
                v
            };
            let (fa, fb): (Vec<_>, Vec<_>) =
                (ga.iter().map(flat).collect(), gb.iter().map(flat).collect());
            for k in 0..9 {
                let scale = fb.iter().map(|v| v[k].abs()).fold(0.0f32, f32::max);
                for (i, (a, b)) in fa.iter().zip(&fb).enumerate() {
                    assert!(
                        (a[k] - b[k]).abs() <= 1e-4 * scale + 1e-7,
                        "case {case} splat {i} component {k}: {} vs {}",
                        a[k],
                        b[k]
                    );
                }
            }
        }
        assert!(
            blended > 10_000,
            "the scenes blend enough splats ({blended})"
        );
    }
}
