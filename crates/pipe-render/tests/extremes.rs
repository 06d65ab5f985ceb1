//! Degenerate and extreme inputs must render and differentiate without NaN, Inf or panic,
//! and invalid inputs must fail with a typed error naming the field.
//!
//! Scenes: zero and huge scales, opacity exactly 0 and 1 (logits ±inf), zero and
//! non-finite quaternions, Gaussians behind the camera, exactly on the near plane and at the
//! camera centre, far outside the image, a 1×1 image, and 10⁶ Gaussians in one tile (the
//! per-tile list, sort and gradient buffers at scale). Every output and gradient is checked
//! to be finite; culled Gaussians must have zero gradients.

mod common;

use common::{Rng, anchor_scene, simple_camera};
use pipe_render::{
    Camera, Colors, Gaussians, Opacities, RenderError, RenderOptions, Scales, backward, render,
};

fn all_finite(out: &pipe_render::Rendered<f32>, gr: &pipe_render::Gradients<f32>) {
    let it = out
        .image
        .iter()
        .flatten()
        .chain(&out.alpha)
        .chain(&out.depth)
        .chain(gr.means.iter().flatten())
        .chain(gr.scales.iter().flatten())
        .chain(gr.log_scales.iter().flatten())
        .chain(gr.quats.iter().flatten())
        .chain(&gr.opacities)
        .chain(&gr.opacity_logits)
        .chain(gr.colors.iter().flatten())
        .chain(gr.sh.iter().flatten())
        .chain(gr.means2d.iter().flatten())
        .chain(gr.conics.iter().flatten());
    for v in it {
        assert!(v.is_finite(), "non-finite output {v}");
    }
    for (p, m) in out.projected.iter().zip(&gr.means) {
        if !p.visible() {
            assert_eq!(*m, [0.0; 3]);
        }
    }
}

fn render_and_grad(
    g: &Gaussians<'_, f32>,
    cam: &Camera<f32>,
) -> (pipe_render::Rendered<f32>, pipe_render::Gradients<f32>) {
    let opts = RenderOptions {
        background: [0.3, 0.2, 0.1],
        eps2d: 0.3,
    };
    let out = render(g, cam, &opts).unwrap();
    let d: Vec<[f32; 3]> = (0..cam.n_pixels())
        .map(|i| [1.0, -0.5, (i % 7) as f32 * 0.1])
        .collect();
    let da: Vec<f32> = vec![0.25; cam.n_pixels()];
    let gr = backward(g, cam, &opts, &out, &d, Some(&da)).unwrap();
    all_finite(&out, &gr);
    (out, gr)
}

#[test]
fn degenerate_gaussians() {
    let cam = simple_camera::<f32>(64, 48, 50.0);
    let inf = f32::INFINITY;
    let means = vec![
        [0.0, 0.0, 3.0],    // zero scale
        [0.1, 0.0, 3.0],    // huge scale (covers everything)
        [0.0, 0.1, 3.0],    // scale so large the covariance overflows
        [0.2, 0.1, 3.0],    // opacity 0
        [0.0, 0.2, 2.0],    // opacity 1
        [0.1, 0.1, 3.0],    // zero quaternion
        [0.1, 0.2, 3.0],    // NaN quaternion
        [0.0, 0.0, -2.0],   // behind the camera
        [0.0, 0.0, 0.01],   // exactly on the near plane
        [0.0, 0.0, 0.0],    // at the camera centre
        [500.0, 0.0, 3.0],  // far outside the image
        [0.0, -0.1, 1e6],   // very far away
        [0.3, 0.3, 0.0101], // just in front of the near plane
        [0.0, 0.0, 3.0],    // scale 3e6 m: conic ~1e-16, still visible
    ];
    let n = means.len();
    let mut log_scales = vec![[(0.05f32).ln(); 3]; n];
    log_scales[0] = [-inf, -inf, -inf];
    log_scales[1] = [(1e3f32).ln(); 3];
    log_scales[2] = [80.0; 3];
    log_scales[13] = [(3e6f32).ln(); 3];
    let mut quats = vec![[1.0, 0.0, 0.0, 0.0]; n];
    quats[5] = [0.0; 4];
    quats[6] = [f32::NAN, 0.0, 0.0, 1.0];
    let mut logits = vec![0.5f32; n];
    logits[3] = -inf;
    logits[4] = inf;
    let rgb = vec![[0.5f32, 0.6, 0.7]; n];
    let g = Gaussians {
        means: &means,
        scales: Scales::Log(&log_scales),
        quats: &quats,
        opacities: Opacities::Logit(&logits),
        colors: Colors::Rgb(&rgb),
        deformation: None,
    };
    let (out, _) = render_and_grad(&g, &cam);
    let vis: Vec<bool> = out.projected.iter().map(|p| p.visible()).collect();
    assert!(
        vis[0] && vis[1] && vis[4],
        "zero-scale, huge and opaque Gaussians render: {vis:?}"
    );
    for i in [2, 5, 6, 7, 8, 9, 10] {
        assert!(!vis[i], "Gaussian {i} must be culled");
    }
    // With linear parameters too (opacity exactly 0 and 1, scale exactly 0).
    let scales: Vec<[f32; 3]> = log_scales.iter().map(|s| s.map(f32::exp)).collect();
    let opac: Vec<f32> = logits.iter().map(|&l| pipe_render::sigmoid(l)).collect();
    assert_eq!((opac[3], opac[4], scales[0]), (0.0, 1.0, [0.0; 3]));
    let g = Gaussians {
        scales: Scales::Linear(&scales),
        opacities: Opacities::Linear(&opac),
        ..g
    };
    render_and_grad(&g, &cam);
}

