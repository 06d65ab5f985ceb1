//! Ground witnesses: do the other views see the ground behind a pixel dimmed as this view sees
//! it?
//!
//! A shadow lies on the ground and dims it by a factor that does not depend on the viewpoint
//! (a diffuse floor), so every view with a clear line of sight to a shadowed ground point sees
//! the same dimming `s = (I + k) / (B + k)` there. A pixel of view `a` that shows an object in
//! front of the ground does not: its dimming is the object's colour over the plate's. For
//! pixel `p`, take the ground points `X_n` of the pixels `n` of its 3×3 block (those not already
//! proven object) and, in every other view `b` that sees `X_p` with no voxel of the hull in
//! between (an occluded witness proves nothing), compare
//! `mean_n |ln s_a(n) − ln s_b(X_n)|` (mean over the block, `ln s` averaged over the channels)
//! with a tolerance `witness_tolerance + witness_noise_factor · spread_b` (`spread_b`: the mean
//! absolute deviation of `ln s_b` over the block, so a noisy dark shadow does not disagree with
//! itself): below it `b` agrees (shadow), above it disagrees. The block compares the
//! dimming's texture, not one value: an object of the shadow's own tone still carries its own
//! texture, while a shadow's dimming is smooth and the plate's texture cancels in the ratio.

use glam::DVec3;

use crate::hull::Hull;
use crate::multiview::View;
use crate::params::MultiViewParams;

/// Counts of the other views that see the ground behind a pixel dimmed the same way, and
/// otherwise.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Witnesses {
    /// Unoccluded views whose dimming agrees.
    pub agree: usize,
    /// Unoccluded views whose dimming differs.
    pub disagree: usize,
}

/// Mean over the channels of `ln((I_c + k) / (B_c + k))` at continuous pixel `(u, v)` of `view`
/// (nearest pixel), if inside the image.
fn log_dimming(view: &View<'_>, u: f64, v: f64, k: f32) -> Option<f32> {
    let (w, h) = (view.image.width(), view.image.height());
    if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
        return None;
    }
    let p = 3 * (v as usize * w + u as usize);
    let (i, b) = (view.image.data(), view.plate.data());
    Some(
        (0..3)
            .map(|c| ((f32::from(i[p + c]) + k) / (f32::from(b[p + c]) + k)).ln())
            .sum::<f32>()
            / 3.0,
    )
}

