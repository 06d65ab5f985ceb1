//! Adjoint of the grid update `v = B(mv/m + dt g)` (B = boundary conditions):
//! `m̄v = B̄(v̄)/m`, `m̄ = −B̄(v̄)·mv/m²` for nodes above the mass threshold, 0 otherwise.

use glam::DVec3;

use crate::boundary::Boundaries;
use crate::grid::{GridSpec, NodeBox};
use crate::grid_update::{NodeVel, mass_threshold};
use crate::p2g::Node;

/// Node gradients `(∂L/∂mv, ∂L/∂m)` stored as a [`Node`], for the nodes of `active` (the
/// particles' box; the rest of `out` is left as it was: nothing reads it).
#[allow(clippy::too_many_arguments)]
pub(crate) fn grid_update_adjoint(
    grid: &GridSpec,
    nodes: &[Node],
    g_vgrid: &[NodeVel],
    active: &NodeBox,
    dt: f64,
    g: DVec3,
    bc: &Boundaries,
    out: &mut Vec<Node>,
) {
    let thr = mass_threshold(grid.dx);
    out.resize(grid.len(), Node::default());
    active.par_for_each(grid, out, |i, o| {
        let (n, gv) = (&nodes[i], g_vgrid[i].v);
        *o = if n.m > thr && gv != DVec3::ZERO {
            let v = n.mv / n.m + dt * g;
            let gpre = bc.adjoint(grid, grid.node_pos(grid.unlinear(i)), v, gv);
            Node {
                mv: gpre / n.m,
                m: -gpre.dot(n.mv) / (n.m * n.m),
            }
        } else {
            Node::default()
        };
    });
}
