//! `polar_rotation` against `svd3`'s `U Vᵀ` on random and adversarial deformation gradients.

use glam::{DMat3, DVec3};
use pipe_mpm::math::max_abs;
use pipe_mpm::svd::{polar_rotation, polar_rotation_adjoint, rotation_adjoint, svd3};
use pipe_mpm::{Constitutive, FixedCorotated};

#[path = "common/rng.rs"]
mod rng;
use rng::Rng;

fn svd_rotation(f: &DMat3) -> DMat3 {
    let d = svd3(f);
    d.u * d.v.transpose()
}

/// Checks `polar_rotation(f)` against `reference` (svd3's `U Vᵀ`); returns the max deviation.
fn check(f: &DMat3, reference: &DMat3, tol: f64) -> f64 {
    let r = polar_rotation(f);
    let dev = max_abs(&(r - *reference));
    assert!(dev <= tol, "deviation {dev:e} > {tol:e} for F = {f:?}");
    let ortho = max_abs(&(r.transpose() * r - DMat3::IDENTITY));
    assert!(ortho <= 1e-14, "RᵀR − I = {ortho:e} for F = {f:?}");
    let det = r.determinant();
    assert!((det - 1.0).abs() <= 1e-14, "det R = {det} for F = {f:?}");
    dev
}

/// Runs `n` cases from `case` (seeded by `name`), asserting deviations ≤ `tol`; returns the max deviation.
fn family(name: &str, n: usize, tol: f64, mut case: impl FnMut(&mut Rng) -> DMat3) -> f64 {
    let mut rng = Rng::seeded(name);
    let mut worst: f64 = 0.0;
    for _ in 0..n {
        let f = case(&mut rng);
        worst = worst.max(check(&f, &svd_rotation(&f), tol));
    }
    println!("{name}: max |R − U Vᵀ| = {worst:.2e} over {n} matrices");
    worst
}

#[test]
fn realistic_near_rotations() {
    family("stretch 0.8–1.2", 20_000, 1e-14, |r| {
        let s = DVec3::new(r.range(0.8, 1.2), r.range(0.8, 1.2), r.range(0.8, 1.2));
        r.usv(s)
    });
}

#[test]
fn wide_stretches() {
    family("stretch 0.05–20", 20_000, 5e-14, |r| {
        let s = DVec3::new(
            r.log_range(0.05, 20.0),
            r.log_range(0.05, 20.0),
            r.log_range(0.05, 20.0),
        );
        r.usv(s)
    });
}

#[test]
fn shears() {
    family("shear", 10_000, 1e-14, |r| {
        let mut s = DMat3::IDENTITY;
        let (i, j) = ((r.next_u64() % 3) as usize, (r.next_u64() % 3) as usize);
        if i != j {
            s.col_mut(j)[i] = r.range(-5.0, 5.0);
        }
        r.rotation() * s
    });
    family("general", 10_000, 1e-14, |r| r.mat(1.0));
}

#[test]
fn near_identity_and_exact_rotations() {
    family("I + 1e-6 noise", 10_000, 4e-15, |r| {
        DMat3::IDENTITY + r.mat(1e-6)
    });
    family("rotation", 10_000, 4e-15, |r| r.rotation());
    family("rotation + 1e-12 noise", 10_000, 4e-15, |r| {
        r.rotation() + r.mat(1e-12)
    });
    check(&DMat3::IDENTITY, &DMat3::IDENTITY, 0.0);
}

#[test]
fn repeated_singular_values() {
    family("σ = (a, a, b)", 10_000, 1e-13, |r| {
        let (a, b) = (r.log_range(0.1, 10.0), r.log_range(0.1, 10.0));
        r.usv(DVec3::new(a, a, b))
    });
    family("σ = (a, a, a)", 10_000, 1e-14, |r| {
        let a = r.log_range(0.1, 10.0);
        r.usv(DVec3::splat(a))
    });
    family("σ = (a, a(1+1e-9), b)", 10_000, 1e-14, |r| {
        let (a, b) = (r.log_range(0.5, 2.0), r.log_range(0.5, 2.0));
        r.usv(DVec3::new(a, a * (1.0 + 1e-9), b))
    });
}

#[test]
fn nearly_singular() {
    family("σ_min 1e-12–1e-2", 10_000, 1e-13, |r| {
        let s = DVec3::new(
            r.range(0.5, 2.0),
            r.range(0.5, 2.0),
            r.log_range(1e-12, 1e-2),
        );
        r.usv(s)
    });
    // Two small singular values: R itself is ill-conditioned (∝ 1/(σ₂ + σ₃)) near the switch.
    family("σ₂, σ₃ 1e-4–1e-1", 10_000, 1e-13, |r| {
        let s = DVec3::new(1.0, r.log_range(1e-4, 1e-1), r.log_range(1e-4, 1e-1));
        r.usv(s)
    });
    family("rank 2", 1_000, 1e-12, |r| {
        let s1 = r.range(0.1, 1.0);
        r.usv(DVec3::new(1.0, s1, 0.0))
    });
    family("rank 1", 1_000, 1e-12, |r| r.usv(DVec3::new(1.0, 0.0, 0.0)));
    check(&DMat3::ZERO, &svd_rotation(&DMat3::ZERO), 0.0);
}

