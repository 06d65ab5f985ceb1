//! Run-time choice of the instruction set for the particle kernels.
//!
//! The kernels are plain Rust written lane by lane with `f64::mul_add`; run inside
//! [`Isa::run`] on a CPU with AVX2 + FMA they are compiled with those features enabled
//! (`pulp`'s `vectorize`), so the fused multiply-adds are single instructions and LLVM packs
//! the four lanes of a grid node into one vector. Without them the same code runs with a
//! software `mul_add`: slower, but bit-identical, since a fused multiply-add is exactly rounded
//! either way. Everything called inside must be `#[inline(always)]` to inherit the features,
//! and the work is handed over as a [`pulp::NullaryFnOnce`] whose `call` is
//! `#[inline(always)]` (a closure's body is not reliably inlined, and would then run without
//! the features, calling the software `fma`).

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

impl Isa {
    /// The best instruction set of this CPU.
    #[inline]
    pub(crate) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if let Some(v) = pulp::x86::V3::try_new() {
            return Isa::Fma(v);
        }
        Isa::Baseline
    }

    /// Runs `op` with this instruction set enabled.
    #[inline(always)]
    pub(crate) fn run<Op: pulp::NullaryFnOnce>(self, op: Op) -> Op::Output {
        match self {
            #[cfg(target_arch = "x86_64")]
            Isa::Fma(v) => v.vectorize(op),
            Isa::Baseline => op.call(),
        }
    }
}
