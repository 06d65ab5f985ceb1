//! P2G and G2P on particle groups ([`super::groups`]): the lanes of a vector are the particles
//! of one group, which share their 27 stencil nodes, so a node's contribution is a sum across
//! lanes (P2G, [`Wide::reduce4`]) and a node's velocity is one broadcast (G2P).
//!
//! Groups of at most half a vector (a cell's last few particles, a stray) run two to a
//! vector, one per half: P2G sums each half into its own group's nodes
//! ([`Wide::reduce4_halves`]), G2P broadcasts each group's node values into its half
//! ([`Wide::splat_halves`]). A pair costs P2G about what one group costs and G2P about 1.4
//! groups; on the anchor workloads 38–45 % of the groups are that small.
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

/// Lanes of one group from slot `sa`, or (`PAIR`) of two side by side: the first half from
/// slot `sa`, the second from slot `sb` ([`Wide::load_halves`]).
#[inline(always)]
pub(crate) fn load_unit<W: Wide, const PAIR: bool>(w: W, f: &[W::T], sa: usize, sb: usize) -> W::V {
    if PAIR {
        w.load_halves(&f[sa..], &f[sb..])
    } else {
        w.load(&f[sa..])
    }
}

/// `a` in every lane, or (`PAIR`) `a` in the first half and `b` in the second.
#[inline(always)]
pub(crate) fn splat_unit<W: Wide, const PAIR: bool>(w: W, a: W::T, b: W::T) -> W::V {
    if PAIR {
        w.splat_halves(a, b)
    } else {
        w.splat(a)
    }
}

/// One unit of work of a transfer kernel: group `a` alone, or with group `b` in the two halves
/// of one vector; `last` when no group of the task comes after it (indices into the task's
/// groups).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Unit {
    pub a: usize,
    pub b: Option<usize>,
    pub last: bool,
}

/// A task's groups as [`Unit`]s: groups of at most half a vector (`lanes / 2` particles) run
/// two to a vector. Kernels that store per slot pair only neighbours ([`Units::neighbours`]:
/// the pair's slots are contiguous); kernels that sum into nodes let a small group wait for the
/// next small one ([`Units::in_order`]).
pub(crate) struct Units<'g> {
    groups: &'g [Group],
    lanes: usize,
    neighbours: bool,
    next: usize,
    waiting: Option<usize>,
}

impl<'g> Units<'g> {
    /// Pairs of consecutive small groups.
    pub fn neighbours(groups: &'g [Group], lanes: usize) -> Self {
        Self {
            groups,
            lanes,
            neighbours: true,
            next: 0,
            waiting: None,
        }
    }

    /// Pairs of small groups in the order they come, whatever lies between them.
    pub fn in_order(groups: &'g [Group], lanes: usize) -> Self {
        Self {
            neighbours: false,
            ..Self::neighbours(groups, lanes)
        }
    }

    #[inline(always)]
    fn small(&self, i: usize) -> bool {
        2 * self.groups[i].n as usize <= self.lanes
    }
}

impl Iterator for Units<'_> {
    type Item = Unit;

    #[inline(always)]
    fn next(&mut self) -> Option<Unit> {
        let n = self.groups.len();
        while self.next < n {
            let i = self.next;
            self.next += 1;
            if self.neighbours {
                if i + 1 < n && self.small(i) && self.small(i + 1) {
                    self.next += 1;
                    return Some(Unit {
                        a: i,
                        b: Some(i + 1),
                        last: i + 2 == n,
                    });
                }
                return Some(Unit {
                    a: i,
                    b: None,
                    last: i + 1 == n,
                });
            }
            if !self.small(i) {
                return Some(Unit {
                    a: i,
                    b: None,
                    last: false,
                });
            }
            match self.waiting.take() {
                Some(first) => {
                    return Some(Unit {
                        a: first,
                        b: Some(i),
                        last: false,
                    });
                }
                None => self.waiting = Some(i),
            }
        }
        self.waiting.take().map(|a| Unit {
            a,
            b: None,
            last: true,
        })
    }
}

