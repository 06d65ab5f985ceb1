//! Splats carried by fewer particles: the Gaussians of a 3DGS cloud that share one voxel of the
//! interior filling (edge `dx/2`, eight per grid cell, as PAC-NeRF samples its particles) ride
//! one simulation particle instead of being one each.
//!
//! A fitted 3DGS surface packs several Gaussians into each surface voxel; simulated one by one
//! they double or triple the particle count (a torus of 14k Gaussians filled to 17k particles
//! against 5.4k voxels), and every substep's cost with it, for no resolution the grid can
//! use: the velocity field lives on the grid of cell `dx`, and a particle's affine motion
//! (APIC's `C`, its deformation gradient `F`) already describes its neighbourhood.
//!
//! Gaussian `g` rides particle `c = carrier[g]` at the rest offset `d_g = X_g − X_c`:
//! `x_g = x_c + A_c d_g` with `A = F` (solids) or `J^{1/3} I` (a Newtonian fluid, whose `F`
//! holds only its volume ratio), its covariance deformed by `F_c` as before. The carrier sits
//! at the volume-weighted centroid of its Gaussians and stands for their summed volume.

use std::borrow::Cow;

use glam::{DMat3, DVec3};

use super::fill::NO_VOXEL;

/// Which particle each Gaussian rides, and where.
#[derive(Debug, Clone, PartialEq)]
pub struct Skin {
    /// Particle index of each Gaussian.
    carrier: Vec<u32>,
    /// Rest offset of each Gaussian from its particle (m).
    offset: Vec<DVec3>,
    /// Particles that carry Gaussians (the highest carrier index plus one).
    particles: usize,
    /// Whether Gaussian `g` is particle `g`, at no offset, for every `g`.
    identity: bool,
}

/// The particles of merged inputs.
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// One particle per group (m), in the order of each group's first input.
    pub particles: Vec<DVec3>,
    /// Each particle's volume: its inputs' summed volume (m³).
    pub volumes: Vec<f64>,
    /// How the inputs ride them.
    pub skin: Skin,
}

impl Skin {
    /// Gaussian `g` rides particle `carrier[g]` at the rest offset `offset[g]` (m).
    pub fn new(carrier: Vec<u32>, offset: Vec<DVec3>) -> Self {
        assert_eq!(carrier.len(), offset.len(), "one offset per Gaussian");
        let particles = carrier.iter().max().map_or(0, |&c| c as usize + 1);
        let identity = carrier.iter().enumerate().all(|(g, c)| *c as usize == g)
            && offset.iter().all(|d| *d == DVec3::ZERO);
        Self {
            carrier,
            offset,
            particles,
            identity,
        }
    }

    /// Every Gaussian its own particle (`carrier[g] = g`, no offset).
    pub fn identity(n: usize) -> Self {
        Self::new((0..n as u32).collect(), vec![DVec3::ZERO; n])
    }

    /// Particle index of each Gaussian.
    pub fn carrier(&self) -> &[u32] {
        &self.carrier
    }

    /// Rest offset of each Gaussian from its particle (m).
    pub fn offset(&self) -> &[DVec3] {
        &self.offset
    }

    /// Gaussians carried.
    pub fn len(&self) -> usize {
        self.carrier.len()
    }

    /// Whether none are.
    pub fn is_empty(&self) -> bool {
        self.carrier.is_empty()
    }

    /// Particles that carry Gaussians (the highest carrier index plus one).
    pub fn particles(&self) -> usize {
        self.particles
    }

    /// Whether Gaussian `g` is particle `g`, at no offset, for every `g`.
    pub fn is_identity(&self) -> bool {
        self.identity
    }

    /// One value per Gaussian: its carrier's (the first particles' own, borrowed, for the
    /// identity skin).
    pub fn gather<'a, T: Clone>(&self, per_particle: &'a [T]) -> Cow<'a, [T]> {
        if self.identity {
            return Cow::Borrowed(&per_particle[..self.len()]);
        }
        Cow::Owned(
            self.carrier
                .iter()
                .map(|&c| per_particle[c as usize].clone())
                .collect(),
        )
    }

    /// The Gaussians' centres (m) for particles at `x` whose neighbourhoods map by `a`
    /// (`x_c + A_c d_g`).
    pub fn positions(&self, x: &[DVec3], a: &[DMat3]) -> Vec<DVec3> {
        self.carrier
            .iter()
            .zip(&self.offset)
            .map(|(&c, d)| x[c as usize] + a[c as usize] * *d)
            .collect()
    }
}

