//! Race-free, thread-count-independent particle → grid scatter.
//!
//! Particles are binned by x-slabs of 3 cells (by the x index of their stencil base); a particle
//! of slab `s` writes only x-layers `[3s, 3s + 5)`. Even slabs are processed in parallel first
//! (grid split into disjoint chunks of 6 layers), then odd slabs (chunks shifted by 3 layers).
//! Inside a slab particles run in ascending index order, so every node receives its
//! contributions in one fixed order whatever the thread count: results are bit-identical.

use glam::DVec3;
use rayon::prelude::*;

use crate::grid::{GridSpec, NodeBox};
use crate::isa::Scalar;

/// Particles grouped by x-slab.
#[derive(Debug, Clone, Default)]
pub struct Bins {
    /// Particle indices ordered by slab (stable).
    pub order: Vec<u32>,
    /// `order[start[s]..start[s + 1]]` are the particles of slab `s`.
    pub start: Vec<usize>,
    /// The nodes the particles' stencils touch.
    pub touched: NodeBox,
    /// Scratch of [`Self::rebuild`] (kept to avoid allocating every substep).
    sorted: Vec<u32>,
    fill: Vec<usize>,
}

impl Bins {
    /// Bin particles at positions `x` (inside the grid domain).
    pub fn new(grid: &GridSpec, x: &[DVec3]) -> Self {
        let mut b = Self::default();
        b.rebuild(grid, x);
        b
    }

    /// Re-bins particles at positions `x`, reusing the buffers (a counting sort, stable).
    pub fn rebuild(&mut self, grid: &GridSpec, x: &[DVec3]) {
        let n_slabs = grid.dims[0].div_ceil(3);
        // `order` first holds each particle's slab, then is overwritten by the sorted indices.
        let mut slab = std::mem::take(&mut self.order);
        slab.clear();
        let (mut lo, mut hi) = ([usize::MAX; 2], [0; 2]);
        slab.extend(x.iter().map(|&p| {
            let l = grid.stencil_base(Scalar, p);
            for a in 0..2 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(l[a]);
            }
            (l[0] / 3) as u32
        }));
        self.touched = if x.is_empty() {
            NodeBox::default()
        } else {
            NodeBox {
                x: lo[0]..hi[0] + 3,
                y: lo[1]..hi[1] + 3,
            }
        };
        self.start.clear();
        self.start.resize(n_slabs + 1, 0);
        for &s in &slab {
            self.start[s as usize + 1] += 1;
        }
        for s in 0..n_slabs {
            self.start[s + 1] += self.start[s];
        }
        let mut fill = std::mem::take(&mut self.fill);
        fill.clear();
        fill.extend_from_slice(&self.start);
        let mut order = std::mem::take(&mut self.sorted);
        order.clear();
        order.resize(x.len(), 0);
        for (p, &s) in slab.iter().enumerate() {
            order[fill[s as usize]] = p as u32;
            fill[s as usize] += 1;
        }
        self.sorted = slab;
        self.fill = fill;
        self.order = order;
    }

    fn slab(&self, s: usize) -> &[u32] {
        if s + 1 < self.start.len() {
            &self.order[self.start[s]..self.start[s + 1]]
        } else {
            &[]
        }
    }
}

/// Runs `f(particles, chunk, first_layer)` for every slab: the slab's particles (in the order
/// they must be processed) and a mutable view of the grid array starting at x-layer
/// `first_layer` that covers all their stencil nodes.
pub fn scatter_slabs<T, F>(grid: &GridSpec, bins: &Bins, out: &mut [T], f: F)
where
    T: Send,
    F: Fn(&[u32], &mut [T], usize) + Sync,
{
    let layer = grid.layer();
    debug_assert_eq!(out.len(), grid.len());
    let chunk = 6 * layer;
    out.par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(k, c)| f(bins.slab(2 * k), c, 6 * k));
    if out.len() > 3 * layer {
        out[3 * layer..]
            .par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(k, c)| f(bins.slab(2 * k + 1), c, 6 * k + 3));
    }
}

/// [`scatter_slabs`] that also hands `f` the slab's entries of `per`, an output buffer in bin
/// order (`per[i]` belongs to particle `bins.order[i]`): `f(particles, entries, chunk, first)`.
pub fn scatter_with_slabs<T, O, F>(grid: &GridSpec, bins: &Bins, out: &mut [T], per: &mut [O], f: F)
where
    T: Send,
    O: Send,
    F: Fn(&[u32], &mut [O], &mut [T], usize) + Sync,
{
    let layer = grid.layer();
    debug_assert_eq!(out.len(), grid.len());
    debug_assert_eq!(per.len(), bins.order.len());
    let chunk = 6 * layer;
    // Split `per` by slab, then by parity (even slabs pair with the chunks at 6k, odd ones with
    // the chunks at 6k + 3, as in `scatter_slabs`).
    let (mut even, mut odd) = (Vec::new(), Vec::new());
    let mut rest = per;
    for s in 0..bins.start.len().saturating_sub(1) {
        let (mine, tail) = rest.split_at_mut(bins.start[s + 1] - bins.start[s]);
        rest = tail;
        let part = (bins.slab(s), mine);
        if s % 2 == 0 {
            even.push(part);
        } else {
            odd.push(part);
        }
    }
    debug_assert!(even.len() <= out.len().div_ceil(chunk));
    out.par_chunks_mut(chunk)
        .zip(even)
        .enumerate()
        .for_each(|(k, (c, (ps, os)))| f(ps, os, c, 6 * k));
    if out.len() > 3 * layer {
        debug_assert!(odd.len() <= (out.len() - 3 * layer).div_ceil(chunk));
        out[3 * layer..]
            .par_chunks_mut(chunk)
            .zip(odd)
            .enumerate()
            .for_each(|(k, (c, (ps, os)))| f(ps, os, c, 6 * k + 3));
    }
}
