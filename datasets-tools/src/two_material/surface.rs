//! The body a particle lattice stands for, as a surface to ray-trace: the level set
//! `φ(x) = ½` of `φ(x) = Σ_p N(A_p⁻¹ (x − x_p) / s)`, with `N` the tensor-product quadratic
//! B-spline (MPM's own weight: `¾ − u²` for `|u| < ½`, `½ (3/2 − |u|)²` for `|u| < 3/2`), `s`
//! the lattice spacing and `A_p` the particle's local deformation (the least-squares affine map
//! of its lattice neighbours' rest offsets onto their current ones).
//!
//! Why this surface: a particle on a cubic lattice of spacing `s` stands for the cube of side
//! `s` around it (its volume `s³`). The B-splines of a lattice sum to 1 (partition of unity),
//! and the half-lattice's sum is exactly ½ half a spacing beyond its last layer, so at rest
//! the surface lies on the cubes' faces (edges and corners rounded inward), and under a smooth
//! deformation it follows the deformed cubes. Spheres of radius `r` per particle, by contrast,
//! put the surface `r − s/2` outside the body (a quarter spacing for `r = 0.75 s`, which a
//! sphere tracer needs to close the gaps between neighbours), so the images show a body
//! thicker and heavier than the one simulated.
//!
//! `φ` and the rest position `Σ w X_p / φ` (which carries the texture, so it moves with the
//! material and stays sharp) are sampled on a grid of `s/3` (coarser only when the particles
//! spread over more than `MAX_NODES` nodes) and interpolated trilinearly; a ray marches in
//! half-node steps, skipping blocks where `φ < ½` everywhere, and bisects the crossing.

use std::collections::HashMap;

use glam::{DMat3, DVec3};

/// The grid's node budget (`φ` and the rest position, 16 bytes a node).
const MAX_NODES: f64 = 8.0e6;
/// Nodes per side of an empty-space block.
const BLOCK: usize = 8;
/// The level of the surface.
pub const LEVEL: f32 = 0.5;

/// The quadratic B-spline.
fn bspline(u: f64) -> f64 {
    let a = u.abs();
    if a < 0.5 {
        0.75 - a * a
    } else if a < 1.5 {
        0.5 * (1.5 - a) * (1.5 - a)
    } else {
        0.0
    }
}

/// Each particle's local deformation: the least-squares affine map `A` with
/// `x_q − x_p ≈ A (X_q − X_p)` over its lattice neighbours `q` (the 26 around it that exist),
/// or the identity where they do not determine one (fewer than three independent offsets) or
/// it is degenerate (volume ratio outside 1/8–8: a particle torn from its neighbours).
pub fn local_deformations(rest: &[DVec3], current: &[DVec3], spacing: f64) -> Vec<DMat3> {
    let Some(origin) = rest.first().copied() else {
        return Vec::new();
    };
    let key = |x: DVec3| {
        let k = ((x - origin) / spacing).round();
        [k.x as i64, k.y as i64, k.z as i64]
    };
    let index: HashMap<[i64; 3], usize> =
        rest.iter().enumerate().map(|(i, x)| (key(*x), i)).collect();
    rest.iter()
        .zip(current)
        .map(|(xr, xc)| {
            let k = key(*xr);
            let (mut xx, mut yx) = (DMat3::ZERO, DMat3::ZERO);
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let Some(&q) = index.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else {
                            continue;
                        };
                        let d_rest = rest[q] - *xr;
                        let d_now = current[q] - *xc;
                        xx += outer(d_rest, d_rest);
                        yx += outer(d_now, d_rest);
                    }
                }
            }
            let scale = spacing * spacing;
            if xx.determinant() < 1e-3 * scale * scale * scale {
                return DMat3::IDENTITY;
            }
            let a = yx * xx.inverse();
            let det = a.determinant();
            if a.is_finite() && (0.125..=8.0).contains(&det) {
                a
            } else {
                DMat3::IDENTITY
            }
        })
        .collect()
}

fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// `φ` and the weighted rest position on a grid, ready to be ray-traced.
#[derive(Debug, Clone)]
pub struct Surface {
    lo: DVec3,
    h: f64,
    n: [usize; 3],
    /// Per node: `φ` and `Σ w X_p` (m).
    node: Vec<[f32; 4]>,
    /// Per block of `BLOCK³` cells: the largest `φ` of its nodes.
    block_max: Vec<f32>,
    nb: [usize; 3],
}

impl Surface {
    /// The surface of the particles at `current` (m) whose lattice rest positions are `rest`
    /// (spacing `spacing`, m).
    pub fn new(rest: &[DVec3], current: &[DVec3], spacing: f64) -> Self {
        assert_eq!(rest.len(), current.len(), "rest and current positions");
        let deformations = local_deformations(rest, current, spacing);
        let reach: Vec<DVec3> = deformations
            .iter()
            .map(|a| {
                let abs = DMat3::from_cols(a.x_axis.abs(), a.y_axis.abs(), a.z_axis.abs());
                abs * DVec3::splat(1.5 * spacing)
            })
            .collect();
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for (x, r) in current.iter().zip(&reach) {
            lo = lo.min(*x - *r);
            hi = hi.max(*x + *r);
        }
        if current.is_empty() {
            (lo, hi) = (DVec3::ZERO, DVec3::ZERO);
        }
        let size = hi - lo;
        let h = (spacing / 3.0).max((size.x * size.y * size.z / MAX_NODES).cbrt());
        lo -= DVec3::splat(h);
        let n = ((size + DVec3::splat(2.0 * h)) / h).ceil().as_uvec3();
        let n = [n.x as usize + 1, n.y as usize + 1, n.z as usize + 1];
        let mut node = vec![[0.0f32; 4]; n[0] * n[1] * n[2]];
        for ((x, r), (a, xr)) in current
            .iter()
            .zip(&reach)
            .zip(deformations.iter().zip(rest))
        {
            let inv = a.inverse() / spacing;
            let first = ((*x - *r - lo) / h).ceil().max(DVec3::ZERO).as_uvec3();
            let last = ((*x + *r - lo) / h).floor().as_uvec3();
            for k in first.z as usize..=(last.z as usize).min(n[2] - 1) {
                for j in first.y as usize..=(last.y as usize).min(n[1] - 1) {
                    for i in first.x as usize..=(last.x as usize).min(n[0] - 1) {
                        let p = lo + DVec3::new(i as f64, j as f64, k as f64) * h;
                        let u = inv * (p - *x);
                        let w = bspline(u.x) * bspline(u.y) * bspline(u.z);
                        if w > 0.0 {
                            let cell = &mut node[(k * n[1] + j) * n[0] + i];
                            cell[0] += w as f32;
                            cell[1] += (w * xr.x) as f32;
                            cell[2] += (w * xr.y) as f32;
                            cell[3] += (w * xr.z) as f32;
                        }
                    }
                }
            }
        }
        let nb = n.map(|c| (c - 1).div_ceil(BLOCK).max(1));
        let mut block_max = vec![0.0f32; nb[0] * nb[1] * nb[2]];
        for k in 0..n[2] {
            for j in 0..n[1] {
                for i in 0..n[0] {
                    let v = node[(k * n[1] + j) * n[0] + i][0];
                    // A node on a block's face belongs to the blocks on both sides.
                    for bk in blocks_of(k, nb[2]) {
                        for bj in blocks_of(j, nb[1]) {
                            for bi in blocks_of(i, nb[0]) {
                                let b = &mut block_max[(bk * nb[1] + bj) * nb[0] + bi];
                                *b = b.max(v);
                            }
                        }
                    }
                }
            }
        }
        Self {
            lo,
            h,
            n,
            node,
            block_max,
            nb,
        }
    }