/// A unit's positions (lanes), the stencil bases of its groups and each lane's `fx` on the
/// three axes (the second group's lanes in the second half when `PAIR`).
#[inline(always)]
#[allow(clippy::type_complexity)]
pub(crate) fn unit_stencil<W: Wide, const PAIR: bool>(
    w: W,
    grid: &GridSpec,
    ga: &Group,
    gb: &Group,
    x: [&[W::T]; 3],
) -> ([W::V; 3], [usize; 3], [usize; 3], [W::V; 3]) {
    let (base_a, base_b) = (ga.base.map(|b| b as usize), gb.base.map(|b| b as usize));
    let (sa, sb) = (ga.start as usize, gb.start as usize);
    let inv = w.c(grid.inv_dx);
    // Bases from the positions' anchor (the window's first node is `shift` cells from it).
    let shift = grid.shift();
    let xv: [W::V; 3] = arr!(3, |a| load_unit::<W, PAIR>(w, x[a], sa, sb));
    let fx = arr!(3, |a| {
        let base = splat_unit::<W, PAIR>(
            w,
            W::T::of(base_a[a] as f64 + shift[a]),
            W::T::of(base_b[a] as f64 + shift[a]),
        );
        w.sub(w.mul(xv[a], inv), base)
    });
    (xv, base_a, base_b, fx)
}

/// The mass and momentum `m v (+ f_ext dt)` of a unit's lanes: one group from slot `sa`, or
/// (`PAIR`) two from `sa` and `sb`; `mass` holds one value for all when `uniform`.
#[inline(always)]
pub(crate) fn unit_momentum<W: Wide, const PAIR: bool>(
    w: W,
    mass: &[W::T],
    uniform: bool,
    v: [&[W::T]; 3],
    extra: Option<[&[W::T]; 3]>,
    sa: usize,
    sb: usize,
) -> (W::V, [W::V; 3]) {
    let m = if uniform {
        w.splat(mass[0])
    } else {
        load_unit::<W, PAIR>(w, mass, sa, sb)
    };
    let mom = arr!(3, |r| {
        let mv = w.mul(m, load_unit::<W, PAIR>(w, v[r], sa, sb));
        match &extra {
            Some(e) => w.add(mv, load_unit::<W, PAIR>(w, e[r], sa, sb)),
            None => mv,
        }
    });
    (m, mom)
}

/// P2G of one slab's groups into its grid piece (starting at x-layer `first`):
/// `mv_i += w (mom + A (x_i − x_p))`, `m_i += w m`, `mom = m v (+ f_ext dt)`.
///
/// Groups of at most half a vector share a vector two by two, in the order they come
/// ([`Units::in_order`]): each half sums into its own group's nodes.
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
    fn with<W: Wide<T = T>>(mut self, w: W) {
        // P2G reads its lanes from anywhere and stores only node sums: any two small groups of
        // the slab can pair.
        let groups = self.groups;
        for u in Units::in_order(groups, T::N) {
            let ga = &groups[u.a];
            match u.b {
                Some(b) => self.unit::<W, true>(w, ga, &groups[b]),
                None => self.unit::<W, false>(w, ga, ga),
            }
        }
    }
}

