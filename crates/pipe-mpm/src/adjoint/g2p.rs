//! Adjoint of G2P. With `v_p = Σ w v_i`, `C_p = (4/dx²) Σ w v_i dposᵀ`, `dpos = x_i − x_p`:
//! `v̄_i += w (v̄_p + (4/dx²) C̄_p dpos)` (scattered, coloured) and
//! `x̄_p += Σ ∇w (v_i·v̄_p + (4/dx²) v_iᵀ C̄_p dpos) − (4/dx²) Σ w C̄_pᵀ v_i`.

use glam::{DMat3, DVec3};

use crate::grid::GridSpec;
use crate::scatter::{Bins, scatter};

/// Gradient of the particle position through the weights and offsets of G2P.
#[inline]
pub(crate) fn position_grad(
    grid: &GridSpec,
    vgrid: &[DVec3],
    x: DVec3,
    gv: DVec3,
    gc: &DMat3,
) -> DVec3 {
    let st = grid.stencil(x);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let mut gx = DVec3::ZERO;
    let mut sum_wv = DVec3::ZERO;
    st.for_each_node(grid, 0, |o, i, w, dpos| {
        let vi = vgrid[i];
        let s = vi.dot(gv) + d_inv * vi.dot(*gc * dpos);
        gx += st.grad_weight(o, grid.inv_dx) * s;
        sum_wv += w * vi;
    });
    gx - gc.transpose() * sum_wv * d_inv
}

/// Scatters `v̄_i` from the particles' `v̄_p`, `C̄_p` (into a zeroed `g_vgrid`).
pub(crate) fn scatter_node_grads(
    grid: &GridSpec,
    bins: &Bins,
    x: &[DVec3],
    gv: &[DVec3],
    gc: &[DMat3],
    g_vgrid: &mut Vec<DVec3>,
) {
    g_vgrid.clear();
    g_vgrid.resize(grid.len(), DVec3::ZERO);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    scatter(grid, bins, g_vgrid, |p, chunk, first| {
        let st = grid.stencil(x[p]);
        st.for_each_node(grid, first, |_, i, w, dpos| {
            chunk[i] += w * (gv[p] + d_inv * (gc[p] * dpos));
        });
    });
}
