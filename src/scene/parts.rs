//! Which Gaussians of a scene are the object and which are its moving part, from point sets
//! that select them (PhysDreamer's `clean_object_points.ply` and `moving_part_points.ply`).
//!
//! A set's *reach* is `1.5·s`, `s` its point spacing
//! ([`crate::scene::neighbors::particle_spacing`]: the cube root of the volume per point inside
//! the set, the median nearest-neighbour distance for surfaces and small sets). A point of a
//! region sampled on a lattice of spacing `s` is within `(√3/2)·s` of a sample; a uniformly
//! random sampling at the same density leaves a point farther than `1.5·s` from every sample
//! with probability `exp(−(4π/3)·1.5³) ≈ 7·10⁻⁷`: the reach covers the set's region without
//! holes, and extends about one spacing beyond its outermost points.
//!
//! A Gaussian belongs to a set when its centre lies within the set's *tolerance* of one of the
//! set's points: the reach, except for a set whose every point is the centre of a Gaussian (to
//! 10⁻⁴ of its spacing: a selection cut out of the Gaussians themselves, as PhysDreamer's
//! tools make them), which selects exactly those Gaussians. (PhysDreamer itself freezes the
//! particles farther than half a grid cell from every moving point.)
//!
//! The sets must describe the same scene as the Gaussians: every point of a set has a Gaussian
//! within its reach, and every moving point lies within the object set's reach.

use glam::DVec3;
use rayon::prelude::*;

use super::neighbors::{PointGrid, particle_spacing};

/// The reach of a set, in point spacings.
pub const TOLERANCE_SPACINGS: f64 = 1.5;

/// A set whose points all lie within this many spacings of a Gaussian's centre is a subset of
/// the Gaussians.
pub const SUBSET_SPACINGS: f64 = 1e-4;

/// A point set and its tolerance.
#[derive(Debug, Clone, PartialEq)]
pub struct PointSet {
    /// Spacing of its points (m).
    pub spacing: f64,
    /// Its reach (m): `TOLERANCE_SPACINGS · spacing`.
    pub reach: f64,
    /// Whether every point is a Gaussian's centre (to `SUBSET_SPACINGS · spacing`).
    pub subset: bool,
    /// Distance within which a Gaussian belongs to it (m): the reach, or
    /// `SUBSET_SPACINGS · spacing` for a subset.
    pub tolerance: f64,
}

/// The Gaussians of each part.
#[derive(Debug, Clone, PartialEq)]
pub struct Parts {
    /// Per Gaussian: part of the object (true for all without an object set).
    pub object: Vec<bool>,
    /// Per Gaussian: part of the moving part (object and near a moving point; every object
    /// Gaussian without a moving set).
    pub moving: Vec<bool>,
    /// The object set, if given.
    pub object_set: Option<PointSet>,
    /// The moving set, if given.
    pub moving_set: Option<PointSet>,
}

/// Which set a problem is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Set {
    /// The object's points.
    Object,
    /// The moving part's points.
    Moving,
}

/// Why the sets do not describe the Gaussians (the caller names the files).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PartsError {
    /// A set without two distinct points has no spacing.
    #[error("holds {points} point(s) but no two distinct ones: its spacing is undefined")]
    NoSpacing {
        /// The set.
        set: Set,
        /// Its points.
        points: usize,
    },
    /// A point of a set far from every Gaussian.
    #[error(
        "point {index} at ({:.4}, {:.4}, {:.4}) m is {distance:.4} m from the nearest Gaussian, \
         beyond the reach {reach:.4} m ({TOLERANCE_SPACINGS} × the points' spacing \
         {spacing:.4} m): do the points and the Gaussians share one world frame?",
        point[0], point[1], point[2]
    )]
    FarFromGaussians {
        /// The set.
        set: Set,
        /// The point's index in its file.
        index: usize,
        /// Where it is (m).
        point: [f64; 3],
        /// Distance to the nearest Gaussian (m).
        distance: f64,
        /// The set's reach and spacing (m).
        reach: f64,
        spacing: f64,
    },
    /// A moving point outside the object.
    #[error(
        "point {index} at ({:.4}, {:.4}, {:.4}) m is not part of the object: the nearest object \
         point is {distance:.4} m away, beyond the object set's reach {reach:.4} m",
        point[0], point[1], point[2]
    )]
    MovingOutsideObject {
        /// The moving point's index.
        index: usize,
        /// Where it is (m).
        point: [f64; 3],
        /// Distance to the nearest object point (m).
        distance: f64,
        /// The object set's reach (m).
        reach: f64,
    },
}

