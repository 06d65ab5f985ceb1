//! Timings of the training loss (L1 + D-SSIM with gradient) and of the report metrics on
//! 256² and 800² RGB images (pseudo-random content, the second image a noisy copy). Run with
//! `cargo bench -p pipe-loss --bench loss`.

use divan::Bencher;
use pipe_loss::{Image, l1_dssim, psnr, ssim_skimage};

fn images(res: usize) -> (Vec<f32>, Vec<f32>) {
    let mut state = 7u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 40) as f32) / (1u64 << 24) as f32
    };
    let a: Vec<f32> = (0..res * res * 3).map(|_| next()).collect();
    let b = a
        .iter()
        .map(|v| (0.9 * v + 0.1 * next()).min(1.0))
        .collect();
    (a, b)
}

#[divan::bench(args = [256, 800], sample_count = 10)]
fn l1_dssim_with_grad(b: Bencher, res: usize) {
    let (x, y) = images(res);
    b.bench_local(|| {
        let a = Image::new("a", &x, res, res).unwrap();
        let c = Image::new("b", &y, res, res).unwrap();
        l1_dssim(a, c, 0.1).unwrap()
    });
}

#[divan::bench(args = [256, 800], sample_count = 10)]
fn report_metrics(b: Bencher, res: usize) {
    let (x, y) = images(res);
    b.bench_local(|| {
        let a = Image::new("a", &x, res, res).unwrap();
        let c = Image::new("b", &y, res, res).unwrap();
        (ssim_skimage(a, c).unwrap(), psnr(a, c).unwrap())
    });
}

fn main() {
    divan::main();
}
