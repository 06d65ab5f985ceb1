//! Particle groups: runs of up to one vector's worth of consecutive particles that share a
//! stencil base cell, so one vector holds a whole group and its 27 nodes are the same for every
//! lane (a node value is broadcast, never gathered).
//!
//! The particles are kept sorted by base cell (a stable counting sort, [`Order`]); between
//! sorts they move, runs break and groups get smaller but stay correct. The groups are also
//! bucketed by x-slabs for the race-free scatter ([`crate::scatter`]'s cuts and colours).

use rayon::prelude::*;

use super::simd::{Precise, Wide, WideOp};
use super::soa::Soa;
use crate::grid::{GridSpec, NodeBox};
use crate::isa::Isa;
use crate::scatter::{colour_pieces, slab_cuts};

/// Particles `start .. start + n` (slots) share the stencil base `base` (local node index;
/// `cell` is its linear index).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Group {
    pub start: u32,
    pub n: u32,
    pub cell: u32,
    pub base: [u32; 3],
}

/// Particles per task of the key pass (groups are also cut at its multiples, so they do not
/// depend on the thread count).
const KEY_CHUNK: usize = 4096;

/// The groups of a substep, bucketed by slab.
#[derive(Debug, Clone, Default)]
pub(crate) struct Groups {
    /// Each slot's base cell (linear local index).
    pub key: Vec<u32>,
    /// Groups in slot order.
    pub list: Vec<Group>,
    /// Groups ordered by slab (stable); slab `s` holds `by_slab[start[s]..start[s + 1]]`.
    pub by_slab: Vec<Group>,
    pub start: Vec<usize>,
    /// Slab `s` holds the base cells `first[s]..first[s + 1]` in x.
    pub first: Vec<usize>,
    /// The nodes the particles' stencils touch.
    pub touched: NodeBox,
    /// Scratch of the slab bucketing: particles per x cell, each x cell's slab, next free
    /// place of each slab.
    per_cell: Vec<usize>,
    slab_of: Vec<u32>,
    fill: Vec<usize>,
}

/// The key pass of one task: each particle's stencil base `⌊x/dx − ½⌋` (local node index,
/// clamped into the grid: positions are held in the domain, whose stencils fit the grid, so
/// the clamp only guards the index arithmetic), its linear index into `keys`, and the box of
/// the bases.
struct KeyTask<'a, T> {
    grid: &'a GridSpec,
    /// The task's first slot.
    first: usize,
    /// Positions from the task's first particle (padded arrays, so whole vectors load).
    x: [&'a [T]; 3],
    keys: &'a mut [u32],
}

