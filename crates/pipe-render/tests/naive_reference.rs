//! The tiled, row-span, lane-batched blend against a literal per-pixel reference loop.
//!
//! The kernel skips, per splat, every pixel outside a widened `α >= 1/255` ellipse and
//! evaluates the rest in branch-free batches; this must never drop a contribution. The
//! reference here walks, for every pixel, all visible Gaussians in global depth order
//! (restricted to those whose tile rectangle contains the pixel's tile, as 3DGS does) with
//! the fixture README's rules, in f64 on the kernel's own projection. Scenes are chosen to
//! stress the pixel-region bounds: needle-like Gaussians (axis ratios up to 200:1, random
//! rotations), opacities up to 0.999, and enough overlap that many pixels reach the
//! `T < 1e-4` stop. The per-pixel decisions are the same, so n_contrib must match exactly and
//! image and alpha to 1e-12.

mod common;

use common::{Rng, Scene, simple_camera};
use pipe_render::{ALPHA_MAX, ALPHA_MIN, RenderOptions, T_MIN, TILE, render};

fn needle_scene(n: usize, seed: u64) -> Scene<f64> {
    let mut rng = Rng(seed);
    let mut s = common::anchor_scene::<f64>(n, seed, 0);
    for i in 0..n {
        s.means[i] = [
            rng.range(-1.0, 1.0),
            rng.range(-0.8, 0.8),
            rng.range(2.0, 4.0),
        ];
        let long = rng.range(0.05, 0.6);
        let ratio = rng.range(1.0, 200.0);
        s.log_scales[i] = [
            long.ln(),
            (long / ratio).ln(),
            (long / rng.range(1.0, ratio)).ln(),
        ];
        let o: f64 = if i % 7 == 0 {
            0.999
        } else {
            rng.range(0.05, 0.95)
        };
        s.logits[i] = (o / (1.0 - o)).ln();
    }
    s
}

#[test]
fn tiled_blend_equals_per_pixel_loop() {
    let cam = simple_camera::<f64>(80, 60, 60.0);
    let opts = RenderOptions {
        background: [0.3, 0.1, 0.7],
        eps2d: 0.3,
    };
    let mut stopped_total = 0;
    for seed in 1..=3 {
        let s = needle_scene(400, seed);
        let out = render(&s.gaussians_rgb(), &cam, &opts).unwrap();
        let p = &out.projected;
        let mut order: Vec<usize> = (0..p.len()).filter(|&i| p[i].visible()).collect();
        order.sort_by(|&a, &b| p[a].depth.total_cmp(&p[b].depth).then(a.cmp(&b)));
        for j in 0..cam.height as usize {
            for i in 0..cam.width as usize {
                let (tx, ty) = ((i / TILE as usize) as u32, (j / TILE as usize) as u32);
                let (px, py) = (i as f64 + 0.5, j as f64 + 0.5);
                let mut t = 1.0;
                let mut rgb = [0.0; 3];
                let mut n = 0u32;
                for &g in &order {
                    let q = &p[g];
                    let [x0, y0, x1, y1] = q.tile_rect;
                    if !(x0 <= tx && tx < x1 && y0 <= ty && ty < y1) {
                        continue;
                    }
                    let (dx, dy) = (q.mean2d[0] - px, q.mean2d[1] - py);
                    let [a, b, c] = q.conic;
                    let power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy;
                    if power > 0.0 {
                        continue;
                    }
                    let alpha = (q.opacity * power.exp()).min(ALPHA_MAX);
                    if alpha < ALPHA_MIN {
                        continue;
                    }
                    let test_t = t * (1.0 - alpha);
                    if test_t < T_MIN {
                        stopped_total += 1;
                        break;
                    }
                    for (acc, col) in rgb.iter_mut().zip(q.color) {
                        *acc += col * alpha * t;
                    }
                    t = test_t;
                    n += 1;
                }
                let k = j * cam.width as usize + i;
                assert_eq!(out.n_contrib[k], n, "seed {seed} pixel ({i}, {j})");
                for ((got, acc), bg) in out.image[k].iter().zip(rgb).zip(opts.background) {
                    assert!(
                        (got - (acc + t * bg)).abs() < 1e-12,
                        "seed {seed} pixel ({i}, {j})"
                    );
                }
                assert!((out.alpha[k] - (1.0 - t)).abs() < 1e-12);
            }
        }
    }
    assert!(
        stopped_total > 100,
        "the scenes must exercise the T < 1e-4 stop ({stopped_total})"
    );
}
