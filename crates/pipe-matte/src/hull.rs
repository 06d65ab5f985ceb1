//! Space carving: the object's visual hull from its masks in calibrated views, and the hull's
//! reprojection into a view.
//!
//! A voxel is kept when its centre projects into the object mask of every view, up to
//! `max_misses` views (robustness to matte errors). A voxel outside a view's frustum counts as a
//! miss: the captures this is for keep the whole object in every view.
//! Carving runs twice: first in the box spanned by the camera centres and their mirror images
//! through the point they look at, then in the bounding box of the first result grown by two
//! coarse voxels, so the final voxels are fine whatever the scene's scale.

use glam::{DVec3, UVec3};
use rayon::prelude::*;

use crate::camera::Pinhole;

/// One view: its camera and binary mask (`width·height` bytes, ≥ 128 = object).
#[derive(Debug, Clone, Copy)]
pub struct MaskedView<'a> {
    /// The camera.
    pub camera: Pinhole,
    /// Row-major mask.
    pub mask: &'a [u8],
}

/// Carving result: the kept voxels of the final box.
#[derive(Debug, Clone, PartialEq)]
pub struct Hull {
    /// Voxel centres, metres (z-slab, then row, then column order).
    pub centres: Vec<DVec3>,
    /// Voxel edge, metres.
    pub voxel: f64,
    /// Lower corner of the box carved in the final pass, metres.
    pub box_min: DVec3,
    /// Upper corner, metres.
    pub box_max: DVec3,
    /// Voxels along x, y, z of the final box.
    pub dims: UVec3,
    /// Whether each voxel of the final box is kept (x fastest, then y, then z).
    pub occupied: Vec<bool>,
}

impl Hull {
    /// The hull of the `occupied` voxels (x fastest, then y, then z) of the box at `box_min`
    /// with `dims` voxels of edge `voxel`.
    pub fn from_occupancy(box_min: DVec3, voxel: f64, dims: UVec3, occupied: Vec<bool>) -> Self {
        let (nx, ny) = (dims.x as usize, dims.y as usize);
        let centres = occupied
            .iter()
            .enumerate()
            .filter(|(_, k)| **k)
            .map(|(n, _)| {
                let (i, j, k) = (n % nx, (n / nx) % ny, n / (nx * ny));
                box_min + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * voxel
            })
            .collect();
        Hull {
            centres,
            voxel,
            box_min,
            box_max: box_min + dims.as_dvec3() * voxel,
            dims,
            occupied,
        }
    }

    /// Volume of the kept voxels, m³.
    pub fn volume(&self) -> f64 {
        self.centres.len() as f64 * self.voxel.powi(3)
    }

