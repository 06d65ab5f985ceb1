//! The simulator: one MLS-MPM substep exactly as PAC-NeRF (fixture README §3 steps 1–7).
//!
//! 1. `F_tmp = (I + dt C) F`; 2–4. return mapping and Kirchhoff stress τ (the model);
//! 5. P2G; 6. grid update and boundaries; 7. G2P, `x ← x + dt v`, held in the domain.
//!
//! The substep runs on the vectorised engine (`crate::wide`) in the configured [`Precision`].

use glam::DVec3;

use crate::boundary::Boundaries;
use crate::error::MpmError;
use crate::forces::ParticleForce;
use crate::grid::{Aabb, GridSpec};
use crate::models::Constitutive;
use crate::state::{Material, State};

/// Scene-level settings (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Cell size (m).
    pub dx: f64,
    /// Substep (s).
    pub dt: f64,
    /// Gravity (m/s²), e.g. `(0, −9.8, 0)`.
    pub gravity: DVec3,
    /// Where the grid lies: a fixed box, or following the particles.
    pub domain: Domain,
    /// Extra grid cells beyond a fixed domain on each side (at least 2).
    pub margin: usize,
    /// Boundary conditions.
    pub boundaries: Boundaries,
    /// External forces and impulses.
    pub forces: Vec<ParticleForce>,
    /// Floating-point precision of the runs, tapes and backward passes.
    pub precision: Precision,
}

/// Where the simulation grid lies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Domain {
    /// A fixed box (m): the grid covers it plus [`SimConfig::margin`] cells; particles that
    /// reach its edge are held there (counted in [`RunReport::held`]) and the domain walls
    /// ([`crate::Boundaries::walls`]) act outside it.
    Fixed(Aabb),
    /// The grid follows the particles: each substep's grid is the window of nodes their
    /// stencils reach (the particles' box plus the stencil margin), on one lattice of cell
    /// `dx`, so nothing but the declared colliders acts on them and no particle is ever held.
    /// A window over `max_nodes` nodes (particles flying apart) stops the run with
    /// [`MpmError::GridTooLarge`].
    Follow {
        /// Most nodes a window may have.
        max_nodes: usize,
    },
}

/// Default node budget of a following grid: 2²⁴ nodes (a 256³ box; 0.5 GB per `f64` node
/// array).
pub const FOLLOW_MAX_NODES: usize = 1 << 24;

/// Floating-point precision of the particle state, the grid and the arithmetic (the boundary
/// conditions and the per-particle return maps of the plastic and fluid families always run
/// in `f64`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Precision {
    /// `f64`, four particles per vector: the reference, used by the gradient checks.
    #[default]
    F64,
    /// `f32`, eight particles per vector, as the peer simulators (Taichi, Warp) run: about
    /// twice the `f64` throughput; positions within ~1e-6 m of it after 40 substeps of the
    /// engine tests' scene.
    F32,
}

impl SimConfig {
    /// Gravity `(0, −9.8, 0)`, sticky ground `y = 0`, separating domain walls, margin 3.
    pub fn new(domain: Aabb, dx: f64, dt: f64) -> Self {
        Self {
            dx,
            dt,
            gravity: DVec3::new(0.0, -9.8, 0.0),
            domain: Domain::Fixed(domain),
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

    /// Gravity `(0, −9.8, 0)`, sticky ground `y = 0`, a grid that follows the particles
    /// ([`Domain::Follow`], budget [`FOLLOW_MAX_NODES`]) and no walls.
    pub fn following(dx: f64, dt: f64) -> Self {
        let mut c = Self::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, dt);
        c.domain = Domain::Follow {
            max_nodes: FOLLOW_MAX_NODES,
        };
        c.boundaries.walls = None;
        c
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
    /// The vectorised engine's arrays from the last run and the last backward pass (reused by
    /// the next).
    pub(crate) wide_cache: BufferCache,
    pub(crate) adjoint_cache: BufferCache,
    /// The checkpoint buffers of the last dropped tape (reused by the next `forward_tape`).
    pub(crate) tape_pool: TapePool,
    /// The gradient arrays of the last dropped [`crate::adjoint::Gradients`] (reused by the
    /// next backward pass).
    pub(crate) grad_pool: TapePool,
}

/// Where a dropped [`crate::adjoint::Tape`] returns its checkpoint buffers: the tape holds it
/// weakly, so a tape that outlives its simulator frees them. A clone of the simulator starts
/// with an empty pool.
#[derive(Default)]
pub(crate) struct TapePool(pub(crate) std::sync::Arc<BufferCache>);

impl Clone for TapePool {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl std::fmt::Debug for TapePool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TapePool")
    }
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
        let grid = match config.domain {
            Domain::Fixed(domain) => GridSpec::new(domain, config.dx, config.margin)?,
            Domain::Follow { max_nodes } => {
                if max_nodes < 27 {
                    return Err(MpmError::InvalidParameter {
                        field: "max_nodes",
                        value: max_nodes as f64,
                        reason: "a grid needs at least the 27 nodes of one stencil",
                    });
                }
                GridSpec::unbounded(config.dx)?
            }
        };
        Ok(Self {
            model,
            config,
            grid,
            wide_cache: BufferCache::default(),
            adjoint_cache: BufferCache::default(),
            tape_pool: TapePool::default(),
            grad_pool: TapePool::default(),
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
        self.validate_material(mat, state.len())?;
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

    /// Checks `mat` for `n` particles and this simulator's model (family parameters).
    pub(crate) fn validate_material(&self, mat: &Material, n: usize) -> Result<(), MpmError> {
        mat.validate(n)?;
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
        Ok(())
    }

    /// Validates a run's input and holds its particles in the domain: the report so far.
    pub(crate) fn prepare(&self, state: &mut State, mat: &Material) -> Result<RunReport, MpmError> {
        self.validate(state, mat)?;
        let held = self.hold_all(state);
        Ok(RunReport {
            held,
            max_held: held,
            ..RunReport::default()
        })
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
        let mut stepper = self.stepper(state, mat)?;
        let rep = stepper.advance(t0, self.config.dt, n_substeps);
        stepper.read(state)?;
        rep
    }
}
