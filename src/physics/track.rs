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
/// `rows` (paths relative to `dir`, an `ingest` entry), with the time (s) of the frame.
pub fn hull_centres(
    dir: &Path,
    rows: &[FrameRow],
    frames: &[u16],
) -> Result<Vec<(f64, DVec3)>, image::ImageError> {
    let mut out = Vec::new();
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
    }
    Ok(out)
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
}
