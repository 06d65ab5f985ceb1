//! Does the plate's texture show through? A shadow keeps it, an object hides it.
//!
//! A shadow multiplies the floor by a smooth factor `s`: `ln I = ln s + ln B`, so a grout line
//! or a mottle of the plate shows in the image at its full contrast in log units. An object
//! replaces the floor: `ln I = ln O`, whatever `B` does behind it, so an object of the shadow's
//! own tone still differs here, by the texture it does *not* have. Per pixel, over the changed
//! pixels of the `(2r+1)²` window around it, both `ln(I + k)` and `ln(B + k)` (means over the
//! channels) are fitted by a plane in the pixel offsets (a penumbra's gradient and an object's
//! smooth shading are planes); where the pixel is itself a feature of the plate (its plate
//! residual `e_B` at least the window's residual standard deviation, itself at least
//! `√min_plate_variance`), the score is
//!
//! `r = e_I / e_B`, clamped to [−1, 2],
//!
//! near 1 where the plate's feature shows (shadow), near 0 where something hides it (object).
//! The ratio is read at the pixel itself, not over the window: a window that straddles the
//! object's outline would otherwise lend the object the shadow's texture.

use rayon::prelude::*;

use crate::view::RgbImageView;

/// Per pixel (row-major), the score `r` of the module doc over the window's pixels that `used`
/// admits, or `None` where the pixel itself is not used or is no feature of the plate, the
/// window holds fewer than 9 used pixels, `used` or `plate` does not match `image`'s size, or
/// the window does not fit in the image (`radius` ≥ 1 pixels; shrunk symmetrically near
/// the border, at least 1). `k` is the log-ratio offset.
pub(crate) fn plate_texture_shown(
    image: &RgbImageView<'_>,
    plate: &RgbImageView<'_>,
    used: &[bool],
    radius: usize,
    k: f32,
    min_plate_variance: f32,
) -> Vec<Option<f32>> {
    let (w, h) = (image.width(), image.height());
    let mut out = vec![None; w * h];
    if used.len() != w * h || (plate.width(), plate.height()) != (w, h) {
        return out;
    }
    let k = k.max(f32::MIN_POSITIVE);
    let log_mean = |d: &[u8]| -> Vec<f32> {
        d.chunks_exact(3)
            .map(|p| p.iter().map(|&c| (f32::from(c) + k).ln()).sum::<f32>() / 3.0)
            .collect()
    };
    let (li, lb) = (log_mean(image.data()), log_mean(plate.data()));
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let r = radius.min(x).min(y).min(w - 1 - x).min(h - 1 - y);
                if r == 0 || !used[y * w + x] {
                    continue;
                }
                *o = shown(&li, &lb, used, w, x, y, r, min_plate_variance);
            }
        });
    out
}

/// `r` at `(x, y)` (inside the image) from the planes fitted by least squares, over the pixels
/// of the window of radius `r` that `used` admits, to both log-intensities.
#[allow(clippy::too_many_arguments)]
fn shown(
    li: &[f32],
    lb: &[f32],
    used: &[bool],
    w: usize,
    x: usize,
    y: usize,
    r: usize,
    min_plate_variance: f32,
) -> Option<f32> {
    let ri = r as isize;
    let window = || {
        (-ri..=ri).flat_map(move |dy| {
            (-ri..=ri).filter_map(move |dx| {
                let p = (y as isize + dy) as usize * w + (x as isize + dx) as usize;
                used[p].then_some((p, [1.0f64, dx as f64, dy as f64]))
            })
        })
    };
    let mut a = [[0f64; 3]; 3];
    let (mut bi, mut bb) = ([0f64; 3], [0f64; 3]);
    let mut n = 0usize;
    for (p, f) in window() {
        n += 1;
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] += f[r] * f[c];
            }
            bi[r] += f[r] * f64::from(li[p]);
            bb[r] += f[r] * f64::from(lb[p]);
        }
    }
    if n < 9 {
        return None;
    }
    let inv = invert3(a)?;
    let solve = |b: [f64; 3]| -> [f64; 3] { (inv * glam::DVec3::from_array(b)).to_array() };
    let (ci, cb) = (solve(bi), solve(bb));
    let plane = |c: [f64; 3], f: [f64; 3]| c[0] * f[0] + c[1] * f[1] + c[2] * f[2];
    let vb = window()
        .map(|(p, f)| (f64::from(lb[p]) - plane(cb, f)).powi(2))
        .sum::<f64>()
        / n as f64;
    let centre = y * w + x;
    // The plane's value at the pixel itself (offset 0, 0) is its first coefficient.
    let (ei, eb) = (f64::from(li[centre]) - ci[0], f64::from(lb[centre]) - cb[0]);
    let sd = vb.sqrt();
    if !(vb >= f64::from(min_plate_variance) && vb > 0.0 && eb.abs() >= sd) {
        return None;
    }
    let score = (ei / eb).clamp(-1.0, 2.0) as f32;
    score.is_finite().then_some(score)
}

