//! Pinhole cameras in OpenCV axes (x right, y down, z forward), built from `frames` rows.

use glam::{DMat3, DVec3};

use super::frames::FrameRow;

/// A pinhole camera. World units are metres; image units pixels, pixel (i, j) centred at
/// (i + 0.5, j + 0.5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
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

impl Camera {
    /// From a `frames` row.
    pub fn from_row(r: &FrameRow) -> Self {
        Self::new(
            &r.world_from_camera,
            [r.fx, r.fy, r.cx, r.cy],
            r.width,
            r.height,
        )
    }

    /// From a 3×4 row-major `world_from_camera` (OpenCV axes, metres), `[fx, fy, cx, cy]`
    /// (pixels) and the image size.
    pub fn new(
        world_from_camera: &[f64; 12],
        intrinsics: [f64; 4],
        width: u32,
        height: u32,
    ) -> Self {
        let m = world_from_camera;
        let [fx, fy, cx, cy] = intrinsics;
        Self {
            world_from_camera_rot: DMat3::from_cols(
                DVec3::new(m[0], m[4], m[8]),
                DVec3::new(m[1], m[5], m[9]),
                DVec3::new(m[2], m[6], m[10]),
            ),
            centre_world: DVec3::new(m[3], m[7], m[11]),
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// The same camera as the matting and carving kernels take it (one projection code).
    pub fn pinhole(&self) -> pipe_matte::Pinhole {
        pipe_matte::Pinhole {
            world_from_camera_rot: self.world_from_camera_rot,
            centre_world: self.centre_world,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width: self.width,
            height: self.height,
        }
    }

    /// Pixel coordinates (continuous) and depth (m) of a world point; `None` behind the camera.
    pub fn project(&self, p_world: DVec3) -> Option<(f64, f64, f64)> {
        self.pinhole().project(p_world)
    }

    /// The pixel (column, row) a world point falls in, if inside the image and in front.
    pub fn pixel(&self, p_world: DVec3) -> Option<(u32, u32)> {
        self.pinhole().pixel(p_world)
    }

    /// Where the ray through image point `(u, v)` (pixels) meets the ground plane y = 0.
    pub fn ground_point(&self, u: f64, v: f64) -> Option<DVec3> {
        self.pinhole().ground_point(u, v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn principal_axis_projects_to_principal_point() {
        let cam = Camera {
            world_from_camera_rot: DMat3::IDENTITY,
            centre_world: DVec3::new(1.0, 2.0, 3.0),
            fx: 100.0,
            fy: 90.0,
            cx: 50.0,
            cy: 40.0,
            width: 100,
            height: 80,
        };
        let (u, v, z) = cam.project(DVec3::new(1.0, 2.0, 5.0)).unwrap();
        assert_eq!((u, v, z), (50.0, 40.0, 2.0));
        // x right, y down in the image.
        let (u, v, _) = cam.project(DVec3::new(1.2, 2.2, 5.0)).unwrap();
        assert!((u - 60.0).abs() < 1e-9 && (v - 49.0).abs() < 1e-9);
        assert!(cam.project(DVec3::new(1.0, 2.0, 2.0)).is_none());
        assert_eq!(cam.pixel(DVec3::new(1.0, 2.0, 5.0)), Some((50, 40)));
    }
}
