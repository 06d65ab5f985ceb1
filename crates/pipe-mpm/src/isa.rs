//! Run-time choice of the instruction set for the particle kernels.
//!
//! On a CPU with AVX2 + FMA the kernels run with `pulp`'s `V3` token (and with AVX-512's 32
//! registers when present), their lanes `crate::wide::simd`'s AVX2 vectors; elsewhere they
//! run the same arithmetic lane by lane. Either way every operation is exactly rounded, so the
//! results are the same bits.

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
}
