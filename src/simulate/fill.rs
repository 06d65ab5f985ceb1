//! Interior filling of a surface-like cloud (3DGS splats, a scanned or meshed surface), as
//! PhysGaussian fills a Gaussian object before simulating it (Xie et al., CVPR 2024, "Internal
//! Filling"): without it a closed surface is simulated as a hollow shell, and a 3DGS fit,
//! whose Gaussians sit inside the surface they render, as a body too small and too light.
//!
//! On voxels of `h = dx/2` (PAC-NeRF's 8 particles per cell) the filling finds the *wall*,
//! closes it, floods the outside and keeps the rest as the *solid*:
//!
//! - 3DGS splats: the solid is the set their opacity field
//!   `F(x) = Σ_i α_i exp(−½ dᵀ Σ_i⁻¹ d)` puts at or above [`WALL_OPACITY`], with what that
//!   surface encloses. For one splat `F ≥ ½` is exactly the set whose projection the
//!   rasterizer draws with α ≥ ½, the mask's edge; a splat set fitted to images renders
//!   through the rasterizer's low-pass filter at their resolution, which the caller adds to
//!   every `Σ_i` ([`Splat::filtered`]). The wall is every voxel whose centre reaches ½, and
//!   both ends of every voxel edge on which the splats' maxima sum to ½ (a splat layer
//!   thinner than a voxel crosses there), so that no 6-connected path crosses a layer.
//!   Each solid voxel's volume `h³` goes to the splats whose centres lie in it, or lie just
//!   outside the solid next to it (shared evenly), or else to one filler particle at its
//!   centre; a splat more than a voxel outside the solid (a faint one) carries
//!   [`STRAY_VOLUME`] of a voxel when it is its own particle (with `merge_splats` it rides
//!   the nearest particle at no volume instead, [`crate::simulate::skin::merge`]).
//! - Points only (a sampled surface): the wall is every voxel holding a point, and those under
//!   the corners of a cube of `h/2` about it (so that a lattice of spacing `h` leaves no gap).
//!   Fillers go into the enclosed voxels; the points share their wall's volume evenly, the
//!   wall's voxels next to the outside counting half (the surface passes through them).
//!
//! The wall is thickened by two voxels (26-neighbourhood) to close gaps up to two grid cells
//! wide and, when the object rests on a ground plane (its lowest wall layer within
//! [`FLOOR_REACH_VOXELS`] of it), closed underneath by a *floor* across that layer (a capture
//! rarely sees the underside of an object on the ground; an object in the air is closed by its
//! own splats, and a floor there would close a cup upside down). A 6-connected flood from the
//! box's faces marks the outside; the thickening is undone on the outside, and for splats the
//! outside then advances (two steps) into the voxels whose centres the field misses unless a
//! layer crosses between, so the solid ends at the splats' surface. What the flood did not
//! reach is the solid: a torus' hole, a bowl or a cup stay empty, since the flood enters
//! through their openings, and a surface with a wider gap is a shell.
//!
//! A splat solid's volume is counted on the voxel centres (unbiased for a surface the voxels
//! resolve): `V = h³ · #solid voxels`. The generated scenes of `fill/scenes.rs` (spheres,
//! boxes, tori on the ground and in the air, a cup; splats on the surface, in the volume, or
//! both) are filled to within 1.8 % of their volume at `h` = 1/48 and 1/32 of their extent.
//! The field is summed splat by splat in order, so the result does not depend on the thread
//! count.

use glam::{DMat3, DQuat, DVec3};

use crate::scene::neighbors::bounds;

/// Largest voxel grid the filling builds (one byte and one `f32` each; ~1 s at 2²⁵ voxels).
pub const MAX_FILL_VOXELS: usize = 32 << 20;

/// Opacity-field value from which a voxel is wall: the rendered α at which a single splat's
/// silhouette lies (the mask's 1/2).
pub const WALL_OPACITY: f64 = 0.5;

