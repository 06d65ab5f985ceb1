//! Spatial order of the particles inside a run.
//!
//! Callers may hand particles in any order (a random cloud, a PLY file's order). Scattering and
//! gathering 27 grid nodes per particle in such an order touches the grid and the particle
//! arrays at random, and cache misses then dominate the substep. A run therefore first
//! reorders the particles by the grid cell they sit in (x-major, a stable counting sort), works
//! on that copy, and hands the results back in the caller's order. Indices a caller sees
//! (forces' particle sets, error reports, gradients) are always the caller's.
//!
//! The order is fixed for a whole run (and kept in its [`crate::Tape`]), so the forward pass
//! and the backward pass's recomputation sum in the same order and stay bit-identical.

use glam::DVec3;

use crate::forces::ParticleForce;
use crate::grid::GridSpec;
use crate::state::{Material, MaterialGrad, State, StateGrad};

/// A permutation of the particles: slot `i` holds the caller's particle `order[i]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Order {
    order: Vec<u32>,
    /// Inverse: the caller's particle `p` sits in slot `rank[p]`.
    rank: Vec<u32>,
}

impl Order {
    /// Particles sorted by the linear index of their stencil's base cell (stable, so equal
    /// cells keep the caller's order); `None` when the caller's order is already sorted.
    /// Positions must lie inside the grid's domain.
    pub(crate) fn by_cell(grid: &GridSpec, x: &[DVec3]) -> Option<Self> {
        let key: Vec<u32> = x
            .iter()
            .map(|&p| grid.linear(grid.stencil(p).local) as u32)
            .collect();
        Self::by_key(&key, grid.len())
    }

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

    /// The caller's index of the particle in slot `i`.
    #[inline]
    pub(crate) fn original(&self, i: usize) -> usize {
        self.order[i] as usize
    }

    /// The slot of the caller's particle `p`.
    #[inline]
    pub(crate) fn slot(&self, p: usize) -> usize {
        self.rank[p] as usize
    }

    /// `src` (caller's order) in slot order.
    pub(crate) fn gather<T: Copy>(&self, src: &[T]) -> Vec<T> {
        self.order.iter().map(|&p| src[p as usize]).collect()
    }

    /// `sorted` (slot order) in the caller's order.
    pub(crate) fn unsorted<T: Copy>(&self, sorted: &[T]) -> Vec<T> {
        self.rank.iter().map(|&i| sorted[i as usize]).collect()
    }

    /// Writes `sorted` (slot order) into `dst` (caller's order).
    pub(crate) fn scatter<T: Copy>(&self, sorted: &[T], dst: &mut [T]) {
        for (&p, &v) in self.order.iter().zip(sorted) {
            dst[p as usize] = v;
        }
    }

    /// A state in slot order.
    pub(crate) fn sort_state(&self, s: &State) -> State {
        State {
            x: self.gather(&s.x),
            v: self.gather(&s.v),
            c: self.gather(&s.c),
            f: self.gather(&s.f),
        }
    }

    /// Writes a slot-order state into `dst` (caller's order, same length).
    pub(crate) fn unsort_state_into(&self, sorted: &State, dst: &mut State) {
        self.scatter(&sorted.x, &mut dst.x);
        self.scatter(&sorted.v, &mut dst.v);
        self.scatter(&sorted.c, &mut dst.c);
        self.scatter(&sorted.f, &mut dst.f);
    }

    /// A slot-order state back in the caller's order.
    pub(crate) fn unsort_state(&self, sorted: &State) -> State {
        State {
            x: self.unsorted(&sorted.x),
            v: self.unsorted(&sorted.v),
            c: self.unsorted(&sorted.c),
            f: self.unsorted(&sorted.f),
        }
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

    /// Adds `g` (caller's order) into `dst` (slot order, same length).
    pub(crate) fn add_sorted_grad(&self, g: &StateGrad, dst: &mut StateGrad) {
        for (i, &p) in self.order.iter().enumerate() {
            let p = p as usize;
            dst.x[i] += g.x[p];
            dst.v[i] += g.v[p];
            dst.c[i] += g.c[p];
            dst.f[i] += g.f[p];
        }
    }

    /// A slot-order gradient back in the caller's order.
    pub(crate) fn unsort_grad(&self, sorted: &StateGrad) -> StateGrad {
        StateGrad {
            x: self.unsorted(&sorted.x),
            v: self.unsorted(&sorted.v),
            c: self.unsorted(&sorted.c),
            f: self.unsorted(&sorted.f),
        }
    }

    /// A slot-order material gradient back in the caller's order.
    pub(crate) fn unsort_material_grad(&self, sorted: &MaterialGrad) -> MaterialGrad {
        MaterialGrad {
            mass: self.unsorted(&sorted.mass),
            volume: self.unsorted(&sorted.volume),
            mu: self.unsorted(&sorted.mu),
            lam: self.unsorted(&sorted.lam),
            family: sorted.family,
            family_per_particle: if sorted.family_per_particle.is_empty() {
                Vec::new()
            } else {
                self.unsorted(&sorted.family_per_particle)
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
    use super::*;
    use crate::grid::Aabb;

    #[test]
    fn sorts_by_cell_stably_and_round_trips() {
        let g = GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.25, 2).unwrap();
        let x = vec![
            DVec3::new(0.9, 0.1, 0.1),
            DVec3::new(0.1, 0.1, 0.1),
            DVec3::new(0.9, 0.1, 0.12),
            DVec3::new(0.1, 0.9, 0.1),
        ];
        let o = Order::by_cell(&g, &x).expect("not sorted");
        assert_eq!(o.order, vec![1, 3, 0, 2]);
        let s = State::at_rest(x.clone());
        let sorted = o.sort_state(&s);
        assert_eq!(sorted.x[0], x[1]);
        assert_eq!(o.unsort_state(&sorted), s);
        assert_eq!(o.original(2), 0);
        // Already sorted input needs no permutation.
        assert!(Order::by_cell(&g, &sorted.x).is_none());
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