impl PartsError {
    /// The set the problem is in.
    pub fn set(&self) -> Set {
        match self {
            Self::NoSpacing { set, .. } | Self::FarFromGaussians { set, .. } => *set,
            Self::MovingOutsideObject { .. } => Set::Moving,
        }
    }
}

/// A set's spacing.
fn spacing(points: &[DVec3], set: Set) -> Result<f64, PartsError> {
    particle_spacing(points)
        .map(|s| s.spacing)
        .filter(|s| s.is_finite() && *s > 0.0)
        .ok_or(PartsError::NoSpacing {
            set,
            points: points.len(),
        })
}

/// Per query: the distance (m) to the nearest point of `grid` (infinite when it is empty).
fn nearest(grid: &PointGrid, queries: &[DVec3]) -> Vec<f64> {
    queries
        .par_iter()
        .map(|&q| grid.nearest(q, None).map_or(f64::INFINITY, |(_, d)| d))
        .collect()
}

/// Whether a distance `d` (m) is beyond `reach` (NaN is).
fn beyond(d: f64, reach: f64) -> bool {
    d.is_nan() || d > reach
}

/// The set of `points`, checked: every point within its reach of a Gaussian.
fn point_set(points: &[DVec3], gaussians: &[DVec3], set: Set) -> Result<PointSet, PartsError> {
    let spacing = spacing(points, set)?;
    let reach = TOLERANCE_SPACINGS * spacing;
    let d = match gaussians.is_empty() {
        true => vec![f64::INFINITY; points.len()],
        false => nearest(&PointGrid::new(gaussians, reach), points),
    };
    if let Some(index) = d.iter().position(|&d| beyond(d, reach)) {
        return Err(PartsError::FarFromGaussians {
            set,
            index,
            point: points[index].to_array(),
            distance: d[index],
            reach,
            spacing,
        });
    }
    let subset = d.iter().all(|&d| d <= SUBSET_SPACINGS * spacing);
    Ok(PointSet {
        spacing,
        reach,
        subset,
        tolerance: if subset {
            SUBSET_SPACINGS * spacing
        } else {
            reach
        },
    })
}

