//! Small deterministic random numbers and matrices for the SVD / polar tests (SplitMix64, no
//! dependency). Included with `#[path = "common/rng.rs"] mod rng;` (from `benches/`:
//! `"../tests/common/rng.rs"`).
#![allow(dead_code)]

use glam::{DMat3, DQuat, DVec3};

/// SplitMix64: small deterministic generator, no dependency.
pub struct Rng(pub u64);

impl Rng {
    pub fn seeded(name: &str) -> Self {
        Rng(name.bytes().fold(0x5EED, |h: u64, b| {
            (h ^ b as u64).wrapping_mul(0x0100_0000_01B3)
        }))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Log-uniform in [lo, hi].
    pub fn log_range(&mut self, lo: f64, hi: f64) -> f64 {
        (lo.ln() + (hi.ln() - lo.ln()) * self.unit()).exp()
    }

    /// Uniformly distributed rotation (normalised 4D point in the unit ball).
    pub fn rotation(&mut self) -> DMat3 {
        loop {
            let q = [0; 4].map(|_| self.range(-1.0, 1.0));
            let n2: f64 = q.iter().map(|v| v * v).sum();
            if n2 > 1e-4 && n2 <= 1.0 {
                let q = DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize();
                return DMat3::from_quat(q);
            }
        }
    }

    pub fn mat(&mut self, amp: f64) -> DMat3 {
        DMat3::from_cols_array(&[0.0; 9].map(|_| self.range(-amp, amp)))
    }

    /// `U diag(s) Vᵀ` with random rotations `U`, `V`.
    pub fn usv(&mut self, s: DVec3) -> DMat3 {
        self.rotation() * DMat3::from_diagonal(s) * self.rotation().transpose()
    }
}
