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

/// Particles whose run starts the key pass collects before cutting their runs (a multiple of
/// the lane counts; one bit each in a `u64`).
const BLOCK: usize = 64;

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
    /// Scratch of the slab bucketing: particles per x cell, each x cell's slab.
    per_cell: Vec<usize>,
    slab_of: Vec<u32>,
    /// Scratch of the key tasks: each one's groups (the first `task_len` of a buffer kept at
    /// its largest size, so no pass re-initialises it) and particles per x cell.
    task_groups: Vec<Vec<Group>>,
    task_len: Vec<usize>,
    task_cells: Vec<Vec<usize>>,
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
    /// The task's groups (runs of equal keys, cut at `T::N` and at the task's end), written
    /// from the start (room for one per particle and one more).
    groups: &'a mut [Group],
    /// The task's particles per x cell of their bases, added to.
    per_cell: &'a mut [usize],
}

impl<T: Precise> WideOp<T> for KeyTask<'_, T> {
    /// The box of the bases, and the number of groups.
    type Output = ([usize; 3], [usize; 3], usize);

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) -> Self::Output {
        let KeyTask {
            grid,
            first,
            x,
            keys,
            groups,
            per_cell,
        } = self;
        let mut run = Group {
            start: first as u32,
            n: 0,
            cell: u32::MAX,
            base: [0; 3],
        };
        let mut prev = u32::MAX;
        let mut cut = RunCutter {
            out: groups,
            count: 0,
            per_cell,
            pending: false,
            lanes: T::N as u32,
        };
        let n = keys.len();
        let inv = w.c(grid.inv_dx);
        // Local bases: the window's first node is `shift` cells from the positions' anchor.
        let shift: [W::V; 3] = arr!(3, |a| w.c(grid.shift()[a]));
        let top: [W::V; 3] = arr!(3, |a| w.c((grid.dims[a] - 3) as f64));
        let (dy, dz) = (w.c(grid.dims[1] as f64), w.c(grid.dims[2] as f64));
        // The linear index is exact in T below 2^(mantissa bits).
        let exact = (grid.len() as f64) < if T::N == 8 { 16_777_216.0 } else { 9e15 };
        let (mut lo, mut hi) = ([w.c(f64::MAX); 3], [w.c(-1.0); 3]);
        let full = n / T::N * T::N;
        // Blocks of `BLOCK` particles: the vectors' run starts gather into one mask, whose runs
        // are then cut (one loop exit per block, not per vector).
        let mut bases = [[0u32; BLOCK]; 3];
        for b0 in (0..n).step_by(BLOCK) {
            let mut block_starts = 0u64;
            for s in (b0..(b0 + BLOCK).min(n)).step_by(T::N) {
                let b: [W::V; 3] = arr!(3, |a| {
                    let f = w.floor(w.sub(w.mul(w.load(&x[a][s..]), inv), w.c(0.5)));
                    w.min(w.max(w.sub(f, shift[a]), w.zero()), top[a])
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
                        grid.linear([bu[0][l] as usize, bu[1][l] as usize, bu[2][l] as usize])
                            as u32
                    })
                };
                if m == T::N {
                    // A whole vector: a copy of known length (no call to `memcpy`).
                    let whole: &mut [u32] = &mut keys[s..s + T::N];
                    for (out, key) in whole.iter_mut().zip(&k) {
                        *out = *key;
                    }
                } else {
                    keys[s..s + m].copy_from_slice(&k[..m]);
                }
                // Lanes whose key differs from the one before start a run (branch-free).
                let mut starts = 0u64;
                for (l, &key) in k[..m].iter().enumerate() {
                    starts |= u64::from(key != prev) << l;
                    prev = key;
                }
                block_starts |= starts << (s - b0);
                for (a, lanes) in bu.iter().enumerate() {
                    let out: &mut [u32] = &mut bases[a][s - b0..s - b0 + T::N];
                    for (o, v) in out.iter_mut().zip(lanes) {
                        *o = *v;
                    }
                }
            }
            while block_starts != 0 {
                let l = block_starts.trailing_zeros() as usize;
                block_starts &= block_starts - 1;
                let at = (first + b0 + l) as u32;
                cut.push(run, at);
                run = Group {
                    start: at,
                    n: 0,
                    cell: keys[b0 + l],
                    base: [bases[0][l], bases[1][l], bases[2][l]],
                };
            }
        }
        cut.push(run, (first + n) as u32);
        let box_of = |v: W::V, f: fn(f64, f64) -> f64, init: f64| {
            w.lanes(v)[..T::N]
                .iter()
                .fold(init, |acc, x| f(acc, x.f64()))
        };
        (
            arr!(3, |a| box_of(lo[a], f64::min, f64::MAX) as usize),
            arr!(3, |a| box_of(hi[a], f64::max, -1.0).max(0.0) as usize),
            cut.count,
        )
    }
}

