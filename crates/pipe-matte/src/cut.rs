//! Binary labelling of an image by a minimum graph cut (Boykov & Jolly, ICCV 2001):
//! minimises `E(L) = Σ_p D_p(L_p) + Σ_{p~q} w_pq [L_p ≠ L_q]` over object/background labels,
//! with 8-connected contrast-sensitive Potts weights
//! `w_pq = λ / |p − q| · exp(−β ‖I_p − I_q‖²)`, `β = 1 / (2 ⟨‖I_p − I_q‖²⟩)` (the image's mean
//! squared neighbour difference, as in GrabCut): cutting along an image edge is cheap, across
//! a flat region dear.

use crate::maxflow::MaxFlow;
use crate::view::RgbImageView;

/// Fixed-point scale of the costs handed to the integer max-flow.
const SCALE: f32 = 1024.0;

/// Per-pixel costs of the two labels (row-major; any finite values ≥ 0).
#[derive(Debug, Clone)]
pub(crate) struct Unary {
    /// Cost of labelling the pixel object.
    pub object: Vec<f32>,
    /// Cost of labelling the pixel background.
    pub background: Vec<f32>,
}

/// The 8-neighbour offsets to the right and below (each pair once) and their distance.
const FORWARD: [(isize, isize, f32); 4] = [
    (1, 0, 1.0),
    (0, 1, 1.0),
    (1, 1, std::f32::consts::SQRT_2),
    (-1, 1, std::f32::consts::SQRT_2),
];

fn colour_distance2(d: &[u8], p: usize, q: usize) -> f32 {
    (0..3)
        .map(|c| {
            let e = f32::from(d[3 * p + c]) - f32::from(d[3 * q + c]);
            e * e
        })
        .sum()
}

/// The labelling of minimum energy (`true` = object); `unary` has one entry per pixel of
/// `image`, `lambda` ≥ 0 weighs the smoothness term against the unary costs.
pub(crate) fn segment(image: &RgbImageView<'_>, unary: &Unary, lambda: f32) -> Vec<bool> {
    let (w, h) = (image.width(), image.height());
    let n = w * h;
    debug_assert!(unary.object.len() == n && unary.background.len() == n);
    let d = image.data();
    let pairs = || {
        (0..h).flat_map(move |y| {
            (0..w).flat_map(move |x| {
                FORWARD.iter().filter_map(move |&(dx, dy, len)| {
                    let (qx, qy) = (x as isize + dx, y as isize + dy);
                    (qx >= 0 && (qx as usize) < w && (qy as usize) < h)
                        .then(|| (y * w + x, qy as usize * w + qx as usize, len))
                })
            })
        })
    };
    let (mut sum, mut count) = (0f64, 0usize);
    for (p, q, _) in pairs() {
        sum += f64::from(colour_distance2(d, p, q));
        count += 1;
    }
    let beta = if sum > 0.0 {
        (count as f64 / (2.0 * sum)) as f32
    } else {
        0.0
    };
    let quantise = |c: f32| (c.max(0.0) * SCALE).round() as i64;
    let mut g = MaxFlow::new(n);
    for p in 0..n {
        g.add_terminal(p, quantise(unary.background[p]), quantise(unary.object[p]));
    }
    for (p, q, len) in pairs() {
        let c = quantise(lambda / len * (-beta * colour_distance2(d, p, q)).exp());
        if c > 0 {
            g.add_edge(p, q, c, c);
        }
    }
    g.solve();
    (0..n).map(|p| g.source_side(p)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smoothness_fills_a_weak_region_bounded_by_edges() {
        // A 12x12 grey image; a bright 6x6 square whose left half is proven object and whose
        // right half has no evidence either way: the cut follows the square's edges.
        let (w, h) = (12, 12);
        let inside = |x: usize, y: usize| (3..9).contains(&x) && (3..9).contains(&y);
        let mut rgb = Vec::new();
        let mut unary = Unary {
            object: vec![0.0; w * h],
            background: vec![0.0; w * h],
        };
        for y in 0..h {
            for x in 0..w {
                let v = if inside(x, y) { 200 } else { 60 };
                rgb.extend([v, v, v]);
                let p = y * w + x;
                if inside(x, y) && x < 6 {
                    unary.background[p] = 3.0;
                } else if inside(x, y) {
                    unary.object[p] = 0.1;
                } else {
                    unary.object[p] = 0.5;
                }
            }
        }
        let image = RgbImageView::new(&rgb, w, h).unwrap();
        let bits = segment(&image, &unary, 2.0);
        for y in 0..h {
            for x in 0..w {
                assert_eq!(bits[y * w + x], inside(x, y), "({x}, {y})");
            }
        }
        // Without smoothness each pixel takes its cheaper label.
        let bits = segment(&image, &unary, 0.0);
        assert!(!bits[5 * w + 7] && bits[5 * w + 4]);
    }
}
