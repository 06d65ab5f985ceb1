//! Pinhole camera in the OpenCV convention (x right, y down, z forward; depth = z_cam).
//!
//! Units: positions in metres, focal lengths and principal point in pixels. Pixel (col i,
//! row j) has its centre at `(i + 0.5, j + 0.5)`.

use crate::error::RenderError;
use crate::real::Real;

/// Side of the square screen tiles, in pixels (3DGS `BLOCK_X = BLOCK_Y = 16`).
pub const TILE: u32 = 16;

/// A pinhole camera: extrinsics as `camera_from_world` (`x_cam = R·x_world + t`) and
/// intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera<T> {
    /// Rotation of `camera_from_world`, row-major (`R[row][col]`).
    pub camera_from_world_rotation: [[T; 3]; 3],
    /// Translation of `camera_from_world` (m).
    pub camera_from_world_translation: [T; 3],
    /// Focal length along x (pixels).
    pub fx: T,
    /// Focal length along y (pixels).
    pub fy: T,
    /// Principal point x (pixels, from the left image edge).
    pub cx: T,
    /// Principal point y (pixels, from the top image edge).
    pub cy: T,
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Near plane (m): Gaussians with `z_cam <= near` are culled.
    pub near: T,
}

impl<T: Real> Camera<T> {
    /// Checks sizes and that every scalar is finite, focal lengths positive and `near > 0`.
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.width == 0 || self.height == 0 {
            return Err(RenderError::ImageSize {
                width: self.width,
                height: self.height,
            });
        }
        let positive = [("fx", self.fx), ("fy", self.fy), ("near", self.near)];
        for (field, v) in positive {
            if !(v.is_finite() && v > T::ZERO) {
                return Err(RenderError::Value {
                    field,
                    value: v.to_f64(),
                    reason: "must be finite and > 0",
                });
            }
        }
        let finite = [("cx", self.cx), ("cy", self.cy)]
            .into_iter()
            .chain(
                self.camera_from_world_rotation
                    .iter()
                    .flatten()
                    .map(|&v| ("camera_from_world_rotation", v)),
            )
            .chain(
                self.camera_from_world_translation
                    .iter()
                    .map(|&v| ("camera_from_world_translation", v)),
            );
        for (field, v) in finite {
            if !v.is_finite() {
                return Err(RenderError::Value {
                    field,
                    value: v.to_f64(),
                    reason: "must be finite",
                });
            }
        }
        Ok(())
    }

    /// Builds a camera from its pose as `world_from_camera` (`x_world = R·x_cam + t`, the
    /// camera-to-world matrix of COLMAP/NeRF datasets after conversion to OpenCV axes).
    #[allow(clippy::too_many_arguments)]
    pub fn from_world_from_camera(
        world_from_camera_rotation: [[T; 3]; 3],
        world_from_camera_translation: [T; 3],
        fx: T,
        fy: T,
        cx: T,
        cy: T,
        width: u32,
        height: u32,
        near: T,
    ) -> Self {
        let r = world_from_camera_rotation;
        let t = world_from_camera_translation;
        // inverse of a rigid transform: Rᵀ, -Rᵀ t
        let rt: [[T; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| r[j][i]));
        let tt = std::array::from_fn(|i| -(rt[i][0] * t[0] + rt[i][1] * t[1] + rt[i][2] * t[2]));
        Self {
            camera_from_world_rotation: rt,
            camera_from_world_translation: tt,
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            near,
        }
    }

    /// Number of tiles along x and y.
    pub fn tile_grid(&self) -> (u32, u32) {
        (self.width.div_ceil(TILE), self.height.div_ceil(TILE))
    }

    /// Number of pixels.
    pub fn n_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// `x_cam = R·x_world + t`.
    #[inline]
    pub fn camera_from_world_point(&self, p_world: [T; 3]) -> [T; 3] {
        let r = &self.camera_from_world_rotation;
        let t = &self.camera_from_world_translation;
        std::array::from_fn(|i| {
            r[i][0] * p_world[0] + r[i][1] * p_world[1] + r[i][2] * p_world[2] + t[i]
        })
    }

    /// Camera centre in world space, `-Rᵀ t` (m).
    pub fn center_world(&self) -> [T; 3] {
        let r = &self.camera_from_world_rotation;
        let t = &self.camera_from_world_translation;
        std::array::from_fn(|j| -(r[0][j] * t[0] + r[1][j] * t[1] + r[2][j] * t[2]))
    }

    /// gsplat's frustum limits on `t.x/t.z` and `t.y/t.z` used in the projection Jacobian:
    /// `(lim_x-, lim_x+, lim_y-, lim_y+)`, with `lim_x+ = (W - cx)/fx + 0.3·tan_fovx`,
    /// `lim_x- = cx/fx + 0.3·tan_fovx`, `tan_fovx = 0.5·W/fx` (same for y).
    pub fn frustum_limits(&self) -> [T; 4] {
        let w = T::from_f64(self.width as f64);
        let h = T::from_f64(self.height as f64);
        let k = T::from_f64(0.3);
        let tan_fovx = T::from_f64(0.5) * w / self.fx;
        let tan_fovy = T::from_f64(0.5) * h / self.fy;
        [
            self.cx / self.fx + k * tan_fovx,
            (w - self.cx) / self.fx + k * tan_fovx,
            self.cy / self.fy + k * tan_fovy,
            (h - self.cy) / self.fy + k * tan_fovy,
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `from_world_from_camera` inverts the pose: the camera centre maps to the origin and
    /// `center_world` returns the pose translation.
    #[test]
    fn world_from_camera_round_trip() {
        let (c, s) = (0.6f64.cos(), 0.6f64.sin());
        let r = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]];
        let t = [0.3, -1.2, 2.5];
        let cam = Camera::from_world_from_camera(r, t, 100.0, 100.0, 32.0, 24.0, 64, 48, 0.01);
        let o = cam.camera_from_world_point(t);
        assert!(o.iter().all(|v| v.abs() < 1e-12), "{o:?}");
        let cw = cam.center_world();
        assert!(cw.iter().zip(&t).all(|(a, b)| (a - b).abs() < 1e-12));
        // the camera's +z axis in world space is the third column of R
        let p = cam.camera_from_world_point([t[0] + r[0][2], t[1] + r[1][2], t[2] + r[2][2]]);
        assert!((p[2] - 1.0).abs() < 1e-12 && p[0].abs() < 1e-12 && p[1].abs() < 1e-12);
    }
}
