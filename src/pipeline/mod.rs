//! The orchestration toolkit: pipeline files, the stage DAG, the cache and the runner.
//! It knows nothing of physics; stages plug in through [`stage::Registry`].

pub mod cache;
pub mod checkpoint;
pub mod graph;
pub mod lock;
pub mod progress;
pub mod runner;
pub mod spec;
pub mod stage;
pub mod yaml;
