//! Checkpointed backpropagation over many substeps.
//!
//! The forward pass keeps the state every `every` substeps (a frame boundary); the backward pass
//! reverses one segment at a time, recomputing states from the segment start with at most
//! [`BackwardOptions::snapshots`] (default [`SEGMENT_SNAPSHOTS`]) of them alive (a binomial
//! schedule, [`super::schedule`]), so memory is O((n/every + snapshots) · particles) whatever
//! the segment length. Short segments (≤ snapshots + 1 substeps) also keep each recomputed
//! substep's intermediates (τ, bins, grid), so their adjoint steps skip the forward
//! recomputation.

use std::borrow::Cow;

use glam::{DMat3, DVec3};

use super::AdjointWork;
use super::schedule::{SEGMENT_SNAPSHOTS, Schedule};
use crate::error::MpmError;
use crate::models::Constitutive;
use crate::order::Order;
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
    /// `checkpoints[j]` = state at substep `j·every`, in the run's slot order.
    pub(crate) checkpoints: Vec<State>,
    /// State after the last substep, in the run's slot order.
    pub(crate) final_state: State,
    /// The run's spatial order of the particles (`None`: the caller's own).
    pub(crate) order: Option<Order>,
    /// Forward statistics.
    pub report: RunReport,
}

impl Tape {
    /// Number of checkpoints kept (`⌈n_substeps / every⌉`).
    pub fn checkpoint_count(&self) -> usize {
        self.checkpoints.len()
    }

    /// Checkpoint `j` (the state at substep `j·every`) in the caller's particle order.
    pub fn checkpoint(&self, j: usize) -> Option<State> {
        let s = self.checkpoints.get(j)?;
        Some(
            self.order
                .as_ref()
                .map_or_else(|| s.clone(), |o| o.unsort_state(s)),
        )
    }
}

/// The state at a seed's substep (see [`Simulator::backward`]).
#[derive(Debug, Clone, Copy)]
pub struct SeedState<'a> {
    slots: &'a State,
    order: Option<&'a Order>,
}

impl SeedState<'_> {
    /// The state, in the caller's particle order (built on demand when the run reordered
    /// the particles).
    pub fn get(&self) -> Cow<'_, State> {
        match self.order {
            None => Cow::Borrowed(self.slots),
            Some(o) => Cow::Owned(o.unsort_state(self.slots)),
        }
    }
}

/// The running gradient `∂L/∂state_k` at a seed's substep, into which the seed of
/// [`Simulator::backward_into`] adds its loss terms, indexed in the caller's particle order
/// (translated to the run's order when it reordered the particles). Adding in place needs no
/// gradient state of the caller's: a loss on positions alone adds `∂L/∂x` particle by
/// particle.
#[derive(Debug)]
pub struct SeedGrad<'a> {
    g: &'a mut StateGrad,
    order: Option<&'a Order>,
}

impl SeedGrad<'_> {
    /// Number of particles.
    pub fn len(&self) -> usize {
        self.g.len()
    }

    /// `true` when there are no particles.
    pub fn is_empty(&self) -> bool {
        self.g.is_empty()
    }

    /// The run's slot of the caller's particle `p` (panics if `p ≥ len`, as indexing does).
    fn slot(&self, p: usize) -> usize {
        assert!(p < self.len(), "particle {p} of {}", self.len());
        self.order.map_or(p, |o| o.slot(p))
    }

    /// Adds `g` (per m) to `∂L/∂x` of particle `p`.
    pub fn add_x(&mut self, p: usize, g: DVec3) {
        let i = self.slot(p);
        self.g.x[i] += g;
    }

    /// Adds `g` (s/m) to `∂L/∂v` of particle `p`.
    pub fn add_v(&mut self, p: usize, g: DVec3) {
        let i = self.slot(p);
        self.g.v[i] += g;
    }

    /// Adds `g` (s) to `∂L/∂C` of particle `p`.
    pub fn add_c(&mut self, p: usize, g: DMat3) {
        let i = self.slot(p);
        self.g.c[i] += g;
    }

    /// Adds `g` to `∂L/∂F` of particle `p`.
    pub fn add_f(&mut self, p: usize, g: DMat3) {
        let i = self.slot(p);
        self.g.f[i] += g;
    }

    /// Adds a whole gradient in the caller's order; [`MpmError::GradientMismatch`] unless each
    /// of its arrays holds one entry per particle.
    pub fn add(&mut self, g: &StateGrad) -> Result<(), MpmError> {
        if !g.has_len(self.len()) {
            return Err(MpmError::GradientMismatch(
                "seed gradient length differs from the particle count",
            ));
        }
        match self.order {
            None => self.g.add_assign(g),
            Some(o) => o.add_sorted_grad(g, self.g),
        }
        Ok(())
    }
}

