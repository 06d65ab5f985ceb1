//! Interior filling of a surface-like cloud (3DGS splats, a scanned or meshed surface), as
//! PhysGaussian fills a Gaussian object before simulating it (Xie et al., CVPR 2024, "Internal
//! Filling"): without it a closed surface is simulated as a hollow shell.
//!
//! Voxels of `h = dx/2` (PAC-NeRF's 8 particles per cell) make a *wall*: every voxel holding a
//! particle (and those under the corners of a cube of `h/2` about it, so that a lattice of
//! spacing `h` leaves no gap), and, for 3DGS splats, every voxel where the splats' opacity
//! field `Σ_i α_i exp(−½ dᵀ Σ_i⁻¹ d)` reaches [`WALL_OPACITY`] (the splats, not their sparse
//! centres, close the surface the renders show). The wall is thickened by two voxels
//! (26-neighbourhood) to close gaps up to two grid cells wide, and closed underneath by a
//! *floor*: its lowest layer along gravity, made solid across the box (a capture rarely sees the
//! underside of an object resting on the ground). A 6-connected flood from the box's faces
//! marks the outside, and the thickening is undone on the outside. Every voxel the flood did not
//! reach gets one filler particle at its centre (volume `h³`), except the wall the particles
//! make and its outer layer: a torus' hole, a bowl or a cup stay empty, since the flood enters
//! from above, and a surface with a wider gap (other than underneath) is a shell. The closing
//! rounds the voxel staircase off: fillers may lie up to a grid cell outside a curved surface.
//!
//! The input particles stand for the rest of the solid: their wall, whole inside and half in
//! its outer layer (such a voxel straddles the surface), plus half of the outer layer of the
//! splats' field. So the solid's volume is `V = h³ (n_fillers + n_inner + n_outer / 2)`.

use glam::{DMat3, DQuat, DVec3};

use crate::scene::neighbors::bounds;

/// Largest voxel grid the filling builds (one byte each; ~1 s at 2²⁵ voxels).
pub const MAX_FILL_VOXELS: usize = 32 << 20;

/// Opacity-field value from which a voxel is wall (a splat of opacity 1 at 1.2 σ from its
/// centre, or two of opacity 0.5 overlapping there).
pub const WALL_OPACITY: f64 = 0.5;

/// Voxels the wall is thickened by to close gaps (up to `2·CLOSING` voxels wide).
const CLOSING: usize = 2;

/// Empty voxels between the particles' box and the grid's edge on every side.
const PAD: usize = CLOSING + 1;

/// Voxel classes.
const EMPTY: u8 = 0;
/// Holds an input particle.
const SURFACE: u8 = 1;
/// The splats' opacity field makes it wall, but it holds no input particle.
const FIELD: u8 = 2;
/// Next to a particle (under its h/2 cube), without holding one.
const COVER: u8 = 8;
const THICKENED: u8 = 3;
const FLOOR: u8 = 4;
const OUTSIDE: u8 = 5;
/// Thickening undone on the outside.
const OUTER: u8 = 6;
/// A wall voxel (SURFACE or FIELD) next to the outside.
const OUTER_WALL: u8 = 7;

/// One 3DGS splat: a Gaussian opacity blob.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Splat {
    /// Centre (m).
    pub centre: DVec3,
    /// Rotation `R` from the splat's axes to the world.
    pub rotation: DMat3,
    /// Standard deviations `S` along its axes (m).
    pub sigma: DVec3,
    /// Opacity α in `[0, 1]`.
    pub opacity: f64,
}

