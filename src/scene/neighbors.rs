//! Nearest-neighbour queries on a hash grid: the particle spacing of an input cloud and the
//! Chamfer distance between two clouds.
//!
//! Points are bucketed into cubic cells of side `h`: a `HashMap` from integer cell to the range
//! of its points in a copy of the points ordered by cell (hashed with `foldhash`'s fixed-seed
//! hasher: std's SipHash took most of a query; one allocation for all cells instead of one per
//! cell, and a cell's points side by side in memory). A query walks shells of cells at growing
//! Chebyshev distance `r` from its own cell and stops once the best distance found is at most
//! `r·h` (no point in a farther shell can be closer); when a shell would hold more cells than the
//! grid has occupied cells it scans the occupied cells directly, so a far query costs O(occupied
//! cells), never more.

use std::collections::HashMap;

use foldhash::fast::FixedState;

use glam::{DVec3, IVec3};
use rayon::prelude::*;

/// Integer cell → `(first, count)`: its points are `first..first + count` of the grid's order.
type CellMap = HashMap<IVec3, (u32, u32), FixedState>;

/// Points bucketed by cell.
#[derive(Debug, Clone)]
pub struct PointGrid {
    h: f64,
    cells: CellMap,
    /// Point indices, cell by cell (in index order within a cell).
    order: Vec<u32>,
    /// The points in that order (m).
    sorted: Vec<DVec3>,
}

impl PointGrid {
    /// Buckets `points` (m) into cells of side `h` (m, > 0).
    pub fn new(points: &[DVec3], h: f64) -> Self {
        assert!(h.is_finite() && h > 0.0, "cell size must be > 0, got {h}");
        let keys: Vec<IVec3> = points.iter().map(|&p| cell_of(p, h)).collect();
        // A counting sort: count each cell's points, give each cell its range, place the points
        // (in index order within a cell).
        let mut cells = CellMap::with_capacity_and_hasher(points.len() / 2, FixedState::default());
        for k in &keys {
            cells.entry(*k).or_insert((0, 0)).1 += 1;
        }
        let mut first = 0u32;
        for v in cells.values_mut() {
            let n = v.1;
            *v = (first, 0);
            first += n;
        }
        let mut order = vec![0u32; points.len()];
        let mut sorted = vec![DVec3::ZERO; points.len()];
        for (i, k) in keys.iter().enumerate() {
            let v = cells.get_mut(k).expect("every key was counted");
            let at = (v.0 + v.1) as usize;
            v.1 += 1;
            order[at] = i as u32;
            sorted[at] = points[i];
        }
        Self {
            h,
            cells,
            order,
            sorted,
        }
    }

    /// Cell side (m).
    pub fn cell_size(&self) -> f64 {
        self.h
    }

    /// The cell holding `p`.
    pub fn cell(&self, p: DVec3) -> IVec3 {
        cell_of(p, self.h)
    }

    /// The nearest point to `q` other than index `skip` (and, when `skip` is given, other than
    /// exact duplicates of `q`), as `(index, distance in m)`; `None` if there is none.
    pub fn nearest(&self, q: DVec3, skip: Option<usize>) -> Option<(usize, f64)> {
        let c = self.cell(q);
        let mut best: Option<(usize, f64)> = None;
        let consider = |&(first, n): &(u32, u32), best: &mut Option<(usize, f64)>| {
            let r = first as usize..(first + n) as usize;
            for (&j, &p) in self.order[r.clone()].iter().zip(&self.sorted[r]) {
                let j = j as usize;
                if Some(j) == skip {
                    continue;
                }
                let d2 = (p - q).length_squared();
                if skip.is_some() && d2 == 0.0 {
                    continue;
                }
                if best.is_none_or(|(_, b)| d2 < b) {
                    *best = Some((j, d2));
                }
            }
        };
        let occupied = self.cells.len();
        for r in 0i32.. {
            let side = (2 * r + 1) as f64;
            if r > 1 && side * side * side > occupied as f64 {
                // The shell is larger than the occupied set: scan that instead.
                for (cell, range) in &self.cells {
                    if (*cell - c).abs().max_element() >= r {
                        consider(range, &mut best);
                    }
                }
                break;
            }
            for_shell(c, r, |cell| {
                if let Some(range) = self.cells.get(&cell) {
                    consider(range, &mut best);
                }
            });
            if let Some((_, d2)) = best
                && d2 <= (r as f64 * self.h).powi(2)
            {
                break;
            }
        }
        best.map(|(j, d2)| (j, d2.sqrt()))
    }

    /// Calls `f` with the index of every point within `radius` (m) of `q` (`q` itself
    /// included when it is one of the points), cell by cell in a fixed order.
    pub fn within(&self, q: DVec3, radius: f64, mut f: impl FnMut(usize)) {
        let reach = (radius / self.h).ceil() as i32;
        let c = self.cell(q);
        let r2 = radius * radius;
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    let Some(&(first, n)) = self.cells.get(&(c + IVec3::new(dx, dy, dz))) else {
                        continue;
                    };
                    let r = first as usize..(first + n) as usize;
                    for (&j, &p) in self.order[r.clone()].iter().zip(&self.sorted[r]) {
                        if (p - q).length_squared() <= r2 {
                            f(j as usize);
                        }
                    }
                }
            }
        }
    }
}

