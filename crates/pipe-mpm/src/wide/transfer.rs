//! P2G and G2P on particle groups ([`super::groups`]): the lanes of a vector are the particles
//! of one group, which share their 27 stencil nodes, so a node's contribution is a sum across
//! lanes (P2G, [`Wide::reduce4`]) and a node's velocity is one broadcast (G2P).
//!
//! The equations are [`crate::p2g`]'s and [`crate::g2p`]'s, on separable stencil sums.

use super::groups::Group;
use super::simd::{Real, Wide, WideOp};
use crate::grid::GridSpec;

/// The three weights of one axis and the node offsets `a − fx` (cells).
pub(crate) type Axis<W> = ([<W as Wide>::V; 3], [<W as Wide>::V; 3]);

/// Quadratic B-spline weights `w_a` of the three nodes on one axis, and the node offsets
/// `a − fx` (cells), from the particle's position in cells relative to its base `fx`.
#[inline(always)]
pub(crate) fn weights<W: Wide>(w: W, fx: W::V) -> Axis<W> {
    let t0 = w.sub(w.c(1.5), fx);
    let t1 = w.sub(fx, w.c(1.0));
    let t2 = w.sub(fx, w.c(0.5));
    (
        [
            w.mul(w.c(0.5), w.mul(t0, t0)),
            w.sub(w.c(0.75), w.mul(t1, t1)),
            w.mul(w.c(0.5), w.mul(t2, t2)),
        ],
        [
            w.sub(w.zero(), fx),
            w.sub(w.c(1.0), fx),
            w.sub(w.c(2.0), fx),
        ],
    )
}

/// A group's stencil base (local node index) and each lane's `fx` on the three axes.
#[inline(always)]
pub(crate) fn group_stencil<W: Wide>(
    w: W,
    grid: &GridSpec,
    g: &Group,
    x: [&[W::T]; 3],
) -> ([usize; 3], [W::V; 3]) {
    let base = g.base.map(|b| b as usize);
    let s = g.start as usize;
    let inv = w.c(grid.inv_dx);
    let fx = arr!(3, |a| {
        w.sub(
            w.mul(w.load(&x[a][s..]), inv),
            w.splat(W::T::of(base[a] as f64)),
        )
    });
    (base, fx)
}

/// The mass and momentum `m v (+ f_ext dt)` of the particles from slot `s` (lanes); `mass`
/// holds one value for all when `uniform`.
#[inline(always)]
pub(crate) fn momentum<W: Wide>(
    w: W,
    mass: &[W::T],
    uniform: bool,
    v: [&[W::T]; 3],
    extra: Option<[&[W::T]; 3]>,
    s: usize,
) -> (W::V, [W::V; 3]) {
    let m = if uniform {
        w.splat(mass[0])
    } else {
        w.load(&mass[s..])
    };
    let mom = arr!(3, |r| {
        let mv = w.mul(m, w.load(&v[r][s..]));
        match &extra {
            Some(e) => w.add(mv, w.load(&e[r][s..])),
            None => mv,
        }
    });
    (m, mom)
}