impl Splat {
    /// From a 3DGS PLY record: log standard deviations (log m), a rotation `(w, x, y, z)` of
    /// any non-zero length and the opacity logit. `None` for a degenerate record.
    pub fn from_3dgs(
        centre: DVec3,
        log_scale: [f64; 3],
        rot: [f64; 4],
        logit: f64,
    ) -> Option<Self> {
        let q = DQuat::from_xyzw(rot[1], rot[2], rot[3], rot[0]);
        let scale = DVec3::from_array(log_scale).exp();
        if !(q.length() > 0.0 && scale.is_finite() && scale.min_element() > 0.0) {
            return None;
        }
        let opacity = 1.0 / (1.0 + (-logit).exp());
        Some(Self {
            centre,
            rotation: DMat3::from_quat(q.normalize()),
            sigma: scale,
            opacity,
        })
        .filter(|s| s.opacity.is_finite() && s.centre.is_finite())
    }

    /// The inverse covariance `R S'⁻² Rᵀ` (1/m²) seen on voxels of edge `voxel`, with every
    /// `σ' = max(σ, voxel/2)` (a flat splat still covers the voxels it passes through), and
    /// the reach evaluated, `3 max σ'` (m).
    pub fn on_voxels(&self, voxel: f64) -> (DMat3, f64) {
        let s = self.sigma.max(DVec3::splat(0.5 * voxel));
        let inv_s2 = DMat3::from_diagonal(DVec3::ONE / (s * s));
        (
            self.rotation * inv_s2 * self.rotation.transpose(),
            3.0 * s.max_element(),
        )
    }
}

/// The filler particles of a closed surface.
#[derive(Debug, Clone, PartialEq)]
pub struct InteriorFill {
    /// Filler positions (m), one per interior voxel, in voxel order (x, then y, then z).
    pub points: Vec<DVec3>,
    /// Voxel edge `h` (m); a filler's volume is `h³`.
    pub voxel: f64,
    /// Wall voxels (particles or splats) before thickening.
    pub surface_voxels: usize,
    /// Wall voxels next to the outside (half inside the solid; no filler).
    pub outer_voxels: usize,
    /// The other voxels holding input particles or surrounded by them (inside the solid).
    pub inner_voxels: usize,
}

impl InteriorFill {
    /// Volume of one filler particle (m³).
    pub fn filler_volume(&self) -> f64 {
        self.voxel.powi(3)
    }

    /// Volume the input particles stand for (m³): their voxels inside the solid, and half the
    /// outer wall.
    pub fn surface_volume(&self) -> f64 {
        (0.5 * self.outer_voxels as f64 + self.inner_voxels as f64) * self.filler_volume()
    }

    /// Volume of the filled solid (m³).
    pub fn solid_volume(&self) -> f64 {
        self.surface_volume() + self.points.len() as f64 * self.filler_volume()
    }
}

/// Which way is down: the axis closest to `g` (e.g. gravity) and whether `g` points to its
/// negative side; `None` for a zero vector.
pub fn down_axis(g: DVec3) -> Option<(usize, bool)> {
    if !g.is_finite() || g.length_squared() == 0.0 {
        return None;
    }
    let a = g.abs().max_position();
    Some((a, g[a] < 0.0))
}

/// Fills the surface sampled by the particles `x` (m) and the optional `splats` with particles
/// on a lattice of edge `voxel` (m); `down` ([`down_axis`]) places the floor (`None`: the
/// surface must be closed on its own). `None` when the voxel grid would exceed `max_voxels` or
/// `x` is empty.
pub fn fill_interior(
    x: &[DVec3],
    splats: &[Splat],
    voxel: f64,
    down: Option<(usize, bool)>,
    max_voxels: usize,
) -> Option<InteriorFill> {
    let mut grid = Voxels::around(x, voxel, max_voxels)?;
    grid.mark_particles(x);
    grid.mark_splats(splats);
    let surface_voxels = grid.count(|c| c == SURFACE || c == FIELD);
    grid.thicken();
    if let Some(down) = down {
        grid.lay_floor(down);
    }
    grid.flood_outside();
    let outer_voxels = grid.peel_outside();
    let inner_voxels = grid.count(|c| c == SURFACE || c == COVER);
    // Every other voxel inside the wall gets a filler.
    let points = grid.centres_of(|c| matches!(c, EMPTY | THICKENED | FIELD));
    Some(InteriorFill {
        points,
        voxel,
        surface_voxels,
        outer_voxels,
        inner_voxels,
    })
}

