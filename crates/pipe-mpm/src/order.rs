//! Spatial order of the particles inside a run.
//!
//! Callers may hand particles in any order (a random cloud, a PLY file's order). Scattering and
//! gathering 27 grid nodes per particle in such an order touches the grid and the particle
//! arrays at random, and cache misses then dominate the substep. A run therefore first
//! reorders the particles by the grid cell they sit in (x-major, a stable radix sort), works
//! on that copy, and hands the results back in the caller's order. Indices a caller sees
//! (forces' particle sets, error reports, gradients) are always the caller's.
//!
//! A taped run keeps its order (the tape's checkpoints hold it), so the forward pass and the
//! backward pass's recomputation sum in the same order and stay bit-identical; a plain run
//! may sort again as the particles move (`crate::wide`).

use crate::forces::ParticleForce;
use crate::state::Material;

/// Bits per pass of [`Order::by_key`]'s radix sort (a 2048-entry count table).
const RADIX_BITS: u32 = 11;

/// A permutation of the particles: slot `i` holds the caller's particle `order[i]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Order {
    order: Vec<u32>,
    /// Inverse: the caller's particle `p` sits in slot `rank[p]`.
    rank: Vec<u32>,
}

impl Order {
    /// Particles sorted by `key` (each `< n_keys`), stably; `None` when already sorted.
    ///
    /// A least-significant-digit radix sort of `key − min` in passes of at most
    /// [`RADIX_BITS`] bits (each a stable counting sort): its tables stay small whatever the
    /// keys' range, which a counting sort over the range would sweep and allocate at every
    /// re-sort (a moving object's keys span ~6 grid nodes per particle).
    pub(crate) fn by_key(key: &[u32], n_keys: usize) -> Option<Self> {
        if key.windows(2).all(|w| w[0] <= w[1]) {
            return None;
        }
        let lo = key.iter().copied().min().unwrap_or(0);
        let hi = key.iter().copied().max().unwrap_or(0);
        debug_assert!((hi as usize) < n_keys.max(1));
        let bits = (u32::BITS - (hi - lo).leading_zeros()).max(1);
        let passes = bits.div_ceil(RADIX_BITS);
        let width = bits.div_ceil(passes);
        let mask = (1u32 << width) - 1;
        let n = key.len();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let mut next = vec![0u32; n];
        let mut start = vec![0u32; (1 << width) + 1];
        for pass in 0..passes {
            let digit = |p: u32| (((key[p as usize] - lo) >> (pass * width)) & mask) as usize;
            start.fill(0);
            for &p in &order {
                start[digit(p) + 1] += 1;
            }
            for c in 0..(1 << width) {
                start[c + 1] += start[c];
            }
            for &p in &order {
                let d = digit(p);
                next[start[d] as usize] = p;
                start[d] += 1;
            }
            std::mem::swap(&mut order, &mut next);
        }
        let mut rank = next;
        for (slot, &p) in order.iter().enumerate() {
            rank[p as usize] = slot as u32;
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

    /// Keys over ranges of 1 to 32 bits (one to three radix passes), many ties: the order
    /// must be a stable sort's.
    #[test]
    fn radix_passes_sort_stably_over_any_range() {
        let mut seed = 0x1234_5678_9abc_def0u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for bits in [1, 5, 11, 12, 17, 22, 23, 31, 32] {
            for n in [2, 37, 5000] {
                let span = if bits == 32 {
                    u32::MAX
                } else {
                    (1u32 << bits) - 1
                };
                let base = if bits == 32 { 0 } else { 1000 };
                // Few distinct values, so ties are common.
                let values: Vec<u32> = (0..8).map(|_| base + (next() as u32 & span)).collect();
                let key: Vec<u32> = (0..n).map(|_| values[next() as usize % 8]).collect();
                let mut expect: Vec<u32> = (0..n as u32).collect();
                expect.sort_by_key(|&p| key[p as usize]);
                match Order::by_key(&key, usize::MAX) {
                    Some(o) => {
                        assert_eq!(o.slots(), &expect[..], "{bits} bits, {n} keys");
                        for (slot, &p) in o.slots().iter().enumerate() {
                            assert_eq!(o.ranks()[p as usize] as usize, slot);
                        }
                    }
                    None => assert!(key.windows(2).all(|w| w[0] <= w[1])),
                }
            }
        }
    }
}
