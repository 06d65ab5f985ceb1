//! A first estimate of the initial velocity from the masks alone: the centre of each frame's
//! visual hull (its training views' masks carved, [`crate::scene::visual_hull`]) moves as
//! `c(t) = c₀ + v t + g t²/2` while the object flies; a least-squares fit of `c₀` and `v` over
//! the first frames gives `v`. It costs a few carvings, and the `velocity` stage starts its
//! gradient descent from it instead of from rest.

use std::path::Path;

use glam::DVec3;

use crate::io::image;
use crate::scene::camera::Camera;
use crate::scene::frames::{FrameRow, Role};
use crate::scene::visual_hull::{MaskedView, carve};

/// Voxels across the carving box.
const RESOLUTION: usize = 48;

/// The hull centre (m) of each frame of `frames` that has training views, from the masks of
/// `rows` (paths relative to `dir`, an `ingest` entry), with the time (s) of the frame; and the
/// largest voxel edge (m) of those hulls.
pub fn hull_centres(
    dir: &Path,
    rows: &[FrameRow],
    frames: &[u16],
) -> Result<(Vec<(f64, DVec3)>, f64), image::ImageError> {
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
        let c = hull.centres.iter().sum::<DVec3>() / hull.centres.len() as f64;
        out.push((mine[0].time_s, c));
        voxel = voxel.max(hull.voxel);
    }
    Ok((out, voxel))
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
