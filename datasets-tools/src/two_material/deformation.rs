//! How much a group of particles has deformed from its rest shape, two ways:
//!
//! - edge strain: over the lattice edges `(i, j)` of the group (neighbours at rest), the 95th
//!   percentile of `| |x_i − x_j| / |X_i − X_j| − 1 |` (local stretch or compression);
//! - the non-rigid residual: the RMS distance between the particles and their rest positions
//!   moved by the best rigid motion (Kabsch: translation of the centroid, rotation the polar
//!   factor of `Σ (x − x̄)(X − X̄)ᵀ`), divided by the rest shape's RMS radius about its
//!   centroid. Zero for any rigid motion.

use glam::{DMat3, DVec3};

use super::bar::Bar;

/// The largest deformation of each half of a bar over its frames (index 0 the soft half,
/// 1 the stiff one).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deformation {
    /// Largest [`non_rigid_residual`].
    pub residual: [f64; 2],
    /// The frame of the soft half's largest residual.
    pub residual_frame: usize,
    /// Largest [`edge_strain_p95`] over each half's lattice edges.
    pub strain: [f64; 2],
}

impl Deformation {
    /// Of `bar` through `frames` (positions per frame, m).
    pub fn of(bar: &Bar, frames: &[Vec<DVec3>]) -> Self {
        let soft = bar.soft();
        let halves = [soft.clone(), soft.iter().map(|s| !s).collect::<Vec<bool>>()];
        let edges = bar.edges();
        let half_edges: [Vec<(usize, usize)>; 2] = std::array::from_fn(|h| {
            edges
                .iter()
                .copied()
                .filter(|&(i, j)| halves[h][i] && halves[h][j])
                .collect()
        });
        let mut out = Self {
            residual: [0.0; 2],
            residual_frame: 0,
            strain: [0.0; 2],
        };
        for (f, x) in frames.iter().enumerate() {
            for h in 0..2 {
                let r = non_rigid_residual(&bar.rest, x, &halves[h]);
                if r > out.residual[h] {
                    out.residual[h] = r;
                    if h == 0 {
                        out.residual_frame = f;
                    }
                }
                out.strain[h] = out.strain[h].max(edge_strain_p95(&bar.rest, x, &half_edges[h]));
            }
        }
        out
    }
}

/// The 95th percentile (nearest rank) of the strain `| |x_i − x_j| / |X_i − X_j| − 1 |` over
/// `edges` (index pairs into `rest` and `x`); 0 without edges.
pub fn edge_strain_p95(rest: &[DVec3], x: &[DVec3], edges: &[(usize, usize)]) -> f64 {
    let mut strain: Vec<f64> = edges
        .iter()
        .map(|&(i, j)| ((x[i] - x[j]).length() / (rest[i] - rest[j]).length() - 1.0).abs())
        .collect();
    if strain.is_empty() {
        return 0.0;
    }
    strain.sort_by(f64::total_cmp);
    let rank = ((0.95 * strain.len() as f64).ceil() as usize).clamp(1, strain.len());
    strain[rank - 1]
}

/// The non-rigid residual of the particles `pick`ed out of `x` against `rest` (see the module).
pub fn non_rigid_residual(rest: &[DVec3], x: &[DVec3], pick: &[bool]) -> f64 {
    let idx: Vec<usize> = (0..rest.len()).filter(|&i| pick[i]).collect();
    let n = idx.len() as f64;
    let rc = idx.iter().map(|&i| rest[i]).sum::<DVec3>() / n;
    let xc = idx.iter().map(|&i| x[i]).sum::<DVec3>() / n;
    let mut cov = DMat3::ZERO;
    for &i in &idx {
        let (a, b) = (x[i] - xc, rest[i] - rc);
        cov += DMat3::from_cols(a * b.x, a * b.y, a * b.z);
    }
    let r = pipe_mpm::svd::polar_rotation(&cov);
    let (mut se, mut radius) = (0.0, 0.0);
    for &i in &idx {
        let b = rest[i] - rc;
        se += ((x[i] - xc) - r * b).length_squared();
        radius += b.length_squared();
    }
    (se / radius).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block() -> Vec<DVec3> {
        let mut p = Vec::new();
        for k in 0..4 {
            for j in 0..3 {
                for i in 0..6 {
                    p.push(DVec3::new(i as f64, j as f64, k as f64) * 0.01);
                }
            }
        }
        p
    }

    #[test]
    fn rigid_motion_is_no_deformation_and_squashing_is() {
        let rest = block();
        let all = vec![true; rest.len()];
        let rot = DMat3::from_axis_angle(DVec3::new(0.3, 1.0, 0.2).normalize(), 0.4);
        let moved: Vec<DVec3> = rest
            .iter()
            .map(|p| rot * *p + DVec3::new(0.5, -0.2, 0.1))
            .collect();
        assert!(non_rigid_residual(&rest, &moved, &all) < 1e-12);
        let squashed: Vec<DVec3> = rest
            .iter()
            .map(|p| DVec3::new(p.x, 0.8 * p.y, p.z))
            .collect();
        let r = non_rigid_residual(&rest, &squashed, &all);
        assert!(r > 0.01 && r < 0.2, "{r}");
        // Edges along x keep their length, edges along y shrink by 20 %: over a third of
        // the edges (all y edges), the 95th percentile is 0.2.
        let mut edges = Vec::new();
        for (i, p) in rest.iter().enumerate() {
            for (j, q) in rest.iter().enumerate() {
                if i < j && (*p - *q).length() < 0.0101 {
                    edges.push((i, j));
                }
            }
        }
        assert_eq!(edges.len(), 5 * 3 * 4 + 6 * 2 * 4 + 6 * 3 * 3);
        assert!(edge_strain_p95(&rest, &moved, &edges) < 1e-12);
        let s = edge_strain_p95(&rest, &squashed, &edges);
        assert!((s - 0.2).abs() < 1e-12, "{s}");
        // Only the picked particles count.
        let mut pick = all.clone();
        let mut partly = moved.clone();
        for (i, p) in partly.iter_mut().enumerate() {
            if i % 2 == 0 {
                p.y *= 3.0;
                pick[i] = false;
            }
        }
        assert!(non_rigid_residual(&rest, &partly, &pick) < 1e-12);
        assert!(non_rigid_residual(&rest, &partly, &all) > 0.1);
    }
}
