//! Space carving: the object's visual hull from its masks in calibrated views.
//!
//! A voxel is kept when its centre projects into the object mask of every view, up to
//! `max_misses` views (robustness to matte errors). A voxel outside a view's frustum counts as a
//! miss: the captures this is for keep the whole object in every view.
//! Carving runs twice: first in the box spanned by the camera centres, then in the bounding box
//! of the first result grown by two coarse voxels, so the final voxels are fine whatever the
//! scene's scale.

use glam::DVec3;
use rayon::prelude::*;

use super::camera::Camera;

/// One view: its camera and binary mask (`width·height` bytes, ≥ 128 = object).
#[derive(Debug, Clone, Copy)]
pub struct MaskedView<'a> {
    /// The camera.
    pub camera: &'a Camera,
    /// Row-major mask.
    pub mask: &'a [u8],
}

/// Carving result: the centres of kept voxels and the voxel edge length.
#[derive(Debug, Clone, PartialEq)]
pub struct Hull {
    /// Voxel centres, metres.
    pub centres: Vec<DVec3>,
    /// Voxel edge, metres.
    pub voxel: f64,
    /// Lower corner of the box carved in the final pass, metres.
    pub box_min: DVec3,
    /// Upper corner, metres.
    pub box_max: DVec3,
}

impl Hull {
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
}

fn keep(p: DVec3, views: &[MaskedView<'_>], max_misses: usize) -> bool {
    let mut misses = 0usize;
    for v in views {
        let inside = v
            .camera
            .pixel(p)
            .is_some_and(|(u, w)| v.mask[(w * v.camera.width + u) as usize] >= 128);
        if !inside {
            misses += 1;
            if misses > max_misses {
                return false;
            }
        }
    }
    views.len() >= 2
}

fn carve_box(
    lo: DVec3,
    hi: DVec3,
    resolution: usize,
    views: &[MaskedView<'_>],
    max_misses: usize,
) -> Hull {
    let extent = hi - lo;
    let voxel = extent.max_element() / resolution as f64;
    let dims = (extent / voxel).ceil().as_uvec3().max(glam::UVec3::ONE);
    let (nx, ny, nz) = (dims.x as usize, dims.y as usize, dims.z as usize);
    // Fixed chunks (one z-slab each) in a fixed order: deterministic whatever the thread count.
    let centres: Vec<DVec3> = (0..nz)
        .into_par_iter()
        .flat_map_iter(|k| {
            let mut out = Vec::new();
            for j in 0..ny {
                for i in 0..nx {
                    let c = lo + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * voxel;
                    if keep(c, views, max_misses) {
                        out.push(c);
                    }
                }
            }
            out.into_iter()
        })
        .collect();
    Hull {
        centres,
        voxel,
        box_min: lo,
        box_max: lo + dims.as_dvec3() * voxel,
    }
}

/// Carve the visual hull at `resolution` voxels along the longest box edge.
pub fn carve(views: &[MaskedView<'_>], resolution: usize, max_misses: usize) -> Hull {
    let resolution = resolution.max(4);
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for v in views {
        lo = lo.min(v.camera.centre_world);
        hi = hi.max(v.camera.centre_world);
    }
    let pad = (hi - lo).max_element().max(1e-3) * 0.1;
    let coarse = carve_box(lo - pad, hi + pad, resolution, views, max_misses);
    match coarse.bounds() {
        None => coarse,
        Some((clo, chi)) => {
            let grow = DVec3::splat(2.0 * coarse.voxel);
            carve_box(clo - grow, chi + grow, resolution, views, max_misses)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    /// A camera at `centre` looking at the origin, OpenCV axes, 64×64, 60° field of view.
    fn look_at(centre: DVec3) -> Camera {
        let z = (-centre).normalize();
        let x = DVec3::Y.cross(z).normalize();
        let y = z.cross(x);
        Camera {
            world_from_camera_rot: DMat3::from_cols(x, y, z),
            centre_world: centre,
            fx: 55.4,
            fy: 55.4,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    /// Mask of a sphere of radius r at the origin (exact silhouette test per pixel centre).
    fn sphere_mask(cam: &Camera, r: f64) -> Vec<u8> {
        let mut m = vec![0u8; 64 * 64];
        for j in 0..64 {
            for i in 0..64 {
                let d_cam = DVec3::new(
                    (i as f64 + 0.5 - cam.cx) / cam.fx,
                    (j as f64 + 0.5 - cam.cy) / cam.fy,
                    1.0,
                );
                let d = (cam.world_from_camera_rot * d_cam).normalize();
                let o = cam.centre_world;
                let t = -o.dot(d);
                if (o + d * t).length() <= r {
                    m[j * 64 + i] = 255;
                }
            }
        }
        m
    }

    #[test]
    fn sphere_hull_has_about_the_sphere_volume_and_contains_it() {
        let cams: Vec<Camera> = (0..8)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 8.0;
                look_at(DVec3::new(
                    2.0 * a.cos(),
                    if k % 2 == 0 { 0.8 } else { -0.6 },
                    2.0 * a.sin(),
                ))
            })
            .collect();
        let masks: Vec<Vec<u8>> = cams.iter().map(|c| sphere_mask(c, 0.3)).collect();
        let views: Vec<MaskedView> = cams
            .iter()
            .zip(&masks)
            .map(|(c, m)| MaskedView { camera: c, mask: m })
            .collect();
        let hull = carve(&views, 48, 0);
        let sphere = 4.0 / 3.0 * std::f64::consts::PI * 0.3f64.powi(3);
        // A hull of 8 views over-estimates the sphere, but not by much.
        assert!(
            hull.volume() > 0.9 * sphere && hull.volume() < 1.6 * sphere,
            "{} vs {sphere}",
            hull.volume()
        );
        let (lo, hi) = hull.bounds().unwrap();
        assert!(
            lo.max_element() < -0.25 && hi.min_element() > 0.25,
            "{lo} {hi}"
        );
        assert!(
            lo.min_element() > -0.45 && hi.max_element() < 0.45,
            "{lo} {hi}"
        );
        // Deterministic whatever the thread count.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let again = pool.install(|| carve(&views, 48, 0));
        assert_eq!(again, hull);
    }

    #[test]
    fn empty_masks_give_an_empty_hull() {
        let cams: Vec<Camera> = (0..3)
            .map(|k| look_at(DVec3::new(2.0, 0.3 * k as f64, 1.0)))
            .collect();
        let empty = vec![0u8; 64 * 64];
        let views: Vec<MaskedView> = cams
            .iter()
            .map(|c| MaskedView {
                camera: c,
                mask: &empty,
            })
            .collect();
        assert!(carve(&views, 16, 0).centres.is_empty());
    }
}