/// Cuts the key pass's runs of equal keys into groups, written from the start of `out` (room
/// for one group per particle and one more), and counts their particles per x cell.
struct RunCutter<'a> {
    out: &'a mut [Group],
    /// Groups written.
    count: usize,
    per_cell: &'a mut [usize],
    /// The last group written is a small one that [`super::transfer::Units::neighbours`]
    /// would leave alone.
    pending: bool,
    /// Lanes of a vector.
    lanes: u32,
}

impl RunCutter<'_> {
    /// The groups of the run of equal keys `run.start..end`: pieces of `lanes` particles and the
    /// rest.
    ///
    /// A rest of at most half a vector goes first when the group before it is `pending`, so the
    /// two share a vector; else last, where the next run's rest can join it. `pending` is
    /// updated as that pairing, left to right, would leave it.
    ///
    /// Runs of up to two vectors (all but a few) take no branch: both of their at most two
    /// groups are written, the second counted only when not empty.
    #[inline(always)]
    fn push(&mut self, run: Group, end: u32) {
        if end <= run.start {
            return;
        }
        let (lanes, pending) = (self.lanes, self.pending);
        let len = end - run.start;
        self.per_cell[run.base[0] as usize] += len as usize;
        let rest = len % lanes;
        let rest_first = (rest > 0) & (2 * rest <= lanes) & pending;
        if len <= 2 * lanes {
            let first = if rest_first { rest } else { len.min(lanes) };
            let second = len - first;
            self.out[self.count] = Group { n: first, ..run };
            self.out[self.count + 1] = Group {
                start: run.start + first,
                n: second,
                ..run
            };
            let after_first = (2 * first <= lanes) & !pending;
            let after_second = (2 * second <= lanes) & !after_first;
            self.pending = if second > 0 {
                after_second
            } else {
                after_first
            };
            self.count += 1 + usize::from(second > 0);
            return;
        }
        let mut at = run.start;
        let mut emit = |n: u32| {
            self.out[self.count] = Group {
                start: at,
                n,
                ..run
            };
            self.count += 1;
            at += n;
            self.pending = 2 * n <= lanes && !self.pending;
        };
        if rest_first {
            emit(rest);
        }
        for _ in 0..len / lanes {
            emit(lanes);
        }
        if rest > 0 && !rest_first {
            emit(rest);
        }
    }
}

