//! Differentiable MLS-MPM (Hu et al. 2018) with every PAC-NeRF material, on the CPU, in `f64`
//! or `f32` ([`Precision`]).
//!
//! Units are SI throughout: metres, seconds, kilograms, pascals. The substep follows PAC-NeRF's
//! `mpm_simulator.py` exactly (see `tests/fixtures` and the fixture README §3):
//! `F_tmp = (I + dt C) F` → return mapping and Kirchhoff stress → P2G (quadratic B-spline, APIC,
//! `D⁻¹ = 4/dx²`) → grid update `v = p/m + dt g` and boundaries → G2P.
//!
//! Reverse mode is written by hand ([`Simulator::substep_backward`], [`Simulator::backward`]
//! with checkpointing). The kernels work on particles across SIMD lanes: a run sorts the
//! particles by stencil cell and cuts them into groups of one vector (eight `f32` or four
//! `f64`) that share their 27 grid nodes, and returns everything in the caller's order. P2G
//! is parallel without atomics and bit-identical for any thread count; the kernels use AVX2 +
//! FMA (and AVX-512's registers) when the CPU has them, with results identical to the
//! portable path.
//!
//! ```
//! use glam::DVec3;
//! use pipe_mpm::{Aabb, Material, NeoHookean, SimConfig, Simulator, State};
//! let cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.1, 1e-4);
//! let sim = Simulator::new(NeoHookean, cfg).unwrap();
//! let mut state = State::at_rest(vec![DVec3::new(0.5, 0.5, 0.5), DVec3::new(0.55, 0.5, 0.5)]);
//! let mat = Material::from_e_nu(2, 1.25e-4, 1000.0, 1e5, 0.3).unwrap();
//! sim.run(&mut state, &mat, 0.0, 10).unwrap();
//! assert!(state.v[0].y < 0.0);
//! ```
//!
//! Gradients: run with checkpoints, then backpropagate a loss on the final positions.
//!
//! ```
//! use glam::DVec3;
//! use pipe_mpm::{Aabb, BackwardOptions, Material, NeoHookean, SimConfig, Simulator, State, StateGrad};
//! let sim = Simulator::new(NeoHookean, SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.1, 1e-4)).unwrap();
//! let mut state = State::at_rest(vec![DVec3::new(0.5, 0.5, 0.5), DVec3::new(0.55, 0.5, 0.5)]);
//! let (e, nu) = (1e5, 0.3);
//! let mat = Material::from_e_nu(2, 1.25e-4, 1000.0, e, nu).unwrap();
//! let tape = sim.forward_tape(&mut state, &mat, 0.0, 20, 10).unwrap(); // checkpoint every 10
//! let mut seed = StateGrad::zeros(2);
//! seed.x[0] = DVec3::Y; // L = y of particle 0 after 20 substeps
//! let g = sim.backward(&tape, &mat, |k, _| (k == 20).then(|| seed.clone()), BackwardOptions::default()).unwrap();
//! let (d_e, d_nu) = g.material.e_nu(e, nu);
//! assert!(g.state.v[0].y > 0.0 && d_e.is_finite() && d_nu.is_finite());
//! ```
//!
//! Modules: [`grid`] (index math, stencil), `grid_update`, [`boundary`], [`forces`],
//! [`timestep`], [`svd`], [`models`] (one file per family), [`adjoint`] (the public reverse
//! mode and checkpointing schedule), `wide` (the vectorised engine: lanes, groups, forward and
//! adjoint kernels, tape), `scatter` (deterministic slab colouring), [`family`] (runtime
//! family choice, monomorphised inside), `order` (permutations of the particles), `isa`
//! (run-time AVX2 + FMA choice), `stepper` (a state kept in the engine between runs).

/// `$body` with `$x` bound to the payload of `$value`, a value of the enum `$kind` that holds
/// one variant per [`Precision`] (`F64`, `F32`) of a type generic in it (a tape, an engine).
macro_rules! per_precision {
    ($kind:ident, $value:expr, $x:ident => $body:expr) => {
        match $value {
            $kind::F64($x) => $body,
            $kind::F32($x) => $body,
        }
    };
}

pub mod adjoint;
pub mod boundary;
mod error;
pub mod family;
pub mod forces;
pub mod grid;
mod grid_update;
mod isa;
pub mod math;
pub mod models;
mod order;
mod scatter;
mod sim;
mod state;
mod stepper;
pub mod svd;
pub mod timestep;
mod wide;

pub use adjoint::{BackwardOptions, Gradients, SeedGrad, SeedState, Tape};
pub use boundary::{Boundaries, BoundaryKind, Collider};
pub use error::MpmError;
pub use family::{Family, ModelVisitor};
pub use forces::{ParticleForce, speed_bound};
pub use grid::{Aabb, GridSpec, MAX_GRID_NODES};
pub use grid_update::mass_threshold;
pub use models::{
    Constitutive, DruckerPrager, FixedCorotated, ModelGrad, NeoHookean, Newtonian, VonMises,
};
pub use sim::{Domain, FOLLOW_MAX_NODES, Precision, RunReport, SimConfig, Simulator};
pub use state::{
    FamilyGrad, FamilyParams, Material, MaterialGrad, State, StateGrad, lame, lame_grad_to_e_nu,
};
pub use stepper::Stepper;
pub use timestep::{StableStep, StepLimits, stable_step, stable_step_at_speed, substeps_per_frame};
