//! Binomial checkpointing schedule for reversing one segment with a fixed number of snapshots.
//!
//! Reversing `k` substeps from a stored start state with `c` snapshot buffers: advance `m`
//! substeps into a snapshot, reverse the last `k − m` with `c − 1` buffers, release it, and
//! reverse the first `m` with `c`. The forward substeps this costs obey
//! `T(1, c) = 0`, `T(k, 0) = ∞` (k > 1), `T(k, c) = min_m m + T(k − m, c − 1) + T(m, c)`,
//! whose minimum grows like `k · r` with `C(c + r, c) ≥ k` (Griewank's binomial bound);
//! [`Schedule`] tabulates the minimising `m` by dynamic programming.

/// Snapshots (recomputed states) alive at once while a segment is reversed, besides the tape.
/// Four keep a 14-frame `f64` rollout of 20k particles (50 substeps per frame) at 1.97× its
/// frame checkpoints, peak RSS included (six: 2.12×), at 2.9 (k = 50) to 5.3 (k = 270)
/// recomputed substeps per reversed substep (six: 2.3 to 3.8).
pub const SEGMENT_SNAPSHOTS: usize = 4;

/// Optimal split points `m(k, c)` for `k ≤ max_k` substeps and `1 ≤ c ≤ max_c` snapshots.
#[derive(Debug, Clone)]
pub(crate) struct Schedule {
    max_c: usize,
    /// `split[k · (max_c + 1) + c]`.
    split: Vec<u32>,
}

impl Schedule {
    /// Tabulates the schedule in O(max_k² · max_c).
    pub(crate) fn new(max_k: usize, max_c: usize) -> Self {
        let max_k = max_k.max(1);
        let max_c = max_c.max(1);
        let w = max_c + 1;
        let mut cost = vec![u64::MAX; (max_k + 1) * w];
        let mut split = vec![0u32; (max_k + 1) * w];
        cost[w..2 * w].fill(0); // k = 1: just the adjoint step
        for k in 2..=max_k {
            for c in 1..=max_c {
                let mut best = (u64::MAX, 1);
                for m in 1..k {
                    let (right, left) = (cost[(k - m) * w + c - 1], cost[m * w + c]);
                    if right == u64::MAX || left == u64::MAX {
                        continue;
                    }
                    let t = m as u64 + right + left;
                    if t < best.0 {
                        best = (t, m);
                    }
                }
                cost[k * w + c] = best.0;
                split[k * w + c] = best.1 as u32;
            }
        }
        Self { max_c, split }
    }

    /// Substeps to advance before the split when reversing `k ≥ 2` substeps with `c ≥ 1`
    /// snapshots (in `1..k`).
    pub(crate) fn split(&self, k: usize, c: usize) -> usize {
        self.split[k * (self.max_c + 1) + c.min(self.max_c)] as usize
    }

    /// What reversing substeps `lo..hi` from `lo` with `c` snapshots computes first: the
    /// states at the outermost chain of splits (`m₁ = lo + split(hi − lo, c)`, then from `m₁`
    /// with `c − 1`, … down to `hi − 1`) and, when the segment keeps its intermediates
    /// (`hi − lo ≤ c + 1`), the substeps whose intermediates it keeps along that chain, `hi − 1`
    /// included.
    pub(crate) fn lead(&self, lo: usize, hi: usize, c: usize) -> (Vec<usize>, Vec<usize>) {
        let (mut states, mut works) = (Vec::new(), Vec::new());
        if hi <= lo {
            return (states, works);
        }
        let keep = hi - lo <= c + 1;
        let (mut a, mut free) = (lo, c);
        while hi - a > 1 && free > 0 {
            let m = a + self.split(hi - a, free);
            states.push(m);
            if keep && m == a + 1 {
                works.push(a);
            }
            a = m;
            free -= 1;
        }
        if keep {
            works.push(hi - 1);
        }
        (states, works)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Forward substeps of the tabulated schedule, by walking it.
    fn walk(s: &Schedule, k: usize, c: usize) -> usize {
        if k == 1 {
            return 0;
        }
        let m = s.split(k, c);
        assert!((1..k).contains(&m));
        m + walk(s, k - m, c - 1) + walk(s, m, c)
    }

    #[test]
    fn costs_match_the_binomial_optimum() {
        let s = Schedule::new(300, 4);
        // One snapshot: recompute every state from the start, k(k − 1)/2.
        assert_eq!(walk(&s, 50, 1), 50 * 49 / 2);
        // k = C(c + r, c) is reversed in r·k − C(c + r, c − 1) forward substeps.
        assert_eq!(walk(&s, 35, 3), 4 * 35 - 35);
        assert_eq!(walk(&s, 50, 4), 144);
        assert_eq!(walk(&s, 270, 4), 1428);
        assert_eq!(walk(&s, 4, 4), 3);
    }

    #[test]
    fn the_lead_is_the_outermost_chain() {
        let s = Schedule::new(50, 4);
        // A short segment is one chain of single substeps, each keeping its intermediates.
        assert_eq!(s.lead(8, 12, 4), (vec![9, 10, 11], vec![8, 9, 10, 11]));
        assert_eq!(s.lead(3, 4, 4), (vec![], vec![3]));
        // A long one: at most `c` states, the last at `hi − 1`, no intermediates.
        let (states, works) = s.lead(0, 50, 4);
        assert!(states.len() <= 4 && works.is_empty(), "{states:?}");
        assert_eq!(states.last(), Some(&49));
        assert!(states.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(states[0], s.split(50, 4));
    }
}
