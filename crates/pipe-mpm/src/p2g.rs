//! Particle to grid (APIC / MLS-MPM, Hu et al. 2018 eq. 3–5).
//!
//! `A_p = −dt V_p (4/dx²) τ_p + m_p C_p`;
//! `mv_i += w_ip (m_p v_p + A_p (x_i − x_p))`, `m_i += w_ip m_p`.

use glam::{DMat3, DVec3};

use crate::grid::GridSpec;
use crate::scatter::{Bins, scatter};

/// Grid node accumulator: momentum (kg·m/s) and mass (kg).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Node {
    /// Momentum (kg·m/s).
    pub mv: DVec3,
    /// Mass (kg).
    pub m: f64,
}

/// Inputs of P2G, one entry per particle.
#[derive(Debug, Clone, Copy)]
pub(crate) struct P2gIn<'a> {
    pub x: &'a [DVec3],
    pub v: &'a [DVec3],
    pub c: &'a [DMat3],
    pub tau: &'a [DMat3],
    pub mass: &'a [f64],
    pub volume: &'a [f64],
    pub extra: Option<&'a [DVec3]>,
    pub dt: f64,
}

/// The APIC affine matrix `A = −dt V (4/dx²) τ + m C`.
#[inline]
pub(crate) fn affine(
    grid: &GridSpec,
    dt: f64,
    volume: f64,
    mass: f64,
    tau: &DMat3,
    c: &DMat3,
) -> DMat3 {
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    *tau * (-dt * volume * d_inv) + *c * mass
}

/// Scatters particles into `nodes` (cleared first). `mom + A dpos` is built axis by axis
/// along the separable stencil: `(mom + A₀ px) + A₁ py` per row, `+ A₂ pz` per node.
pub(crate) fn p2g(grid: &GridSpec, bins: &Bins, inp: P2gIn<'_>, nodes: &mut Vec<Node>) {
    nodes.clear();
    nodes.resize(grid.len(), Node::default());
    scatter(grid, bins, nodes, |p, chunk, first| {
        let st = grid.stencil(inp.x[p]);
        let d = st.offsets(grid.dx);
        let m = inp.mass[p];
        let a = affine(grid, inp.dt, inp.volume[p], m, &inp.tau[p], &inp.c[p]);
        let mut mom = inp.v[p] * m;
        if let Some(e) = inp.extra {
            mom += e[p];
        }
        for i in 0..3 {
            let q_x = mom + a.x_axis * d[i].x;
            for j in 0..3 {
                let q_xy = q_x + a.y_axis * d[j].y;
                let wxy = st.w[i].x * st.w[j].y;
                let row = grid.row_mut(chunk, first, st.local, i, j);
                for (k, n) in row.iter_mut().enumerate() {
                    let w = wxy * st.w[k].z;
                    n.mv += w * (q_xy + a.z_axis * d[k].z);
                    n.m += w * m;
                }
            }
        }
    });
}
