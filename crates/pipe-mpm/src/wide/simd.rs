//! Vectors of particles: one SIMD lane per particle, in `f32` (eight lanes) or `f64` (four).
//!
//! [`Wide`] is the lane arithmetic the particle-group kernels are written against. Under AVX2 +
//! FMA ([`Isa::Fma`]) the lanes are `__m256` / `__m256d`; elsewhere they are arrays with the
//! same operations lane by lane ([`Port`]). Every operation is an IEEE operation on each lane
//! (fused multiply-adds are exactly rounded either way), sums across lanes run in one fixed
//! order ([`Wide::reduce4`]) and the logarithm is the same polynomial, so both give the same
//! bits: the instruction set is a speed choice, never a result choice.

use std::fmt::Debug;

use crate::isa::Isa;

/// The floating-point type of a precision: `f32` or `f64`.
pub(crate) trait Real:
    Copy
    + bytemuck::Pod
    + Debug
    + Default
    + PartialOrd
    + Send
    + Sync
    + 'static
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
{
    /// Lanes per vector (eight `f32` or four `f64` in 256 bits).
    const N: usize;
    /// Terms of the `atanh` series of [`Wide::ln`] (enough for this precision).
    const LN_TERMS: usize;
    /// `x` rounded to this precision.
    fn of(x: f64) -> Self;
    /// `self` as `f64` (exact).
    fn f64(self) -> f64;
    /// `a b + c`, rounded once.
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// ⌊x⌋.
    fn floor(self) -> Self;
    /// √x.
    fn sqrt(self) -> Self;
    /// Whether the value is neither NaN nor ±Inf.
    fn is_finite(self) -> bool;
    /// `(exponent, mantissa)` with `x = mantissa · 2^exponent`, mantissa in [1, 2), for finite
    /// `x > 0` (the bit fields, so the same in every lane implementation).
    fn split_exponent(self) -> (Self, Self);
    /// The largest value not above `x` (rounding towards −∞).
    fn of_down(x: f64) -> Self {
        let r = Self::of(x);
        if r.f64() > x { Self::prev(r) } else { r }
    }
    /// The smallest value not below `x` (rounding towards +∞).
    fn of_up(x: f64) -> Self {
        let r = Self::of(x);
        if r.f64() < x { Self::next(r) } else { r }
    }
    /// The next representable value towards −∞ (finite input).
    fn prev(x: Self) -> Self;
    /// The next representable value towards +∞ (finite input).
    fn next(x: Self) -> Self;
}