impl<T: Precise> WideOp<T> for KeyTask<'_, T> {
    /// The box of the bases and the task's groups (runs of equal keys, cut at `T::N` and at
    /// the task's end).
    type Output = ([usize; 3], [usize; 3], Vec<Group>);

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) -> Self::Output {
        let KeyTask {
            grid,
            first,
            x,
            keys,
        } = self;
        let mut groups = Vec::with_capacity(keys.len() / 4);
        let mut run = Group {
            start: first as u32,
            n: 0,
            cell: u32::MAX,
            base: [0; 3],
        };
        let n = keys.len();
        let inv = w.c(grid.inv_dx);
        let top: [W::V; 3] = arr!(3, |a| w.c((grid.dims[a] - 3) as f64));
        let (dy, dz) = (w.c(grid.dims[1] as f64), w.c(grid.dims[2] as f64));
        // The linear index is exact in T below 2^(mantissa bits).
        let exact = (grid.len() as f64) < if T::N == 8 { 16_777_216.0 } else { 9e15 };
        let (mut lo, mut hi) = ([w.c(f64::MAX); 3], [w.c(-1.0); 3]);
        let full = n / T::N * T::N;
        for s in (0..n).step_by(T::N) {
            let b: [W::V; 3] = arr!(3, |a| {
                let f = w.floor(w.sub(w.mul(w.load(&x[a][s..]), inv), w.c(0.5)));
                w.min(w.max(f, w.zero()), top[a])
            });
            let m = (n - s).min(T::N);
            let bu: [[u32; 8]; 3] = arr!(3, |a| w.to_u32(b[a]));
            if s < full {
                for a in 0..3 {
                    lo[a] = w.min(lo[a], b[a]);
                    hi[a] = w.max(hi[a], b[a]);
                }
            } else {
                // The tail: only its particles count towards the box.
                for a in 0..3 {
                    let (mut l, mut h) = (w.lanes(lo[a]), w.lanes(hi[a]));
                    for v in &w.lanes(b[a])[..m] {
                        if *v < l[0] {
                            l[0] = *v;
                        }
                        if *v > h[0] {
                            h[0] = *v;
                        }
                    }
                    lo[a] = w.vector(l);
                    hi[a] = w.vector(h);
                }
            }
            let k = if exact {
                w.to_u32(w.fma(w.fma(b[0], dy, b[1]), dz, b[2]))
            } else {
                arr!(8, |l| {
                    grid.linear([bu[0][l] as usize, bu[1][l] as usize, bu[2][l] as usize]) as u32
                })
            };
            keys[s..s + m].copy_from_slice(&k[..m]);
            for l in 0..m {
                if k[l] != run.cell || run.n as usize == T::N {
                    if run.n > 0 {
                        groups.push(run);
                    }
                    run = Group {
                        start: (first + s + l) as u32,
                        n: 0,
                        cell: k[l],
                        base: [bu[0][l], bu[1][l], bu[2][l]],
                    };
                }
                run.n += 1;
            }
        }
        if run.n > 0 {
            groups.push(run);
        }
        let box_of = |v: W::V, f: fn(f64, f64) -> f64, init: f64| {
            w.lanes(v)[..T::N]
                .iter()
                .fold(init, |acc, x| f(acc, x.f64()))
        };
        (
            arr!(3, |a| box_of(lo[a], f64::min, f64::MAX) as usize),
            arr!(3, |a| box_of(hi[a], f64::max, -1.0).max(0.0) as usize),
            groups,
        )
    }
}

