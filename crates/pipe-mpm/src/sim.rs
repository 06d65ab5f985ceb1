//! The simulator: one MLS-MPM substep exactly as PAC-NeRF (fixture README §3 steps 1–7).
//!
//! 1. `F_tmp = (I + dt C) F`; 2–4. return mapping and Kirchhoff stress τ (the model);
//! 5. P2G; 6. grid update and boundaries; 7. G2P, `x ← x + dt v`, held in the domain.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::boundary::Boundaries;
use crate::error::MpmError;
use crate::forces::{ParticleForce, extra_momentum};
use crate::g2p::g2p;
use crate::grid::{Aabb, GridSpec, NodeBox};
use crate::grid_update::{NodeVel, grid_update};
use crate::isa::{Isa, Lanes, WithLanes};
use crate::models::{Constitutive, particle_model};
use crate::order::Order;
use crate::p2g::{Node, P2gIn, p2g};
use crate::scatter::Bins;
use crate::state::{FamilyParams, Material, State};

/// Scene-level settings (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Cell size (m).
    pub dx: f64,
    /// Substep (s).
    pub dt: f64,
    /// Gravity (m/s²), e.g. `(0, −9.8, 0)`.
    pub gravity: DVec3,
    /// Box the particles are held in (m); the grid adds `margin` cells around it.
    pub domain: Aabb,
    /// Extra grid cells beyond the domain on each side (at least 2).
    pub margin: usize,
    /// Boundary conditions.
    pub boundaries: Boundaries,
    /// External forces and impulses.
    pub forces: Vec<ParticleForce>,
    /// Floating-point precision of [`Simulator::run`].
    pub precision: Precision,
}

/// Floating-point precision of a forward run ([`Simulator::run`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Precision {
    /// `f64` throughout: the reference, and the precision of the taped forward pass and the
    /// backward pass.
    #[default]
    F64,
    /// `f32` particle state and arithmetic on the vectorised engine (eight particles per
    /// vector; the grid stays `f64`), as the peer simulators (Taichi, Warp) run: about three
    /// times the `f64` throughput, positions within ~1e-5 cells per 100 substeps of it.
    F32,
}

impl SimConfig {
    /// Gravity `(0, −9.8, 0)`, sticky ground `y = 0`, separating domain walls, margin 3.
    pub fn new(domain: Aabb, dx: f64, dt: f64) -> Self {
        Self {
            dx,
            dt,
            gravity: DVec3::new(0.0, -9.8, 0.0),
            domain,
            margin: 3,
            boundaries: Boundaries {
                colliders: vec![crate::boundary::Collider::ground(
                    0.0,
                    crate::boundary::BoundaryKind::Sticky,
                )],
                walls: Some(crate::boundary::BoundaryKind::Separate),
            },
            forces: Vec::new(),
            precision: Precision::F64,
        }
    }
}

/// Outcome of a forward run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RunReport {
    /// Substeps taken.
    pub substeps: usize,
    /// Particle-substeps in which a particle was held at the domain edge.
    pub held: usize,
    /// Most particles held in a single substep.
    pub max_held: usize,
}

/// Intermediates of one substep (reused across substeps; the adjoint recomputes them).
#[derive(Debug, Clone, Default)]
pub(crate) struct Work {
    pub bins: Bins,
    pub tau: Vec<DMat3>,
    /// [`Constitutive::update_with_aux`]'s scalar per particle (empty unless
    /// [`Constitutive::STRESS_AUX`]).
    pub aux: Vec<f64>,
    pub nodes: Vec<Node>,
    /// Nodes `nodes` and `vgrid` hold for this substep (outside it `nodes` is zero and `vgrid`
    /// is stale).
    pub active: NodeBox,
    pub vgrid: Vec<NodeVel>,
    pub extra: Option<Vec<DVec3>>,
    /// Set by [`Simulator::forward`] when some new `x, v, C` or `F` is NaN/Inf (checked in the
    /// kernels, so the full scan runs only then).
    pub non_finite: bool,
}

/// Particles per parallel task of the stress pass.
const STRESS_CHUNK: usize = 1024;

