//! Particle to grid (APIC / MLS-MPM, Hu et al. 2018 eq. 3–5).
//!
//! `A_p = −dt V_p (4/dx²) τ_p + m_p C_p`;
//! `mv_i += w_ip (m_p v_p + A_p (x_i − x_p))`, `m_i += w_ip m_p`.

use glam::{DMat3, DVec3};

use crate::grid::{GridSpec, NodeBox};
use crate::isa::{Isa, Lanes, WithLanes};
use crate::scatter::{Bins, scatter_slabs};

/// Grid node accumulator: momentum (kg·m/s) and mass (kg), laid out as four consecutive `f64`
/// so that one node is one 4-lane vector.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[repr(C, align(32))]
pub struct Node {
    /// Momentum (kg·m/s).
    pub mv: DVec3,
    /// Mass (kg).
    pub m: f64,
}

impl Node {
    /// The four lanes `(mv, m)`.
    #[inline(always)]
    pub(crate) fn lanes(&self) -> [f64; 4] {
        [self.mv.x, self.mv.y, self.mv.z, self.m]
    }

    /// A node from its four lanes `(mv, m)`.
    #[inline(always)]
    pub(crate) fn from_lanes(a: [f64; 4]) -> Self {
        Self {
            mv: DVec3::new(a[0], a[1], a[2]),
            m: a[3],
        }
    }
}

/// Inputs of P2G, one entry per particle.
#[derive(Debug, Clone, Copy)]
pub(crate) struct P2gIn<'a> {
    pub x: &'a [DVec3],
    pub v: &'a [DVec3],
    pub c: &'a [DMat3],
    pub tau: &'a [DMat3],
    pub mass: &'a [f64],
    pub volume: &'a [f64],
    pub extra: Option<&'a [DVec3]>,
    pub dt: f64,
}

/// The APIC affine matrix `A = −dt V (4/dx²) τ + m C`.
#[inline(always)]
pub(crate) fn affine(
    grid: &GridSpec,
    dt: f64,
    volume: f64,
    mass: f64,
    tau: &DMat3,
    c: &DMat3,
) -> DMat3 {
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    *tau * (-dt * volume * d_inv) + *c * mass
}

/// Scatters particles into `nodes` (cleared first), one slab at a time with the best
/// instruction set ([`Isa`]).
///
/// Only the nodes the particles touch (`bins.touched`) can be non-zero: `active` holds the box
/// the previous call wrote, which is zeroed instead of the whole grid, and is set to this
/// call's box.
pub(crate) fn p2g(
    grid: &GridSpec,
    bins: &Bins,
    inp: P2gIn<'_>,
    nodes: &mut Vec<Node>,
    active: &mut NodeBox,
) {
    if nodes.len() == grid.len() {
        active.fill(grid, nodes, Node::default());
    } else {
        nodes.clear();
        nodes.resize(grid.len(), Node::default());
    }
    *active = bins.touched.clone();
    let isa = Isa::detect();
    scatter_slabs(grid, bins, nodes, |ps, chunk, first| {
        isa.run_lanes(Slab {
            grid,
            inp: &inp,
            ps,
            chunk,
            first,
        })
    });
}

/// P2G of one slab's particles into its grid chunk.
struct Slab<'a> {
    grid: &'a GridSpec,
    inp: &'a P2gIn<'a>,
    ps: &'a [u32],
    chunk: &'a mut [Node],
    first: usize,
}

impl WithLanes for Slab<'_> {
    type Output = ();

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) {
        let Slab {
            grid,
            inp,
            ps,
            chunk,
            first,
        } = self;
        for &p in ps {
            let p = p as usize;
            let m = inp.mass[p];
            let a = affine(grid, inp.dt, inp.volume[p], m, &inp.tau[p], &inp.c[p]);
            let mut mom = inp.v[p] * m;
            if let Some(e) = inp.extra {
                mom += e[p];
            }
            scatter_particle(l, grid, chunk, first, inp.x[p], mom, m, &a);
        }
    }
}

/// Adds one particle's `w (mom + A dpos, m)` to its 27 nodes. Along the separable stencil,
/// `q = (mom + A₀ px + A₁ py, m)` per row, and node `k` of the row gets
/// `wx wy (wz_k q + wz_k pz_k (A₂, 0))`, the second term being fixed per particle: two fused
/// multiply-adds on the node's four lanes.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn scatter_particle<L: Lanes>(
    l: L,
    grid: &GridSpec,
    chunk: &mut [Node],
    first: usize,
    x: DVec3,
    mom: DVec3,
    m: f64,
    a: &DMat3,
) {
    let st = grid.stencil_with(l, x);
    let d = st.offsets(grid.dx);
    let (a0, a1, a2) = (
        l.load3(a.x_axis, 0.0),
        l.load3(a.y_axis, 0.0),
        l.load3(a.z_axis, 0.0),
    );
    let wz: [L::V; 3] = std::array::from_fn(|k| l.splat(st.w[k].z));
    let a2k: [L::V; 3] = std::array::from_fn(|k| l.mul(a2, l.splat(st.w[k].z * d[k].z)));
    let mom4 = l.load3(mom, m);
    for i in 0..3 {
        let q_x = l.fma(a0, l.splat(d[i].x), mom4);
        for (j, (dj, wj)) in d.iter().zip(st.w).enumerate() {
            let q = l.fma(a1, l.splat(dj.y), q_x);
            let wxy = l.splat(st.w[i].x * wj.y);
            let row = grid.row_mut(chunk, first, st.local, i, j);
            for (k, n) in row.iter_mut().enumerate() {
                let qk = l.fma(q, wz[k], a2k[k]);
                *n = Node::from_lanes(l.store(l.fma(qk, wxy, l.load(n.lanes()))));
            }
        }
    }
}
