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
/// FMA without AVX-512, 2: baseline), so a test can run every path in one process. Set only
/// through a [`CapGuard`], which serialises the tests that compare paths.
#[cfg(test)]
static CAP: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(0);

/// Held by whichever test is setting [`CAP`].
#[cfg(test)]
static CAP_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Test hook: the instruction-set cap, owned by one test at a time. Tests run in parallel, so
/// a test that compares the paths holds a guard for the whole comparison: no other test can
/// change the cap under it (which would silently compare a path with itself). Tests that do
/// not hold one may run on any path, which gives them the same bits.
#[cfg(test)]
#[derive(Debug)]
pub(crate) struct CapGuard {
    _lock: std::sync::MutexGuard<'static, ()>,
}

#[cfg(test)]
impl CapGuard {
    /// Waits until no other test holds the cap, then holds it at 0 (the best instructions).
    pub(crate) fn lock() -> Self {
        // A test that panicked while holding the lock leaves it poisoned; the cap it set is
        // reset by its guard's drop, so the lock is still good.
        let lock = CAP_LOCK
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        CAP.store(0, std::sync::atomic::Ordering::Relaxed);
        Self { _lock: lock }
    }

    /// Caps the instruction set at `cap` until the next call or the guard's drop.
    pub(crate) fn set(&self, cap: u8) {
        CAP.store(cap, std::sync::atomic::Ordering::Relaxed);
    }
}

#[cfg(test)]
impl Drop for CapGuard {
    fn drop(&mut self) {
        CAP.store(0, std::sync::atomic::Ordering::Relaxed);
    }
}

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

#[cfg(test)]
mod tests {
    use super::{CapGuard, cap};

    /// Two tests that set the cap at once take turns: each sees its own cap for as long as
    /// its guard lives, and the cap is back at 0 after.
    #[test]
    fn a_guard_keeps_its_cap_until_dropped() {
        let tests: Vec<_> = [1u8, 2]
            .into_iter()
            .map(|c| {
                std::thread::spawn(move || {
                    let isa = CapGuard::lock();
                    isa.set(c);
                    for _ in 0..20 {
                        std::thread::sleep(std::time::Duration::from_millis(1));
                        assert_eq!(cap(), c, "another test changed the cap under this one");
                    }
                })
            })
            .collect();
        for t in tests {
            t.join().unwrap();
        }
        let _isa = CapGuard::lock();
        assert_eq!(cap(), 0);
    }
}
