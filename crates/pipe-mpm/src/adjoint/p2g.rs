//! Adjoint of P2G, gathered per particle (no races). With `A = −dt V (4/dx²) τ + m C`,
//! `mom = m v + f_ext`, `mv_i += w (mom + A dpos)`, `m_i += w m`:
//! `Ā = Σ w m̄v_i dposᵀ`, `v̄ = m Σ w m̄v_i`, `m̄ = Σ w (m̄v_i·(v + C dpos) + m̄_i)`,
//! `C̄ = m Ā`, `τ̄ = −dt V (4/dx²) Ā`, `V̄ = −dt (4/dx²) Ā:τ`,
//! `x̄ = Σ ∇w (m̄v_i·(mom + A dpos) + m m̄_i) − Aᵀ Σ w m̄v_i`.

use glam::{DMat3, DVec3};

use super::ZWeights;
use crate::grid::GridSpec;
use crate::isa::{Lanes, WithLanes};
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

/// [`p2g_adjoint_particle`] as a unit of work for [`crate::isa::Isa::run`].
pub(crate) struct P2gAdjoint<'a> {
    pub grid: &'a GridSpec,
    pub g_nodes: &'a [Node],
    pub dt: f64,
    pub x: DVec3,
    pub v: DVec3,
    pub c: &'a DMat3,
    pub tau: &'a DMat3,
    pub mass: f64,
    pub volume: f64,
    pub extra: DVec3,
}

impl WithLanes for P2gAdjoint<'_> {
    type Output = P2gGrad;

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) -> P2gGrad {
        p2g_adjoint_particle(l, &self)
    }
}

/// Per-particle adjoint of P2G, gathered over the 27 nodes. The sums are arranged around the
/// separable stencil (`w = wx wy wz`, `dpos = (px, py, pz)`): `Ā`'s first two columns are
/// `Σ_i px_i (Σ_jk w m̄v)` and `Σ_j py_j (Σ_ik w m̄v)`, `Σ w m̄v·(C dpos) = C : Ā`. Per row
/// `(i, j)` the z-sums `Σ_k (wz_k, wz_k pz_k, wz'_k, wz'_k pz_k) (m̄v_k, m̄_k)` (four lanes
/// each) give the weight-gradient factors `Σ_k wz_k t_k` and `Σ_k wz'_k t_k` of
/// `t_k = m̄v_k·(mom_ij + A₂ pz_k) + m m̄_k` with two dot products each.
#[inline(always)]
pub(crate) fn p2g_adjoint_particle<L: Lanes>(l: L, inp: &P2gAdjoint<'_>) -> P2gGrad {
    let P2gAdjoint {
        grid,
        g_nodes,
        dt,
        x,
        v,
        c,
        tau,
        mass,
        volume,
        extra,
    } = *inp;
    let st = grid.stencil_with(l, x);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let a = affine(grid, dt, volume, mass, tau, c);
    let mom = v * mass + extra;
    let p = st.offsets(grid.dx);
    let zw = ZWeights::new(l, &st, &p);
    let (ax, ay, az) = (
        l.load3(a.x_axis, 0.0),
        l.load3(a.y_axis, 0.0),
        l.load3(a.z_axis, 0.0),
    );
    let mom4 = l.load3(mom, mass);
    let zero = l.splat(0.0);
    let (mut ga0, mut ga2, mut sum_wg) = (zero, zero, zero);
    let mut by_j = [zero; 3];
    let mut gx = DVec3::ZERO;
    for i in 0..3 {
        let (wx, dwx, px) = (st.w[i].x, st.dw[i].x, p[i].x);
        let mut s_i = zero;
        let mut gx_i = DVec3::ZERO;
        let mom_x = l.fma(ax, l.splat(px), mom4);
        for (j, b) in by_j.iter_mut().enumerate() {
            let (wy, dwy, py) = (st.w[j].y, st.dw[j].y, p[j].y);
            // (mom + A dpos_xy, m): the mass lane is 0·p + m = m.
            let m4 = l.fma(ay, l.splat(py), mom_x);
            let row = grid.row(g_nodes, st.local, i, j);
            let [s, sp, ds, dsp] = zw.row_sums(l, [0, 1, 2].map(|k| l.load(row[k].lanes())));
            // Σ_k wz_k t_k = s·(mom_ij, m) + sp·(A₂, 0), likewise with wz'.
            let [sw, sdw] = l.hsum2(l.fma(sp, az, l.mul(s, m4)), l.fma(dsp, az, l.mul(ds, m4)));
            let wxy = wx * wy;
            s_i = l.fma(s, l.splat(wy), s_i);
            *b = l.fma(s, l.splat(wxy), *b);
            ga2 = l.fma(sp, l.splat(wxy), ga2);
            // x̄ weight terms, factored by i: (wx' Σ_j wy sw, wx Σ_j wy' sw, wx Σ_j wy sdw).
            gx_i = DVec3::new(
                wy.mul_add(sw, gx_i.x),
                dwy.mul_add(sw, gx_i.y),
                wy.mul_add(sdw, gx_i.z),
            );
        }
        gx += DVec3::new(dwx * gx_i.x, wx * gx_i.y, wx * gx_i.z);
        ga0 = l.fma(s_i, l.splat(wx * px), ga0);
        sum_wg = l.fma(s_i, l.splat(wx), sum_wg);
    }
    let ga1 = l.fma(
        by_j[2],
        l.splat(p[2].y),
        l.fma(by_j[1], l.splat(p[1].y), l.mul(by_j[0], l.splat(p[0].y))),
    );
    let v3 = |a: L::V| {
        let a = l.store(a);
        DVec3::new(a[0], a[1], a[2])
    };
    let ga = DMat3::from_cols(v3(ga0), v3(ga1), v3(ga2));
    let sum_wm = l.store(sum_wg)[3];
    let sum_wg = v3(sum_wg);
    P2gGrad {
        x: gx * grid.inv_dx - a.transpose() * sum_wg,
        v: sum_wg * mass,
        c: ga * mass,
        tau: ga * (-dt * volume * d_inv),
        mass: v.dot(sum_wg) + ddot(c, &ga) + sum_wm,
        volume: -dt * d_inv * ddot(&ga, tau),
    }
}
