//! Background grid: node layout, index math and the quadratic B-spline stencil.
//!
//! Node `(i, j, k)` sits at `(i·dx, j·dx, k·dx)` (m) for integer, possibly negative, indices;
//! the grid stores the box of nodes `origin .. origin + dims`. A fixed grid is built from the
//! caller's particle domain (an AABB) plus a margin, so that every particle kept inside the
//! AABB has all 27 stencil nodes inside the grid. A following grid ([`GridSpec::unbounded`])
//! has no domain: each substep stores the window of nodes the particles' stencils reach
//! ([`GridSpec::window`]), on the same lattice, so the window can move and grow with them.

use std::ops::Range;

use glam::{DVec3, IVec3};

use crate::error::MpmError;

/// Axis-aligned box (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Lower corner (m).
    pub lo: DVec3,
    /// Upper corner (m).
    pub hi: DVec3,
}

impl Aabb {
    /// A box from its corners.
    pub fn new(lo: DVec3, hi: DVec3) -> Self {
        Self { lo, hi }
    }

    /// `true` if `p` is inside (closed box).
    pub fn contains(&self, p: DVec3) -> bool {
        p.cmpge(self.lo).all() && p.cmple(self.hi).all()
    }
}

/// Node box of the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridSpec {
    /// Cell size dx (m).
    pub dx: f64,
    /// `1/dx` (1/m).
    pub inv_dx: f64,
    /// Integer index of the first stored node on each axis.
    pub origin: IVec3,
    /// Number of stored nodes per axis.
    pub dims: [usize; 3],
    /// Particles are held inside this box (m); infinite for a following grid.
    pub domain: Aabb,
    /// Index of the node that the engine measures particle positions from (the first node of
    /// a fixed grid; a following grid's windows keep the anchor of the run).
    pub anchor: IVec3,
}

/// Extra cells between the particle domain and the grid edge (the stencil needs 2).
pub const MIN_MARGIN: usize = 2;

/// Most nodes a grid may have (about 13 GB per 32-byte node buffer).
pub const MAX_GRID_NODES: f64 = 4e8;

impl GridSpec {
    /// Grid covering `domain` (m) with cell size `dx` (m) and `margin ≥ 2` extra cells per side.
    pub fn new(domain: Aabb, dx: f64, margin: usize) -> Result<Self, MpmError> {
        if !(dx.is_finite() && dx > 0.0) {
            return Err(MpmError::InvalidParameter {
                field: "dx",
                value: dx,
                reason: "must be finite and > 0",
            });
        }
        for (field, v) in [("domain.lo", domain.lo), ("domain.hi", domain.hi)] {
            for value in v.to_array() {
                if !value.is_finite() {
                    return Err(MpmError::NonFiniteInput {
                        field,
                        index: 0,
                        value,
                    });
                }
            }
        }
        let ext = domain.hi - domain.lo;
        if ext.min_element() <= 0.0 {
            return Err(MpmError::InvalidParameter {
                field: "domain",
                value: ext.min_element(),
                reason: "hi must exceed lo on every axis",
            });
        }
        let cells = (domain.lo.abs().max(domain.hi.abs()) / dx)
            .max_element()
            .max((ext / dx).max_element());
        if cells > 1e6 || margin > 1000 {
            return Err(MpmError::InvalidParameter {
                field: "domain",
                value: cells,
                reason: "domain spans more than 1e6 cells from the origin (or margin > 1000)",
            });
        }
        let margin = margin.max(MIN_MARGIN) as i32;
        let inv_dx = 1.0 / dx;
        let lo = (domain.lo * inv_dx).floor().as_ivec3() - IVec3::splat(margin);
        let hi = (domain.hi * inv_dx).ceil().as_ivec3() + IVec3::splat(margin);
        let d = hi - lo + IVec3::ONE;
        let dims = [d.x as usize, d.y as usize, d.z as usize];
        let nodes = dims[0] as f64 * dims[1] as f64 * dims[2] as f64;
        if nodes > MAX_GRID_NODES {
            return Err(MpmError::InvalidParameter {
                field: "domain",
                value: nodes,
                reason: "grid too large (> 4e8 nodes)",
            });
        }
        Ok(Self {
            dx,
            inv_dx,
            origin: lo,
            dims,
            domain,
            anchor: lo,
        })
    }