/// Where a stress chunk reads `F_old` and whether it writes the new `F`.
enum FIo<'a> {
    /// Read and overwrite `F` in place.
    InPlace(&'a mut [DMat3]),
    /// Read the first, write the second.
    From(&'a [DMat3], &'a mut [DMat3]),
    /// Read only (the stress alone is wanted).
    Read(&'a [DMat3]),
}

/// Steps 1–4 for a chunk of particles: `F ← update((I + dt C) F_old)` and `τ`; returns whether
/// some new `F` is NaN/Inf.
struct StressChunk<'a, M> {
    model: &'a M,
    dt: f64,
    c: &'a [DMat3],
    mu: &'a [f64],
    lam: &'a [f64],
    /// Per-particle family scalars (empty: the model's own).
    family: &'a [FamilyParams],
    f: FIo<'a>,
    tau: &'a mut [DMat3],
    /// Written when [`Constitutive::STRESS_AUX`] (else empty).
    aux: &'a mut [f64],
}

/// `v` (resized to `n`) in chunks of `chunk` when `used`, else as many empty slices: per-chunk
/// outputs that only some models write, zipped with the other chunks of a parallel pass.
pub(crate) fn chunks_or_empty<T: Default + Clone>(
    v: &mut Vec<T>,
    n: usize,
    chunk: usize,
    used: bool,
) -> Vec<&mut [T]> {
    if used {
        v.resize(n, T::default());
        v.chunks_mut(chunk).collect()
    } else {
        v.clear();
        (0..n.div_ceil(chunk))
            .map(|_| <&mut [T]>::default())
            .collect()
    }
}

impl<M: Constitutive> WithLanes for StressChunk<'_, M> {
    type Output = bool;

    #[inline(always)]
    fn with<L: Lanes>(self, _l: L) -> bool {
        let StressChunk {
            model,
            dt,
            c,
            mu,
            lam,
            family,
            mut f,
            tau,
            aux,
        } = self;
        let mut bad = false;
        for (p, tau) in tau.iter_mut().enumerate() {
            let f0 = match &f {
                FIo::InPlace(io) => io[p],
                FIo::From(old, _) | FIo::Read(old) => old[p],
            };
            let model = particle_model(model, family, p);
            let ft = model.predict(&c[p], &f0, dt);
            let (f_new, t_new, a) = model.update_with_aux(&ft, &c[p], mu[p], lam[p], dt);
            *tau = t_new;
            if M::STRESS_AUX {
                aux[p] = a;
            }
            match &mut f {
                FIo::InPlace(out) | FIo::From(_, out) => {
                    out[p] = f_new;
                    bad |= !f_new.is_finite();
                }
                FIo::Read(_) => {}
            }
        }
        bad
    }
}

/// The part `r` of per-particle family scalars (empty stays empty: the model's own).
#[inline]
fn family_chunk(family: &[FamilyParams], r: std::ops::Range<usize>) -> &[FamilyParams] {
    if family.is_empty() {
        family
    } else {
        &family[r]
    }
}

/// Runs `f` on a worker thread of the current rayon pool (inline when already on one).
///
/// A loop of parallel kernels driven from outside the pool hands every kernel to the pool and
/// sleeps until it is done: five futex round trips per substep, about 10 % of a substep at
/// 20k particles. Driven from a worker, the kernels start and join without sleeping.
pub(crate) fn on_worker<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        f()
    } else {
        rayon::scope(|_| f())
    }
}

/// A differentiable MLS-MPM simulator for one constitutive model `M`.
#[derive(Debug, Clone)]
pub struct Simulator<M: Constitutive> {
    pub(crate) model: M,
    pub(crate) config: SimConfig,
    pub(crate) grid: GridSpec,
    /// The vectorised engine's arrays from the last run (reused by the next).
    pub(crate) wide_cache: BufferCache,
}

/// Buffers kept from one run to the next (any type; a run takes them or starts empty). A
/// clone of the simulator starts with an empty cache.
#[derive(Default)]
pub(crate) struct BufferCache(std::sync::Mutex<Option<Box<dyn std::any::Any + Send>>>);