/// Options of [`Simulator::backward`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BackwardOptions {
    /// Backpropagate through only the last `n` substeps (e.g. one frame); `None` = all.
    pub truncate: Option<usize>,
    /// Recomputed states kept alive while a segment is reversed (≥ 1; default
    /// [`SEGMENT_SNAPSHOTS`]): the memory/time trade of the backward pass. A segment of `k`
    /// substeps costs about `k·r` recomputed substeps with `C(c + r, c) ≥ k` for `c` snapshots;
    /// `c ≥ k − 1` recomputes each substep once, keeping its intermediates.
    pub snapshots: usize,
}

impl Default for BackwardOptions {
    fn default() -> Self {
        Self {
            truncate: None,
            snapshots: SEGMENT_SNAPSHOTS,
        }
    }
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
        let (report, order) = self.advance(state, mat, t0, n_substeps, |k, s| {
            if k.is_multiple_of(every) {
                checkpoints.push(s.clone());
            }
        })?;
        let final_state = order
            .as_ref()
            .map_or_else(|| state.clone(), |o| o.sort_state(state));
        Ok(Tape {
            t0,
            n_substeps,
            every,
            checkpoints,
            final_state,
            order,
            report,
        })
    }

    /// Backpropagates through a tape. `seed(k, state_k)` returns `∂L/∂state_k` of the loss
    /// terms at substep `k` (called for `k = n_substeps` down to the start; `None` = no term);
    /// [`SeedState::get`] builds the state only for the seeds that read it.
    /// A non-finite gradient stops the pass with [`MpmError::NonFinite`] naming the substep.
    ///
    /// Each segment is reversed with at most [`BackwardOptions::snapshots`] recomputed states
    /// alive besides the tape (binomial schedule, see `adjoint::schedule`).
    /// [`Self::backward_into`] takes the seeds in place, without a gradient state per seed.
    pub fn backward(
        &self,
        tape: &Tape,
        mat: &Material,
        mut seed: impl FnMut(usize, SeedState<'_>) -> Option<StateGrad> + Send,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        self.backward_into(
            tape,
            mat,
            |k, s, g| seed(k, s).map_or(Ok(()), |extra| g.add(&extra)),
            opts,
        )
    }

    /// [`Self::backward`] with seeds that add their terms into the running gradient:
    /// `seed(k, state_k, g)` adds `∂L/∂state_k` into `g` ([`SeedGrad`], caller's particle
    /// order); an error it returns stops the pass.
    pub fn backward_into(
        &self,
        tape: &Tape,
        mat: &Material,
        seed: impl FnMut(usize, SeedState<'_>, &mut SeedGrad<'_>) -> Result<(), MpmError> + Send,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        crate::sim::on_worker(|| self.backward_on_worker(tape, mat, seed, opts))
    }

    /// [`Self::backward_into`] on the calling thread.
    fn backward_on_worker(
        &self,
        tape: &Tape,
        mat: &Material,
        mut seed: impl FnMut(usize, SeedState<'_>, &mut SeedGrad<'_>) -> Result<(), MpmError>,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        if opts.snapshots == 0 {
            return Err(MpmError::InvalidParameter {
                field: "snapshots",
                value: 0.0,
                reason: "must be >= 1",
            });
        }
        let order = tape.order.as_ref();
        // The tape is in slot order: the reverser runs there, and each seed sees the state
        // and adds its gradient through the permutation (caller's order).
        let in_slots = |k: usize, s: &State, g: &mut StateGrad| {
            let view = SeedState { slots: s, order };
            seed(k, view, &mut SeedGrad { g, order })
        };
        let Some(o) = order else {
            return self.backward_in_order(tape, mat, in_slots, opts);
        };
        let grads = self
            .sorted(o)
            .backward_in_order(tape, &o.sort_material(mat), in_slots, opts);
        match grads {
            Ok(g) => Ok(Gradients {
                state: o.unsort_grad(&g.state),
                start: g.start,
                material: o.unsort_material_grad(&g.material),
            }),
            Err(MpmError::NonFinite {
                substep,
                quantity,
                particle,
            }) => Err(MpmError::NonFinite {
                substep,
                quantity,
                particle: o.original(particle),
            }),
            Err(e) => Err(e),
        }
    }

    /// [`Self::backward`] with the tape's states and `mat` in one order; `seed(k, state_k, g)`
    /// adds the loss gradient at substep `k` into `g` (in that order).
    fn backward_in_order(
        &self,
        tape: &Tape,
        mat: &Material,
        seed: impl FnMut(usize, &State, &mut StateGrad) -> Result<(), MpmError>,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        let n = tape.n_substeps;
        let np = tape.final_state.len();
        let mut seed = seed;
        let mut g = StateGrad::zeros(np);
        seed(n, &tape.final_state, &mut g)?;
        let start = n - opts.truncate.unwrap_or(n).min(n);
        let mut rev = Reverser {
            sim: self,
            mat,
            t0: tape.t0,
            start,
            seed,
            g,
            gmat: MaterialGrad::zeros(np),
            aw: AdjointWork::default(),
            stack: Vec::with_capacity(opts.snapshots + 1),
            snapshots: opts.snapshots,
            spare: Vec::new(),
            spare_work: Vec::new(),
            keep: false,
            plan: Schedule::new(tape.every.min(n.max(1)), opts.snapshots),
        };
        for (j, ck) in tape.checkpoints.iter().enumerate().rev() {
            let lo = j * tape.every;
            let hi = (lo + tape.every).min(n);
            if hi <= start {
                break;
            }
            rev.segment(ck, lo, hi)?;
        }
        Ok(Gradients {
            state: rev.g,
            start,
            material: rev.gmat,
        })
    }
}

