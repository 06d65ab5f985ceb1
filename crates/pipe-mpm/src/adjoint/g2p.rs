//! Adjoint of G2P. With `v_p = Σ w v_i`, `C_p = (4/dx²) Σ w v_i dposᵀ`, `dpos = x_i − x_p`:
//! `v̄_i += w (v̄_p + (4/dx²) C̄_p dpos)` (scattered, coloured) and
//! `x̄_p += Σ ∇w (v_i·v̄_p + (4/dx²) v_iᵀ C̄_p dpos) − (4/dx²) Σ w C̄_pᵀ v_i`, both in one pass
//! over the stencil (run through [`crate::scatter::scatter_with_slabs`]).

use glam::{DMat3, DVec3};

use super::ZWeights;
use crate::g2p::gather;
use crate::grid::GridSpec;
use crate::grid_update::NodeVel;
use crate::isa::{Lanes, WithLanes};

/// The G2P adjoint of one slab's particles, including the position update
/// `x' = hold(x + dt v')`, as a unit of work for [`crate::isa::Isa::run_lanes`]: writes
/// `x̄` of particle `ps[i]` to `out[i]` and scatters the node gradients into `chunk`.
pub(crate) struct G2pAdjoint<'a> {
    pub grid: &'a GridSpec,
    pub vgrid: &'a [NodeVel],
    /// The slab's particles, in processing order.
    pub ps: &'a [u32],
    /// `x̄` per particle of `ps`.
    pub out: &'a mut [DVec3],
    /// Node gradients `v̄_i` of the slab's chunk, starting at x-layer `first`.
    pub chunk: &'a mut [NodeVel],
    pub first: usize,
    pub dt: f64,
    /// Particles closer than this (m) to a domain wall may have been held there.
    pub reach: f64,
    /// Positions and `∂L/∂x'`, `∂L/∂v'`, `∂L/∂C'` of all particles.
    pub x: &'a [DVec3],
    pub gx: &'a [DVec3],
    pub gv: &'a [DVec3],
    pub gc: &'a [DMat3],
}

impl WithLanes for G2pAdjoint<'_> {
    type Output = ();

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) {
        let G2pAdjoint {
            grid,
            vgrid,
            ps,
            out,
            chunk,
            first,
            dt,
            reach,
            x,
            gx,
            gv,
            gc,
        } = self;
        for (&p, o) in ps.iter().zip(out) {
            let p = p as usize;
            let x = x[p];
            // |v'| ≤ max |v_i| (convex weights): far enough from the walls x' was not held
            // (x̄' passes); else redo G2P's exact sum to decide.
            let margin = (x - grid.domain.lo).min(grid.domain.hi - x).min_element();
            let mask = if margin > reach {
                DVec3::ONE
            } else {
                let unclamped = x + dt * gather(l, grid, vgrid, x).0;
                let held = unclamped.clamp(grid.domain.lo, grid.domain.hi);
                DVec3::select(unclamped.cmpeq(held), DVec3::ONE, DVec3::ZERO)
            };
            let gxn = gx[p] * mask;
            let gv = gv[p] + dt * gxn;
            let gx_w = g2p_adjoint_particle(l, grid, vgrid, chunk, first, x, gv, &gc[p]);
            *o = gxn + gx_w;
        }
    }
}

/// Adjoint of G2P for one particle, fused with the scatter of its node gradients: with
/// `y_i = v̄_p + (4/dx²) C̄_p dpos_i` (built axis by axis along the separable stencil),
/// `v̄_i += w_i y_i` into `chunk` (starting at x-layer `first`) and the returned
/// `x̄_p = Σ ∇w_i (v_i·y_i) − (4/dx²) C̄_pᵀ v_p`, `v_p = Σ w_i v_i`.
///
/// Per row `(i, j)`, `y_k = y_ij + pz_k ȳ_z` (ȳ_z the third column of `(4/dx²) C̄`), so the
/// z-sums `Σ_k (wz_k, wz_k pz_k, wz'_k, wz'_k pz_k) v_k` (four lanes each) give both weight
/// terms `Σ wz_k v_k·y_k` and `Σ wz'_k v_k·y_k` with two dot products each.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn g2p_adjoint_particle<L: Lanes>(
    l: L,
    grid: &GridSpec,
    vgrid: &[NodeVel],
    chunk: &mut [NodeVel],
    first: usize,
    x: DVec3,
    gv: DVec3,
    gc: &DMat3,
) -> DVec3 {
    let st = grid.stencil_with(l, x);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let p = st.offsets(grid.dx);
    let gcd = *gc * d_inv;
    let zw = ZWeights::new(l, &st, &p);
    let (gvl, gcx, gcy, gz) = (
        l.load3(gv, 0.0),
        l.load3(gcd.x_axis, 0.0),
        l.load3(gcd.y_axis, 0.0),
        l.load3(gcd.z_axis, 0.0),
    );
    // Node k of a row gets w_xy (wz_k y + wz_k pz_k ȳ_z); the second term is fixed per particle.
    let wz: [L::V; 3] = std::array::from_fn(|k| l.splat(st.w[k].z));
    let gzk: [L::V; 3] = std::array::from_fn(|k| l.mul(gz, l.splat(st.w[k].z * p[k].z)));
    let zero = l.splat(0.0);
    let (mut v, mut gx) = (zero, DVec3::ZERO);
    for i in 0..3 {
        let (wx, dwx) = (st.w[i].x, st.dw[i].x);
        let y_x = l.fma(gcx, l.splat(p[i].x), gvl);
        // x̄ weight terms, factored by i and kept in lanes until the end of the layer:
        // (wx' Σ_j wy a_j, wx Σ_j wy' a_j, wx Σ_j wy b_j), a_j, b_j the rows' products below.
        let (mut acc_x, mut acc_y, mut acc_z) = (zero, zero, zero);
        for (j, pj) in p.iter().enumerate() {
            let (wy, dwy) = (st.w[j].y, st.dw[j].y);
            let y = l.fma(gcy, l.splat(pj.y), y_x);
            let wxy = wx * wy;
            let row = grid.row(vgrid, st.local, i, j);
            let [s, sp, ds, dsp] = zw.row_sums(l, [0, 1, 2].map(|k| l.load(row[k].lanes())));
            let out = grid.row_mut(chunk, first, st.local, i, j);
            let wxy_v = l.splat(wxy);
            for (k, o) in out.iter_mut().enumerate() {
                let yk = l.fma(y, wz[k], gzk[k]);
                *o = NodeVel::from_lanes(l.store(l.fma(yk, wxy_v, l.load(o.lanes()))));
            }
            let a = l.fma(sp, gz, l.mul(s, y));
            let b = l.fma(dsp, gz, l.mul(ds, y));
            let wy_v = l.splat(wy);
            v = l.fma(s, l.splat(wxy), v);
            acc_x = l.fma(a, wy_v, acc_x);
            acc_y = l.fma(a, l.splat(dwy), acc_y);
            acc_z = l.fma(b, wy_v, acc_z);
        }
        let [sx, sy] = l.hsum2(acc_x, acc_y);
        gx += DVec3::new(dwx * sx, wx * sy, wx * l.hsum(acc_z));
    }
    let v = l.store(v);
    gx * grid.inv_dx - gcd.transpose() * DVec3::new(v[0], v[1], v[2])
}
