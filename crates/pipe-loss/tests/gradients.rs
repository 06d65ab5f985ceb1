//! Finite-difference checks of the SSIM (3DGS convention), D-SSIM, L1 and combined-loss
//! gradients, and invariants.
//!
//! SSIM's gradient is checked by central differences (h = 1e-3 on f32 pixels, the loss
//! evaluated in f64) at pixels in the interior, on the zero-padded border and in corners of
//! a 23×17 image — the border is where a wrong adjoint of the padded filter would show. The
//! L1 gradient is checked away from its kink. Invariants: SSIM(x, x) = 1 in both
//! conventions; constant images (zero variance) give finite values; identical images give
//! PSNR = +inf, never NaN; size mismatches are typed errors naming the buffer; results are
//! bit-identical with 1 and 2 rayon threads.

use pipe_loss::{
    Image, LossError, dssim_grad, l1, l1_dssim, l1_grad, psnr, ssim, ssim_grad, ssim_skimage,
};

struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

const W: usize = 23;
const H: usize = 17;

fn pair(seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut r = Rng(seed);
    let a: Vec<f32> = (0..W * H * 3).map(|_| r.uniform()).collect();
    let b: Vec<f32> = a
        .iter()
        .map(|v| (0.8 * v + 0.2 * r.uniform()).clamp(0.0, 1.0))
        .collect();
    (a, b)
}

fn img(d: &[f32]) -> Image<'_> {
    Image::new("img", d, W, H).unwrap()
}

/// Pixel indices (value index into [H][W][3]) to probe: corners, borders, interior.
fn probes() -> Vec<usize> {
    let at = |y: usize, x: usize, c: usize| (y * W + x) * 3 + c;
    vec![
        at(0, 0, 0),
        at(0, W - 1, 1),
        at(H - 1, 0, 2),
        at(H - 1, W - 1, 0),
        at(0, 11, 1),
        at(8, 0, 2),
        at(2, 3, 0),
        at(8, 11, 1),
        at(12, 17, 2),
        at(4, 20, 0),
    ]
}

fn fd_check(f: &dyn Fn(&[f32]) -> f64, a: &[f32], g: &[f32], rel: f64) -> f64 {
    // `f64::max` drops NaN: check the whole gradient first, not only the probed entries.
    if let Some(i) = g.iter().position(|v| !v.is_finite()) {
        panic!("gradient entry {i} is not finite: {}", g[i]);
    }
    let gmax = g.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    let mut worst = 0.0f64;
    for i in probes() {
        let h = 1e-3f32;
        let mut p = a.to_vec();
        p[i] = a[i] + h;
        let lp = f(&p);
        p[i] = a[i] - h;
        let lm = f(&p);
        let fd = (lp - lm) / (((a[i] + h) - (a[i] - h)) as f64);
        let err = (fd - g[i] as f64).abs();
        assert!(
            err <= rel * gmax,
            "index {i}: fd {fd:e} vs analytic {:e} (max|g| {gmax:e})",
            g[i]
        );
        worst = worst.max(err / gmax);
    }
    worst
}

#[test]
fn ssim_gradient_matches_finite_differences() {
    let (a, b) = pair(1);
    let (_, g) = ssim_grad(img(&a), img(&b)).unwrap();
    let worst = fd_check(&|x| ssim(img(x), img(&b)).unwrap(), &a, &g, 1e-3);
    println!("ssim: max |fd - g| / max|g| = {worst:.1e}");
    let (_, gd) = dssim_grad(img(&a), img(&b)).unwrap();
    fd_check(&|x| 1.0 - ssim(img(x), img(&b)).unwrap(), &a, &gd, 1e-3);
}

