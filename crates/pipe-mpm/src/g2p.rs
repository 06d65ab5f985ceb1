//! Grid to particle: `v_p = Σ w_ip v_i`, `C_p = (4/dx²) Σ w_ip v_i (x_i − x_p)ᵀ`,
//! `x_p ← x_p + dt v_p`, then the position is held inside the domain.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::grid::{GridSpec, Stencil};

/// Gathers `(v, C)` of the particle at `x` from node velocities. Along the separable stencil
/// (`w = wx wy wz`, `dpos = (px, py, pz)`): with `u = w v_i`, `v = Σ u`, and `C`'s columns are
/// `Σ_i px_i Σ_jk u`, `Σ_j py_j Σ_ik u`, `Σ u pz` (times `4/dx²`).
#[inline]
pub(crate) fn gather(grid: &GridSpec, vgrid: &[DVec3], x: DVec3) -> (DVec3, DMat3) {
    let st = grid.stencil(x);
    let d = st.offsets(grid.dx);
    let (mut v, mut c0, mut c2) = (DVec3::ZERO, DVec3::ZERO, DVec3::ZERO);
    let mut by_j = [DVec3::ZERO; 3];
    for i in 0..3 {
        let mut s_i = DVec3::ZERO;
        for (j, b) in by_j.iter_mut().enumerate() {
            let (s_ij, t_ij) = row_sums(&st, grid.row(vgrid, st.local, i, j), i, j, d);
            s_i += s_ij;
            *b += s_ij;
            c2 += t_ij;
        }
        v += s_i;
        c0 += s_i * d[i].x;
    }
    let c1 = by_j[0] * d[0].y + by_j[1] * d[1].y + by_j[2] * d[2].y;
    (
        v,
        DMat3::from_cols(c0, c1, c2) * (4.0 * grid.inv_dx * grid.inv_dx),
    )
}

/// `(Σ_k u_k, Σ_k u_k pz_k)` over the three nodes of row `(i, j)`, `u_k = w_ijk v_k`.
#[inline(always)]
fn row_sums(st: &Stencil, row: &[DVec3], i: usize, j: usize, d: [DVec3; 3]) -> (DVec3, DVec3) {
    let wxy = st.w[i].x * st.w[j].y;
    let (mut s, mut t) = (DVec3::ZERO, DVec3::ZERO);
    for k in 0..3 {
        let u = row[k] * (wxy * st.w[k].z);
        s += u;
        t += u * d[k].z;
    }
    (s, t)
}

/// New `x, v, C` of every particle from the old positions `x_old` (`None`: `x` itself, updated
/// in place); returns the number held at the domain edge and whether any new value is NaN/Inf.
pub(crate) fn g2p(
    grid: &GridSpec,
    vgrid: &[DVec3],
    dt: f64,
    x_old: Option<&[DVec3]>,
    x: &mut [DVec3],
    v: &mut [DVec3],
    c: &mut [DMat3],
) -> (usize, bool) {
    x.par_iter_mut()
        .zip(v.par_iter_mut())
        .zip(c.par_iter_mut())
        .enumerate()
        .map(|(p, ((xp, vp), cp))| {
            let x0 = x_old.map_or(*xp, |xo| xo[p]);
            let (vn, cn) = gather(grid, vgrid, x0);
            *vp = vn;
            *cp = cn;
            *xp = x0 + dt * vn;
            let held = grid.hold(xp);
            (
                usize::from(held),
                !(xp.is_finite() && vn.is_finite() && cn.is_finite()),
            )
        })
        .reduce(|| (0, false), |a, b| (a.0 + b.0, a.1 | b.1))
}
