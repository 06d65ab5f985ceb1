//! Deformed Gaussians ([`pipe_render::Deformation`]) beyond the finite-difference checks of
//! `finite_diff.rs`: the identity deformation changes nothing (image, depth, projection and
//! every gradient equal to the canonical render's, f32 and f64), and bad deformations are
//! typed errors (wrong lengths) or culled Gaussians with zero gradients (NaN or infinite `F`
//! or `R`), never a panic or a NaN in the outputs.

mod common;

use common::{Rng, Scene, anchor_scene, simple_camera};
use pipe_render::{
    Camera, Colors, Deformation, Gaussians, Gradients, Real, RenderError, RenderOptions, Rendered,
    backward, render,
};

const IDENTITY: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];

fn opts<T: Real>() -> RenderOptions<T> {
    RenderOptions {
        background: [0.1, 0.2, 0.3].map(T::from_f64),
        eps2d: T::from_f64(0.3),
    }
}

/// Renders and differentiates with pseudo-random image and alpha adjoints.
fn render_and_grad<T: Real>(g: &Gaussians<'_, T>, cam: &Camera<T>) -> (Rendered<T>, Gradients<T>) {
    let out = render(g, cam, &opts()).unwrap();
    let mut rng = Rng(17);
    let d: Vec<[T; 3]> = (0..cam.n_pixels())
        .map(|_| std::array::from_fn(|_| T::from_f64(rng.range(-1.0, 1.0))))
        .collect();
    let da: Vec<T> = (0..cam.n_pixels())
        .map(|_| T::from_f64(rng.range(-1.0, 1.0)))
        .collect();
    let gr = backward(g, cam, &opts(), &out, &d, Some(&da)).unwrap();
    (out, gr)
}

/// Every float a render and its gradients produce (except the new `F`/`R` gradients).
fn outputs<T: Real>(out: &Rendered<T>, gr: &Gradients<T>) -> Vec<T> {
    let proj = out.projected.iter().flat_map(|p| {
        p.mean2d
            .into_iter()
            .chain(p.conic)
            .chain(p.cov2d)
            .chain(p.color)
            .chain([p.depth, p.opacity])
    });
    out.image
        .iter()
        .flatten()
        .chain(&out.alpha)
        .chain(&out.depth)
        .copied()
        .chain(proj)
        .chain(gr.means.iter().flatten().copied())
        .chain(gr.scales.iter().flatten().copied())
        .chain(gr.log_scales.iter().flatten().copied())
        .chain(gr.quats.iter().flatten().copied())
        .chain(gr.opacities.iter().copied())
        .chain(gr.opacity_logits.iter().copied())
        .chain(gr.colors.iter().flatten().copied())
        .chain(gr.sh.iter().flatten().copied())
        .chain(gr.means2d.iter().flatten().copied())
        .chain(gr.conics.iter().flatten().copied())
        .collect()
}

fn identity_changes_nothing<T: Real>() {
    let cam = simple_camera::<T>(96, 80, 50.0);
    let s: Scene<T> = anchor_scene(3000, 21, 3);
    let n = s.means.len();
    let eye = vec![IDENTITY.map(T::from_f64); n];
    let canonical = s.gaussians_sh();
    let (out0, gr0) = render_and_grad(&canonical, &cam);
    assert!(gr0.deformation.is_empty() && gr0.sh_rotation.is_empty());
    for sh_rotation in [None, Some(&eye[..])] {
        let g = Gaussians {
            deformation: Some(Deformation {
                f: &eye,
                sh_rotation,
            }),
            ..canonical
        };
        let (out, gr) = render_and_grad(&g, &cam);
        assert_eq!(out.n_contrib, out0.n_contrib);
        assert_eq!(out.bins.ids, out0.bins.ids);
        assert_eq!(
            out.projected.iter().map(|p| p.radius).collect::<Vec<_>>(),
            out0.projected.iter().map(|p| p.radius).collect::<Vec<_>>()
        );
        let (a, b) = (outputs(&out, &gr), outputs(&out0, &gr0));
        assert_eq!(a.len(), b.len());
        let differing = a.iter().zip(&b).filter(|(x, y)| x != y).count();
        assert_eq!(differing, 0, "{differing} of {} values differ", a.len());
        // The new gradients exist and are not trivially zero.
        assert_eq!(gr.deformation.len(), n);
        assert!(gr.deformation.iter().flatten().any(|&v| v != T::ZERO));
        assert!(gr.deformation.iter().flatten().all(|v| v.is_finite()));
        match sh_rotation {
            None => assert!(gr.sh_rotation.is_empty()),
            Some(_) => {
                assert_eq!(gr.sh_rotation.len(), n);
                assert!(gr.sh_rotation.iter().flatten().any(|&v| v != T::ZERO));
            }
        }
    }
}

