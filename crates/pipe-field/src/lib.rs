//! Triplane + MLP fields over the simulation domain (the seed paper's §3.2, eq. 8): a map from a
//! particle's rest position `x` (metres) to `outputs` numbers (e.g. log10 E and encoded ν, or
//! an initial velocity in m/s), with a hand-written backward, the plane total-variation
//! regulariser and Adam with per-group learning-rate schedules.
//!
//! # The field
//!
//! - Normalisation ([`Domain`]): `u = clamp((x − min)/(max − min), 0, 1)` per axis. **Points
//!   outside the box are clamped to it**: they take the value at the nearest point of the box,
//!   and `∂y/∂x` is 0 along clamped axes. Infinite coordinates clamp too; NaN coordinates are
//!   errors. A zero-extent axis is an error naming the axis.
//! - Triplane ([`Triplane`]): planes XY, XZ, YZ of `R × R` nodes × `C` channels, nodes at
//!   `u = i/(R−1)` (the box's faces lie on the outer nodes), sampled bilinearly at the
//!   projection of `u`; features summed (`C` values) or concatenated (`3C`), see [`Combine`].
//!   Bilinear sampling is continuous across cell edges (and piecewise linear in `u`).
//! - MLP ([`Mlp`]): `z_l = a_{l−1} W_l + b_l`, `a_l = σ(z_l)` on `layers` hidden layers of width
//!   `hidden` (σ = ReLU or softplus, see [`Activation`]), linear output `y = z_L`.
//!
//! `y(x) = MLP(triplane(u(x)))`, in the units of whatever the caller encodes (the field itself
//! is dimensionless apart from `x`).
//!
//! # Regulariser (eq. 8)
//!
//! `TV = w Σ_{p ∈ {XY, XZ, YZ}} [ mean (P[j, i+1] − P[j, i])² + mean (P[j+1, i] − P[j, i])² ]`,
//! squared differences of neighbouring nodes along each plane axis, each mean over its
//! `R(R−1)C` pairs; `w` = [`FieldConfig::tv_weight`]. See [`Triplane::tv`].
//!
//! # Optimiser
//!
//! [`Adam`] over parameter groups, each with an [`LrSchedule`] (exponential decay from `lr` to
//! `lr_final`); [`FieldAdam`] wires the two groups of a field, `planes` and `mlp`.
//!
//! # Determinism
//!
//! Initialisation draws from a PCG stream seeded by the caller. [`Field::forward`] is per
//! point; [`Field::backward`] sums per-point gradients in fixed chunks of [`CHUNK`] points in
//! point order, then the chunks in order, so every result is bit-identical whatever the
//! number of rayon threads.
//!
//! # Weights
//!
//! [`Field::to_flat`] / [`Field::set_flat`] (planes then MLP parameters) for optimisers;
//! [`Field::weights`] / [`Field::from_weights`] give the serde-serialisable [`FieldWeights`]
//! (config, box and named tensors) for a weights table.

pub mod adam;
pub mod config;
pub mod domain;
pub mod error;
pub mod field;
pub mod mlp;
pub mod triplane;
pub mod weights;

pub use adam::{Adam, AdamConfig, FieldAdam, LrSchedule, ParamGroup};
pub use config::FieldConfig;
pub use domain::Domain;
pub use error::{FieldError, Result};
pub use field::{CHUNK, Field, FieldGradient};
pub use mlp::{Activation, Mlp, MlpScratch};
pub use triplane::{Combine, PLANE_AXES, PLANE_NAMES, Triplane};
pub use weights::{FieldWeights, NamedTensor};
