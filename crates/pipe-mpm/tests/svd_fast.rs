//! `svd3` (one-sided Jacobi warm-started from an analytic eigenbasis of `FᵀF`) against the
//! cold-start reference `svd3_jacobi`: the decomposition and its conventions on random and
//! adversarial matrices, then every quantity the models derive from it (return maps, stresses,
//! adjoints), which must not depend on the non-unique singular vectors of repeated σ.

use glam::{DMat3, DVec3};
use pipe_mpm::math::max_abs;
use pipe_mpm::svd::{Svd, rotation_adjoint, svd3, svd3_jacobi, with_jacobi_svd};
use pipe_mpm::{Constitutive, DruckerPrager, FixedCorotated, ModelGrad, VonMises};

#[path = "common/rng.rs"]
mod rng;
use rng::Rng;

/// Largest deviations of `svd3` from `svd3_jacobi`, relative to σ₀.
#[derive(Debug, Default, Clone, Copy)]
struct Dev {
    /// `|U diag(σ) Vᵀ − F| / σ₀`.
    recon: f64,
    /// `|σ − σ_ref| / σ₀`.
    sigma: f64,
    /// `|U Vᵀ − (U Vᵀ)_ref|` where the rotation is well defined (`σ₁ + σ₂ > 1e-3 σ₀`).
    rot: f64,
    /// `|UᵀU − I|`, `|VᵀV − I|`, `|det − 1|`.
    ortho: f64,
}

impl Dev {
    fn max(self, o: Dev) -> Dev {
        Dev {
            recon: self.recon.max(o.recon),
            sigma: self.sigma.max(o.sigma),
            rot: self.rot.max(o.rot),
            ortho: self.ortho.max(o.ortho),
        }
    }
}

fn orthonormality(m: &DMat3) -> f64 {
    max_abs(&(m.transpose() * *m - DMat3::IDENTITY)).max((m.determinant() - 1.0).abs())
}

fn conventions(d: &Svd, f: &DMat3) {
    let s = d.s;
    assert!(
        s[0] >= s[1] && s[1] >= s[2].abs(),
        "order σ = {s:?} for F = {f:?}"
    );
    let det = f.determinant();
    if det.abs() > 1e-12 * s[0].powi(3) {
        assert_eq!(
            s[2] < 0.0,
            det < 0.0,
            "sign σ₂ = {} for det F = {det:e}",
            s[2]
        );
    }
}

/// Compares `svd3(f)` with `svd3_jacobi(f)` and checks conventions; asserts `dev ≤ tol`
/// (each field) and returns the deviations.
fn check(f: &DMat3, tol: f64) -> Dev {
    let d = svd3(f);
    let r = svd3_jacobi(f);
    conventions(&d, f);
    conventions(&r, f);
    let scale = r.s[0];
    let dev = if scale == 0.0 {
        assert_eq!(d.s, DVec3::ZERO);
        Dev {
            ortho: orthonormality(&d.u).max(orthonormality(&d.v)),
            ..Dev::default()
        }
    } else {
        let well_defined = d.s[1] + d.s[2] > 1e-3 * scale;
        let rot = if well_defined {
            max_abs(&(d.u * d.v.transpose() - r.u * r.v.transpose())) * (d.s[1] + d.s[2]) / scale
        } else {
            0.0
        };
        Dev {
            recon: max_abs(&(d.compose(d.s) - *f)) / scale,
            sigma: (d.s - r.s).abs().max_element() / scale,
            rot,
            ortho: orthonormality(&d.u).max(orthonormality(&d.v)),
        }
    };
    for (name, v, t) in [
        ("reconstruction", dev.recon, tol),
        ("σ", dev.sigma, tol),
        ("U Vᵀ", dev.rot, tol),
        ("orthonormality", dev.ortho, 1e-14),
    ] {
        assert!(
            v <= t,
            "{name} deviation {v:e} > {t:e} for F = {f:?}\n{d:?}\n{r:?}"
        );
    }
    dev
}