#[test]
fn identity_deformation_changes_nothing_f32() {
    identity_changes_nothing::<f32>();
}

#[test]
fn identity_deformation_changes_nothing_f64() {
    identity_changes_nothing::<f64>();
}

#[test]
fn deformation_lengths_are_typed_errors() {
    let cam = simple_camera::<f32>(16, 16, 50.0);
    let s = anchor_scene::<f32>(4, 1, 1);
    let eye = vec![IDENTITY.map(|v| v as f32); 4];
    let o = opts();
    let short_f = Gaussians {
        deformation: Some(Deformation {
            f: &eye[..3],
            sh_rotation: None,
        }),
        ..s.gaussians_sh()
    };
    let err = render(&short_f, &cam, &o).unwrap_err();
    assert_eq!(
        err,
        RenderError::Length {
            field: "deformation.f",
            expected: 4,
            got: 3
        }
    );
    assert!(err.to_string().contains("deformation.f"), "{err}");
    let short_r = Gaussians {
        deformation: Some(Deformation {
            f: &eye,
            sh_rotation: Some(&eye[..2]),
        }),
        ..s.gaussians_sh()
    };
    assert_eq!(
        render(&short_r, &cam, &o).unwrap_err(),
        RenderError::Length {
            field: "deformation.sh_rotation",
            expected: 4,
            got: 2
        }
    );
    // The backward validates the same way (a forward of the valid Gaussians, then a call
    // with mismatched ones).
    let good = Gaussians {
        deformation: Some(Deformation {
            f: &eye,
            sh_rotation: Some(&eye),
        }),
        ..s.gaussians_sh()
    };
    let out = render(&good, &cam, &o).unwrap();
    let d = vec![[1.0f32; 3]; cam.n_pixels()];
    assert!(backward(&good, &cam, &o, &out, &d, None).is_ok());
    assert!(matches!(
        backward(&short_r, &cam, &o, &out, &d, None),
        Err(RenderError::Length {
            field: "deformation.sh_rotation",
            ..
        })
    ));
    assert!(matches!(
        backward(&short_f, &cam, &o, &out, &d, None),
        Err(RenderError::Length {
            field: "deformation.f",
            ..
        })
    ));
}

/// Non-finite `F` or `R` culls the Gaussian (zero gradients everywhere, including `F` and
/// `R`); a singular `F` flattens it to the `eps2d` blur and it still renders; every output
/// stays finite.
#[test]
fn non_finite_deformations_are_culled() {
    let cam = simple_camera::<f32>(32, 32, 50.0);
    let n = 8;
    let mut s = anchor_scene::<f32>(n, 3, 2);
    for (i, m) in s.means.iter_mut().enumerate() {
        *m = [0.05 * i as f32 - 0.2, 0.02 * i as f32 - 0.1, 3.0];
    }
    s.log_scales = vec![[(0.08f32).ln(); 3]; n];
    let eye = IDENTITY.map(|v| v as f32);
    let mut f = vec![eye; n];
    let mut r = vec![eye; n];
    f[1][4] = f32::NAN;
    f[2][0] = f32::INFINITY;
    f[3] = [0.0; 9]; // singular: flattened to a point
    r[4][2] = f32::NAN;
    r[5][8] = f32::NEG_INFINITY;
    f[6] = [1e30; 9]; // Σ overflows
    let g = Gaussians {
        deformation: Some(Deformation {
            f: &f,
            sh_rotation: Some(&r),
        }),
        ..s.gaussians_sh()
    };
    let (out, gr) = render_and_grad(&g, &cam);
    let vis: Vec<bool> = out.projected.iter().map(|p| p.visible()).collect();
    assert_eq!(
        vis,
        [true, false, false, true, false, false, false, true],
        "which Gaussians render"
    );
    for v in outputs(&out, &gr)
        .iter()
        .chain(gr.deformation.iter().flatten())
        .chain(gr.sh_rotation.iter().flatten())
    {
        assert!(v.is_finite(), "non-finite output {v}");
    }
    for (i, &visible) in vis.iter().enumerate() {
        let zero = gr.means[i] == [0.0; 3]
            && gr.quats[i] == [0.0; 4]
            && gr.deformation[i] == [0.0; 9]
            && gr.sh_rotation[i] == [0.0; 9];
        assert_eq!(!visible, zero, "Gaussian {i}: zero gradients iff culled");
    }
    // With RGB colours the SH rotation is unused: a NaN there culls nothing.
    let g = Gaussians {
        colors: Colors::Rgb(&s.rgb),
        ..g
    };
    let (out, gr) = render_and_grad(&g, &cam);
    assert!(out.projected[4].visible() && out.projected[5].visible());
    assert!(gr.sh_rotation.iter().flatten().all(|&v| v == 0.0));
}
