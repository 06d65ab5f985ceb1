//! The parts of a material field: where its values fall into a few groups.
//!
//! A field gives every particle its own E, but a user asks of it what a material has: "how
//! stiff is the stiff part, and how sure is that?". The field's `log10 E` values are grouped
//! into `k` parts by natural breaks: the split of the sorted values that minimises the
//! volume-weighted variance within the parts (Jenks 1967; optimal 1-D k-means), exact on a
//! histogram by dynamic programming. A part is a set of particles, and the profile of the fit
//! ([`super::profile`]) moves each part's E alone to say how closely the frames hold it
//! (`material.json` `field.parts`).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::rollout::Moduli;

/// Histogram bins the natural breaks are searched on (the breaks fall on bin edges).
pub const BINS: usize = 256;

/// A field's values in parts: its `log10 E` cut at `thresholds` (ascending), and each part's
/// weighted median `log10 E` (E in Pa).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Parts {
    /// Where the field's `log10 E` passes from one part to the next (one fewer than parts).
    pub thresholds: Vec<f64>,
    /// Each part's median `log10 E`, in the order of the field's values.
    pub log10_e: Vec<f64>,
}

impl Parts {
    /// The cuts in log10 E, for a log line ("1.234, 5.678").
    pub fn cuts_text(&self) -> String {
        self.thresholds
            .iter()
            .map(|t| format!("{t:.3}"))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The number of parts.
    pub fn len(&self) -> usize {
        self.log10_e.len()
    }

    /// Whether there are no parts.
    pub fn is_empty(&self) -> bool {
        self.log10_e.is_empty()
    }

    /// The part of a point whose field value is `field_log10_e`.
    pub fn part_of(&self, field_log10_e: f64) -> usize {
        self.thresholds
            .iter()
            .filter(|t| field_log10_e >= **t)
            .count()
    }

    /// The part of each particle from the field's E (Pa) at it.
    pub fn assign(&self, field_e: &[f64]) -> Vec<usize> {
        field_e.iter().map(|e| self.part_of(e.log10())).collect()
    }

    /// `moduli` with each particle's E replaced by its part's (`part` from [`Parts::assign`]).
    pub fn apply(&self, part: &[usize], moduli: &mut Moduli) {
        for (e, k) in moduli.e.iter_mut().zip(part) {
            *e = 10f64.powf(self.log10_e[*k]);
        }
    }

    /// `∂L/∂(log10 E_k)` of each part from the per-particle `∂L/∂E_p` (`grad_e`) at the parts'
    /// moduli: `Σ_{p ∈ k} ∂L/∂E_p · E_k · ln 10`.
    pub fn gradient(&self, part: &[usize], grad_e: &[f64]) -> Vec<f64> {
        let mut g = vec![0.0; self.len()];
        for (k, d) in part.iter().zip(grad_e) {
            g[*k] += d;
        }
        for (g, l) in g.iter_mut().zip(&self.log10_e) {
            *g *= 10f64.powf(*l) * std::f64::consts::LN_10;
        }
        g
    }

    /// Each part's share of `weight` (e.g. the particles' volumes) and its particle count.
    pub fn shares(&self, part: &[usize], weight: &[f64]) -> Vec<(f64, usize)> {
        let mut s = vec![(0.0, 0usize); self.len()];
        for (k, w) in part.iter().zip(weight) {
            s[*k].0 += w;
            s[*k].1 += 1;
        }
        let total: f64 = s.iter().map(|(w, _)| w).sum();
        if total > 0.0 {
            for (w, _) in &mut s {
                *w /= total;
            }
        }
        s
    }
}

/// The `k` parts of `values` (a field's `log10 E` per particle) with the least within-part
/// variance weighted by `weight` (natural breaks, exact on a histogram of [`BINS`] bins by
/// dynamic programming), each part starting at its members' weighted median. `None` when the
/// values do not span `k` non-empty parts (all equal, fewer than `k` occupied bins), `k < 2`,
/// or the inputs' lengths differ or hold a non-finite value.
pub fn natural_breaks(values: &[f64], weight: &[f64], k: usize) -> Option<Parts> {
    if k < 2 || values.len() != weight.len() || values.is_empty() {
        return None;
    }
    if values.iter().chain(weight).any(|v| !v.is_finite()) || weight.iter().any(|w| *w < 0.0) {
        return None;
    }
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if hi <= lo {
        return None;
    }
    let width = (hi - lo) / BINS as f64;
    let bin = |v: f64| (((v - lo) / width) as usize).min(BINS - 1);
    // Per bin: weight, weighted sum and weighted sum of squares.
    let mut w = vec![0.0; BINS];
    let mut s = vec![0.0; BINS];
    let mut q = vec![0.0; BINS];
    for (v, wt) in values.iter().zip(weight) {
        let b = bin(*v);
        w[b] += wt;
        s[b] += wt * v;
        q[b] += wt * v * v;
    }
    let prefix = |a: &[f64]| {
        let mut p = vec![0.0; BINS + 1];
        for i in 0..BINS {
            p[i + 1] = p[i] + a[i];
        }
        p
    };
    let (pw, ps, pq) = (prefix(&w), prefix(&s), prefix(&q));
    // Within-part sum of squares of bins i..j (j exclusive); infinite when empty.
    let cost = |i: usize, j: usize| {
        let ww = pw[j] - pw[i];
        if ww <= 0.0 {
            return f64::INFINITY;
        }
        let ss = ps[j] - ps[i];
        ((pq[j] - pq[i]) - ss * ss / ww).max(0.0)
    };
    // best[m][j]: the least cost of bins 0..j in m + 1 parts; from[m][j] its last cut.
    let mut best = vec![vec![f64::INFINITY; BINS + 1]; k];
    let mut from = vec![vec![0usize; BINS + 1]; k];
    for (j, b) in best[0].iter_mut().enumerate().skip(1) {
        *b = cost(0, j);
    }
    for m in 1..k {
        for j in (m + 1)..=BINS {
            for i in m..j {
                let c = best[m - 1][i] + cost(i, j);
                if c < best[m][j] {
                    best[m][j] = c;
                    from[m][j] = i;
                }
            }
        }
    }
    if !best[k - 1][BINS].is_finite() {
        return None;
    }
    let mut cuts = vec![BINS; k + 1];
    cuts[0] = 0;
    for m in (1..k).rev() {
        cuts[m] = from[m][cuts[m + 1]];
    }
    let thresholds: Vec<f64> = cuts[1..k].iter().map(|c| lo + *c as f64 * width).collect();
    let mut parts = Parts {
        thresholds,
        log10_e: vec![0.0; k],
    };
    // Assign by bin (as the cuts were made), so that a value on an edge is where the cost put it.
    let part: Vec<usize> = values
        .iter()
        .map(|v| cuts[1..k].iter().filter(|c| bin(*v) >= **c).count())
        .collect();
    for (p, l) in parts.log10_e.iter_mut().enumerate() {
        let mut members: Vec<(f64, f64)> = values
            .iter()
            .zip(weight)
            .zip(&part)
            .filter(|(_, k)| **k == p)
            .map(|((v, w), _)| (*v, *w))
            .collect();
        *l = weighted_median(&mut members)?;
    }
    Some(parts)
}

/// The weighted median of `(value, weight)` pairs (the lowest value at which the cumulative
/// weight reaches half; the plain median when every weight is 0). `None` when empty.
fn weighted_median(v: &mut [(f64, f64)]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = v.iter().map(|(_, w)| w).sum();
    if total <= 0.0 {
        return Some(v[(v.len() - 1) / 2].0);
    }
    let mut acc = 0.0;
    for (x, w) in v.iter() {
        acc += w;
        if acc >= 0.5 * total {
            return Some(*x);
        }
    }
    v.last().map(|(x, _)| *x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_groups_are_cut_between_them_and_start_at_their_medians() {
        // A soft half about 4.3 and a stiff half about 5.4–5.9 (a free end left low), with a
        // ramp between them: the cut falls in the gap, the stiff part starts at its median.
        let mut v = Vec::new();
        for i in 0..100 {
            v.push(4.3 + 0.001 * f64::from(i % 7));
        }
        for i in 0..60 {
            v.push(5.8 + 0.002 * f64::from(i % 5));
        }
        for i in 0..40 {
            v.push(5.4 + 0.002 * f64::from(i % 5));
        }
        let w = vec![1.0; v.len()];
        let p = natural_breaks(&v, &w, 2).unwrap();
        assert_eq!(p.len(), 2);
        assert!(p.thresholds[0] > 4.31 && p.thresholds[0] < 5.4, "{p:?}");
        assert!((p.log10_e[0] - 4.303).abs() < 0.01, "{p:?}");
        assert!(p.log10_e[1] > 5.79 && p.log10_e[1] < 5.81, "{p:?}");
        let part = p.assign(&v.iter().map(|l| 10f64.powf(*l)).collect::<Vec<_>>());
        assert!(part[..100].iter().all(|k| *k == 0) && part[100..].iter().all(|k| *k == 1));
        let shares = p.shares(&part, &w);
        assert!((shares[0].0 - 0.5).abs() < 1e-12 && shares[1].1 == 100);
        // Three parts separate the free end too.
        let p3 = natural_breaks(&v, &w, 3).unwrap();
        assert!(p3.thresholds[1] > 5.41 && p3.thresholds[1] < 5.8, "{p3:?}");
    }

    #[test]
    fn weights_move_the_cut() {
        // Three clusters, the middle one heavy by volume: it forms a part of its own.
        let v = [1.0, 1.0, 2.0, 2.0, 3.0, 3.0];
        let p = natural_breaks(&v, &[1.0, 1.0, 10.0, 10.0, 1.0, 1.0], 2).unwrap();
        let part = p.assign(&v.map(|l| 10f64.powf(l)));
        assert_eq!(part[2], part[3]);
        assert_ne!(part[0], part[5]);
    }

    #[test]
    fn uniform_or_bad_values_have_no_parts() {
        assert!(natural_breaks(&[5.0; 10], &[1.0; 10], 2).is_none());
        assert!(natural_breaks(&[5.0, 6.0], &[1.0, 1.0], 1).is_none());
        assert!(natural_breaks(&[5.0, 6.0], &[1.0], 2).is_none());
        assert!(natural_breaks(&[5.0, f64::NAN], &[1.0, 1.0], 2).is_none());
        assert!(natural_breaks(&[5.0, 6.0], &[1.0, -1.0], 2).is_none());
        // Two distinct values cannot make three non-empty parts.
        assert!(natural_breaks(&[5.0, 5.0, 6.0], &[1.0; 3], 3).is_none());
        assert!(natural_breaks(&[5.0, 5.0, 6.0], &[1.0; 3], 2).is_some());
    }
}
