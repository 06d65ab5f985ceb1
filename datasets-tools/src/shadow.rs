//! A directional light's shadow of a point cloud on the ground plane y = 0.
//!
//! Each particle `x` casts its shadow at `g = x − (x_y / L_y)·L` along the light's direction of
//! travel `L` (L_y < 0). The shadow's opacity on a ground grid is the maximum over particles of
//! a disc of radius `core` (full shadow) with a Gaussian fall-off of width
//! `σ = penumbra_base + penumbra_slope·x_y` (a higher occluder casts a softer edge, as an area
//! light does). The plate is then multiplied by `1 − (1 − floor_factor)·opacity`.

use glam::{DVec2, DVec3};

/// A shadow-opacity map over a patch of the ground plane.
#[derive(Debug, Clone)]
pub struct GroundShadow {
    origin: DVec2,
    cell: f64,
    nx: usize,
    nz: usize,
    opacity: Vec<f32>,
    /// Plate factor under full shadow.
    pub floor_factor: f64,
}

/// How the shadow is cast.
#[derive(Debug, Clone, Copy)]
pub struct ShadowParams {
    /// Direction of travel of the light (normalised inside; must point down).
    pub light: DVec3,
    /// Radius of full shadow around each particle's shadow point, metres.
    pub core: f64,
    /// Penumbra width at height 0, metres.
    pub penumbra_base: f64,
    /// Penumbra width growth per metre of occluder height.
    pub penumbra_slope: f64,
    /// Plate factor under full shadow (the sample scenes' shadows dim the floor to ~0.33).
    pub floor_factor: f64,
    /// Ground grid cell, metres.
    pub cell: f64,
}

impl GroundShadow {
    /// Casts the shadow of `points` (metres).
    pub fn cast(points: &[DVec3], p: &ShadowParams) -> Self {
        let light = p.light.normalize();
        assert!(light.y < -1e-6, "the light must travel downwards");
        let hits: Vec<(DVec2, f64)> = points
            .iter()
            .map(|x| {
                let g = *x - light * (x.y.max(0.0) / light.y);
                (
                    DVec2::new(g.x, g.z),
                    p.penumbra_base + p.penumbra_slope * x.y.max(0.0),
                )
            })
            .collect();
        let reach = |s: f64| p.core + 3.0 * s;
        let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for (g, s) in &hits {
            lo = lo.min(*g - reach(*s));
            hi = hi.max(*g + reach(*s));
        }
        if hits.is_empty() {
            (lo, hi) = (DVec2::ZERO, DVec2::ZERO);
        }
        let nx = ((hi.x - lo.x) / p.cell).ceil() as usize + 1;
        let nz = ((hi.y - lo.y) / p.cell).ceil() as usize + 1;
        let mut opacity = vec![0f32; nx * nz];
        for (g, s) in &hits {
            let r = reach(*s);
            let i0 = ((g.x - r - lo.x) / p.cell).floor().max(0.0) as usize;
            let i1 = (((g.x + r - lo.x) / p.cell).ceil() as usize).min(nx - 1);
            let k0 = ((g.y - r - lo.y) / p.cell).floor().max(0.0) as usize;
            let k1 = (((g.y + r - lo.y) / p.cell).ceil() as usize).min(nz - 1);
            for k in k0..=k1 {
                for i in i0..=i1 {
                    let c = lo + DVec2::new(i as f64, k as f64) * p.cell;
                    let d = (c.distance(*g) - p.core).max(0.0);
                    let o = (-(d * d) / (2.0 * s * s)).exp() as f32;
                    let cell = &mut opacity[k * nx + i];
                    *cell = cell.max(o);
                }
            }
        }
        Self {
            origin: lo,
            cell: p.cell,
            nx,
            nz,
            opacity,
            floor_factor: p.floor_factor,
        }
    }

    /// Shadow opacity in [0, 1] at ground point `(x, z)` (bilinear; 0 off the map).
    pub fn opacity(&self, x: f64, z: f64) -> f64 {
        let fx = (x - self.origin.x) / self.cell;
        let fz = (z - self.origin.y) / self.cell;
        if !(fx >= 0.0 && fz >= 0.0) || fx >= (self.nx - 1) as f64 || fz >= (self.nz - 1) as f64 {
            return 0.0;
        }
        let (i, k) = (fx as usize, fz as usize);
        let (tx, tz) = (fx - i as f64, fz - k as f64);
        let at = |i: usize, k: usize| f64::from(self.opacity[k * self.nx + i]);
        (1.0 - tz) * ((1.0 - tx) * at(i, k) + tx * at(i + 1, k))
            + tz * ((1.0 - tx) * at(i, k + 1) + tx * at(i + 1, k + 1))
    }

    /// The factor the plate is multiplied by at ground point `(x, z)`.
    pub fn factor(&self, x: f64, z: f64) -> f64 {
        1.0 - (1.0 - self.floor_factor) * self.opacity(x, z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_straight_above_shadows_the_ground_below_it_only() {
        let p = ShadowParams {
            light: DVec3::new(0.0, -1.0, 0.0),
            core: 0.01,
            penumbra_base: 0.005,
            penumbra_slope: 0.0,
            floor_factor: 0.3,
            cell: 0.002,
        };
        let s = GroundShadow::cast(&[DVec3::new(0.1, 0.5, -0.2)], &p);
        assert!((s.factor(0.1, -0.2) - 0.3).abs() < 1e-9);
        assert_eq!(s.factor(0.2, -0.2), 1.0);
        // Oblique light: the shadow moves away from the light by height / tan(elevation).
        let oblique = ShadowParams {
            light: DVec3::new(1.0, -1.0, 0.0),
            ..p
        };
        let s = GroundShadow::cast(&[DVec3::new(0.0, 0.5, 0.0)], &oblique);
        assert!((s.factor(0.5, 0.0) - 0.3).abs() < 1e-6);
        assert_eq!(s.factor(0.0, 0.0), 1.0);
    }
}
