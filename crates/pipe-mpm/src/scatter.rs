//! Race-free, thread-count-independent particle → grid scatter.
//!
//! Particles are binned by x-slabs: runs of whole cells, by the x index of their stencil base.
//! A particle of a slab starting at cell `a` and ending before cell `b` writes only x-layers
//! `[a, b + 2)`, so two slabs with at least `MIN_SLAB` = 2 cells between them never write the
//! same node. Even slabs are processed in parallel first (the grid split at the even slabs'
//! first layers), then odd slabs (split at the odd ones').
//!
//! The slabs hold equal shares of the particles (`slab_cuts`): `4k` slabs of at least two
//! cells, as many as the particles' x-extent allows (up to `MAX_SLABS`), so each colour is
//! `2k` equal tasks and two threads (or four, when k is even) finish a colour together. Narrow
//! clouds fall back to slabs of `FALLBACK_SLAB` cells. The cuts depend only on the positions,
//! and inside a slab particles run in ascending index order, so every node receives its
//! contributions in one fixed order whatever the thread count: results are bit-identical.

use glam::DVec3;
use rayon::prelude::*;

use crate::grid::{GridSpec, NodeBox};
use crate::isa::{Isa, Lanes, WithLanes};

/// Fewest cells in a slab: a stencil spans 3 layers, so same-colour slabs must be 2 apart.
const MIN_SLAB: usize = 2;

/// Most slabs per rebuild (a multiple of 4).
const MAX_SLABS: usize = 32;

/// Slab width (cells) when the particles are too narrow in x for 4 slabs of `MIN_SLAB`.
const FALLBACK_SLAB: usize = 3;

/// Particles per parallel task of [`Bins::rebuild`].
const BIN_CHUNK: usize = 4096;

/// Particles grouped by x-slab.
#[derive(Debug, Clone, Default)]
pub struct Bins {
    /// Particle indices ordered by slab (stable).
    pub order: Vec<u32>,
    /// `order[start[s]..start[s + 1]]` are the particles of slab `s`.
    pub start: Vec<usize>,
    /// Slab `s` holds the cells `first[s]..first[s + 1]` (x; `first[0] = 0`, the last entry is
    /// the grid's x size).
    pub first: Vec<usize>,
    /// The nodes the particles' stencils touch.
    pub touched: NodeBox,
    /// Scratch of [`Self::rebuild`] (kept to avoid allocating every substep): each particle's
    /// x cell, each task's particle count per x cell, then per slab, and each cell's slab.
    cell: Vec<u32>,
    counts: Vec<usize>,
    slab_counts: Vec<usize>,
    slab_of_cell: Vec<u32>,
}

impl Bins {
    /// Bin particles at positions `x` (inside the grid domain).
    pub fn new(grid: &GridSpec, x: &[DVec3]) -> Self {
        let mut b = Self::default();
        b.rebuild(grid, x);
        b
    }

