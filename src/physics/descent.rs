//! Quasi-Newton descent (BFGS) with a backtracking line search, for the handful of parameters
//! of a global material or a rigid velocity: each iteration takes the gradient `g` (one
//! rollout with its adjoint) and steps along `d = −H g`, where `H` approximates the inverse
//! Hessian from the steps and gradient changes seen so far (Nocedal & Wright, *Numerical
//! Optimization*, §6.1: `H ← (I − ρ s yᵀ) H (I − ρ y sᵀ) + ρ s sᵀ`, `ρ = 1/(yᵀs)`, the
//! first `H` scaled by `yᵀs / yᵀy`, eq. 6.20). Parameters of very different sensitivity (a
//! plasticine's yield stress and its Young's modulus) then move by what each needs, where plain
//! gradient descent moves the steepest and leaves the others behind. The full step `t = 1` is
//! tried first (capped so that no coordinate moves more than `max_step`), halved until
//! Armijo's condition `L(u + t d) ≤ L(u) + c·t·(g·d)` holds (a forward rollout per trial).
//!
//! Before any curvature is known (the first iteration, or after a step that does not bend the
//! right way), the step is steepest descent `d = −g / max_k |g_k|` with the remembered step
//! length `step` (the steepest coordinate moves by `step`), doubled after an accepted trial.
//! When no trial along the quasi-Newton direction lowers the loss, or the direction is shorter
//! than `min_step` (a curvature estimate gone stale, as on a plasticine's flat valley in E),
//! the same iteration falls back to steepest descent from the last steepest step length: only
//! steepest descent declares convergence, never the estimate alone.
//! The descent has converged when no move above `min_step` (in any coordinate) lowers the loss.
//! The optimiser's coordinates are comparable: log10 of moduli, logits of bounded ratios.

use serde::{Deserialize, Serialize};

/// Armijo's constant. A step is accepted only if it achieves a quarter of the decrease the
/// slope promises: on a quadratic that accepts at most 1.5× the best step, so accepted steps
/// contract towards the minimum instead of jumping across it back and forth (with the
/// textbook 1e-4, a doubled step nearly twice the best one is accepted and the search can
/// oscillate about the minimum for ever).
const ARMIJO: f64 = 0.25;

/// Trials per iteration before it gives up (the step halves each time).
pub const TRIALS: usize = 4;

/// The search's state (serialisable, for checkpoints).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LineSearch {
    /// The steepest-descent step length (optimiser coordinates); after a quasi-Newton step, the
    /// largest coordinate move it made.
    pub step: f64,
    /// Smallest move worth trying: below it the descent has converged.
    pub min_step: f64,
    /// Largest move of any coordinate in one step.
    pub max_step: f64,
    /// The inverse-Hessian estimate, row-major `n × n` (empty until curvature is known).
    #[serde(default)]
    pub inverse_hessian: Vec<f64>,
    /// The point and gradient of the previous iteration (for the next update).
    #[serde(default)]
    pub previous: Option<(Vec<f64>, Vec<f64>)>,
    /// The steepest-descent step length to fall back to when a quasi-Newton step fails
    /// (`None`: `step`).
    #[serde(default)]
    pub steepest_step: Option<f64>,
}

/// What an iteration did.
#[derive(Debug, Clone, PartialEq)]
pub struct Iteration {
    /// The parameters after it.
    pub u: Vec<f64>,
    /// The loss there.
    pub loss: f64,
    /// The largest coordinate move taken (0 when none lowered the loss).
    pub step: f64,
    /// Trials evaluated.
    pub trials: usize,
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

impl LineSearch {
    /// Starts with step `step`, stopping below `min_step`, never moving a coordinate more than
    /// `max_step`.
    pub fn new(step: f64, min_step: f64, max_step: f64) -> Self {
        Self {
            step: step.clamp(min_step, max_step),
            min_step,
            max_step,
            inverse_hessian: Vec::new(),
            previous: None,
            steepest_step: None,
        }
    }

    /// Whether no step worth trying is left.
    pub fn converged(&self) -> bool {
        self.step < self.min_step
    }

