//! Adversarial object textures for matting tests, fixed to the material (evaluated at each
//! particle's rest position, so they move and stretch with the object), with Lambert shading.

use glam::DVec3;

/// What the object looks like.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Texture {
    /// Blotches of the floor's own colour dimmed to shadow tones (×0.22–0.55): every object
    /// pixel over the floor passes the per-pixel shadow test.
    ShadowGreys,
    /// The box: blotches of the shadow-tone greys (~60 %) and crimson (~40 %).
    GreysCrimson,
    /// A neutral dark grey (levels ~46–66 before shading) close to the floor's grout lines.
    DarkGrey,
    /// Camouflage: blotches of the floor's own colour (divided by the mean shading 0.9, so lit
    /// it matches the floor in hue and brightness; ~60 %) and a pale pink (~40 %).
    FloorTone,
    /// The cream and pink object over the beige floor: blotches of a light cream
    /// (238, 226, 196; ~60 %), whose shaded sides fall to the floor's levels, and a pale pink
    /// (~40 %).
    Cream,
}

/// Hash of a lattice point to [0, 1).
fn lattice(i: i64, j: i64, k: i64, seed: u64) -> f64 {
    let mut h = seed ^ 0x9E37_79B9_7F4A_7C15;
    for v in [i, j, k] {
        h ^= v as u64;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 31;
    }
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Trilinear value noise in [0, 1) with unit lattice spacing (smoothstep-weighted).
pub fn value_noise(p: DVec3, seed: u64) -> f64 {
    let f = p.floor();
    let t = p - f;
    let s = t * t * (DVec3::splat(3.0) - 2.0 * t);
    let (i, j, k) = (f.x as i64, f.y as i64, f.z as i64);
    let mut acc = 0.0;
    for dk in 0..2 {
        for dj in 0..2 {
            for di in 0..2 {
                let w = (if di == 1 { s.x } else { 1.0 - s.x })
                    * (if dj == 1 { s.y } else { 1.0 - s.y })
                    * (if dk == 1 { s.z } else { 1.0 - s.z });
                acc += w * lattice(i + di, j + dj, k + dk, seed);
            }
        }
    }
    acc
}

/// Deterministic per-pixel noise in [−1, 1].
pub fn pixel_noise(view: u16, frame: i32, x: u32, y: u32, channel: usize) -> f64 {
    2.0 * lattice(
        i64::from(x),
        i64::from(y),
        (i64::from(frame) << 20) | ((i64::from(view)) << 4) | channel as i64,
        7,
    ) - 1.0
}

impl Texture {
    /// Unshaded colour (0–255 RGB) at rest position `rest` (metres); `floor` is the floor's
    /// median plate colour.
    pub fn albedo(self, rest: DVec3, floor: [f64; 3]) -> [f64; 3] {
        // Two octaves, blotches ~4 cm across.
        let n = 0.65 * value_noise(rest / 0.04, 1) + 0.35 * value_noise(rest / 0.015, 2);
        match self {
            Texture::ShadowGreys => {
                // Quantised into three tones: distinct blotches, each a dimmed floor colour.
                let tone = if n < 0.42 {
                    0.24
                } else if n < 0.58 {
                    0.36
                } else {
                    0.52
                };
                floor.map(|c| c * tone)
            }
            Texture::GreysCrimson => {
                if value_noise(rest / 0.05, 3) < 0.6 {
                    Texture::ShadowGreys.albedo(rest, floor)
                } else {
                    [150.0, 28.0, 40.0]
                }
            }
            Texture::DarkGrey => {
                let g = 46.0 + 20.0 * n;
                [g, g, g + 2.0]
            }
            Texture::FloorTone => {
                if value_noise(rest / 0.05, 3) < 0.6 {
                    floor.map(|c| (c / 0.9).min(255.0))
                } else {
                    [236.0, 176.0, 186.0]
                }
            }
            Texture::Cream => {
                if value_noise(rest / 0.05, 3) < 0.6 {
                    [238.0, 226.0, 196.0]
                } else {
                    [236.0, 176.0, 186.0]
                }
            }
        }
    }
}

/// Outward normal of each point of a particle cloud: the normalised sum of the offsets to its
/// neighbours within `radius` (points inward from the surface, so negated), or +y when
/// the neighbourhood is balanced (interior particles, never seen).
pub fn normals(points: &[DVec3], radius: f64) -> Vec<DVec3> {
    use std::collections::HashMap;
    let key = |p: DVec3| {
        let c = (p / radius).floor();
        (c.x as i64, c.y as i64, c.z as i64)
    };
    let mut grid: HashMap<(i64, i64, i64), Vec<usize>> = HashMap::new();
    for (i, p) in points.iter().enumerate() {
        grid.entry(key(*p)).or_default().push(i);
    }
    points
        .iter()
        .map(|p| {
            let (ci, cj, ck) = key(*p);
            let mut sum = DVec3::ZERO;
            for dk in -1..=1 {
                for dj in -1..=1 {
                    for di in -1..=1 {
                        for &q in grid.get(&(ci + di, cj + dj, ck + dk)).into_iter().flatten() {
                            let d = points[q] - *p;
                            if d.length_squared() <= radius * radius {
                                sum += d;
                            }
                        }
                    }
                }
            }
            let n = -sum;
            if n.length() > 1e-9 {
                n.normalize()
            } else {
                DVec3::Y
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_bounded_continuous_and_deterministic() {
        let a = value_noise(DVec3::new(0.3, 1.7, -2.2), 1);
        assert!((0.0..1.0).contains(&a));
        assert_eq!(a, value_noise(DVec3::new(0.3, 1.7, -2.2), 1));
        let b = value_noise(DVec3::new(0.3001, 1.7, -2.2), 1);
        assert!((a - b).abs() < 1e-2);
    }

    #[test]
    fn normals_of_a_slab_point_out_of_its_faces() {
        let mut pts = Vec::new();
        for i in 0..10 {
            for j in 0..3 {
                for k in 0..10 {
                    pts.push(DVec3::new(i as f64, j as f64, k as f64) * 0.01);
                }
            }
        }
        let n = normals(&pts, 0.025);
        let top = pts
            .iter()
            .position(|p| *p == DVec3::new(0.05, 0.02, 0.05))
            .unwrap();
        let bottom = pts
            .iter()
            .position(|p| *p == DVec3::new(0.05, 0.0, 0.05))
            .unwrap();
        assert!(n[top].y > 0.99, "{}", n[top]);
        assert!(n[bottom].y < -0.99, "{}", n[bottom]);
    }
}