    /// `φ` and the rest position (m) at `p`, trilinearly; zero outside the grid.
    pub fn sample(&self, p: DVec3) -> (f64, DVec3) {
        let g = (p - self.lo) / self.h;
        let f = g.floor();
        if f.min_element() < 0.0
            || f.x as usize + 1 >= self.n[0]
            || f.y as usize + 1 >= self.n[1]
            || f.z as usize + 1 >= self.n[2]
        {
            return (0.0, DVec3::ZERO);
        }
        let t = g - f;
        let (i, j, k) = (f.x as usize, f.y as usize, f.z as usize);
        let mut acc = [0.0f64; 4];
        for (dk, wk) in [(0, 1.0 - t.z), (1, t.z)] {
            for (dj, wj) in [(0, 1.0 - t.y), (1, t.y)] {
                for (di, wi) in [(0, 1.0 - t.x), (1, t.x)] {
                    let v = self.node[((k + dk) * self.n[1] + j + dj) * self.n[0] + i + di];
                    let w = wi * wj * wk;
                    for c in 0..4 {
                        acc[c] += w * f64::from(v[c]);
                    }
                }
            }
        }
        (acc[0], DVec3::new(acc[1], acc[2], acc[3]))
    }

    /// The first crossing of `φ = ½` along `o + t d` (`d` unit) with `0 < t < t_max`: the
    /// distance, the outward unit normal and the rest position there.
    pub fn hit(&self, o: DVec3, d: DVec3, t_max: f64) -> Option<(f64, DVec3, DVec3)> {
        let hi = self.lo
            + DVec3::new(
                (self.n[0] - 1) as f64,
                (self.n[1] - 1) as f64,
                (self.n[2] - 1) as f64,
            ) * self.h;
        let (mut t, t_end) = slab(o, d, self.lo, hi)?;
        t = t.max(0.0);
        let t_end = t_end.min(t_max);
        let step = 0.5 * self.h;
        let level = f64::from(LEVEL);
        if self.sample(o + t * d).0 >= level {
            return (t > 0.0).then(|| self.finish(o, d, t));
        }
        while t < t_end {
            if let Some(exit) = self.empty_block_exit(o + t * d, o, d) {
                t = exit.max(t + 1e-9 * self.h);
                continue;
            }
            let next = (t + step).min(t_end);
            if self.sample(o + next * d).0 >= level {
                // The crossing lies in (t, next]: bisect it.
                let (mut a, mut b) = (t, next);
                for _ in 0..20 {
                    let m = 0.5 * (a + b);
                    if self.sample(o + m * d).0 >= level {
                        b = m;
                    } else {
                        a = m;
                    }
                }
                return Some(self.finish(o, d, b));
            }
            if next >= t_end {
                break;
            }
            t = next;
        }
        None
    }

    fn finish(&self, o: DVec3, d: DVec3, t: f64) -> (f64, DVec3, DVec3) {
        let p = o + t * d;
        let e = 0.5 * self.h;
        let grad = DVec3::new(
            self.sample(p + DVec3::X * e).0 - self.sample(p - DVec3::X * e).0,
            self.sample(p + DVec3::Y * e).0 - self.sample(p - DVec3::Y * e).0,
            self.sample(p + DVec3::Z * e).0 - self.sample(p - DVec3::Z * e).0,
        );
        let normal = if grad.length_squared() > 0.0 {
            -grad.normalize()
        } else {
            -d
        };
        let (phi, weighted) = self.sample(p);
        let rest = if phi > 0.0 {
            weighted / phi
        } else {
            DVec3::ZERO
        };
        (t, normal, rest)
    }

    /// Where the ray leaves the block holding `p`, when every node of that block has `φ < ½`.
    fn empty_block_exit(&self, p: DVec3, o: DVec3, d: DVec3) -> Option<f64> {
        let g = (p - self.lo) / (self.h * BLOCK as f64);
        let b = g.floor();
        if b.min_element() < 0.0 {
            return None;
        }
        let (bi, bj, bk) = (b.x as usize, b.y as usize, b.z as usize);
        if bi >= self.nb[0] || bj >= self.nb[1] || bk >= self.nb[2] {
            return None;
        }
        if self.block_max[(bk * self.nb[1] + bj) * self.nb[0] + bi] >= LEVEL {
            return None;
        }
        let side = self.h * BLOCK as f64;
        let lo = self.lo + b * side;
        slab(o, d, lo, lo + DVec3::splat(side)).map(|(_, exit)| exit)
    }
}

