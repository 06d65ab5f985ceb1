//! A first estimate of the initial velocity from the masks alone: the centre of each frame's
//! visual hull (its training views' masks carved, [`crate::scene::visual_hull`]) moves as
//! `c(t) = c₀ + v t + g t²/2` while the object flies; a least-squares fit of `c₀` and `v` over
//! the first frames gives `v`. The hulls' second moments turn with the object: the rotation
//! that carries the first hull's principal axes onto each later one's gives a first angular
//! velocity, when the axes can be told apart. It costs a few carvings, and the `velocity`
//! stage starts its gradient descent from it instead of from rest.

use std::path::Path;

use glam::{DMat3, DQuat, DVec3};
use pipe_mpm::svd::svd3;

use crate::io::image;
use crate::scene::camera::Camera;
use crate::scene::frames::{FrameRow, Role};
use crate::scene::visual_hull::{MaskedView, carve};

/// Voxels across the carving box.
const RESOLUTION: usize = 48;

/// Relative gap each pair of a hull's principal second moments must keep for its axes to be
/// told apart: a ball, a cube or a disc about its axis turns without its moments showing it.
pub const AXIS_GAP: f64 = 0.15;

/// One frame's visual hull, as the first estimates read it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HullSample {
    /// Time of the frame (s).
    pub time_s: f64,
    /// Centre of the hull's voxels (m).
    pub centre: DVec3,
    /// Covariance of the voxel centres (m²): the hull's second moments, which turn with it.
    pub covariance: DMat3,
}

/// The hull of each frame of `frames` that has training views, from the masks of `rows`
/// (paths relative to `dir`, an `ingest` entry); and the largest voxel edge (m) of those hulls.
pub fn hull_samples(
    dir: &Path,
    rows: &[FrameRow],
    frames: &[u16],
) -> Result<(Vec<HullSample>, f64), image::ImageError> {
    let mut out = Vec::new();
    let mut voxel = 0.0f64;
    for &f in frames {
        let mine: Vec<&FrameRow> = rows
            .iter()
            .filter(|r| r.frame == f && r.role == Role::Train)
            .collect();
        if mine.len() < 2 {
            continue;
        }
        let cams: Vec<Camera> = mine.iter().map(|r| Camera::from_row(r)).collect();
        let masks = mine
            .iter()
            .map(|r| image::read_gray8(&dir.join(&r.mask)).map(|(_, _, m)| m))
            .collect::<Result<Vec<_>, _>>()?;
        let views: Vec<MaskedView<'_>> = cams
            .iter()
            .zip(&masks)
            .map(|(camera, mask)| MaskedView { camera, mask })
            .collect();
        let hull = carve(&views, RESOLUTION, 1);
        if hull.centres.is_empty() {
            continue;
        }
        out.push(HullSample {
            time_s: mine[0].time_s,
            centre: centroid(&hull.centres),
            covariance: covariance(&hull.centres),
        });
        voxel = voxel.max(hull.voxel);
    }
    Ok((out, voxel))
}

fn centroid(x: &[DVec3]) -> DVec3 {
    x.iter().sum::<DVec3>() / x.len() as f64
}