/// Points of `points` (m) per occupied cell of side `h` (m).
fn count_cells(points: &[DVec3], h: f64) -> HashMap<IVec3, u32, FixedState> {
    let mut counts = HashMap::with_capacity_and_hasher(points.len() / 8, FixedState::default());
    for &p in points {
        *counts.entry(cell_of(p, h)).or_insert(0) += 1;
    }
    counts
}

fn cell_of(p: DVec3, h: f64) -> IVec3 {
    let c = (p / h).floor();
    // Clamp so absurd coordinates cannot overflow the integer cell index.
    c.clamp(DVec3::splat(-1e9), DVec3::splat(1e9)).as_ivec3()
}

/// Calls `f` for every cell at Chebyshev distance exactly `r` from `c`.
fn for_shell(c: IVec3, r: i32, mut f: impl FnMut(IVec3)) {
    for dx in -r..=r {
        for dy in -r..=r {
            let edge = dx.abs() == r || dy.abs() == r;
            if edge {
                for dz in -r..=r {
                    f(c + IVec3::new(dx, dy, dz));
                }
            } else {
                f(c + IVec3::new(dx, dy, -r));
                if r > 0 {
                    f(c + IVec3::new(dx, dy, r));
                }
            }
        }
    }
}

/// Axis-aligned bounds of `points` (None when empty).
pub fn bounds(points: &[DVec3]) -> Option<(DVec3, DVec3)> {
    let first = *points.first()?;
    Some(
        points
            .iter()
            .fold((first, first), |(lo, hi), &p| (lo.min(p), hi.max(p))),
    )
}

/// At most `max` indices spread evenly over `0..n` (deterministic).
fn sample(n: usize, max: usize) -> impl Iterator<Item = usize> {
    let k = n.min(max);
    (0..k).map(move |i| i * n / k.max(1))
}

/// Median distance (m) from a point to its nearest distinct neighbour, over up to 8192 evenly
/// spread points; `None` with fewer than two distinct points.
pub fn median_nn_distance(points: &[DVec3]) -> Option<f64> {
    let (lo, hi) = bounds(points)?;
    let ext = hi - lo;
    let n = points.len() as f64;
    // A cell holding about two points if the cloud filled its box; degenerate boxes (planes,
    // lines) fall back to the largest extent spread over the points.
    let vol = ext.x * ext.y * ext.z;
    let mut h = if vol > 0.0 {
        (vol / n).cbrt() * 1.26
    } else {
        ext.max_element() / n.cbrt()
    };
    if !(h.is_finite() && h > 0.0) {
        h = ext.max_element().max(1e-9);
    }
    let grid = PointGrid::new(points, h);
    let queries: Vec<usize> = sample(points.len(), 8192).collect();
    let mut d: Vec<f64> = queries
        .par_iter()
        .filter_map(|&i| grid.nearest(points[i], Some(i)).map(|(_, d)| d))
        .collect();
    if d.is_empty() {
        return None;
    }
    let mid = d.len() / 2;
    let (_, m, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*m)
}

/// How the particle spacing was measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spacing {
    /// Spacing `s` (m): the cube root of the volume per particle.
    pub spacing: f64,
    /// Median nearest-neighbour distance (m).
    pub median_nn: f64,
    /// Interior cells the density was measured in (0: fell back to `median_nn`).
    pub interior_cells: usize,
}

/// The particle spacing of a volumetric cloud: `s = (volume per particle)^(1/3)`, so that
/// `s³` is the particle volume and a cell of `2s` holds 8 particles (PAC-NeRF's sampling).
///
/// Measured as the mean number density inside *interior* cells (cells of side `4·d_nn`, about
/// 15–60 points each, whose 26 neighbours are all occupied, so the surface does not dilute it).
/// This is exact for lattices and unbiased for randomly jittered sampling, where the median
/// nearest-neighbour distance `d_nn` is far below the spacing (≈ 0.62 s for PAC-NeRF's clouds).
/// Clouds without interior cells (surfaces, thin sheets, tiny sets) fall back to `s = d_nn`.
pub fn particle_spacing(points: &[DVec3]) -> Option<Spacing> {
    let median_nn = median_nn_distance(points)?;
    if median_nn.is_nan() || median_nn <= 0.0 {
        return None;
    }
    for factor in [4.0, 3.0] {
        let h = factor * median_nn;
        let counts = count_cells(points, h);
        let occupied: Vec<(&IVec3, &u32)> = counts.iter().collect();
        let (cells, count) = occupied
            .par_iter()
            .filter(|(c, _)| {
                (-1..=1).all(|dx| {
                    (-1..=1).all(|dy| {
                        (-1..=1).all(|dz| counts.contains_key(&(**c + IVec3::new(dx, dy, dz))))
                    })
                })
            })
            .map(|(_, n)| (1usize, **n as usize))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        if cells >= 8 {
            let volume_per_particle = cells as f64 * h * h * h / count as f64;
            return Some(Spacing {
                spacing: volume_per_particle.cbrt(),
                median_nn,
                interior_cells: cells,
            });
        }
    }
    Some(Spacing {
        spacing: median_nn,
        median_nn,
        interior_cells: 0,
    })
}

