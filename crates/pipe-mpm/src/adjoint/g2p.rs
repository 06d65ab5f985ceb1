//! Adjoint of G2P. With `v_p = Σ w v_i`, `C_p = (4/dx²) Σ w v_i dposᵀ`, `dpos = x_i − x_p`:
//! `v̄_i += w (v̄_p + (4/dx²) C̄_p dpos)` (scattered, coloured) and
//! `x̄_p += Σ ∇w (v_i·v̄_p + (4/dx²) v_iᵀ C̄_p dpos) − (4/dx²) Σ w C̄_pᵀ v_i`, both in one pass
//! over the stencil (run through [`crate::scatter::scatter_with`]).

use glam::{DMat3, DVec3};

use crate::grid::GridSpec;
use crate::grid_update::NodeVel;

/// Adjoint of G2P for one particle, fused with the scatter of its node gradients: with
/// `y_i = v̄_p + (4/dx²) C̄_p dpos_i` (built axis by axis along the separable stencil),
/// `v̄_i += w_i y_i` into `chunk` (starting at x-layer `first`) and the returned
/// `x̄_p = Σ ∇w_i (v_i·y_i) − (4/dx²) C̄_pᵀ v_p`, `v_p = Σ w_i v_i`.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn g2p_adjoint_particle(
    grid: &GridSpec,
    vgrid: &[NodeVel],
    chunk: &mut [DVec3],
    first: usize,
    x: DVec3,
    gv: DVec3,
    gc: &DMat3,
) -> DVec3 {
    let st = grid.stencil(x);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let p = st.offsets(grid.dx);
    let gcd = *gc * d_inv;
    let (mut v, mut gx) = (DVec3::ZERO, DVec3::ZERO);
    for i in 0..3 {
        let (wx, dwx) = (st.w[i].x, st.dw[i].x);
        let y_x = gv + gcd.x_axis * p[i].x;
        for j in 0..3 {
            let (wy, dwy) = (st.w[j].y, st.dw[j].y);
            let y_xy = y_x + gcd.y_axis * p[j].y;
            let wxy = wx * wy;
            let row = grid.row(vgrid, st.local, i, j);
            let out = grid.row_mut(chunk, first, st.local, i, j);
            let (mut v_ij, mut sw, mut sdw) = (DVec3::ZERO, 0.0, 0.0);
            for k in 0..3 {
                let y = y_xy + gcd.z_axis * p[k].z;
                let vk = row[k].v;
                let t = vk.dot(y);
                v_ij += vk * st.w[k].z;
                sw += st.w[k].z * t;
                sdw += st.dw[k].z * t;
                out[k] += y * (wxy * st.w[k].z);
            }
            v += v_ij * wxy;
            gx += DVec3::new(dwx * wy * sw, wx * dwy * sw, wxy * sdw);
        }
    }
    gx * grid.inv_dx - gcd.transpose() * v
}