/// Merges the inputs `x` (m) that share a voxel (`voxel`, from the filling) into one particle
/// each, at their volume-weighted centroid. An input outside the solid ([`NO_VOXEL`]: a faint
/// splat the opacity field does not hold) is appearance, not matter: it rides the particle
/// nearest to it at no volume, so that it can neither weigh on the body nor hang under it as
/// a keel (a thin plate fitted from cameras above it gathered faint splats up to 10 cm under
/// it, and its simulated double tipped over where the capture lay flat). Only when no input
/// shares a voxel does each stay its own particle, at its own volume.
pub fn merge(x: &[DVec3], voxel: &[usize], volume: &[f64]) -> Merged {
    assert_eq!(x.len(), voxel.len(), "one voxel per input");
    assert_eq!(x.len(), volume.len(), "one volume per input");
    let mut group_of = std::collections::HashMap::new();
    let mut carrier = vec![u32::MAX; x.len()];
    let mut sums: Vec<(DVec3, f64, DVec3, usize)> = Vec::new();
    let strays_alone = voxel.iter().all(|&v| v == NO_VOXEL);
    for (i, (&p, &v)) in x.iter().zip(volume).enumerate() {
        let g = if voxel[i] == NO_VOXEL {
            if !strays_alone {
                continue;
            }
            sums.push((DVec3::ZERO, 0.0, DVec3::ZERO, 0));
            sums.len() - 1
        } else {
            *group_of.entry(voxel[i]).or_insert_with(|| {
                sums.push((DVec3::ZERO, 0.0, DVec3::ZERO, 0));
                sums.len() - 1
            })
        };
        let s = &mut sums[g];
        s.0 += p * v;
        s.1 += v;
        s.2 += p;
        s.3 += 1;
        carrier[i] = g as u32;
    }
    let particles: Vec<DVec3> = sums
        .iter()
        .map(|&(px, v, p, n)| if v > 0.0 { px / v } else { p / n as f64 })
        .collect();
    if carrier.contains(&u32::MAX) {
        // Strays ride the nearest particle (ties: the lowest index).
        let (lo, hi) = crate::scene::neighbors::bounds(&particles).expect("a voxel group");
        let h = ((hi - lo).max_element() / 32.0).max(1e-6);
        let grid = crate::scene::neighbors::PointGrid::new(&particles, h);
        for (i, c) in carrier.iter_mut().enumerate() {
            if *c == u32::MAX {
                *c = grid.nearest(x[i], None).expect("a particle").0 as u32;
            }
        }
    }
    let offset = x
        .iter()
        .zip(&carrier)
        .map(|(p, &c)| *p - particles[c as usize])
        .collect();
    Merged {
        volumes: sums.iter().map(|s| s.1).collect(),
        particles,
        skin: Skin::new(carrier, offset),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_of_one_voxel_ride_one_particle_at_their_centroid() {
        let x = [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(5.0, 5.0, 5.0),
            DVec3::new(0.0, 2.0, 0.0),
            DVec3::new(9.0, 9.0, 9.0),
        ];
        let m = merge(&x, &[7, 7, NO_VOXEL, 7, 3], &[1.0, 1.0, 0.5, 2.0, 1.0]);
        // The stray (input 2) rides the nearest particle, the other voxel's, at no volume.
        assert_eq!(m.skin.carrier(), &[0, 0, 1, 0, 1]);
        assert_eq!(m.skin.particles(), 2);
        assert_eq!(m.volumes, vec![4.0, 1.0]);
        // (0 + 1 + 2·(0, 2, 0)) / 4.
        assert_eq!(m.particles[0], DVec3::new(0.25, 1.0, 0.0));
        assert_eq!(m.particles[1], x[4]);
        // Strays alone (no input in the solid) stay particles, at their own volume.
        let alone = merge(&x[..2], &[NO_VOXEL; 2], &[0.5, 0.25]);
        assert_eq!(alone.skin.carrier(), &[0, 1]);
        assert_eq!(alone.volumes, vec![0.5, 0.25]);
        // The skin puts every input back where it was at rest, whatever F is at rest (I).
        let back = m.skin.positions(&m.particles, &[DMat3::IDENTITY; 2]);
        for (a, b) in back.iter().zip(&x) {
            assert!((*a - *b).length() < 1e-15, "{a} vs {b}");
        }
        assert!(!m.skin.is_identity());
        assert!(Skin::identity(4).is_identity());
        // Under F the offsets turn with the carrier.
        let f = DMat3::from_rotation_z(0.5) * 2.0;
        let moved = m.skin.positions(&m.particles, &[f; 2]);
        assert!((moved[1] - (m.particles[0] + f * (x[1] - m.particles[0]))).length() < 1e-15);
    }
}
