//! The scalar type the kernels are generic over.
//!
//! The rasterizer is written once for `T: Real` and compiled for `f32` (production) and `f64`
//! (finite-difference checks and reference comparisons). Only the handful of operations the
//! kernels need are required.

use std::fmt::Debug;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Sub, SubAssign};

/// A floating-point scalar (`f32` or `f64`).
pub trait Real:
    Copy
    + Send
    + Sync
    + Debug
    + Default
    + PartialOrd
    + 'static
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
{
    /// 0.
    const ZERO: Self;
    /// 1.
    const ONE: Self;
    /// Nearest representable value (constants fold at compile time).
    fn from_f64(v: f64) -> Self;
    /// Widen (exact for `f32`).
    fn to_f64(self) -> f64;
    /// Square root.
    fn sqrt(self) -> Self;
    /// e^self.
    fn exp(self) -> Self;
    /// e^self for the blend's hot loop: `f32` uses a range-reduced degree-7 polynomial
    /// (relative error < 2e-7 for |x| < 80), `f64` the standard library.
    fn exp_fast(self) -> Self;
    /// Natural logarithm.
    fn ln(self) -> Self;
    /// Round toward +inf.
    fn ceil(self) -> Self;
    /// Round toward -inf.
    fn floor(self) -> Self;
    /// Absolute value.
    fn abs(self) -> Self;
    /// Smaller of the two (the non-NaN one if one is NaN).
    fn min(self, o: Self) -> Self;
    /// Larger of the two (the non-NaN one if one is NaN).
    fn max(self, o: Self) -> Self;
    /// Neither NaN nor infinite.
    fn is_finite(self) -> bool;
    /// Bit pattern widened to `u64`; monotonic in the value for non-negative finite numbers,
    /// which is what the depth sort uses.
    fn sort_bits(self) -> u64;
}

macro_rules! impl_real {
    ($t:ty, $fast_exp:expr) => {
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            #[inline(always)]
            fn from_f64(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn exp(self) -> Self {
                <$t>::exp(self)
            }
            #[inline(always)]
            fn exp_fast(self) -> Self {
                $fast_exp(self)
            }
            #[inline(always)]
            fn ln(self) -> Self {
                <$t>::ln(self)
            }
            #[inline(always)]
            fn ceil(self) -> Self {
                <$t>::ceil(self)
            }
            #[inline(always)]
            fn floor(self) -> Self {
                <$t>::floor(self)
            }
            #[inline(always)]
            fn abs(self) -> Self {
                <$t>::abs(self)
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                <$t>::min(self, o)
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                <$t>::max(self, o)
            }
            #[inline(always)]
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
            #[inline(always)]
            fn sort_bits(self) -> u64 {
                self.to_bits() as u64
            }
        }
    };
}

/// `e^x = 2^n · e^r`, `n = round(x·log2 e)`, `|r| <= ln2/2`, `e^r` by its Taylor polynomial
/// of degree 7 (truncation error < 6e-9), `2^n` assembled from the exponent bits. Branch-
/// and conversion-free so that loops over lanes of it vectorise.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    // 1.5·2^23: adding it rounds to an integer held in the low mantissa bits.
    const MAGIC: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let t = x * std::f32::consts::LOG2_E + MAGIC;
    let n = t - MAGIC;
    let ni = t.to_bits().wrapping_sub(MAGIC.to_bits());
    // ln 2 split in a high part exact in f32 times small n, and the rest
    let r = (x - n * 0.693_359_4) + n * 2.121_944_4e-4;
    let mut p = 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    p * f32::from_bits(ni.wrapping_add(127) << 23)
}

impl_real!(f32, exp_f32);
impl_real!(f64, f64::exp);

#[cfg(test)]
mod tests {
    use super::*;

    /// The f32 fast exponential stays within the documented relative error of the exact
    /// value over the blend's range (power in [-5.6, 0]) and beyond, and never overflows.
    #[test]
    fn fast_exp_accuracy() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -80.0 + 85.0 * i as f64 / 200_000.0; // [-80, 5]
            let xf = x as f32;
            let got = xf.exp_fast() as f64;
            let want = (xf as f64).exp();
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 2e-7, "max relative error {worst:e}");
        assert!(f32::NEG_INFINITY.exp_fast() >= 0.0 && f32::NEG_INFINITY.exp_fast() < 1e-37);
        assert!(100.0f32.exp_fast().is_finite());
        assert_eq!(0.0f32.exp_fast(), 1.0);
    }
}
