//! `pipe`: multi-view videos of a deforming object → an editable, physics-driven 3D scene.
//!
//! The crate holds the product's orchestration ([`pipeline`]: pipeline files, stage DAG,
//! content-addressed cache, runner), the stages ([`stages`]), the shared domain types and their
//! Arrow tables ([`scene`]), the file formats ([`io`]) and the command line ([`cli`]). Numerical
//! kernels live in the `pipe-*` member crates.

pub mod cli;
pub mod export;
pub mod io;
pub mod physics;
pub mod pipeline;
pub mod preview;
pub mod report;
pub mod scene;
pub mod simulate;
pub mod stages;
pub mod sweep;