/// A floor is laid only when the lowest wall layer is within this many voxels (two grid
/// cells) of a ground plane under it.
pub const FLOOR_REACH_VOXELS: f64 = 4.0;

/// Volume of an input particle more than a voxel outside the solid (a faint splat), in voxels
/// (`h³`): about a splat's share of a voxel, so that it weighs as much as its neighbours (a
/// grid node that only a far lighter particle reaches accelerates without bound).
pub const STRAY_VOLUME: f64 = 0.125;

/// Voxels the wall is thickened by to close gaps (up to `2·CLOSING` voxels wide).
const CLOSING: usize = 2;

/// Empty voxels between the box and the grid's edge on every side.
const PAD: usize = CLOSING + 1;

/// Voxel classes.
const EMPTY: u8 = 0;
/// Holds an input point (points only).
const SURFACE: u8 = 1;
/// The splats' opacity field reaches [`WALL_OPACITY`] at its centre.
const WALL: u8 = 2;
const THICKENED: u8 = 3;
const FLOOR: u8 = 4;
const OUTSIDE: u8 = 5;
/// Thickening (or a point's cover) undone on the outside.
const OUTER: u8 = 6;
/// Next to a point (under its h/2 cube), without holding one (points only).
const COVER: u8 = 8;
/// Outside, under the floor: the peels do not start there (the floor closes the object).
const GROUND: u8 = 9;

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

    /// The splat as a rasterizer draws it through a low-pass filter of `s` (m) on every axis:
    /// `Σ + s² I` at the same opacity (3DGS adds 0.3 px² to every projected covariance, i.e.
    /// `s = √0.3 · depth / focal` at the images it was fitted to; `s = 0` leaves it).
    pub fn filtered(mut self, s: f64) -> Self {
        self.sigma = (self.sigma * self.sigma + DVec3::splat(s * s)).powf(0.5);
        self
    }

    /// The inverse covariance `R S⁻² Rᵀ` (1/m²) and the reach evaluated, `3 max σ` (m).
    pub fn inverse_covariance(&self) -> (DMat3, f64) {
        let inv_s2 = DMat3::from_diagonal(DVec3::ONE / (self.sigma * self.sigma));
        (
            self.rotation * inv_s2 * self.rotation.transpose(),
            3.0 * self.sigma.max_element(),
        )
    }
}

/// [`InteriorFill::input_voxels`] of an input that shares no solid voxel.
pub const NO_VOXEL: usize = usize::MAX;

/// A ground plane under the object, perpendicular to an axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Floor {
    /// Which way is down ([`down_axis`]).
    pub down: (usize, bool),
    /// The plane's coordinate along that axis (m).
    pub level: f64,
}

/// The filler particles of a closed surface and the volumes of all particles.
#[derive(Debug, Clone, PartialEq)]
pub struct InteriorFill {
    /// Filler positions (m), one per solid voxel holding no input particle (for points: per
    /// enclosed voxel), in voxel order (x, then y, then z).
    pub points: Vec<DVec3>,
    /// Volume of each filler (m³): `h³`, or `h³/2` next to the outside.
    pub filler_volumes: Vec<f64>,
    /// Volume each input particle stands for (m³).
    pub input_volumes: Vec<f64>,
    /// The solid voxel whose volume each input shares ([`NO_VOXEL`] for an input outside the
    /// solid, and for every point of a cloud without splats): inputs of one voxel may ride one
    /// particle ([`crate::simulate::skin`]).
    pub input_voxels: Vec<usize>,
    /// Voxel edge `h` (m).
    pub voxel: f64,
    /// Wall voxels (splats' field or points) before thickening.
    pub wall_voxels: usize,
    /// Solid voxels that are not wall (enclosed, or closed gaps): 0 for a shell or a solid
    /// cloud.
    pub enclosed_voxels: usize,
}

impl InteriorFill {
    /// Volume of a voxel, a whole filler (m³).
    pub fn filler_volume(&self) -> f64 {
        self.voxel.powi(3)
    }