    /// A grid without domain and without nodes, of cell size `dx` (m): the template of the
    /// windows ([`Self::window`]) a grid that follows its particles stores substep by substep.
    pub fn unbounded(dx: f64) -> Result<Self, MpmError> {
        if !(dx.is_finite() && dx > 0.0) {
            return Err(MpmError::InvalidParameter {
                field: "dx",
                value: dx,
                reason: "must be finite and > 0",
            });
        }
        Ok(Self {
            dx,
            inv_dx: 1.0 / dx,
            origin: IVec3::ZERO,
            dims: [0; 3],
            domain: Aabb::new(DVec3::NEG_INFINITY, DVec3::INFINITY),
            anchor: IVec3::ZERO,
        })
    }

    /// A grid without nodes (the layout of arrays not yet laid out).
    pub(crate) fn empty() -> Self {
        Self {
            dx: 1.0,
            inv_dx: 1.0,
            origin: IVec3::ZERO,
            dims: [0; 3],
            domain: Aabb::new(DVec3::ZERO, DVec3::ZERO),
            anchor: IVec3::ZERO,
        }
    }

    /// `true` when the grid follows its particles (no domain).
    pub fn follows(&self) -> bool {
        !self.domain.lo.is_finite()
    }

    /// The nodes `lo ..= hi` (node indices) of this grid's lattice, positions still measured
    /// from `anchor`.
    pub fn window(&self, lo: IVec3, hi: IVec3, anchor: IVec3) -> Self {
        let d = (hi - lo + IVec3::ONE).max(IVec3::ZERO);
        Self {
            origin: lo,
            dims: [d.x as usize, d.y as usize, d.z as usize],
            anchor,
            ..*self
        }
    }

    /// The first stored node's index minus the anchor's, per axis (cells): a position `x`
    /// (m, from the anchor) has the local stencil base `⌊x/dx − ½⌋ − shift`.
    #[inline]
    pub fn shift(&self) -> [f64; 3] {
        (self.origin - self.anchor).as_dvec3().to_array()
    }

    /// The world box (m) of the stored nodes.
    pub fn extent(&self) -> Aabb {
        let hi = self.origin
            + IVec3::new(
                self.dims[0] as i32,
                self.dims[1] as i32,
                self.dims[2] as i32,
            )
            - IVec3::ONE;
        Aabb::new(self.origin.as_dvec3() * self.dx, hi.as_dvec3() * self.dx)
    }

    /// Total node count.
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// `true` for an empty grid (never for a constructed one).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Nodes per x-layer.
    #[inline]
    pub fn layer(&self) -> usize {
        self.dims[1] * self.dims[2]
    }

    /// Linear index of a local node index (x-major).
    #[inline]
    pub fn linear(&self, l: [usize; 3]) -> usize {
        (l[0] * self.dims[1] + l[1]) * self.dims[2] + l[2]
    }

    /// Local index of a linear index.
    #[inline]
    pub fn unlinear(&self, i: usize) -> [usize; 3] {
        let z = i % self.dims[2];
        let r = i / self.dims[2];
        [r / self.dims[1], r % self.dims[1], z]
    }

