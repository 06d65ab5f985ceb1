//! The axis-aligned box the planes are laid over, and the map of a point to plane coordinates.

use crate::error::{AXES, FieldError, Result};

/// Axis-aligned box of the simulation domain, metres (`min < max` on every axis).
///
/// A point `x` maps to normalised coordinates `u = clamp((x − min) / (max − min), 0, 1)` per
/// axis: points outside the box take the value of the nearest point of its surface, and the
/// derivative of `u` along a clamped axis is 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Domain {
    min: [f64; 3],
    max: [f64; 3],
    inv_extent: [f64; 3],
}

impl Domain {
    /// The box `[min, max]` (metres); an error names a non-finite bound or an axis whose
    /// extent `max − min` is not positive.
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Result<Self> {
        let mut inv_extent = [0.0; 3];
        for a in 0..3 {
            for (field, value) in [("min", min[a]), ("max", max[a])] {
                if !value.is_finite() {
                    return Err(FieldError::DomainNotFinite {
                        field,
                        axis: AXES[a],
                        value,
                    });
                }
            }
            let extent = max[a] - min[a];
            // `1/extent` must be finite too (a subnormal extent would overflow).
            if extent <= 0.0 || !(1.0 / extent).is_finite() {
                return Err(FieldError::DomainExtent {
                    axis: AXES[a],
                    min: min[a],
                    max: max[a],
                    extent,
                });
            }
            inv_extent[a] = 1.0 / extent;
        }
        Ok(Self {
            min,
            max,
            inv_extent,
        })
    }

    /// The bounding box of `points` (metres) grown by `margin` metres on every side, e.g. the
    /// box of a scene's particles at rest. A flat set of points with `margin = 0` is an error
    /// naming the flat axis; a NaN point is an error naming it.
    pub fn around(points: &[[f64; 3]], margin: f64) -> Result<Self> {
        if !margin.is_finite() || margin < 0.0 {
            return Err(FieldError::Config {
                field: "margin",
                value: margin.to_string(),
                reason: "must be finite and >= 0 metres",
            });
        }
        if points.is_empty() {
            return Err(FieldError::Config {
                field: "points",
                value: "0 points".to_owned(),
                reason: "the box of no points is undefined",
            });
        }
        check_points("points", points)?;
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for p in points {
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        for a in 0..3 {
            min[a] -= margin;
            max[a] += margin;
        }
        Self::new(min, max)
    }

    /// Lower corner, metres.
    pub fn min(&self) -> [f64; 3] {
        self.min
    }

    /// Upper corner, metres.
    pub fn max(&self) -> [f64; 3] {
        self.max
    }

    /// Normalised coordinates `u ∈ [0, 1]³` of `x` (clamped to the box) and `∂u/∂x` per axis
    /// (`1/extent` in 1/m on or inside the box, 0 where clamped). `x` must not be NaN.
    #[inline]
    pub fn normalise(&self, x: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let mut u = [0.0; 3];
        let mut du = [0.0; 3];
        for a in 0..3 {
            let t = (x[a] - self.min[a]) * self.inv_extent[a];
            if t < 0.0 {
                u[a] = 0.0;
            } else if t > 1.0 {
                u[a] = 1.0;
            } else {
                u[a] = t;
                du[a] = self.inv_extent[a];
            }
        }
        (u, du)
    }
}

/// An error naming the first NaN coordinate of `points` (infinities are allowed: they clamp).
pub(crate) fn check_points(field: &'static str, points: &[[f64; 3]]) -> Result<()> {
    for (index, p) in points.iter().enumerate() {
        if let Some(a) = p.iter().position(|v| v.is_nan()) {
            return Err(FieldError::PointNaN {
                field,
                index,
                axis: AXES[a],
            });
        }
    }
    Ok(())
}
