//! Spatial order of the particles inside a run.
//!
//! Callers may hand particles in any order (a random cloud, a PLY file's order). Scattering and
//! gathering 27 grid nodes per particle in such an order touches the grid and the particle
//! arrays at random, and cache misses then dominate the substep. A run therefore first
//! reorders the particles by the grid cell they sit in (x-major, a stable counting sort), works
//! on that copy, and hands the results back in the caller's order. Indices a caller sees
//! (forces' particle sets, error reports, gradients) are always the caller's.
//!
//! A taped run keeps its order (the tape's checkpoints hold it), so the forward pass and the
//! backward pass's recomputation sum in the same order and stay bit-identical; a plain run
//! may sort again as the particles move (`crate::wide`).

use crate::forces::ParticleForce;
use crate::state::Material;

/// A permutation of the particles: slot `i` holds the caller's particle `order[i]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Order {
    order: Vec<u32>,
    /// Inverse: the caller's particle `p` sits in slot `rank[p]`.
    rank: Vec<u32>,
}

impl Order {
    /// Particles sorted by `key` (each `< n_keys`), stably; `None` when already sorted.
    pub(crate) fn by_key(key: &[u32], n_keys: usize) -> Option<Self> {
        if key.windows(2).all(|w| w[0] <= w[1]) {
            return None;
        }
        // Counting sort by key, over the keys' range.
        let lo = key.iter().copied().min().unwrap_or(0) as usize;
        let hi = key.iter().copied().max().unwrap_or(0) as usize;
        debug_assert!(hi < n_keys.max(1));
        let mut start = vec![0u32; hi - lo + 2];
        for &k in key {
            start[k as usize - lo + 1] += 1;
        }
        for c in 0..=hi - lo {
            start[c + 1] += start[c];
        }
        let mut order = vec![0u32; key.len()];
        let mut rank = vec![0u32; key.len()];
        for (p, &k) in key.iter().enumerate() {
            let slot = start[k as usize - lo];
            start[k as usize - lo] += 1;
            order[slot as usize] = p as u32;
            rank[p] = slot;
        }
        Some(Self { order, rank })
    }

    /// The permutation whose slot `i` holds particle `order[i]`.
    pub(crate) fn from_slots(order: Vec<u32>) -> Self {
        let mut rank = vec![0u32; order.len()];
        for (i, &p) in order.iter().enumerate() {
            rank[p as usize] = i as u32;
        }
        Self { order, rank }
    }

    /// Slot `i` holds the caller's particle `slots()[i]`.
    pub(crate) fn slots(&self) -> &[u32] {
        &self.order
    }

    /// The caller's particle `p` sits in slot `ranks()[p]`.
    pub(crate) fn ranks(&self) -> &[u32] {
        &self.rank
    }

    /// `src` (caller's order) in slot order.
    pub(crate) fn gather<T: Copy>(&self, src: &[T]) -> Vec<T> {
        self.order.iter().map(|&p| src[p as usize]).collect()
    }

    /// A material in slot order.
    pub(crate) fn sort_material(&self, m: &Material) -> Material {
        Material {
            mass: self.gather(&m.mass),
            volume: self.gather(&m.volume),
            mu: self.gather(&m.mu),
            lam: self.gather(&m.lam),
            family: if m.family.is_empty() {
                Vec::new()
            } else {
                self.gather(&m.family)
            },
        }
    }

    /// Forces with their particle sets renumbered to slots.
    pub(crate) fn sort_forces(&self, forces: &[ParticleForce]) -> Vec<ParticleForce> {
        let remap = |ps: &[usize]| -> Vec<usize> {
            let mut out: Vec<usize> = ps.iter().map(|&p| self.rank[p] as usize).collect();
            // The per-particle sums do not depend on the listing order; sorted slots read the
            // momentum buffer in memory order.
            out.sort_unstable();
            out
        };
        forces
            .iter()
            .map(|f| match f {
                ParticleForce::Force {
                    particles,
                    force,
                    start,
                    end,
                } => ParticleForce::Force {
                    particles: remap(particles),
                    force: *force,
                    start: *start,
                    end: *end,
                },
                ParticleForce::Impulse {
                    particles,
                    impulse,
                    time,
                } => ParticleForce::Impulse {
                    particles: remap(particles),
                    impulse: *impulse,
                    time: *time,
                },
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;

    #[test]
    fn sorts_by_key_stably_and_follows_forces() {
        let key = [9, 1, 9, 4];
        let o = Order::by_key(&key, 10).expect("not sorted");
        assert_eq!(o.slots(), &[1, 3, 0, 2]);
        assert_eq!(o.ranks(), &[2, 0, 3, 1]);
        assert_eq!(o.gather(&[10, 11, 12, 13]), vec![11, 13, 10, 12]);
        // Already sorted keys need no permutation.
        assert!(Order::by_key(&[1, 4, 9, 9], 10).is_none());
        // Force sets follow the particles.
        let f = o.sort_forces(&[ParticleForce::Impulse {
            particles: vec![0, 3],
            impulse: DVec3::X,
            time: 0.0,
        }]);
        let ParticleForce::Impulse { particles, .. } = &f[0] else {
            unreachable!()
        };
        assert_eq!(particles, &vec![1, 2]);
    }
}