/// Runs `n` cases from `case`, asserting deviations ≤ `tol`; returns the max deviations.
fn family(name: &str, n: usize, tol: f64, mut case: impl FnMut(&mut Rng) -> DMat3) -> Dev {
    let mut rng = Rng::seeded(name);
    let mut worst = Dev::default();
    for _ in 0..n {
        worst = worst.max(check(&case(&mut rng), tol));
    }
    println!(
        "{name}: recon {:.1e}, σ {:.1e}, U Vᵀ {:.1e}, ortho {:.1e} over {n}",
        worst.recon, worst.sigma, worst.rot, worst.ortho
    );
    worst
}

fn stretch(r: &mut Rng, lo: f64, hi: f64) -> DVec3 {
    DVec3::new(
        r.log_range(lo, hi),
        r.log_range(lo, hi),
        r.log_range(lo, hi),
    )
}

#[test]
fn random_stretches() {
    family("stretch 0.8–1.2", 20_000, 1e-14, |r| {
        let s = DVec3::new(r.range(0.8, 1.2), r.range(0.8, 1.2), r.range(0.8, 1.2));
        r.usv(s)
    });
    family("stretch 0.05–20", 20_000, 2e-14, |r| {
        let s = stretch(r, 0.05, 20.0);
        r.usv(s)
    });
    family("stretch 1e-6–1e6", 5_000, 2e-14, |r| {
        let s = stretch(r, 1e-6, 1e6);
        r.usv(s)
    });
    family("general", 20_000, 1e-14, |r| r.mat(1.0));
    family("shear", 10_000, 1e-14, |r| {
        let mut s = DMat3::IDENTITY;
        let (i, j) = ((r.next_u64() % 3) as usize, (r.next_u64() % 3) as usize);
        if i != j {
            s.col_mut(j)[i] = r.range(-5.0, 5.0);
        }
        r.rotation() * s
    });
}

#[test]
fn near_identity_and_rotations() {
    family("I + 1e-6 noise", 10_000, 1e-14, |r| {
        DMat3::IDENTITY + r.mat(1e-6)
    });
    family("I + 1e-13 noise", 10_000, 1e-14, |r| {
        DMat3::IDENTITY + r.mat(1e-13)
    });
    family("rotation", 10_000, 1e-14, |r| r.rotation());
    family("a × rotation", 10_000, 1e-14, |r| {
        r.rotation() * r.log_range(0.1, 10.0)
    });
    for f in [
        DMat3::IDENTITY,
        DMat3::from_diagonal(DVec3::new(3.0, 2.0, 1.0)),
        DMat3::from_diagonal(DVec3::new(1.0, 2.0, 3.0)),
        DMat3::from_diagonal(DVec3::new(-1.0, 1.0, 1.0)),
        DMat3::from_cols(DVec3::Y, DVec3::Z, DVec3::X),
        DMat3::from_cols(DVec3::Y, DVec3::X, DVec3::Z),
    ] {
        check(&f, 1e-15);
    }
}

#[test]
fn repeated_singular_values() {
    family("σ = (a, a, b)", 10_000, 1e-14, |r| {
        let (a, b) = (r.log_range(0.1, 10.0), r.log_range(0.1, 10.0));
        r.usv(DVec3::new(a, a, b))
    });
    family("σ = (a, b, b)", 10_000, 1e-14, |r| {
        let (a, b) = (r.log_range(0.1, 10.0), r.log_range(0.1, 10.0));
        r.usv(DVec3::new(a, b, b))
    });
    family("σ = (a, a(1+1e-9), b)", 10_000, 1e-14, |r| {
        let (a, b) = (r.log_range(0.5, 2.0), r.log_range(0.5, 2.0));
        r.usv(DVec3::new(a, a * (1.0 + 1e-9), b))
    });
    family("σ = (a, a(1+1e-5), a(1-1e-5))", 10_000, 1e-14, |r| {
        let a = r.log_range(0.5, 2.0);
        r.usv(DVec3::new(a, a * (1.0 + 1e-5), a * (1.0 - 1e-5)))
    });
    family("diag(a, a, b) exact", 1_000, 1e-15, |r| {
        let (a, b) = (r.log_range(0.1, 10.0), r.log_range(0.1, 10.0));
        DMat3::from_diagonal(DVec3::new(a, b, a))
    });
}

