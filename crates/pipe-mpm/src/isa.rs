//! Run-time choice of the instruction set for the particle kernels.
//!
//! The node kernels work on four `f64` lanes (a grid node's momentum and mass, or a node
//! velocity padded with 0) through [`Lanes`]. Run by [`Isa::run_lanes`] on a CPU with AVX2 +
//! FMA they get `pulp`'s `f64x4` vectors and are compiled with those features enabled
//! (`pulp`'s `vectorize`); elsewhere they get plain arrays and `f64::mul_add` (a software
//! fused multiply-add: slower, but bit-identical, since a fused multiply-add is exactly rounded
//! either way). The G2P adjoint alone also enables AVX-512 when present
//! ([`Isa::run_lanes_avx512`]: the same lanes with 32 registers). Everything called inside must
//! be `#[inline(always)]` to inherit the features, and the work is handed over as a
//! [`WithLanes`] value whose `with` is `#[inline(always)]` (a closure's body is not reliably
//! inlined, and would then run without the features, calling the software `fma`).

/// The instruction set the kernels run with (detected once per call site; `pulp` caches it).
#[derive(Debug, Clone, Copy)]
pub(crate) enum Isa {
    /// AVX2 + FMA (x86-64-v3).
    #[cfg(target_arch = "x86_64")]
    Fma(pulp::x86::V3),
    /// Baseline instructions.
    #[allow(dead_code)]
    Baseline,
}

/// Test hook: caps the instruction set the kernels may use (0: the best the CPU has, 1: AVX2 +
/// FMA without AVX-512, 2: baseline), so a test can run every path in one process.
#[cfg(test)]
pub(crate) static CAP: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(0);

#[cfg(test)]
pub(crate) fn cap() -> u8 {
    CAP.load(std::sync::atomic::Ordering::Relaxed)
}

#[cfg(not(test))]
#[inline(always)]
pub(crate) fn cap() -> u8 {
    0
}

impl Isa {
    /// The best instruction set of this CPU.
    #[inline]
    pub(crate) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if cap() < 2
            && let Some(v) = pulp::x86::V3::try_new()
        {
            return Isa::Fma(v);
        }
        Isa::Baseline
    }

    /// [`Self::run_lanes`] with AVX-512 enabled as well when the CPU has it: the same four-lane
    /// arithmetic (so the same results), but 32 vector registers. Only the G2P adjoint uses it:
    /// its node loop spills with 16 registers and runs ~10 % faster with 32, while the forward
    /// G2P and the per-particle adjoint were measured slightly slower (BENCHMARKS.md §3).
    #[inline(always)]
    pub(crate) fn run_lanes_avx512<Op: WithLanes>(self, op: Op) -> Op::Output {
        #[cfg(target_arch = "x86_64")]
        if let Isa::Fma(_) = self
            && cap() < 1
            && let Some(v) = pulp::x86::V4::try_new()
        {
            return v.vectorize(InLanes(Avx512(v), op));
        }
        self.run_lanes(op)
    }

    /// Runs `op` with this instruction set enabled and its [`Lanes`].
    #[inline(always)]
    pub(crate) fn run_lanes<Op: WithLanes>(self, op: Op) -> Op::Output {
        match self {
            #[cfg(target_arch = "x86_64")]
            Isa::Fma(v) => v.vectorize(InLanes(v, op)),
            Isa::Baseline => op.with(Scalar),
        }
    }
}

/// Work generic over the [`Lanes`] implementation, for [`Isa::run_lanes`].
pub(crate) trait WithLanes {
    /// Result.
    type Output;
    /// Runs the work with lanes `l` (must be `#[inline(always)]`).
    fn with<L: Lanes>(self, l: L) -> Self::Output;
}

/// `op` bound to lanes `l`, as a [`pulp::NullaryFnOnce`].
struct InLanes<L, Op>(L, Op);

impl<L: Lanes, Op: WithLanes> pulp::NullaryFnOnce for InLanes<L, Op> {
    type Output = Op::Output;

    #[inline(always)]
    fn call(self) -> Op::Output {
        self.1.with(self.0)
    }
}

