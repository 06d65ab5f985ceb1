//! The stages: one file per stage kind, each thin (read inputs, call kernels, write outputs).
//! They register here; the runner knows them only through [`Registry`].

pub mod edit;
pub mod evaluate;
pub mod ingest;
pub mod init;
pub mod material;
mod material_field;
mod material_parts;
pub mod material_select;
pub mod velocity;
pub mod warmup;

use crate::pipeline::stage::Registry;

/// Every stage kind the `pipe` binary knows, in natural pipeline order.
pub fn builtin() -> Registry {
    Registry::new()
        .with(ingest::Ingest)
        .with(init::Init)
        .with(warmup::Warmup)
        .with(velocity::Velocity)
        .with(material::MaterialStage)
        .with(evaluate::Evaluate)
        .with(edit::Edit)
}
