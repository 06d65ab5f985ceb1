//! Adjoint of P2G, gathered per particle (no races). With `A = −dt V (4/dx²) τ + m C`,
//! `mom = m v + f_ext`, `mv_i += w (mom + A dpos)`, `m_i += w m`:
//! `Ā = Σ w m̄v_i dposᵀ`, `v̄ = m Σ w m̄v_i`, `m̄ = Σ w (m̄v_i·(v + C dpos) + m̄_i)`,
//! `C̄ = m Ā`, `τ̄ = −dt V (4/dx²) Ā`, `V̄ = −dt (4/dx²) Ā:τ`,
//! `x̄ = Σ ∇w (m̄v_i·(mom + A dpos) + m m̄_i) − Aᵀ Σ w m̄v_i`.

use glam::{DMat3, DVec3};

use crate::grid::GridSpec;
use crate::math::ddot;
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

/// Per-particle adjoint of P2G, gathered over the 27 nodes. The sums are arranged around the
/// separable stencil (`w = wx wy wz`, `dpos = (px, py, pz)`): `Ā`'s first two columns are
/// `Σ_i px_i (Σ_jk w m̄v)` and `Σ_j py_j (Σ_ik w m̄v)`, `Σ w m̄v·(C dpos) = C : Ā`, and the
/// weight-gradient terms are summed along z before the x/y factors are applied.
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
    let (sy, dx) = (grid.dims[2], grid.dx);
    let sx = grid.dims[1] * sy;
    let base = grid.linear(st.local);
    let p = [0.0, 1.0, 2.0].map(|o| (DVec3::splat(o) - st.fx) * dx);
    let (mut ga0, mut ga2, mut sum_wg) = (DVec3::ZERO, DVec3::ZERO, DVec3::ZERO);
    let mut by_j = [DVec3::ZERO; 3];
    let (mut sum_wm, mut gx) = (0.0, DVec3::ZERO);
    for i in 0..3 {
        let (wx, dwx, px) = (st.w[i].x, st.dw[i].x, p[i].x);
        let mut s_i = DVec3::ZERO;
        let mom_x = mom + a.x_axis * px;
        for j in 0..3 {
            let (wy, dwy, py) = (st.w[j].y, st.dw[j].y, p[j].y);
            let mom_xy = mom_x + a.y_axis * py;
            let row = base + i * sx + j * sy;
            let row = &g_nodes[row..row + 3];
            let (mut s_ij, mut sw, mut sdw) = (DVec3::ZERO, 0.0, 0.0);
            for k in 0..3 {
                let (wz, dwz, pz) = (st.w[k].z, st.dw[k].z, p[k].z);
                let gn = row[k];
                let u = gn.mv * (wx * wy * wz);
                s_ij += u;
                ga2 += u * pz;
                sum_wm += wx * wy * wz * gn.m;
                // m̄v·(mom + A dpos) + m m̄, the factor of ∇w.
                let t = gn.mv.dot(mom_xy + a.z_axis * pz) + mass * gn.m;
                sw += wz * t;
                sdw += dwz * t;
            }
            s_i += s_ij;
            by_j[j] += s_ij;
            gx += DVec3::new(dwx * wy * sw, wx * dwy * sw, wx * wy * sdw);
        }
        ga0 += s_i * px;
        sum_wg += s_i;
    }
    let ga1 = by_j[0] * p[0].y + by_j[1] * p[1].y + by_j[2] * p[2].y;
    let ga = DMat3::from_cols(ga0, ga1, ga2);
    P2gGrad {
        x: gx * grid.inv_dx - a.transpose() * sum_wg,
        v: sum_wg * mass,
        c: ga * mass,
        tau: ga * (-dt * volume * d_inv),
        mass: v.dot(sum_wg) + ddot(c, &ga) + sum_wm,
        volume: -dt * d_inv * ddot(&ga, tau),
    }
}
