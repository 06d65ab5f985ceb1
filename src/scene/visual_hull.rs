//! Space carving: the object's visual hull from its masks in calibrated views.
//!
//! The carving itself is `pipe_matte::hull` (the matting's multi-view check carves the same
//! way); this module takes the scene's cameras.

pub use pipe_matte::Hull;

use super::camera::Camera;

/// One view: its camera and binary mask (`width·height` bytes, ≥ 128 = object).
#[derive(Debug, Clone, Copy)]
pub struct MaskedView<'a> {
    /// The camera.
    pub camera: &'a Camera,
    /// Row-major mask.
    pub mask: &'a [u8],
}

/// Carve the visual hull at `resolution` voxels along the longest box edge; a voxel is kept
/// when its centre projects into the masks of all views but at most `max_misses`.
pub fn carve(views: &[MaskedView<'_>], resolution: usize, max_misses: usize) -> Hull {
    let views: Vec<pipe_matte::MaskedView<'_>> = views
        .iter()
        .map(|v| pipe_matte::MaskedView {
            camera: v.camera.pinhole(),
            mask: v.mask,
        })
        .collect();
    pipe_matte::carve(&views, resolution, max_misses)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DMat3, DVec3};

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