/// A voxel grid over the particles' box plus [`PAD`] voxels, one class per voxel.
struct Voxels {
    dims: [usize; 3],
    /// Corner of voxel (0, 0, 0) (m).
    origin: DVec3,
    /// Edge (m).
    h: f64,
    class: Vec<u8>,
}

impl Voxels {
    /// All empty, or `None` over `max` voxels or without particles.
    fn around(x: &[DVec3], h: f64, max: usize) -> Option<Self> {
        let (lo, hi) = bounds(x)?;
        let ext = (hi - lo) / h;
        let mut dims = [0usize; 3];
        let mut total = 1.0f64;
        for a in 0..3 {
            let n = ext[a].floor() + 1.0 + 2.0 * PAD as f64;
            total *= n;
            if !n.is_finite() || total > max as f64 {
                return None;
            }
            dims[a] = n as usize;
        }
        Some(Self {
            dims,
            origin: lo - PAD as f64 * h,
            h,
            class: vec![EMPTY; dims.iter().product()],
        })
    }

    fn at(&self, [i, j, k]: [usize; 3]) -> usize {
        (i * self.dims[1] + j) * self.dims[2] + k
    }

    fn coord(&self, n: usize) -> [usize; 3] {
        let [_, ny, nz] = self.dims;
        [n / (ny * nz), (n / nz) % ny, n % nz]
    }

