//! Adjoint of the grid update `v = B(mv/m + dt g)` (B = boundary conditions):
//! `m̄v = B̄(v̄)/m`, `m̄ = −B̄(v̄)·mv/m²` for nodes above the mass threshold, 0 otherwise.

use glam::DVec3;
use rayon::prelude::*;

use crate::boundary::Boundaries;
use crate::grid::GridSpec;
use crate::grid_update::{NodeVel, mass_threshold};
use crate::p2g::Node;

/// Node gradients `(∂L/∂mv, ∂L/∂m)` stored as a [`Node`].
pub(crate) fn grid_update_adjoint(
    grid: &GridSpec,
    nodes: &[Node],
    g_vgrid: &[NodeVel],
    dt: f64,
    g: DVec3,
    bc: &Boundaries,
    out: &mut Vec<Node>,
) {
    let thr = mass_threshold(grid.dx);
    nodes
        .par_iter()
        .zip(g_vgrid.par_iter())
        .enumerate()
        .map(|(i, (n, gv))| {
            if n.m > thr && gv.v != DVec3::ZERO {
                let v = n.mv / n.m + dt * g;
                let gpre = bc.adjoint(grid, grid.node_pos(grid.unlinear(i)), v, gv.v);
                Node {
                    mv: gpre / n.m,
                    m: -gpre.dot(n.mv) / (n.m * n.m),
                }
            } else {
                Node::default()
            }
        })
        .collect_into_vec(out);
}