    /// Axis-aligned bounds of the kept voxels (grown by half a voxel).
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        let first = *self.centres.first()?;
        let (lo, hi) = self
            .centres
            .iter()
            .fold((first, first), |(lo, hi), c| (lo.min(*c), hi.max(*c)));
        let h = DVec3::splat(self.voxel / 2.0);
        Some((lo - h, hi + h))
    }

    /// Whether the voxel holding world point `p` is kept (`false` outside the box).
    pub fn contains(&self, p: DVec3) -> bool {
        self.index(p).is_some_and(|i| self.occupied[i])
    }

    /// Index of the voxel holding `p` (x fastest), if inside the box.
    fn index(&self, p: DVec3) -> Option<usize> {
        let f = (p - self.box_min) / self.voxel;
        if f.min_element() < 0.0 {
            return None;
        }
        let i = f.as_uvec3();
        if i.x >= self.dims.x || i.y >= self.dims.y || i.z >= self.dims.z {
            return None;
        }
        let (nx, ny) = (self.dims.x as usize, self.dims.y as usize);
        Some((i.z as usize * ny + i.y as usize) * nx + i.x as usize)
    }

    /// Where the ray through image point `(u, v)` of `camera` first enters a kept voxel
    /// (sampled every half voxel), if it does.
    pub fn front(&self, camera: &Pinhole, (u, v): (f64, f64)) -> Option<DVec3> {
        let o = camera.centre_world;
        let d = camera.ray(u, v);
        let (t0, t1) = slab(o, d, self.box_min, self.box_max)?;
        let step = self.voxel / 2.0;
        let mut t = t0 + step / 2.0;
        while t < t1 {
            let p = o + d * t;
            if self.contains(p) {
                return Some(p);
            }
            t += step;
        }
        None
    }

    /// Whether the segment from `from` to `to` meets a kept voxel short of its last `margin`
    /// metres (sampled every half voxel inside the box).
    pub fn blocks(&self, from: DVec3, to: DVec3, margin: f64) -> bool {
        let len = (to - from).length();
        if len <= margin {
            return false;
        }
        let d = (to - from) / len;
        let Some((t0, t1)) = slab(from, d, self.box_min, self.box_max) else {
            return false;
        };
        let end = t1.min(len - margin);
        let step = self.voxel / 2.0;
        // The same samples as a march from `from`: t = step, 2 step, ...
        let mut t = ((t0 / step).floor().max(1.0)) * step;
        while t < end {
            if self.contains(from + d * t) {
                return true;
            }
            t += step;
        }
        false
    }

    /// The hull's silhouette in `camera`: per pixel (row-major), whether it lies in the
    /// footprint of a kept voxel: the pixel holding the voxel's projected centre, and every
    /// pixel whose centre is within half the voxel's projected width of it
    /// (`½·voxel·f/z` along each image axis). The footprints of neighbouring voxels touch, so
    /// the silhouette has no gaps whatever the image's resolution against the voxels' (with
    /// centres alone, a 400² image of a 64-voxel hull is a grid of dots).
    pub fn reproject(&self, camera: &Pinhole) -> Vec<bool> {
        let (w, h) = (camera.width as i64, camera.height as i64);
        let mut out = vec![false; (w * h) as usize];
        for c in &self.centres {
            let Some((u, v, z)) = camera.project(*c) else {
                continue;
            };
            let (ru, rv) = (
                0.5 * self.voxel * camera.fx / z,
                0.5 * self.voxel * camera.fy / z,
            );
            // Pixels i with |i + 0.5 − u| ≤ ru, and the one holding u.
            let span = |x: f64, r: f64, n: i64| {
                let lo = ((x - r - 0.5).ceil() as i64).min(x.floor() as i64).max(0);
                let hi = ((x + r - 0.5).floor() as i64)
                    .max(x.floor() as i64)
                    .min(n - 1);
                lo..=hi
            };
            for j in span(v, rv, h) {
                for i in span(u, ru, w) {
                    out[(j * w + i) as usize] = true;
                }
            }
        }
        out
    }
}

/// Entry and exit ray parameters of the box `[lo, hi]` (t ≥ 0), if the ray meets it.
fn slab(o: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let inv = d.recip();
    let a = (lo - o) * inv;
    let b = (hi - o) * inv;
    let t0 = a.min(b).max_element().max(0.0);
    let t1 = a.max(b).min_element();
    (t0 < t1 && t0.is_finite() && t1.is_finite()).then_some((t0, t1))
}

