//! Central finite-difference checks of every gradient of the f64 build of the rasterizer.
//!
//! Loss `L = Σ image·W + Σ alpha·W_a` with fixed random weights, so both the colour and the
//! alpha adjoints are exercised. Every parameter of every Gaussian is perturbed by ±1e-6
//! (f64) and `(L(+h) - L(-h))/2h` is compared with the hand-written backward:
//! `|fd - g| <= 1e-6·max|g_kind| + 1e-8` per parameter kind (means, log-scales or linear
//! scales, raw quaternions of non-unit length, opacity logits or activated opacities, RGB or
//! SH degree-3 coefficients). The scenes are chosen to hit the cases a per-pixel backward
//! gets wrong easily: Gaussians centred on and straddling 16-px tile borders (their lists
//! span several tiles, so the per-tile gradient reduction is exercised), heavy overlap at
//! mixed depths (order != index order), a rotated camera (transposes in the chain rule), a
//! Gaussian beyond gsplat's frustum clamp that is still visible (zero gradient through the
//! clamped ratio) and a 0.99-clamped opaque Gaussian. Discontinuities (1/255 skip, radius
//! ceil) are far from ±1e-6 for these scenes.
//!
//! Deformed variants (PhysGaussian §4.1) give every Gaussian a non-symmetric deformation
//! gradient `F = Q·(I + shear)·diag(stretch)` (rotation, shear and stretch, det > 0) and an
//! SH rotation `R`; all 9 entries of each `F` and `R` are perturbed (`R` entrywise, which
//! leaves the rotations: the colour is linear in `R`), and the mean, scale, quaternion,
//! opacity and colour gradients are checked again with the deformation present.

mod common;

use common::Rng;
use pipe_render::{
    Camera, Colors, Deformation, Gaussians, Opacities, RenderOptions, Scales, backward, render,
};

/// Rotated camera, 48×40 pixels, hfov 60°.
fn camera() -> Camera<f64> {
    let (ax, ay) = (0.2f64, -0.3f64);
    let rx = [
        [1.0, 0.0, 0.0],
        [0.0, ax.cos(), -ax.sin()],
        [0.0, ax.sin(), ax.cos()],
    ];
    let ry = [
        [ay.cos(), 0.0, ay.sin()],
        [0.0, 1.0, 0.0],
        [-ay.sin(), 0.0, ay.cos()],
    ];
    let r: [[f64; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| rx[i][k] * ry[k][j]).sum()));
    let f = 24.0 / (30f64).to_radians().tan();
    Camera {
        camera_from_world_rotation: r,
        camera_from_world_translation: [0.1, -0.2, 0.5],
        fx: f,
        fy: f * 1.05,
        cx: 24.0,
        cy: 20.0,
        width: 48,
        height: 40,
        near: 0.01,
    }
}

/// World point that projects to pixel `(u, v)` at depth `z`.
fn unproject(cam: &Camera<f64>, u: f64, v: f64, z: f64) -> [f64; 3] {
    let pc = [(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z];
    let r = cam.camera_from_world_rotation;
    let t = cam.camera_from_world_translation;
    let d = [pc[0] - t[0], pc[1] - t[1], pc[2] - t[2]];
    std::array::from_fn(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2])
}

/// All trainable values of a scene in one place, perturbable by index.
#[derive(Clone)]
struct Params {
    means: Vec<[f64; 3]>,
    scales: Vec<[f64; 3]>,
    quats: Vec<[f64; 4]>,
    opac: Vec<f64>,
    rgb: Vec<[f64; 3]>,
    sh: Vec<[f64; 3]>,
    /// Deformation gradients (row-major), used when `deform`.
    f: Vec<[f64; 9]>,
    /// SH rotations (row-major), used when `deform` and `rotate_sh`.
    r: Vec<[f64; 9]>,
    /// log-scales / logits (true) or linear scales / opacities (false).
    log_params: bool,
    sh_degree: Option<u32>,
    deform: bool,
    rotate_sh: bool,
}