/// The witnesses of pixel `i` of view `a` (see the module doc): `proven` marks view `a`'s
/// pixels already proven object (left out of the block), `hull` is what may occlude the ground;
/// the ratio offset `k` and the tolerances are `p`'s.
pub(crate) fn witnesses(
    a: usize,
    i: usize,
    views: &[View<'_>],
    proven: &[bool],
    hull: &Hull,
    p: &MultiViewParams,
) -> Witnesses {
    let k = p.view.ratio_offset.max(f32::MIN_POSITIVE);
    let cam = &views[a].camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (x0, y0) = (i % w, i / w);
    let mut out = Witnesses::default();
    if x0 == 0 || y0 == 0 || x0 + 1 >= w || y0 + 1 >= h {
        return out;
    }
    let Some(centre) = cam.ground_point(x0 as f64 + 0.5, y0 as f64 + 0.5) else {
        return out;
    };
    let mut block: Vec<(DVec3, f32)> = Vec::with_capacity(9);
    for y in y0 - 1..=y0 + 1 {
        for x in x0 - 1..=x0 + 1 {
            if proven[y * w + x] {
                continue;
            }
            let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
            let (Some(g), Some(l)) = (cam.ground_point(u, v), log_dimming(&views[a], u, v, k))
            else {
                return out;
            };
            block.push((g, l));
        }
    }
    if block.is_empty() {
        return out;
    }
    for (b, vb) in views.iter().enumerate() {
        if b == a || vb.camera.project(centre).is_none() {
            continue;
        }
        // An occluded witness proves nothing; stop short of the ground point, on which the
        // object may rest.
        if hull.blocks(vb.camera.centre_world, centre, 1.5 * hull.voxel) {
            continue;
        }
        let theirs: Option<Vec<f32>> = block
            .iter()
            .map(|(g, _)| {
                vb.camera
                    .project(*g)
                    .and_then(|(u, v, _)| log_dimming(vb, u, v, k))
            })
            .collect();
        let Some(theirs) = theirs else {
            continue;
        };
        let n = block.len() as f32;
        let difference = block
            .iter()
            .zip(&theirs)
            .map(|((_, l), lb)| (lb - l).abs())
            .sum::<f32>()
            / n;
        let mean = theirs.iter().sum::<f32>() / n;
        let spread = theirs.iter().map(|lb| (lb - mean).abs()).sum::<f32>() / n;
        if difference <= p.witness_tolerance + p.witness_noise_factor * spread {
            out.agree += 1;
        } else {
            out.disagree += 1;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, UVec3};

    use super::*;
    use crate::camera::Pinhole;
    use crate::view::RgbImageView;

    const SIZE: u32 = 64;
    const SHADOW: f64 = 0.4;

    /// A camera at `eye` looking at the origin, 50° field of view.
    fn look_at(eye: DVec3) -> Pinhole {
        let z = (-eye).normalize();
        let x = z.cross(DVec3::Y).normalize();
        let y = z.cross(x);
        let f = f64::from(SIZE) / 2.0 / 25f64.to_radians().tan();
        Pinhole {
            world_from_camera_rot: DMat3::from_cols(x, y, z),
            centre_world: eye,
            fx: f,
            fy: f,
            cx: f64::from(SIZE) / 2.0,
            cy: f64::from(SIZE) / 2.0,
            width: SIZE,
            height: SIZE,
        }
    }

    /// A textured floor (RGB, 0–255): smooth waves and tiles, so a shifted copy of it differs.
    fn floor(g: DVec3) -> [f64; 3] {
        let tile = if ((g.x * 10.0).floor() + (g.z * 10.0).floor()) as i64 % 2 == 0 {
            30.0
        } else {
            0.0
        };
        let wave = 60.0 * (17.0 * g.x).sin() * (13.0 * g.z).cos();
        [
            130.0 + wave + tile,
            120.0 + 0.8 * wave + tile,
            100.0 + 0.6 * wave,
        ]
    }

    /// The shadow: a square on the ground, dimming it by [`SHADOW`] from every side.
    fn in_shadow(g: DVec3) -> bool {
        g.x.abs() < 0.1 && g.z.abs() < 0.1
    }

    /// Where view 0 sees an object of the shadow's tone (its own texture: the floor's, moved).
    fn in_object(g: DVec3) -> bool {
        (0.0..0.08).contains(&g.x) && g.z.abs() < 0.08
    }

    /// Plate and image of a camera; view 0 also shows the object.
    fn render(cam: &Pinhole, with_object: bool) -> (Vec<u8>, Vec<u8>) {
        let n = (SIZE * SIZE) as usize;
        let (mut plate, mut image) = (vec![0u8; 3 * n], vec![0u8; 3 * n]);
        for i in 0..n {
            let (u, v) = (
                (i % SIZE as usize) as f64 + 0.5,
                (i / SIZE as usize) as f64 + 0.5,
            );
            let g = cam.ground_point(u, v).expect("every pixel sees the floor");
            let b = floor(g);
            let seen = match (with_object && in_object(g), in_shadow(g)) {
                (true, _) => floor(g + DVec3::new(0.13, 0.0, 0.07)).map(|c| c * SHADOW),
                (false, true) => b.map(|c| c * SHADOW),
                (false, false) => b,
            };
            for c in 0..3 {
                plate[3 * i + c] = b[c].round() as u8;
                image[3 * i + c] = seen[c].round() as u8;
            }
        }
        (plate, image)
    }

    fn pixel_of(cam: &Pinhole, g: DVec3) -> usize {
        let (u, v) = cam.pixel(g).expect("in view");
        (v * SIZE + u) as usize
    }

    #[test]
    fn a_shadow_is_witnessed_alike_an_object_of_its_tone_is_not_and_occluded_views_abstain() {
        let cams: Vec<Pinhole> = [0.0f64, 2.1, 4.2]
            .iter()
            .map(|a| look_at(DVec3::new(1.0 * a.cos(), 1.0, 1.0 * a.sin())))
            .collect();
        let pictures: Vec<(Vec<u8>, Vec<u8>)> = cams
            .iter()
            .enumerate()
            .map(|(k, c)| render(c, k == 0))
            .collect();
        let views: Vec<View<'_>> = cams
            .iter()
            .zip(&pictures)
            .map(|(c, (plate, image))| View {
                camera: *c,
                image: RgbImageView::new(image, SIZE as usize, SIZE as usize).unwrap(),
                plate: RgbImageView::new(plate, SIZE as usize, SIZE as usize).unwrap(),
            })
            .collect();
        let proven = vec![false; (SIZE * SIZE) as usize];
        let p = MultiViewParams::default();
        let empty = Hull::from_occupancy(DVec3::splat(5.0), 0.05, UVec3::ONE, vec![false]);
        let of =
            |g: DVec3, hull: &Hull| witnesses(0, pixel_of(&cams[0], g), &views, &proven, hull, &p);

        // The shadow: both other views see the ground behind the pixel dimmed the same way.
        let shadow = DVec3::new(-0.06, 0.0, 0.0);
        assert_eq!(
            of(shadow, &empty),
            Witnesses {
                agree: 2,
                disagree: 0
            }
        );
        // The object of the shadow's mean tone, in front of the shadowed ground: its texture
        // is not the dimmed floor's, and both views say so.
        let object = DVec3::new(0.04, 0.0, 0.0);
        assert_eq!(
            of(object, &empty),
            Witnesses {
                agree: 0,
                disagree: 2
            }
        );
        // A kept voxel between camera 1 and the shadowed point: camera 1 abstains.
        let mid = 0.5 * (cams[1].centre_world + shadow);
        let wall = Hull::from_occupancy(mid - DVec3::splat(0.05), 0.1, UVec3::ONE, vec![true]);
        assert_eq!(
            of(shadow, &wall),
            Witnesses {
                agree: 1,
                disagree: 0
            }
        );
        // A pixel on the image border has no block: no witness.
        assert_eq!(
            witnesses(0, 5, &views, &proven, &empty, &p),
            Witnesses::default()
        );
    }
}
