//! The two-material bar: particles on a regular lattice, a soft half and a stiff half, and a
//! texture fixed to the material that does not reveal where the halves meet.

use std::f64::consts::TAU;

use glam::DVec3;

use crate::texture::value_noise;

/// A box of particles on a cubic lattice, long axis along world x.
#[derive(Debug, Clone, PartialEq)]
pub struct Bar {
    /// Rest positions (m): cell centres of a lattice of spacing [`Bar::spacing`] filling the
    /// box `centre ± size/2`.
    pub rest: Vec<DVec3>,
    /// Lattice spacing (m); each particle stands for a volume `spacing³`.
    pub spacing: f64,
    /// Particles per axis.
    pub counts: [usize; 3],
    /// Where the halves meet: particles with rest `x < split_x` are the soft half (m).
    pub split_x: f64,
}

impl Bar {
    /// A bar of `size` (m, x × y × z) whose lowest face is at `bottom` (m) above the ground and
    /// whose centre is above the origin, filled with particles `spacing` (m) apart (a whole
    /// number per axis: `round(size / spacing)`, at least 2). Particle order: x fastest, then
    /// y, then z.
    pub fn new(size: DVec3, spacing: f64, bottom: f64) -> Self {
        let counts = size
            .to_array()
            .map(|s| ((s / spacing).round() as usize).max(2));
        let extent = DVec3::new(counts[0] as f64, counts[1] as f64, counts[2] as f64) * spacing;
        let lo = DVec3::new(-0.5 * extent.x, bottom, -0.5 * extent.z);
        let mut rest = Vec::with_capacity(counts.iter().product());
        for k in 0..counts[2] {
            for j in 0..counts[1] {
                for i in 0..counts[0] {
                    let cell = DVec3::new(i as f64, j as f64, k as f64) + DVec3::splat(0.5);
                    rest.push(lo + cell * spacing);
                }
            }
        }
        Self {
            rest,
            spacing,
            counts,
            split_x: 0.0,
        }
    }

    /// The box the lattice fills (m): `(lowest corner, highest corner)`.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        let extent = DVec3::new(
            self.counts[0] as f64,
            self.counts[1] as f64,
            self.counts[2] as f64,
        ) * self.spacing;
        let lo = self.rest[0] - DVec3::splat(0.5 * self.spacing);
        (lo, lo + extent)
    }

    /// `true` for the particles of the soft half (rest `x < split_x`).
    pub fn soft(&self) -> Vec<bool> {
        self.rest.iter().map(|p| p.x < self.split_x).collect()
    }

    /// The lattice edges: index pairs of neighbours along x, y and z.
    pub fn edges(&self) -> Vec<(usize, usize)> {
        let [nx, ny, nz] = self.counts;
        let at = |i: usize, j: usize, k: usize| i + nx * (j + ny * k);
        let mut out = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    if i + 1 < nx {
                        out.push((at(i, j, k), at(i + 1, j, k)));
                    }
                    if j + 1 < ny {
                        out.push((at(i, j, k), at(i, j + 1, k)));
                    }
                    if k + 1 < nz {
                        out.push((at(i, j, k), at(i, j, k + 1)));
                    }
                }
            }
        }
        out
    }

    /// Young's modulus per particle (Pa): `e_soft` on the soft half, `e_stiff` on the other.
    pub fn youngs_moduli(&self, e_soft: f64, e_stiff: f64) -> Vec<f64> {
        self.soft()
            .iter()
            .map(|&s| if s { e_soft } else { e_stiff })
            .collect()
    }
}

/// Unshaded colour (0–255 RGB) of the material at rest position `rest` (m): diagonal stripes
/// (period 8.5 cm along `(1, 0.45, 0.7)`, their phase wobbled by value noise) blending an
/// orange and a teal, times a ±15 % brightness noise of ~2.5 cm blotches. The pattern depends
/// on the rest position only, smoothly, the same way on both sides of the split: nothing in
/// it marks where the halves meet.
pub fn albedo(rest: DVec3) -> [f64; 3] {
    const ORANGE: [f64; 3] = [226.0, 112.0, 42.0];
    const TEAL: [f64; 3] = [38.0, 142.0, 152.0];
    let dir = DVec3::new(1.0, 0.45, 0.7).normalize();
    let phase = rest.dot(dir) / 0.085 + 1.2 * value_noise(rest / 0.06, 11);
    let s = 0.5 + 0.5 * (TAU * phase).sin();
    let bright = 0.85 + 0.3 * value_noise(rest / 0.025, 12);
    std::array::from_fn(|c| bright * (ORANGE[c] * (1.0 - s) + TEAL[c] * s))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_fills_the_box_and_splits_in_two_equal_halves() {
        let bar = Bar::new(DVec3::new(0.6, 0.15, 0.15), 0.0125, 0.25);
        assert_eq!(bar.counts, [48, 12, 12]);
        assert_eq!(bar.rest.len(), 48 * 12 * 12);
        let (lo, hi) = bar.bounds();
        assert!((lo - DVec3::new(-0.3, 0.25, -0.075)).abs().max_element() < 1e-12);
        assert!((hi - DVec3::new(0.3, 0.40, 0.075)).abs().max_element() < 1e-12);
        let soft = bar.soft();
        assert_eq!(soft.iter().filter(|&&s| s).count(), bar.rest.len() / 2);
        let edges = bar.edges();
        assert_eq!(edges.len(), 47 * 12 * 12 + 48 * 11 * 12 + 48 * 12 * 11);
        for (i, j) in edges {
            let d = (bar.rest[i] - bar.rest[j]).length();
            assert!((d - 0.0125).abs() < 1e-12, "{i} {j} {d}");
        }
        let e = bar.youngs_moduli(2e4, 6e5);
        assert_eq!(e[0], 2e4);
        assert_eq!(e[47], 6e5);
    }

    /// The texture carries no trace of the split: its mean colour over each half's particles
    /// differs by less than 8 levels of 255 (measured at most 4.6), and across the split it is
    /// as continuous as anywhere else along the bar.
    #[test]
    fn texture_does_not_reveal_the_split() {
        let bar = Bar::new(DVec3::new(0.6, 0.15, 0.15), 0.0125, 0.25);
        let soft = bar.soft();
        let mut sum = [[0.0; 3]; 2];
        let mut n = [0.0; 2];
        for (p, s) in bar.rest.iter().zip(&soft) {
            let a = albedo(*p);
            assert!(a.iter().all(|c| (0.0..=255.0).contains(c)), "{a:?}");
            let h = usize::from(*s);
            for (s, a) in sum[h].iter_mut().zip(a) {
                *s += a;
            }
            n[h] += 1.0;
        }
        for (c, (s0, s1)) in sum[0].iter().zip(&sum[1]).enumerate() {
            let (a, b) = (s0 / n[0], s1 / n[1]);
            assert!((a - b).abs() < 8.0, "channel {c}: {a:.1} vs {b:.1}");
        }
        // The largest colour step between neighbouring particles along x at the split is no
        // larger than the largest step anywhere along the bar.
        let step = |x: f64, y: f64, z: f64| {
            let a = albedo(DVec3::new(x, y, z));
            let b = albedo(DVec3::new(x + 0.0125, y, z));
            (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f64::max)
        };
        let at_split = step(-0.00625, 0.3, 0.0);
        let elsewhere = (0..47)
            .map(|i| step(-0.29375 + 0.0125 * i as f64, 0.3, 0.0))
            .fold(0.0, f64::max);
        assert!(at_split <= elsewhere, "{at_split} vs {elsewhere}");
    }
}
