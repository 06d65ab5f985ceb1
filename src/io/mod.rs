//! File formats: where outside data enters, and is validated.

pub mod image;
pub mod pacnerf;