    fn centre(&self, n: usize) -> DVec3 {
        let [i, j, k] = self.coord(n);
        self.origin + self.h * DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5)
    }

    /// The voxel coordinates of `q` (m), kept inside the padding so that the grid's faces stay
    /// free for the flood.
    fn coords_of(&self, q: DVec3) -> [usize; 3] {
        let c = ((q - self.origin) / self.h).floor();
        [0, 1, 2].map(|a| (c[a].max(PAD as f64) as usize).min(self.dims[a] - 1 - PAD))
    }

    fn count(&self, pred: impl Fn(u8) -> bool) -> usize {
        self.class.iter().filter(|&&c| pred(c)).count()
    }

    fn centres_of(&self, pred: impl Fn(u8) -> bool) -> Vec<DVec3> {
        (0..self.class.len())
            .filter(|&n| pred(self.class[n]))
            .map(|n| self.centre(n))
            .collect()
    }

    /// The voxels (not on the grid's faces) of class `of` with a 26-neighbour `next_to`.
    fn touching(&self, of: impl Fn(u8) -> bool, next_to: impl Fn(u8) -> bool) -> Vec<usize> {
        (0..self.class.len())
            .filter(|&n| of(self.class[n]))
            .filter(|&n| {
                let c = self.coord(n);
                (0..3).all(|a| c[a] > 0 && c[a] + 1 < self.dims[a])
                    && neighbours26(c).any(|m| next_to(self.class[self.at(m)]))
            })
            .collect()
    }

    /// A particle's voxel is surface; the voxels under the corners of a cube of h/2 about it are
    /// covered by it, so that a lattice of spacing h leaves no voxel empty whatever its offset
    /// and rounding.
    fn mark_particles(&mut self, x: &[DVec3]) {
        for p in x {
            let n = self.at(self.coords_of(*p));
            self.class[n] = SURFACE;
        }
        for p in x {
            for corner in 0..8 {
                let d = DVec3::new(
                    f64::from(corner & 1),
                    f64::from((corner >> 1) & 1),
                    f64::from(corner >> 2),
                ) * 0.5
                    - 0.25;
                let n = self.at(self.coords_of(*p + d * self.h));
                if self.class[n] == EMPTY {
                    self.class[n] = COVER;
                }
            }
        }
    }

    /// Empty voxels where the splats' opacity field reaches [`WALL_OPACITY`] become wall.
    fn mark_splats(&mut self, splats: &[Splat]) {
        if splats.is_empty() {
            return;
        }
        let mut field = vec![0.0f32; self.class.len()];
        for s in splats {
            let (inv_cov, reach) = s.on_voxels(self.h);
            let lo = self.coords_of(s.centre - reach);
            let hi = self.coords_of(s.centre + reach);
            for i in lo[0]..=hi[0] {
                for j in lo[1]..=hi[1] {
                    for k in lo[2]..=hi[2] {
                        let n = self.at([i, j, k]);
                        let d = self.centre(n) - s.centre;
                        let m = d.dot(inv_cov * d);
                        if m < 9.0 {
                            field[n] += (s.opacity * (-0.5 * m).exp()) as f32;
                        }
                    }
                }
            }
        }
        for (c, f) in self.class.iter_mut().zip(&field) {
            if *c == EMPTY && f64::from(*f) >= WALL_OPACITY {
                *c = FIELD;
            }
        }
    }

    /// Thickens the wall by [`CLOSING`] voxels, growing a front from it (the padding keeps the
    /// grid's faces empty).
    fn thicken(&mut self) {
        let mut front: Vec<usize> = (0..self.class.len())
            .filter(|&n| self.class[n] != EMPTY)
            .collect();
        for _ in 0..CLOSING {
            let mut grown = Vec::new();
            for &n in &front {
                for m in neighbours26(self.coord(n)) {
                    let m = self.at(m);
                    if self.class[m] == EMPTY {
                        self.class[m] = THICKENED;
                        grown.push(m);
                    }
                }
            }
            front = grown;
        }
    }

    /// The floor: the wall's lowest layer along `down` (axis, towards its negative side), solid
    /// across the box.
    fn lay_floor(&mut self, (axis, negative): (usize, bool)) {
        let layers = (0..self.class.len())
            .filter(|&n| matches!(self.class[n], SURFACE | FIELD))
            .map(|n| self.coord(n)[axis]);
        let Some(layer) = (if negative { layers.min() } else { layers.max() }) else {
            return;
        };
        for n in 0..self.class.len() {
            if self.coord(n)[axis] == layer && self.class[n] == EMPTY {
                self.class[n] = FLOOR;
            }
        }
    }

    /// Floods the outside (6-connected) through empty voxels, from every face voxel.
    fn flood_outside(&mut self) {
        let dims = self.dims;
        let on_face = |c: [usize; 3]| (0..3).any(|a| c[a] == 0 || c[a] == dims[a] - 1);
        let mut stack: Vec<usize> = (0..self.class.len())
            .filter(|&n| self.class[n] == EMPTY && on_face(self.coord(n)))
            .collect();
        stack.iter().for_each(|&n| self.class[n] = OUTSIDE);
        let strides = [dims[1] * dims[2], dims[2], 1];
        while let Some(n) = stack.pop() {
            let c = self.coord(n);
            for a in 0..3 {
                let below = (c[a] > 0).then(|| n - strides[a]);
                let above = (c[a] + 1 < dims[a]).then(|| n + strides[a]);
                for m in [below, above].into_iter().flatten() {
                    if self.class[m] == EMPTY {
                        self.class[m] = OUTSIDE;
                        stack.push(m);
                    }
                }
            }
        }
    }

    /// Undoes the thickening on the outside, and the cover's outer layer (it only closes a
    /// lattice's gaps); marks the wall next to the outside as its outer layer and returns how
    /// many voxels that is.
    fn peel_outside(&mut self) -> usize {
        let outside_or_outer = |c: u8| c == OUTSIDE || c == OUTER;
        for _ in 0..CLOSING {
            for n in self.touching(|c| c == THICKENED, outside_or_outer) {
                self.class[n] = OUTER;
            }
        }
        for n in self.touching(|c| c == COVER, |c| outside_or_outer(c) || c == FLOOR) {
            self.class[n] = OUTER;
        }
        let outer = self.touching(
            |c| c == SURFACE || c == FIELD,
            |c| outside_or_outer(c) || c == FLOOR,
        );
        outer.iter().for_each(|&n| self.class[n] = OUTER_WALL);
        outer.len()
    }
}

