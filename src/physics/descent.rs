//! Gradient descent with a backtracking line search, for the handful of parameters of a global
//! material: each iteration takes the gradient `g` (one rollout with its adjoint), steps along
//! `d = −g / max_k |g_k|` (the steepest parameter moves by the step `t`, the others in
//! proportion; the optimiser's coordinates are comparable: log10 of moduli, logits of bounded
//! ratios) and accepts the first trial `u + t·d` whose loss (a forward rollout) satisfies
//! Armijo's condition `L(u + t d) ≤ L(u) + c·t·(g·d)`, halving `t` otherwise; an accepted step
//! doubles `t` for the next iteration, up to `max_step`. The descent has converged when no
//! step above `min_step` lowers the loss.
//!
//! Unlike Adam's fixed schedule, the step follows the loss: from a guess ten times off, the
//! first steps cover the decade in a few iterations, and near the optimum they shrink to what
//! still lowers it.

use serde::{Deserialize, Serialize};

/// Armijo's constant. A step is accepted only if it achieves a quarter of the decrease the
/// slope promises: on a quadratic that accepts at most 1.5× the best step, so accepted steps
/// contract towards the minimum instead of jumping across it back and forth (with the
/// textbook 1e-4, a doubled step nearly twice the best one is accepted and the search can
/// oscillate about the minimum for ever).
const ARMIJO: f64 = 0.25;

/// Trials per iteration before it gives up (the step halves each time).
pub const TRIALS: usize = 4;

/// The line search's state (serialisable, for checkpoints).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LineSearch {
    /// The next trial step (optimiser coordinates).
    pub step: f64,
    /// Smallest step worth trying: below it the descent has converged.
    pub min_step: f64,
    /// Largest step.
    pub max_step: f64,
}

/// What an iteration did.
#[derive(Debug, Clone, PartialEq)]
pub struct Iteration {
    /// The parameters after it.
    pub u: Vec<f64>,
    /// The loss there.
    pub loss: f64,
    /// The step taken (0 when none lowered the loss).
    pub step: f64,
    /// Trials evaluated.
    pub trials: usize,
}

impl LineSearch {
    /// Starts with step `step`, stopping below `min_step`, never above `max_step`.
    pub fn new(step: f64, min_step: f64, max_step: f64) -> Self {
        Self {
            step: step.clamp(min_step, max_step),
            min_step,
            max_step,
        }
    }

    /// Whether no step worth trying is left.
    pub fn converged(&self) -> bool {
        self.step < self.min_step
    }

    /// One iteration from `u` (loss `l0`, gradient `g`), evaluating trial losses with `loss`
    /// (which may fail: the error stops the descent).
    pub fn iterate<E>(
        &mut self,
        u: &[f64],
        l0: f64,
        g: &[f64],
        mut loss: impl FnMut(&[f64]) -> Result<f64, E>,
    ) -> Result<Iteration, E> {
        let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let stay = |trials| Iteration {
            u: u.to_vec(),
            loss: l0,
            step: 0.0,
            trials,
        };
        if scale == 0.0 || !scale.is_finite() {
            self.step = 0.0;
            return Ok(stay(0));
        }
        let d: Vec<f64> = g.iter().map(|v| -v / scale).collect();
        let slope: f64 = g.iter().zip(&d).map(|(g, d)| g * d).sum();
        for trial in 1..=TRIALS {
            let t = self.step;
            let at: Vec<f64> = u.iter().zip(&d).map(|(u, d)| u + t * d).collect();
            let l = loss(&at)?;
            if l.is_finite() && l <= l0 + ARMIJO * t * slope {
                self.step = (2.0 * t).min(self.max_step);
                return Ok(Iteration {
                    u: at,
                    loss: l,
                    step: t,
                    trials: trial,
                });
            }
            self.step = t / 2.0;
            if self.converged() {
                return Ok(stay(trial));
            }
        }
        Ok(stay(TRIALS))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_search_covers_a_decade_in_a_few_iterations_and_converges() {
        // L = (u0 − 1)² + 0.1 (u1 − 0.2)², from (−1, 0): two decades off in u0.
        let f = |u: &[f64]| (u[0] - 1.0).powi(2) + 0.1 * (u[1] - 0.2).powi(2);
        let grad = |u: &[f64]| vec![2.0 * (u[0] - 1.0), 0.2 * (u[1] - 0.2)];
        let mut ls = LineSearch::new(0.5, 1e-4, 1.0);
        let mut u = vec![-1.0, 0.0];
        let mut l = f(&u);
        let mut iterations = 0;
        while !ls.converged() && iterations < 200 {
            let it = ls
                .iterate(&u, l, &grad(&u), |x| Ok::<f64, ()>(f(x)))
                .unwrap();
            assert!(it.loss <= l, "the loss never rises");
            (u, l) = (it.u, it.loss);
            iterations += 1;
        }
        assert!((u[0] - 1.0).abs() < 1e-3, "{u:?} after {iterations}");
        assert!(ls.converged(), "{ls:?}");
        // The first iterations move u0 most of the way.
        let mut ls = LineSearch::new(0.5, 1e-4, 1.0);
        let (mut u, mut l) = (vec![-1.0, 0.0], f(&[-1.0, 0.0]));
        for _ in 0..3 {
            let it = ls
                .iterate(&u, l, &grad(&u), |x| Ok::<f64, ()>(f(x)))
                .unwrap();
            (u, l) = (it.u, it.loss);
        }
        assert!((u[0] - 1.0).abs() < 0.5, "{u:?}");
    }
}
