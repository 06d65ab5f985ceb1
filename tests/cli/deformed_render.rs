//! The rasterizer's native deformed Gaussians (`pipe_render::Deformation`: covariance
//! `F Σ Fᵀ`, SH evaluated at `Rᵀ·d`) against the baked path of `pipe::scene::deform`
//! (new scales and quaternion from an SVD of `F R(q) diag(s)`, SH coefficients re-fitted to
//! the turned function), which `pipe simulate --splats` writes. Both are PhysGaussian §4.1 for
//! the same positions, `F` and `R` = the polar rotation of `F`, so they must render the same
//! image up to f32 rounding: per visible Gaussian the 2D covariance within 1e-5 of its size
//! and the colour within 1e-5, the image within 1e-4 (measured: 1.1e-6, 4.8e-7, 4.8e-7).
//!
//! Scene: 400 Gaussians of SH degree 3 in a 1 m blob, each moved and deformed by its own
//! `F = Q·(I + shear)·diag(stretch)` (rotations up to π, shears up to 0.4, stretches
//! 0.5–1.8), seen by a tilted 128×128 camera.

use glam::{DMat3, DQuat, DVec3};
use pipe::scene::deform::deform;
use pipe::scene::gaussians::{Gaussians, sh_coeffs};
use pipe::scene::splat::render_gaussians;
use pipe_mpm::svd::polar_rotation;

/// SplitMix64, uniform in [lo, hi).
struct Rng(u64);

impl Rng {
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        let u = ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * u
    }
    fn unit(&mut self) -> DVec3 {
        loop {
            let v = DVec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            if v.length_squared() > 0.01 && v.length_squared() < 1.0 {
                return v.normalize();
            }
        }
    }
}

/// A camera 3 m from the origin, looking at it from above and to the side.
fn camera() -> pipe_render::Camera<f32> {
    let eye = DVec3::new(1.2, -1.5, -2.3);
    let forward = (-eye).normalize();
    let right = forward.cross(DVec3::Y).normalize();
    let down = forward.cross(right);
    // camera_from_world rows: the camera axes (x right, y down, z forward) in world.
    let rows = [right, down, forward];
    let t = rows.map(|r| -r.dot(eye));
    let f = 64.0 / (25f64).to_radians().tan();
    pipe_render::Camera {
        camera_from_world_rotation: rows.map(|r| r.to_array().map(|v| v as f32)),
        camera_from_world_translation: t.map(|v| v as f32),
        fx: f as f32,
        fy: f as f32,
        cx: 64.0,
        cy: 64.0,
        width: 128,
        height: 128,
        near: 0.01,
    }
}

fn row_major(m: &DMat3) -> [f32; 9] {
    m.transpose().to_cols_array().map(|v| v as f32)
}