    /// The BFGS update from the previous iteration's point and gradient to `(u, g)`; drops the
    /// estimate when the change does not curve upwards (`yᵀs ≤ 0`).
    fn update(&mut self, u: &[f64], g: &[f64]) {
        let n = u.len();
        let Some((u0, g0)) = self.previous.take() else {
            return;
        };
        if u0.len() != n || g0.len() != n {
            self.inverse_hessian.clear();
            return;
        }
        let s: Vec<f64> = u.iter().zip(&u0).map(|(a, b)| a - b).collect();
        let y: Vec<f64> = g.iter().zip(&g0).map(|(a, b)| a - b).collect();
        let sy = dot(&s, &y);
        let curved = sy > 1e-12 * dot(&s, &s).sqrt() * dot(&y, &y).sqrt();
        if !curved || !sy.is_finite() {
            self.inverse_hessian.clear();
            return;
        }
        if self.inverse_hessian.len() != n * n {
            let scale = sy / dot(&y, &y);
            self.inverse_hessian = (0..n * n)
                .map(|k| if k / n == k % n { scale } else { 0.0 })
                .collect();
        }
        let h = &self.inverse_hessian;
        let rho = 1.0 / sy;
        // H y and yᵀ H y.
        let hy: Vec<f64> = (0..n).map(|i| dot(&h[i * n..(i + 1) * n], &y)).collect();
        let yhy = dot(&y, &hy);
        // H' = H − ρ (H y sᵀ + s yᵀ H) + (ρ² yᵀHy + ρ) s sᵀ   (H symmetric).
        let mut next = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                next[i * n + j] = h[i * n + j] - rho * (hy[i] * s[j] + s[i] * hy[j])
                    + (rho * rho * yhy + rho) * s[i] * s[j];
            }
        }
        self.inverse_hessian = next;
    }

    /// One iteration from `u` (loss `l0`, gradient `g`), evaluating trial losses with
    /// `loss(at, bound)` (which may fail: the error stops the descent). `bound` is the value
    /// above which the trial is rejected whatever it is: an evaluator may stop early and return
    /// any value above it (a partial sum of non-negative frame losses, [`Wants::LossUpTo`]);
    /// the search takes the same steps as with exact losses.
    ///
    /// [`Wants::LossUpTo`]: super::rollout::Wants::LossUpTo
    pub fn iterate<E>(
        &mut self,
        u: &[f64],
        l0: f64,
        g: &[f64],
        mut loss: impl FnMut(&[f64], f64) -> Result<f64, E>,
    ) -> Result<Iteration, E> {
        let n = u.len();
        let stay = |trials| Iteration {
            u: u.to_vec(),
            loss: l0,
            step: 0.0,
            trials,
        };
        let scale = max_abs(g);
        if scale == 0.0 || !scale.is_finite() {
            self.step = 0.0;
            return Ok(stay(0));
        }
        self.update(u, g);
        self.previous = Some((u.to_vec(), g.to_vec()));
        // Quasi-Newton direction when curvature is known and it descends.
        let newton = (self.inverse_hessian.len() == n * n)
            .then(|| {
                let h = &self.inverse_hessian;
                (0..n)
                    .map(|i| -dot(&h[i * n..(i + 1) * n], g))
                    .collect::<Vec<f64>>()
            })
            .filter(|d| dot(d, g) < 0.0 && d.iter().all(|v| v.is_finite()));
        let steepest: Vec<f64> = g.iter().map(|v| -v / scale).collect();
        let mut trials = 0;
        if let Some(d) = newton {
            let t = (self.max_step / max_abs(&d)).min(1.0);
            match Self::search(u, l0, g, &d, t, self.min_step, &mut trials, &mut loss)? {
                Search::Accepted(it) => {
                    self.step = it.step.max(self.min_step);
                    return Ok(it);
                }
                // The model's minimum is closer than `min_step`, or no trial along the model's
                // direction lowered the loss: either way the estimate is not trusted alone
                // (it may be stale); steepest descent decides.
                Search::TooShort(_) | Search::Failed(_) => {
                    self.inverse_hessian.clear();
                    self.step = self.steepest_step.unwrap_or(self.step).max(self.min_step);
                }
            }
        } else {
            self.inverse_hessian.clear();
        }
        let t = self.step;
        match Self::search(
            u,
            l0,
            g,
            &steepest,
            t,
            self.min_step,
            &mut trials,
            &mut loss,
        )? {
            Search::Accepted(it) => {
                self.step = (2.0 * it.step).min(self.max_step);
                self.steepest_step = Some(self.step);
                Ok(it)
            }
            Search::TooShort(moved) | Search::Failed(moved) => {
                // Nothing lowered the loss: go on from a shorter steepest step.
                self.step = moved;
                self.steepest_step = Some(moved);
                Ok(stay(trials))
            }
        }
    }

    /// Backtracking along `d` from `t` (halving, at most [`TRIALS`] losses): the first trial
    /// meeting Armijo's condition, or why none did (the move fell below `min_step`, or every
    /// trial failed; both with the next move to try).
    #[allow(clippy::too_many_arguments)]
    fn search<E>(
        u: &[f64],
        l0: f64,
        g: &[f64],
        d: &[f64],
        mut t: f64,
        min_step: f64,
        trials: &mut usize,
        loss: &mut impl FnMut(&[f64], f64) -> Result<f64, E>,
    ) -> Result<Search, E> {
        let largest = max_abs(d);
        let slope = dot(g, d);
        for _ in 0..TRIALS {
            let moved = t * largest;
            if moved < min_step {
                return Ok(Search::TooShort(moved));
            }
            let at: Vec<f64> = u.iter().zip(d).map(|(u, d)| u + t * d).collect();
            let armijo = l0 + ARMIJO * t * slope;
            let l = loss(&at, armijo)?;
            *trials += 1;
            if l.is_finite() && l <= armijo {
                return Ok(Search::Accepted(Iteration {
                    u: at,
                    loss: l,
                    step: moved,
                    trials: *trials,
                }));
            }
            t /= 2.0;
        }
        Ok(Search::Failed(t * largest))
    }
}

