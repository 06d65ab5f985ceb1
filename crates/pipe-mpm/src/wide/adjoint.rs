//! Reverse mode of the vectorised substep, kernel by kernel (the equations of
//! [`crate::adjoint`]'s scalar kernels, on particle groups):
//!
//! * G2P: `y_i = v̄' + (4/dx²) C̄' (x_i − x_p)`, `v̄_i += w y_i` (a scatter, coloured like P2G),
//!   `x̄ = x̄'(not held) + Σ ∇w (v_i·y_i) − (4/dx²) C̄'ᵀ v'`, with `v̄' ← v̄' + dt x̄'(not held)`;
//! * the grid update: `m̄v = B̄(v̄)/m`, `m̄ = −B̄(v̄)·mv/m²`;
//! * P2G (a gather): `Ā = Σ w m̄v dᵀ`, `ḡ = Σ w m̄v`, `x̄ += Σ ∇w (m̄v·(mom + A d) + m m̄) − Aᵀ ḡ`;
//! * then, per particle: `v̄ = m ḡ`, `C̄ = m Ā + …`, `τ̄ = −dt V (4/dx²) Ā`,
//!   `m̄ += v·ḡ + C:Ā + Σ w m̄_i`, `V̄ += −dt (4/dx²) Ā:τ`, and the model's adjoint with the
//!   strain prediction's.
//!
//! Both transfers run small groups two to a vector as their forward kernels do
//! ([`super::transfer`]): the G2P adjoint pairs a slab's small groups in order (it scatters
//! like P2G), the P2G adjoint pairs neighbouring ones (it writes per slot like G2P).

use glam::DMat3;

use super::groups::Group;
use super::simd::{Real, Wide, WideOp};
use super::stress::{
    Mat, SlotMaterial, cofactor, ddot, det_with, lane_of, mul, mul_at, mul_bt, polar, predict,
};
use super::transfer::{
    self, Axis, SlotStores, Units, gather_unit, load_unit, splat_unit, unit_momentum, weights,
};
use crate::boundary::Boundaries;
use crate::grid::{GridSpec, NodeBox};
use crate::grid_update::mass_threshold;
use crate::math::{from_rows, to_rows};
use crate::models::{Constitutive, LaneKernel, particle_model};
use crate::state::FamilyGrad;
use crate::svd::{polar_rotation_adjoint, rotation_adjoint, svd3};

/// `d w_a / d fx` of the quadratic B-spline on one axis: `fx − 1.5`, `−2 (fx − 1)`, `fx − 0.5`.
#[inline(always)]
fn dweights<W: Wide>(w: W, fx: W::V) -> [W::V; 3] {
    [
        w.sub(fx, w.c(1.5)),
        w.mul(w.c(-2.0), w.sub(fx, w.c(1.0))),
        w.sub(fx, w.c(0.5)),
    ]
}

