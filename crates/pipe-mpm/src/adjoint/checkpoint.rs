//! Checkpointed backpropagation over many substeps.
//!
//! The forward pass keeps the state every `every` substeps (a frame boundary); the backward pass
//! reverses one segment at a time, recomputing states from the segment start with at most
//! [`BackwardOptions::snapshots`] (default [`SEGMENT_SNAPSHOTS`]) of them alive (a binomial
//! schedule, [`super::schedule`]), so memory is O((n/every + snapshots) · particles) whatever
//! the segment length. Short segments (≤ snapshots + 1 substeps) also keep each recomputed
//! substep's intermediates (τ, groups, grid), so their adjoint steps skip the forward
//! recomputation. The forward pass keeps what the last segment's reversal would recompute
//! first (its first snapshots and, when short, its intermediates): the first backward pass
//! through the tape takes them instead of recomputing. Both run on the vectorised engine (`crate::wide::tape`), in the simulator's
//! [`crate::Precision`].

use std::borrow::Cow;
use std::sync::{Arc, Weak};

use glam::{DMat3, DVec3};

use super::schedule::SEGMENT_SNAPSHOTS;
use crate::error::MpmError;
use crate::models::Constitutive;
use crate::sim::{BufferCache, Precision, RunReport, Simulator};
use crate::state::{Material, MaterialGrad, State, StateGrad};
use crate::wide::tape::{WideTape, backward, forward_tape};

/// The checkpoints of a tape, in its precision.
#[derive(Debug, Clone)]
pub(crate) enum TapeData {
    F64(WideTape<f64>),
    F32(WideTape<f32>),
}

/// States at segment boundaries of a forward run.
#[derive(Debug, Clone)]
pub struct Tape {
    /// Start time (s).
    pub t0: f64,
    /// Substeps run.
    pub n_substeps: usize,
    /// Substeps per segment (checkpoint interval).
    pub every: usize,
    /// The checkpoints (`j` = state at substep `j·every`, in the run's slot order) and the
    /// state after the last substep.
    pub(crate) data: TapeData,
    /// Forward statistics.
    pub report: RunReport,
    /// The simulator's pool, which takes the checkpoint buffers back when the tape is dropped.
    pub(crate) pool: Weak<BufferCache>,
}

impl Drop for Tape {
    /// Returns the checkpoint buffers to the simulator that made the tape (if it still
    /// exists), so its next tape reuses them instead of faulting in fresh memory.
    fn drop(&mut self) {
        let Some(pool) = self.pool.upgrade() else {
            return;
        };
        per_precision!(TapeData, &mut self.data, t => pool.put(t.take_buffers()));
    }
}

impl Tape {
    /// Number of checkpoints kept (`⌈n_substeps / every⌉`).
    pub fn checkpoint_count(&self) -> usize {
        per_precision!(TapeData, &self.data, t => t.checkpoints.len())
    }

    /// Checkpoint `j` (the state at substep `j·every`) in the caller's particle order.
    pub fn checkpoint(&self, j: usize) -> Option<State> {
        per_precision!(TapeData, &self.data, t => {
            t.checkpoints.get(j).map(|c| c.state(t.origin))
        })
    }

    /// Particles on the tape.
    fn len(&self) -> usize {
        per_precision!(TapeData, &self.data, t => t.last.p.n)
    }
}

/// A state a seed can read, built on demand.
pub(crate) trait SeedSource {
    /// The state, in the caller's particle order.
    fn state(&self) -> State;
}

/// A running gradient a seed adds into, indexed in the caller's particle order.
pub(crate) trait GradSink {
    fn len(&self) -> usize;
    fn add_x(&mut self, p: usize, g: DVec3);
    fn add_v(&mut self, p: usize, g: DVec3);
    fn add_c(&mut self, p: usize, g: DMat3);
    fn add_f(&mut self, p: usize, g: DMat3);
}

/// The state at a seed's substep (see [`Simulator::backward`]).
#[derive(Clone, Copy)]
pub struct SeedState<'a> {
    src: &'a dyn SeedSource,
}

impl std::fmt::Debug for SeedState<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SeedState")
    }
}

impl SeedState<'_> {
    /// The state, in the caller's particle order (built on demand from the run's own order
    /// and precision).
    pub fn get(&self) -> Cow<'_, State> {
        Cow::Owned(self.src.state())
    }
}

/// The running gradient `∂L/∂state_k` at a seed's substep, into which the seed of
/// [`Simulator::backward_into`] adds its loss terms, indexed in the caller's particle order
/// (translated to the run's order). Adding in place needs no gradient state of the caller's:
/// a loss on positions alone adds `∂L/∂x` particle by particle.
pub struct SeedGrad<'a> {
    sink: &'a mut dyn GradSink,
}

impl std::fmt::Debug for SeedGrad<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SeedGrad")
    }
}

