//! Grid update: `v_i = mv_i/m_i + dt g` for nodes with `m_i > 1e-8 dx³` (kg), then the boundary
//! conditions; nodes below the mass threshold get `v = 0`.

use glam::DVec3;
use rayon::prelude::*;

use crate::boundary::Boundaries;
use crate::grid::GridSpec;
use crate::p2g::Node;

/// Mass threshold `1e-8 dx³` (kg) below which a node is considered empty (PAC-NeRF).
#[inline]
pub fn mass_threshold(dx: f64) -> f64 {
    1e-8 * dx * dx * dx
}

/// Node velocities (m/s) after gravity `g` (m/s²) and the boundary conditions.
pub(crate) fn grid_update(
    grid: &GridSpec,
    nodes: &[Node],
    dt: f64,
    g: DVec3,
    bc: &Boundaries,
    out: &mut Vec<DVec3>,
) {
    let thr = mass_threshold(grid.dx);
    nodes
        .par_iter()
        .enumerate()
        .map(|(i, n)| {
            if n.m > thr {
                let v = n.mv / n.m + dt * g;
                bc.apply(grid, grid.node_pos(grid.unlinear(i)), v)
            } else {
                DVec3::ZERO
            }
        })
        .collect_into_vec(out);
}