    /// Re-bins particles at positions `x`, reusing the buffers: a stable counting sort run by
    /// tasks of `BIN_CHUNK` particles. Each task counts its particles per x cell; the cuts
    /// come from the summed counts; the slab ranges of `order` are then cut into one piece per
    /// task (tasks in particle order), so every task writes its own pieces and the result is
    /// the serial sort's, whatever the thread count.
    pub fn rebuild(&mut self, grid: &GridSpec, x: &[DVec3]) {
        let nx = grid.dims[0];
        let n_tasks = x.len().div_ceil(BIN_CHUNK);
        let isa = Isa::detect();
        self.cell.resize(x.len(), 0);
        self.counts.clear();
        self.counts.resize(n_tasks * nx, 0);
        let boxes: Vec<([usize; 2], [usize; 2])> = x
            .par_chunks(BIN_CHUNK)
            .zip(self.cell.par_chunks_mut(BIN_CHUNK))
            .zip(self.counts.par_chunks_mut(nx.max(1)))
            .map(|((xs, cells), counts)| {
                isa.run_lanes(CountTask {
                    grid,
                    xs,
                    cells,
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
        let per_cell: Vec<usize> = (0..nx)
            .map(|c| (0..n_tasks).map(|t| self.counts[t * nx + c]).sum())
            .collect();
        self.first = slab_cuts(&per_cell, x.len());
        let n_slabs = self.first.len() - 1;
        self.slab_of_cell.clear();
        for s in 0..n_slabs {
            let width = self.first[s + 1] - self.first[s];
            self.slab_of_cell
                .extend(std::iter::repeat_n(s as u32, width));
        }
        self.slab_counts.clear();
        self.slab_counts.resize(n_tasks * n_slabs, 0);
        for t in 0..n_tasks {
            for c in 0..nx {
                self.slab_counts[t * n_slabs + self.slab_of_cell[c] as usize] +=
                    self.counts[t * nx + c];
            }
        }
        self.start.clear();
        self.start.resize(n_slabs + 1, 0);
        for s in 0..n_slabs {
            let in_slab: usize = (0..n_tasks)
                .map(|t| self.slab_counts[t * n_slabs + s])
                .sum();
            self.start[s + 1] = self.start[s] + in_slab;
        }
        // Cut `order` into pieces in (slab, task) order and hand each task its pieces.
        self.order.resize(x.len(), 0);
        let mut pieces: Vec<Vec<&mut [u32]>> =
            (0..n_tasks).map(|_| Vec::with_capacity(n_slabs)).collect();
        let mut rest = self.order.as_mut_slice();
        for s in 0..n_slabs {
            for (t, task) in pieces.iter_mut().enumerate() {
                let (piece, tail) = rest.split_at_mut(self.slab_counts[t * n_slabs + s]);
                task.push(piece);
                rest = tail;
            }
        }
        let slab_of_cell = &self.slab_of_cell;
        pieces
            .into_par_iter()
            .zip(self.cell.par_chunks(BIN_CHUNK))
            .enumerate()
            .for_each(|(t, (task, cells))| {
                let mut out: Vec<_> = task.into_iter().map(|p| p.iter_mut()).collect();
                for (i, &c) in cells.iter().enumerate() {
                    let slot = out[slab_of_cell[c as usize] as usize].next();
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

    /// The slabs of one colour with their grid pieces ([`colour_pieces`]).
    fn colour<'o, T>(
        &self,
        parity: usize,
        layer: usize,
        out: &'o mut [T],
    ) -> Vec<(usize, usize, &'o mut [T])> {
        colour_pieces(&self.first, parity, layer, out)
    }
}

/// The slabs of one colour (`parity` 0: even, 1: odd) of the cuts `first` (x cells) with their
/// grid pieces, split off `out` (x-major, `layer` entries per x-layer): slab `s` gets layers
/// `first[s]..first[s + 2]`, which hold the stencils of all its particles. Returns
/// `(slab, first layer, piece)`.
pub(crate) fn colour_pieces<'o, T>(
    first: &[usize],
    parity: usize,
    layer: usize,
    mut out: &'o mut [T],
) -> Vec<(usize, usize, &'o mut [T])> {
    let n_slabs = first.len().saturating_sub(1);
    let mut pieces = Vec::with_capacity(n_slabs / 2 + 1);
    let mut at = 0;
    for s in (parity..n_slabs).step_by(2) {
        let (lo, hi) = (first[s], first[(s + 2).min(n_slabs)]);
        let (_, tail) = out.split_at_mut((lo - at) * layer);
        let (piece, tail) = tail.split_at_mut((hi - lo) * layer);
        pieces.push((s, lo, piece));
        out = tail;
        at = hi;
    }
    pieces
}

/// Slab boundaries (cells; `0`, the cuts, `nx`) for `n` particles counted per x cell: the
/// most slabs, a multiple of 4 up to `MAX_SLABS`, whose equal-count cuts leave every slab
/// at least `MIN_SLAB` cells wide; slabs of `FALLBACK_SLAB` cells when not even 4 fit.
pub(crate) fn slab_cuts(per_cell: &[usize], n: usize) -> Vec<usize> {
    let nx = per_cell.len();
    let mut k = (nx / MIN_SLAB).min(MAX_SLABS) / 4 * 4;
    while k >= 4 && n > 0 {
        if let Some(cuts) = equal_count_cuts(per_cell, n, k) {
            return cuts;
        }
        k -= 4;
    }
    (0..nx.div_ceil(FALLBACK_SLAB))
        .map(|s| s * FALLBACK_SLAB)
        .chain(std::iter::once(nx))
        .collect()
}

/// Boundaries of `k` slabs: cut `i` is the cell boundary whose count of particles below is
/// nearest `i·n/k` (the upper one on a tie); `None` if a slab would be narrower than
/// `MIN_SLAB`.
fn equal_count_cuts(per_cell: &[usize], n: usize, k: usize) -> Option<Vec<usize>> {
    let nx = per_cell.len();
    // below[b] = particles in cells < b.
    let below: Vec<usize> = std::iter::once(0)
        .chain(per_cell.iter().scan(0, |acc, &m| {
            *acc += m;
            Some(*acc)
        }))
        .collect();
    let mut cuts = Vec::with_capacity(k + 1);
    cuts.push(0);
    for i in 1..k {
        // Compare in units of 1/k particle: target i·n.
        let target = i * n;
        let hi = below.partition_point(|&b| b * k < target);
        let lo = hi.saturating_sub(1);
        let cut = if hi < below.len() && below[hi] * k - target <= target - below[lo] * k {
            hi
        } else {
            lo
        };
        cuts.push(cut);
    }
    cuts.push(nx);
    cuts.windows(2)
        .all(|w| w[1] >= w[0] + MIN_SLAB)
        .then_some(cuts)
}

/// One task of [`Bins::rebuild`]'s first pass: each particle's x cell, the task's count per
/// x cell and the `(lo, hi)` of its stencil bases in x and y.
struct CountTask<'a> {
    grid: &'a GridSpec,
    xs: &'a [DVec3],
    cells: &'a mut [u32],
    counts: &'a mut [usize],
}

impl WithLanes for CountTask<'_> {
    type Output = ([usize; 2], [usize; 2]);

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) -> Self::Output {
        let (mut lo, mut hi) = ([usize::MAX; 2], [0; 2]);
        for (&p, c) in self.xs.iter().zip(self.cells) {
            let b = self.grid.stencil_base(l, p);
            for a in 0..2 {
                lo[a] = lo[a].min(b[a]);
                hi[a] = hi[a].max(b[a]);
            }
            *c = b[0] as u32;
            self.counts[b[0]] += 1;
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
    // No per-particle output: a zero-sized one (no allocation).
    let mut none = vec![(); bins.order.len()];
    scatter_with_slabs(grid, bins, out, &mut none, |ps, _, chunk, first| {
        f(ps, chunk, first)
    });
}

/// [`scatter_slabs`] that also hands `f` the slab's entries of `per`, an output buffer in bin
/// order (`per[i]` belongs to particle `bins.order[i]`): `f(particles, entries, chunk, first)`.
pub fn scatter_with_slabs<T, O, F>(grid: &GridSpec, bins: &Bins, out: &mut [T], per: &mut [O], f: F)
where
    T: Send,
    O: Send,
    F: Fn(&[u32], &mut [O], &mut [T], usize) + Sync,
{
    debug_assert_eq!(out.len(), grid.len());
    debug_assert_eq!(per.len(), bins.order.len());
    // Split `per` by slab, then by parity (as the grid pieces of `Bins::colour`).
    let mut by_parity: [Vec<&mut [O]>; 2] = [Vec::new(), Vec::new()];
    let mut rest = per;
    for s in 0..bins.start.len().saturating_sub(1) {
        let (mine, tail) = rest.split_at_mut(bins.start[s + 1] - bins.start[s]);
        rest = tail;
        by_parity[s % 2].push(mine);
    }
    for (parity, entries) in by_parity.into_iter().enumerate() {
        let pieces = bins.colour(parity, grid.layer(), out);
        debug_assert_eq!(pieces.len(), entries.len());
        pieces
            .into_par_iter()
            .zip(entries)
            .for_each(|((s, first, piece), os)| f(bins.slab(s), os, piece, first));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cuts are equal-count, at least two cells wide, a multiple of 4 when they can be, and
    /// fall back to 3-cell slabs for narrow clouds.
    #[test]
    fn cuts_balance_the_particles() {
        // 40 cells, particles uniform over cells 10..30 (100 each).
        let mut per_cell = vec![0; 40];
        per_cell[10..30].fill(100);
        let cuts = slab_cuts(&per_cell, 2000);
        assert_eq!(cuts.first(), Some(&0));
        assert_eq!(cuts.last(), Some(&40));
        assert_eq!((cuts.len() - 1) % 4, 0);
        // 20 occupied cells: 8 slabs alternating 3 and 2 cells (300 and 200 particles); 12
        // would need slabs of one cell.
        assert_eq!(cuts, vec![0, 13, 15, 18, 20, 23, 25, 28, 40]);
        for w in cuts.windows(2) {
            assert!(w[1] - w[0] >= MIN_SLAB, "{cuts:?}");
        }
        let share = |s: usize| per_cell[cuts[s]..cuts[s + 1]].iter().sum::<usize>();
        let n_slabs = cuts.len() - 1;
        let max = (0..n_slabs).map(share).max().unwrap();
        assert!(max * n_slabs <= 2000 * 3 / 2, "{cuts:?}");
        // A cloud 5 cells wide cannot hold 4 slabs of 2 cells: fixed 3-cell slabs.
        let mut narrow = vec![0; 12];
        narrow[4..9].fill(10);
        assert_eq!(slab_cuts(&narrow, 50), vec![0, 3, 6, 9, 12]);
        // All particles in one cell: fallback too.
        let mut one = vec![0; 12];
        one[5] = 1000;
        assert_eq!(slab_cuts(&one, 1000), vec![0, 3, 6, 9, 12]);
    }

    /// Every particle lands in the slab of its cell, in ascending order, and each colour's
    /// grid pieces are disjoint and cover every stencil of their slab.
    #[test]
    fn bins_are_a_stable_sort_and_pieces_cover_the_stencils() {
        let grid = GridSpec::new(crate::Aabb::new(DVec3::ZERO, DVec3::ONE), 1.0 / 32.0, 3).unwrap();
        let mut x = Vec::new();
        for i in 0..9000u32 {
            let h = |k: u32| (i.wrapping_mul(2_654_435_761).rotate_left(k) % 1000) as f64 / 1e3;
            x.push(DVec3::new(
                0.2 + 0.5 * h(0) * h(5),
                0.3 + 0.4 * h(11),
                0.5 * h(22) + 0.2,
            ));
        }
        let bins = Bins::new(&grid, &x);
        let n_slabs = bins.first.len() - 1;
        assert!(n_slabs >= 4);
        let mut seen = vec![false; x.len()];
        for s in 0..n_slabs {
            let ps = bins.slab(s);
            assert!(ps.windows(2).all(|w| w[0] < w[1]));
            for &p in ps {
                let b = grid.stencil(x[p as usize]).local[0];
                assert!((bins.first[s]..bins.first[s + 1]).contains(&b));
                seen[p as usize] = true;
            }
        }
        assert!(seen.iter().all(|&v| v));
        let layer = grid.layer();
        for parity in 0..2 {
            let mut grid_data = vec![0u8; grid.len()];
            for (s, first, piece) in bins.colour(parity, layer, &mut grid_data) {
                assert_eq!(s % 2, parity);
                for &p in bins.slab(s) {
                    let b = grid.stencil(x[p as usize]).local[0];
                    assert!(b >= first && (b + 3) * layer <= first * layer + piece.len());
                }
                piece.fill(1);
            }
        }
    }
}