#[test]
fn one_pixel_image() {
    let cam = simple_camera::<f32>(1, 1, 50.0);
    let s = anchor_scene::<f32>(200, 5, 3);
    let (out, _) = render_and_grad(&s.gaussians_sh(), &cam);
    assert_eq!(out.image.len(), 1);
    let (out, _) = render_and_grad(&s.gaussians_rgb(), &cam);
    assert!(out.alpha[0] > 0.0);
}

#[test]
fn many_gaussians_in_one_tile() {
    let n = 1_000_000;
    let cam = simple_camera::<f32>(16, 16, 50.0);
    let mut rng = Rng(11);
    let mut s = anchor_scene::<f32>(n, 7, 0);
    for ((m, o), ls) in s.means.iter_mut().zip(&mut s.logits).zip(&mut s.log_scales) {
        *m = [
            rng.range(-0.5, 0.5) as f32,
            rng.range(-0.5, 0.5) as f32,
            rng.range(3.0, 5.0) as f32,
        ];
        *ls = [(0.6f32).ln(); 3]; // each covers most of the 16x16 tile
        *o = -4.0; // opacity 0.018: thousands of contributors before T < 1e-4
    }
    let (out, gr) = render_and_grad(&s.gaussians_rgb(), &cam);
    assert_eq!(out.bins.offsets.len(), 2);
    assert!(
        out.bins.n_intersections() > 750_000,
        "{}",
        out.bins.n_intersections()
    );
    assert!(out.n_contrib[8 * 16 + 8] > 500, "{:?}", out.n_contrib);
    assert!(gr.means2d.iter().any(|g| g[0] != 0.0));
}

#[test]
fn invalid_input_is_a_typed_error() {
    let cam = simple_camera::<f32>(8, 8, 50.0);
    let s = anchor_scene::<f32>(4, 1, 2);
    let opts = RenderOptions::default();
    let mut g = s.gaussians_sh();
    g.quats = &s.quats[..3];
    assert_eq!(
        render(&g, &cam, &opts).unwrap_err(),
        RenderError::Length {
            field: "quats",
            expected: 4,
            got: 3
        }
    );
    let g = Gaussians {
        colors: Colors::Sh {
            degree: 4,
            coeffs: &s.sh,
        },
        ..s.gaussians_sh()
    };
    assert_eq!(
        render(&g, &cam, &opts).unwrap_err(),
        RenderError::ShDegree(4)
    );
    let g = Gaussians {
        colors: Colors::Sh {
            degree: 3,
            coeffs: &s.sh,
        },
        ..s.gaussians_sh()
    };
    assert!(matches!(
        render(&g, &cam, &opts),
        Err(RenderError::Length {
            field: "sh",
            expected: 64,
            got: 36
        })
    ));
    let bad = Camera { width: 0, ..cam };
    assert!(matches!(
        render(&s.gaussians_rgb(), &bad, &opts),
        Err(RenderError::ImageSize { width: 0, .. })
    ));
    let bad = Camera {
        fx: f32::NAN,
        ..cam
    };
    assert!(matches!(
        render(&s.gaussians_rgb(), &bad, &opts),
        Err(RenderError::Value { field: "fx", .. })
    ));
    let bad = Camera { near: 0.0, ..cam };
    assert!(matches!(
        render(&s.gaussians_rgb(), &bad, &opts),
        Err(RenderError::Value { field: "near", .. })
    ));
    let out = render(&s.gaussians_rgb(), &cam, &opts).unwrap();
    let d = vec![[0.0f32; 3]; 10];
    let err = backward(&s.gaussians_rgb(), &cam, &opts, &out, &d, None).unwrap_err();
    assert_eq!(
        err,
        RenderError::Length {
            field: "d_image",
            expected: 64,
            got: 10
        }
    );
    let msg = err.to_string();
    assert!(
        msg.contains("d_image") && msg.contains("64") && msg.contains("10"),
        "{msg}"
    );
}