    /// The three z-consecutive entries of `data` (a grid array, or a chunk starting at x-layer
    /// `first_layer`) at stencil row `(local.x + i, local.y + j, local.z ..)`.
    #[inline(always)]
    pub fn row<'a, T>(&self, data: &'a [T], local: [usize; 3], i: usize, j: usize) -> &'a [T] {
        let r = self.linear([local[0] + i, local[1] + j, local[2]]);
        &data[r..r + 3]
    }

    /// Mutable [`Self::row`] of a chunk that starts at x-layer `first_layer`.
    #[inline(always)]
    pub fn row_mut<'a, T>(
        &self,
        data: &'a mut [T],
        first_layer: usize,
        local: [usize; 3],
        i: usize,
        j: usize,
    ) -> &'a mut [T] {
        let r = self.linear([local[0] + i, local[1] + j, local[2]]) - first_layer * self.layer();
        &mut data[r..r + 3]
    }

    /// World position (m) of a local node index.
    #[inline]
    pub fn node_pos(&self, l: [usize; 3]) -> DVec3 {
        (self.origin + IVec3::new(l[0] as i32, l[1] as i32, l[2] as i32)).as_dvec3() * self.dx
    }

    /// Stencil of a particle at `x` (m); `x` must lie in the domain.
    #[inline(always)]
    pub fn stencil(&self, x: DVec3) -> Stencil {
        let xs = x * self.inv_dx;
        // base = ⌊x/dx − 1/2⌋ (cells) and its local index.
        let h = xs - DVec3::splat(0.5);
        let base = DVec3::new(floor1(h.x), floor1(h.y), floor1(h.z));
        let b = base.as_ivec3() - self.origin;
        debug_assert!(
            b.min_element() >= 0,
            "particle at {xs:?} cells below the grid"
        );
        let local = [
            b.x.max(0) as usize,
            b.y.max(0) as usize,
            b.z.max(0) as usize,
        ];
        let fx = xs - base;
        debug_assert!(
            (0..3).all(|a| local[a] + 2 < self.dims[a]),
            "particle {x:?} beyond the grid"
        );
        let w = [
            0.5 * (DVec3::splat(1.5) - fx) * (DVec3::splat(1.5) - fx),
            DVec3::splat(0.75) - (fx - DVec3::ONE) * (fx - DVec3::ONE),
            0.5 * (fx - DVec3::splat(0.5)) * (fx - DVec3::splat(0.5)),
        ];
        let dw = [
            fx - DVec3::splat(1.5),
            -2.0 * (fx - DVec3::ONE),
            fx - DVec3::splat(0.5),
        ];
        Stencil { local, fx, w, dw }
    }

    /// Clamp a position into the particle domain; returns `true` if it moved.
    #[inline(always)]
    pub fn hold(&self, x: &mut DVec3) -> bool {
        let c = x.clamp(self.domain.lo, self.domain.hi);
        let moved = c != *x;
        *x = c;
        moved
    }
}

/// The nodes a set of particles touches: x-layers `x`, y-rows `y` and z-columns `z` (local
/// indices; in the x-major layout each `(x, y)` row's part is one contiguous index range).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeBox {
    /// Local x indices.
    pub x: Range<usize>,
    /// Local y indices.
    pub y: Range<usize>,
    /// Local z indices.
    pub z: Range<usize>,
}

impl NodeBox {
    /// The box's linear index range in each of its `(x, y)` rows.
    pub fn rows(&self, grid: &GridSpec) -> impl Iterator<Item = Range<usize>> + use<> {
        let (layer, dz) = (grid.layer(), grid.dims[2]);
        let (ys, z) = (self.y.clone(), self.z.clone());
        self.x.clone().flat_map(move |x| {
            let z = z.clone();
            ys.clone().map(move |y| {
                let at = x * layer + y * dz;
                at + z.start..at + z.end
            })
        })
    }

    /// Sets the box's entries of a grid array to `v`.
    pub fn fill<T: Clone>(&self, grid: &GridSpec, data: &mut [T], v: T) {
        for r in self.rows(grid) {
            data[r].fill(v.clone());
        }
    }
}

/// `floor` without a libm call (exact for |x| < 2⁵³; the baseline x86-64 target lacks `roundsd`).
#[inline(always)]
pub(crate) fn floor1(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x { t - 1.0 } else { t }
}

/// Quadratic B-spline stencil of one particle: 3 weights per axis and their derivatives.
#[derive(Debug, Clone, Copy)]
pub struct Stencil {
    /// Local index of the first of the 3×3×3 nodes.
    pub local: [usize; 3],
    /// `x/dx − base`, in [0.5, 1.5).
    pub fx: DVec3,
    /// `w[o]` = per-axis weights of offset `o` ∈ {0,1,2}.
    pub w: [DVec3; 3],
    /// `d w[o] / d fx` per axis.
    pub dw: [DVec3; 3],
}

impl Stencil {
    /// Weight of offset `o`.
    #[inline]
    pub fn weight(&self, o: [usize; 3]) -> f64 {
        self.w[o[0]].x * self.w[o[1]].y * self.w[o[2]].z
    }

    /// Gradient of the weight of offset `o` w.r.t. the particle position (1/m).
    #[inline]
    pub fn grad_weight(&self, o: [usize; 3], inv_dx: f64) -> DVec3 {
        let (wx, wy, wz) = (self.w[o[0]].x, self.w[o[1]].y, self.w[o[2]].z);
        DVec3::new(
            self.dw[o[0]].x * wy * wz,
            wx * self.dw[o[1]].y * wz,
            wx * wy * self.dw[o[2]].z,
        ) * inv_dx
    }

