//! 3×3 SVD and polar rotation of deformation gradients, on 10 000 realistic elastic
//! `F = U diag(σ) Vᵀ` with random rotations `U`, `V` and stretches σ uniform in [0.8, 1.2] (plus
//! a near-rest set, σ in [0.99, 1.01]). Counter = matrices, so divan's time per item is ns/matrix.
//!
//! * full SVD: `svd3` (warm-started Jacobi) against `svd3_jacobi` (cold-start reference) and
//!   `svd3_before` (a verbatim copy of the cold-start `svd3` before the warm start);
//! * rotation `R = U Vᵀ`: `svd3` against `polar_rotation` (scaled Newton).
//!
//! `CARGO_TARGET_DIR=/work/target-bench cargo bench -p pipe-mpm --bench svd`

use divan::Bencher;
use divan::counter::ItemsCount;
use glam::{DMat3, DQuat, DVec3};
use pipe_mpm::svd::{Svd, polar_rotation, svd3, svd3_jacobi};

fn main() {
    divan::main();
}

const N: usize = 10_000;

/// SplitMix64 uniform numbers in [0, 1).
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn rotation(&mut self) -> DMat3 {
        let q = [0; 4].map(|_| self.unit() - 0.5);
        DMat3::from_quat(DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize())
    }
}

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

#[divan::bench(args = [0.2, 0.01], sample_count = 20)]
fn svd3_before_cold(b: Bencher, w: f64) {
    run_svd(b, w, svd3_before);
}

/// The one-sided Jacobi `svd3` as it was before the warm start (for the comparison only).
fn svd3_before(f: &DMat3) -> Svd {
    const TINY: f64 = 1e-30;
    const ORTHO_TOL: f64 = 2.0 * f64::EPSILON;
    let mut b = [f.x_axis, f.y_axis, f.z_axis];
    let mut v = [DVec3::X, DVec3::Y, DVec3::Z];
    for _sweep in 0..30 {
        let mut rotated = false;
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let alpha = b[p].length_squared();
            let beta = b[q].length_squared();
            let gamma = b[p].dot(b[q]);
            if gamma == 0.0 || gamma.abs() <= ORTHO_TOL * (alpha * beta).sqrt() {
                continue;
            }
            rotated = true;
            let zeta = (beta - alpha) / (2.0 * gamma);
            let t = zeta.signum() / (zeta.abs() + (1.0 + zeta * zeta).sqrt());
            let c = 1.0 / (1.0 + t * t).sqrt();
            let s = c * t;
            let (bp, bq) = (b[p], b[q]);
            b[p] = c * bp - s * bq;
            b[q] = s * bp + c * bq;
            let (vp, vq) = (v[p], v[q]);
            v[p] = c * vp - s * vq;
            v[q] = s * vp + c * vq;
        }
        if !rotated {
            break;
        }
    }
    let mut sig = [b[0].length(), b[1].length(), b[2].length()];
    for i in 1..3 {
        let mut j = i;
        while j > 0 && sig[j] > sig[j - 1] {
            sig.swap(j, j - 1);
            b.swap(j, j - 1);
            v.swap(j, j - 1);
            j -= 1;
        }
    }
    let scale = sig[0].max(f64::MIN_POSITIVE);
    let u0 = if sig[0] > 0.0 {
        b[0] / sig[0]
    } else {
        DVec3::X
    };
    let u1 = if sig[1] > TINY * scale {
        b[1] / sig[1]
    } else {
        u0.any_orthonormal_vector()
    };
    let mut u2 = if sig[2] > TINY * scale {
        b[2] / sig[2]
    } else {
        u0.cross(u1)
    };
    let mut vm = DMat3::from_cols(v[0], v[1], v[2]);
    if vm.determinant() < 0.0 {
        vm.z_axis = -vm.z_axis;
        u2 = -u2;
    }
    let mut um = DMat3::from_cols(u0, u1, u2);
    if um.determinant() < 0.0 {
        um.z_axis = -um.z_axis;
        sig[2] = -sig[2];
    }
    Svd {
        u: um,
        s: DVec3::from_array(sig),
        v: vm,
    }
}
