//! Grid update: `v_i = mv_i/m_i + dt g` for nodes with `m_i > 1e-8 dx³` (kg), then the boundary
//! conditions; nodes below the mass threshold get `v = 0`.

use glam::DVec3;

use crate::boundary::Boundaries;
use crate::grid::{GridSpec, NodeBox};
use crate::p2g::Node;

/// Mass threshold `1e-8 dx³` (kg) below which a node is considered empty (PAC-NeRF).
#[inline]
pub fn mass_threshold(dx: f64) -> f64 {
    1e-8 * dx * dx * dx
}

/// Node velocity (m/s), padded to four `f64` lanes so that one node is one vector.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[repr(C, align(32))]
pub struct NodeVel {
    /// Velocity (m/s).
    pub v: DVec3,
    /// Always 0.
    pad: f64,
}

impl NodeVel {
    /// A node velocity (m/s).
    #[inline(always)]
    pub fn new(v: DVec3) -> Self {
        Self { v, pad: 0.0 }
    }

    /// The four lanes `(vx, vy, vz, 0)`.
    #[inline(always)]
    pub(crate) fn lanes(&self) -> [f64; 4] {
        [self.v.x, self.v.y, self.v.z, self.pad]
    }

    /// A node velocity from four lanes whose fourth is 0 (kept as the padding, so the node is
    /// written as one 32-byte store: split stores made the next 32-byte load of the same node
    /// miss store-to-load forwarding).
    #[inline(always)]
    pub(crate) fn from_lanes(a: [f64; 4]) -> Self {
        debug_assert!(a[3] == 0.0, "padding lane {} is not 0", a[3]);
        Self {
            v: DVec3::new(a[0], a[1], a[2]),
            pad: a[3],
        }
    }
}

/// Node velocities (m/s) after gravity `g` (m/s²) and the boundary conditions, for the nodes
/// of `active` (the particles' box; the rest of `out` is left as it was: nothing reads it).
pub(crate) fn grid_update(
    grid: &GridSpec,
    nodes: &[Node],
    active: &NodeBox,
    dt: f64,
    g: DVec3,
    bc: &Boundaries,
    out: &mut Vec<NodeVel>,
) {
    let thr = mass_threshold(grid.dx);
    out.resize(grid.len(), NodeVel::default());
    active.par_for_each(grid, out, |i, o| {
        let n = &nodes[i];
        *o = if n.m > thr {
            let v = n.mv / n.m + dt * g;
            NodeVel::new(bc.apply(grid, grid.node_pos(grid.unlinear(i)), v))
        } else {
            NodeVel::default()
        };
    });
}