impl Groups {
    /// Rebuilds keys, groups and slabs for the particles of `p` (positions inside the domain).
    ///
    /// Every pass runs by key task (`KEY_CHUNK` particles): the keys and each task's groups,
    /// their concatenation, and the bucketing by slab (each task writes its groups to its own
    /// place in each slab, so slabs hold their groups in slot order, as a serial stable
    /// bucketing would).
    pub fn rebuild<T: Precise>(&mut self, grid: &GridSpec, p: &Soa<T>) {
        let n = p.n;
        let dims = grid.dims;
        self.key.resize(n, 0);
        let xs = [p.x(0), p.x(1), p.x(2)];
        let n_tasks = n.div_ceil(KEY_CHUNK);
        self.task_groups.resize_with(n_tasks, Vec::new);
        self.task_len.resize(n_tasks, 0);
        self.task_cells.resize_with(n_tasks, Vec::new);
        let isa = Isa::detect();
        let boxes: Vec<([usize; 3], [usize; 3], usize)> = self
            .key
            .par_chunks_mut(KEY_CHUNK)
            .zip(self.task_groups.par_iter_mut())
            .zip(self.task_cells.par_iter_mut())
            .enumerate()
            .map(|(t, ((keys, groups), per_cell))| {
                let at = t * KEY_CHUNK;
                if groups.len() < keys.len() + 1 {
                    groups.resize(keys.len() + 1, Group::default());
                }
                per_cell.clear();
                per_cell.resize(dims[0], 0);
                isa.run_wide(KeyTask {
                    grid,
                    first: at,
                    x: [&xs[0][at..], &xs[1][at..], &xs[2][at..]],
                    keys,
                    groups,
                    per_cell,
                })
            })
            .collect();
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        for (t, (l, h, count)) in boxes.iter().enumerate() {
            self.task_len[t] = *count;
            for a in 0..3 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(h[a]);
            }
        }
        self.touched = NodeBox {
            x: lo[0]..hi[0] + 3,
            y: lo[1]..hi[1] + 3,
            z: lo[2]..hi[2] + 3,
        };
        // The tasks' groups, concatenated in slot order.
        let task_groups: Vec<&[Group]> = (self.task_groups.iter())
            .zip(&self.task_len)
            .map(|(g, &len)| &g[..len])
            .collect();
        let total: usize = self.task_len.iter().sum();
        self.list.resize(total, Group::default());
        let mut rest = self.list.as_mut_slice();
        let mut pieces = Vec::with_capacity(n_tasks);
        for g in &task_groups {
            let (mine, tail) = rest.split_at_mut(g.len());
            pieces.push(mine);
            rest = tail;
        }
        pieces
            .into_par_iter()
            .zip(task_groups.par_iter())
            .for_each(|(out, g)| out.copy_from_slice(g));
        // Slabs: equal-count cuts of the particles' x cells.
        self.per_cell.clear();
        self.per_cell.resize(dims[0], 0);
        for cells in &self.task_cells {
            for (sum, c) in self.per_cell.iter_mut().zip(cells) {
                *sum += c;
            }
        }
        self.first = slab_cuts(&self.per_cell, n);
        let n_slabs = self.first.len() - 1;
        self.slab_of.clear();
        for s in 0..n_slabs {
            let w = self.first[s + 1] - self.first[s];
            self.slab_of.extend(std::iter::repeat_n(s as u32, w));
        }
        // Each task's groups per slab, then each (slab, task)'s place in `by_slab`.
        let slab_of = &self.slab_of;
        let counts: Vec<Vec<usize>> = task_groups
            .par_iter()
            .map(|g| {
                let mut c = vec![0usize; n_slabs];
                for gr in g.iter() {
                    c[slab_of[gr.base[0] as usize] as usize] += 1;
                }
                c
            })
            .collect();
        self.start.clear();
        self.start.resize(n_slabs + 1, 0);
        for s in 0..n_slabs {
            self.start[s + 1] = self.start[s] + counts.iter().map(|c| c[s]).sum::<usize>();
        }
        self.by_slab.resize(total, Group::default());
        let mut places: Vec<Vec<&mut [Group]>> =
            (0..n_tasks).map(|_| Vec::with_capacity(n_slabs)).collect();
        let mut rest = self.by_slab.as_mut_slice();
        for s in 0..n_slabs {
            for (t, c) in counts.iter().enumerate() {
                let (mine, tail) = rest.split_at_mut(c[s]);
                places[t].push(mine);
                rest = tail;
            }
        }
        places
            .into_par_iter()
            .zip(task_groups.par_iter())
            .for_each(|(mut out, g)| {
                let mut fill = vec![0usize; n_slabs];
                for gr in g.iter() {
                    let s = slab_of[gr.base[0] as usize] as usize;
                    out[s][fill[s]] = *gr;
                    fill[s] += 1;
                }
            });
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

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::grid::Aabb;