/// State of one backward pass: the running gradients and the recomputed states.
struct Reverser<'a, M: Constitutive, S> {
    sim: &'a Simulator<M>,
    mat: &'a Material,
    t0: f64,
    start: usize,
    seed: S,
    g: StateGrad,
    gmat: MaterialGrad,
    aw: AdjointWork,
    /// Recomputed states, innermost last.
    stack: Vec<State>,
    /// Released state buffers, reused instead of allocating.
    spare: Vec<State>,
    /// Released intermediates buffers, likewise.
    spare_work: Vec<Work>,
    /// Snapshots alive at once ([`BackwardOptions::snapshots`]).
    snapshots: usize,
    /// Keep each recomputed substep's intermediates (segments of ≤ snapshots + 1).
    keep: bool,
    plan: Schedule,
}

impl<M: Constitutive, S: FnMut(usize, &State, &mut StateGrad) -> Result<(), MpmError>>
    Reverser<'_, M, S>
{
    /// Reverses substeps `lo..hi` (only those `≥ start`) from the checkpoint at `lo`.
    fn segment(&mut self, ck: &State, lo: usize, hi: usize) -> Result<(), MpmError> {
        debug_assert!(self.stack.is_empty());
        let a = lo.max(self.start);
        let free = if lo < a {
            self.snapshots.max(2) - 1
        } else {
            self.snapshots
        };
        self.keep = hi - a <= free + 1;
        if lo < a {
            // Truncated: first recompute the state at `start` (one extra snapshot).
            self.push(ck, lo, a, false);
            let r = self.reverse(ck, a, hi, free);
            self.pop();
            return r;
        }
        self.reverse(ck, a, hi, free)
    }

    /// The state at the innermost snapshot, or the checkpoint when none is alive.
    fn base<'s>(&'s self, ck: &'s State) -> &'s State {
        self.stack.last().unwrap_or(ck)
    }

    /// Recomputes the state at `to` from the base (at `from`) into a new snapshot. With `keep`,
    /// returns the intermediates of the last substep (those of substep `from` when
    /// `to = from + 1`, which its adjoint step then need not recompute).
    fn push(&mut self, ck: &State, from: usize, to: usize, keep: bool) -> Option<Work> {
        let mut buf = self.spare.pop().unwrap_or_else(|| self.base(ck).clone());
        let mut w = if keep {
            self.spare_work.pop().unwrap_or_default()
        } else {
            std::mem::take(&mut self.aw.fwd)
        };
        let dt = self.sim.config.dt;
        // The first substep reads the base and writes the new buffer (no copy), the rest run
        // in place.
        let base = self.stack.last().unwrap_or(ck);
        self.sim.forward_from(
            Some(base),
            &mut buf,
            self.mat,
            self.t0 + from as f64 * dt,
            &mut w,
        );
        for k in from + 1..to {
            self.sim
                .forward(&mut buf, self.mat, self.t0 + k as f64 * dt, &mut w);
        }
        self.stack.push(buf);
        if keep {
            Some(w)
        } else {
            self.aw.fwd = w;
            None
        }
    }

    fn pop(&mut self) {
        if let Some(s) = self.stack.pop() {
            self.spare.push(s);
        }
    }

    /// Reverses substeps `a..b` whose start state is the base, with `free ≥ 1` snapshots left:
    /// recompute the state at the planned split `m`, reverse `m..b` with one snapshot fewer,
    /// release it, then continue with `a..m` (a loop, so recursion depth ≤ `free`).
    ///
    /// When the whole segment fits in the snapshots (at most snapshots + 1 substeps,
    /// every split is one substep) the intermediates of each recomputed substep are kept too,
    /// so only the segment's last substep is recomputed for its adjoint.
    fn reverse(&mut self, ck: &State, a: usize, b: usize, free: usize) -> Result<(), MpmError> {
        let keep = self.keep;
        let mut b = b;
        let mut kept = None;
        while b - a > 1 {
            let m = a + self.plan.split(b - a, free);
            kept = self.push(ck, a, m, keep && m == a + 1);
            let r = self.reverse(ck, m, b, free - 1);
            self.pop();
            r?;
            b = m;
        }
        let r = self.step(ck, a, kept.as_ref());
        self.spare_work.extend(kept);
        r
    }

    /// Backpropagates substep `k` from its start state (the base), given its intermediates
    /// when kept, then adds the seed at `k`.
    fn step(&mut self, ck: &State, k: usize, kept: Option<&Work>) -> Result<(), MpmError> {
        let s = self.stack.last().unwrap_or(ck);
        let t = self.t0 + k as f64 * self.sim.config.dt;
        let bad = self.sim.substep_backward_with(
            s,
            self.mat,
            t,
            &mut self.g,
            &mut self.gmat,
            &mut self.aw,
            kept,
        );
        if let Some((quantity, particle)) = bad.then(|| self.g.first_non_finite()).flatten() {
            return Err(MpmError::NonFinite {
                substep: k,
                quantity,
                particle,
            });
        }
        (self.seed)(k, s, &mut self.g)?;
        Ok(())
    }
}
