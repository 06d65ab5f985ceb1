//! A learned per-particle material against a per-particle ground truth
//! (`gt/material_particles.ply`: rest positions with `E` (Pa) and `nu`, as generated
//! multi-material scenes ship): each learned particle takes the truth of the nearest true
//! particle at rest; the errors are reported over all particles and, when the truth has few
//! distinct values (the parts of a multi-material object), per part.

use std::path::Path;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::rollout::Moduli;
use crate::scene::neighbors::{PointGrid, median_nn_distance};

/// The truth file, relative to the scene folder.
pub const TRUTH_FILE: &str = "gt/material_particles.ply";

/// Parts are reported when the truth has at most this many distinct `E`.
pub const MAX_PARTS: usize = 8;

/// One part of the object: the particles whose true `E` is `youngs_modulus_truth`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PartError {
    /// The part's true E (Pa).
    pub youngs_modulus_truth: f64,
    /// Learned particles in the part.
    pub particles: usize,
    /// Median over the part of the learned `log10 E`.
    pub log10_youngs_modulus_median: f64,
    /// `|median − log10 truth|`.
    pub log10_youngs_modulus_error: f64,
    /// Median of the learned ν, and its distance to the part's true ν (the part's median).
    pub poisson_ratio_median: f64,
    pub poisson_ratio_error: f64,
}

/// The learned material against the per-particle truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaterialTruthErrors {
    /// Median over particles of `|log10 E − log10 E_true|`.
    pub log10_youngs_modulus_abs_median: f64,
    /// Median over particles of `|ν − ν_true|`.
    pub poisson_ratio_abs_median: f64,
    /// Per part (by true E), when the truth has at most [`MAX_PARTS`] distinct values.
    pub parts: Vec<PartError>,
    /// Median distance (m) from a learned particle to its true particle at rest.
    pub match_distance_median_m: f64,
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The errors of `learned` (per-particle E and ν at rest positions `rest`, m) against the
/// truth at `path`; `Ok(None)` when the file does not exist.
///
/// # Errors
/// An unreadable truth file, an empty one, or length mismatches, named.
pub fn errors(
    path: &Path,
    rest: &[DVec3],
    learned: &Moduli,
) -> Result<Option<MaterialTruthErrors>, String> {
    if !path.is_file() {
        return Ok(None);
    }
    if learned.e.len() != rest.len() || learned.nu.len() != rest.len() {
        return Err(format!(
            "{} positions, {} E and {} ν learned",
            rest.len(),
            learned.e.len(),
            learned.nu.len()
        ));
    }
    let t = crate::io::ply::read_point_scalars(path, &["E", "nu"]).map_err(|e| e.to_string())?;
    if t.positions.is_empty() {
        return Err(format!("{}: no particle", path.display()));
    }
    let (te, tnu) = (&t.columns[0], &t.columns[1]);
    if let Some(i) = te.iter().position(|e| *e <= 0.0) {
        return Err(format!(
            "{}: particle {i}: E = {} is not positive",
            path.display(),
            te[i]
        ));
    }
    let pts: Vec<DVec3> = t
        .positions
        .iter()
        .map(|p| DVec3::from_array(p.map(f64::from)))
        .collect();
    let h = median_nn_distance(&pts)
        .filter(|h| *h > 0.0)
        .unwrap_or(1e-3);
    let grid = PointGrid::new(&pts, h);
    let mut distinct: Vec<f64> = te.clone();
    distinct.sort_by(f64::total_cmp);
    distinct.dedup();
    let parted = distinct.len() <= MAX_PARTS;
    let mut parts: Vec<(Vec<f64>, Vec<f64>, Vec<f64>)> = vec![Default::default(); distinct.len()];
    let (mut de, mut dnu, mut dist) = (Vec::new(), Vec::new(), Vec::new());
    for (i, x) in rest.iter().enumerate() {
        let (j, d) = grid
            .nearest(*x, None)
            .ok_or_else(|| format!("{}: no nearest particle", path.display()))?;
        let (le, lnu) = (learned.e[i].log10(), learned.nu[i]);
        de.push((le - te[j].log10()).abs());
        dnu.push((lnu - tnu[j]).abs());
        dist.push(d);
        if parted {
            let k = distinct.partition_point(|v| *v < te[j]);
            parts[k].0.push(le);
            parts[k].1.push(lnu);
            parts[k].2.push(tnu[j]);
        }
    }
    let parts = match parted {
        false => Vec::new(),
        true => distinct
            .iter()
            .zip(parts)
            .filter(|(_, p)| !p.0.is_empty())
            .map(|(e, (mut le, mut lnu, mut tnu))| {
                let m = median(&mut le);
                let n = median(&mut lnu);
                PartError {
                    youngs_modulus_truth: *e,
                    particles: le.len(),
                    log10_youngs_modulus_median: m,
                    log10_youngs_modulus_error: (m - e.log10()).abs(),
                    poisson_ratio_median: n,
                    poisson_ratio_error: (n - median(&mut tnu)).abs(),
                }
            })
            .collect(),
    };
    Ok(Some(MaterialTruthErrors {
        log10_youngs_modulus_abs_median: median(&mut de),
        poisson_ratio_abs_median: median(&mut dnu),
        parts,
        match_distance_median_m: median(&mut dist),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_two_part_truth_is_scored_per_part() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.ply");
        assert_eq!(errors(&path, &[], &Moduli::default()).unwrap(), None);
        // Ten true particles on a line, x < 0.5 soft.
        let x: Vec<[f32; 3]> = (0..10).map(|i| [i as f32 * 0.1, 0.0, 0.0]).collect();
        let e: Vec<f64> = (0..10).map(|i| if i < 5 { 1e4 } else { 1e6 }).collect();
        crate::io::ply::write_point_scalars(&path, &x, &[("E", &e), ("nu", &[0.3; 10])]).unwrap();
        // Learned particles between them: one global E of 1e5, ν 0.25.
        let rest: Vec<DVec3> = (0..10)
            .map(|i| DVec3::new(i as f64 * 0.1 + 0.01, 0.0, 0.0))
            .collect();
        let learned = Moduli {
            e: vec![1e5; 10],
            nu: vec![0.25; 10],
        };
        let r = errors(&path, &rest, &learned).unwrap().unwrap();
        assert_eq!(r.parts.len(), 2);
        assert_eq!(r.parts[0].particles, 5);
        assert!((r.parts[0].log10_youngs_modulus_error - 1.0).abs() < 1e-12);
        assert!((r.parts[1].log10_youngs_modulus_median - 5.0).abs() < 1e-12);
        assert!((r.log10_youngs_modulus_abs_median - 1.0).abs() < 1e-12);
        assert!((r.poisson_ratio_abs_median - 0.05).abs() < 1e-12);
        assert!((r.match_distance_median_m - 0.01).abs() < 1e-6);
        // A length mismatch is an error, not a silent score.
        let short = Moduli {
            e: vec![1e5; 9],
            nu: vec![0.25; 10],
        };
        assert!(errors(&path, &rest, &short).unwrap_err().contains("9 E"));
    }
}