impl Params {
    fn gaussians(&self) -> Gaussians<'_, f64> {
        Gaussians {
            means: &self.means,
            scales: if self.log_params {
                Scales::Log(&self.scales)
            } else {
                Scales::Linear(&self.scales)
            },
            quats: &self.quats,
            opacities: if self.log_params {
                Opacities::Logit(&self.opac)
            } else {
                Opacities::Linear(&self.opac)
            },
            colors: match self.sh_degree {
                Some(degree) => Colors::Sh {
                    degree,
                    coeffs: &self.sh,
                },
                None => Colors::Rgb(&self.rgb),
            },
            deformation: self.deform.then_some(Deformation {
                f: &self.f,
                sh_rotation: self.rotate_sh.then_some(&self.r[..]),
            }),
        }
    }
    fn kinds(&mut self) -> Vec<(&'static str, &mut [f64])> {
        let mut v: Vec<(&'static str, &mut [f64])> = vec![
            ("means", self.means.as_flattened_mut()),
            ("scales", self.scales.as_flattened_mut()),
            ("quats", self.quats.as_flattened_mut()),
            ("opacities", &mut self.opac[..]),
        ];
        if self.sh_degree.is_some() {
            v.push(("sh", self.sh.as_flattened_mut()));
        } else {
            v.push(("rgb", self.rgb.as_flattened_mut()));
        }
        if self.deform {
            v.push(("F", self.f.as_flattened_mut()));
        }
        if self.deform && self.rotate_sh {
            v.push(("R", self.r.as_flattened_mut()));
        }
        v
    }

    /// Gives every Gaussian a random deformation gradient and SH rotation.
    fn with_deformation(mut self, rotate_sh: bool, seed: u64) -> Self {
        let mut rng = Rng(seed);
        let n = self.means.len();
        self.f = (0..n)
            .map(|_| {
                let q = rotation(&mut rng);
                let mut shear = [[0.0; 3]; 3];
                for (i, row) in shear.iter_mut().enumerate() {
                    for (j, e) in row.iter_mut().enumerate() {
                        *e = if i == j { 1.0 } else { rng.range(-0.3, 0.3) };
                    }
                }
                let stretch: [f64; 3] = std::array::from_fn(|_| rng.range(0.6, 1.5));
                let qs = matmul(&q, &shear);
                std::array::from_fn(|e| qs[e / 3][e % 3] * stretch[e % 3])
            })
            .collect();
        self.r = (0..n)
            .map(|_| {
                let q = rotation(&mut rng);
                std::array::from_fn(|e| q[e / 3][e % 3])
            })
            .collect();
        self.deform = true;
        self.rotate_sh = rotate_sh;
        self
    }
}