/// Bit `i` set iff view `i` does not see `p` inside its object mask (outside its frustum, or
/// past the end of a mask shorter than its camera's image, counts as not seen).
fn missed_by(p: DVec3, views: &[MaskedView<'_>]) -> u64 {
    let mut bits = 0u64;
    for (i, v) in views.iter().enumerate() {
        let inside = v
            .camera
            .pixel(p)
            .and_then(|(u, w)| v.mask.get((w * v.camera.width + u) as usize))
            .is_some_and(|m| *m >= 128);
        if !inside {
            bits |= 1 << i;
        }
    }
    bits
}

/// Which views miss each voxel of a box: carving with any rule, from one pass over the views.
#[derive(Debug, Clone, PartialEq)]
pub struct Votes {
    /// Voxel edge, metres.
    pub voxel: f64,
    /// Lower corner of the box, metres.
    pub box_min: DVec3,
    /// Voxels along x, y, z.
    pub dims: UVec3,
    /// Per voxel (x fastest, then y, then z), bit `i` set iff view `i` misses it.
    pub missed_by: Vec<u64>,
    /// Number of views.
    pub views: usize,
}

impl Votes {
    fn in_box(lo: DVec3, hi: DVec3, resolution: usize, views: &[MaskedView<'_>]) -> Self {
        let extent = hi - lo;
        let voxel = extent.max_element() / resolution as f64;
        let dims = (extent / voxel).ceil().as_uvec3().max(UVec3::ONE);
        let (nx, ny, nz) = (dims.x as usize, dims.y as usize, dims.z as usize);
        // Fixed chunks (one z-slab each) in a fixed order: deterministic whatever the thread
        // count.
        let missed_by: Vec<u64> = (0..nz)
            .into_par_iter()
            .flat_map_iter(|k| {
                let mut out = Vec::with_capacity(nx * ny);
                for j in 0..ny {
                    for i in 0..nx {
                        let c = lo + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * voxel;
                        out.push(missed_by(c, views));
                    }
                }
                out.into_iter()
            })
            .collect();
        Self {
            voxel,
            box_min: lo,
            dims,
            missed_by,
            views: views.len(),
        }
    }

    /// The hull of the voxels for which `keep(missed_by)` holds (never any with fewer than
    /// two views).
    pub fn hull(&self, keep: impl Fn(u64) -> bool) -> Hull {
        let occupied: Vec<bool> = self
            .missed_by
            .iter()
            .map(|m| self.views >= 2 && keep(*m))
            .collect();
        Hull::from_occupancy(self.box_min, self.voxel, self.dims, occupied)
    }

    /// The hull of voxels missed by at most `max_misses` views.
    pub fn within(&self, max_misses: usize) -> Hull {
        self.hull(|m| m.count_ones() as usize <= max_misses)
    }

    /// The hull of voxels missed by at most `max_misses` views other than `view` (the hull of
    /// all the other views).
    pub fn without(&self, view: usize, max_misses: usize) -> Hull {
        let others = !(1u64.checked_shl(view as u32).unwrap_or(0));
        self.hull(|m| (m & others).count_ones() as usize <= max_misses)
    }
}

/// The box the first pass carves: the camera centres and their mirror images through the point
/// nearest to all optical axes (least squares: `Σ (I − d dᵀ) x = Σ (I − d dᵀ) c`), so it holds
/// what the cameras look at even when they all stand on one side of it (a dome over the
/// ground). Parallel axes (no such point) fall back to the centres' box.
fn coarse_box(views: &[MaskedView<'_>]) -> (DVec3, DVec3) {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    let mut a = glam::DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for v in views {
        let c = v.camera.centre_world;
        lo = lo.min(c);
        hi = hi.max(c);
        let d = v.camera.world_from_camera_rot.z_axis.normalize();
        let m = glam::DMat3::IDENTITY - glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * c;
    }
    if a.determinant().abs() > 1e-6 * (views.len() as f64).powi(3) {
        let target = a.inverse() * b;
        for v in views {
            let mirror = 2.0 * target - v.camera.centre_world;
            lo = lo.min(mirror);
            hi = hi.max(mirror);
        }
    }
    (lo, hi)
}

/// The most views [`carve`] and [`votes`] take (one bit each per voxel).
pub const MAX_VIEWS: usize = 64;

/// Carve the visual hull at `resolution` voxels along the longest box edge.
///
/// Views past the [`MAX_VIEWS`]th are ignored.
pub fn carve(views: &[MaskedView<'_>], resolution: usize, max_misses: usize) -> Hull {
    votes(views, resolution, max_misses).within(max_misses)
}

/// The votes of every view on the voxels of the box the hull with `max_misses` fits in (see
/// the module doc), at `resolution` voxels along its longest edge.
///
/// Views past the [`MAX_VIEWS`]th are ignored.
pub fn votes(views: &[MaskedView<'_>], resolution: usize, max_misses: usize) -> Votes {
    let views = &views[..views.len().min(MAX_VIEWS)];
    let resolution = resolution.max(4);
    let (lo, hi) = coarse_box(views);
    let pad = (hi - lo).max_element().max(1e-3) * 0.1;
    let coarse = Votes::in_box(lo - pad, hi + pad, resolution, views).within(max_misses);
    match coarse.bounds() {
        None => Votes::in_box(lo - pad, hi + pad, resolution, views),
        Some((clo, chi)) => {
            let grow = DVec3::splat(2.0 * coarse.voxel);
            Votes::in_box(clo - grow, chi + grow, resolution, views)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ball carved at 24 voxels across, reprojected into cameras of 48² to 768²: the
    /// silhouette is solid and close to the ball's own whatever the resolution.
    #[test]
    fn a_coarse_hull_reprojects_without_gaps_at_any_image_resolution() {
        let (n, r) = (24u32, 0.2);
        let voxel = 2.0 * r / f64::from(n);
        let lo = DVec3::splat(-r);
        let occupied: Vec<bool> = (0..n * n * n)
            .map(|k| {
                let (i, j, l) = (k % n, (k / n) % n, k / (n * n));
                let c = lo + (DVec3::new(f64::from(i), f64::from(j), f64::from(l)) + 0.5) * voxel;
                c.length() <= r
            })
            .collect();
        let hull = Hull::from_occupancy(lo, voxel, UVec3::splat(n), occupied);
        for size in [48u32, 96, 192, 384, 768] {
            // Looking down −z from 1 m; the ball covers about half the image.
            let f = f64::from(size) * 1.2;
            let cam = Pinhole {
                world_from_camera_rot: glam::DMat3::from_cols(DVec3::X, -DVec3::Y, -DVec3::Z),
                centre_world: DVec3::new(0.0, 0.0, 1.0),
                fx: f,
                fy: f,
                cx: f64::from(size) / 2.0,
                cy: f64::from(size) / 2.0,
                width: size,
                height: size,
            };
            let got = hull.reproject(&cam);
            // The ball's silhouette: pixels whose ray passes within r of the centre.
            let truth: Vec<bool> = (0..size * size)
                .map(|k| {
                    let d = cam.ray(f64::from(k % size) + 0.5, f64::from(k / size) + 0.5);
                    (cam.centre_world - d * cam.centre_world.dot(d)).length() <= r
                })
                .collect();
            let both = got.iter().zip(&truth).filter(|(a, b)| **a && **b).count();
            let either = got.iter().zip(&truth).filter(|(a, b)| **a || **b).count();
            let iou = both as f64 / either as f64;
            assert!(iou > 0.9, "{size}²: IoU {iou}");
            // No hole inside the ball's silhouette (apparent radius f·r/√(d² − r²) at d = 1 m)
            // shrunk by two voxels.
            let radius_px = f * r / (1.0 - r * r).sqrt() - 2.0 * voxel * f;
            let centre = f64::from(size) / 2.0;
            let holes = (0..size * size)
                .filter(|&k| {
                    let (x, y) = (f64::from(k % size) + 0.5, f64::from(k / size) + 0.5);
                    ((x - centre).powi(2) + (y - centre).powi(2)).sqrt() < radius_px
                        && !got[k as usize]
                })
                .count();
            assert_eq!(holes, 0, "{size}²: {holes} holes inside the silhouette");
        }
    }

    #[test]
    fn a_segment_through_a_kept_voxel_is_blocked_short_of_its_end_only() {
        // A 3×3×3 box of 0.1 m voxels with only the centre voxel kept.
        let mut occupied = vec![false; 27];
        occupied[13] = true;
        let hull = Hull::from_occupancy(DVec3::ZERO, 0.1, UVec3::splat(3), occupied);
        let from = DVec3::new(-1.0, 0.15, 0.15);
        assert!(hull.blocks(from, DVec3::new(1.0, 0.15, 0.15), 0.0));
        // Ending inside the kept voxel: blocked without a margin, not with one.
        let to = DVec3::new(0.15, 0.15, 0.15);
        assert!(hull.blocks(from, to, 0.0));
        assert!(!hull.blocks(from, to, 0.1));
        // Passing beside it.
        assert!(!hull.blocks(from, DVec3::new(1.0, 0.25, 0.15), 0.0));
        // Starting past it.
        assert!(!hull.blocks(
            DVec3::new(0.25, 0.15, 0.15),
            DVec3::new(1.0, 0.15, 0.15),
            0.0
        ));
    }
}