#[test]
fn inverted_and_singular() {
    family("det < 0", 10_000, 1e-14, |r| {
        let s = stretch(r, 0.05, 20.0) * DVec3::new(1.0, 1.0, -1.0);
        r.usv(s)
    });
    family("det < 0, σ = (a, a, -a)", 2_000, 1e-14, |r| {
        let a = r.log_range(0.1, 10.0);
        r.usv(DVec3::new(a, a, -a))
    });
    family("σ_min 1e-12–1e-2", 10_000, 1e-14, |r| {
        let s = DVec3::new(
            r.range(0.5, 2.0),
            r.range(0.5, 2.0),
            r.log_range(1e-12, 1e-2),
        );
        r.usv(s)
    });
    family("rank 2", 2_000, 1e-14, |r| {
        let s1 = r.range(0.1, 1.0);
        r.usv(DVec3::new(1.0, s1, 0.0))
    });
    family("rank 1", 2_000, 1e-14, |r| r.usv(DVec3::new(1.0, 0.0, 0.0)));
    family("rank 1 outer", 2_000, 1e-14, |r| {
        let (a, b) = (r.mat(1.0).x_axis, r.mat(1.0).y_axis);
        DMat3::from_cols(a * b.x, a * b.y, a * b.z)
    });
    check(&DMat3::ZERO, 0.0);
    let d = svd3(&DMat3::ZERO);
    assert_eq!(
        (d.u, d.s, d.v),
        (DMat3::IDENTITY, DVec3::ZERO, DMat3::IDENTITY)
    );
}

#[test]
fn extreme_scales() {
    // Both decompositions normalise F by a power of two: exact scale invariance under 2^k, and
    // the rotation is scale invariant otherwise (the old Jacobi test overflowed at 1e150).
    let mut rng = Rng::seeded("scales");
    for k in 0..2_000 {
        let s = stretch(&mut rng, 0.1, 10.0)
            * DVec3::new(1.0, 1.0, if k % 3 == 0 { -1.0 } else { 1.0 });
        let f = rng.usv(s);
        let base = svd3(&f);
        let base_ref = svd3_jacobi(&f);
        for e in [-1000, -600, 600, 1000, 1016] {
            let scale = 2f64.powi(e);
            let fs = f * scale;
            for (d, b) in [(svd3(&fs), base), (svd3_jacobi(&fs), base_ref)] {
                assert_eq!(
                    (d.u, d.s, d.v),
                    (b.u, b.s * scale, b.v),
                    "2^{e} F, F = {f:?}"
                );
            }
        }
        // Subnormal entries keep ~33 bits of F (and of σ).
        let fs = f * 2f64.powi(-1040);
        for d in [svd3(&fs), svd3_jacobi(&fs)] {
            conventions(&d, &fs);
            let rot = max_abs(&(d.u * d.v.transpose() - base.u * base.v.transpose()));
            let sig = (d.s * 2f64.powi(520) * 2f64.powi(520) - base.s)
                .abs()
                .max_element()
                / base.s[0];
            assert!(
                rot < 1e-7 && sig < 1e-7,
                "subnormal F: R {rot:e}, σ {sig:e}"
            );
        }
        for scale in [1e150, 1e-150, 1e300, 1e-300] {
            let fs = f * scale;
            check(&fs, 1e-14);
            for (d, b) in [(svd3(&fs), base), (svd3_jacobi(&fs), base_ref)] {
                // F · scale is rounded: R moves by ~ε σ₀/|σ₁ + σ₂|.
                let rot = max_abs(&(d.u * d.v.transpose() - b.u * b.v.transpose()))
                    * (b.s[1] + b.s[2]).abs()
                    / b.s[0];
                let sig = ((d.s / scale) - b.s).abs().max_element() / b.s[0];
                assert!(
                    rot < 1e-14 && sig < 1e-14,
                    "scale {scale:e}: R {rot:e}, σ {sig:e}"
                );
                conventions(&d, &fs);
            }
        }
    }
}