impl Real for f32 {
    const N: usize = 8;
    const LN_TERMS: usize = 5;
    #[inline(always)]
    fn of(x: f64) -> f32 {
        x as f32
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn mul_add(self, b: f32, c: f32) -> f32 {
        f32::mul_add(self, b, c)
    }
    #[inline(always)]
    fn floor(self) -> f32 {
        // Without a libm call (exact; |x| ≥ 2²³ is already an integer).
        if self.abs() < 8_388_608.0 {
            let t = self as i32 as f32;
            if t > self { t - 1.0 } else { t }
        } else {
            self
        }
    }
    #[inline(always)]
    fn sqrt(self) -> f32 {
        f32::sqrt(self)
    }
    #[inline(always)]
    fn is_finite(self) -> bool {
        f32::is_finite(self)
    }
    #[inline(always)]
    fn split_exponent(self) -> (f32, f32) {
        let b = self.to_bits();
        let e = ((b >> 23) & 0xff) as i32 - 127;
        (e as f32, f32::from_bits((b & 0x007f_ffff) | 0x3f80_0000))
    }
    fn prev(x: f32) -> f32 {
        x.next_down()
    }
    fn next(x: f32) -> f32 {
        x.next_up()
    }
}

impl Real for f64 {
    const N: usize = 4;
    const LN_TERMS: usize = 11;
    #[inline(always)]
    fn of(x: f64) -> f64 {
        x
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn mul_add(self, b: f64, c: f64) -> f64 {
        f64::mul_add(self, b, c)
    }
    #[inline(always)]
    fn floor(self) -> f64 {
        // Without a libm call (exact; |x| ≥ 2⁵² is already an integer).
        if self.abs() < 4_503_599_627_370_496.0 {
            crate::grid::floor1(self)
        } else {
            self
        }
    }
    #[inline(always)]
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn is_finite(self) -> bool {
        f64::is_finite(self)
    }
    #[inline(always)]
    fn split_exponent(self) -> (f64, f64) {
        let b = self.to_bits();
        let e = ((b >> 52) & 0x7ff) as i64 - 1023;
        (
            e as f64,
            f64::from_bits((b & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000),
        )
    }
    fn prev(x: f64) -> f64 {
        x.next_down()
    }
    fn next(x: f64) -> f64 {
        x.next_up()
    }
}

/// Lane arithmetic of one precision `T` and instruction set: a vector holds [`Real::N`]
/// particles. All methods must be `#[inline(always)]` so that they take the target features
/// of the kernel that calls them ([`Isa::run_wide`]).
pub(crate) trait Wide: Copy + Send + Sync {
    /// The precision.
    type T: Real;
    /// A vector of `T::N` lanes.
    type V: Copy;
    /// `x` in every lane.
    fn splat(self, x: Self::T) -> Self::V;
    /// The first `T::N` values of `s`.
    fn load(self, s: &[Self::T]) -> Self::V;
    /// Writes all lanes to the first `T::N` values of `s`.
    fn store(self, v: Self::V, s: &mut [Self::T]);
    /// The lanes as an array (the first `T::N` entries are used).
    fn lanes(self, v: Self::V) -> [Self::T; 8];
    /// A vector from the first `T::N` entries of `a`.
    fn vector(self, a: [Self::T; 8]) -> Self::V;
    fn add(self, a: Self::V, b: Self::V) -> Self::V;
    fn sub(self, a: Self::V, b: Self::V) -> Self::V;
    fn mul(self, a: Self::V, b: Self::V) -> Self::V;
    fn div(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a b + c`, rounded once.
    fn fma(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V;
    /// `a < b ? a : b` per lane (x86 `min` semantics).
    fn min(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a > b ? a : b` per lane (x86 `max` semantics).
    fn max(self, a: Self::V, b: Self::V) -> Self::V;
    fn floor(self, a: Self::V) -> Self::V;
    fn sqrt(self, a: Self::V) -> Self::V;
    /// `a > b ? x : y` per lane.
    fn select_gt(self, a: Self::V, b: Self::V, x: Self::V, y: Self::V) -> Self::V;
    /// Bit `i` set where lane `i` of `a` differs from `b` (or either is NaN).
    fn ne_mask(self, a: Self::V, b: Self::V) -> u32;
    /// Bit `i` set where lane `i` is NaN or ±Inf.
    fn non_finite_mask(self, a: Self::V) -> u32;
    /// `(exponent, mantissa)` of every lane ([`Real::split_exponent`]).
    fn split_exponent(self, a: Self::V) -> (Self::V, Self::V);
    /// Lanes `0 ≤ x < 2³¹` truncated to integers (the first `T::N` entries).
    fn to_u32(self, a: Self::V) -> [u32; 8];
    /// Sums of the lanes of four vectors, `[Σa, Σb, Σc, Σd]`, each in one fixed order:
    /// `((l₀+l₂)+(l₁+l₃)) + ((l₄+l₆)+(l₅+l₇))` for eight lanes, `(l₀+l₁)+(l₂+l₃)` for four.
    fn reduce4(self, a: Self::V, b: Self::V, c: Self::V, d: Self::V) -> [Self::T; 4];

    /// Adds the lane sums `[Σa, Σb, Σc, Σd]` ([`Self::reduce4`], the same bits) to `out`.
    #[inline(always)]
    fn reduce4_add(self, a: Self::V, b: Self::V, c: Self::V, d: Self::V, out: &mut [Self::T; 4]) {
        let s = self.reduce4(a, b, c, d);
        for k in 0..4 {
            out[k] = out[k] + s[k];
        }
    }

    /// [`Self::reduce4_add`] of two nodes at once: `p`'s sums to `out[..4]`, `q`'s to
    /// `out[4..]` (the same bits).
    #[inline(always)]
    fn reduce4_add_pair(self, p: [Self::V; 4], q: [Self::V; 4], out: &mut [Self::T; 8]) {
        let (lo, hi) = out.split_at_mut(4);
        let (lo, hi): (&mut [Self::T; 4], &mut [Self::T; 4]) =
            (lo.try_into().expect("4"), hi.try_into().expect("4"));
        self.reduce4_add(p[0], p[1], p[2], p[3], lo);
        self.reduce4_add(q[0], q[1], q[2], q[3], hi);
    }

    /// Two groups of up to half a vector side by side ([`super::transfer`]'s pairs): lanes
    /// `0..N/2` from `a[..N/2]`, lanes `N/2..N` from `b[..N/2]`.
    #[inline(always)]
    fn load_halves(self, a: &[Self::T], b: &[Self::T]) -> Self::V {
        let h = Self::T::N / 2;
        let mut v = [Self::T::default(); 8];
        v[..h].copy_from_slice(&a[..h]);
        v[h..2 * h].copy_from_slice(&b[..h]);
        self.vector(v)
    }

    /// `a` in lanes `0..N/2`, `b` in lanes `N/2..N`.
    #[inline(always)]
    fn splat_halves(self, a: Self::T, b: Self::T) -> Self::V {
        let h = Self::T::N / 2;
        let mut v = [b; 8];
        for x in &mut v[..h] {
            *x = a;
        }
        self.vector(v)
    }

    /// Lanes `0..na` and `N/2..N/2 + nb` of `v`, the others 0.
    #[inline(always)]
    fn keep_halves(self, v: Self::V, na: usize, nb: usize) -> Self::V {
        let h = Self::T::N / 2;
        let iota = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0].map(Self::T::of);
        let end = self.splat_halves(Self::T::of(na as f64), Self::T::of((h + nb) as f64));
        self.select_gt(end, self.vector(iota), v, self.zero())
    }

    /// The lane sums `[Σa, Σb, Σc, Σd]` of each half apart: over lanes `0..N/2`, and over
    /// lanes `N/2..N`, each in the order of that half in [`Self::reduce4`] (`(l₀+l₂)+(l₁+l₃)`
    /// for four lanes, `l₀+l₁` for two).
    #[inline(always)]
    fn reduce4_halves(
        self,
        a: Self::V,
        b: Self::V,
        c: Self::V,
        d: Self::V,
    ) -> ([Self::T; 4], [Self::T; 4]) {
        let h = Self::T::N / 2;
        let sum = |v: [Self::T; 8], at: usize| {
            if h == 4 {
                (v[at] + v[at + 2]) + (v[at + 1] + v[at + 3])
            } else {
                v[at] + v[at + 1]
            }
        };
        let l = [self.lanes(a), self.lanes(b), self.lanes(c), self.lanes(d)];
        (
            [sum(l[0], 0), sum(l[1], 0), sum(l[2], 0), sum(l[3], 0)],
            [sum(l[0], h), sum(l[1], h), sum(l[2], h), sum(l[3], h)],
        )
    }

    /// `out[k] += s[k]`.
    #[inline(always)]
    fn add4(self, s: [Self::T; 4], out: &mut [Self::T; 4]) {
        for k in 0..4 {
            out[k] = out[k] + s[k];
        }
    }

    /// A pair's lanes to its slots: lanes `0..N/2` to `s[..]`, then lanes `N/2..` to
    /// `s[na..]` (the second group follows the first). With `whole`, `N/2` lanes each (the
    /// first store's lanes past `na` are overwritten by the second, the second's past `nb`
    /// land on later slots, which their own groups overwrite afterwards); else `na` and `nb`.
    #[inline(always)]
    fn store_halves(self, v: Self::V, s: &mut [Self::T], na: usize, nb: usize, whole: bool) {
        let h = Self::T::N / 2;
        let l = self.lanes(v);
        if whole {
            s[..h].copy_from_slice(&l[..h]);
            s[na..na + h].copy_from_slice(&l[h..2 * h]);
        } else {
            s[..na].copy_from_slice(&l[..na]);
            s[na..na + nb].copy_from_slice(&l[h..h + nb]);
        }
    }

    /// 0 in every lane.
    #[inline(always)]
    fn zero(self) -> Self::V {
        self.splat(Self::T::of(0.0))
    }

    /// `c` as a constant vector.
    #[inline(always)]
    fn c(self, c: f64) -> Self::V {
        self.splat(Self::T::of(c))
    }

    /// Lanes `≥ n` set to 0.
    #[inline(always)]
    fn keep_first(self, v: Self::V, n: usize) -> Self::V {
        let iota = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0].map(Self::T::of);
        self.select_gt(self.c(n as f64), self.vector(iota), v, self.zero())
    }

    /// The first `T::N` values of `s`, or all of a shorter `s` with the other lanes 0.
    #[inline(always)]
    fn load_part(self, s: &[Self::T]) -> Self::V {
        if s.len() >= Self::T::N {
            self.load(s)
        } else {
            let mut a = [Self::T::default(); 8];
            a[..s.len()].copy_from_slice(s);
            self.vector(a)
        }
    }

    /// Writes the first `n` lanes to `s[..n]`.
    #[inline(always)]
    fn store_n(self, v: Self::V, s: &mut [Self::T], n: usize) {
        if n == Self::T::N {
            self.store(v, s);
        } else {
            s[..n].copy_from_slice(&self.lanes(v)[..n]);
        }
    }

    /// Natural logarithm of lanes `> 0` (NaN where `≤ 0` or NaN): `x = m 2^e`, `m` reduced
    /// to `[√½, √2)`, `ln m = 2 atanh s = 2 Σ s^(2k+1)/(2k+1)`, `s = (m−1)/(m+1)`,
    /// [`Real::LN_TERMS`] terms (`|s| ≤ 0.172`: below half an ulp of either precision).
    #[inline(always)]
    fn ln(self, x: Self::V) -> Self::V {
        let (e, m) = self.split_exponent(x);
        let sqrt2 = self.c(std::f64::consts::SQRT_2);
        let m2 = self.select_gt(m, sqrt2, self.mul(m, self.c(0.5)), m);
        let e = self.add(e, self.select_gt(m, sqrt2, self.c(1.0), self.zero()));
        let m = m2;
        let one = self.c(1.0);
        let s = self.div(self.sub(m, one), self.add(m, one));
        let s2 = self.mul(s, s);
        let n = Self::T::LN_TERMS;
        let mut p = self.c(2.0 / (2 * n - 1) as f64);
        for k in (0..n - 1).rev() {
            p = self.fma(s2, p, self.c(2.0 / (2 * k + 1) as f64));
        }
        let r = self.fma(e, self.c(std::f64::consts::LN_2), self.mul(s, p));
        self.select_gt(x, self.zero(), r, self.c(f64::NAN))
    }
}

/// Work generic over the lane arithmetic of precision `T`, for [`Isa::run_wide`].
pub(crate) trait WideOp<T: Real> {
    type Output;
    /// Runs with lanes `w` (must be `#[inline(always)]`).
    fn with<W: Wide<T = T>>(self, w: W) -> Self::Output;
}

/// The precisions with a lane implementation per instruction set.
pub(crate) trait Precise: Real {
    /// Runs `op` with the AVX2 lanes of this precision (`v3` proves the CPU has them).
    #[cfg(target_arch = "x86_64")]
    fn run_avx2<Op: WideOp<Self>>(v3: pulp::x86::V3, op: Op) -> Op::Output;
}

impl Precise for f32 {
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn run_avx2<Op: WideOp<f32>>(v3: pulp::x86::V3, op: Op) -> Op::Output {
        match avx512() {
            Some(v4) => v4.vectorize(InWide(avx2::F32x8(v3), op)),
            None => v3.vectorize(InWide(avx2::F32x8(v3), op)),
        }
    }
}

impl Precise for f64 {
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn run_avx2<Op: WideOp<f64>>(v3: pulp::x86::V3, op: Op) -> Op::Output {
        match avx512() {
            Some(v4) => v4.vectorize(InWide(avx2::F64x4(v3), op)),
            None => v3.vectorize(InWide(avx2::F64x4(v3), op)),
        }
    }
}

/// AVX-512, when the CPU has it (and the test cap allows): the kernels then run the same
/// 256-bit instructions with 32 vector registers instead of 16 (fewer spills), so the same bits.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn avx512() -> Option<pulp::x86::V4> {
    if crate::isa::cap() < 1 {
        pulp::x86::V4::try_new()
    } else {
        None
    }
}

impl Isa {
    /// Runs `op` with this instruction set's lanes of precision `T`.
    #[inline(always)]
    pub(crate) fn run_wide<T: Precise, Op: WideOp<T>>(self, op: Op) -> Op::Output {
        match self {
            #[cfg(target_arch = "x86_64")]
            Isa::Fma(v3) => T::run_avx2(v3, op),
            Isa::Baseline => op.with(Port::<T>::default()),
        }
    }
}

/// `op` bound to lanes `w`, as a [`pulp::NullaryFnOnce`].
#[cfg(target_arch = "x86_64")]
struct InWide<W, Op>(W, Op);

#[cfg(target_arch = "x86_64")]
impl<W: Wide, Op: WideOp<W::T>> pulp::NullaryFnOnce for InWide<W, Op> {
    type Output = Op::Output;

