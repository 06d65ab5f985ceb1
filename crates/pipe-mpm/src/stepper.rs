//! A state kept in the vectorised engine from one run to the next.
//!
//! [`Simulator::run`] loads its state into the engine (structure of arrays, sorted by cell)
//! and writes all of it back at the end. A caller that runs frame after frame and reads only
//! the positions and velocities in between (`pipe simulate`) keeps the state in a
//! [`Stepper`] instead: it is loaded and sorted once, re-sorted only when its groups have
//! broken up (as inside a run), and each frame reads back `x` and `v` alone.

use glam::DVec3;

use crate::error::MpmError;
use crate::grid::Aabb;
use crate::models::Constitutive;
use crate::sim::{Precision, RunReport, Simulator, on_worker};
use crate::state::{Material, State};
use crate::wide::{Buffers, Engine};

/// The engine in the simulator's precision.
enum Kept<'s, M: Constitutive> {
    F64(Engine<'s, f64, M>),
    F32(Engine<'s, f32, M>),
}

/// A simulator's particles kept in its engine between calls to [`Stepper::advance`] (from
/// [`Simulator::stepper`]). Its runs give what [`Simulator::run`] gives to rounding: the
/// engine sums each node's contributions in the order of its particle groups, and a kept state
/// keeps its groups across runs where a run sorts them afresh. Dropping it returns the
/// engine's buffers to the simulator.
pub struct Stepper<'s, M: Constitutive> {
    engine: Kept<'s, M>,
    /// Particles held at the domain edge when loaded (counted into the first report).
    held_at_load: usize,
    /// Per boundary (colliders in order, then the domain walls), the particles whose stencils
    /// reached it since [`Stepper::take_contacts`] (empty unless watched).
    contacts: Vec<Vec<bool>>,
    /// The union of the grids of the substeps of the last [`Stepper::advance`].
    span: Option<Aabb>,
}

impl<M: Constitutive> std::fmt::Debug for Stepper<'_, M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let precision = match self.engine {
            Kept::F64(_) => Precision::F64,
            Kept::F32(_) => Precision::F32,
        };
        f.debug_struct("Stepper")
            .field("particles", &self.len())
            .field("precision", &precision)
            .finish()
    }
}

impl<M: Constitutive> Simulator<M> {
    /// `state` (validated, then held in the domain) and `mat` loaded into the engine, to be
    /// advanced by [`Stepper::advance`]; the state and material are copied, so `state` is
    /// the caller's to reuse (e.g. as [`Stepper::read_motion`]'s output).
    pub fn stepper(&self, state: &mut State, mat: &Material) -> Result<Stepper<'_, M>, MpmError> {
        let rep = self.prepare(state, mat)?;
        let state = &*state;
        let engine = on_worker(|| match self.config.precision {
            Precision::F64 => Kept::F64(Engine::new(self, state, mat, self.cached())),
            Precision::F32 => Kept::F32(Engine::new(self, state, mat, self.cached())),
        });
        Ok(Stepper {
            engine,
            held_at_load: rep.held,
            contacts: Vec::new(),
            span: None,
        })
    }

    /// The engine's buffers of the last run in precision `T`, or empty ones.
    fn cached<T: 'static>(&self) -> Buffers<T> {
        self.wide_cache.take::<Buffers<T>>().unwrap_or_default()
    }
}

impl<M: Constitutive> Stepper<'_, M> {
    /// Number of particles.
    pub fn len(&self) -> usize {
        per_precision!(Kept, &self.engine, e => e.p.n)
    }

    /// `true` without particles.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Advances the particles by `n_substeps` substeps of `dt` (s) from time `t0` (s),
    /// checking for NaN/Inf after every substep (the error names the substep, quantity and
    /// particle; [`Self::read`] then gives the state as it was when the value appeared).
    pub fn advance(&mut self, t0: f64, dt: f64, n_substeps: usize) -> Result<RunReport, MpmError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(MpmError::InvalidParameter {
                field: "dt",
                value: dt,
                reason: "must be finite and > 0",
            });
        }
        let held = std::mem::take(&mut self.held_at_load);
        let mut rep = RunReport {
            held,
            max_held: held,
            ..RunReport::default()
        };
        let (contacts, span) = (&mut self.contacts, &mut self.span);
        *span = None;
        per_precision!(Kept, &mut self.engine, e => on_worker(|| {
            e.dt = dt;
            for k in 0..n_substeps {
                e.regroup(true).map_err(|err| err.at_substep(k))?;
                let g = e.grid().extent();
                *span = Some(match *span {
                    Some(s) => Aabb::new(s.lo.min(g.lo), s.hi.max(g.hi)),
                    None => g,
                });
                if !contacts.is_empty() {
                    e.mark_contacts(contacts);
                }
                let outcome = e.step(t0 + k as f64 * dt);
                e.record(k, outcome, &mut rep)?;
            }
            Ok::<(), MpmError>(())
        }))?;
        Ok(rep)
    }

    /// Starts counting, per boundary, the particles it acts on: those whose stencil reaches a
    /// node the boundary treats in some substep (colliders in order, then the domain walls of
    /// a fixed domain), read and reset by [`Self::take_contacts`].
    pub fn watch_contacts(&mut self) {
        let n = self.len();
        let b = per_precision!(Kept, &self.engine, e => e.sim.config.boundaries.colliders.len());
        self.contacts = vec![vec![false; n]; b + 1];
    }

    /// Per boundary (colliders in order, then the domain walls), how many particles it acted
    /// on since the last call (or [`Self::watch_contacts`]); empty when not watched.
    pub fn take_contacts(&mut self) -> Vec<usize> {
        self.contacts
            .iter_mut()
            .map(|m| {
                let c = m.iter().filter(|&&b| b).count();
                m.fill(false);
                c
            })
            .collect()
    }

    /// The box (m) of the grid nodes the substeps of the last [`Self::advance`] stored (the
    /// union of a following grid's windows; the fixed grid otherwise); `None` before any.
    pub fn grid_span(&self) -> Option<Aabb> {
        self.span
    }

    /// Writes the positions (m, held in the domain) and velocities (m/s) into `state.x` and
    /// `state.v` (the caller's particle order; `C` and `F` untouched). `state` must hold
    /// [`Self::len`] particles.
    pub fn read_motion(&self, state: &mut State) -> Result<(), MpmError> {
        self.read_into(state, true)
    }

    /// Writes the whole state into `state` (the caller's particle order): positions (m, held in
    /// the domain), velocities (m/s), `C` (1/s) and `F`. `state` must hold [`Self::len`]
    /// particles.
    pub fn read(&self, state: &mut State) -> Result<(), MpmError> {
        self.read_into(state, false)
    }

    fn read_into(&self, state: &mut State, motion_only: bool) -> Result<(), MpmError> {
        state.check_len(self.len())?;
        per_precision!(Kept, &self.engine, e => on_worker(|| e.read(state, motion_only)));
        Ok(())
    }

    /// The whole state as a new [`State`].
    pub fn state(&self) -> State {
        let mut s = State::at_rest(vec![DVec3::ZERO; self.len()]);
        per_precision!(Kept, &self.engine, e => on_worker(|| e.read(&mut s, false)));
        s
    }
}

impl<M: Constitutive> Drop for Stepper<'_, M> {
    fn drop(&mut self) {
        per_precision!(Kept, &mut self.engine, e => e.sim.wide_cache.put(e.take_buffers()));
    }
}
