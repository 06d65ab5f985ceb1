//! Grid to particle: `v_p = Σ w_ip v_i`, `C_p = (4/dx²) Σ w_ip v_i (x_i − x_p)ᵀ`,
//! `x_p ← x_p + dt v_p`, then the position is held inside the domain.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::grid::GridSpec;
use crate::math::outer;

/// Gathers `(v, C)` of the particle at `x` from node velocities.
#[inline]
pub(crate) fn gather(grid: &GridSpec, vgrid: &[DVec3], x: DVec3) -> (DVec3, DMat3) {
    let st = grid.stencil(x);
    let mut v = DVec3::ZERO;
    let mut c = DMat3::ZERO;
    st.for_each_node(grid, 0, |_, i, w, dpos| {
        let vi = vgrid[i];
        v += w * vi;
        c += outer(w * vi, dpos);
    });
    (v, c * (4.0 * grid.inv_dx * grid.inv_dx))
}

/// New `x, v, C` of every particle; returns the number of particles held at the domain edge.
pub(crate) fn g2p(
    grid: &GridSpec,
    vgrid: &[DVec3],
    x: &[DVec3],
    dt: f64,
    x_out: &mut [DVec3],
    v_out: &mut [DVec3],
    c_out: &mut [DMat3],
) -> usize {
    x_out
        .par_iter_mut()
        .zip(v_out.par_iter_mut())
        .zip(c_out.par_iter_mut())
        .enumerate()
        .map(|(p, ((xo, vo), co))| {
            let (v, c) = gather(grid, vgrid, x[p]);
            *vo = v;
            *co = c;
            *xo = x[p] + dt * v;
            usize::from(grid.hold(xo))
        })
        .sum()
}