/// The G2P adjoint of one slab's groups: node gradients `v̄_i` scattered into its grid piece
/// (from x-layer `first`, `[v̄x, v̄y, v̄z, 0]` per node) and each group's `x̄` (lanes) into
/// `out_x` (one entry per group of the slab).
pub(crate) struct G2pAdjTask<'a, T> {
    pub grid: &'a GridSpec,
    pub groups: &'a [Group],
    /// Positions at the start of the substep.
    pub x: [&'a [T]; 3],
    /// `∂L/∂x'`, `∂L/∂v'`, `∂L/∂C'` of the substep's results.
    pub gx: [&'a [T]; 3],
    pub gv: [&'a [T]; 3],
    pub gc: [&'a [T]; 9],
    /// Node velocities `[v, 0]` of the forward substep.
    pub vgrid: &'a [T],
    pub dt: f64,
    /// The domain (relative to the grid's first node, as the forward pass holds it) and the
    /// farthest a particle can move in the substep (m): farther from the walls, no particle
    /// was held.
    pub lo: [T; 3],
    pub hi: [T; 3],
    pub reach: T,
    pub piece: &'a mut [[T; 4]],
    pub first: usize,
    pub out_x: &'a mut [[[T; 8]; 3]],
}

impl<T: Real> WideOp<T> for G2pAdjTask<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with<W: Wide<T = T>>(mut self, w: W) {
        // It scatters like P2G: any two small groups of the slab can pair.
        for u in Units::in_order(self.groups, T::N) {
            match u.b {
                Some(b) => self.unit::<W, true>(w, u.a, b),
                None => self.unit::<W, false>(w, u.a, u.a),
            }
        }
    }
}

impl<T: Real> G2pAdjTask<'_, T> {
    /// The G2P adjoint of the slab's group `ia`, or (`PAIR`) of groups `ia < ib` in the two
    /// halves of one vector.
    #[inline(always)]
    fn unit<W: Wide<T = T>, const PAIR: bool>(&mut self, w: W, ia: usize, ib: usize) {
        let (grid, x, gx, gv, gc, vgrid) =
            (self.grid, self.x, self.gx, self.gv, self.gc, self.vgrid);
        let (ga, gb) = (&self.groups[ia], &self.groups[ib]);
        let off = self.first * grid.layer();
        let inv = w.c(grid.inv_dx);
        let c4 = w.c(4.0 * grid.inv_dx);
        let dtv = w.c(self.dt);
        let (lov, hiv) = (
            arr!(3, |a| w.splat(self.lo[a])),
            arr!(3, |a| w.splat(self.hi[a])),
        );
        let zero = w.zero();
        let (sa, sb) = (ga.start as usize, gb.start as usize);
        let (na, nb) = (ga.n as usize, gb.n as usize);
        let h = T::N / 2;
        let (xv, base_a, base_b, st, dw) = stencil_with_derivatives::<W, PAIR>(w, grid, ga, gb, x);
        // Which components were held at the walls (x̄' stops there): only near a wall.
        let mut margin = w.c(f64::MAX);
        for a in 0..3 {
            margin = w.min(margin, w.min(w.sub(xv[a], lov[a]), w.sub(hiv[a], xv[a])));
        }
        let margins = w.lanes(margin);
        let reach = self.reach;
        let close = |m: &T| m.partial_cmp(&reach) != Some(std::cmp::Ordering::Greater);
        let near = if PAIR {
            margins[..na].iter().any(close) || margins[h..h + nb].iter().any(close)
        } else {
            margins[..na].iter().any(close)
        };
        let gxp: [W::V; 3] = arr!(3, |a| load_unit::<W, PAIR>(w, gx[a], sa, sb));
        let gxm: [W::V; 3] = if near {
            let (vel, _) = gather_unit::<W, PAIR>(w, grid, vgrid, base_a, base_b, &st);
            arr!(3, |a| {
                let xn = w.fma(dtv, vel[a], xv[a]);
                let held = w.min(w.max(xn, lov[a]), hiv[a]);
                let free = !w.ne_mask(held, xn);
                let m = arr!(8, |l| T::of(f64::from(u8::from(free & (1 << l) != 0))));
                w.mul(gxp[a], w.vector(m))
            })
        } else {
            gxp
        };
        let vbar: [W::V; 3] = arr!(3, |r| w.fma(
            dtv,
            gxm[r],
            load_unit::<W, PAIR>(w, gv[r], sa, sb)
        ));
        let gm: Mat<W> = arr!(9, |k| w.mul(c4, load_unit::<W, PAIR>(w, gc[k], sa, sb)));
        let (e0, e1, e2) = (st[0].1, st[1].1, st[2].1);
        let (w0, w1, w2) = (st[0].0, st[1].0, st[2].0);
        // Lanes past the group(s) scatter nothing.
        let w0m: [W::V; 3] = arr!(3, |i| {
            if PAIR {
                w.keep_halves(w0[i], na, nb)
            } else {
                w.keep_first(w0[i], na)
            }
        });
        // y = v̄ + G (e0_a, e1_b, e2_c): the z part per node, the x part per layer.
        let yz: [[W::V; 3]; 3] = arr!(3, |k| arr!(3, |r| w.mul(gm[3 * r + 2], e2[k])));
        let wyz: [[W::V; 3]; 3] = arr!(3, |k| arr!(3, |r| w.mul(w2[k], yz[k][r])));
        let (mut px, mut py, mut pz) = (zero, zero, zero);
        let mut vsum = [zero; 3];
        let piece = &mut *self.piece;
        for i in 0..3 {
            let yx: [W::V; 3] = arr!(3, |r| w.fma(gm[3 * r], e0[i], vbar[r]));
            for j in 0..3 {
                let yab: [W::V; 3] = arr!(3, |r| w.fma(gm[3 * r + 1], e1[j], yx[r]));
                let wab = w.mul(w0m[i], w1[j]);
                let row_a = grid.linear([base_a[0] + i, base_a[1] + j, base_a[2]]);
                let row_b = grid.linear([base_b[0] + i, base_b[1] + j, base_b[2]]);
                let (vn_a, vn_b) = (
                    &vgrid[4 * row_a..4 * row_a + 12],
                    &vgrid[4 * row_b..4 * row_b + 12],
                );
                let (mut s_w, mut s_dw) = (zero, zero);
                let mut sv = [zero; 3];
                let mut contrib = [[zero; 4]; 3];
                for k in 0..3 {
                    let v: [W::V; 3] = arr!(3, |r| splat_unit::<W, PAIR>(
                        w,
                        vn_a[4 * k + r],
                        vn_b[4 * k + r]
                    ));
                    let y: [W::V; 3] = arr!(3, |r| w.add(yab[r], yz[k][r]));
                    // w y = wab (w2 yab + w2 yz).
                    contrib[k] = [
                        w.mul(wab, w.fma(w2[k], yab[0], wyz[k][0])),
                        w.mul(wab, w.fma(w2[k], yab[1], wyz[k][1])),
                        w.mul(wab, w.fma(w2[k], yab[2], wyz[k][2])),
                        zero,
                    ];
                    let dot = w.fma(v[2], y[2], w.fma(v[1], y[1], w.mul(v[0], y[0])));
                    s_w = w.fma(w2[k], dot, s_w);
                    s_dw = w.fma(dw[2][k], dot, s_dw);
                    for r in 0..3 {
                        sv[r] = w.fma(w2[k], v[r], sv[r]);
                    }
                }
                if PAIR {
                    for (k, [c0, c1, c2, c3]) in contrib.into_iter().enumerate() {
                        let (sum_a, sum_b) = w.reduce4_halves(c0, c1, c2, c3);
                        w.add4(sum_a, &mut piece[row_a - off + k]);
                        w.add4(sum_b, &mut piece[row_b - off + k]);
                    }
                } else {
                    let local = row_a - off;
                    let (pair, last) = piece[local..local + 3].split_at_mut(2);
                    let pair: &mut [T; 8] = bytemuck::cast_slice_mut::<[T; 4], T>(pair)
                        .try_into()
                        .expect("8");
                    w.reduce4_add_pair(contrib[0], contrib[1], pair);
                    let c2 = contrib[2];
                    w.reduce4_add(c2[0], c2[1], c2[2], c2[3], &mut last[0]);
                }
                px = w.fma(w.mul(dw[0][i], w1[j]), s_w, px);
                py = w.fma(w.mul(w0[i], dw[1][j]), s_w, py);
                let w01 = w.mul(w0[i], w1[j]);
                pz = w.fma(w01, s_dw, pz);
                for r in 0..3 {
                    vsum[r] = w.fma(w01, sv[r], vsum[r]);
                }
            }
        }
        // x̄ = x̄'(free) + (1/dx) Σ ∇w (v·y) − (1/dx) Gᵀ v'.
        let p = [px, py, pz];
        let (head, tail) = self.out_x.split_at_mut(ib);
        for d in 0..3 {
            let gtv = w.fma(
                gm[6 + d],
                vsum[2],
                w.fma(gm[3 + d], vsum[1], w.mul(gm[d], vsum[0])),
            );
            let lanes = w.lanes(w.add(gxm[d], w.mul(inv, w.sub(p[d], gtv))));
            if PAIR {
                head[ia][d] = lanes;
                tail[0][d][..h].copy_from_slice(&lanes[h..2 * h]);
            } else {
                tail[0][d] = lanes;
            }
        }
    }
}

/// A unit's positions, stencil bases, weights with node offsets and weight derivatives
/// ([`transfer::unit_stencil`]).
#[inline(always)]
#[allow(clippy::type_complexity)]
fn stencil_with_derivatives<W: Wide, const PAIR: bool>(
    w: W,
    grid: &GridSpec,
    ga: &Group,
    gb: &Group,
    x: [&[W::T]; 3],
) -> (
    [W::V; 3],
    [usize; 3],
    [usize; 3],
    [Axis<W>; 3],
    [[W::V; 3]; 3],
) {
    let (xv, base_a, base_b, fx) = transfer::unit_stencil::<W, PAIR>(w, grid, ga, gb, x);
    let st: [Axis<W>; 3] = arr!(3, |a| weights(w, fx[a]));
    let dw: [[W::V; 3]; 3] = arr!(3, |a| dweights(w, fx[a]));
    (xv, base_a, base_b, st, dw)
}

/// Node gradients `(m̄v, m̄)` (`[m̄v, m̄]` per node) from `v̄` (`[v̄, 0]`), for the nodes of
/// `active`: `m̄v = B̄(v̄)/m`, `m̄ = −B̄(v̄)·mv/m²` above the mass threshold, 0 below (`B̄` the
/// boundary conditions' adjoint, in `f64`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn grid_update_adjoint<T: Real>(
    grid: &GridSpec,
    nodes: &[[T; 4]],
    g_vgrid: &[[T; 4]],
    active: &NodeBox,
    dt: f64,
    g: glam::DVec3,
    bc: &Boundaries,
    out: &mut Vec<[T; 4]>,
) {
    use rayon::prelude::*;
    let thr = mass_threshold(grid.dx);
    out.resize(grid.len(), [T::of(0.0); 4]);
    let (layer, dz) = (grid.layer(), grid.dims[2]);
    let clear = bc.clear_axes(grid);
    out.par_chunks_mut(layer)
        .zip(nodes.par_chunks(layer))
        .zip(g_vgrid.par_chunks(layer))
        .enumerate()
        .skip(active.x.start)
        .take(active.x.len())
        .for_each(|(x, ((out, nodes), gv))| {
            for y in active.y.clone() {
                let row = y * dz + active.z.start..y * dz + active.z.end;
                let zs = active.z.clone();
                let clear_z = clear.as_ref().filter(|c| c[0][x] && c[1][y]).map(|c| &c[2]);
                for (z, ((o, n), gv)) in zs.zip(
                    out[row.clone()]
                        .iter_mut()
                        .zip(&nodes[row.clone()])
                        .zip(&gv[row]),
                ) {
                    let m = n[3].f64();
                    let gvel = glam::DVec3::new(gv[0].f64(), gv[1].f64(), gv[2].f64());
                    *o = if m > thr && gvel != glam::DVec3::ZERO {
                        let mv = glam::DVec3::new(n[0].f64(), n[1].f64(), n[2].f64());
                        let v = mv / m + dt * g;
                        let gpre = if clear_z.is_some_and(|c| c[z]) {
                            gvel
                        } else {
                            bc.adjoint(grid, grid.node_pos([x, y, z]), v, gvel)
                        };
                        let gmv = gpre / m;
                        let gm = -gpre.dot(mv) / (m * m);
                        [T::of(gmv.x), T::of(gmv.y), T::of(gmv.z), T::of(gm)]
                    } else {
                        [T::of(0.0); 4]
                    };
                }
            }
        });
}

