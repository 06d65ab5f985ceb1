//! Race-free, thread-count-independent particle → grid scatter.
//!
//! Particles are binned by x-slabs of 3 cells (by the x index of their stencil base); a particle
//! of slab `s` writes only x-layers `[3s, 3s + 5)`. Even slabs are processed in parallel first
//! (grid split into disjoint chunks of 6 layers), then odd slabs (chunks shifted by 3 layers).
//! Inside a slab particles run in ascending index order, so every node receives its
//! contributions in one fixed order whatever the thread count: results are bit-identical.

use glam::DVec3;
use rayon::prelude::*;

use crate::grid::GridSpec;

/// Particles grouped by x-slab.
#[derive(Debug, Clone, Default)]
pub struct Bins {
    /// Particle indices ordered by slab (stable).
    pub order: Vec<u32>,
    /// `order[start[s]..start[s + 1]]` are the particles of slab `s`.
    pub start: Vec<usize>,
}

impl Bins {
    /// Bin particles at positions `x` (inside the grid domain).
    pub fn new(grid: &GridSpec, x: &[DVec3]) -> Self {
        let n_slabs = grid.dims[0].div_ceil(3);
        let slab: Vec<usize> = x.iter().map(|&p| grid.stencil(p).local[0] / 3).collect();
        let mut count = vec![0usize; n_slabs + 1];
        for &s in &slab {
            count[s + 1] += 1;
        }
        for s in 0..n_slabs {
            count[s + 1] += count[s];
        }
        let start = count.clone();
        let mut fill = count;
        let mut order = vec![0u32; x.len()];
        for (p, &s) in slab.iter().enumerate() {
            order[fill[s]] = p as u32;
            fill[s] += 1;
        }
        Self { order, start }
    }

    fn slab(&self, s: usize) -> &[u32] {
        if s + 1 < self.start.len() {
            &self.order[self.start[s]..self.start[s + 1]]
        } else {
            &[]
        }
    }
}

/// Calls `f(particle, chunk, first_layer)` for every particle, where `chunk` is a mutable view of
/// the grid array starting at x-layer `first_layer` that covers all 27 stencil nodes.
pub fn scatter<T, F>(grid: &GridSpec, bins: &Bins, out: &mut [T], f: F)
where
    T: Send,
    F: Fn(usize, &mut [T], usize) + Sync,
{
    let layer = grid.layer();
    debug_assert_eq!(out.len(), grid.len());
    let chunk = 6 * layer;
    out.par_chunks_mut(chunk).enumerate().for_each(|(k, c)| {
        for &p in bins.slab(2 * k) {
            f(p as usize, c, 6 * k);
        }
    });
    if out.len() > 3 * layer {
        out[3 * layer..]
            .par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(k, c)| {
                for &p in bins.slab(2 * k + 1) {
                    f(p as usize, c, 6 * k + 3);
                }
            });
    }
}