impl BufferCache {
    /// The cached buffers if they are a `B` (the cache is left empty).
    pub(crate) fn take<B: 'static>(&self) -> Option<B> {
        let mut slot = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let b = slot.take()?;
        b.downcast::<B>().ok().map(|b| *b)
    }

    /// Keeps `b` for the next run.
    pub(crate) fn put<B: Send + 'static>(&self, b: B) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(Box::new(b));
    }
}

impl Clone for BufferCache {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl std::fmt::Debug for BufferCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("BufferCache")
    }
}

impl<M: Constitutive> Simulator<M> {
    /// Validates the settings and builds the grid.
    pub fn new(model: M, config: SimConfig) -> Result<Self, MpmError> {
        model.validate()?;
        if !(config.dt.is_finite() && config.dt > 0.0) {
            return Err(MpmError::InvalidParameter {
                field: "dt",
                value: config.dt,
                reason: "must be finite and > 0",
            });
        }
        if !config.gravity.is_finite() {
            return Err(MpmError::NonFiniteInput {
                field: "gravity",
                index: 0,
                value: config.gravity.max_element(),
            });
        }
        config.boundaries.validate()?;
        let grid = GridSpec::new(config.domain, config.dx, config.margin)?;
        Ok(Self {
            model,
            config,
            grid,
            wide_cache: BufferCache::default(),
        })
    }

    /// The constitutive model and its family parameters.
    pub fn model(&self) -> &M {
        &self.model
    }

    /// Scene settings (change them through the setters, which keep the grid consistent).
    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The grid built from the domain.
    pub fn grid(&self) -> &GridSpec {
        &self.grid
    }

    /// Replaces the model (e.g. new family parameters during optimisation).
    pub fn set_model(&mut self, model: M) -> Result<(), MpmError> {
        model.validate()?;
        self.model = model;
        Ok(())
    }

    /// Replaces the external forces and impulses.
    pub fn set_forces(&mut self, forces: Vec<ParticleForce>) {
        self.config.forces = forces;
    }

    /// Replaces the boundary conditions.
    pub fn set_boundaries(&mut self, boundaries: Boundaries) -> Result<(), MpmError> {
        boundaries.validate()?;
        self.config.boundaries = boundaries;
        Ok(())
    }