#[test]
fn non_finite_terminates() {
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let mut f = DMat3::IDENTITY;
        f.y_axis.z = bad;
        let _ = svd3(&f);
        let _ = svd3(&DMat3::from_diagonal(DVec3::splat(bad)));
    }
}

#[test]
fn jacobi_hook_is_scoped() {
    let f = Rng::seeded("hook").usv(DVec3::new(1.3, 0.9, 0.7));
    let d = svd3(&f);
    let r = with_jacobi_svd(|| svd3(&f));
    assert_eq!(r, svd3_jacobi(&f));
    assert_eq!(svd3(&f), d);
}

// ---------------------------------------------------------------------------------------------
// Model level: outputs with svd3 against the same call with svd3 replaced by svd3_jacobi.

/// `|a − b|` relative to `max(|b|, floor)`.
fn rel(a: f64, b: f64, floor: f64) -> f64 {
    (a - b).abs() / b.abs().max(floor)
}

fn rel_mat(a: &DMat3, b: &DMat3, floor: f64) -> f64 {
    max_abs(&(*a - *b)) / max_abs(b).max(floor)
}

/// Deviation of every field of two model gradients; scalars relative to their own size, but
/// no smaller than `1e-12` of the largest term they are built from (`floor`).
fn grad_dev(a: &ModelGrad, b: &ModelGrad, floor: f64) -> f64 {
    let fam = [
        (a.family.yield_stress, b.family.yield_stress),
        (a.family.eta, b.family.eta),
        (a.family.friction_alpha, b.family.friction_alpha),
    ];
    fam.iter().map(|&(x, y)| rel(x, y, 1e-300)).fold(
        rel_mat(&a.f_tmp, &b.f_tmp, 1e-300)
            .max(rel_mat(&a.c, &b.c, 1e-300))
            .max(rel(a.mu, b.mu, floor))
            .max(rel(a.lam, b.lam, floor)),
        f64::max,
    )
}

/// Deformation gradients covering the elastic range and the repeated-σ special cases.
fn model_cases(rng: &mut Rng, lo: f64, hi: f64) -> Vec<DMat3> {
    let mut fs = vec![DMat3::IDENTITY];
    for _ in 0..300 {
        let s = DVec3::new(rng.range(lo, hi), rng.range(lo, hi), rng.range(lo, hi));
        fs.push(rng.usv(s));
    }
    for _ in 0..100 {
        let (a, b) = (rng.range(lo, hi), rng.range(lo, hi));
        fs.push(DMat3::from_diagonal(DVec3::new(a, a, b)));
        fs.push(DMat3::from_diagonal(DVec3::new(b, a, a)));
        let rot = rng.rotation();
        fs.push(rot * DMat3::from_diagonal(DVec3::new(a, a, b)));
        fs.push(rng.usv(DVec3::new(a, b, b)));
        fs.push(rot * a);
        fs.push(rng.usv(DVec3::new(a, a * (1.0 + 1e-9), b)));
    }
    fs
}