    #[inline(always)]
    fn call(self) -> Op::Output {
        self.1.with(self.0)
    }
}

/// Lane-by-lane implementation (any CPU).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Port<T>(std::marker::PhantomData<T>);

impl<T: Real> Port<T> {
    #[inline(always)]
    fn map(a: [T; 8], f: impl Fn(T) -> T) -> [T; 8] {
        let mut r = a;
        for x in r.iter_mut().take(T::N) {
            *x = f(*x);
        }
        r
    }

    #[inline(always)]
    fn zip(a: [T; 8], b: [T; 8], f: impl Fn(T, T) -> T) -> [T; 8] {
        let mut r = a;
        for i in 0..T::N {
            r[i] = f(a[i], b[i]);
        }
        r
    }
}

impl<T: Real> Wide for Port<T> {
    type T = T;
    type V = [T; 8];

    #[inline(always)]
    fn splat(self, x: T) -> [T; 8] {
        [x; 8]
    }
    #[inline(always)]
    fn load(self, s: &[T]) -> [T; 8] {
        let mut a = [T::default(); 8];
        a[..T::N].copy_from_slice(&s[..T::N]);
        a
    }
    #[inline(always)]
    fn store(self, v: [T; 8], s: &mut [T]) {
        s[..T::N].copy_from_slice(&v[..T::N]);
    }
    #[inline(always)]
    fn lanes(self, v: [T; 8]) -> [T; 8] {
        v
    }
    #[inline(always)]
    fn vector(self, a: [T; 8]) -> [T; 8] {
        a
    }
    #[inline(always)]
    fn add(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| x + y)
    }
    #[inline(always)]
    fn sub(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| x - y)
    }
    #[inline(always)]
    fn mul(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| x * y)
    }
    #[inline(always)]
    fn div(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| x / y)
    }
    #[inline(always)]
    fn fma(self, a: [T; 8], b: [T; 8], c: [T; 8]) -> [T; 8] {
        let mut r = a;
        for i in 0..T::N {
            r[i] = a[i].mul_add(b[i], c[i]);
        }
        r
    }
    #[inline(always)]
    fn min(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| if x < y { x } else { y })
    }
    #[inline(always)]
    fn max(self, a: [T; 8], b: [T; 8]) -> [T; 8] {
        Self::zip(a, b, |x, y| if x > y { x } else { y })
    }
    #[inline(always)]
    fn floor(self, a: [T; 8]) -> [T; 8] {
        Self::map(a, T::floor)
    }
    #[inline(always)]
    fn sqrt(self, a: [T; 8]) -> [T; 8] {
        Self::map(a, T::sqrt)
    }
    #[inline(always)]
    fn select_gt(self, a: [T; 8], b: [T; 8], x: [T; 8], y: [T; 8]) -> [T; 8] {
        let mut r = y;
        for i in 0..T::N {
            if a[i] > b[i] {
                r[i] = x[i];
            }
        }
        r
    }
    #[inline(always)]
    fn ne_mask(self, a: [T; 8], b: [T; 8]) -> u32 {
        (0..T::N).fold(0, |m, i| m | (u32::from(a[i] != b[i]) << i))
    }
    #[inline(always)]
    fn non_finite_mask(self, a: [T; 8]) -> u32 {
        (0..T::N).fold(0, |m, i| m | (u32::from(!a[i].is_finite()) << i))
    }
    #[inline(always)]
    fn to_u32(self, a: [T; 8]) -> [u32; 8] {
        let mut r = [0u32; 8];
        for i in 0..T::N {
            r[i] = a[i].f64() as u32;
        }
        r
    }
    #[inline(always)]
    fn split_exponent(self, a: [T; 8]) -> ([T; 8], [T; 8]) {
        let (mut e, mut m) = ([T::default(); 8], [T::default(); 8]);
        for i in 0..T::N {
            (e[i], m[i]) = a[i].split_exponent();
        }
        (e, m)
    }
    #[inline(always)]
    fn reduce4(self, a: [T; 8], b: [T; 8], c: [T; 8], d: [T; 8]) -> [T; 4] {
        let sum = |v: [T; 8]| {
            if T::N == 8 {
                ((v[0] + v[2]) + (v[1] + v[3])) + ((v[4] + v[6]) + (v[5] + v[7]))
            } else {
                (v[0] + v[1]) + (v[2] + v[3])
            }
        };
        [sum(a), sum(b), sum(c), sum(d)]
    }
}