/// A random rotation (from a random unit quaternion).
fn rotation(rng: &mut Rng) -> [[f64; 3]; 3] {
    let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|c| c / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

fn matmul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn scene(log_params: bool, sh_degree: Option<u32>, seed: u64) -> Params {
    let cam = camera();
    let mut rng = Rng(seed);
    // (u, v) pixel centres: tile corners and borders, plus two spread ones.
    let centres = [
        (16.0, 16.0),
        (15.6, 16.3),
        (16.4, 15.8),
        (32.2, 15.9),
        (31.7, 16.2),
        (16.2, 31.6),
        (24.0, 20.0),
        (8.0, 8.0),
        (40.0, 30.0),
        (33.0, 33.0),
    ];
    let mut p = Params {
        means: vec![],
        scales: vec![],
        quats: vec![],
        opac: vec![],
        rgb: vec![],
        sh: vec![],
        f: vec![],
        r: vec![],
        log_params,
        sh_degree,
        deform: false,
        rotate_sh: false,
    };
    let k = sh_degree.map_or(0, |d| ((d + 1) * (d + 1)) as usize);
    let push = |p: &mut Params, rng: &mut Rng, mean: [f64; 3], scale: [f64; 3], o: f64| {
        p.means.push(mean);
        p.scales.push(if log_params {
            scale.map(f64::ln)
        } else {
            scale
        });
        let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
        let qn = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        let len = rng.range(0.7, 1.4);
        p.quats.push(q.map(|x| x / qn * len));
        p.opac
            .push(if log_params { (o / (1.0 - o)).ln() } else { o });
        p.rgb.push(std::array::from_fn(|_| rng.uniform()));
        for j in 0..k {
            let s = if j == 0 { 1.0 } else { 0.4 };
            p.sh.push(std::array::from_fn(|_| s * rng.range(-1.0, 1.0)));
        }
    };
    for (i, &(u, v)) in centres.iter().enumerate() {
        let z = 2.0 + 0.2 * i as f64 + rng.range(0.0, 0.1);
        let mean = unproject(&cam, u, v, z);
        let scale = std::array::from_fn(|_| rng.range(0.05, 0.25));
        let o = rng.range(0.3, 0.8);
        push(&mut p, &mut rng, mean, scale, o);
    }
    // Beyond the frustum clamp (centre ~x = 70 px) but large enough to reach the image.
    let mean = unproject(&cam, 70.0, 22.0, 3.0);
    push(&mut p, &mut rng, mean, [0.5, 0.6, 0.4], 0.6);
    // Opaque and large: alpha clamped at 0.99 near its centre.
    let mean = unproject(&cam, 12.5, 28.5, 4.0);
    push(&mut p, &mut rng, mean, [0.3, 0.2, 0.25], 0.9999);
    p
}

fn run(p0: &Params) {
    let cam = camera();
    let opts = RenderOptions {
        background: [0.2, 0.5, 0.7],
        eps2d: 0.3,
    };
    let n_pix = cam.n_pixels();
    let mut rng = Rng(99);
    let w: Vec<[f64; 3]> = (0..n_pix)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    let wa: Vec<f64> = (0..n_pix).map(|_| rng.range(-1.0, 1.0)).collect();
    let loss = |p: &Params| {
        let out = render(&p.gaussians(), &cam, &opts).unwrap();
        let li: f64 = out
            .image
            .iter()
            .zip(&w)
            .map(|(c, w)| c[0] * w[0] + c[1] * w[1] + c[2] * w[2])
            .sum();
        li + out.alpha.iter().zip(&wa).map(|(a, w)| a * w).sum::<f64>()
    };
    let g = p0.gaussians();
    let fwd = render(&g, &cam, &opts).unwrap();
    assert!(
        fwd.projected.iter().all(|p| p.visible()),
        "every test Gaussian must be visible"
    );
    assert!(
        fwd.n_contrib.iter().any(|&c| c >= 5),
        "Gaussians must overlap"
    );
    let gr = backward(&g, &cam, &opts, &fwd, &w, Some(&wa)).unwrap();
    let mut analytic: Vec<(&str, Vec<f64>)> = vec![
        ("means", gr.means.as_flattened().to_vec()),
        (
            "scales",
            if p0.log_params {
                gr.log_scales.as_flattened().to_vec()
            } else {
                gr.scales.as_flattened().to_vec()
            },
        ),
        ("quats", gr.quats.as_flattened().to_vec()),
        (
            "opacities",
            if p0.log_params {
                gr.opacity_logits.clone()
            } else {
                gr.opacities.clone()
            },
        ),
        (
            if p0.sh_degree.is_some() { "sh" } else { "rgb" },
            if p0.sh_degree.is_some() {
                gr.sh.as_flattened().to_vec()
            } else {
                gr.colors.as_flattened().to_vec()
            },
        ),
    ];
    if p0.deform {
        analytic.push(("F", gr.deformation.as_flattened().to_vec()));
    } else {
        assert!(gr.deformation.is_empty(), "no deformation, no dL/dF");
    }
    if p0.deform && p0.rotate_sh {
        analytic.push(("R", gr.sh_rotation.as_flattened().to_vec()));
    } else {
        assert!(gr.sh_rotation.is_empty(), "no SH rotation, no dL/dR");
    }
    let h = 1e-6;
    let mut p = p0.clone();
    assert_eq!(p.kinds().len(), analytic.len());
    for (kind, (name, an)) in analytic.iter().enumerate() {
        let len = p.kinds()[kind].1.len();
        assert_eq!(len, an.len(), "{name}");
        let scale = an.iter().map(|x| x.abs()).fold(0.0, f64::max);
        assert!(scale > 0.0, "{name}: all-zero gradient");
        let mut worst = 0.0f64;
        for (j, &g) in an.iter().enumerate() {
            let x0 = p.kinds()[kind].1[j];
            p.kinds()[kind].1[j] = x0 + h;
            let lp = loss(&p);
            p.kinds()[kind].1[j] = x0 - h;
            let lm = loss(&p);
            p.kinds()[kind].1[j] = x0;
            let fd = (lp - lm) / (2.0 * h);
            let err = (fd - g).abs();
            assert!(
                err <= 1e-6 * scale + 1e-8,
                "{name}[{j}]: fd {fd:e} vs analytic {g:e}"
            );
            worst = worst.max(err / scale);
        }
        println!("{name:>10}: max |fd - g| / max|g| = {worst:.1e}");
    }
}

#[test]
fn fd_rgb_log_params() {
    run(&scene(true, None, 1));
}

#[test]
fn fd_rgb_linear_params() {
    run(&scene(false, None, 2));
}

#[test]
fn fd_sh3_log_params() {
    run(&scene(true, Some(3), 3));
}

#[test]
fn fd_sh1_linear_params() {
    run(&scene(false, Some(1), 4));
}

#[test]
fn fd_deformed_sh3_log_params() {
    run(&scene(true, Some(3), 3).with_deformation(true, 5));
}

#[test]
fn fd_deformed_sh2_linear_params() {
    run(&scene(false, Some(2), 4).with_deformation(true, 7));
}

/// `F` without an SH rotation, RGB colours.
#[test]
fn fd_deformed_rgb_no_sh_rotation() {
    run(&scene(true, None, 1).with_deformation(false, 8));
}

/// An SH rotation with RGB colours is accepted and gets zero gradients.
#[test]
fn sh_rotation_with_rgb_colours_has_zero_gradient() {
    let p = scene(true, None, 2).with_deformation(true, 9);
    let cam = camera();
    let opts = RenderOptions::default();
    let out = render(&p.gaussians(), &cam, &opts).unwrap();
    let d = vec![[1.0; 3]; cam.n_pixels()];
    let gr = backward(&p.gaussians(), &cam, &opts, &out, &d, None).unwrap();
    assert_eq!(gr.sh_rotation.len(), p.means.len());
    assert!(gr.sh_rotation.iter().flatten().all(|&g| g == 0.0));
    assert!(gr.deformation.iter().flatten().any(|&g| g != 0.0));
}

#[test]
fn frustum_clamp_and_alpha_clamp_are_active() {
    let p = scene(true, None, 1);
    let cam = camera();
    let out = render(&p.gaussians(), &cam, &RenderOptions::default()).unwrap();
    let clamped = &out.projected[10];
    assert!(
        clamped.mean2d[0] > 60.0 && clamped.visible(),
        "Gaussian 10 must be off-image yet visible"
    );
    let lim = cam.frustum_limits();
    let tc = cam.camera_from_world_point(p.means[10]);
    assert!(
        tc[0] / tc[2] > lim[1],
        "Gaussian 10 must be beyond the frustum clamp"
    );
    // The opaque Gaussian saturates alpha at 0.99 at some pixel centre.
    let q = &out.projected[11];
    let [a, b, c] = q.conic;
    let saturated = (0..cam.height)
        .flat_map(|j| (0..cam.width).map(move |i| (i, j)))
        .any(|(i, j)| {
            let dx = q.mean2d[0] - (i as f64 + 0.5);
            let dy = q.mean2d[1] - (j as f64 + 0.5);
            let power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy;
            q.opacity * power.exp() > 0.99
        });
    assert!(saturated, "Gaussian 11 must hit the 0.99 alpha clamp");
}
