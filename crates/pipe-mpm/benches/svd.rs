//! 3×3 SVD and polar rotation of deformation gradients, on 10 000 realistic elastic
//! `F = U diag(σ) Vᵀ` with random rotations `U`, `V` and stretches σ uniform in [0.8, 1.2] (plus
//! a near-rest set, σ in [0.99, 1.01]). Counter = matrices, so divan's time per item is ns/matrix.
//!
//! * full SVD: `svd3` (warm-started Jacobi) against `svd3_jacobi` (the cold-start reference);
//! * rotation `R = U Vᵀ`: `svd3` against `polar_rotation` (scaled Newton).
//!
//! `cargo bench -p pipe-mpm --bench svd`

use divan::Bencher;
use divan::counter::ItemsCount;
use glam::{DMat3, DVec3};
use pipe_mpm::svd::{Svd, polar_rotation, svd3, svd3_jacobi};

fn main() {
    divan::main();
}

const N: usize = 10_000;

#[path = "../tests/common/rng.rs"]
mod rng;
use rng::Rng;

/// Deterministic batch: `F = U diag(σ) Vᵀ`, σ uniform in `[1 − w, 1 + w]`.
fn batch(w: f64) -> Vec<DMat3> {
    let mut rng = Rng(0x0DDB_A110);
    (0..N)
        .map(|_| {
            let (u, v) = (rng.rotation(), rng.rotation());
            let s =
                DVec3::new(rng.unit(), rng.unit(), rng.unit()) * (2.0 * w) + DVec3::splat(1.0 - w);
            u * DMat3::from_diagonal(s) * v.transpose()
        })
        .collect()
}

fn run(b: Bencher, w: f64, rot: fn(&DMat3) -> DMat3) {
    let fs = batch(w);
    let mut out = vec![DMat3::ZERO; N];
    b.counter(ItemsCount::new(N)).bench_local(|| {
        for (o, f) in out.iter_mut().zip(divan::black_box(&fs)) {
            *o = rot(f);
        }
        divan::black_box(&out);
    });
}

fn svd_rotation(f: &DMat3) -> DMat3 {
    let d = svd3(f);
    d.u * d.v.transpose()
}

#[divan::bench(args = [0.2, 0.01], sample_count = 20)]
fn svd3_uvt(b: Bencher, w: f64) {
    run(b, w, svd_rotation);
}

#[divan::bench(args = [0.2, 0.01], sample_count = 20)]
fn polar_rotation_fast(b: Bencher, w: f64) {
    run(b, w, polar_rotation);
}

fn run_svd(b: Bencher, w: f64, svd: fn(&DMat3) -> Svd) {
    let fs = batch(w);
    let mut out = vec![DVec3::ZERO; N];
    b.counter(ItemsCount::new(N)).bench_local(|| {
        for (o, f) in out.iter_mut().zip(divan::black_box(&fs)) {
            let d = svd(f);
            *o = d.s + d.u.x_axis + d.v.z_axis;
        }
        divan::black_box(&out);
    });
}

#[divan::bench(args = [0.2, 0.01], sample_count = 20)]
fn svd3_warm(b: Bencher, w: f64) {
    run_svd(b, w, svd3);
}

#[divan::bench(args = [0.2, 0.01], sample_count = 20)]
fn svd3_jacobi_cold(b: Bencher, w: f64) {
    run_svd(b, w, svd3_jacobi);
}