/// The blocks a node index belongs to (two when it lies on a face between blocks).
fn blocks_of(i: usize, nb: usize) -> impl Iterator<Item = usize> {
    let b = i / BLOCK;
    let on_face = i.is_multiple_of(BLOCK) && i > 0;
    let first = if on_face { b - 1 } else { b };
    (first..=b).filter(move |x| *x < nb)
}

/// The ray's entry and exit distances through the box `[lo, hi]`, if it meets it ahead.
fn slab(o: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let inv = d.recip();
    let a = (lo - o) * inv;
    let b = (hi - o) * inv;
    let t0 = a.min(b).max_element();
    let t1 = a.max(b).min_element();
    (t1 >= t0.max(0.0)).then_some((t0, t1))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slab_lattice(nx: i32, ny: i32, nz: i32, s: f64) -> Vec<DVec3> {
        let mut out = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    out.push(DVec3::new(
                        (f64::from(i) + 0.5) * s,
                        (f64::from(j) + 0.5) * s,
                        (f64::from(k) + 0.5) * s,
                    ));
                }
            }
        }
        out
    }

    /// At rest a box of particles is drawn at the faces of its cubes: a ray along x through
    /// the middle of a face meets the surface where the lattice's cubes end.
    #[test]
    fn a_box_at_rest_is_drawn_at_its_cubes_faces() {
        let s = 0.02;
        let rest = slab_lattice(10, 6, 6, s);
        let surface = Surface::new(&rest, &rest, s);
        let o = DVec3::new(-1.0, 3.0 * s, 3.0 * s);
        let (t, n, r) = surface.hit(o, DVec3::X, f64::INFINITY).unwrap();
        assert!((t - 1.0).abs() < 0.02 * s, "{t}");
        assert!((n - DVec3::NEG_X).length() < 1e-3, "{n}");
        assert!((r.x - 0.5 * s).abs() < 0.3 * s, "{r}");
        // A ray that misses the box misses the surface.
        let off = DVec3::new(-1.0, 6.0 * s + 0.3 * s, 3.0 * s);
        assert!(surface.hit(off, DVec3::X, f64::INFINITY).is_none());
        // Even a one-particle-thick plate is drawn at its faces.
        let plate = slab_lattice(8, 1, 8, s);
        let surface = Surface::new(&plate, &plate, s);
        let o = DVec3::new(4.0 * s, 1.0, 4.0 * s);
        let (t, _, _) = surface.hit(o, DVec3::NEG_Y, f64::INFINITY).unwrap();
        assert!((t - (1.0 - s)).abs() < 0.05 * s, "{t}");
    }

    /// A turned and stretched box is drawn where its cubes went: the local deformation is the
    /// map itself, and the face moves with it.
    #[test]
    fn a_deformed_box_follows_its_deformation() {
        let s = 0.02;
        let rest = slab_lattice(8, 8, 8, s);
        let rot = DMat3::from_rotation_y(0.6) * DMat3::from_diagonal(DVec3::new(1.2, 1.0, 0.9));
        let current: Vec<DVec3> = rest.iter().map(|x| rot * *x).collect();
        let a = local_deformations(&rest, &current, s);
        assert!(
            a.iter()
                .all(|m| (*m - rot).abs().to_cols_array().iter().all(|v| *v < 1e-9))
        );
        let surface = Surface::new(&rest, &current, s);
        // The centre of the rest box's +y face, carried by the map; a ray down onto it.
        let top = rot * DVec3::new(4.0 * s, 8.0 * s, 4.0 * s);
        let (t, n, _) = surface
            .hit(top + DVec3::Y, DVec3::NEG_Y, f64::INFINITY)
            .unwrap();
        assert!((t - 1.0).abs() < 0.05 * s, "{t}");
        assert!(n.y > 0.99, "{n}");
        // Beyond the ground cut-off nothing is hit.
        assert!(surface.hit(top + DVec3::Y, DVec3::NEG_Y, 0.9).is_none());
    }
}