/// Outputs of the P2G adjoint for one task's slots (from `s0`): `x̄` (added), `ḡ = Σ w m̄v`,
/// `Ā` and `Σ w m̄_i`.
pub(crate) struct P2gAdjOut<'a, T> {
    pub gx: [&'a mut [T]; 3],
    pub sg: [&'a mut [T]; 3],
    pub abar: [&'a mut [T]; 9],
    pub sm: &'a mut [T],
}

/// The P2G adjoint of one task's groups (a gather from the node gradients `[m̄v, m̄]`).
pub(crate) struct P2gAdjTask<'a, T> {
    pub grid: &'a GridSpec,
    pub groups: &'a [Group],
    pub s0: usize,
    pub x: [&'a [T]; 3],
    pub v: [&'a [T]; 3],
    pub a: [&'a [T]; 9],
    /// Per-particle mass, or one value for all (`uniform_mass`).
    pub mass: &'a [T],
    pub uniform_mass: bool,
    pub extra: Option<[&'a [T]; 3]>,
    pub gnodes: &'a [T],
    pub out: P2gAdjOut<'a, T>,
}

impl<T: Real> WideOp<T> for P2gAdjTask<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with<W: Wide<T = T>>(mut self, w: W) {
        // It stores per slot like G2P: only neighbouring small groups pair.
        let groups = self.groups;
        for u in Units::neighbours(groups, T::N) {
            let ga = &groups[u.a];
            match u.b {
                Some(b) => self.unit::<W, true>(w, ga, &groups[b], u.last),
                None => self.unit::<W, false>(w, ga, ga, u.last),
            }
        }
    }
}

impl<T: Real> P2gAdjTask<'_, T> {
    /// The P2G adjoint of group `ga`, or (`PAIR`) of `ga` and the group `gb` right after it
    /// in the two halves of one vector; `last` when no group of the task follows.
    #[inline(always)]
    fn unit<W: Wide<T = T>, const PAIR: bool>(&mut self, w: W, ga: &Group, gb: &Group, last: bool) {
        let (grid, x, v, a, gnodes) = (self.grid, self.x, self.v, self.a, self.gnodes);
        let dx = w.c(grid.dx);
        let inv = w.c(grid.inv_dx);
        let zero = w.zero();
        let (sa, sb) = (ga.start as usize, gb.start as usize);
        let (na, nb) = (ga.n as usize, gb.n as usize);
        let h = T::N / 2;
        let o = sa - self.s0;
        let (_, base_a, base_b, st, dw) = stencil_with_derivatives::<W, PAIR>(w, grid, ga, gb, x);
        let am: Mat<W> = arr!(9, |k| load_unit::<W, PAIR>(w, a[k], sa, sb));
        let (m, mom) =
            unit_momentum::<W, PAIR>(w, self.mass, self.uniform_mass, v, self.extra, sa, sb);
        let (e0, e1, e2) = (st[0].1, st[1].1, st[2].1);
        let (w0, w1, w2) = (st[0].0, st[1].0, st[2].0);
        // A d = dx (A₀ e0 + A₁ e1 + A₂ e2); the z column per node.
        let ax: [W::V; 3] = arr!(3, |r| w.mul(dx, am[3 * r]));
        let ay: [W::V; 3] = arr!(3, |r| w.mul(dx, am[3 * r + 1]));
        let az: [W::V; 3] = arr!(3, |r| w.mul(dx, am[3 * r + 2]));
        let we2: [W::V; 3] = arr!(3, |k| w.mul(w2[k], e2[k]));
        let (mut px, mut py, mut pz) = (zero, zero, zero);
        let mut sgv = [zero; 3];
        let mut smv = zero;
        let mut ab = [zero; 9];
        for i in 0..3 {
            let qa: [W::V; 3] = arr!(3, |r| w.fma(ax[r], e0[i], mom[r]));
            let mut u = [zero; 3];
            for j in 0..3 {
                let q: [W::V; 3] = arr!(3, |r| w.fma(ay[r], e1[j], qa[r]));
                let row_a = grid.linear([base_a[0] + i, base_a[1] + j, base_a[2]]);
                let row_b = grid.linear([base_b[0] + i, base_b[1] + j, base_b[2]]);
                let gn_a = &gnodes[4 * row_a..4 * row_a + 12];
                let gn_b = &gnodes[4 * row_b..4 * row_b + 12];
                let (mut sr, mut se) = ([zero; 3], [zero; 3]);
                let (mut smr, mut s_w, mut s_dw) = (zero, zero, zero);
                for k in 0..3 {
                    let gmv: [W::V; 3] = arr!(3, |r| splat_unit::<W, PAIR>(
                        w,
                        gn_a[4 * k + r],
                        gn_b[4 * k + r]
                    ));
                    let gmm = splat_unit::<W, PAIR>(w, gn_a[4 * k + 3], gn_b[4 * k + 3]);
                    for r in 0..3 {
                        sr[r] = w.fma(w2[k], gmv[r], sr[r]);
                        se[r] = w.fma(we2[k], gmv[r], se[r]);
                    }
                    smr = w.fma(w2[k], gmm, smr);
                    // t = m̄v·(mom + A d) + m m̄.
                    let dq = w.fma(gmv[2], q[2], w.fma(gmv[1], q[1], w.mul(gmv[0], q[0])));
                    let da = w.fma(gmv[2], az[2], w.fma(gmv[1], az[1], w.mul(gmv[0], az[0])));
                    let t = w.fma(m, gmm, w.fma(da, e2[k], dq));
                    s_w = w.fma(w2[k], t, s_w);
                    s_dw = w.fma(dw[2][k], t, s_dw);
                }
                let w01 = w.mul(w0[i], w1[j]);
                px = w.fma(w.mul(dw[0][i], w1[j]), s_w, px);
                py = w.fma(w.mul(w0[i], dw[1][j]), s_w, py);
                pz = w.fma(w01, s_dw, pz);
                smv = w.fma(w01, smr, smv);
                let w0e1 = w.mul(w01, e1[j]);
                for r in 0..3 {
                    u[r] = w.fma(w1[j], sr[r], u[r]);
                    ab[3 * r + 1] = w.fma(w0e1, sr[r], ab[3 * r + 1]);
                    ab[3 * r + 2] = w.fma(w01, se[r], ab[3 * r + 2]);
                }
            }
            let w0e0 = w.mul(w0[i], e0[i]);
            for r in 0..3 {
                sgv[r] = w.fma(w0[i], u[r], sgv[r]);
                ab[3 * r] = w.fma(w0e0, u[r], ab[3 * r]);
            }
        }
        let out = &mut self.out;
        let how = SlotStores::new::<PAIR>(na, nb, out.sm.len() - o, last, T::N);
        // Ā = dx Σ w m̄v eᵀ; x̄ += (1/dx)(Px, Py, Pz) − Aᵀ ḡ.
        for (abk, out_k) in ab.iter().zip(out.abar.iter_mut()) {
            how.store::<W, PAIR>(w, w.mul(dx, *abk), &mut out_k[o..]);
        }
        let p = [px, py, pz];
        for d in 0..3 {
            let atg = w.fma(
                am[6 + d],
                sgv[2],
                w.fma(am[3 + d], sgv[1], w.mul(am[d], sgv[0])),
            );
            let add = w.sub(w.mul(inv, p[d]), atg);
            // x̄ is read back here, so exactly the unit's lanes are written.
            if PAIR {
                let add = w.lanes(add);
                let gx = &mut out.gx[d][o..];
                for l in 0..na {
                    gx[l] = gx[l] + add[l];
                }
                for l in 0..nb {
                    gx[na + l] = gx[na + l] + add[h + l];
                }
            } else {
                let cur = w.load_part(&out.gx[d][o..]);
                w.store_n(w.add(cur, add), &mut out.gx[d][o..], na);
            }
            how.store::<W, PAIR>(w, sgv[d], &mut out.sg[d][o..]);
        }
        how.store::<W, PAIR>(w, smv, &mut out.sm[o..]);
    }
}

/// Per-particle gradients of one task of the model pass: state gradients in and out, and the
/// material gradients accumulated (`f64`).
pub(crate) struct ModelAdjGrad<'a, T> {
    /// `ḡ = Σ w m̄v` in (from the P2G adjoint); `v̄ = m ḡ` out.
    pub gv: [&'a mut [T]; 3],
    /// `C̄` out.
    pub gc: [&'a mut [T]; 9],
    /// `F̄` of the substep's result in, of its start out.
    pub gf: [&'a mut [T]; 9],
    pub gmass: &'a mut [f64],
    pub gvolume: &'a mut [f64],
    pub gmu: &'a mut [f64],
    pub glam: &'a mut [f64],
    /// Per-particle family gradients (empty unless the model has family scalars).
    pub gfamily: &'a mut [FamilyGrad],
}

/// The per-particle part of the substep's adjoint for one task (particles `0..len`, the first
/// `real` of them particles, the rest padding): `v̄`, `C̄`, `τ̄`, `m̄`, `V̄` from the P2G
/// adjoint's `ḡ`, `Ā`, `Σ w m̄_i`, then the model's and the strain prediction's adjoints.
pub(crate) struct ModelAdjTask<'a, T, M> {
    pub model: &'a M,
    pub dt: f64,
    /// `4/dx²` (1/m²).
    pub d_inv: f64,
    pub real: usize,
    pub v: [&'a [T]; 3],
    pub c: [&'a [T]; 9],
    pub f: [&'a [T]; 9],
    pub tau: [&'a [T]; 9],
    pub aux: &'a [T],
    pub abar: [&'a [T]; 9],
    pub sm: &'a [T],
    pub mat: SlotMaterial<'a, T>,
    pub g: ModelAdjGrad<'a, T>,
}

/// Adds the first `n` lanes of `v` to `acc` (in `f64`).
#[inline(always)]
fn accumulate<W: Wide>(w: W, v: W::V, acc: &mut [f64], n: usize) {
    let lanes = w.lanes(v);
    if n == W::T::N && acc.len() >= W::T::N {
        // A whole vector: a fixed-length loop the compiler turns into vector conversions.
        let acc = &mut acc[..W::T::N];
        for l in 0..W::T::N {
            acc[l] += lanes[l].f64();
        }
    } else {
        for (a, x) in acc.iter_mut().zip(&lanes[..n]) {
            *a += x.f64();
        }
    }
}

impl<T: Real, M: Constitutive> WideOp<T> for ModelAdjTask<'_, T, M> {
    /// Whether some new state gradient is NaN/Inf.
    type Output = bool;

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) -> bool {
        let t = self;
        let len = t.g.gf[0].len();
        let dt = w.c(t.dt);
        let kd = -t.dt * t.d_inv;
        // x·0 is NaN exactly for NaN/Inf x: independent accumulators (no long dependency chain).
        let mut probe = [w.zero(); 4];
        for i in (0..len).step_by(T::N) {
            let n = t.real.saturating_sub(i).min(T::N);
            let u = t.mat.uniform;
            let m = lane_of(w, t.mat.mass, i, u);
            let vol = lane_of(w, t.mat.volume, i, u);
            let c: Mat<W> = arr!(9, |k| w.load(&t.c[k][i..]));
            let f: Mat<W> = arr!(9, |k| w.load(&t.f[k][i..]));
            let ab: Mat<W> = arr!(9, |k| w.load(&t.abar[k][i..]));
            let sg: [W::V; 3] = arr!(3, |r| w.load(&t.g.gv[r][i..]));
            let vv: [W::V; 3] = arr!(3, |r| w.load(&t.v[r][i..]));
            // m̄ = v·ḡ + C:Ā + Σ w m̄_i; V̄ = −dt (4/dx²) Ā:τ; τ̄ = −dt V (4/dx²) Ā.
            let gmass = w.add(
                w.add(
                    w.fma(vv[2], sg[2], w.fma(vv[1], sg[1], w.mul(vv[0], sg[0]))),
                    ddot(w, &c, &ab),
                ),
                w.load(&t.sm[i..]),
            );
            let ktau = w.mul(w.c(kd), vol);
            let gtau: Mat<W> = arr!(9, |k| w.mul(ktau, ab[k]));
            let gf_next: Mat<W> = arr!(9, |k| w.load(&t.g.gf[k][i..]));
            accumulate(w, gmass, &mut t.g.gmass[i..], n);
            for r in 0..3 {
                let gv = w.mul(m, sg[r]);
                probe[r] = w.fma(gv, w.zero(), probe[r]);
                w.store(gv, &mut t.g.gv[r][i..]);
            }
            // The model's adjoint (F̄_tmp), then the strain prediction's: C̄ += dt F̄_tmp Fᵀ,
            // F̄ = (I + dt C)ᵀ F̄_tmp.
            match M::LANE_KERNEL {
                LaneKernel::PerParticle => {
                    // Per particle, in f64, through the model's own adjoint.
                    let tau: Mat<W> = arr!(9, |k| w.load(&t.tau[k][i..]));
                    accumulate(
                        w,
                        w.mul(w.c(kd), ddot(w, &ab, &tau)),
                        &mut t.g.gvolume[i..],
                        n,
                    );
                    let lanes = |v: &Mat<W>| -> [[T; 8]; 9] { arr!(9, |k| w.lanes(v[k])) };
                    let (cl, fl, tl, gtl, gfl) = (
                        lanes(&c),
                        lanes(&f),
                        lanes(&tau),
                        lanes(&gtau),
                        lanes(&gf_next),
                    );
                    let (ml, abl) = (w.lanes(m), lanes(&ab));
                    let auxl = w.lanes(w.load(&t.aux[i..]));
                    let mut gc_out = [[T::of(0.0); 8]; 9];
                    let mut gf_out = [[T::of(0.0); 8]; 9];
                    for l in 0..n {
                        let p = i + l;
                        let mat = |a: &[[T; 8]; 9]| -> DMat3 {
                            from_rows(std::array::from_fn(|r| {
                                std::array::from_fn(|col| a[3 * r + col][l].f64())
                            }))
                        };
                        let (cm, fm) = (mat(&cl), mat(&fl));
                        let model = particle_model(t.model, t.mat.family, p);
                        let ft = model.predict(&cm, &fm, t.dt);
                        let mg = model.update_adjoint_given_stress(
                            &ft,
                            &cm,
                            t.mat.mu64[p],
                            t.mat.lam64[p],
                            t.dt,
                            (&mat(&tl), auxl[l].f64()),
                            &mat(&gfl),
                            &mat(&gtl),
                        );
                        let (gc_pred, gf_new) = model.predict_adjoint(&cm, &fm, t.dt, &mg.f_tmp);
                        let gc = mat(&abl) * ml[l].f64() + mg.c + gc_pred;
                        let (gcr, gfr) = (to_rows(&gc), to_rows(&gf_new));
                        for k in 0..9 {
                            gc_out[k][l] = T::of(gcr[k / 3][k % 3]);
                            gf_out[k][l] = T::of(gfr[k / 3][k % 3]);
                        }
                        t.g.gmu[p] += mg.mu;
                        t.g.glam[p] += mg.lam;
                        if M::HAS_FAMILY_PARAMS {
                            t.g.gfamily[p] = t.g.gfamily[p] + mg.family;
                        }
                    }
                    for k in 0..9 {
                        let (gc, gf) = (w.vector(gc_out[k]), w.vector(gf_out[k]));
                        probe[k % 4] = w.fma(w.add(gc, gf), w.zero(), probe[k % 4]);
                        w.store(gc, &mut t.g.gc[k][i..]);
                        w.store(gf, &mut t.g.gf[k][i..]);
                    }
                }
                kernel => {
                    let ft = predict(w, &c, &f, dt);
                    let mu = lane_of(w, t.mat.mu, i, u);
                    let lam = lane_of(w, t.mat.lam, i, u);
                    let (gft, gmu, glam, tau) = if kernel == LaneKernel::NeoHookean {
                        let ln_j = w.load(&t.aux[i..]);
                        neo_hookean_adjoint(w, &ft, mu, lam, ln_j, &gf_next, &gtau)
                    } else {
                        fixed_corotated_adjoint(w, &ft, mu, lam, &gf_next, &gtau)
                    };
                    accumulate(
                        w,
                        w.mul(w.c(kd), ddot(w, &ab, &tau)),
                        &mut t.g.gvolume[i..],
                        n,
                    );
                    accumulate(w, gmu, &mut t.g.gmu[i..], n);
                    accumulate(w, glam, &mut t.g.glam[i..], n);
                    let gcp = mul_bt(w, &gft, &f);
                    let ctg = mul_at(w, &c, &gft);
                    for k in 0..9 {
                        let gc = w.fma(dt, gcp[k], w.mul(m, ab[k]));
                        let gfk = w.fma(dt, ctg[k], gft[k]);
                        probe[k % 4] = w.fma(w.add(gc, gfk), w.zero(), probe[k % 4]);
                        w.store(gc, &mut t.g.gc[k][i..]);
                        w.store(gfk, &mut t.g.gf[k][i..]);
                    }
                }
            }
        }
        let p = w.add(w.add(probe[0], probe[1]), w.add(probe[2], probe[3]));
        w.non_finite_mask(p) != 0
    }
}

/// Adjoint of the neo-Hookean `τ = μ F Fᵀ + (λ ln J − μ) I` given `ln J`: `(F̄, μ̄, λ̄, τ)`
/// with `F̄ = F̄' + μ (τ̄ + τ̄ᵀ) F + λ tr τ̄ cof(F)/J`, `μ̄ = ½ h:F − tr τ̄`, `λ̄ = tr τ̄ ln J`.
#[inline(always)]
pub(crate) fn neo_hookean_adjoint<W: Wide>(
    w: W,
    f: &Mat<W>,
    mu: W::V,
    lam: W::V,
    ln_j: W::V,
    gf: &Mat<W>,
    gtau: &Mat<W>,
) -> (Mat<W>, W::V, W::V, Mat<W>) {
    let cof = cofactor(w, f);
    let j = det_with(w, f, &cof);
    let tr = w.add(w.add(gtau[0], gtau[4]), gtau[8]);
    let b = mul_bt(w, f, f);
    let diag = w.sub(w.mul(lam, ln_j), mu);
    let tau: Mat<W> = arr!(9, |k| {
        let t = w.mul(mu, b[k]);
        if k.is_multiple_of(4) {
            w.add(t, diag)
        } else {
            t
        }
    });
    let sym: Mat<W> = arr!(9, |k| w.add(gtau[k], gtau[3 * (k % 3) + k / 3]));
    let h = mul(w, &sym, f);
    let s = w.div(w.mul(lam, tr), j);
    let g: Mat<W> = arr!(9, |k| w.fma(s, cof[k], w.fma(mu, h[k], gf[k])));
    let gmu = w.sub(w.mul(w.c(0.5), ddot(w, &h, f)), tr);
    (g, gmu, w.mul(tr, ln_j), tau)
}

/// Adjoint of the fixed-corotated `τ = 2μ (F − R) Fᵀ + λ J (J − 1) I`: `(F̄, μ̄, λ̄, τ)`, the
/// rotation's adjoint from `R` alone ([`polar_rotation_adjoint`]'s equations) where `F` is well
/// inside `det F > 0`, else per lane through the SVD ([`rotation_adjoint`]).
#[inline(always)]
pub(crate) fn fixed_corotated_adjoint<W: Wide>(
    w: W,
    f: &Mat<W>,
    mu: W::V,
    lam: W::V,
    gf: &Mat<W>,
    gtau: &Mat<W>,
) -> (Mat<W>, W::V, W::V, Mat<W>) {
    let r = polar(w, f);
    let cof = cofactor(w, f);
    let j = det_with(w, f, &cof);
    let tr = w.add(w.add(gtau[0], gtau[4]), gtau[8]);
    let gtf = mul(w, gtau, f);
    let fr: Mat<W> = arr!(9, |k| w.sub(f[k], r[k]));
    let gtt: Mat<W> = arr!(9, |k| gtau[3 * (k % 3) + k / 3]);
    let tfr = mul(w, &gtt, &fr);
    let two_mu = w.add(mu, mu);
    let sj = w.mul(w.mul(lam, w.sub(w.add(j, j), w.c(1.0))), tr);
    let mut g: Mat<W> = arr!(9, |k| w.fma(
        sj,
        cof[k],
        w.fma(two_mu, w.add(gtf[k], tfr[k]), gf[k])
    ));
    let gr: Mat<W> = arr!(9, |k| w.mul(w.sub(w.zero(), two_mu), gtf[k]));
    let rot = rotation_adjoint_lanes(w, f, &r, &gr, j);
    for k in 0..9 {
        g[k] = w.add(g[k], rot[k]);
    }
    let gmu = w.mul(w.c(2.0), ddot(w, &gtf, &fr));
    let jj = w.mul(j, w.sub(j, w.c(1.0)));
    let p = mul_bt(w, &fr, f);
    let diag = w.mul(lam, jj);
    let tau: Mat<W> = arr!(9, |k| {
        let t = w.mul(two_mu, p[k]);
        if k.is_multiple_of(4) {
            w.add(t, diag)
        } else {
            t
        }
    });
    (g, gmu, w.mul(tr, jj), tau)
}

/// `F̄` of `R = polar(F)` given `R̄` (`gr`) and `J = det F`: with `S = sym(RᵀF)`,
/// `K = tr S · I − S`, `M = Rᵀ R̄`, `m = (M₂₁ − M₁₂, M₀₂ − M₂₀, M₁₀ − M₀₁)`, `z = K⁻¹ m`,
/// `F̄ = R [z]×` ([`polar_rotation_adjoint`]); lanes with `det F ≤ 0` or
/// `det K ≤ 1e-6 (tr S)³` go through [`polar_rotation_adjoint`] / the SVD in `f64`.
#[inline(always)]
fn rotation_adjoint_lanes<W: Wide>(w: W, f: &Mat<W>, r: &Mat<W>, gr: &Mat<W>, j: W::V) -> Mat<W> {
    let rtf = mul_at(w, r, f);
    let s: Mat<W> = arr!(9, |k| w
        .mul(w.c(0.5), w.add(rtf[k], rtf[3 * (k % 3) + k / 3])));
    let t = w.add(w.add(s[0], s[4]), s[8]);
    let kk: Mat<W> = arr!(9, |k| {
        let neg = w.sub(w.zero(), s[k]);
        if k.is_multiple_of(4) {
            w.add(t, neg)
        } else {
            neg
        }
    });
    let cofk = cofactor(w, &kk);
    let det_k = det_with(w, &kk, &cofk);
    let mm = mul_at(w, r, gr);
    let mv = [
        w.sub(mm[7], mm[5]),
        w.sub(mm[2], mm[6]),
        w.sub(mm[3], mm[1]),
    ];
    let z: [W::V; 3] = arr!(3, |a| {
        w.div(
            w.fma(
                cofk[3 * a + 2],
                mv[2],
                w.fma(cofk[3 * a + 1], mv[1], w.mul(cofk[3 * a], mv[0])),
            ),
            det_k,
        )
    });
    let zero = w.zero();
    let nz: [W::V; 3] = arr!(3, |a| w.sub(zero, z[a]));
    let skew: Mat<W> = [zero, nz[2], z[1], z[2], zero, nz[0], nz[1], z[0], zero];
    let mut out = mul(w, r, &skew);
    // Lanes outside the closed form.
    let t3 = w.mul(w.mul(t, t), t);
    let (jl, dk, t3l) = (w.lanes(j), w.lanes(det_k), w.lanes(w.mul(w.c(1e-6), t3)));
    let bad: Vec<usize> = (0..W::T::N)
        .filter(|&l| !(jl[l] > W::T::of(0.0) && dk[l] > t3l[l]))
        .collect();
    if !bad.is_empty() {
        let lanes = |v: &Mat<W>| -> [[W::T; 8]; 9] { arr!(9, |k| w.lanes(v[k])) };
        let (fl, rl, gl) = (lanes(f), lanes(r), lanes(gr));
        let mut ol = lanes(&out);
        for l in bad {
            let mat = |a: &[[W::T; 8]; 9]| -> DMat3 {
                from_rows(std::array::from_fn(|rr| {
                    std::array::from_fn(|c| a[3 * rr + c][l].f64())
                }))
            };
            let (fm, rm, gm) = (mat(&fl), mat(&rl), mat(&gl));
            let g = polar_rotation_adjoint(&fm, &rm, &gm)
                .unwrap_or_else(|| rotation_adjoint(&svd3(&fm), &gm));
            let rows = to_rows(&g);
            for k in 0..9 {
                ol[k][l] = W::T::of(rows[k / 3][k % 3]);
            }
        }
        out = arr!(9, |k| w.vector(ol[k]));
    }
    out
}