    /// Volume the input particles stand for (m³).
    pub fn input_volume(&self) -> f64 {
        self.input_volumes.iter().sum()
    }

    /// Volume of the filled solid (m³).
    pub fn solid_volume(&self) -> f64 {
        self.input_volume() + self.filler_volumes.iter().sum::<f64>()
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

/// Fills the solid of the splats `splats` (their centres among `x`), or, without splats, of
/// the surface sampled by the points `x` (m), on a lattice of edge `voxel` (m); `floor` is the
/// ground the object may rest on. `None` when the voxel grid would exceed `max_voxels` or `x`
/// is empty.
pub fn fill_interior(
    x: &[DVec3],
    splats: &[Splat],
    voxel: f64,
    floor: Option<Floor>,
    max_voxels: usize,
) -> Option<InteriorFill> {
    let (mut lo, mut hi) = bounds(x)?;
    for s in splats {
        let r = s.reach();
        lo = lo.min(s.centre - r);
        hi = hi.max(s.centre + r);
    }
    let mut grid = Voxels::around(lo, hi, voxel, max_voxels)?;
    let field = if splats.is_empty() {
        grid.mark_particles(x);
        None
    } else {
        Some(grid.mark_splats(splats))
    };
    let wall_voxels = grid.count(|c| matches!(c, SURFACE | WALL | COVER));
    grid.thicken();
    if let Some(f) = floor {
        grid.lay_floor(f);
    }
    grid.flood_outside();
    grid.peel_outside(field.is_none());
    grid.mark_ground();
    if let Some(f) = &field {
        grid.peel_to_the_splats(f);
    }
    grid.resolve_floor();
    let weight = grid.weights(field.is_none());
    let enclosed_voxels = (0..grid.class.len())
        .filter(|&n| weight[n] > 0.0 && !matches!(grid.class[n], SURFACE | WALL | COVER))
        .filter(|&n| field.as_ref().is_none_or(|f| !f.solid(n)))
        .count();
    let h3 = voxel.powi(3);
    let (points, filler_volumes, input_volumes, input_voxels) = match field {
        None => {
            // Fillers in the enclosed voxels; the points share their wall evenly.
            let wall: f64 = (0..grid.class.len())
                .filter(|&n| matches!(grid.class[n], SURFACE | COVER))
                .map(|n| weight[n])
                .sum();
            let (points, volumes) =
                grid.fillers(&weight, |n| !matches!(grid.class[n], SURFACE | COVER));
            (
                points,
                volumes,
                vec![wall * h3 / x.len() as f64; x.len()],
                vec![NO_VOXEL; x.len()],
            )
        }
        Some(_) => {
            // Each solid voxel's volume to the inputs centred in it or, for an input just
            // outside the solid, next to it; else to a filler.
            let mut cell: Vec<(usize, usize)> = x
                .iter()
                .enumerate()
                .map(|(i, p)| (grid.solid_voxel_of(*p, &weight).unwrap_or(usize::MAX), i))
                .collect();
            cell.sort_unstable();
            let mut input_volumes = vec![STRAY_VOLUME * h3; x.len()];
            let mut input_voxels = vec![NO_VOXEL; x.len()];
            let mut occupied = vec![false; grid.class.len()];
            for run in cell.chunk_by(|a, b| a.0 == b.0) {
                let n = run[0].0;
                if n == usize::MAX {
                    continue;
                }
                occupied[n] = true;
                let share = weight[n] * h3 / run.len() as f64;
                run.iter().for_each(|&(_, i)| {
                    input_volumes[i] = share;
                    input_voxels[i] = n;
                });
            }
            let (points, volumes) = grid.fillers(&weight, |n| !occupied[n]);
            (points, volumes, input_volumes, input_voxels)
        }
    };
    Some(InteriorFill {
        points,
        filler_volumes,
        input_volumes,
        input_voxels,
        voxel,
        wall_voxels,
        enclosed_voxels,
    })
}

impl Splat {
    /// How far from its centre (m) the splat can matter: where `α exp(−½ m)` falls below a
    /// tenth of [`WALL_OPACITY`] along its largest axis, at most `3 max σ`.
    fn reach(&self) -> f64 {
        let m = 2.0 * (self.opacity / (0.1 * WALL_OPACITY)).ln();
        m.clamp(0.0, 9.0).sqrt() * self.sigma.max_element()
    }
}

/// The splats' opacity field on a voxel grid.
struct SplatField {
    /// At each voxel's centre.
    centre: Vec<f32>,
    /// On each voxel's segment to its +x, +y, +z neighbour: the sum of the splats' maxima on
    /// it (at least the field's maximum there).
    segment: [Vec<f32>; 3],
}

impl SplatField {
    /// Whether voxel `n`'s centre lies inside the rendered surface.
    fn solid(&self, n: usize) -> bool {
        f64::from(self.centre[n]) >= WALL_OPACITY
    }

    /// Whether the surface may cross voxel `n`'s segment along axis `a`.
    fn crossed(&self, a: usize, n: usize) -> bool {
        f64::from(self.segment[a][n]) >= WALL_OPACITY
    }
}

/// A voxel grid over a box plus [`PAD`] voxels, one class per voxel.
struct Voxels {
    dims: [usize; 3],
    /// Corner of voxel (0, 0, 0) (m).
    origin: DVec3,
    /// Edge (m).
    h: f64,
    class: Vec<u8>,
    /// The floor's axis, direction (towards the negative side) and layer, once laid.
    floor: Option<(usize, bool, usize)>,
}

impl Voxels {
    /// All empty over `[lo, hi]` (m), or `None` over `max` voxels.
    fn around(lo: DVec3, hi: DVec3, h: f64, max: usize) -> Option<Self> {
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
            floor: None,
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

    /// The solid voxel (`weight` > 0) of `q` (m), a point of the grid's box, or else the
    /// solid 26-neighbour of its voxel whose centre is nearest (the first of equals).
    fn solid_voxel_of(&self, q: DVec3, weight: &[f64]) -> Option<usize> {
        let c = self.coords_of(q);
        let n = self.at(c);
        if weight[n] > 0.0 {
            return Some(n);
        }
        neighbours26(c)
            .map(|m| self.at(m))
            .filter(|&m| weight[m] > 0.0)
            .min_by(|&a, &b| {
                (self.centre(a) - q)
                    .length_squared()
                    .total_cmp(&(self.centre(b) - q).length_squared())
            })
    }

    fn count(&self, pred: impl Fn(u8) -> bool) -> usize {
        self.class.iter().filter(|&&c| pred(c)).count()
    }

    /// The voxels (not on the grid's faces) of class `of` with a 26-neighbour `next_to`.
    fn touching(&self, of: impl Fn(u8) -> bool, next_to: impl Fn(u8) -> bool) -> Vec<usize> {
        (0..self.class.len())
            .filter(|&n| of(self.class[n]))
            .filter(|&n| self.next_to(n, &next_to))
            .collect()
    }

    /// Whether voxel `n` (not on the grid's faces) has a 26-neighbour of a class `pred` takes.
    fn next_to(&self, n: usize, pred: impl Fn(u8) -> bool) -> bool {
        let c = self.coord(n);
        (0..3).all(|a| c[a] > 0 && c[a] + 1 < self.dims[a])
            && neighbours26(c).any(|m| pred(self.class[self.at(m)]))
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

    /// The splats' opacity field at the voxel centres, and on each voxel's segments to its
    /// neighbours along +x, +y and +z the sum of every splat's largest value on it (summed in
    /// splat order, so the same whatever the thread count). Wall: a voxel whose centre reaches
    /// [`WALL_OPACITY`], and both ends of a segment where it does (a splat layer thinner than
    /// a voxel crosses between their centres), so a 6-connected flood cannot pass a layer.
    fn mark_splats(&mut self, splats: &[Splat]) -> SplatField {
        let len = self.class.len();
        let mut centre = vec![0.0f32; len];
        let mut segment = [vec![0.0f32; len], vec![0.0f32; len], vec![0.0f32; len]];
        let h = self.h;
        for s in splats {
            let (inv_cov, reach) = s.inverse_covariance();
            // One voxel more below, for the segments that end in the splat's box.
            let lo = self.coords_of(s.centre - reach - h);
            let hi = self.coords_of(s.centre + reach);
            let axes = [inv_cov.x_axis * h, inv_cov.y_axis * h, inv_cov.z_axis * h];
            for i in lo[0]..=hi[0] {
                for j in lo[1]..=hi[1] {
                    for k in lo[2]..=hi[2] {
                        let n = self.at([i, j, k]);
                        let d = self.centre(n) - s.centre;
                        let m = d.dot(inv_cov * d);
                        if m < 9.0 {
                            centre[n] += (s.opacity * (-0.5 * m).exp()) as f32;
                        }
                        // m(t) = m + 2 t b + t² q on the segment d + t h e_a, t in [0, 1].
                        for (a, au) in axes.iter().enumerate() {
                            let (b, q) = (d.dot(*au), h * au[a]);
                            let t = (-b / q).clamp(0.0, 1.0);
                            let m_seg = m + t * (2.0 * b + t * q);
                            if m_seg < 9.0 {
                                segment[a][n] += (s.opacity * (-0.5 * m_seg).exp()) as f32;
                            }
                        }
                    }
                }
            }
        }
        let field = SplatField { centre, segment };
        let strides = self.strides();
        for n in 0..len {
            if field.solid(n) {
                self.class[n] = WALL;
            }
            for (a, &stride) in strides.iter().enumerate() {
                if field.crossed(a, n) && self.coord(n)[a] + 1 < self.dims[a] {
                    self.class[n] = WALL;
                    self.class[n + stride] = WALL;
                }
            }
        }
        field
    }

    /// Index steps along x, y and z.
    fn strides(&self) -> [usize; 3] {
        [self.dims[1] * self.dims[2], self.dims[2], 1]
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

    /// The floor: the wall's lowest layer along `down`, solid across the box, when that layer
    /// lies within [`FLOOR_REACH_VOXELS`] of the ground.
    fn lay_floor(&mut self, floor: Floor) {
        let (axis, negative) = floor.down;
        let layers = (0..self.class.len())
            .filter(|&n| matches!(self.class[n], SURFACE | WALL | COVER))
            .map(|n| self.coord(n)[axis]);
        let Some(layer) = (if negative { layers.min() } else { layers.max() }) else {
            return;
        };
        // The layer's outer face, and how far the ground lies beyond it.
        let face = self.origin[axis] + self.h * (layer + usize::from(!negative)) as f64;
        let gap = if negative {
            face - floor.level
        } else {
            floor.level - face
        };
        let near = gap.abs() <= FLOOR_REACH_VOXELS * self.h;
        if !near {
            return;
        }
        for n in 0..self.class.len() {
            if self.coord(n)[axis] == layer && self.class[n] == EMPTY {
                self.class[n] = FLOOR;
            }
        }
        self.floor = Some((axis, negative, layer));
    }

    /// Whether voxel `n` lies beyond the floor (under it).
    fn under_floor(&self, n: usize) -> bool {
        self.floor.is_some_and(|(axis, negative, layer)| {
            let c = self.coord(n)[axis];
            if negative { c < layer } else { c > layer }
        })
    }

    /// The voxels under the floor are ground: outside, but the peels do not start there.
    fn mark_ground(&mut self) {
        for n in 0..self.class.len() {
            if matches!(self.class[n], OUTSIDE | THICKENED | EMPTY) && self.under_floor(n) {
                self.class[n] = GROUND;
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

    /// Undoes the thickening on the outside and, for points, the cover's outer layer (it only
    /// closes a lattice's gaps).
    fn peel_outside(&mut self, points: bool) {
        let outside_or_outer = |c: u8| c == OUTSIDE || c == OUTER;
        for _ in 0..CLOSING {
            for n in self.touching(|c| c == THICKENED, outside_or_outer) {
                self.class[n] = OUTER;
            }
        }
        if points {
            for n in self.touching(
                |c| c == COVER,
                |c| outside_or_outer(c) || c == FLOOR || c == GROUND,
            ) {
                self.class[n] = OUTER;
            }
        }
    }

    /// Moves the outside up to the splats' surface: a voxel whose centre lies outside it (the
    /// field misses it) joins the outside when no splat layer crosses between it and an
    /// outside 6-neighbour, for [`CLOSING`] rounds (the wall's thickness; a closed gap keeps
    /// its core). The floor stays.
    fn peel_to_the_splats(&mut self, field: &SplatField) {
        let outside = |c: u8| c == OUTSIDE || c == OUTER;
        let strides = self.strides();
        for _ in 0..CLOSING {
            let reached: Vec<usize> = (0..self.class.len())
                .filter(|&n| matches!(self.class[n], WALL | THICKENED))
                .filter(|&n| !field.solid(n))
                .filter(|&n| {
                    let c = self.coord(n);
                    (0..3).any(|a| {
                        let below = c[a] > 0
                            && outside(self.class[n - strides[a]])
                            && !field.crossed(a, n - strides[a]);
                        let above = c[a] + 1 < self.dims[a]
                            && outside(self.class[n + strides[a]])
                            && !field.crossed(a, n);
                        below || above
                    })
                })
                .collect();
            reached.iter().for_each(|&n| self.class[n] = OUTER);
        }
    }

    /// The floor stays under the object (below a voxel of the solid) and is outside elsewhere.
    fn resolve_floor(&mut self) {
        let Some((axis, negative, _)) = self.floor else {
            return;
        };
        let step = self.strides()[axis];
        for n in 0..self.class.len() {
            if self.class[n] != FLOOR {
                continue;
            }
            let c = self.coord(n)[axis];
            let up = if negative {
                (c + 1 < self.dims[axis]).then(|| n + step)
            } else {
                (c > 0).then(|| n - step)
            };
            if up.is_none_or(|m| matches!(self.class[m], OUTSIDE | OUTER | FLOOR)) {
                self.class[n] = OUTER;
            }
        }
    }

    /// The share of each voxel in the solid: 0 outside, 1 inside; ½ for the points' own wall
    /// next to the outside (the surface passes through it). The splats' solid was peeled to
    /// their surface, so its voxels count on their centres.
    fn weights(&self, points: bool) -> Vec<f64> {
        let outside = |c: u8| matches!(c, OUTSIDE | OUTER | GROUND);
        (0..self.class.len())
            .map(|n| match self.class[n] {
                OUTSIDE | OUTER | GROUND => 0.0,
                SURFACE | COVER if points && self.next_to(n, outside) => 0.5,
                _ => 1.0,
            })
            .collect()
    }

    /// One filler at the centre of every solid voxel `free` takes, with the voxel's volume.
    fn fillers(&self, weight: &[f64], free: impl Fn(usize) -> bool) -> (Vec<DVec3>, Vec<f64>) {
        let h3 = self.h.powi(3);
        (0..self.class.len())
            .filter(|&n| weight[n] > 0.0 && free(n))
            .map(|n| (self.centre(n), weight[n] * h3))
            .unzip()
    }
}

/// The 26 neighbours of a voxel not on the grid's faces.
fn neighbours26([i, j, k]: [usize; 3]) -> impl Iterator<Item = [usize; 3]> {
    (0..27)
        .filter(|&n| n != 13)
        .map(move |n| [i + n / 9 - 1, j + (n / 3) % 3 - 1, k + n % 3 - 1])
}

#[cfg(test)]
mod scenes;

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Points on a sphere of radius `r` (m) about `c`, about `spacing` apart (Fibonacci lattice).
    fn sphere_surface(c: DVec3, r: f64, spacing: f64) -> Vec<DVec3> {
        super::scenes::sphere_normals(r, spacing)
            .into_iter()
            .map(|normal| c + r * normal)
            .collect()
    }

    const DOWN: DVec3 = DVec3::new(0.0, -9.8, 0.0);

    fn down() -> Option<(usize, bool)> {
        down_axis(DOWN)
    }

    /// A ground plane at height `y` (m) under gravity along −y.
    fn ground(y: f64) -> Option<Floor> {
        Some(Floor {
            down: down().unwrap(),
            level: y,
        })
    }

    fn ball(r: f64) -> f64 {
        4.0 / 3.0 * PI * r.powi(3)
    }

    #[test]
    fn a_closed_sphere_is_filled_to_its_volume() {
        let (c, r, h) = (DVec3::new(0.3, 0.5, -0.2), 0.1, 0.01);
        let x = sphere_surface(c, r, 0.003);
        // In the air, resting on the ground, and with the ground too far below for a floor.
        for floor in [None, ground(c.y - r), ground(c.y - r - 0.1)] {
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
        let fill = fill_interior(&x, &[], h, ground(-r), MAX_FILL_VOXELS).unwrap();
        let v = fill.solid_volume();
        assert!(
            (v / ball(r) - 1.0).abs() < 0.05,
            "volume {v} vs {}",
            ball(r)
        );
        assert!(
            fill.input_volume() > 0.4 * ball(r),
            "{}",
            fill.input_volume()
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
        // Resting on the ground (the cap's 2 cm are within the floor's reach) ...
        let fill = fill_interior(&bottomless, &[], 0.01, ground(-r), MAX_FILL_VOXELS).unwrap();
        let v = fill.solid_volume();
        assert!((v / ball(r) - 1.0).abs() < 0.1, "{v} vs {}", ball(r));
        // ... but not without gravity, with gravity along x, or in the air (the ground 10 cm
        // below): the flood gets in (a layer one voxel thin under the shell remains, where the
        // closing rounded off the staircase).
        let sideways = Some(Floor {
            down: down_axis(DVec3::X).unwrap(),
            level: r,
        });
        for floor in [None, sideways, ground(-r - 0.1)] {
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
        let hollow = fill_interior(&bowl, &[], 0.01, ground(-r), MAX_FILL_VOXELS).unwrap();
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
        let lowest = x.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
        for floor in [None, ground(lowest)] {
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
        // A half turn about z keeps the axes: Σ⁻¹ = diag(1/σ²); the filter adds s² to every σ².
        for f in [0.0, 0.02] {
            let (inv_cov, reach) = s.filtered(f).inverse_covariance();
            let sigma2 = DVec3::new(1e-4, 4e-4, 9e-4) + f * f;
            assert!((reach - 3.0 * sigma2.z.sqrt()).abs() < 1e-12);
            let want = DVec3::ONE / sigma2;
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
        let fill = fill_interior(&x, &[], 0.005, ground(0.0), MAX_FILL_VOXELS).unwrap();
        assert!(fill.points.is_empty());
        assert_eq!(fill.wall_voxels, 1000);
        // Inner voxels whole, the outer layer half (it straddles the surface).
        let v = fill.solid_volume() / 0.005f64.powi(3);
        assert!((v - (512.0 + 0.5 * 488.0)).abs() < 1e-6, "{v}");
        // A lattice as a PLY stores it (f32, offset): its points straddle the voxel boundaries,
        // leaving whole planes of voxels without a point, yet nothing is filled.
        let f32_lattice: Vec<DVec3> = x
            .iter()
            .map(|p| (*p * 2.0 + DVec3::new(0.0, 0.5, 0.0)).as_vec3().as_dvec3())
            .collect();
        let fill = fill_interior(&f32_lattice, &[], 0.01, ground(0.0), MAX_FILL_VOXELS).unwrap();
        assert!(fill.wall_voxels < 1000, "{}", fill.wall_voxels);
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
