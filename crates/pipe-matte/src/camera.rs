//! The pinhole camera the multi-view steps project with (OpenCV axes: x right, y down,
//! z forward; world y up, the ground being the plane y = 0).

use glam::{DMat3, DVec3};

/// A pinhole camera. World units are metres; image units pixels, pixel (i, j) centred at
/// (i + 0.5, j + 0.5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    /// Rotation of `world_from_camera` (columns: camera x, y, z axes in world).
    pub world_from_camera_rot: DMat3,
    /// Camera centre in world, metres.
    pub centre_world: DVec3,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl Pinhole {
    /// Pixel coordinates (continuous) and depth (m) of a world point; `None` behind the camera.
    /// `q = Rᵀ (p − c)`, `(u, v) = (fx·q_x/q_z + cx, fy·q_y/q_z + cy)`.
    pub fn project(&self, p_world: DVec3) -> Option<(f64, f64, f64)> {
        let q = self.world_from_camera_rot.transpose() * (p_world - self.centre_world);
        (q.z > 1e-9).then(|| {
            (
                self.fx * q.x / q.z + self.cx,
                self.fy * q.y / q.z + self.cy,
                q.z,
            )
        })
    }

    /// The pixel (column, row) a world point falls in, if inside the image and in front.
    pub fn pixel(&self, p_world: DVec3) -> Option<(u32, u32)> {
        let (u, v, _) = self.project(p_world)?;
        (u >= 0.0 && v >= 0.0 && u < f64::from(self.width) && v < f64::from(self.height))
            .then_some((u as u32, v as u32))
    }

    /// Unit world direction of the ray through image point `(u, v)` (pixels, continuous).
    pub fn ray(&self, u: f64, v: f64) -> DVec3 {
        let d = DVec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0);
        (self.world_from_camera_rot * d).normalize()
    }

    /// Where the ray through `(u, v)` meets the ground plane y = 0, if it goes down to it.
    pub fn ground_point(&self, u: f64, v: f64) -> Option<DVec3> {
        let d = self.ray(u, v);
        let t = -self.centre_world.y / d.y;
        (d.y < -1e-9 && t > 0.0).then(|| self.centre_world + d * t)
    }
}
