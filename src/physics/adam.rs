//! Adam (Kingma & Ba 2015) on a handful of `f64` parameters, with gradient-norm clipping and
//! an exponentially decaying step; its whole state serialises, so a stage can checkpoint it
//! and resume to the same bits.

use serde::{Deserialize, Serialize};

/// Adam's state for `n` parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// First moments.
    m: Vec<f64>,
    /// Second moments.
    v: Vec<f64>,
    /// Steps taken.
    pub t: u32,
}

/// Adam's hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    /// Decay of the first moment.
    pub beta1: f64,
    /// Decay of the second moment.
    pub beta2: f64,
    /// Denominator guard.
    pub eps: f64,
    /// The gradient is scaled down to this norm when longer (`f64::INFINITY`: never).
    pub clip: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-12,
            clip: f64::INFINITY,
        }
    }
}

/// What a step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepInfo {
    /// The gradient's norm before clipping.
    pub norm: f64,
    /// Whether it was clipped.
    pub clipped: bool,
}

impl Adam {
    /// Zero moments for `n` parameters.
    pub fn new(n: usize) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// One step: `p ← p − lr_k·m̂/(√v̂ + ε)` with the rate `lr[k]` of parameter `k`.
    pub fn step(
        &mut self,
        cfg: &AdamConfig,
        params: &mut [f64],
        grad: &[f64],
        lr: &[f64],
    ) -> StepInfo {
        assert_eq!(params.len(), self.m.len(), "one parameter per moment");
        assert_eq!(grad.len(), self.m.len(), "one gradient per parameter");
        assert_eq!(lr.len(), self.m.len(), "one rate per parameter");
        let norm = grad.iter().map(|g| g * g).sum::<f64>().sqrt();
        let scale = if norm > cfg.clip {
            cfg.clip / norm
        } else {
            1.0
        };
        self.t += 1;
        let bc1 = 1.0 - cfg.beta1.powi(self.t as i32);
        let bc2 = 1.0 - cfg.beta2.powi(self.t as i32);
        for k in 0..params.len() {
            let g = grad[k] * scale;
            self.m[k] = cfg.beta1 * self.m[k] + (1.0 - cfg.beta1) * g;
            self.v[k] = cfg.beta2 * self.v[k] + (1.0 - cfg.beta2) * g * g;
            let (mh, vh) = (self.m[k] / bc1, self.v[k] / bc2);
            params[k] -= lr[k] * mh / (vh.sqrt() + cfg.eps);
        }
        StepInfo {
            norm,
            clipped: scale < 1.0,
        }
    }
}

/// The rate at `progress ∈ [0, 1]` of a schedule decaying exponentially from `start` to `end`.
pub fn decayed(start: f64, end: f64, progress: f64) -> f64 {
    if start <= 0.0 || end <= 0.0 {
        return start.max(0.0);
    }
    start * (end / start).powf(progress.clamp(0.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adam_finds_the_minimum_of_a_quadratic_and_clips() {
        let mut a = Adam::new(2);
        let mut p = [3.0, -2.0];
        let cfg = AdamConfig {
            clip: 1.0,
            ..Default::default()
        };
        let mut clipped = false;
        for i in 0..2000 {
            let g = [2.0 * (p[0] - 1.0), 20.0 * (p[1] + 0.5)];
            let lr = decayed(0.1, 1e-4, i as f64 / 2000.0);
            clipped |= a.step(&cfg, &mut p, &g, &[lr, lr]).clipped;
        }
        assert!(
            (p[0] - 1.0).abs() < 1e-3 && (p[1] + 0.5).abs() < 1e-3,
            "{p:?}"
        );
        assert!(clipped);
        assert_eq!(a.t, 2000);
    }
}