#[test]
fn inverted() {
    // det F < 0: must stay on svd3's rotation-variant convention (det R = +1), bit for bit.
    family("det < 0", 10_000, 0.0, |r| {
        let s = DVec3::new(r.range(0.5, 2.0), r.range(0.5, 2.0), -r.range(0.01, 2.0));
        r.usv(s)
    });
    check(
        &DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0)),
        &svd_rotation(&DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0))),
        0.0,
    );
}

#[test]
fn extreme_scales() {
    // R is scale invariant: the reference is the rotation of the unscaled matrix (svd3 at these
    // scales is checked in tests/svd_fast.rs).
    let mut rng = Rng(77);
    let mut worst: f64 = 0.0;
    for _ in 0..2_000 {
        let s = DVec3::new(
            rng.range(0.5, 2.0),
            rng.range(0.5, 2.0),
            rng.range(0.5, 2.0),
        );
        let f = rng.usv(s);
        let reference = svd_rotation(&f);
        for scale in [1e150, 1e-150, 1e300, 1e-300] {
            worst = worst.max(check(&(f * scale), &reference, 1e-13));
        }
        // Subnormal entries keep only ~10 significant digits of F.
        check(&(f * 1e-310), &reference, 1e-8);
        // Inverted: svd3 on the power-of-two normalised F, so bit-identical to the reference
        // (svd3 is exactly scale invariant under powers of two away from over/underflow).
        let inv = f * DMat3::from_diagonal(DVec3::new(1.0, -1.0, 1.0));
        let reference = svd_rotation(&inv);
        for scale in [2f64.powi(500), 2f64.powi(-500)] {
            worst = worst.max(check(&(inv * scale), &reference, 0.0));
        }
    }
    println!("extreme scales: max deviation {worst:.2e}");
}

#[test]
fn non_finite_returns() {
    // Must terminate (bounded iterations); the value itself is unspecified.
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let mut f = DMat3::IDENTITY;
        f.y_axis.z = bad;
        let _ = polar_rotation(&f);
        let _ = polar_rotation(&DMat3::from_diagonal(DVec3::splat(bad)));
    }
}

#[test]
fn fixed_corotated_stress_matches_svd_formula() {
    // τ = 2μ (F − U Vᵀ) Fᵀ + λ J (J − 1) I with svd3's rotation, elastic and inverted F.
    let (mu, lam) = (3.0e5, 2.0e5);
    let mut rng = Rng(2024);
    for k in 0..2_000 {
        let s = DVec3::new(
            rng.range(0.7, 1.3),
            rng.range(0.7, 1.3),
            rng.range(0.7, 1.3),
        );
        let sign = if k % 4 == 0 { -1.0 } else { 1.0 };
        let f = rng.usv(s * DVec3::new(1.0, 1.0, sign));
        let (f_new, tau) = FixedCorotated.update(&f, &DMat3::ZERO, mu, lam, 1e-4);
        let j = f.determinant();
        let expected = (f - svd_rotation(&f)) * f.transpose() * (2.0 * mu)
            + DMat3::IDENTITY * (lam * j * (j - 1.0));
        assert_eq!(f_new, f);
        let err = max_abs(&(tau - expected));
        assert!(
            err <= 1e-14 * max_abs(&expected).max(mu),
            "{err:e} for F = {f:?}"
        );
    }
}

/// The SVD-free rotation adjoint equals `rotation_adjoint` of the SVD (relative to the largest
/// entry) wherever it accepts `F`, and it declines inverted and nearly flat `F`.
#[test]
fn polar_rotation_adjoint_matches_svd_adjoint() {
    let mut rng = Rng(0xAD70);
    let mut worst: f64 = 0.0;
    let mut accepted = 0;
    for n in 0..20_000 {
        let f = match n % 4 {
            0 => {
                let s = DVec3::new(
                    rng.range(0.8, 1.2),
                    rng.range(0.8, 1.2),
                    rng.range(0.8, 1.2),
                );
                rng.usv(s)
            }
            1 => {
                let s = DVec3::new(
                    rng.log_range(0.05, 20.0),
                    rng.log_range(0.05, 20.0),
                    rng.log_range(0.05, 20.0),
                );
                rng.usv(s)
            }
            2 => DMat3::IDENTITY + rng.mat(0.3),
            _ => {
                let z = rng.range(0.5, 1.5);
                rng.rotation() * DMat3::from_diagonal(DVec3::new(1.1, 1.1, z))
            }
        };
        let gr = rng.mat(1.0);
        let reference = rotation_adjoint(&svd3(&f), &gr);
        if let Some(g) = polar_rotation_adjoint(&f, &polar_rotation(&f), &gr) {
            accepted += 1;
            let dev = max_abs(&(g - reference)) / max_abs(&reference).max(1e-300);
            worst = worst.max(dev);
            assert!(dev <= 1e-10, "relative deviation {dev:e} for F = {f:?}");
        }
    }
    println!(
        "polar rotation adjoint: max relative deviation {worst:.2e}, {accepted} of 20000 accepted"
    );
    assert!(accepted > 18_000, "only {accepted} accepted");
    let inverted = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -0.5));
    assert!(
        polar_rotation_adjoint(&inverted, &polar_rotation(&inverted), &DMat3::IDENTITY).is_none()
    );
    let flat = DMat3::from_diagonal(DVec3::new(1.0, 1e-7, 1e-7));
    assert!(polar_rotation_adjoint(&flat, &polar_rotation(&flat), &DMat3::IDENTITY).is_none());
}