/// Four `f64` lanes and the operations the node kernels need: AVX2 vectors under
/// [`Isa::Fma`], plain arrays (the same arithmetic lane by lane) otherwise.
pub(crate) trait Lanes: Copy {
    /// The vector type.
    type V: Copy;
    /// `[a, b, c, d]` as a vector.
    fn load(self, a: [f64; 4]) -> Self::V;
    /// The lanes of a vector.
    fn store(self, v: Self::V) -> [f64; 4];
    /// `[v.x, v.y, v.z, w]`: a 3-vector with a fourth lane (0 to pad, or a node's mass).
    #[inline(always)]
    fn load3(self, v: glam::DVec3, w: f64) -> Self::V {
        self.load([v.x, v.y, v.z, w])
    }
    /// `x` in every lane.
    fn splat(self, x: f64) -> Self::V;
    /// `a b + c`, fused.
    fn fma(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V;
    /// `a b`.
    fn mul(self, a: Self::V, b: Self::V) -> Self::V;
    /// `⌊x⌋` of a scalar (exact).
    fn floor(self, x: f64) -> f64;
    /// `(v₀ + v₁) + (v₂ + v₃)`, the same order for every implementation.
    #[inline(always)]
    fn hsum(self, v: Self::V) -> f64 {
        let a = self.store(v);
        (a[0] + a[1]) + (a[2] + a[3])
    }
    /// [`Self::hsum`] of two vectors at once (same sums, same order).
    #[inline(always)]
    fn hsum2(self, a: Self::V, b: Self::V) -> [f64; 2] {
        [self.hsum(a), self.hsum(b)]
    }
}

#[cfg(target_arch = "x86_64")]
impl Lanes for pulp::x86::V3 {
    type V = pulp::f64x4;

    #[inline(always)]
    fn load(self, a: [f64; 4]) -> pulp::f64x4 {
        pulp::cast(a)
    }

    #[inline(always)]
    fn store(self, v: pulp::f64x4) -> [f64; 4] {
        pulp::cast(v)
    }

    #[inline(always)]
    fn splat(self, x: f64) -> pulp::f64x4 {
        self.splat_f64x4(x)
    }

    #[inline(always)]
    fn fma(self, a: pulp::f64x4, b: pulp::f64x4, c: pulp::f64x4) -> pulp::f64x4 {
        self.mul_add_f64x4(a, b, c)
    }

    #[inline(always)]
    fn mul(self, a: pulp::f64x4, b: pulp::f64x4) -> pulp::f64x4 {
        self.mul_f64x4(a, b)
    }

    #[inline(always)]
    fn hsum2(self, a: pulp::f64x4, b: pulp::f64x4) -> [f64; 2] {
        // [a0 + a1, b0 + b1, a2 + a3, b2 + b3], then the halves added: the order of `hsum`.
        let h = self.avx._mm256_hadd_pd(pulp::cast(a), pulp::cast(b));
        let lo = self.avx._mm256_castpd256_pd128(h);
        let hi = self.avx._mm256_extractf128_pd::<1>(h);
        pulp::cast(self.sse2._mm_add_pd(lo, hi))
    }

    #[inline(always)]
    fn floor(self, x: f64) -> f64 {
        // `roundsd` (SSE4.1, part of x86-64-v3) once inlined under these features.
        x.floor()
    }
}

/// The AVX2 lanes of [`pulp::x86::V3`], used under AVX-512's target features
/// ([`Isa::run_lanes_avx512`]).
#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy)]
pub(crate) struct Avx512(pulp::x86::V4);

#[cfg(target_arch = "x86_64")]
impl Lanes for Avx512 {
    type V = pulp::f64x4;

    #[inline(always)]
    fn load(self, a: [f64; 4]) -> pulp::f64x4 {
        Lanes::load(*self.0, a)
    }

    #[inline(always)]
    fn store(self, v: pulp::f64x4) -> [f64; 4] {
        Lanes::store(*self.0, v)
    }

    #[inline(always)]
    fn splat(self, x: f64) -> pulp::f64x4 {
        Lanes::splat(*self.0, x)
    }

