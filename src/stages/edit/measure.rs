//! What `edit.json` records of the object every frame: its height along the scene's up axis,
//! centre of mass, box, momentum, top speed, and how many particles lie inside each declared
//! boundary (pushed through a wall: counted, never dropped).

use glam::DVec3;
use serde::Serialize;

use crate::simulate::spec::BoundarySpec;

/// The object at one output frame (every simulated particle: Gaussians and fillers).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameMeasure {
    /// Output frame (0 = the canonical state).
    pub frame: u32,
    /// Time (s).
    pub time_s: f64,
    /// Extent along the up axis: highest minus lowest particle (m).
    pub height_m: f64,
    /// Lowest and highest particle along the up axis (m).
    pub bottom_m: f64,
    pub top_m: f64,
    /// Mass-weighted centre (m).
    pub centre_of_mass_m: [f64; 3],
    /// Box of the particles (m).
    pub box_min_m: [f64; 3],
    pub box_max_m: [f64; 3],
    /// Total momentum `Σ m v` (N·s).
    pub momentum_n_s: [f64; 3],
    /// Largest particle speed (m/s).
    pub max_speed_m_s: f64,
    /// Per declared boundary (in order), the particles more than half a cell inside its
    /// solid side (pushed through it).
    pub inside_boundaries: Vec<usize>,
    /// Per declared boundary, the particles it acted on during the frame (their stencil
    /// reached a node it treats; `pipe simulate`'s `contacts`); empty at frame 0.
    pub contacts: Vec<usize>,
    /// Substeps of the frame and the limit that set them (none at frame 0).
    pub substeps: usize,
    pub substeps_reason: String,
    /// The speed bound (m/s) the substeps hold for: speeds at the frame's start plus what its
    /// forces and impulses can add.
    pub speed_bound_m_s: f64,
}

/// Measures particles at `x` (m) moving at `v` (m/s) of masses `mass` (kg) with `up` the
/// unit up axis, against `boundaries` at cell size `dx` (m).
pub fn measure(
    (frame, time_s): (u32, f64),
    (x, v, mass): (&[DVec3], &[DVec3], &[f64]),
    up: DVec3,
    boundaries: &[BoundarySpec],
    dx: f64,
) -> FrameMeasure {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    let (mut bottom, mut top) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut mx, mut p, mut m_total, mut speed) = (DVec3::ZERO, DVec3::ZERO, 0.0, 0.0f64);
    for ((x, v), m) in x.iter().zip(v).zip(mass) {
        lo = lo.min(*x);
        hi = hi.max(*x);
        let h = x.dot(up);
        bottom = bottom.min(h);
        top = top.max(h);
        mx += *x * *m;
        p += *v * *m;
        m_total += m;
        speed = speed.max(v.length());
    }
    let inside_boundaries = boundaries
        .iter()
        .map(|b| {
            x.iter()
                .filter(|&&p| crate::simulate::setup::depth_inside(b, p) > 0.5 * dx)
                .count()
        })
        .collect();
    FrameMeasure {
        frame,
        time_s,
        height_m: top - bottom,
        bottom_m: bottom,
        top_m: top,
        centre_of_mass_m: (mx / m_total).to_array(),
        box_min_m: lo.to_array(),
        box_max_m: hi.to_array(),
        momentum_n_s: p.to_array(),
        max_speed_m_s: speed,
        inside_boundaries,
        contacts: Vec::new(),
        substeps: 0,
        substeps_reason: String::new(),
        speed_bound_m_s: speed,
    }
}

/// The scene's up axis: against gravity, `+y` without gravity.
pub fn up_axis(gravity: [f64; 3]) -> DVec3 {
    let g = DVec3::from_array(gravity);
    if g.length() > 0.0 {
        -g.normalize()
    } else {
        DVec3::Y
    }
}
