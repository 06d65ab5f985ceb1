//! Grid to particle: `v_p = Σ w_ip v_i`, `C_p = (4/dx²) Σ w_ip v_i (x_i − x_p)ᵀ`,
//! `x_p ← x_p + dt v_p`, then the position is held inside the domain.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::grid::GridSpec;
use crate::grid_update::NodeVel;
use crate::isa::{Isa, Lanes, WithLanes};

/// Particles per parallel task of [`g2p`].
const CHUNK: usize = 1024;

/// Gathers `(v, C)` of the particle at `x` from node velocities. Along the separable stencil
/// (`w = wx wy wz`, `dpos = (px, py, pz)`), per row `(i, j)`: `r = Σ_k wz_k v_k` and
/// `u = Σ_k wz_k pz_k v_k`; then `v = Σ_i wx_i Σ_j wy_j r`, and `C`'s columns are
/// `Σ_i wx_i px_i Σ_j wy_j r`, `Σ_j wy_j py_j Σ_i wx_i r` and `Σ_ij wx_i wy_j u` (times
/// `4/dx²`). Four lanes per node (the fourth is 0) and fused multiply-adds throughout, so the
/// result is the same with any [`Lanes`] and on every CPU.
#[inline(always)]
pub(crate) fn gather<L: Lanes>(
    l: L,
    grid: &GridSpec,
    vgrid: &[NodeVel],
    x: DVec3,
) -> (DVec3, DMat3) {
    let st = grid.stencil_with(l, x);
    let d = st.offsets(grid.dx);
    let wz = [st.w[0].z, st.w[1].z, st.w[2].z].map(|w| l.splat(w));
    let wzpz: [L::V; 3] = std::array::from_fn(|k| l.splat(st.w[k].z * d[k].z));
    let zero = l.splat(0.0);
    let (mut v, mut c0, mut c2) = (zero, zero, zero);
    let mut by_j = [zero; 3];
    for (i, (di, wi)) in d.iter().zip(st.w).enumerate() {
        let (mut r_i, mut u_i) = (zero, zero);
        for (j, b) in by_j.iter_mut().enumerate() {
            let row = grid.row(vgrid, st.local, i, j);
            let n = [0, 1, 2].map(|k| l.load(row[k].lanes()));
            let r = l.fma(n[2], wz[2], l.fma(n[1], wz[1], l.mul(n[0], wz[0])));
            let u = l.fma(n[2], wzpz[2], l.fma(n[1], wzpz[1], l.mul(n[0], wzpz[0])));
            let wy = st.w[j].y;
            r_i = l.fma(r, l.splat(wy), r_i);
            u_i = l.fma(u, l.splat(wy), u_i);
            *b = l.fma(r, l.splat(wi.x * wy), *b);
        }
        v = l.fma(r_i, l.splat(wi.x), v);
        c0 = l.fma(r_i, l.splat(wi.x * di.x), c0);
        c2 = l.fma(u_i, l.splat(wi.x), c2);
    }
    let c1 = l.fma(
        by_j[2],
        l.splat(d[2].y),
        l.fma(by_j[1], l.splat(d[1].y), l.mul(by_j[0], l.splat(d[0].y))),
    );
    let s = 4.0 * grid.inv_dx * grid.inv_dx;
    let col = |a: L::V| {
        let a = l.store(a);
        DVec3::new(a[0] * s, a[1] * s, a[2] * s)
    };
    let v = l.store(v);
    (
        DVec3::new(v[0], v[1], v[2]),
        DMat3::from_cols(col(c0), col(c1), col(c2)),
    )
}

/// New `x, v, C` of every particle from the old positions `x_old` (`None`: `x` itself, updated
/// in place); returns the number held at the domain edge and whether any new value is NaN/Inf.
pub(crate) fn g2p(
    grid: &GridSpec,
    vgrid: &[NodeVel],
    dt: f64,
    x_old: Option<&[DVec3]>,
    x: &mut [DVec3],
    v: &mut [DVec3],
    c: &mut [DMat3],
) -> (usize, bool) {
    let isa = Isa::detect();
    x.par_chunks_mut(CHUNK)
        .zip(v.par_chunks_mut(CHUNK))
        .zip(c.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(k, ((x, v), c))| {
            isa.run_lanes(Chunk {
                grid,
                vgrid,
                dt,
                x_old: x_old.map(|xo| &xo[k * CHUNK..k * CHUNK + x.len()]),
                x,
                v,
                c,
            })
        })
        .reduce(|| (0, false), |a, b| (a.0 + b.0, a.1 | b.1))
}

/// G2P of one chunk of particles.
struct Chunk<'a> {
    grid: &'a GridSpec,
    vgrid: &'a [NodeVel],
    dt: f64,
    x_old: Option<&'a [DVec3]>,
    x: &'a mut [DVec3],
    v: &'a mut [DVec3],
    c: &'a mut [DMat3],
}

impl WithLanes for Chunk<'_> {
    type Output = (usize, bool);

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) -> (usize, bool) {
        let (mut held, mut bad) = (0, false);
        for (p, ((xp, vp), cp)) in self.x.iter_mut().zip(self.v).zip(self.c).enumerate() {
            // Read the old position straight from its array: a copy made by `map_or` was
            // reloaded across two stores (a failed store-to-load forward, ~10 % of G2P).
            let src: &DVec3 = match self.x_old {
                Some(xo) => &xo[p],
                None => xp,
            };
            let x0 = DVec3::new(src.x, src.y, src.z);
            let (vn, cn) = gather(l, self.grid, self.vgrid, x0);
            *vp = vn;
            *cp = cn;
            *xp = x0 + self.dt * vn;
            held += usize::from(self.grid.hold(xp));
            bad |= !(xp.is_finite() && vn.is_finite() && cn.is_finite());
        }
        (held, bad)
    }
}