    #[inline(always)]
    fn fma(self, a: pulp::f64x4, b: pulp::f64x4, c: pulp::f64x4) -> pulp::f64x4 {
        Lanes::fma(*self.0, a, b, c)
    }

    #[inline(always)]
    fn mul(self, a: pulp::f64x4, b: pulp::f64x4) -> pulp::f64x4 {
        Lanes::mul(*self.0, a, b)
    }

    #[inline(always)]
    fn hsum2(self, a: pulp::f64x4, b: pulp::f64x4) -> [f64; 2] {
        Lanes::hsum2(*self.0, a, b)
    }

    #[inline(always)]
    fn floor(self, x: f64) -> f64 {
        Lanes::floor(*self.0, x)
    }
}

/// Lane-by-lane fallback of [`Lanes`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Scalar;

impl Lanes for Scalar {
    type V = [f64; 4];

    #[inline(always)]
    fn load(self, a: [f64; 4]) -> [f64; 4] {
        a
    }

    #[inline(always)]
    fn store(self, v: [f64; 4]) -> [f64; 4] {
        v
    }

    #[inline(always)]
    fn splat(self, x: f64) -> [f64; 4] {
        [x; 4]
    }

    #[inline(always)]
    fn fma(self, a: [f64; 4], b: [f64; 4], c: [f64; 4]) -> [f64; 4] {
        std::array::from_fn(|l| a[l].mul_add(b[l], c[l]))
    }

    #[inline(always)]
    fn mul(self, a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
        std::array::from_fn(|l| a[l] * b[l])
    }

    #[inline(always)]
    fn floor(self, x: f64) -> f64 {
        crate::grid::floor1(x)
    }
}

/// Whether some value of `data` is NaN or ±Inf: `0·x` is NaN exactly for those, so the lanes
/// accumulate `x·0 + acc` and stay 0 otherwise (two vectors of four per step).
#[inline(always)]
pub(crate) fn any_non_finite<L: Lanes>(l: L, data: &[f64]) -> bool {
    let zero = l.splat(0.0);
    let (mut a, mut b) = (zero, zero);
    let mut blocks = data.chunks_exact(8);
    for x in &mut blocks {
        a = l.fma(l.load([x[0], x[1], x[2], x[3]]), zero, a);
        b = l.fma(l.load([x[4], x[5], x[6], x[7]]), zero, b);
    }
    let sum = l.hsum(l.mul(a, b));
    !sum.is_finite() || !blocks.remainder().iter().all(|x| x.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Probe<'a>(&'a [f64]);

    impl WithLanes for Probe<'_> {
        type Output = (bool, [f64; 2]);

        #[inline(always)]
        fn with<L: Lanes>(self, l: L) -> (bool, [f64; 2]) {
            let a = l.load([1e-17, 1.0, -1.0, 3.0]);
            let b = l.load([0.1, 0.2, 0.3, 1e20]);
            (any_non_finite(l, self.0), l.hsum2(a, b))
        }
    }

    /// Both instruction sets flag a NaN/Inf at every position (in the blocks of eight and in
    /// the remainder) and nothing else; `hsum2` sums in `hsum`'s order.
    #[test]
    fn non_finite_probe_and_pair_sums() {
        let isas = [Isa::detect(), Isa::Baseline];
        for n in [0, 5, 8, 13, 24] {
            let finite: Vec<f64> = (0..n).map(|i| 1e300 * (i as f64 - 3.0)).collect();
            for isa in isas {
                assert!(!isa.run_lanes(Probe(&finite)).0, "n={n}");
            }
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                for at in 0..n {
                    let mut v = finite.clone();
                    v[at] = bad;
                    for isa in isas {
                        assert!(isa.run_lanes(Probe(&v)).0, "n={n} at={at} {bad}");
                    }
                }
            }
        }
        let want = [(1e-17 + 1.0) + (-1.0 + 3.0), (0.1 + 0.2) + (0.3 + 1e20)];
        for isa in isas {
            assert_eq!(isa.run_lanes(Probe(&[])).1, want);
        }
    }
}
