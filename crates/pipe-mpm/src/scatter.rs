//! Race-free, thread-count-independent particle → grid scatter: the slab cuts and colours
//! ([`crate::wide::groups`] bins the particle groups by them).
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

/// Fewest cells in a slab: a stencil spans 3 layers, so same-colour slabs must be 2 apart.
const MIN_SLAB: usize = 2;

/// Most slabs per rebuild (a multiple of 4).
const MAX_SLABS: usize = 32;

/// Slab width (cells) when the particles are too narrow in x for 4 slabs of `MIN_SLAB`.
const FALLBACK_SLAB: usize = 3;

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
}
