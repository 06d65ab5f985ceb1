//! Adjoint of P2G, gathered per particle (no races). With `A = −dt V (4/dx²) τ + m C`,
//! `mom = m v + f_ext`, `mv_i += w (mom + A dpos)`, `m_i += w m`:
//! `Ā = Σ w m̄v_i dposᵀ`, `v̄ = m Σ w m̄v_i`, `m̄ = Σ w (m̄v_i·(v + C dpos) + m̄_i)`,
//! `C̄ = m Ā`, `τ̄ = −dt V (4/dx²) Ā`, `V̄ = −dt (4/dx²) Ā:τ`,
//! `x̄ = Σ ∇w (m̄v_i·(mom + A dpos) + m m̄_i) − Aᵀ Σ w m̄v_i`.

use glam::{DMat3, DVec3};

use crate::grid::GridSpec;
use crate::math::{ddot, outer};
use crate::p2g::{Node, affine};

/// Per-particle gradients from P2G.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct P2gGrad {
    pub x: DVec3,
    pub v: DVec3,
    pub c: DMat3,
    pub tau: DMat3,
    pub mass: f64,
    pub volume: f64,
}

#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn p2g_adjoint_particle(
    grid: &GridSpec,
    g_nodes: &[Node],
    dt: f64,
    x: DVec3,
    v: DVec3,
    c: &DMat3,
    tau: &DMat3,
    mass: f64,
    volume: f64,
    extra: DVec3,
) -> P2gGrad {
    let st = grid.stencil(x);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let a = affine(grid, dt, volume, mass, tau, c);
    let mom = v * mass + extra;
    let mut ga = DMat3::ZERO;
    let mut sum_wg = DVec3::ZERO;
    let mut gm = 0.0;
    let mut gx = DVec3::ZERO;
    st.for_each_node(grid, 0, |o, i, w, dpos| {
        let gn = g_nodes[i];
        if gn.mv == DVec3::ZERO && gn.m == 0.0 {
            return;
        }
        ga += outer(w * gn.mv, dpos);
        sum_wg += w * gn.mv;
        gm += w * (gn.mv.dot(v + *c * dpos) + gn.m);
        gx += st.grad_weight(o, grid.inv_dx) * (gn.mv.dot(mom + a * dpos) + mass * gn.m);
    });
    gx -= a.transpose() * sum_wg;
    P2gGrad {
        x: gx,
        v: sum_wg * mass,
        c: ga * mass,
        tau: ga * (-dt * volume * d_inv),
        mass: gm,
        volume: -dt * d_inv * ddot(&ga, tau),
    }
}
