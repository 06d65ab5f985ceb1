//! Physics from video: what the `velocity` and `material` stages (and later `evaluate` and
//! `edit`) share. The canonical Gaussians become a simulated [`object::Object`] (the same
//! [`crate::simulate::Body`] as `pipe simulate`); a [`rollout::Rollout`] simulates its frames
//! and differentiates a per-frame loss back to the material's parameters
//! ([`params`]) and the initial velocity; the loss of a frame is the image loss of the
//! Gaussians posed at its state ([`pose`], [`views`]).

pub mod adam;
pub mod appearance;
pub mod descent;
pub mod field_parts;
pub mod fit;
pub mod free_flight;
pub mod material_field;
pub mod material_truth;
pub mod object;
pub mod params;
pub mod particles;
pub mod pose;
pub mod profile;
pub mod rollout;
pub mod step_search;
pub mod torque_free;
pub mod track;
pub mod velocity_field;
pub mod views;