/// The inverse of a 3×3 matrix (rows), if it is not (nearly) singular.
fn invert3(m: [[f64; 3]; 3]) -> Option<glam::DMat3> {
    let mat = glam::DMat3::from_cols_array_2d(&m).transpose();
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    let det = mat.determinant();
    (det.is_finite() && det.abs() > 1e-9 * scale.powi(3)).then(|| mat.inverse())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plate of tiles with dark grout lines and a mottle, a copy of it dimmed by a penumbra on
    /// the left, and on the right an object of the shadow's mean tone with smooth shading.
    #[test]
    fn a_shadow_shows_the_plates_grout_an_object_of_its_tone_hides_it() {
        let (w, h) = (40usize, 20usize);
        let grout = |x: usize, y: usize| x.is_multiple_of(7) || y.is_multiple_of(7);
        let floor = |x: usize, y: usize| {
            150.0 + 10.0 * ((x as f32) * 0.9).sin() * ((y as f32) * 0.7).cos()
                - if grout(x, y) { 60.0 } else { 0.0 }
        };
        let (mut plate, mut image) = (Vec::new(), Vec::new());
        for y in 0..h {
            for x in 0..w {
                let b = floor(x, y);
                let seen = if x < 20 {
                    // Penumbra: the dimming falls from 0.9 to 0.33 across the half.
                    b * (0.9 - 0.0285 * x as f32)
                } else {
                    50.0 + 8.0 * (0.3 * x as f32).sin()
                };
                plate.extend([b.round() as u8; 3]);
                image.extend([seen.round().clamp(0.0, 255.0) as u8; 3]);
            }
        }
        let image = RgbImageView::new(&image, w, h).unwrap();
        let plate = RgbImageView::new(&plate, w, h).unwrap();
        let all = vec![true; w * h];
        let score = plate_texture_shown(&image, &plate, &all, 2, 4.0, 1e-3);
        assert_eq!(score.len(), w * h);
        let (mut shadow, mut object) = (0, 0);
        for y in 3..h - 3 {
            for x in 3..w - 3 {
                let Some(r) = score[y * w + x] else {
                    // Only the plate's features are scored.
                    assert!(!grout(x, y) || x == 20, "({x}, {y}) has no score");
                    continue;
                };
                assert!(r.is_finite() && (-1.0..=2.0).contains(&r));
                if grout(x, y) && x < 17 {
                    assert!(r > 0.8, "shadow ({x}, {y}): {r}");
                    shadow += 1;
                }
                if grout(x, y) && x > 23 {
                    assert!(r.abs() < 0.3, "object ({x}, {y}): {r}");
                    object += 1;
                }
            }
        }
        assert!(shadow > 10 && object > 10, "{shadow} {object}");
        // The image border has no window; a flat plate or too few used pixels give no score.
        assert!(score[0].is_none());
        let flat = vec![120u8; 3 * w * h];
        let flat = RgbImageView::new(&flat, w, h).unwrap();
        assert!(
            plate_texture_shown(&image, &flat, &all, 2, 4.0, 1e-3)
                .iter()
                .all(Option::is_none)
        );
        let none = vec![false; w * h];
        assert!(
            plate_texture_shown(&image, &plate, &none, 2, 4.0, 1e-3)
                .iter()
                .all(Option::is_none)
        );
    }
}
