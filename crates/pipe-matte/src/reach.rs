//! Where the object's shadow can fall: a shadow lies within reach of the body that casts it.
//!
//! Light that comes down at most `θ` from the vertical (the sun or a lamp at least `90° − θ`
//! above the horizon) casts the shadow of a point at height `h` at most `h · tan θ` from the
//! point's foot. Every point of the object lies in the visual hull of the changed pixels, so a
//! ground point farther than that from every column of the hull (its foot, its top height) is
//! in no shadow of the object: a pixel that shows it dimmed shows the object in front of it.
//! This decides what the ground test cannot: pixels whose ground point no other camera sees
//! (a dark object against distant floor).

use glam::{DVec2, DVec3};

use crate::hull::Hull;

/// The hull's columns and how far their shadows can reach.
#[derive(Debug, Clone)]
pub(crate) struct ShadowReach {
    /// Per occupied column: its foot (x, z) and the radius its shadow may reach, metres.
    columns: Vec<(DVec2, f64)>,
}

impl ShadowReach {
    /// The reach of the shadow of `hull` under light at most `max_zenith_deg` from the
    /// vertical (a column's top grown by half a voxel, its foot by half a voxel's diagonal).
    pub(crate) fn new(hull: &Hull, max_zenith_deg: f64) -> Self {
        let tan = max_zenith_deg.clamp(0.0, 89.0).to_radians().tan();
        let (nx, ny) = (hull.dims.x as usize, hull.dims.y as usize);
        let nz = hull.dims.z as usize;
        let mut columns = Vec::new();
        for k in 0..nz {
            for i in 0..nx {
                let top = (0..ny)
                    .rev()
                    .find(|&j| hull.occupied[(k * ny + j) * nx + i]);
                if let Some(j) = top {
                    let c = hull.box_min
                        + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * hull.voxel;
                    let height = (c.y + hull.voxel / 2.0).max(0.0);
                    columns.push((
                        DVec2::new(c.x, c.z),
                        height * tan + hull.voxel * std::f64::consts::FRAC_1_SQRT_2,
                    ));
                }
            }
        }
        Self { columns }
    }

    /// Whether the object's shadow can fall on ground point `g` (its y is ignored).
    pub(crate) fn reaches(&self, g: DVec3) -> bool {
        let g = DVec2::new(g.x, g.z);
        self.columns
            .iter()
            .any(|(foot, radius)| foot.distance_squared(g) <= radius * radius)
    }
}

#[cfg(test)]
mod tests {
    use glam::UVec3;

    use super::*;

    #[test]
    fn a_columns_shadow_reaches_as_far_as_its_height_allows() {
        // One voxel column 0.1 m wide from the ground to 0.3 m, at the origin.
        let hull = Hull::from_occupancy(
            DVec3::new(-0.05, 0.0, -0.05),
            0.1,
            UVec3::new(1, 3, 1),
            vec![true; 3],
        );
        let reach = ShadowReach::new(&hull, 45.0);
        let r = 0.3 + 0.1 * std::f64::consts::FRAC_1_SQRT_2;
        assert!(reach.reaches(DVec3::new(r - 1e-6, 0.0, 0.0)));
        assert!(reach.reaches(DVec3::new(0.0, 0.0, -(r - 1e-6))));
        assert!(!reach.reaches(DVec3::new(r + 1e-3, 0.0, 0.0)));
        // Lower light reaches farther; an empty hull casts no shadow.
        assert!(ShadowReach::new(&hull, 75.0).reaches(DVec3::new(1.0, 0.0, 0.0)));
        let empty = Hull::from_occupancy(DVec3::ZERO, 0.1, UVec3::ONE, vec![false]);
        assert!(!ShadowReach::new(&empty, 75.0).reaches(DVec3::ZERO));
    }
}