impl<T: Real> P2gTask<'_, T> {
    /// P2G of group `ga`, or (`PAIR`) of `ga` and `gb` in the two halves of one vector.
    #[inline(always)]
    fn unit<W: Wide<T = T>, const PAIR: bool>(&mut self, w: W, ga: &Group, gb: &Group) {
        let (grid, x, v, a) = (self.grid, self.x, self.v, self.a);
        let dx = w.c(grid.dx);
        let off = self.first * grid.layer();
        let (sa, sb) = (ga.start as usize, gb.start as usize);
        let (_, base_a, base_b, fx) = unit_stencil::<W, PAIR>(w, grid, ga, gb, x);
        let st: [Axis<W>; 3] = arr!(3, |ax| weights(w, fx[ax]));
        // Lanes past the group(s) weigh nothing.
        let wx: [W::V; 3] = arr!(3, |i| {
            if PAIR {
                w.keep_halves(st[0].0[i], ga.n as usize, gb.n as usize)
            } else {
                w.keep_first(st[0].0[i], ga.n as usize)
            }
        });
        let (wy, wz) = (st[1].0, st[2].0);
        let d: [[W::V; 3]; 3] = arr!(3, |ax| arr!(3, |i| w.mul(st[ax].1[i], dx)));
        let am: [W::V; 9] = arr!(9, |k| load_unit::<W, PAIR>(w, a[k], sa, sb));
        let (m, mom) =
            unit_momentum::<W, PAIR>(w, self.mass, self.uniform_mass, v, self.extra, sa, sb);
        // Node (i, j, k) gets wx_i wy_j (wz_k (P_i + Q_j) + RW_k), with P_i = mom + A₀ px_i,
        // Q_j = A₁ py_j, RW_k = wz_k A₂ pz_k; and mass wx_i wy_j wz_k m.
        let p: [[W::V; 3]; 3] = arr!(3, |i| arr!(3, |r| w.fma(am[3 * r], d[0][i], mom[r])));
        let q: [[W::V; 3]; 3] = arr!(3, |j| arr!(3, |r| w.mul(am[3 * r + 1], d[1][j])));
        let rw: [[W::V; 3]; 3] = arr!(3, |k| {
            arr!(3, |r| w.mul(wz[k], w.mul(am[3 * r + 2], d[2][k])))
        });
        let mw: [W::V; 3] = arr!(3, |k| w.mul(wz[k], m));
        let piece = &mut *self.piece;
        for i in 0..3 {
            for j in 0..3 {
                let wij = w.mul(wx[i], wy[j]);
                let pq: [W::V; 3] = arr!(3, |r| w.add(p[i][r], q[j][r]));
                let nodes: [[W::V; 4]; 3] = arr!(3, |k| {
                    [
                        w.mul(wij, w.fma(wz[k], pq[0], rw[k][0])),
                        w.mul(wij, w.fma(wz[k], pq[1], rw[k][1])),
                        w.mul(wij, w.fma(wz[k], pq[2], rw[k][2])),
                        w.mul(wij, mw[k]),
                    ]
                });
                let row_a = grid.linear([base_a[0] + i, base_a[1] + j, base_a[2]]) - off;
                if PAIR {
                    let row_b = grid.linear([base_b[0] + i, base_b[1] + j, base_b[2]]) - off;
                    for (k, [n0, n1, n2, n3]) in nodes.into_iter().enumerate() {
                        let (sum_a, sum_b) = w.reduce4_halves(n0, n1, n2, n3);
                        w.add4(sum_a, &mut piece[row_a + k]);
                        w.add4(sum_b, &mut piece[row_b + k]);
                    }
                } else {
                    let [n0, n1, n2] = nodes;
                    let (pair, last) = piece[row_a..row_a + 3].split_at_mut(2);
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

/// `v_p = Σ w v_i` and `Σ w v_i (a − fx)ᵀ` (cells; `C_p` is `4/dx` times it) of a unit's
/// lanes from node velocities `[vx, vy, vz, 0]` (`vgrid`), along the separable stencil: per
/// row `(i, j)`, `Σ_k wz_k v_k` and `Σ_k wz_k (k − fz) v_k`, then the sums over `j` and `i`.
/// One group at stencil base `base_a`, or (`PAIR`) two, the second's lanes (second half) at
/// `base_b`.
#[inline(always)]
pub(crate) fn gather_unit<W: Wide, const PAIR: bool>(
    w: W,
    grid: &GridSpec,
    vgrid: &[W::T],
    base_a: [usize; 3],
    base_b: [usize; 3],
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
            let row_a = 4 * grid.linear([base_a[0] + i, base_a[1] + j, base_a[2]]);
            let row_b = 4 * grid.linear([base_b[0] + i, base_b[1] + j, base_b[2]]);
            let (nodes_a, nodes_b) = (&vgrid[row_a..row_a + 12], &vgrid[row_b..row_b + 12]);
            let (mut sm, mut tm) = ([zero; 3], [zero; 3]);
            for k in 0..3 {
                for r in 0..3 {
                    let gv = splat_unit::<W, PAIR>(w, nodes_a[4 * k + r], nodes_b[4 * k + r]);
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
    fn with<W: Wide<T = T>>(mut self, w: W) -> (usize, bool) {
        let groups = self.groups;
        let mut held = 0usize;
        // x·0 is 0 for finite x and NaN otherwise: one accumulator flags NaN/Inf in any lane of
        // v or x (C follows from the same node velocities). Lanes past a group hold other
        // particles' finite values.
        let mut nan_probe = w.zero();
        let bounds = (
            arr!(3, |a| w.splat(self.lo[a])),
            arr!(3, |a| w.splat(self.hi[a])),
        );
        for u in Units::neighbours(groups, T::N) {
            let ga = &groups[u.a];
            held += match u.b {
                Some(b) => self.unit::<W, true>(w, ga, &groups[b], u.last, bounds, &mut nan_probe),
                None => self.unit::<W, false>(w, ga, ga, u.last, bounds, &mut nan_probe),
            };
        }
        (held, w.non_finite_mask(nan_probe) != 0)
    }
}

impl<T: Real> G2pTask<'_, T> {
    /// G2P of group `ga`, or (`PAIR`) of `ga` and the group `gb` right after it in the two
    /// halves of one vector; `last` when no group of the task follows. Returns the particles
    /// held.
    #[inline(always)]
    fn unit<W: Wide<T = T>, const PAIR: bool>(
        &mut self,
        w: W,
        ga: &Group,
        gb: &Group,
        last: bool,
        bounds: ([W::V; 3], [W::V; 3]),
        nan_probe: &mut W::V,
    ) -> usize {
        let grid = self.grid;
        let c4 = w.c(4.0 * grid.inv_dx);
        let dt = w.c(self.dt);
        let (na, nb) = (ga.n as usize, gb.n as usize);
        let o = ga.start as usize - self.s0;
        let (x, base_a, base_b, fx) = unit_stencil::<W, PAIR>(w, grid, ga, gb, self.x_old);
        let st: [Axis<W>; 3] = arr!(3, |a| weights(w, fx[a]));
        let (vel, b) = gather_unit::<W, PAIR>(w, grid, self.vgrid, base_a, base_b, &st);
        let out = &mut self.out;
        // The old positions are read from a separate buffer, so spilled stores are safe.
        let how = SlotStores::new::<PAIR>(na, nb, out.v[0].len() - o, last, T::N);
        let zero = w.zero();
        let mut moved = 0u32;
        for r in 0..3 {
            let xn = w.fma(dt, vel[r], x[r]);
            let held_x = w.min(w.max(xn, bounds.0[r]), bounds.1[r]);
            moved |= w.ne_mask(held_x, xn);
            *nan_probe = w.fma(xn, zero, *nan_probe);
            how.store::<W, PAIR>(w, vel[r], &mut out.v[r][o..]);
            how.store::<W, PAIR>(w, held_x, &mut out.x[r][o..]);
            for (col, bc) in b[r].iter().enumerate() {
                let c = w.mul(c4, *bc);
                how.store::<W, PAIR>(w, c, &mut out.c[3 * r + col][o..]);
            }
        }
        let real = if PAIR {
            ((1u32 << na) - 1) | (((1u32 << nb) - 1) << (T::N / 2))
        } else {
            (1u32 << na) - 1
        };
        (moved & real).count_ones() as usize
    }
}

/// How a unit's lanes go to its slots.
///
/// Whole-vector stores spill into the next groups' slots, which those groups overwrite
/// afterwards; a task's last unit stores exactly its lanes.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SlotStores {
    na: usize,
    nb: usize,
    lanes: usize,
    whole: bool,
}

impl SlotStores {
    /// For a unit of `na` (and, `PAIR`, `nb`) particles with `room` slots of the task from its
    /// first, `last` when no group of the task follows it, `n` lanes per vector.
    #[inline(always)]
    pub fn new<const PAIR: bool>(na: usize, nb: usize, room: usize, last: bool, n: usize) -> Self {
        let (lanes, whole) = if PAIR {
            (0, !last && room >= na + n / 2)
        } else if last {
            (na, false)
        } else {
            (n.min(room), false)
        };
        Self {
            na,
            nb,
            lanes,
            whole,
        }
    }

    /// Stores `v` to the unit's slots `s[..]`: one group's lanes, or (`PAIR`) a pair's halves
    /// ([`Wide::store_halves`]).
    #[inline(always)]
    pub fn store<W: Wide, const PAIR: bool>(self, w: W, v: W::V, s: &mut [W::T]) {
        if PAIR {
            w.store_halves(v, s, self.na, self.nb, self.whole);
        } else {
            w.store_n(v, s, self.lanes);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn groups(sizes: &[u32]) -> Vec<Group> {
        let mut start = 0;
        sizes
            .iter()
            .map(|&n| {
                let g = Group {
                    start,
                    n,
                    ..Group::default()
                };
                start += n;
                g
            })
            .collect()
    }

    fn units(u: Units<'_>) -> Vec<(usize, Option<usize>, bool)> {
        u.map(|u| (u.a, u.b, u.last)).collect()
    }

    /// Small groups (at most half the lanes) pair: in order for the scatter kernels, only as
    /// neighbours for the per-slot ones; every group runs exactly once.
    #[test]
    fn units_pair_small_groups() {
        let g = groups(&[1, 8, 2, 3, 8, 4, 5]);
        assert_eq!(
            units(Units::in_order(&g, 8)),
            [
                (1, None, false),
                (0, Some(2), false),
                (4, None, false),
                (3, Some(5), false),
                (6, None, false)
            ]
        );
        assert_eq!(
            units(Units::neighbours(&g, 8)),
            [
                (0, None, false),
                (1, None, false),
                (2, Some(3), false),
                (4, None, false),
                (5, None, false),
                (6, None, true)
            ]
        );
        // A small group left waiting runs alone at the end; with 4 lanes only 1–2 pair.
        let g = groups(&[2, 3, 1]);
        assert_eq!(
            units(Units::in_order(&g, 4)),
            [(1, None, false), (0, Some(2), false)]
        );
        assert_eq!(
            units(Units::in_order(&groups(&[1, 4, 1, 2]), 4)),
            [(1, None, false), (0, Some(2), false), (3, None, true)]
        );
        assert_eq!(
            units(Units::neighbours(&groups(&[1, 2]), 4)),
            [(0, Some(1), true)]
        );
    }
}