/// AVX2 + FMA lanes, through `pulp`'s safe intrinsics (its `V3` token proves the CPU has
/// them).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use core::arch::x86_64::{__m128, __m256, __m256d};

    use super::Wide;

    /// Eight `f32` lanes.
    #[derive(Debug, Clone, Copy)]
    pub(crate) struct F32x8(pub pulp::x86::V3);

    /// Four `f64` lanes.
    #[derive(Debug, Clone, Copy)]
    pub(crate) struct F64x4(pub pulp::x86::V3);

    impl Wide for F32x8 {
        type T = f32;
        type V = __m256;

        #[inline(always)]
        fn splat(self, x: f32) -> __m256 {
            self.0.avx._mm256_set1_ps(x)
        }
        #[inline(always)]
        fn load(self, s: &[f32]) -> __m256 {
            let a: [f32; 8] = s[..8].try_into().expect("8 lanes");
            pulp::cast(a)
        }
        #[inline(always)]
        fn store(self, v: __m256, s: &mut [f32]) {
            s[..8].copy_from_slice(&pulp::cast::<__m256, [f32; 8]>(v));
        }
        #[inline(always)]
        fn lanes(self, v: __m256) -> [f32; 8] {
            pulp::cast(v)
        }
        #[inline(always)]
        fn vector(self, a: [f32; 8]) -> __m256 {
            pulp::cast(a)
        }
        #[inline(always)]
        fn add(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_add_ps(a, b)
        }
        #[inline(always)]
        fn sub(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_sub_ps(a, b)
        }
        #[inline(always)]
        fn mul(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_mul_ps(a, b)
        }
        #[inline(always)]
        fn div(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_div_ps(a, b)
        }
        #[inline(always)]
        fn fma(self, a: __m256, b: __m256, c: __m256) -> __m256 {
            self.0.fma._mm256_fmadd_ps(a, b, c)
        }
        #[inline(always)]
        fn min(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_min_ps(a, b)
        }
        #[inline(always)]
        fn max(self, a: __m256, b: __m256) -> __m256 {
            self.0.avx._mm256_max_ps(a, b)
        }
        #[inline(always)]
        fn floor(self, a: __m256) -> __m256 {
            self.0.avx._mm256_floor_ps(a)
        }
        #[inline(always)]
        fn sqrt(self, a: __m256) -> __m256 {
            self.0.avx._mm256_sqrt_ps(a)
        }
        #[inline(always)]
        fn select_gt(self, a: __m256, b: __m256, x: __m256, y: __m256) -> __m256 {
            let avx = self.0.avx;
            avx._mm256_blendv_ps(y, x, avx._mm256_cmp_ps::<30>(a, b)) // _CMP_GT_OQ
        }
        #[inline(always)]
        fn ne_mask(self, a: __m256, b: __m256) -> u32 {
            let avx = self.0.avx;
            avx._mm256_movemask_ps(avx._mm256_cmp_ps::<4>(a, b)) as u32 // _CMP_NEQ_UQ
        }
        #[inline(always)]
        fn non_finite_mask(self, a: __m256) -> u32 {
            // x − x is 0 for finite x, NaN otherwise.
            let avx = self.0.avx;
            let d = avx._mm256_sub_ps(a, a);
            avx._mm256_movemask_ps(avx._mm256_cmp_ps::<3>(d, d)) as u32 // _CMP_UNORD_Q
        }
        #[inline(always)]
        fn to_u32(self, a: __m256) -> [u32; 8] {
            pulp::cast(self.0.avx._mm256_cvttps_epi32(a))
        }
        #[inline(always)]
        fn split_exponent(self, a: __m256) -> (__m256, __m256) {
            let (avx, avx2) = (self.0.avx, self.0.avx2);
            let b = avx._mm256_castps_si256(a);
            let e = avx2._mm256_sub_epi32(
                avx2._mm256_and_si256(avx2._mm256_srli_epi32::<23>(b), avx._mm256_set1_epi32(0xff)),
                avx._mm256_set1_epi32(127),
            );
            let m = avx2._mm256_or_si256(
                avx2._mm256_and_si256(b, avx._mm256_set1_epi32(0x007f_ffff)),
                avx._mm256_set1_epi32(0x3f80_0000),
            );
            (avx._mm256_cvtepi32_ps(e), avx._mm256_castsi256_ps(m))
        }
        #[inline(always)]
        fn reduce4(self, a: __m256, b: __m256, c: __m256, d: __m256) -> [f32; 4] {
            let avx = self.0.avx;
            let h = self.halves(a, b, c, d);
            let s = self.0.sse._mm_add_ps(
                avx._mm256_castps256_ps128(h),
                avx._mm256_extractf128_ps::<1>(h),
            );
            pulp::cast::<__m128, [f32; 4]>(s)
        }
        #[inline(always)]
        fn reduce4_add(self, a: __m256, b: __m256, c: __m256, d: __m256, out: &mut [f32; 4]) {
            let (avx, sse) = (self.0.avx, self.0.sse);
            let h = self.halves(a, b, c, d);
            let s = sse._mm_add_ps(
                avx._mm256_castps256_ps128(h),
                avx._mm256_extractf128_ps::<1>(h),
            );
            let o: __m128 = pulp::cast(*out);
            *out = pulp::cast(sse._mm_add_ps(o, s));
        }
        #[inline(always)]
        fn reduce4_add_pair(self, p: [__m256; 4], q: [__m256; 4], out: &mut [f32; 8]) {
            let avx = self.0.avx;
            let hp = self.halves(p[0], p[1], p[2], p[3]);
            let hq = self.halves(q[0], q[1], q[2], q[3]);
            let lo = avx._mm256_permute2f128_ps::<0x20>(hp, hq);
            let hi = avx._mm256_permute2f128_ps::<0x31>(hp, hq);
            let o: __m256 = pulp::cast(*out);
            *out = pulp::cast(avx._mm256_add_ps(o, avx._mm256_add_ps(lo, hi)));
        }
        #[inline(always)]
        fn load_halves(self, a: &[f32], b: &[f32]) -> __m256 {
            let lo: [f32; 4] = a[..4].try_into().expect("4 lanes");
            let hi: [f32; 4] = b[..4].try_into().expect("4 lanes");
            self.0.avx._mm256_set_m128(pulp::cast(hi), pulp::cast(lo))
        }
        #[inline(always)]
        fn splat_halves(self, a: f32, b: f32) -> __m256 {
            let sse = self.0.sse;
            self.0
                .avx
                ._mm256_set_m128(sse._mm_set1_ps(b), sse._mm_set1_ps(a))
        }
        #[inline(always)]
        fn reduce4_halves(
            self,
            a: __m256,
            b: __m256,
            c: __m256,
            d: __m256,
        ) -> ([f32; 4], [f32; 4]) {
            let avx = self.0.avx;
            let h = self.halves(a, b, c, d);
            (
                pulp::cast(avx._mm256_castps256_ps128(h)),
                pulp::cast(avx._mm256_extractf128_ps::<1>(h)),
            )
        }
        #[inline(always)]
        fn add4(self, s: [f32; 4], out: &mut [f32; 4]) {
            let o: __m128 = pulp::cast(*out);
            *out = pulp::cast(self.0.sse._mm_add_ps(o, pulp::cast(s)));
        }
        #[inline(always)]
        fn store_halves(self, v: __m256, s: &mut [f32], na: usize, nb: usize, whole: bool) {
            let avx = self.0.avx;
            let lo: [f32; 4] = pulp::cast(avx._mm256_castps256_ps128(v));
            let hi: [f32; 4] = pulp::cast(avx._mm256_extractf128_ps::<1>(v));
            if whole {
                s[..4].copy_from_slice(&lo);
                s[na..na + 4].copy_from_slice(&hi);
            } else {
                s[..na].copy_from_slice(&lo[..na]);
                s[na..na + nb].copy_from_slice(&hi[..nb]);
            }
        }
    }

    impl F32x8 {
        /// `[Σa, Σb, Σc, Σd]` of lanes 0–3 in the low half, of lanes 4–7 in the high half, each
        /// as `(l₀+l₂)+(l₁+l₃)` (unpacks and shuffles: `hadd` is slower on these CPUs).
        #[inline(always)]
        fn halves(self, a: __m256, b: __m256, c: __m256, d: __m256) -> __m256 {
            let avx = self.0.avx;
            // [a0+a2, b0+b2, a1+a3, b1+b3 | lanes 4–7], likewise for c, d.
            let ab = avx._mm256_add_ps(avx._mm256_unpacklo_ps(a, b), avx._mm256_unpackhi_ps(a, b));
            let cd = avx._mm256_add_ps(avx._mm256_unpacklo_ps(c, d), avx._mm256_unpackhi_ps(c, d));
            avx._mm256_add_ps(
                avx._mm256_shuffle_ps::<0x44>(ab, cd),
                avx._mm256_shuffle_ps::<0xEE>(ab, cd),
            )
        }
    }

    impl Wide for F64x4 {
        type T = f64;
        type V = __m256d;

        #[inline(always)]
        fn splat(self, x: f64) -> __m256d {
            self.0.avx._mm256_set1_pd(x)
        }
        #[inline(always)]
        fn load(self, s: &[f64]) -> __m256d {
            let a: [f64; 4] = s[..4].try_into().expect("4 lanes");
            pulp::cast(a)
        }
        #[inline(always)]
        fn store(self, v: __m256d, s: &mut [f64]) {
            s[..4].copy_from_slice(&pulp::cast::<__m256d, [f64; 4]>(v));
        }
        #[inline(always)]
        fn lanes(self, v: __m256d) -> [f64; 8] {
            let a: [f64; 4] = pulp::cast(v);
            [a[0], a[1], a[2], a[3], 0.0, 0.0, 0.0, 0.0]
        }
        #[inline(always)]
        fn vector(self, a: [f64; 8]) -> __m256d {
            pulp::cast([a[0], a[1], a[2], a[3]])
        }
        #[inline(always)]
        fn add(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_add_pd(a, b)
        }
        #[inline(always)]
        fn sub(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_sub_pd(a, b)
        }
        #[inline(always)]
        fn mul(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_mul_pd(a, b)
        }
        #[inline(always)]
        fn div(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_div_pd(a, b)
        }
        #[inline(always)]
        fn fma(self, a: __m256d, b: __m256d, c: __m256d) -> __m256d {
            self.0.fma._mm256_fmadd_pd(a, b, c)
        }
        #[inline(always)]
        fn min(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_min_pd(a, b)
        }
        #[inline(always)]
        fn max(self, a: __m256d, b: __m256d) -> __m256d {
            self.0.avx._mm256_max_pd(a, b)
        }
        #[inline(always)]
        fn floor(self, a: __m256d) -> __m256d {
            self.0.avx._mm256_floor_pd(a)
        }
        #[inline(always)]
        fn sqrt(self, a: __m256d) -> __m256d {
            self.0.avx._mm256_sqrt_pd(a)
        }
        #[inline(always)]
        fn select_gt(self, a: __m256d, b: __m256d, x: __m256d, y: __m256d) -> __m256d {
            let avx = self.0.avx;
            avx._mm256_blendv_pd(y, x, avx._mm256_cmp_pd::<30>(a, b)) // _CMP_GT_OQ
        }
        #[inline(always)]
        fn ne_mask(self, a: __m256d, b: __m256d) -> u32 {
            let avx = self.0.avx;
            avx._mm256_movemask_pd(avx._mm256_cmp_pd::<4>(a, b)) as u32 // _CMP_NEQ_UQ
        }
        #[inline(always)]
        fn non_finite_mask(self, a: __m256d) -> u32 {
            let avx = self.0.avx;
            let d = avx._mm256_sub_pd(a, a);
            avx._mm256_movemask_pd(avx._mm256_cmp_pd::<3>(d, d)) as u32 // _CMP_UNORD_Q
        }
        #[inline(always)]
        fn to_u32(self, a: __m256d) -> [u32; 8] {
            let r: [u32; 4] = pulp::cast(self.0.avx._mm256_cvttpd_epi32(a));
            [r[0], r[1], r[2], r[3], 0, 0, 0, 0]
        }
        #[inline(always)]
        fn split_exponent(self, a: __m256d) -> (__m256d, __m256d) {
            // The biased exponent (0..2047) as a double by the 2⁵² trick: OR it into the
            // mantissa of 2⁵² and subtract 2⁵² (exact).
            let (avx, avx2) = (self.0.avx, self.0.avx2);
            let b = avx._mm256_castpd_si256(a);
            let eb = avx2._mm256_and_si256(
                avx2._mm256_srli_epi64::<52>(b),
                avx._mm256_set1_epi64x(0x7ff),
            );
            let two52 = avx._mm256_set1_epi64x(0x4330_0000_0000_0000);
            let ef = avx._mm256_sub_pd(
                avx._mm256_castsi256_pd(avx2._mm256_or_si256(eb, two52)),
                avx._mm256_castsi256_pd(two52),
            );
            let e = avx._mm256_sub_pd(ef, avx._mm256_set1_pd(1023.0));
            let m = avx2._mm256_or_si256(
                avx2._mm256_and_si256(b, avx._mm256_set1_epi64x(0x000f_ffff_ffff_ffff)),
                avx._mm256_set1_epi64x(0x3ff0_0000_0000_0000),
            );
            (e, avx._mm256_castsi256_pd(m))
        }
        #[inline(always)]
        fn reduce4(self, a: __m256d, b: __m256d, c: __m256d, d: __m256d) -> [f64; 4] {
            // hadd(a, b) = [a₀+a₁, b₀+b₁, a₂+a₃, b₂+b₃]; the 128-bit halves of the two hadds
            // regrouped and added: [(a₀+a₁)+(a₂+a₃), ...].
            let avx = self.0.avx;
            let h1 = avx._mm256_hadd_pd(a, b);
            let h2 = avx._mm256_hadd_pd(c, d);
            let lo = avx._mm256_permute2f128_pd::<0x20>(h1, h2);
            let hi = avx._mm256_permute2f128_pd::<0x31>(h1, h2);
            pulp::cast::<__m256d, [f64; 4]>(avx._mm256_add_pd(lo, hi))
        }
        #[inline(always)]
        fn reduce4_add(self, a: __m256d, b: __m256d, c: __m256d, d: __m256d, out: &mut [f64; 4]) {
            let avx = self.0.avx;
            let h1 = avx._mm256_hadd_pd(a, b);
            let h2 = avx._mm256_hadd_pd(c, d);
            let lo = avx._mm256_permute2f128_pd::<0x20>(h1, h2);
            let hi = avx._mm256_permute2f128_pd::<0x31>(h1, h2);
            let o: __m256d = pulp::cast(*out);
            *out = pulp::cast(avx._mm256_add_pd(o, avx._mm256_add_pd(lo, hi)));
        }
        #[inline(always)]
        fn load_halves(self, a: &[f64], b: &[f64]) -> __m256d {
            let lo: [f64; 2] = a[..2].try_into().expect("2 lanes");
            let hi: [f64; 2] = b[..2].try_into().expect("2 lanes");
            self.0.avx._mm256_set_m128d(pulp::cast(hi), pulp::cast(lo))
        }
        #[inline(always)]
        fn splat_halves(self, a: f64, b: f64) -> __m256d {
            let sse2 = self.0.sse2;
            self.0
                .avx
                ._mm256_set_m128d(sse2._mm_set1_pd(b), sse2._mm_set1_pd(a))
        }
        #[inline(always)]
        fn reduce4_halves(
            self,
            a: __m256d,
            b: __m256d,
            c: __m256d,
            d: __m256d,
        ) -> ([f64; 4], [f64; 4]) {
            // [a0+a1, b0+b1, a2+a3, b2+b3] and the same for c, d.
            let avx = self.0.avx;
            let h1 = avx._mm256_hadd_pd(a, b);
            let h2 = avx._mm256_hadd_pd(c, d);
            (
                pulp::cast(avx._mm256_permute2f128_pd::<0x20>(h1, h2)),
                pulp::cast(avx._mm256_permute2f128_pd::<0x31>(h1, h2)),
            )
        }
        #[inline(always)]
        fn add4(self, s: [f64; 4], out: &mut [f64; 4]) {
            let o: __m256d = pulp::cast(*out);
            *out = pulp::cast(self.0.avx._mm256_add_pd(o, pulp::cast(s)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every lane operation of the AVX2 lanes gives the bits of the portable ones, for both
    /// precisions, and `ln` is within two ulps of the library logarithm.
    struct Probe<T>(Vec<T>);

    impl<T: Real> WideOp<T> for Probe<T> {
        type Output = Vec<T>;

        #[inline(always)]
        fn with<W: Wide<T = T>>(self, w: W) -> Vec<T> {
            let mut out = Vec::new();
            for c in self.0.chunks(T::N) {
                let mut buf = [T::default(); 8];
                buf[..c.len()].copy_from_slice(c);
                let a = w.vector(buf);
                let b = w.mul(a, w.c(1.7));
                let r = [
                    w.ln(a),
                    w.fma(a, b, w.c(-0.3)),
                    w.floor(b),
                    w.sqrt(a),
                    w.div(b, a),
                    w.min(a, b),
                    w.max(a, b),
                ];
                for v in r {
                    out.extend_from_slice(&w.lanes(v)[..T::N]);
                }
                let s = w.reduce4(a, b, r[0], r[1]);
                out.extend_from_slice(&s);
                out.push(T::of(w.ne_mask(a, w.floor(a)) as f64));
                // The pair operations: halves loaded, splat, kept, summed and stored apart.
                let h = T::N / 2;
                let ab = w.load_halves(&buf[1..], &buf[h - 1..]);
                let sp = w.splat_halves(c[0], c[c.len() - 1]);
                let kept = w.keep_halves(w.mul(ab, sp), 1 + c.len() % h, h - 1);
                let (sa, sb) = w.reduce4_halves(ab, sp, kept, b);
                let mut acc = sb;
                w.add4(sa, &mut acc);
                out.extend_from_slice(&acc);
                for whole in [true, false] {
                    let mut slots = [T::of(-1.0); 16];
                    w.store_halves(kept, &mut slots, h - 1, h, whole);
                    out.extend_from_slice(&slots);
                }
            }
            out
        }
    }

    fn same_bits<T: Precise>(xs: Vec<T>) -> Vec<T> {
        let best = Isa::detect().run_wide(Probe(xs.clone()));
        let port = Isa::Baseline.run_wide(Probe(xs));
        assert_eq!(best.len(), port.len());
        for (i, (a, b)) in best.iter().zip(&port).enumerate() {
            assert!(
                a.f64().to_bits() == b.f64().to_bits(),
                "entry {i}: {a:?} vs {b:?}"
            );
        }
        best
    }

    #[test]
    fn lanes_agree_bit_for_bit_and_ln_is_accurate() {
        let xs: Vec<f64> = (0..64)
            .map(|i| 10f64.powf(-6.0 + 12.0 * i as f64 / 63.0) * (1.0 + 0.1 * (i % 5) as f64))
            .collect();
        same_bits(xs.clone());
        same_bits(xs.iter().map(|&x| x as f32).collect::<Vec<_>>());
        for &x in &xs {
            let l64 = Isa::detect().run_wide(Probe(vec![x; 4]))[0];
            assert!(
                (l64 - x.ln()).abs() <= 4.0 * f64::EPSILON * x.ln().abs().max(1.0),
                "{x}"
            );
            let x32 = x as f32;
            let l32 = Isa::detect().run_wide(Probe(vec![x32; 8]))[0];
            assert!(
                (l32 - x32.ln()).abs() <= 4.0 * f32::EPSILON * x32.ln().abs().max(1.0),
                "{x32}: {l32} vs {}",
                x32.ln()
            );
        }
        for bad in [0.0f64, -1.0, f64::NAN] {
            assert!(Isa::detect().run_wide(Probe(vec![bad; 4]))[0].is_nan());
            assert!(Isa::Baseline.run_wide(Probe(vec![bad as f32; 8]))[0].is_nan());
        }
    }
}