#[test]
fn native_deformation_renders_as_the_baked_svd_path() {
    let n = 400;
    let degree = 3u8;
    let mut rng = Rng(2024);
    let k = sh_coeffs(degree);
    let g = Gaussians {
        sh_degree: degree,
        id: (0..n as u32).collect(),
        position: (0..n)
            .map(|_| std::array::from_fn(|_| rng.range(-0.5, 0.5) as f32))
            .collect(),
        log_scale: (0..n)
            .map(|_| std::array::from_fn(|_| rng.range(0.02f64.ln(), 0.07f64.ln()) as f32))
            .collect(),
        rotation: (0..n)
            .map(|_| {
                let q = DQuat::from_axis_angle(rng.unit(), rng.range(0.0, 3.1));
                [q.w, q.x, q.y, q.z].map(|v| v as f32)
            })
            .collect(),
        opacity_logit: (0..n).map(|_| rng.range(-1.0, 2.0) as f32).collect(),
        sh: (0..n * k * 3)
            .map(|e| {
                let s = if e % (3 * k) < 3 { 1.0 } else { 0.4 };
                (s * rng.range(-1.0, 1.0)) as f32
            })
            .collect(),
        simulated: vec![true; n],
    };
    let x: Vec<DVec3> = g
        .position
        .iter()
        .map(|p| DVec3::from_array(p.map(f64::from)) + 0.1 * rng.unit())
        .collect();
    let f: Vec<DMat3> = (0..n)
        .map(|_| {
            let q = DMat3::from_quat(DQuat::from_axis_angle(
                rng.unit(),
                rng.range(0.0, std::f64::consts::PI),
            ));
            let mut shear = DMat3::IDENTITY;
            for (i, j) in [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)] {
                shear.col_mut(j)[i] = rng.range(-0.4, 0.4);
            }
            let stretch = DVec3::new(
                rng.range(0.5, 1.8),
                rng.range(0.5, 1.8),
                rng.range(0.5, 1.8),
            );
            q * shear * DMat3::from_diagonal(stretch)
        })
        .collect();
    assert!(f.iter().all(|f| f.determinant() > 0.0));

    let cam = camera();
    let opts = pipe_render::RenderOptions {
        background: [1.0, 1.0, 1.0],
        eps2d: 0.3,
    };
    let baked = deform(&g, &x, &f);
    let want = pipe_render::render(&render_gaussians(&baked), &cam, &opts).unwrap();

    let means: Vec<[f32; 3]> = x.iter().map(|p| p.as_vec3().to_array()).collect();
    let f_rows: Vec<[f32; 9]> = f.iter().map(row_major).collect();
    let r_rows: Vec<[f32; 9]> = f.iter().map(|f| row_major(&polar_rotation(f))).collect();
    let native = pipe_render::Gaussians {
        means: &means,
        deformation: Some(pipe_render::Deformation {
            f: &f_rows,
            sh_rotation: Some(&r_rows),
        }),
        ..render_gaussians(&g)
    };
    let got = pipe_render::render(&native, &cam, &opts).unwrap();

    // Per Gaussian: the same footprint (2D covariance, relative to its size) and colour.
    let visible = got.projected.iter().filter(|p| p.visible()).count();
    assert!(
        visible > n * 3 / 4,
        "only {visible} of {n} Gaussians visible"
    );
    let (mut cov_err, mut colour_err) = (0.0f64, 0.0f64);
    for (i, (a, b)) in got.projected.iter().zip(&want.projected).enumerate() {
        assert_eq!(a.visible(), b.visible(), "Gaussian {i}");
        if !a.visible() {
            continue;
        }
        let size = f64::from(b.cov2d[0].max(b.cov2d[2]));
        for (u, v) in a.cov2d.iter().zip(&b.cov2d) {
            cov_err = cov_err.max(f64::from(u - v).abs() / size);
        }
        for (u, v) in a.color.iter().zip(&b.color) {
            colour_err = colour_err.max(f64::from(u - v).abs());
        }
    }
    // The image.
    let diffs: Vec<f64> = got
        .image
        .as_flattened()
        .iter()
        .zip(want.image.as_flattened())
        .map(|(u, v)| f64::from(u - v).abs())
        .collect();
    let max = diffs.iter().copied().fold(0.0, f64::max);
    let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
    let covered = got.alpha.iter().filter(|&&a| a > 0.5).count();
    println!(
        "{visible} visible, {covered} px with alpha > 0.5; cov2d max rel err {cov_err:.1e}, \
         colour max err {colour_err:.1e}; image max |Δ| {max:.1e}, mean |Δ| {mean:.1e}"
    );
    assert!(
        covered > 2000,
        "the blob must cover the image: {covered} px"
    );
    assert!(
        cov_err < 1e-4,
        "2D covariance: max relative error {cov_err:e}"
    );
    assert!(colour_err < 1e-4, "colour: max error {colour_err:e}");
    assert!(max < 1e-3, "image: max |Δ| {max:e}");
}