/// Symmetric mean Chamfer distance (m): the mean over `a` of the distance to the nearest point
/// of `b`, and the same from `b` to `a`, averaged. `None` if either set is empty.
pub fn mean_chamfer(a: &[DVec3], b: &[DVec3]) -> Option<f64> {
    fn one_way(from: &[DVec3], to: &[DVec3]) -> Option<f64> {
        let (lo, hi) = bounds(to)?;
        let ext = (hi - lo).max_element().max(1e-9);
        let h = ext / (to.len() as f64).cbrt().max(1.0);
        let grid = PointGrid::new(to, h);
        let sum: f64 = from
            .iter()
            .map(|&p| grid.nearest(p, None).map_or(0.0, |(_, d)| d))
            .sum();
        (!from.is_empty()).then(|| sum / from.len() as f64)
    }
    Some(0.5 * (one_way(a, b)? + one_way(b, a)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute(points: &[DVec3], q: DVec3, skip: Option<usize>) -> Option<f64> {
        points
            .iter()
            .enumerate()
            .filter(|(j, p)| Some(*j) != skip && !(skip.is_some() && **p == q))
            .map(|(_, p)| (*p - q).length())
            .min_by(f64::total_cmp)
    }

    fn cloud(n: usize, seed: u64) -> Vec<DVec3> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(0.0..0.1),
                    rng.random_range(-1.0..1.0),
                )
            })
            .collect()
    }

    #[test]
    fn nearest_matches_brute_force() {
        let pts = cloud(500, 1);
        let grid = PointGrid::new(&pts, 0.07);
        for (i, &p) in pts.iter().enumerate().step_by(7) {
            let got = grid.nearest(p, Some(i)).unwrap().1;
            assert_eq!(got, brute(&pts, p, Some(i)).unwrap());
        }
        // Far-away queries take the occupied-cell scan.
        for q in [DVec3::new(40.0, -3.0, 2.0), DVec3::new(0.0, 5.0, 0.0)] {
            assert_eq!(
                grid.nearest(q, None).unwrap().1,
                brute(&pts, q, None).unwrap()
            );
        }
    }

    #[test]
    fn spacing_of_a_lattice_and_of_a_jittered_cloud() {
        let s = 0.01;
        let lattice: Vec<DVec3> = (0..20)
            .flat_map(|i| (0..20).flat_map(move |j| (0..20).map(move |k| (i, j, k))))
            .map(|(i, j, k)| DVec3::new(i as f64, j as f64, k as f64) * s)
            .collect();
        let sp = particle_spacing(&lattice).unwrap();
        assert!((sp.median_nn - s).abs() < 1e-9, "{sp:?}");
        assert!((sp.spacing - s).abs() < 1e-3 * s, "{sp:?}");
        // PAC-NeRF style: 8 uniform random points in every cell of side dx = 0.02.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let dx = 0.02;
        let mut jit = Vec::new();
        for i in 0..16 {
            for j in 0..16 {
                for k in 0..16 {
                    for _ in 0..8 {
                        let u = DVec3::new(rng.random(), rng.random(), rng.random());
                        jit.push((DVec3::new(i as f64, j as f64, k as f64) + u) * dx);
                    }
                }
            }
        }
        let sp = particle_spacing(&jit).unwrap();
        assert!(sp.median_nn < 0.7 * dx / 2.0, "{sp:?}");
        assert!((sp.spacing - dx / 2.0).abs() < 0.02 * dx / 2.0, "{sp:?}");
    }

    #[test]
    fn degenerate_clouds() {
        assert!(particle_spacing(&[DVec3::ZERO]).is_none());
        assert!(particle_spacing(&[DVec3::ONE, DVec3::ONE]).is_none());
        let line: Vec<DVec3> = (0..10).map(|i| DVec3::X * i as f64 * 0.5).collect();
        let sp = particle_spacing(&line).unwrap();
        assert_eq!((sp.spacing, sp.interior_cells), (0.5, 0));
    }

    #[test]
    fn chamfer_of_a_shifted_copy() {
        let a = cloud(300, 3);
        let b: Vec<DVec3> = a.iter().map(|p| *p + DVec3::new(0.0, 0.0, 1e-3)).collect();
        let c = mean_chamfer(&a, &b).unwrap();
        assert!(c <= 1e-3 + 1e-12 && c > 0.0, "{c}");
        assert_eq!(mean_chamfer(&a, &a), Some(0.0));
        assert_eq!(mean_chamfer(&a, &[]), None);
    }
}
