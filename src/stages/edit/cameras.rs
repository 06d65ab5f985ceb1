//! The cameras an edit is rendered from: cameras of the capture (fixed, over their
//! background plates) and orbit cameras (circling the object, over a plain background).

use glam::{DMat3, DVec3};

use super::params::OrbitSpec;
use crate::scene::camera::Camera;

/// A camera of an edit.
#[derive(Debug, Clone)]
pub struct EditCamera {
    /// File-name stem of its outputs: `view<index>` or `orbit<k>`.
    pub name: String,
    /// Where it is at each frame.
    pub pose: Pose,
    /// What the object is composited over: the camera's plate (RGB in [0, 1]) or a colour.
    pub backdrop: Backdrop,
}

/// A camera's motion.
#[derive(Debug, Clone)]
pub enum Pose {
    /// A camera of the capture.
    Fixed(Camera),
    /// One turn around `center` every `frames` frames.
    Orbit(Orbit),
}

/// What a render is composited over.
#[derive(Debug, Clone)]
pub enum Backdrop {
    /// An image (RGB in [0, 1], the camera's size).
    Plate(Vec<f32>),
    /// A colour (RGB in [0, 1]).
    Solid([f32; 3]),
}

impl Backdrop {
    /// `width·height·3` values.
    pub fn pixels(&self, width: u32, height: u32) -> std::borrow::Cow<'_, [f32]> {
        match self {
            Backdrop::Plate(p) => p.as_slice().into(),
            Backdrop::Solid(c) => c.repeat(width as usize * height as usize).into(),
        }
    }
}

/// An orbit resolved against the object.
#[derive(Debug, Clone, Copy)]
pub struct Orbit {
    /// What it looks at (m).
    pub center: DVec3,
    /// Distance (m).
    pub radius: f64,
    /// Elevation (radians).
    pub elevation: f64,
    /// Azimuth at frame 0 (radians).
    pub start: f64,
    /// Frames per turn (0: still).
    pub frames: u32,
    /// The up axis (unit).
    pub up: DVec3,
    /// Image size (pixels).
    pub size: [u32; 2],
    /// Focal length (pixels).
    pub focal: f64,
}

impl Orbit {
    /// `spec` around an object of centre of mass `com` and bounding radius `extent` (m),
    /// with the scene's up axis `up`, over an edit of `frames` frames.
    pub fn new(spec: &OrbitSpec, com: DVec3, extent: f64, up: DVec3, frames: u32) -> Self {
        let half_fov = (0.5 * spec.fov_deg).to_radians();
        // The bounding sphere spans 60 % of the view's height.
        let radius = spec
            .radius
            .unwrap_or_else(|| extent.max(1e-3) / (0.6 * half_fov.tan()));
        Self {
            center: spec.center.map_or(com, DVec3::from_array),
            radius,
            elevation: spec.elevation_deg.to_radians(),
            start: spec.start_deg.to_radians(),
            frames: spec.frames.unwrap_or(frames),
            up,
            size: spec.size,
            focal: 0.5 * f64::from(spec.size[1]) / half_fov.tan(),
        }
    }

    /// The camera at output frame `frame`.
    pub fn at(&self, frame: u32) -> Camera {
        let (a, b) = horizontal_axes(self.up);
        let turn = match self.frames {
            0 => 0.0,
            n => f64::from(frame % n) / f64::from(n),
        };
        let azimuth = self.start + std::f64::consts::TAU * turn;
        let dir = self.elevation.cos() * (azimuth.cos() * a + azimuth.sin() * b)
            + self.elevation.sin() * self.up;
        look_at(
            self.center + self.radius * dir,
            self.center,
            self.up,
            self.size,
            self.focal,
        )
    }
}

impl EditCamera {
    /// The camera at output frame `frame`.
    pub fn at(&self, frame: u32) -> Camera {
        match &self.pose {
            Pose::Fixed(c) => *c,
            Pose::Orbit(o) => o.at(frame),
        }
    }
}

/// Two unit axes spanning the plane normal to `up`: for `up = +y`, `+x` and `+z`.
fn horizontal_axes(up: DVec3) -> (DVec3, DVec3) {
    let seed = if up.x.abs() < 0.9 { DVec3::X } else { DVec3::Z };
    let a = (seed - up * seed.dot(up)).normalize();
    (a, a.cross(up).normalize())
}

/// A pinhole camera at `eye` looking at `target` with `up` up in the image (OpenCV axes:
/// x right, y down, z forward), of `size` pixels and focal length `focal` (pixels).
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3, size: [u32; 2], focal: f64) -> Camera {
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let down = forward.cross(right);
    Camera {
        world_from_camera_rot: DMat3::from_cols(right, down, forward),
        centre_world: eye,
        fx: focal,
        fy: focal,
        cx: 0.5 * f64::from(size[0]),
        cy: 0.5 * f64::from(size[1]),
        width: size[0],
        height: size[1],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_orbit_camera_sees_its_center_in_the_middle_with_up_up() {
        let spec = OrbitSpec {
            center: Some([0.1, 0.2, -0.3]),
            radius: Some(2.0),
            elevation_deg: 30.0,
            frames: Some(8),
            start_deg: 0.0,
            size: [200, 100],
            fov_deg: 40.0,
        };
        let orbit = Orbit::new(&spec, DVec3::ZERO, 0.5, DVec3::Y, 48);
        assert_eq!(orbit.frames, 8);
        for f in 0..8 {
            let cam = orbit.at(f);
            let c = DVec3::new(0.1, 0.2, -0.3);
            let (u, v, depth) = cam.project(c).unwrap();
            assert!(
                (u - 100.0).abs() < 1e-9 && (v - 50.0).abs() < 1e-9,
                "{u} {v}"
            );
            assert!((depth - 2.0).abs() < 1e-9);
            // A point above the centre is higher in the image (smaller row).
            let (_, v_up, _) = cam.project(c + 0.1 * DVec3::Y).unwrap();
            assert!(v_up < v);
            // Elevation 30°: the eye is 1 m above the centre.
            assert!((cam.centre_world.y - c.y - 1.0).abs() < 1e-9);
        }
        // Frame 0 at azimuth 0: on the +x side; a quarter turn later on the +z side.
        assert!(orbit.at(0).centre_world.x > 1.0);
        assert!(orbit.at(2).centre_world.z - (-0.3) > 1.0);
        // One turn per 8 frames; `frames: 0` stays still.
        assert_eq!(orbit.at(8), orbit.at(0));
        let still = Orbit::new(
            &OrbitSpec {
                frames: Some(0),
                ..spec
            },
            DVec3::ZERO,
            0.5,
            DVec3::Y,
            48,
        );
        assert_eq!(still.at(5), orbit.at(0));
    }
}