#[test]
fn l1_and_combined_gradients_match_finite_differences() {
    let (a, b) = pair(2);
    // keep every probed value away from the |.| kink
    assert!(probes().iter().all(|&i| (a[i] - b[i]).abs() > 2e-3));
    let (_, g) = l1_grad(img(&a), img(&b)).unwrap();
    fd_check(&|x| l1(img(x), img(&b)).unwrap(), &a, &g, 1e-4);
    let (_, g) = l1_dssim(img(&a), img(&b), 0.2).unwrap();
    let worst = fd_check(
        &|x| 0.2 * l1(img(x), img(&b)).unwrap() + 0.8 * (1.0 - ssim(img(x), img(&b)).unwrap()),
        &a,
        &g,
        1e-3,
    );
    println!("l1_dssim: max |fd - g| / max|g| = {worst:.1e}");
}

#[test]
fn ssim_of_identical_images_is_one() {
    let (a, _) = pair(3);
    assert!((ssim(img(&a), img(&a)).unwrap() - 1.0).abs() < 1e-12);
    assert!((ssim_skimage(img(&a), img(&a)).unwrap() - 1.0).abs() < 1e-12);
    let (v, g) = ssim_grad(img(&a), img(&a)).unwrap();
    assert!((v - 1.0).abs() < 1e-12);
    assert!(g.iter().all(|x| x.abs() < 1e-6), "SSIM is maximal at a = b");
    assert_eq!(psnr(img(&a), img(&a)).unwrap(), f64::INFINITY);
}

#[test]
fn constant_images_give_finite_values() {
    for (ca, cb) in [(0.0f32, 0.0f32), (1.0, 1.0), (0.5, 0.25), (0.0, 1.0)] {
        let a = vec![ca; W * H * 3];
        let b = vec![cb; W * H * 3];
        let s = ssim(img(&a), img(&b)).unwrap();
        let sk = ssim_skimage(img(&a), img(&b)).unwrap();
        let (v, g) = ssim_grad(img(&a), img(&b)).unwrap();
        let (l, gl) = l1_dssim(img(&a), img(&b), 0.1).unwrap();
        let p = psnr(img(&a), img(&b)).unwrap();
        assert!(
            s.is_finite() && sk.is_finite() && v.is_finite() && l.is_finite() && !p.is_nan(),
            "{ca} {cb}"
        );
        assert!(g.iter().chain(&gl).all(|x| x.is_finite()));
        if ca == cb {
            assert!((s - 1.0).abs() < 1e-12 && (sk - 1.0).abs() < 1e-12);
        }
    }
}

#[test]
fn invalid_input_is_a_typed_error() {
    let (a, b) = pair(4);
    assert_eq!(
        Image::new("rendered", &a[..10], W, H).unwrap_err(),
        LossError::Length {
            field: "rendered",
            expected: W * H * 3,
            got: 10,
            height: H,
            width: W
        }
    );
    assert!(matches!(
        Image::new("x", &[], 0, 3),
        Err(LossError::ImageSize {
            width: 0,
            height: 3
        })
    ));
    let small = Image::new("b", &b[..(W - 1) * H * 3], W - 1, H).unwrap();
    assert!(matches!(
        ssim(img(&a), small),
        Err(LossError::SizeMismatch { .. })
    ));
    let tiny = vec![0.5f32; 5 * 5 * 3];
    let t = Image::new("t", &tiny, 5, 5).unwrap();
    assert!(matches!(
        ssim_skimage(t, t),
        Err(LossError::Value { field: "width", .. })
    ));
    assert!(
        ssim(t, t).is_ok(),
        "the 3DGS SSIM works on tiny images (zero padding)"
    );
    assert!(matches!(
        l1_dssim(img(&a), img(&b), 1.5),
        Err(LossError::Value {
            field: "lambda",
            ..
        })
    ));
}

#[test]
fn same_bits_for_1_and_2_threads() {
    let (a, b) = pair(5);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (v, g) = l1_dssim(img(&a), img(&b), 0.1).unwrap();
            let s = ssim_skimage(img(&a), img(&b)).unwrap();
            (
                v.to_bits(),
                s.to_bits(),
                g.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            )
        })
    };
    assert_eq!(run(1), run(2));
}
