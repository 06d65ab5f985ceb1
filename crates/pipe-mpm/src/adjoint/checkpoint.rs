//! Checkpointed backpropagation over many substeps.
//!
//! The forward pass keeps the state every `every` substeps (a frame boundary); the backward pass
//! recomputes one segment at a time in two levels (sub-checkpoints every ⌈√every⌉ substeps,
//! then the states of one sub-segment), so memory is O((n/every + 2√every) · particles), never
//! O(substeps · particles), for about one extra forward pass.

use super::AdjointWork;
use crate::error::MpmError;
use crate::models::Constitutive;
use crate::sim::{RunReport, Simulator, Work};
use crate::state::{Material, MaterialGrad, State, StateGrad};

/// States at segment boundaries of a forward run.
#[derive(Debug, Clone)]
pub struct Tape {
    /// Start time (s).
    pub t0: f64,
    /// Substeps run.
    pub n_substeps: usize,
    /// Substeps per segment (checkpoint interval).
    pub every: usize,
    /// `checkpoints[j]` = state at substep `j·every`.
    pub checkpoints: Vec<State>,
    /// State after the last substep.
    pub final_state: State,
    /// Forward statistics.
    pub report: RunReport,
}

/// Options of [`Simulator::backward`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BackwardOptions {
    /// Backpropagate through only the last `n` substeps (e.g. one frame); `None` = all.
    pub truncate: Option<usize>,
}

/// Result of [`Simulator::backward`].
#[derive(Debug, Clone)]
pub struct Gradients {
    /// `∂L/∂(state at substep start)`.
    pub state: StateGrad,
    /// Substep the state gradient refers to (0 unless truncated).
    pub start: usize,
    /// Material and family gradients.
    pub material: MaterialGrad,
}

impl<M: Constitutive> Simulator<M> {
    /// Runs `n_substeps` from `state` (advanced in place) keeping a checkpoint every `every`.
    pub fn forward_tape(
        &self,
        state: &mut State,
        mat: &Material,
        t0: f64,
        n_substeps: usize,
        every: usize,
    ) -> Result<Tape, MpmError> {
        if every == 0 {
            return Err(MpmError::InvalidParameter {
                field: "every",
                value: 0.0,
                reason: "must be >= 1",
            });
        }
        let mut checkpoints = Vec::with_capacity(n_substeps.div_ceil(every));
        let report = self.advance(state, mat, t0, n_substeps, |k, s| {
            if k.is_multiple_of(every) {
                checkpoints.push(s.clone());
            }
        })?;
        Ok(Tape {
            t0,
            n_substeps,
            every,
            checkpoints,
            final_state: state.clone(),
            report,
        })
    }

    /// Backpropagates through a tape. `seed(k, state_k)` returns `∂L/∂state_k` of the loss
    /// terms at substep `k` (called for `k = n_substeps` down to the start; `None` = no term).
    /// A non-finite gradient stops the pass with [`MpmError::NonFinite`] naming the substep.
    pub fn backward(
        &self,
        tape: &Tape,
        mat: &Material,
        mut seed: impl FnMut(usize, &State) -> Option<StateGrad>,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        let n = tape.n_substeps;
        let np = tape.final_state.len();
        let mut g = seed(n, &tape.final_state).unwrap_or_else(|| StateGrad::zeros(np));
        if g.len() != np {
            return Err(MpmError::GradientMismatch(
                "seed gradient length differs from the particle count",
            ));
        }
        let start = n - opts.truncate.unwrap_or(n).min(n);
        let mut gmat = MaterialGrad::zeros(np);
        let dt = self.config.dt;
        let mut aw = AdjointWork::default();
        let mut w = Work::default();
        for (j, ck) in tape.checkpoints.iter().enumerate().rev() {
            let lo = j * tape.every;
            let hi = (lo + tape.every).min(n);
            if hi <= start {
                break;
            }
            // Two-level recomputation: first the sub-checkpoints of this segment every
            // `sub` substeps, then the states of one sub-segment at a time, so at most
            // about 2·√every states are alive besides the tape (not `every` of them).
            let sub = ((hi - lo) as f64).sqrt().ceil().max(1.0) as usize;
            let mut subs = Vec::with_capacity((hi - lo).div_ceil(sub));
            let last_sub = lo + (hi - 1 - lo) / sub * sub;
            let mut cur = ck.clone();
            let mut next = ck.clone();
            for k in lo..=last_sub {
                if (k - lo).is_multiple_of(sub) {
                    subs.push(cur.clone());
                }
                if k < last_sub {
                    self.forward(&cur, mat, tape.t0 + k as f64 * dt, &mut next, &mut w);
                    std::mem::swap(&mut cur, &mut next);
                }
            }
            drop((cur, next));
            for (i, sc) in subs.iter().enumerate().rev() {
                let a = lo + i * sub;
                let b = (a + sub).min(hi);
                if b <= start {
                    break;
                }
                let mut states = Vec::with_capacity(b - a);
                states.push(sc.clone());
                for k in a..b - 1 {
                    let mut next = sc.clone();
                    self.forward(
                        &states[k - a],
                        mat,
                        tape.t0 + k as f64 * dt,
                        &mut next,
                        &mut w,
                    );
                    states.push(next);
                }
                for k in (a.max(start)..b).rev() {
                    let s = &states[k - a];
                    g = self.substep_backward_with(
                        s,
                        mat,
                        tape.t0 + k as f64 * dt,
                        &g,
                        &mut gmat,
                        &mut aw,
                    );
                    if let Some((quantity, particle)) = g.first_non_finite() {
                        return Err(MpmError::NonFinite {
                            substep: k,
                            quantity,
                            particle,
                        });
                    }
                    if let Some(extra) = seed(k, s) {
                        if extra.len() != np {
                            return Err(MpmError::GradientMismatch(
                                "seed gradient length differs from the particle count",
                            ));
                        }
                        g.add_assign(&extra);
                    }
                }
            }
        }
        Ok(Gradients {
            state: g,
            start,
            material: gmat,
        })
    }
}
