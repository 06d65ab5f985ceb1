//! Arrows drawn over a render where and how a force acts (the seed paper's fig. 5): each
//! arrow points along the force, its tip on the face of the pushed material it meets first,
//! its length in proportion to the force's size (the largest of the edit's forces, or
//! impulses, gets `reach`).

use glam::DVec3;

use crate::io::image::Rgb8;
use crate::scene::camera::Camera;

/// An arrow in the world (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrow {
    /// Where it starts.
    pub tail: DVec3,
    /// Where it points to.
    pub tip: DVec3,
    /// Its colour.
    pub color: [u8; 3],
}

/// Red: forces.
pub const FORCE_COLOR: [u8; 3] = [230, 30, 30];
/// Orange: impulses.
pub const IMPULSE_COLOR: [u8; 3] = [255, 150, 0];

impl Arrow {
    /// The arrow of a push `direction` (any length) on particles at `x` (m): its tip on the
    /// face of their set the push enters (the farthest point against it, through their
    /// centre `centre`), its length `length` (m).
    pub fn onto(x: &[DVec3], centre: DVec3, direction: DVec3, length: f64, color: [u8; 3]) -> Self {
        let d = direction.normalize_or_zero();
        let back = x.iter().map(|p| (*p - centre).dot(-d)).fold(0.0, f64::max);
        let tip = centre - d * back;
        Self {
            tail: tip - d * length,
            tip,
            color,
        }
    }

    /// Draws the arrow as `camera` sees it into `img` (its size); parts behind the camera
    /// are left out.
    pub fn draw(&self, camera: &Camera, img: &mut Rgb8) {
        let (Some(a), Some(b)) = (camera.project(self.tail), camera.project(self.tip)) else {
            return;
        };
        let (a, b) = ((a.0, a.1), (b.0, b.1));
        let width = (f64::from(img.height.min(img.width)) / 110.0).max(1.0);
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len = (dx * dx + dy * dy).sqrt();
        // The head: two strokes 28° off the shaft, a quarter of its length (4 widths at least).
        let head = (0.28 * len).max(4.0 * width).min(len);
        let (ux, uy) = if len > 0.0 {
            (dx / len, dy / len)
        } else {
            (0.0, 1.0)
        };
        let (c, s) = (28f64.to_radians().cos(), 28f64.to_radians().sin());
        let wing = |sign: f64| {
            let (wx, wy) = (-ux * c - sign * uy * s, -uy * c + sign * ux * s);
            (b.0 + head * wx, b.1 + head * wy)
        };
        let strokes = [(a, b), (b, wing(1.0)), (b, wing(-1.0))];
        // A dark outline first, so the arrow reads over any colour.
        for (p, q) in strokes {
            stroke(img, p, q, width + 1.0, [20, 20, 20]);
        }
        for (p, q) in strokes {
            stroke(img, p, q, width, self.color);
        }
    }
}

/// A segment of half-width `r` (pixels) from `p` to `q` (pixel coordinates, pixel `(i, j)`
/// centred at `(i + 0.5, j + 0.5)`).
fn stroke(img: &mut Rgb8, p: (f64, f64), q: (f64, f64), r: f64, color: [u8; 3]) {
    let (w, h) = (img.width as i64, img.height as i64);
    let x0 = (p.0.min(q.0) - r).floor().max(0.0) as i64;
    let x1 = (p.0.max(q.0) + r).ceil().min(w as f64) as i64;
    let y0 = (p.1.min(q.1) - r).floor().max(0.0) as i64;
    let y1 = (p.1.max(q.1) + r).ceil().min(h as f64) as i64;
    let (dx, dy) = (q.0 - p.0, q.1 - p.1);
    let l2 = dx * dx + dy * dy;
    for y in y0.max(0)..y1.min(h) {
        for x in x0.max(0)..x1.min(w) {
            let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
            let t = if l2 > 0.0 {
                (((cx - p.0) * dx + (cy - p.1) * dy) / l2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (ex, ey) = (cx - (p.0 + t * dx), cy - (p.1 + t * dy));
            if ex * ex + ey * ey <= r * r {
                let i = 3 * (y * w + x) as usize;
                img.data[i..i + 3].copy_from_slice(&color);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::edit::cameras::look_at;

    #[test]
    fn a_downward_arrow_ends_on_the_top_face_and_is_drawn_above_it() {
        // Particles filling y in [0, 1].
        let x: Vec<DVec3> = (0..=10)
            .map(|i| DVec3::new(0.0, i as f64 * 0.1, 0.0))
            .collect();
        let arrow = Arrow::onto(&x, DVec3::new(0.0, 0.5, 0.0), -DVec3::Y, 0.5, FORCE_COLOR);
        assert!((arrow.tip - DVec3::Y).length() < 1e-12);
        assert!((arrow.tail - DVec3::new(0.0, 1.5, 0.0)).length() < 1e-12);
        let cam = look_at(
            DVec3::new(0.0, 1.0, 5.0),
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::Y,
            [100, 100],
            100.0,
        );
        let mut img = Rgb8 {
            width: 100,
            height: 100,
            data: vec![255; 30_000],
        };
        arrow.draw(&cam, &mut img);
        let px = |x: usize, y: usize| &img.data[3 * (y * 100 + x)..3 * (y * 100 + x) + 3];
        // The shaft runs down the middle column above the tip (row 50), nothing below it.
        assert_eq!(px(50, 45), &FORCE_COLOR);
        assert_eq!(px(50, 42), &FORCE_COLOR);
        assert_eq!(px(50, 60), &[255, 255, 255]);
        assert_eq!(px(10, 45), &[255, 255, 255]);
    }
}
