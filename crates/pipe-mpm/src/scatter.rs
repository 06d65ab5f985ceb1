//! Race-free, thread-count-independent particle → grid scatter.
//!
//! Particles are binned by x-slabs of [`SLAB`] = 3 cells (by the x index of their stencil
//! base); a particle of slab `s` writes only x-layers `[3s, 3s + 5)`. Even slabs are processed
//! in parallel first (grid split into disjoint chunks of 6 layers), then odd slabs (chunks
//! shifted by 3 layers).
//! Inside a slab particles run in ascending index order, so every node receives its
//! contributions in one fixed order whatever the thread count: results are bit-identical.

use glam::DVec3;
use rayon::prelude::*;

use crate::grid::{GridSpec, NodeBox};
use crate::isa::{Isa, Lanes, WithLanes};

/// Width of a slab in cells (≥ 2, so that slabs of one colour, 2·SLAB layers apart, never
/// write the same layer: a slab's particles write SLAB + 2 layers).
pub(crate) const SLAB: usize = 3;

/// Layers of one parallel chunk: a slab's and the next slab's (the other colour) cells.
const CHUNK_LAYERS: usize = 2 * SLAB;

/// Particles per parallel task of [`Bins::rebuild`].
const BIN_CHUNK: usize = 4096;

/// Particles grouped by x-slab.
#[derive(Debug, Clone, Default)]
pub struct Bins {
    /// Particle indices ordered by slab (stable).
    pub order: Vec<u32>,
    /// `order[start[s]..start[s + 1]]` are the particles of slab `s`.
    pub start: Vec<usize>,
    /// The nodes the particles' stencils touch.
    pub touched: NodeBox,
    /// Scratch of [`Self::rebuild`] (kept to avoid allocating every substep): each particle's
    /// slab, and each task's particle count per slab.
    slab: Vec<u32>,
    counts: Vec<usize>,
}

impl Bins {
    /// Bin particles at positions `x` (inside the grid domain).
    pub fn new(grid: &GridSpec, x: &[DVec3]) -> Self {
        let mut b = Self::default();
        b.rebuild(grid, x);
        b
    }

    /// Re-bins particles at positions `x`, reusing the buffers: a stable counting sort run by
    /// tasks of [`BIN_CHUNK`] particles. Each task counts its particles per slab; the slab
    /// ranges of `order` are then cut into one piece per task (tasks in particle order), so
    /// every task writes its own pieces and the result is the serial sort's, whatever the
    /// thread count.
    pub fn rebuild(&mut self, grid: &GridSpec, x: &[DVec3]) {
        let n_slabs = grid.dims[0].div_ceil(SLAB);
        let n_tasks = x.len().div_ceil(BIN_CHUNK);
        let isa = Isa::detect();
        self.slab.resize(x.len(), 0);
        self.counts.clear();
        self.counts.resize(n_tasks * n_slabs, 0);
        let boxes: Vec<([usize; 2], [usize; 2])> = x
            .par_chunks(BIN_CHUNK)
            .zip(self.slab.par_chunks_mut(BIN_CHUNK))
            .zip(self.counts.par_chunks_mut(n_slabs.max(1)))
            .map(|((xs, slabs), counts)| {
                isa.run_lanes(CountTask {
                    grid,
                    xs,
                    slabs,
                    counts,
                })
            })
            .collect();
        let (lo, hi) = boxes.iter().fold(
            ([usize::MAX; 2], [0; 2]),
            |(lo, hi): ([usize; 2], [usize; 2]), (l, h)| {
                (
                    [lo[0].min(l[0]), lo[1].min(l[1])],
                    [hi[0].max(h[0]), hi[1].max(h[1])],
                )
            },
        );
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
        for s in 0..n_slabs {
            let in_slab: usize = (0..n_tasks).map(|t| self.counts[t * n_slabs + s]).sum();
            self.start[s + 1] = self.start[s] + in_slab;
        }
        // Cut `order` into pieces in (slab, task) order and hand each task its pieces.
        self.order.resize(x.len(), 0);
        let mut pieces: Vec<Vec<&mut [u32]>> = (0..n_tasks)
            .map(|_| Vec::with_capacity(n_slabs))
            .collect();
        let mut rest = self.order.as_mut_slice();
        for s in 0..n_slabs {
            for (t, task) in pieces.iter_mut().enumerate() {
                let (piece, tail) = rest.split_at_mut(self.counts[t * n_slabs + s]);
                task.push(piece);
                rest = tail;
            }
        }
        pieces
            .into_par_iter()
            .zip(self.slab.par_chunks(BIN_CHUNK))
            .enumerate()
            .for_each(|(t, (task, slabs))| {
                let mut out: Vec<_> = task.into_iter().map(|p| p.iter_mut()).collect();
                for (i, &s) in slabs.iter().enumerate() {
                    let slot = out[s as usize].next();
                    debug_assert!(slot.is_some(), "pieces are sized by the counts");
                    if let Some(o) = slot {
                        *o = (t * BIN_CHUNK + i) as u32;
                    }
                }
            });
    }

    fn slab(&self, s: usize) -> &[u32] {
        if s + 1 < self.start.len() {
            &self.order[self.start[s]..self.start[s + 1]]
        } else {
            &[]
        }
    }
}

/// One task of [`Bins::rebuild`]'s first pass: each particle's slab, the task's count per slab
/// and the `(lo, hi)` of its stencil bases in x and y.
struct CountTask<'a> {
    grid: &'a GridSpec,
    xs: &'a [DVec3],
    slabs: &'a mut [u32],
    counts: &'a mut [usize],
}

impl WithLanes for CountTask<'_> {
    type Output = ([usize; 2], [usize; 2]);

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) -> Self::Output {
        let (mut lo, mut hi) = ([usize::MAX; 2], [0; 2]);
        for (&p, s) in self.xs.iter().zip(self.slabs) {
            let b = self.grid.stencil_base(l, p);
            for a in 0..2 {
                lo[a] = lo[a].min(b[a]);
                hi[a] = hi[a].max(b[a]);
            }
            *s = (b[0] / SLAB) as u32;
            self.counts[*s as usize] += 1;
        }
        (lo, hi)
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
    let chunk = CHUNK_LAYERS * layer;
    out.par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(k, c)| f(bins.slab(2 * k), c, CHUNK_LAYERS * k));
    if out.len() > SLAB * layer {
        out[SLAB * layer..]
            .par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(k, c)| f(bins.slab(2 * k + 1), c, CHUNK_LAYERS * k + SLAB));
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
    let chunk = CHUNK_LAYERS * layer;
    // Split `per` by slab, then by parity (even slabs pair with the chunks at 2·SLAB·k, odd
    // ones with the chunks at 2·SLAB·k + SLAB, as in `scatter_slabs`).
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
        .for_each(|(k, (c, (ps, os)))| f(ps, os, c, CHUNK_LAYERS * k));
    if out.len() > SLAB * layer {
        debug_assert!(odd.len() <= (out.len() - SLAB * layer).div_ceil(chunk));
        out[SLAB * layer..]
            .par_chunks_mut(chunk)
            .zip(odd)
            .enumerate()
            .for_each(|(k, (c, (ps, os)))| f(ps, os, c, CHUNK_LAYERS * k + SLAB));
    }
}