/// The object and moving Gaussians of `gaussians` (centres, m) given the object's points and
/// the moving part's (m), each optional.
pub fn select(
    gaussians: &[DVec3],
    object: Option<&[DVec3]>,
    moving: Option<&[DVec3]>,
) -> Result<Parts, PartsError> {
    let object_set = object
        .map(|p| point_set(p, gaussians, Set::Object))
        .transpose()?;
    let moving_set = moving
        .map(|p| point_set(p, gaussians, Set::Moving))
        .transpose()?;
    let mut in_object = vec![true; gaussians.len()];
    let mut object_grid = None;
    if let (Some(points), Some(s)) = (object, &object_set) {
        let grid = PointGrid::new(points, s.reach);
        in_object = nearest(&grid, gaussians)
            .into_iter()
            .map(|d| d <= s.tolerance)
            .collect();
        object_grid = Some(grid);
    }
    let mut in_moving = in_object.clone();
    if let (Some(points), Some(s)) = (moving, &moving_set) {
        if let (Some(grid), Some(o)) = (&object_grid, &object_set) {
            let d = nearest(grid, points);
            if let Some(index) = d.iter().position(|&d| beyond(d, o.reach)) {
                return Err(PartsError::MovingOutsideObject {
                    index,
                    point: points[index].to_array(),
                    distance: d[index],
                    reach: o.reach,
                });
            }
        }
        let grid = PointGrid::new(points, s.reach);
        in_moving = nearest(&grid, gaussians)
            .into_iter()
            .zip(&in_object)
            .map(|(d, &o)| o && d <= s.tolerance)
            .collect();
    }
    Ok(Parts {
        object: in_object,
        moving: in_moving,
        object_set,
        moving_set,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lattice points of spacing `a` in the box `lo..hi`.
    fn lattice(lo: DVec3, hi: DVec3, a: f64) -> Vec<DVec3> {
        let n = ((hi - lo) / a).round().as_ivec3();
        let mut out = Vec::new();
        for i in 0..n.x {
            for j in 0..n.y {
                for k in 0..n.z {
                    out.push(lo + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * a);
                }
            }
        }
        out
    }

    #[test]
    fn a_coarser_offset_selection_covers_its_region_without_holes() {
        // Gaussians every 1 cm in a 10 × 20 × 10 cm block; the moving part is its top half,
        // selected by points every 1.7 cm on another lattice (offset, coarser).
        let g = lattice(DVec3::ZERO, DVec3::new(0.1, 0.2, 0.1), 0.01);
        let top = lattice(
            DVec3::new(0.0, 0.1, 0.0),
            DVec3::new(0.102, 0.204, 0.102),
            0.017,
        );
        let parts = select(&g, None, Some(&top)).unwrap();
        let s = parts.moving_set.as_ref().unwrap();
        assert!((s.spacing - 0.017).abs() < 1e-9, "{s:?}");
        assert!(!s.subset && s.tolerance == s.reach, "{s:?}");
        for (x, m) in g.iter().zip(&parts.moving) {
            // Every Gaussian of the top half moves; none more than the tolerance below it.
            if x.y > 0.1 {
                assert!(*m, "{x} should move");
            }
            if x.y < 0.1 - s.tolerance {
                assert!(!*m, "{x} should stay");
            }
        }
        assert!(parts.object.iter().all(|o| *o));
    }

    #[test]
    fn clutter_outside_the_object_never_moves_and_bad_sets_are_named() {
        let object = lattice(DVec3::ZERO, DVec3::splat(0.1), 0.01);
        let clutter = lattice(DVec3::new(0.3, 0.0, 0.0), DVec3::new(0.4, 0.1, 0.1), 0.01);
        let g: Vec<DVec3> = object.iter().chain(&clutter).copied().collect();
        let parts = select(&g, Some(&object), Some(&object)).unwrap();
        assert_eq!(parts.object.iter().filter(|o| **o).count(), object.len());
        assert_eq!(parts.moving, parts.object);
        // Without an object set, everything is object, and a moving set of all the Gaussians
        // moves them all.
        let parts = select(&g, None, Some(&g)).unwrap();
        assert!(parts.object.iter().chain(&parts.moving).all(|m| *m));
        // A subset of the Gaussians selects exactly them, not their neighbours one spacing
        // away (the reach would take those).
        let upper: Vec<DVec3> = object.iter().filter(|x| x.y > 0.05).copied().collect();
        let parts = select(&g, Some(&object), Some(&upper)).unwrap();
        assert!(parts.moving_set.as_ref().unwrap().subset);
        assert_eq!(parts.moving.iter().filter(|m| **m).count(), upper.len());
        for (x, m) in g.iter().zip(&parts.moving) {
            assert_eq!(*m, x.y > 0.05 && x.x < 0.2, "{x}");
        }
        // A moving point in the clutter: outside the object.
        let e = select(&g, Some(&object), Some(&clutter)).unwrap_err();
        assert!(
            matches!(e, PartsError::MovingOutsideObject { index: 0, .. }),
            "{e}"
        );
        // A point far from every Gaussian (another frame?).
        let mut far = object.clone();
        far[7] += DVec3::new(0.0, 5.0, 0.0);
        let e = select(&g, Some(&far), None).unwrap_err();
        assert_eq!(e.set(), Set::Object);
        assert!(e.to_string().starts_with("point 7 at "), "{e}");
        let e = select(&g, None, Some(&[DVec3::ZERO])).unwrap_err();
        assert!(matches!(e, PartsError::NoSpacing { points: 1, .. }), "{e}");
    }
}
