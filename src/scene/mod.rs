//! Domain types shared by stages and their Arrow tables (ARCHITECTURE §5).

pub mod frames;
pub mod gaussians;
pub mod metrics;
pub mod table;