    /// `node − particle` offset (m) of offset `o`.
    #[inline]
    pub fn dpos(&self, o: [usize; 3], dx: f64) -> DVec3 {
        (DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64) - self.fx) * dx
    }

    /// Calls `f(o, index, weight, dpos)` for the 27 nodes, `index` being the linear node index
    /// minus `first_layer` x-layers (0 for the whole grid), `dpos = x_node − x` (m).
    #[inline(always)]
    pub fn for_each_node(
        &self,
        grid: &GridSpec,
        first_layer: usize,
        mut f: impl FnMut([usize; 3], usize, f64, DVec3),
    ) {
        let sy = grid.dims[2];
        let sx = grid.dims[1] * sy;
        let base = grid.linear(self.local) - first_layer * sx;
        let dx = grid.dx;
        for i in 0..3 {
            let wi = self.w[i].x;
            let px = (i as f64 - self.fx.x) * dx;
            for j in 0..3 {
                let wij = wi * self.w[j].y;
                let py = (j as f64 - self.fx.y) * dx;
                let row = base + i * sx + j * sy;
                for k in 0..3 {
                    let pz = (k as f64 - self.fx.z) * dx;
                    f(
                        [i, j, k],
                        row + k,
                        wij * self.w[k].z,
                        DVec3::new(px, py, pz),
                    );
                }
            }
        }
    }

    /// `node − particle` offsets (m) per axis for offsets 0, 1, 2: `d[o].x` is `px` of `o`, etc.
    #[inline(always)]
    pub fn offsets(&self, dx: f64) -> [DVec3; 3] {
        [0.0, 1.0, 2.0].map(|o| (DVec3::splat(o) - self.fx) * dx)
    }

    /// Local node index of offset `o`.
    #[inline]
    pub fn node(&self, o: [usize; 3]) -> [usize; 3] {
        [
            self.local[0] + o[0],
            self.local[1] + o[1],
            self.local[2] + o[2],
        ]
    }
}

/// The 27 stencil offsets.
pub const OFFSETS: [[usize; 3]; 27] = {
    let mut out = [[0usize; 3]; 27];
    let mut i = 0;
    while i < 27 {
        out[i] = [i / 9, (i / 3) % 3, i % 3];
        i += 1;
    }
    out
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stencil_partition_of_unity_and_gradients() {
        let g = GridSpec::new(Aabb::new(DVec3::splat(-0.3), DVec3::ONE), 0.1, 2).unwrap();
        for x in [
            DVec3::new(0.123, -0.3, 0.999),
            DVec3::splat(1.0),
            DVec3::new(-0.3, 0.55, 0.05),
        ] {
            let st = g.stencil(x);
            let (mut sw, mut swd) = (0.0, DVec3::ZERO);
            for o in OFFSETS {
                sw += st.weight(o);
                swd += st.weight(o) * st.dpos(o, g.dx);
                let l = st.node(o);
                assert!((0..3).all(|a| l[a] < g.dims[a]));
                // Weight gradient against central differences.
                let h = 1e-7;
                for a in 0..3 {
                    let mut xp = x;
                    let mut xm = x;
                    xp[a] += h;
                    xm[a] -= h;
                    let (sp, sm) = (g.stencil(xp), g.stencil(xm));
                    if sp.local == st.local && sm.local == st.local {
                        let fd = (sp.weight(o) - sm.weight(o)) / (2.0 * h);
                        assert!((fd - st.grad_weight(o, g.inv_dx)[a]).abs() < 1e-6);
                    }
                }
            }
            assert!((sw - 1.0).abs() < 1e-14);
            assert!(swd.abs().max_element() < 1e-15);
        }
    }

    #[test]
    fn index_round_trip_and_invalid_grids() {
        let g = GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::new(1.0, 0.5, 0.3)), 0.1, 3).unwrap();
        for i in [0, 17, g.len() - 1] {
            assert_eq!(g.linear(g.unlinear(i)), i);
        }
        assert_eq!(g.node_pos([0, 0, 0]), DVec3::splat(-0.30000000000000004));
        assert!(GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.0, 2).is_err());
        assert!(GridSpec::new(Aabb::new(DVec3::ONE, DVec3::ZERO), 0.1, 2).is_err());
        assert!(GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::splat(1e9)), 0.1, 2).is_err());
        assert!(
            GridSpec::new(
                Aabb::new(DVec3::ZERO, DVec3::new(f64::NAN, 1.0, 1.0)),
                0.1,
                2
            )
            .is_err()
        );
    }
}