/// The covariance of the points `x` (m²).
fn covariance(x: &[DVec3]) -> DMat3 {
    let c = centroid(x);
    let mut m = DMat3::ZERO;
    for p in x {
        let d = *p - c;
        m += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    m * (1.0 / x.len() as f64)
}

/// The principal axes of `covariance` as the columns of a rotation, largest moment first;
/// `None` when two moments are within [`AXIS_GAP`] of each other (or the matrix is not
/// finite).
fn principal_axes(covariance: &DMat3) -> Option<DMat3> {
    let svd = svd3(covariance);
    let s = svd.s.abs();
    let apart = |a: f64, b: f64| a > 0.0 && (a - b) >= AXIS_GAP * a;
    if !(s.is_finite() && apart(s.x, s.y) && apart(s.y, s.z)) {
        return None;
    }
    let u = svd.u;
    Some(if u.determinant() < 0.0 {
        DMat3::from_cols(u.x_axis, u.y_axis, -u.z_axis)
    } else {
        u
    })
}

/// The angular velocity (rad/s) of the rotations `R_k` that carry the first sample's principal
/// axes onto each later sample's, fitted by least squares to `θ_k = ω (t_k − t_0)` (`θ_k`:
/// the rotation vector of `R_k`; over a few frames a spinning body's ω barely precesses). Of
/// the four ways an axis frame maps onto another (an axis' sign is arbitrary), each frame
/// takes the one nearest the previous frame's rotation, so the samples must be close enough
/// in time that the body turns by less than a right angle between them. `None` with fewer
/// than two samples or when a hull's axes cannot be told apart ([`AXIS_GAP`]).
pub fn fit_angular_velocity(samples: &[HullSample]) -> Option<DVec3> {
    let (first, rest) = samples.split_first()?;
    if rest.is_empty() {
        return None;
    }
    let axes0 = principal_axes(&first.covariance)?;
    let mut previous = DMat3::IDENTITY;
    let (mut num, mut den) = (DVec3::ZERO, 0.0);
    for s in rest {
        let axes = principal_axes(&s.covariance)?;
        let closeness = |r: &DMat3| {
            r.x_axis.dot(previous.x_axis)
                + r.y_axis.dot(previous.y_axis)
                + r.z_axis.dot(previous.z_axis)
        };
        let r = [
            [1.0, 1.0, 1.0],
            [1.0, -1.0, -1.0],
            [-1.0, 1.0, -1.0],
            [-1.0, -1.0, 1.0],
        ]
        .into_iter()
        .map(|signs| axes * DMat3::from_diagonal(DVec3::from_array(signs)) * axes0.transpose())
        .max_by(|a, b| closeness(a).total_cmp(&closeness(b)))?;
        previous = r;
        let (axis, angle) = DQuat::from_mat3(&r).normalize().to_axis_angle();
        let angle = if angle > std::f64::consts::PI {
            angle - std::f64::consts::TAU
        } else {
            angle
        };
        let dt = s.time_s - first.time_s;
        num += axis * angle * dt;
        den += dt * dt;
    }
    (den > 0.0).then(|| num / den).filter(|w| w.is_finite())
}

/// The velocity `v` (m/s) of `c(t) = c₀ + v t + g t²/2` fitted to `centres` (time s, centre m)
/// by least squares; `None` with fewer than two distinct times.
pub fn fit_velocity(centres: &[(f64, DVec3)], gravity: DVec3) -> Option<DVec3> {
    if centres.len() < 2 {
        return None;
    }
    let n = centres.len() as f64;
    let tm = centres.iter().map(|(t, _)| t).sum::<f64>() / n;
    let var: f64 = centres.iter().map(|(t, _)| (t - tm) * (t - tm)).sum();
    if var <= 0.0 {
        return None;
    }
    // y = c − g t²/2 is linear in t.
    let y = |(t, c): &(f64, DVec3)| *c - 0.5 * gravity * t * t;
    let ym = centres.iter().map(y).sum::<DVec3>() / n;
    let cov: DVec3 = centres.iter().map(|p| (p.0 - tm) * (y(p) - ym)).sum();
    Some(cov / var)
}

/// How many leading `centres` lie on one ballistic path: the largest `k ≥ 2` whose least-squares
/// fit of `c₀ + v t + g t²/2` to the first `k` leaves every one of them within `tolerance` (m)
/// (a hull's centre wanders by about a voxel). The frames after it are no longer free flight
/// (the object met the ground or something else), so neither the first estimate nor the
/// `velocity` stage's fit should use them. `centres.len()` when it has fewer than three.
pub fn free_flight(centres: &[(f64, DVec3)], gravity: DVec3, tolerance: f64) -> usize {
    let on_path = |k: usize| {
        let part = &centres[..k];
        let Some(v) = fit_velocity(part, gravity) else {
            return false;
        };
        let n = k as f64;
        // c₀ from the fitted v: the mean of c − v t − g t²/2.
        let c0 = part
            .iter()
            .map(|(t, c)| *c - v * *t - 0.5 * gravity * t * t)
            .sum::<DVec3>()
            / n;
        part.iter()
            .all(|(t, c)| (*c - (c0 + v * *t + 0.5 * gravity * t * t)).length() <= tolerance)
    };
    if centres.len() < 3 {
        return centres.len();
    }
    let mut k = 2;
    while k < centres.len() && on_path(k + 1) {
        k += 1;
    }
    k
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A box's hull turned by `exp(t [ω]×)` in each frame: its moments give ω back; a cube's do
    /// not (its axes cannot be told apart), nor does a single frame.
    #[test]
    fn a_spinning_boxs_moments_give_its_angular_velocity() {
        let omega = DVec3::new(3.0, -1.0, 6.0);
        let lattice = |half: DVec3| -> Vec<DVec3> {
            let n = [12, 4, 8];
            let mut x = Vec::new();
            for i in 0..n[0] {
                for j in 0..n[1] {
                    for k in 0..n[2] {
                        let f = DVec3::new(
                            (i as f64 + 0.5) / n[0] as f64,
                            (j as f64 + 0.5) / n[1] as f64,
                            (k as f64 + 0.5) / n[2] as f64,
                        );
                        x.push((2.0 * f - 1.0) * half);
                    }
                }
            }
            x
        };
        let samples = |half: DVec3| -> Vec<HullSample> {
            let body = lattice(half);
            (0..4)
                .map(|k| {
                    let t = k as f64 / 24.0;
                    let r = DMat3::from_quat(DQuat::from_scaled_axis(omega * t));
                    let c = DVec3::new(0.1, 0.3, 0.0) + DVec3::new(0.5, 0.6, -0.2) * t;
                    let x: Vec<DVec3> = body.iter().map(|p| c + r * *p).collect();
                    HullSample {
                        time_s: t,
                        centre: centroid(&x),
                        covariance: covariance(&x),
                    }
                })
                .collect()
        };
        let bar = samples(DVec3::new(0.2, 0.05, 0.1));
        let w = fit_angular_velocity(&bar).unwrap();
        assert!((w - omega).length() < 1e-9 * omega.length(), "{w}");
        assert!(fit_angular_velocity(&bar[..1]).is_none());
        assert!(fit_angular_velocity(&samples(DVec3::splat(0.1))).is_none());
        assert!(fit_angular_velocity(&samples(DVec3::new(0.2, 0.1, 0.1))).is_none());
    }

    #[test]
    fn a_thrown_centre_gives_its_velocity() {
        let (c0, v, g) = (
            DVec3::new(0.1, 0.3, -0.2),
            DVec3::new(0.15, -0.3, 0.1),
            DVec3::new(0.0, -9.8, 0.0),
        );
        let centres: Vec<(f64, DVec3)> = (0..4)
            .map(|k| {
                let t = k as f64 / 24.0;
                (t, c0 + v * t + 0.5 * g * t * t)
            })
            .collect();
        let fit = fit_velocity(&centres, g).unwrap();
        assert!((fit - v).length() < 1e-12, "{fit}");
        assert!(fit_velocity(&centres[..1], g).is_none());
    }

    /// Falling fast, the centre leaves the ballistic path when the object lands (frame 2):
    /// only frames 0 and 1 are free flight, and their velocity is the throw's.
    #[test]
    fn free_flight_ends_where_the_centre_leaves_the_ballistic_path() {
        let (c0, v, g) = (
            DVec3::new(0.0, 0.33, 0.0),
            DVec3::new(0.3, -3.0, 0.0),
            DVec3::new(0.0, -9.8, 0.0),
        );
        let path = |t: f64| c0 + v * t + 0.5 * g * t * t;
        let mut centres: Vec<(f64, DVec3)> = (0..2)
            .map(|k| {
                let t = k as f64 / 24.0;
                (t, path(t))
            })
            .collect();
        // Landed: the centre stays near the ground, moving sideways.
        for k in 2..5 {
            let t = k as f64 / 24.0;
            centres.push((t, DVec3::new(0.3 * t, 0.09, 0.0)));
        }
        assert_eq!(free_flight(&centres, g, 0.005), 2);
        let fit = fit_velocity(&centres[..2], g).unwrap();
        assert!((fit - v).length() < 1e-9, "{fit}");
        // A whole flight with a voxel's noise stays free flight.
        let noisy: Vec<(f64, DVec3)> = (0..4)
            .map(|k| {
                let t = k as f64 / 24.0;
                (
                    t,
                    path(t) + DVec3::splat(if k % 2 == 0 { 0.002 } else { -0.002 }),
                )
            })
            .collect();
        assert_eq!(free_flight(&noisy, g, 0.005), 4);
        assert_eq!(free_flight(&noisy[..2], g, 0.005), 2);
    }
}
