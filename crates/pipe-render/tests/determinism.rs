//! Results must be bit-identical whatever the rayon thread count: the forward writes each
//! pixel from one task, and the backward accumulates per-(tile, Gaussian) gradients into a
//! buffer parallel to the tile lists that is reduced per Gaussian in tile order. A scene of
//! 3000 anchor-workload Gaussians (SH degree 2) at 96×80 spans several bands and several
//! projection chunks; it is rendered and differentiated in local pools of 1, 2 and 3
//! threads and every output compared bit for bit; the same scene under a deformation (`F`
//! and an SH rotation per Gaussian) in pools of 1 and 2 threads.

mod common;

use common::{Rng, anchor_scene, simple_camera};
use pipe_render::{Deformation, Gaussians, RenderOptions, backward, render};

/// Per Gaussian a deformation gradient near the identity and a (non-orthonormal, which the
/// renderer accepts) SH rotation, row-major.
fn deformation(n: usize) -> (Vec<[f32; 9]>, Vec<[f32; 9]>) {
    let mut rng = Rng(5);
    let mut near_identity = || {
        std::array::from_fn(|e| (if e % 4 == 0 { 1.0 } else { 0.0 }) + rng.range(-0.3, 0.3) as f32)
    };
    let f = (0..n).map(|_| near_identity()).collect();
    let r = (0..n).map(|_| near_identity()).collect();
    (f, r)
}

fn run(threads: usize, deformed: bool) -> (Vec<u32>, Vec<u32>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let cam = simple_camera::<f32>(96, 80, 50.0);
        let s = anchor_scene::<f32>(9000, 3, 2);
        let (f, r) = deformation(s.means.len());
        let g = Gaussians {
            deformation: deformed.then_some(Deformation {
                f: &f,
                sh_rotation: Some(&r),
            }),
            ..s.gaussians_sh()
        };
        let opts = RenderOptions {
            background: [0.1, 0.2, 0.3],
            eps2d: 0.3,
        };
        let out = render(&g, &cam, &opts).unwrap();
        let d: Vec<[f32; 3]> = (0..cam.n_pixels())
            .map(|i| [(i % 5) as f32 - 2.0, 0.5, -((i % 3) as f32)])
            .collect();
        let gr = backward(&g, &cam, &opts, &out, &d, Some(&out.alpha)).unwrap();
        let image: Vec<u32> = out
            .image
            .iter()
            .flatten()
            .chain(&out.alpha)
            .chain(&out.depth)
            .map(|v| v.to_bits())
            .collect();
        let grads: Vec<u32> = gr
            .means
            .iter()
            .flatten()
            .chain(gr.log_scales.iter().flatten())
            .chain(gr.quats.iter().flatten())
            .chain(&gr.opacity_logits)
            .chain(gr.sh.iter().flatten())
            .chain(gr.means2d.iter().flatten())
            .chain(gr.deformation.iter().flatten())
            .chain(gr.sh_rotation.iter().flatten())
            .map(|v| v.to_bits())
            .collect();
        (image, grads)
    })
}

#[test]
fn same_bits_for_1_2_3_threads() {
    let one = run(1, false);
    assert!(one.1.iter().any(|&b| b != 0));
    assert!(one == run(2, false), "2 threads differ from 1");
    assert!(one == run(3, false), "3 threads differ from 1");
}

#[test]
fn deformed_same_bits_for_1_2_threads() {
    let one = run(1, true);
    assert!(one.1.iter().any(|&b| b != 0));
    assert!(
        one != run(1, false),
        "the deformation must change the render"
    );
    assert!(one == run(2, true), "2 threads differ from 1");
}