    /// Changes the substep `dt` (s), e.g. after [`crate::stable_step`] as E changes.
    pub fn set_dt(&mut self, dt: f64) -> Result<(), MpmError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(MpmError::InvalidParameter {
                field: "dt",
                value: dt,
                reason: "must be finite and > 0",
            });
        }
        self.config.dt = dt;
        Ok(())
    }

    /// Validates a state and material for this simulator (lengths, finiteness, forces' indices).
    pub fn validate(&self, state: &State, mat: &Material) -> Result<(), MpmError> {
        state.validate()?;
        mat.validate(state.len())?;
        if !mat.family.is_empty() {
            if !M::HAS_FAMILY_PARAMS {
                return Err(MpmError::InvalidParameter {
                    field: "family",
                    value: mat.family.len() as f64,
                    reason: "per-particle family parameters given to a model without any",
                });
            }
            for (index, p) in mat.family.iter().enumerate() {
                self.model
                    .with_params(p)
                    .validate()
                    .map_err(|e| e.at_particle(index))?;
            }
        }
        self.config
            .forces
            .iter()
            .try_for_each(|f| f.validate(state.len()))
    }

    /// Holds every particle inside the domain; returns how many moved.
    pub fn hold_all(&self, state: &mut State) -> usize {
        state
            .x
            .iter_mut()
            .map(|x| usize::from(self.grid.hold(x)))
            .sum()
    }

    /// One substep of `s` (positions inside the domain) at time `t` (s), in place: every
    /// kernel reads only its own particle's old values after the previous kernel wrote them
    /// (`F` before P2G, `x, v, C` after it), so no second state is needed.
    /// Returns the number of particles held at the domain edge.
    pub(crate) fn forward(&self, s: &mut State, mat: &Material, t: f64, w: &mut Work) -> usize {
        self.forward_from(None, s, mat, t, w)
    }

    /// One substep from `src` into `s` (buffers of the same length), or of `s` in place when
    /// `src` is `None`; bit-identical either way.
    pub(crate) fn forward_from(
        &self,
        src: Option<&State>,
        s: &mut State,
        mat: &Material,
        t: f64,
        w: &mut Work,
    ) -> usize {
        let dt = self.config.dt;
        let model = &self.model;
        let n = s.len();
        w.tau.resize(n, DMat3::ZERO);
        {
            let (c_old, f_old) = match src {
                Some(src) => (&src.c, Some(&src.f)),
                None => (&s.c, None),
            };
            let isa = Isa::detect();
            let aux = chunks_or_empty(&mut w.aux, n, STRESS_CHUNK, M::STRESS_AUX);
            w.non_finite =
                s.f.par_chunks_mut(STRESS_CHUNK)
                    .zip(w.tau.par_chunks_mut(STRESS_CHUNK))
                    .zip(aux)
                    .enumerate()
                    .map(|(k, ((f, tau), aux))| {
                        let r = k * STRESS_CHUNK..k * STRESS_CHUNK + f.len();
                        let f = match f_old {
                            Some(fo) => FIo::From(&fo[r.clone()], f),
                            None => FIo::InPlace(f),
                        };
                        isa.run_lanes(StressChunk {
                            model,
                            dt,
                            c: &c_old[r.clone()],
                            mu: &mat.mu[r.clone()],
                            lam: &mat.lam[r.clone()],
                            family: family_chunk(&mat.family, r),
                            f,
                            tau,
                            aux,
                        })
                    })
                    .reduce(|| false, |a, b| a | b);
        }
        let x_old = match src {
            Some(src) => {
                self.to_grid(src, mat, t, w);
                Some(src.x.as_slice())
            }
            None => {
                self.to_grid(s, mat, t, w);
                None
            }
        };
        let State { x, v, c, .. } = s;
        let (held, bad) = g2p(&self.grid, &w.vgrid, dt, x_old, x, v, c);
        w.non_finite |= bad;
        held
    }

    /// Kirchhoff stress τ of every particle into `w.tau` (steps 1–4 without writing `F`).
    pub(crate) fn stress(&self, s: &State, mat: &Material, w: &mut Work) {
        let (dt, model, isa) = (self.config.dt, &self.model, Isa::detect());
        w.tau.resize(s.len(), DMat3::ZERO);
        let aux = chunks_or_empty(&mut w.aux, s.len(), STRESS_CHUNK, M::STRESS_AUX);
        w.tau
            .par_chunks_mut(STRESS_CHUNK)
            .zip(aux)
            .enumerate()
            .for_each(|(k, (tau, aux))| {
                let r = k * STRESS_CHUNK..k * STRESS_CHUNK + tau.len();
                isa.run_lanes(StressChunk {
                    model,
                    dt,
                    c: &s.c[r.clone()],
                    mu: &mat.mu[r.clone()],
                    lam: &mat.lam[r.clone()],
                    family: family_chunk(&mat.family, r.clone()),
                    f: FIo::Read(&s.f[r]),
                    tau,
                    aux,
                });
            });
    }

    /// Steps 5–6 given `w.tau`: binning, P2G and the grid update into `w.vgrid`.
    pub(crate) fn to_grid(&self, s: &State, mat: &Material, t: f64, w: &mut Work) {
        let dt = self.config.dt;
        w.bins.rebuild(&self.grid, &s.x);
        w.extra = extra_momentum(&self.config.forces, s.len(), t, dt);
        let inp = P2gIn {
            x: &s.x,
            v: &s.v,
            c: &s.c,
            tau: &w.tau,
            mass: &mat.mass,
            volume: &mat.volume,
            extra: w.extra.as_deref(),
            dt,
        };
        p2g(&self.grid, &w.bins, inp, &mut w.nodes, &mut w.active);
        grid_update(
            &self.grid,
            &w.nodes,
            &w.active,
            dt,
            self.config.gravity,
            &self.config.boundaries,
            &mut w.vgrid,
        );
    }

    /// Advances `state` by `n_substeps` substeps from time `t0` (s), checking for NaN/Inf after
    /// every substep. Particles outside the domain are first held at its edge (counted).
    pub fn run(
        &self,
        state: &mut State,
        mat: &Material,
        t0: f64,
        n_substeps: usize,
    ) -> Result<RunReport, MpmError> {
        match self.config.precision {
            Precision::F64 => self
                .advance(state, mat, t0, n_substeps, |_, _| {})
                .map(|(rep, _)| rep),
            Precision::F32 => on_worker(|| {
                self.validate(state, mat)?;
                let held = self.hold_all(state);
                let mut rep = RunReport {
                    held,
                    max_held: held,
                    ..RunReport::default()
                };
                crate::wide::run::<f32, M>(self, state, mat, t0, n_substeps, &mut rep)?;
                Ok(rep)
            }),
        }
    }

    /// The simulator seen in slot order `o`: forces renumbered to slots.
    pub(crate) fn sorted(&self, o: &Order) -> Self {
        let mut sim = self.clone();
        sim.config.forces = o.sort_forces(&self.config.forces);
        sim
    }

    /// The substep loop shared by [`Self::run`] and [`Self::forward_tape`]. The particles are
    /// put in spatial order ([`Order`]) for the loop and handed back in the caller's order;
    /// `before(k, state_k)` sees the state at the start of every substep `k` in that slot
    /// order, which is returned (`None`: the caller's order was already spatial).
    pub(crate) fn advance(
        &self,
        state: &mut State,
        mat: &Material,
        t0: f64,
        n_substeps: usize,
        before: impl FnMut(usize, &State) + Send,
    ) -> Result<(RunReport, Option<Order>), MpmError> {
        on_worker(|| self.advance_on_worker(state, mat, t0, n_substeps, before))
    }

    /// [`Self::advance`] on the calling thread.
    fn advance_on_worker(
        &self,
        state: &mut State,
        mat: &Material,
        t0: f64,
        n_substeps: usize,
        before: impl FnMut(usize, &State),
    ) -> Result<(RunReport, Option<Order>), MpmError> {
        self.validate(state, mat)?;
        let mut rep = RunReport::default();
        let h = self.hold_all(state);
        rep.held += h;
        rep.max_held = h;
        let order = Order::by_cell(&self.grid, &state.x);
        let done = match &order {
            None => self.substeps(state, mat, t0, n_substeps, &mut rep, before),
            Some(o) => {
                let mut s = o.sort_state(state);
                let done = self.sorted(o).substeps(
                    &mut s,
                    &o.sort_material(mat),
                    t0,
                    n_substeps,
                    &mut rep,
                    before,
                );
                o.unsort_state_into(&s, state);
                // Name the first offending particle in the caller's order.
                done.map_err(|e| match e {
                    MpmError::NonFinite { substep, .. } => {
                        let (quantity, particle) = state.first_non_finite().unwrap_or(("x", 0));
                        MpmError::NonFinite {
                            substep,
                            quantity,
                            particle,
                        }
                    }
                    e => e,
                })
            }
        };
        done.map(|()| (rep, order))
    }

    /// `n_substeps` substeps of `state` (already validated and held), counted into `rep`.
    fn substeps(
        &self,
        state: &mut State,
        mat: &Material,
        t0: f64,
        n_substeps: usize,
        rep: &mut RunReport,
        mut before: impl FnMut(usize, &State),
    ) -> Result<(), MpmError> {
        let mut w = Work::default();
        for k in 0..n_substeps {
            before(k, state);
            let held = self.forward(state, mat, t0 + k as f64 * self.config.dt, &mut w);
            let bad = w.non_finite.then(|| state.first_non_finite()).flatten();
            if let Some((quantity, particle)) = bad {
                return Err(MpmError::NonFinite {
                    substep: k,
                    quantity,
                    particle,
                });
            }
            rep.substeps += 1;
            rep.held += held;
            rep.max_held = rep.max_held.max(held);
        }
        Ok(())
    }
}