/// Runs `update` and `update_adjoint` of `model` with svd3 and with svd3_jacobi on each F;
/// asserts deviations ≤ `tol` and returns (forward, adjoint) maxima.
fn compare_model<M: Constitutive>(name: &str, model: &M, fs: &[DMat3], tol: f64) -> (f64, f64) {
    let (mu, lam, dt) = (3.8e5, 5.8e5, 1e-4);
    let mut rng = Rng::seeded(name);
    let (mut fwd, mut adj) = (0.0f64, 0.0f64);
    for f in fs {
        let c = rng.mat(50.0);
        let (g_f, g_tau) = (rng.mat(1.0), rng.mat(1e-6));
        let run = || {
            (
                model.update(f, &c, mu, lam, dt),
                model.update_adjoint(f, &c, mu, lam, dt, &g_f, &g_tau),
            )
        };
        let ((f_new, tau), grad) = run();
        let ((f_ref, tau_ref), grad_ref) = with_jacobi_svd(run);
        let d_fwd = rel_mat(&f_new, &f_ref, 1e-300).max(rel_mat(&tau, &tau_ref, 1e-6 * mu));
        // μ and λ gradients are sums of terms of size |g_τ| μ-free stress ~ |g_τ| |F|²·(2 + …).
        let d_adj = grad_dev(&grad, &grad_ref, 1e-12);
        assert!(
            d_fwd <= tol && d_adj <= tol,
            "{name}: forward {d_fwd:e}, adjoint {d_adj:e} for F = {f:?}\n{grad:?}\n{grad_ref:?}"
        );
        fwd = fwd.max(d_fwd);
        adj = adj.max(d_adj);
    }
    println!(
        "{name}: forward {fwd:.1e}, adjoint {adj:.1e} over {} F",
        fs.len()
    );
    (fwd, adj)
}

#[test]
fn rotation_adjoint_matches() {
    let mut rng = Rng::seeded("rotation adjoint");
    let mut fs = model_cases(&mut rng, 0.3, 3.0);
    for _ in 0..200 {
        let s = stretch(&mut rng, 0.05, 20.0) * DVec3::new(1.0, 1.0, -1.0);
        fs.push(rng.usv(s));
    }
    let mut worst = 0.0f64;
    for f in &fs {
        let g = rng.mat(1.0);
        let a = rotation_adjoint(&svd3(f), &g);
        let b = rotation_adjoint(&svd3_jacobi(f), &g);
        let dev = rel_mat(&a, &b, 1e-300);
        assert!(dev <= 1e-11, "rotation_adjoint {dev:e} for F = {f:?}");
        worst = worst.max(dev);
    }
    println!("rotation_adjoint: {worst:.1e} over {} F", fs.len());
}

#[test]
fn fixed_corotated_matches() {
    let mut rng = Rng::seeded("fixed corotated");
    let mut fs = model_cases(&mut rng, 0.5, 1.5);
    for _ in 0..100 {
        let s = stretch(&mut rng, 0.5, 2.0) * DVec3::new(1.0, 1.0, -1.0);
        fs.push(rng.usv(s));
    }
    compare_model("fixed_corotated", &FixedCorotated, &fs, 1e-11);
}

#[test]
fn von_mises_matches() {
    let mut rng = Rng::seeded("von mises");
    let fs = model_cases(&mut rng, 0.6, 1.6);
    for (name, model) in [
        (
            "von_mises plastic",
            VonMises {
                yield_stress: 2e3,
                eta: 0.0,
            },
        ),
        (
            "von_mises viscous",
            VonMises {
                yield_stress: 2e3,
                eta: 5.0,
            },
        ),
        (
            "von_mises elastic",
            VonMises {
                yield_stress: 1e9,
                eta: 0.0,
            },
        ),
    ] {
        compare_model(name, &model, &fs, 1e-10);
    }
}

#[test]
fn drucker_prager_matches() {
    let mut rng = Rng::seeded("drucker prager");
    let compressed = model_cases(&mut rng, 0.6, 1.05);
    let mixed = model_cases(&mut rng, 0.7, 1.4);
    let model = DruckerPrager::from_friction_angle_deg(30.0);
    compare_model("drucker_prager compressed", &model, &compressed, 1e-10);
    compare_model("drucker_prager mixed", &model, &mixed, 1e-10);
}