impl SeedGrad<'_> {
    /// Number of particles.
    pub fn len(&self) -> usize {
        self.sink.len()
    }

    /// `true` when there are no particles.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adds `g` (per m) to `∂L/∂x` of particle `p` (panics if `p ≥ len`, as indexing does).
    pub fn add_x(&mut self, p: usize, g: DVec3) {
        self.sink.add_x(p, g);
    }

    /// Adds `g` (s/m) to `∂L/∂v` of particle `p`.
    pub fn add_v(&mut self, p: usize, g: DVec3) {
        self.sink.add_v(p, g);
    }

    /// Adds `g` (s) to `∂L/∂C` of particle `p`.
    pub fn add_c(&mut self, p: usize, g: DMat3) {
        self.sink.add_c(p, g);
    }

    /// Adds `g` to `∂L/∂F` of particle `p`.
    pub fn add_f(&mut self, p: usize, g: DMat3) {
        self.sink.add_f(p, g);
    }

    /// Adds a whole gradient in the caller's order; [`MpmError::GradientMismatch`] unless each
    /// of its arrays holds one entry per particle.
    pub fn add(&mut self, g: &StateGrad) -> Result<(), MpmError> {
        if !g.has_len(self.len()) {
            return Err(MpmError::GradientMismatch(
                "seed gradient length differs from the particle count",
            ));
        }
        for p in 0..self.len() {
            if g.x[p] != DVec3::ZERO {
                self.add_x(p, g.x[p]);
            }
            if g.v[p] != DVec3::ZERO {
                self.add_v(p, g.v[p]);
            }
            if g.c[p] != DMat3::ZERO {
                self.add_c(p, g.c[p]);
            }
            if g.f[p] != DMat3::ZERO {
                self.add_f(p, g.f[p]);
            }
        }
        Ok(())
    }
}

/// Options of [`Simulator::backward`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BackwardOptions {
    /// Backpropagate through only the last `n` substeps (e.g. one frame); `None` = all.
    pub truncate: Option<usize>,
    /// Recomputed states kept alive while a segment is reversed (≥ 1: 0 is refused with
    /// [`crate::MpmError::InvalidParameter`]; default [`SEGMENT_SNAPSHOTS`]): the memory/time
    /// trade of the backward pass. A segment of `k`
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
///
/// Dropped, it returns its arrays to the simulator that made it (if it still exists), and the
/// next backward pass of the same particle count fills them instead of faulting in fresh
/// memory (an optimisation loop's gradients, like its tapes, are recycled).
#[derive(Debug, Clone)]
pub struct Gradients {
    /// `∂L/∂(state at substep start)`.
    pub state: StateGrad,
    /// Substep the state gradient refers to (0 unless truncated).
    pub start: usize,
    /// Material and family gradients.
    pub material: MaterialGrad,
    /// The simulator's pool, which takes the arrays back.
    pub(crate) pool: Weak<BufferCache>,
}

/// The arrays a dropped [`Gradients`] leaves for the next backward pass.
pub(crate) type GradArrays = (StateGrad, MaterialGrad);

impl Gradients {
    /// The state and material gradients, owned (they are then not recycled).
    pub fn into_parts(mut self) -> (StateGrad, MaterialGrad) {
        self.pool = Weak::new();
        self.take_arrays()
    }

    fn take_arrays(&mut self) -> GradArrays {
        (
            std::mem::take(&mut self.state),
            std::mem::take(&mut self.material),
        )
    }
}

impl Drop for Gradients {
    fn drop(&mut self) {
        if let Some(pool) = self.pool.upgrade() {
            pool.put(self.take_arrays());
        }
    }
}

impl<M: Constitutive> Simulator<M> {
    /// Runs `n_substeps` from `state` (advanced in place) keeping a checkpoint every `every`,
    /// in the simulator's precision. The particles are re-sorted by cell only at checkpoints
    /// (when their groups have broken up), so a segment's recomputation runs in the forward's
    /// order. A dropped tape returns its checkpoint buffers to this simulator, and the next
    /// tape of the same particle count reuses them (an optimisation loop's tapes fault in no
    /// fresh memory); they are freed with the simulator. The tape also holds up to
    /// [`SEGMENT_SNAPSHOTS`] states of its last segment (and, when that segment is at most
    /// `SEGMENT_SNAPSHOTS + 1` substeps long, each substep's intermediates), which the first
    /// backward pass takes instead of recomputing them.
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
        crate::sim::on_worker(|| {
            let mut report = self.prepare(state, mat)?;
            let data = match self.config.precision {
                Precision::F64 => TapeData::F64(forward_tape(
                    self,
                    state,
                    mat,
                    t0,
                    n_substeps,
                    every,
                    &mut report,
                )?),
                Precision::F32 => TapeData::F32(forward_tape(
                    self,
                    state,
                    mat,
                    t0,
                    n_substeps,
                    every,
                    &mut report,
                )?),
            };
            Ok(Tape {
                t0,
                n_substeps,
                every,
                data,
                report,
                pool: Arc::downgrade(&self.tape_pool.0),
            })
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
        mut seed: impl FnMut(usize, SeedState<'_>, &mut SeedGrad<'_>) -> Result<(), MpmError> + Send,
        opts: BackwardOptions,
    ) -> Result<Gradients, MpmError> {
        if opts.snapshots == 0 {
            return Err(MpmError::InvalidParameter {
                field: "snapshots",
                value: 0.0,
                reason: "must be >= 1",
            });
        }
        self.validate_material(mat, tape.len())?;
        let n = tape.n_substeps;
        let start = n - opts.truncate.unwrap_or(n).min(n);
        let mut seed_fn = |k: usize, src: &dyn SeedSource, sink: &mut dyn GradSink| {
            seed(k, SeedState { src }, &mut SeedGrad { sink })
        };
        let mut reuse = self.grad_pool.0.take::<GradArrays>();
        let (state, material) = crate::sim::on_worker(|| {
            per_precision!(TapeData, &tape.data, t => backward(
                self,
                t,
                mat,
                tape.t0,
                n,
                tape.every,
                start,
                opts.snapshots,
                &mut seed_fn,
                reuse.take(),
            ))
        })?;
        Ok(Gradients {
            state,
            start,
            material,
            pool: Arc::downgrade(&self.grad_pool.0),
        })
    }
}
