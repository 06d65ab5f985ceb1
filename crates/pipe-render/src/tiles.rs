//! Tile binning: for each 16×16 tile, the visible Gaussians whose tile rectangle contains it,
//! sorted front to back by depth (ties by index), as in 3DGS `duplicateWithKeys` + sort, but
//! with a counting sort over tiles and an independent (parallel) depth sort per tile.

use rayon::prelude::*;

use crate::project::ProjectedGaussian;
use crate::real::Real;

/// Per-tile lists of Gaussian indices, flattened: tile `t` owns `ids[offsets[t]..offsets[t+1]]`.
/// Tiles are numbered row-major, `t = ty·tiles_x + tx`.
#[derive(Debug, Clone, Default)]
pub struct TileBins {
    /// `n_tiles + 1` prefix offsets into `ids`.
    pub offsets: Vec<usize>,
    /// Gaussian indices, per tile in ascending depth.
    pub ids: Vec<u32>,
}

impl TileBins {
    /// Number of (tile, Gaussian) pairs.
    pub fn n_intersections(&self) -> usize {
        self.ids.len()
    }

    /// The sorted Gaussian indices of tile `t`.
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.ids[self.offsets[t]..self.offsets[t + 1]]
    }

    /// The largest per-tile list length.
    pub fn max_per_tile(&self) -> usize {
        self.offsets
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or(0)
    }
}

/// Splits `s` into consecutive sub-slices at the given prefix `offsets` (`offsets[0] = 0`,
/// last = `s.len()`), one per window, so they can be processed in parallel.
pub(crate) fn split_by_offsets<'a, X>(mut s: &'a mut [X], offsets: &[usize]) -> Vec<&'a mut [X]> {
    debug_assert_eq!(offsets.first().copied().unwrap_or(0), 0);
    debug_assert_eq!(offsets.last().copied().unwrap_or(0), s.len());
    let mut out = Vec::with_capacity(offsets.len().saturating_sub(1));
    for w in offsets.windows(2) {
        let (head, tail) = std::mem::take(&mut s).split_at_mut(w[1] - w[0]);
        out.push(head);
        s = tail;
    }
    out
}

/// Bins the visible Gaussians into tiles and depth-sorts each tile's list.
pub(crate) fn bin<T: Real>(
    projected: &[ProjectedGaussian<T>],
    tiles_x: u32,
    tiles_y: u32,
) -> TileBins {
    let n_tiles = tiles_x as usize * tiles_y as usize;
    let mut counts = vec![0usize; n_tiles + 1];
    for p in projected.iter().filter(|p| p.visible()) {
        let [x0, y0, x1, y1] = p.tile_rect;
        debug_assert!(x1 <= tiles_x && y1 <= tiles_y && x0 < x1 && y0 < y1);
        for ty in y0..y1 {
            let row = ty as usize * tiles_x as usize;
            for c in &mut counts[row + x0 as usize..row + x1 as usize] {
                *c += 1;
            }
        }
    }
    // exclusive prefix sum -> offsets
    let mut offsets = Vec::with_capacity(n_tiles + 1);
    let mut acc = 0usize;
    for &c in &counts[..n_tiles] {
        offsets.push(acc);
        acc += c;
    }
    offsets.push(acc);
    let mut cursor = offsets.clone();
    // (depth key, index): filled in index order, then sorted per tile.
    let mut keyed = vec![(0u64, 0u32); acc];
    for (i, p) in projected.iter().enumerate().filter(|(_, p)| p.visible()) {
        let key = p.depth.sort_bits();
        let [x0, y0, x1, y1] = p.tile_rect;
        for ty in y0..y1 {
            let row = ty as usize * tiles_x as usize;
            for tx in x0..x1 {
                let t = row + tx as usize;
                keyed[cursor[t]] = (key, i as u32);
                cursor[t] += 1;
            }
        }
    }
    split_by_offsets(&mut keyed, &offsets)
        .into_par_iter()
        .for_each(|tile| tile.sort_unstable());
    let ids = keyed.into_iter().map(|(_, i)| i).collect();
    TileBins { offsets, ids }
}