impl Groups {
    /// Rebuilds keys, groups and slabs for the particles of `p` (positions inside the domain).
    pub fn rebuild<T: Precise>(&mut self, grid: &GridSpec, p: &Soa<T>) {
        let n = p.n;
        let dims = grid.dims;
        self.key.resize(n, 0);
        let xs = [p.x(0), p.x(1), p.x(2)];
        // Keys, the bounding box of the bases and the groups, by tasks of KEY_CHUNK particles.
        let isa = Isa::detect();
        let tasks: Vec<([usize; 3], [usize; 3], Vec<Group>)> = self
            .key
            .par_chunks_mut(KEY_CHUNK)
            .enumerate()
            .map(|(t, keys)| {
                let at = t * KEY_CHUNK;
                isa.run_wide(KeyTask {
                    grid,
                    first: at,
                    x: [&xs[0][at..], &xs[1][at..], &xs[2][at..]],
                    keys,
                })
            })
            .collect();
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        self.list.clear();
        for (l, h, g) in &tasks {
            for a in 0..3 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(h[a]);
            }
            self.list.extend_from_slice(g);
        }
        self.touched = NodeBox {
            x: lo[0]..hi[0] + 3,
            y: lo[1]..hi[1] + 3,
            z: lo[2]..hi[2] + 3,
        };
        // Slabs: equal-count cuts of the particles' x cells, groups bucketed stably.
        self.per_cell.clear();
        self.per_cell.resize(dims[0], 0);
        for g in &self.list {
            self.per_cell[g.base[0] as usize] += g.n as usize;
        }
        self.first = slab_cuts(&self.per_cell, n);
        let n_slabs = self.first.len() - 1;
        self.slab_of.clear();
        for s in 0..n_slabs {
            let w = self.first[s + 1] - self.first[s];
            self.slab_of.extend(std::iter::repeat_n(s as u32, w));
        }
        self.start.clear();
        self.start.resize(n_slabs + 1, 0);
        for g in &self.list {
            self.start[self.slab_of[g.base[0] as usize] as usize + 1] += 1;
        }
        for s in 0..n_slabs {
            self.start[s + 1] += self.start[s];
        }
        self.fill.clear();
        self.fill.extend_from_slice(&self.start[..n_slabs]);
        self.by_slab.resize(self.list.len(), Group::default());
        for g in &self.list {
            let s = self.slab_of[g.base[0] as usize] as usize;
            self.by_slab[self.fill[s]] = *g;
            self.fill[s] += 1;
        }
    }

    /// Runs `f(groups, piece, first_layer)` for every slab with a mutable view of the grid
    /// array `out` from x-layer `first_layer` covering all its groups' stencils: even slabs in
    /// parallel, then odd ones (same-colour slabs write disjoint nodes).
    pub fn scatter<N: Send>(
        &self,
        grid: &GridSpec,
        out: &mut [N],
        f: impl Fn(&[Group], &mut [N], usize) + Sync,
    ) {
        for parity in 0..2 {
            colour_pieces(&self.first, parity, grid.layer(), out)
                .into_par_iter()
                .for_each(|(s, first, piece)| {
                    f(
                        &self.by_slab[self.start[s]..self.start[s + 1]],
                        piece,
                        first,
                    )
                });
        }
    }

    /// [`Self::scatter`] that also hands `f` the slab's entries of `per_group` (one per group,
    /// in slab order: `per_group[i]` belongs to `by_slab[i]`).
    pub fn scatter_with<N: Send, O: Send>(
        &self,
        grid: &GridSpec,
        out: &mut [N],
        per_group: &mut [O],
        f: impl Fn(&[Group], &mut [O], &mut [N], usize) + Sync,
    ) {
        debug_assert_eq!(per_group.len(), self.by_slab.len());
        let mut by_parity: [Vec<&mut [O]>; 2] = [Vec::new(), Vec::new()];
        let mut rest = per_group;
        for s in 0..self.start.len().saturating_sub(1) {
            let (mine, tail) = rest.split_at_mut(self.start[s + 1] - self.start[s]);
            rest = tail;
            by_parity[s % 2].push(mine);
        }
        for (parity, entries) in by_parity.into_iter().enumerate() {
            colour_pieces(&self.first, parity, grid.layer(), out)
                .into_par_iter()
                .zip(entries)
                .for_each(|((s, first, piece), os)| {
                    f(
                        &self.by_slab[self.start[s]..self.start[s + 1]],
                        os,
                        piece,
                        first,
                    )
                });
        }
    }

    /// Groups cut into tasks of about `per_task` particles, each a contiguous slot range
    /// `(groups, first_slot, end_slot)`.
    pub fn tasks(&self, per_task: usize) -> Vec<(&[Group], usize, usize)> {
        let mut out = Vec::new();
        let mut g0 = 0;
        while g0 < self.list.len() {
            let s0 = self.list[g0].start as usize;
            let mut g1 = g0;
            while g1 < self.list.len() && (self.list[g1].start as usize) < s0 + per_task {
                g1 += 1;
            }
            let last = self.list[g1 - 1];
            out.push((&self.list[g0..g1], s0, (last.start + last.n) as usize));
            g0 = g1;
        }
        out
    }
}

/// The first slot of each of `tasks` ([`Groups::tasks`]), then `n`: the cuts that split the
/// per-slot outputs between the tasks.
pub fn task_cuts(tasks: &[(&[Group], usize, usize)], n: usize) -> Vec<usize> {
    tasks
        .iter()
        .map(|t| t.1)
        .chain(std::iter::once(n))
        .collect()
}