/// Compass probes about a point where the descent found no lower loss: each coordinate in
/// `axes` moved by `−step` and `+step` alone (Kolda, Lewis & Torczon 2003, *Optimization by
/// direct search*, §3). A gradient sees only its neighbourhood; on a plateau (a plasticine's
/// Young's modulus far above its yield stress moves the object as a rigid–plastic body, so the
/// loss no longer depends on it) the descent stops although a decade away the loss is lower.
/// On each axis the step down comes first and the step up only when it did not lower the loss.
/// Returns the lowest probe and its loss, when that loss is below `l0` by more than `rel` of
/// it, and the count of losses evaluated. `loss(at, bound)` as [`LineSearch::iterate`]'s:
/// a probe above `(1 − rel) l0` is rejected whatever its value.
pub fn probe<E>(
    u: &[f64],
    l0: f64,
    axes: &[usize],
    step: f64,
    rel: f64,
    mut loss: impl FnMut(&[f64], f64) -> Result<f64, E>,
) -> Result<Probe, E> {
    let mut best: Option<(Vec<f64>, f64)> = None;
    let mut evaluated = 0;
    let enough = l0 * (1.0 - rel);
    for &k in axes.iter().filter(|&&k| k < u.len()) {
        for sign in [-1.0, 1.0] {
            let mut at = u.to_vec();
            at[k] += sign * step;
            // Above `enough` a probe neither wins nor ends the axis.
            let l = loss(&at, enough)?;
            evaluated += 1;
            let lowest = best.as_ref().map_or(enough, |(_, b)| *b);
            if l.is_finite() && l < lowest {
                best = Some((at, l));
            }
            if l.is_finite() && l < enough {
                // The step down lowered the loss: the step up (a stiffer, costlier rollout
                // for a modulus) is not tried on this axis.
                break;
            }
        }
    }
    Ok(Probe { best, evaluated })
}

/// What [`probe`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct Probe {
    /// The lowest probe and its loss, when it lowers the loss enough.
    pub best: Option<(Vec<f64>, f64)>,
    /// Losses evaluated.
    pub evaluated: usize,
}