    /// The parallel rebuild gives what a serial pass gives: runs of equal keys in slot order
    /// cut at the lane count (and at key-task boundaries), their particles per x cell, and a
    /// stable bucketing by slab.
    fn check<T: Precise>() {
        let grid = GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 1.0 / 24.0, 3).unwrap();
        // Clustered positions over several key tasks, with runs longer than a vector, runs cut
        // by strays and a tail shorter than a vector.
        let n = 3 * KEY_CHUNK + 13;
        let mut p = Soa::<T>::new(n);
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut at = [0.3, 0.4, 0.5];
        for i in 0..n {
            if i % 11 == 0 {
                at = [0.2 + 0.6 * next(), 0.2 + 0.6 * next(), 0.2 + 0.6 * next()];
            }
            let stray = next() < 0.1;
            for (a, centre) in at.iter().enumerate() {
                let jitter = if stray { 0.2 * next() } else { 0.01 * next() };
                p.x[a * p.stride + i] = T::of(centre + jitter - grid.origin[a] as f64 * grid.dx);
            }
        }
        let mut g = Groups::default();
        g.rebuild(&grid, &p);

        let base = |i: usize| -> [u32; 3] {
            std::array::from_fn(|a| {
                let f = (p.x[a * p.stride + i].f64() * grid.inv_dx - 0.5).floor();
                f.clamp(0.0, (grid.dims[a] - 3) as f64) as u32
            })
        };
        // Runs of one base, cut at key-task boundaries; each cut into vectors with the rest
        // first when the group before it is a small one still unpaired, else last.
        let lanes = T::N;
        let mut want: Vec<Group> = Vec::new();
        let mut per_cell = vec![0usize; grid.dims[0]];
        let mut pending = false;
        let mut i = 0;
        while i < n {
            if i % KEY_CHUNK == 0 {
                pending = false;
            }
            let b = base(i);
            let cell = grid.linear(b.map(|v| v as usize)) as u32;
            let mut j = i + 1;
            while j < n && base(j) == b && j % KEY_CHUNK != 0 {
                j += 1;
            }
            for k in i..j {
                assert_eq!(g.key[k], cell, "key of particle {k}");
            }
            per_cell[b[0] as usize] += j - i;
            let (len, rest) = (j - i, (j - i) % lanes);
            let mut sizes = vec![lanes; len / lanes];
            if rest > 0 {
                if 2 * rest <= lanes && pending {
                    sizes.insert(0, rest);
                } else {
                    sizes.push(rest);
                }
            }
            let mut at = i;
            for size in sizes {
                want.push(Group {
                    start: at as u32,
                    n: size as u32,
                    cell,
                    base: b,
                });
                at += size;
                pending = 2 * size <= lanes && !pending;
            }
            i = j;
        }
        // Some rests went first, next to the small group they pair with.
        assert!(
            want.windows(3)
                .any(|w| { w[0].cell != w[1].cell && w[1].cell == w[2].cell && w[1].n < w[2].n })
        );
        assert_eq!(g.list, want);
        assert!(want.iter().any(|x| x.n == 1) && want.iter().any(|x| x.n as usize == T::N));
        assert_eq!(g.first, slab_cuts(&per_cell, n));
        let slab = |gr: &Group| {
            g.first
                .iter()
                .rposition(|&f| f <= gr.base[0] as usize)
                .unwrap()
        };
        let mut by_slab = want.clone();
        by_slab.sort_by_key(slab);
        assert_eq!(g.by_slab, by_slab);
        for s in 0..g.first.len() - 1 {
            for gr in &g.by_slab[g.start[s]..g.start[s + 1]] {
                assert_eq!(slab(gr), s);
            }
        }
        // A second rebuild on the same buffers gives the same groups.
        let list = g.list.clone();
        g.rebuild(&grid, &p);
        assert_eq!(g.list, list);
    }

    #[test]
    fn rebuild_matches_a_serial_pass() {
        check::<f32>();
        check::<f64>();
    }
}