/// P2G of one slab's groups into its grid piece (starting at x-layer `first`):
/// `mv_i += w (mom + A (x_i − x_p))`, `m_i += w m`, `mom = m v (+ f_ext dt)`.
pub(crate) struct P2gTask<'a, T> {
    pub grid: &'a GridSpec,
    pub groups: &'a [Group],
    pub x: [&'a [T]; 3],
    pub v: [&'a [T]; 3],
    pub a: [&'a [T]; 9],
    /// Per-particle mass, or one value for all (`uniform_mass`).
    pub mass: &'a [T],
    pub uniform_mass: bool,
    /// Extra momentum per particle (forces, impulses), when any.
    pub extra: Option<[&'a [T]; 3]>,
    pub piece: &'a mut [[T; 4]],
    pub first: usize,
}

impl<T: Real> WideOp<T> for P2gTask<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) {
        let P2gTask {
            grid,
            groups,
            x,
            v,
            a,
            mass,
            uniform_mass,
            extra,
            piece,
            first,
        } = self;
        let dx = w.c(grid.dx);
        let off = first * grid.layer();
        for g in groups {
            let s = g.start as usize;
            let (base, fx) = group_stencil(w, grid, g, x);
            let st: [Axis<W>; 3] = arr!(3, |ax| weights(w, fx[ax]));
            // Lanes past the group weigh nothing.
            let wx: [W::V; 3] = arr!(3, |i| w.keep_first(st[0].0[i], g.n as usize));
            let (wy, wz) = (st[1].0, st[2].0);
            let d: [[W::V; 3]; 3] = arr!(3, |ax| arr!(3, |i| w.mul(st[ax].1[i], dx)));
            let am: [W::V; 9] = arr!(9, |k| w.load(&a[k][s..]));
            let (m, mom) = momentum(w, mass, uniform_mass, v, extra, s);
            // Node (i, j, k) gets wx_i wy_j (wz_k (P_i + Q_j) + RW_k), with P_i = mom + A₀ px_i,
            // Q_j = A₁ py_j, RW_k = wz_k A₂ pz_k; and mass wx_i wy_j wz_k m.
            let p: [[W::V; 3]; 3] = arr!(3, |i| arr!(3, |r| w.fma(am[3 * r], d[0][i], mom[r])));
            let q: [[W::V; 3]; 3] = arr!(3, |j| arr!(3, |r| w.mul(am[3 * r + 1], d[1][j])));
            let rw: [[W::V; 3]; 3] = arr!(3, |k| {
                arr!(3, |r| w.mul(wz[k], w.mul(am[3 * r + 2], d[2][k])))
            });
            let mw: [W::V; 3] = arr!(3, |k| w.mul(wz[k], m));
            for i in 0..3 {
                for j in 0..3 {
                    let wij = w.mul(wx[i], wy[j]);
                    let pq: [W::V; 3] = arr!(3, |r| w.add(p[i][r], q[j][r]));
                    let row = grid.linear([base[0] + i, base[1] + j, base[2]]) - off;
                    let nodes: [[W::V; 4]; 3] = arr!(3, |k| {
                        [
                            w.mul(wij, w.fma(wz[k], pq[0], rw[k][0])),
                            w.mul(wij, w.fma(wz[k], pq[1], rw[k][1])),
                            w.mul(wij, w.fma(wz[k], pq[2], rw[k][2])),
                            w.mul(wij, mw[k]),
                        ]
                    });
                    let [n0, n1, n2] = nodes;
                    let (pair, last) = piece[row..row + 3].split_at_mut(2);
                    let pair: &mut [T; 8] = bytemuck::cast_slice_mut::<[T; 4], T>(pair)
                        .try_into()
                        .expect("8");
                    w.reduce4_add_pair(n0, n1, pair);
                    w.reduce4_add(n2[0], n2[1], n2[2], n2[3], &mut last[0]);
                }
            }
        }
    }
}

/// `v_p = Σ w v_i` and `Σ w v_i (a − fx)ᵀ` (cells; `C_p` is `4/dx` times it) of a group's
/// lanes from node velocities `[vx, vy, vz, 0]` (`vgrid`), along the separable stencil: per
/// row `(i, j)`, `Σ_k wz_k v_k` and `Σ_k wz_k (k − fz) v_k`, then the sums over `j` and `i`.
#[inline(always)]
pub(crate) fn gather<W: Wide>(
    w: W,
    grid: &GridSpec,
    vgrid: &[W::T],
    base: [usize; 3],
    st: &[Axis<W>; 3],
) -> ([W::V; 3], [[W::V; 3]; 3]) {
    // wd = w (a − fx): the weights times the node offsets (cells).
    let wd: [[W::V; 3]; 3] = arr!(3, |a| arr!(3, |i| w.mul(st[a].0[i], st[a].1[i])));
    let (wx, wy, wz) = (st[0].0, st[1].0, st[2].0);
    let zero = w.zero();
    let mut vel = [zero; 3];
    let mut b = [[zero; 3]; 3];
    for i in 0..3 {
        let (mut u, mut uy, mut uz) = ([zero; 3], [zero; 3], [zero; 3]);
        for j in 0..3 {
            let row = 4 * grid.linear([base[0] + i, base[1] + j, base[2]]);
            let nodes = &vgrid[row..row + 12];
            let (mut sm, mut tm) = ([zero; 3], [zero; 3]);
            for k in 0..3 {
                for r in 0..3 {
                    let gv = w.splat(nodes[4 * k + r]);
                    sm[r] = w.fma(wz[k], gv, sm[r]);
                    tm[r] = w.fma(wd[2][k], gv, tm[r]);
                }
            }
            for r in 0..3 {
                u[r] = w.fma(wy[j], sm[r], u[r]);
                uy[r] = w.fma(wd[1][j], sm[r], uy[r]);
                uz[r] = w.fma(wy[j], tm[r], uz[r]);
            }
        }
        for r in 0..3 {
            vel[r] = w.fma(wx[i], u[r], vel[r]);
            b[r][0] = w.fma(wd[0][i], u[r], b[r][0]);
            b[r][1] = w.fma(wx[i], uy[r], b[r][1]);
            b[r][2] = w.fma(wx[i], uz[r], b[r][2]);
        }
    }
    (vel, b)
}

/// Outputs of G2P for one task's slots `s0..`: new `x, v, C`.
pub(crate) struct G2pOut<'a, T> {
    pub x: [&'a mut [T]; 3],
    pub v: [&'a mut [T]; 3],
    pub c: [&'a mut [T]; 9],
}

/// G2P of one task's groups (slots from `s0`): `v_p = Σ w v_i`,
/// `C_p = (4/dx²) Σ w v_i (x_i − x_p)ᵀ`, `x_p ← hold(x_p + dt v_p)`.
///
/// Every group but the task's last writes whole vectors: its lanes past the group land on the
/// next groups' slots, which those groups overwrite afterwards (the old positions are read
/// from a separate buffer).
pub(crate) struct G2pTask<'a, T> {
    pub grid: &'a GridSpec,
    pub groups: &'a [Group],
    pub s0: usize,
    /// Positions at the start of the substep (all slots, padded).
    pub x_old: [&'a [T]; 3],
    /// Node velocities `[vx, vy, vz, 0]` per node (m/s).
    pub vgrid: &'a [T],
    pub dt: f64,
    /// The domain relative to the first node, rounded inwards to `T` (m).
    pub lo: [T; 3],
    pub hi: [T; 3],
    pub out: G2pOut<'a, T>,
}

impl<T: Real> WideOp<T> for G2pTask<'_, T> {
    /// Particles held at the domain edge, and whether some new value is NaN/Inf.
    type Output = (usize, bool);

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) -> (usize, bool) {
        let G2pTask {
            grid,
            groups,
            s0,
            x_old,
            vgrid,
            dt,
            lo,
            hi,
            out,
        } = self;
        let G2pOut {
            x: xo,
            v: vo,
            c: co,
        } = out;
        let c4 = w.c(4.0 * grid.inv_dx);
        let dt = w.c(dt);
        let inv = w.c(grid.inv_dx);
        let (lo, hi) = (arr!(3, |a| w.splat(lo[a])), arr!(3, |a| w.splat(hi[a])));
        let mut held = 0usize;
        // x·0 is 0 for finite x and NaN otherwise: one accumulator flags NaN/Inf in any lane of
        // v or x (C follows from the same node velocities). Lanes past a group hold other
        // particles' finite values.
        let mut nan_probe = w.zero();
        let last = groups.len().saturating_sub(1);
        for (gi, g) in groups.iter().enumerate() {
            let s = g.start as usize;
            let o = s - s0;
            let n = g.n as usize;
            let x: [W::V; 3] = arr!(3, |a| w.load(&x_old[a][s..]));
            let base = g.base.map(|b| b as usize);
            let st: [Axis<W>; 3] = arr!(3, |a| {
                weights(w, w.sub(w.mul(x[a], inv), w.splat(T::of(base[a] as f64))))
            });
            let (vel, b) = gather(w, grid, vgrid, base, &st);
            let mut moved = 0u32;
            let lanes = if gi == last {
                n
            } else {
                T::N.min(vo[0].len() - o)
            };
            let zero = w.zero();
            for r in 0..3 {
                let xn = w.fma(dt, vel[r], x[r]);
                let held_x = w.min(w.max(xn, lo[r]), hi[r]);
                moved |= w.ne_mask(held_x, xn);
                nan_probe = w.fma(xn, zero, nan_probe);
                w.store_n(vel[r], &mut vo[r][o..], lanes);
                w.store_n(held_x, &mut xo[r][o..], lanes);
                for col in 0..3 {
                    w.store_n(w.mul(c4, b[r][col]), &mut co[3 * r + col][o..], lanes);
                }
            }
            held += (moved & ((1u32 << n) - 1)).count_ones() as usize;
        }
        (held, w.non_finite_mask(nan_probe) != 0)
    }
}