/// How a backtracking search ended.
enum Search {
    Accepted(Iteration),
    TooShort(f64),
    Failed(f64),
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
                .iterate(&u, l, &grad(&u), |x, _| Ok::<f64, ()>(f(x)))
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
                .iterate(&u, l, &grad(&u), |x, _| Ok::<f64, ()>(f(x)))
                .unwrap();
            (u, l) = (it.u, it.loss);
        }
        assert!((u[0] - 1.0).abs() < 0.5, "{u:?}");
    }

    fn descend(
        f: &dyn Fn(&[f64]) -> f64,
        grad: &dyn Fn(&[f64]) -> Vec<f64>,
        u: Vec<f64>,
        iterations: usize,
    ) -> (Vec<f64>, usize, LineSearch) {
        let mut ls = LineSearch::new(0.5, 1e-6, 1.0);
        let (mut u, mut l) = (u.clone(), f(&u));
        let mut evaluations = 0;
        for _ in 0..iterations {
            if ls.converged() {
                break;
            }
            let it = ls
                .iterate(&u, l, &grad(&u), |x, _| {
                    evaluations += 1;
                    Ok::<f64, ()>(f(x))
                })
                .unwrap();
            assert!(it.loss <= l && it.loss.is_finite(), "the loss never rises");
            (u, l) = (it.u, it.loss);
        }
        (u, evaluations, ls)
    }

    #[test]
    fn parameters_of_very_different_sensitivity_converge_together() {
        // An ill-conditioned quadratic (curvatures 1000 : 1, coupled), like a yield stress and
        // a Young's modulus: steepest descent crawls along the flat direction, BFGS does not.
        let f = |u: &[f64]| {
            let (a, b) = (u[0] - 0.3, u[1] + 1.0);
            1000.0 * (a + 0.5 * b).powi(2) + b * b
        };
        let grad = |u: &[f64]| {
            let (a, b) = (u[0] - 0.3, u[1] + 1.0);
            let c = 2000.0 * (a + 0.5 * b);
            vec![c, 0.5 * c + 2.0 * b]
        };
        let (u, evaluations, ls) = descend(&f, &grad, vec![1.3, 0.0], 12);
        assert!(
            (u[0] - 0.3).abs() < 1e-3 && (u[1] + 1.0).abs() < 1e-3,
            "{u:?} after {evaluations} trial losses ({ls:?})"
        );
    }

    #[test]
    fn a_curved_valley_is_followed() {
        // Rosenbrock's function from (−1.2, 1): minimum at (1, 1).
        let f = |u: &[f64]| (1.0 - u[0]).powi(2) + 100.0 * (u[1] - u[0] * u[0]).powi(2);
        let grad = |u: &[f64]| {
            vec![
                -2.0 * (1.0 - u[0]) - 400.0 * u[0] * (u[1] - u[0] * u[0]),
                200.0 * (u[1] - u[0] * u[0]),
            ]
        };
        let (u, _, _) = descend(&f, &grad, vec![-1.2, 1.0], 200);
        assert!(
            (u[0] - 1.0).abs() < 1e-3 && (u[1] - 1.0).abs() < 1e-3,
            "{u:?}"
        );
    }

    #[test]
    fn a_stale_curvature_estimate_falls_back_to_steepest_descent() {
        // L = 100 u0² + u1² from (1, 0): an estimate H = I promises a step of 200 in u0, capped
        // at 20; the four halvings (20, 10, 5, 2.5) all overshoot. The same iteration then
        // takes the steepest step (0.5 in u0) and lowers the loss instead of giving up.
        let f = |u: &[f64]| 100.0 * u[0] * u[0] + u[1] * u[1];
        let g = vec![200.0, 0.0];
        let mut ls = LineSearch::new(0.5, 1e-4, 20.0);
        ls.inverse_hessian = vec![1.0, 0.0, 0.0, 1.0];
        let u = vec![1.0, 0.0];
        let it = ls
            .iterate(&u, f(&u), &g, |x, _| Ok::<f64, ()>(f(x)))
            .unwrap();
        assert!(it.loss < f(&u) / 2.0, "{it:?}");
        assert_eq!(it.trials, TRIALS + 1, "{it:?}");
        assert!(
            ls.inverse_hessian.is_empty(),
            "the stale estimate is dropped"
        );
        assert!(!ls.converged(), "{ls:?}");
    }

    #[test]
    fn a_probe_leaves_a_plateau_a_gradient_cannot() {
        // Flat for u0 > 1 (zero gradient), a valley at u0 = −0.2: from u0 = 2 a probe one unit
        // down sees nothing, from 1.5 it reaches the slope.
        let f = |u: &[f64]| (u[0].min(1.0) + 0.2).powi(2) + (u[1] - 0.5).powi(2);
        let Probe {
            best: none,
            evaluated: n,
        } = probe(&[2.5, 0.5], f(&[2.5, 0.5]), &[0, 1], 1.0, 1e-3, |x, _| {
            Ok::<f64, ()>(f(x))
        })
        .unwrap();
        assert!(none.is_none(), "{none:?}");
        assert_eq!(n, 4);
        let Probe {
            best: some,
            evaluated: n,
        } = probe(&[1.5, 0.5], f(&[1.5, 0.5]), &[0], 1.0, 1e-3, |x, _| {
            Ok::<f64, ()>(f(x))
        })
        .unwrap();
        let (at, l) = some.expect("the step down lowers the loss");
        assert_eq!(at, vec![0.5, 0.5]);
        assert_eq!(
            n, 1,
            "the step up is not tried once the step down lowered the loss"
        );
        assert!(l < f(&[1.5, 0.5]));
        // NaN losses and axes out of range are skipped, never chosen.
        let Probe {
            best: nan,
            evaluated: n,
        } = probe(&[0.0], 1.0, &[0, 3], 1.0, 0.0, |_, _| {
            Ok::<f64, ()>(f64::NAN)
        })
        .unwrap();
        assert!(nan.is_none());
        assert_eq!(n, 2);
    }

    #[test]
    fn a_trial_cut_short_above_its_bound_changes_no_step() {
        // An evaluator that stops as soon as the loss is known to exceed the bound (it returns
        // a value just above it, as a partial sum of frame losses would) against the exact
        // one: the same points, losses and trial counts, iteration after iteration, probes
        // included.
        let f = |u: &[f64]| (u[0].min(1.5) - 0.3).powi(2) + 3.0 * (u[1] + 0.2).powi(2);
        let grad = |u: &[f64]| {
            let a = if u[0] < 1.5 { 2.0 * (u[0] - 0.3) } else { 0.0 };
            vec![a, 6.0 * (u[1] + 0.2)]
        };
        let cut = |x: &[f64], bound: f64| {
            let l = f(x);
            Ok::<f64, ()>(if l > bound { bound.next_up() } else { l })
        };
        let (mut exact, mut short) = (
            LineSearch::new(0.5, 1e-4, 1.0),
            LineSearch::new(0.5, 1e-4, 1.0),
        );
        let (mut u, mut l) = (vec![2.2, 1.0], f(&[2.2, 1.0]));
        let mut probed = 0;
        for _ in 0..25 {
            let a = exact
                .iterate(&u, l, &grad(&u), |x, _| Ok::<f64, ()>(f(x)))
                .unwrap();
            let b = short.iterate(&u, l, &grad(&u), cut).unwrap();
            assert_eq!(a, b);
            assert_eq!(exact, short);
            (u, l) = (a.u, a.loss);
            if a.step == 0.0 {
                let pa = probe(&u, l, &[0, 1], 1.0, 1e-3, |x, _| Ok::<f64, ()>(f(x))).unwrap();
                let pb = probe(&u, l, &[0, 1], 1.0, 1e-3, cut).unwrap();
                assert_eq!(pa, pb);
                if let Some((at, lp)) = pa.best {
                    (u, l) = (at, lp);
                    probed += 1;
                    exact = LineSearch::new(0.5, 1e-4, 1.0);
                    short = exact.clone();
                }
            }
        }
        assert_eq!(probed, 1, "the plateau is left by one probe");
        assert!(
            (u[0] - 0.3).abs() < 1e-3 && (u[1] + 0.2).abs() < 1e-3,
            "{u:?}"
        );
    }

    #[test]
    fn the_state_survives_a_checkpoint() {
        let mut ls = LineSearch::new(0.5, 1e-4, 1.0);
        let f = |u: &[f64]| u[0] * u[0] + 3.0 * u[1] * u[1];
        let grad = |u: &[f64]| vec![2.0 * u[0], 6.0 * u[1]];
        let mut u = vec![1.0, 1.0];
        for _ in 0..2 {
            u = ls
                .iterate(&u, f(&u), &grad(&u), |x, _| Ok::<f64, ()>(f(x)))
                .unwrap()
                .u;
        }
        let json = serde_json::to_string(&ls).unwrap();
        let back: LineSearch = serde_json::from_str(&json).unwrap();
        assert_eq!(back, ls);
        assert!(
            !ls.inverse_hessian.is_empty(),
            "curvature known after two steps"
        );
    }
}
