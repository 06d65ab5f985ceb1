//! Domain types shared by stages and their Arrow tables (ARCHITECTURE §5).

pub mod camera;
pub mod deform;
pub mod frames;
pub mod gaussians;
pub mod metrics;
pub mod neighbors;
pub mod parts;
pub mod shading;
pub mod splat;
pub mod table;
pub mod targets;
pub mod visual_hull;
