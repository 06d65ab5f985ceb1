//! A ring of pinhole cameras around the scene, written as PAC-NeRF camera entries (`c2w` 3×4 in
//! OpenGL axes: x right, y up, looking down −z; `intrinsic` in pixels, `cx = W/2`, `cy = H/2`).
//! The renderer uses the cameras as the pipeline's reader reads them back from those entries
//! (`pipe::io::pacnerf`), so the images and the cameras agree by construction.

use glam::DVec3;
use serde_json::{Value, json};

/// Where the cameras are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ring {
    /// Number of cameras, evenly spaced in azimuth.
    pub views: u16,
    /// The point they look at (m).
    pub target: DVec3,
    /// Distance from the target (m).
    pub distance: f64,
    /// Mean elevation above the horizontal (degrees); even cameras sit `elevation_swing`
    /// lower, odd ones higher (two heights carve a tighter visual hull than one).
    pub elevation_deg: f64,
    /// Half the spread of elevations (degrees).
    pub elevation_swing_deg: f64,
    /// Azimuth of camera 0 (degrees, from +x towards +z).
    pub azimuth0_deg: f64,
    /// Horizontal field of view (degrees).
    pub fov_x_deg: f64,
}

impl Ring {
    /// Camera `k`'s centre (m) in world coordinates.
    pub fn centre(&self, k: u16) -> DVec3 {
        let az = (self.azimuth0_deg + 360.0 * f64::from(k) / f64::from(self.views)).to_radians();
        let swing = if k.is_multiple_of(2) { -1.0 } else { 1.0 };
        let el = (self.elevation_deg + swing * self.elevation_swing_deg).to_radians();
        self.target + self.distance * DVec3::new(el.cos() * az.cos(), el.sin(), el.cos() * az.sin())
    }

    /// Camera `k`'s `c2w` (3×4, OpenGL axes): columns right, up, back (−forward), centre.
    pub fn c2w(&self, k: u16) -> [[f64; 4]; 3] {
        let c = self.centre(k);
        let forward = (self.target - c).normalize();
        let right = forward.cross(DVec3::Y).normalize();
        let up = right.cross(forward);
        let back = -forward;
        std::array::from_fn(|i| [right[i], up[i], back[i], c[i]])
    }

    /// Pinhole intrinsics for a `size`×`size` image: `[[f, 0, size/2], [0, f, size/2], [0, 0, 1]]`
    /// with `f = (size/2) / tan(fov/2)`.
    pub fn intrinsic(&self, size: u32) -> [[f64; 3]; 3] {
        let half = 0.5 * f64::from(size);
        let f = half / (0.5 * self.fov_x_deg.to_radians()).tan();
        [[f, 0.0, half], [0.0, f, half], [0.0, 0.0, 1.0]]
    }

    /// `all_data.json`: per camera, its plate (frame −1 at time −frame_dt) then frames
    /// `0..frames` at `frame · frame_dt` (s), as PAC-NeRF lists them.
    pub fn all_data(&self, size: u32, frames: u32, frame_dt: f64) -> Value {
        let mut entries = Vec::new();
        for k in 0..self.views {
            for f in -1..frames as i64 {
                entries.push(json!({
                    "c2w": self.c2w(k),
                    "file_path": format!("./data/r_{k}_{f}.png"),
                    "intrinsic": self.intrinsic(size),
                    "time": f as f64 * frame_dt,
                }));
            }
        }
        Value::Array(entries)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pipe::io::pacnerf;
    use pipe::scene::camera::Camera;

    fn ring() -> Ring {
        Ring {
            views: 5,
            target: DVec3::new(0.05, 0.2, 0.0),
            distance: 1.6,
            elevation_deg: 25.0,
            elevation_swing_deg: 5.0,
            azimuth0_deg: 10.0,
            fov_x_deg: 40.0,
        }
    }

    /// The entries read back through the pipeline's PAC-NeRF reader give cameras that see the
    /// target at the image centre, world up as image up (smaller row), and the camera's right
    /// as image right; the camera sits where the ring puts it.
    #[test]
    fn the_pipeline_reader_projects_as_the_ring_intends() {
        let ring = ring();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("all_data.json");
        std::fs::write(&path, ring.all_data(100, 2, 1.0 / 24.0).to_string()).unwrap();
        let scene = pacnerf::read_cameras(&path).unwrap();
        assert_eq!(scene.images.len(), 5 * 2);
        assert_eq!(scene.plates.len(), 5);
        for img in &scene.images {
            assert!((img.time_s - f64::from(img.frame) / 24.0).abs() < 1e-15);
            let cam = Camera::new(&img.world_from_camera, img.intrinsics, 100, 100);
            let k = img.view;
            assert!((cam.centre_world - ring.centre(k)).length() < 1e-12);
            let (u, v, z) = cam.project(ring.target).unwrap();
            assert!(
                (u - 50.0).abs() < 1e-9 && (v - 50.0).abs() < 1e-9,
                "{u} {v}"
            );
            assert!((z - 1.6).abs() < 1e-9);
            let (_, v_up, _) = cam.project(ring.target + 0.1 * DVec3::Y).unwrap();
            assert!(v_up < 50.0 - 5.0, "world up is image up: {v_up}");
            let right = DVec3::from_array(std::array::from_fn(|i| ring.c2w(k)[i][0]));
            let (u_right, _, _) = cam.project(ring.target + 0.1 * right).unwrap();
            assert!(u_right > 55.0, "{u_right}");
            // Elevations alternate 20° / 30°.
            let el = ((cam.centre_world - ring.target).y / 1.6)
                .asin()
                .to_degrees();
            let want = if k.is_multiple_of(2) { 20.0 } else { 30.0 };
            assert!((el - want).abs() < 1e-9, "{el}");
        }
        // 40° horizontal field of view: a point 20° off the axis lands on the image edge.
        let img = &scene.images[0];
        let cam = Camera::new(&img.world_from_camera, img.intrinsics, 100, 100);
        let c2w = ring.c2w(0);
        let col = |j: usize| DVec3::from_array(std::array::from_fn(|i| c2w[i][j]));
        let edge = cam.centre_world
            + (-col(2)) * 20f64.to_radians().cos()
            + col(0) * 20f64.to_radians().sin();
        let (u, _, _) = cam.project(edge).unwrap();
        assert!((u - 100.0).abs() < 1e-9, "{u}");
    }
}