/// The 26 neighbours of a voxel not on the grid's faces.
fn neighbours26([i, j, k]: [usize; 3]) -> impl Iterator<Item = [usize; 3]> {
    (0..27)
        .filter(|&n| n != 13)
        .map(move |n| [i + n / 9 - 1, j + (n / 3) % 3 - 1, k + n % 3 - 1])
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Points on a sphere of radius `r` (m) about `c`, about `spacing` apart (Fibonacci lattice).
    fn sphere_surface(c: DVec3, r: f64, spacing: f64) -> Vec<DVec3> {
        let n = (4.0 * PI * r * r / (spacing * spacing)).ceil() as usize;
        let golden = PI * (3.0 - 5f64.sqrt());
        (0..n)
            .map(|i| {
                let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let rho = (1.0 - y * y).sqrt();
                let phi = golden * i as f64;
                c + r * DVec3::new(rho * phi.cos(), y, rho * phi.sin())
            })
            .collect()
    }

    const DOWN: DVec3 = DVec3::new(0.0, -9.8, 0.0);

    fn down() -> Option<(usize, bool)> {
        down_axis(DOWN)
    }

    fn ball(r: f64) -> f64 {
        4.0 / 3.0 * PI * r.powi(3)
    }

    #[test]
    fn a_closed_sphere_is_filled_to_its_volume() {
        let (c, r, h) = (DVec3::new(0.3, 0.5, -0.2), 0.1, 0.01);
        let x = sphere_surface(c, r, 0.003);
        for floor in [None, down()] {
            let fill = fill_interior(&x, &[], h, floor, MAX_FILL_VOXELS).unwrap();
            let v = fill.solid_volume();
            assert!(
                (v / ball(r) - 1.0).abs() < 0.05,
                "volume {v} vs {}",
                ball(r)
            );
            // Every filler lies inside the sphere to two voxels, one grid cell (the closing rounds
            // off the voxel staircase), and the fillers reach its centre.
            let far = fill
                .points
                .iter()
                .map(|p| (*p - c).length())
                .fold(0.0, f64::max);
            assert!(far < r + 2.0 * h, "a filler {far} m from the centre");
            assert!(fill.points.iter().any(|p| (*p - c).length() < h));
            // The fillers start within 2.5 voxels (1.25 cells) of the surface: no hollow layer.
            let gap = fill
                .points
                .iter()
                .map(|p| r - (*p - c).length())
                .fold(f64::INFINITY, f64::min);
            assert!(gap < 2.5 * h, "{gap}");
        }
    }

    #[test]
    fn a_thick_layer_of_splats_counts_whole() {
        // Particles 0 to 3 voxels deep under the surface, as a 3DGS fit puts its centres.
        let (r, h) = (0.1, 0.01);
        let x: Vec<DVec3> = (0..4)
            .flat_map(|d| sphere_surface(DVec3::ZERO, r - 0.01 * d as f64, 0.003))
            .collect();
        let fill = fill_interior(&x, &[], h, down(), MAX_FILL_VOXELS).unwrap();
        let v = fill.solid_volume();
        assert!(
            (v / ball(r) - 1.0).abs() < 0.05,
            "volume {v} vs {}",
            ball(r)
        );
        assert!(
            fill.surface_volume() > 0.4 * ball(r),
            "{}",
            fill.surface_volume()
        );
    }

    #[test]
    fn a_surface_open_underneath_is_closed_by_the_floor() {
        let (c, r) = (DVec3::ZERO, 0.1);
        // The sphere without a cap 12 cm wide at the bottom (unseen from above) ...
        let bottomless: Vec<DVec3> = sphere_surface(c, r, 0.003)
            .into_iter()
            .filter(|p| p.y > -0.08)
            .collect();
        let fill = fill_interior(&bottomless, &[], 0.01, down(), MAX_FILL_VOXELS).unwrap();
        let v = fill.solid_volume();
        assert!((v / ball(r) - 1.0).abs() < 0.1, "{v} vs {}", ball(r));
        // ... but not without gravity, or with gravity along x: the flood gets in (a layer one
        // voxel thin under the shell remains, where the closing rounded off the staircase).
        for floor in [None, down_axis(DVec3::X)] {
            let open = fill_interior(&bottomless, &[], 0.01, floor, MAX_FILL_VOXELS).unwrap();
            assert!(
                open.points.len() * 10 < fill.points.len(),
                "{} fillers of {}",
                open.points.len(),
                fill.points.len()
            );
        }
        // A bowl (the lower hemisphere, open at the top) stays hollow: fillers only in the thin
        // layer under its wall.
        let bowl: Vec<DVec3> = sphere_surface(c, r, 0.003)
            .into_iter()
            .filter(|p| p.y < 0.0)
            .collect();
        let hollow = fill_interior(&bowl, &[], 0.01, down(), MAX_FILL_VOXELS).unwrap();
        assert!(hollow.points.len() * 10 < fill.points.len());
        assert!(hollow.points.iter().all(|p| p.length() > r - 0.015));
    }

    #[test]
    fn a_torus_is_filled_in_its_tube_and_not_in_its_hole() {
        // Major radius 0.15 m, tube radius 0.06 m, about the PAC-NeRF torus; tilted 30°.
        let (big, small, spacing) = (0.15f64, 0.06f64, 0.003);
        let tilt = DQuat::from_rotation_x(0.5);
        let nu = (2.0 * PI * big / spacing) as usize;
        let nv = (2.0 * PI * small / spacing) as usize;
        let x: Vec<DVec3> = (0..nu)
            .flat_map(|a| (0..nv).map(move |b| (a, b)))
            .map(|(a, b)| {
                let (u, v) = (
                    2.0 * PI * a as f64 / nu as f64,
                    2.0 * PI * b as f64 / nv as f64,
                );
                let ring = big + small * v.cos();
                tilt * DVec3::new(ring * u.cos(), small * v.sin(), ring * u.sin())
            })
            .collect();
        let exact = 2.0 * PI * PI * big * small * small;
        let tube_distance = |p: &DVec3| {
            let q = tilt.inverse() * *p;
            let ring = DVec3::new(q.x, 0.0, q.z).normalize() * big;
            (q - ring).length()
        };
        for floor in [None, down()] {
            let fill = fill_interior(&x, &[], 0.01, floor, MAX_FILL_VOXELS).unwrap();
            let v = fill.solid_volume();
            assert!((v / exact - 1.0).abs() < 0.05, "{v} vs {exact}");
            assert!(fill.points.iter().all(|p| tube_distance(p) < small + 0.02));
        }
    }

    #[test]
    fn small_gaps_in_the_surface_are_closed() {
        // Samples 1.8 voxels apart: the flood could pass between them.
        let x = sphere_surface(DVec3::ZERO, 0.1, 0.018);
        let fill = fill_interior(&x, &[], 0.01, None, MAX_FILL_VOXELS).unwrap();
        assert!(
            fill.solid_volume() > 0.8 * ball(0.1),
            "{}",
            fill.solid_volume()
        );
    }

    #[test]
    fn splats_close_a_surface_their_centres_do_not() {
        // Centres 6 voxels apart on the sphere, each a flat splat (σ = 2 voxels along the
        // surface, 0.2 across it).
        let (r, h) = (0.1, 0.01);
        let x = sphere_surface(DVec3::ZERO, r, 0.06);
        let sparse = fill_interior(&x, &[], h, None, MAX_FILL_VOXELS).unwrap();
        assert!(sparse.points.len() < 10, "{}", sparse.points.len());
        let splats: Vec<Splat> = x
            .iter()
            .map(|&c| {
                let q = DQuat::from_rotation_arc(DVec3::Z, c.normalize());
                let log_s = [0.02f64.ln(), 0.02f64.ln(), 0.002f64.ln()];
                Splat::from_3dgs(c, log_s, [q.w, q.x, q.y, q.z], 3.0).unwrap()
            })
            .collect();
        let fill = fill_interior(&x, &splats, h, None, MAX_FILL_VOXELS).unwrap();
        let v = fill.solid_volume();
        assert!((v / ball(r) - 1.0).abs() < 0.1, "volume {v} vs {}", ball(r));
        assert!(fill.points.iter().all(|p| p.length() < r + 1.5 * h));
    }

    #[test]
    fn a_splat_from_3dgs_fields() {
        let s = Splat::from_3dgs(
            DVec3::ONE,
            [0.01f64.ln(), 0.02f64.ln(), 0.03f64.ln()],
            [0.0, 0.0, 0.0, 1.0],
            0.0,
        )
        .unwrap();
        assert!((s.opacity - 0.5).abs() < 1e-12);
        // A half turn about z keeps the axes: Σ⁻¹ = diag(1/σ²), σ at least half a voxel.
        for (voxel, sx) in [(0.01, 0.01), (0.04, 0.02)] {
            let (inv_cov, reach) = s.on_voxels(voxel);
            assert!((reach - 0.09).abs() < 1e-12);
            let want = DVec3::new(1.0 / (sx * sx), 2500.0, 1.0 / 9e-4);
            let got = DVec3::new(inv_cov.x_axis.x, inv_cov.y_axis.y, inv_cov.z_axis.z);
            assert!((got - want).abs().max_element() < 1e-6 * want.max_element());
        }
        assert!(Splat::from_3dgs(DVec3::ZERO, [0.0; 3], [0.0; 4], 0.0).is_none());
        assert!(
            Splat::from_3dgs(
                DVec3::ZERO,
                [f64::INFINITY, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
                0.0
            )
            .is_none()
        );
    }

    #[test]
    fn a_solid_cloud_gets_no_fillers_and_large_grids_are_refused() {
        let mut x = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                for k in 0..10 {
                    x.push(DVec3::new(i as f64, j as f64, k as f64) * 0.005);
                }
            }
        }
        let fill = fill_interior(&x, &[], 0.005, down(), MAX_FILL_VOXELS).unwrap();
        assert!(fill.points.is_empty());
        assert_eq!(fill.surface_voxels, 1000);
        // A lattice as a PLY stores it (f32, offset): its points straddle the voxel boundaries,
        // leaving whole planes of voxels without a point, yet nothing is filled.
        let f32_lattice: Vec<DVec3> = x
            .iter()
            .map(|p| (*p * 2.0 + DVec3::new(0.0, 0.5, 0.0)).as_vec3().as_dvec3())
            .collect();
        let fill = fill_interior(&f32_lattice, &[], 0.01, down(), MAX_FILL_VOXELS).unwrap();
        assert!(fill.surface_voxels < 1000, "{}", fill.surface_voxels);
        assert!(fill.points.is_empty(), "{} fillers", fill.points.len());
        assert!(fill_interior(&x, &[], 1e-6, None, MAX_FILL_VOXELS).is_none());
        assert!(fill_interior(&[], &[], 0.01, None, MAX_FILL_VOXELS).is_none());
    }

    #[test]
    fn down_is_the_axis_closest_to_gravity() {
        assert_eq!(down(), Some((1, true)));
        assert_eq!(down_axis(DVec3::new(0.1, 0.0, 0.0)), Some((0, false)));
        assert_eq!(down_axis(DVec3::new(0.0, 1.0, -3.0)), Some((2, true)));
        assert_eq!(down_axis(DVec3::ZERO), None);
    }
}
