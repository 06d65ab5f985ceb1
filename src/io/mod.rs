//! File formats: where outside data enters, and is validated.

pub mod colmap;
pub mod exr;
pub mod image;
pub mod pacnerf;
pub mod parquet;
pub mod ply;
