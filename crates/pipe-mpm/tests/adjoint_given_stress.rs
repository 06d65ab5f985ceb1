//! `Constitutive::update_adjoint_given_stress` (the backward pass hands the model the stress its
//! forward pass computed) must equal `update_adjoint` to round-off for every model: fixed
//! corotated recovers `R` from the stress, and must fall back to the polar iteration where
//! that is ill-conditioned (flat or inverted `F`) or where the stress belongs to another `F`.

use glam::{DMat3, DVec3};
use pipe_mpm::math::max_abs;
use pipe_mpm::{Constitutive, DruckerPrager, FixedCorotated, ModelGrad, NeoHookean, VonMises};

#[path = "common/rng.rs"]
mod rng;
use rng::Rng;

const DT: f64 = 1e-4;

/// Largest difference of the two adjoints relative to their size.
fn rel_diff(a: &ModelGrad, b: &ModelGrad) -> f64 {
    let scale = max_abs(&a.f_tmp).max(a.mu.abs()).max(a.lam.abs()).max(1.0);
    let d = max_abs(&(a.f_tmp - b.f_tmp))
        .max(max_abs(&(a.c - b.c)))
        .max((a.mu - b.mu).abs())
        .max((a.lam - b.lam).abs());
    d / scale
}

/// μ, λ (Pa) of the tests: E = 1 kPa, ν = 0.2.
const LAME: (f64, f64) = (1e3 / 2.4, 1e3 * 0.2 / (1.2 * 0.6));

/// Both adjoints of `model` at `f` with the stress `tau` handed over.
fn both<M: Constitutive>(model: &M, f: &DMat3, tau: &DMat3, g: &(DMat3, DMat3)) -> f64 {
    both_with(model, f, tau, g, LAME)
}

fn both_with<M: Constitutive>(
    model: &M,
    f: &DMat3,
    tau: &DMat3,
    g: &(DMat3, DMat3),
    (mu, lam): (f64, f64),
) -> f64 {
    let c = DMat3::from_cols_array(&[0.1, -0.2, 0.3, 0.0, 0.5, -0.1, 0.2, 0.1, -0.4]);
    let a = model.update_adjoint(f, &c, mu, lam, DT, &g.0, &g.1);
    let aux = model.update_with_aux(f, &c, mu, lam, DT).2;
    let b = model.update_adjoint_given_stress(f, &c, mu, lam, DT, (tau, aux), &g.0, &g.1);
    rel_diff(&a, &b)
}

fn stress_of<M: Constitutive>(model: &M, f: &DMat3) -> DMat3 {
    stress_with(model, f, LAME)
}

fn stress_with<M: Constitutive>(model: &M, f: &DMat3, (mu, lam): (f64, f64)) -> DMat3 {
    model.update(f, &DMat3::ZERO, mu, lam, DT).1
}

#[test]
fn adjoint_given_the_forward_stress_matches() {
    let mut rng = Rng::seeded("adjoint_given_stress");
    let g = (rng.mat(1.0), rng.mat(1.0));
    let mut worst = [0.0f64; 4];
    for amp in [1e-6, 1e-3, 1e-1, 0.5] {
        for _ in 0..1000 {
            let f = rng.rotation() * (DMat3::IDENTITY + rng.mat(amp));
            let d = [
                both(&FixedCorotated, &f, &stress_of(&FixedCorotated, &f), &g),
                both(&NeoHookean, &f, &stress_of(&NeoHookean, &f), &g),
                both(
                    &VonMises {
                        yield_stress: 500.0,
                        eta: 0.0,
                    },
                    &f,
                    &DMat3::IDENTITY,
                    &g,
                ),
                both(
                    &DruckerPrager::from_friction_angle_deg(30.0),
                    &f,
                    &DMat3::IDENTITY,
                    &g,
                ),
            ];
            for (w, d) in worst.iter_mut().zip(d) {
                *w = w.max(d);
            }
        }
    }
    assert!(worst[0] < 1e-11, "fixed corotated: {:e}", worst[0]);
    // The other models ignore the stress: identical.
    assert_eq!(&worst[1..], &[0.0; 3]);
}

#[test]
fn fixed_corotated_falls_back_where_the_stress_cannot_give_r() {
    let mut rng = Rng::seeded("adjoint_given_stress_fallback");
    let g = (rng.mat(1.0), rng.mat(1.0));
    let flat = rng.usv(DVec3::new(1.2, 0.9, 1e-5));
    let inverted = rng.usv(DVec3::new(1.1, 0.8, -0.7));
    let near_zero = rng.usv(DVec3::new(1e-60, 2e-60, 3e-60));
    for f in [flat, inverted, near_zero] {
        let d = both(&FixedCorotated, &f, &stress_of(&FixedCorotated, &f), &g);
        assert!(d < 1e-11, "{f:?}: {d:e}");
    }
    // A stress that belongs to another F (here: rotated) must not be used.
    let f = rng.usv(DVec3::new(1.1, 0.95, 0.9));
    let other = DMat3::from_rotation_z(0.3) * f;
    let d = both(&FixedCorotated, &f, &stress_of(&FixedCorotated, &other), &g);
    assert!(d < 1e-11, "foreign stress: {d:e}");
    assert!(both(&FixedCorotated, &f, &DMat3::ZERO, &g) < 1e-11);
}

/// The extremes the simulator accepts (E from 1e2 to 1e9 Pa, ν from 0 to 0.499): λ/μ up to
/// ~500 amplifies the rounding of the stress, which must stay far below the gradient tolerance.
#[test]
fn fixed_corotated_stress_rotation_holds_at_extreme_materials() {
    let mut rng = Rng::seeded("adjoint_given_stress_extremes");
    let g = (rng.mat(1.0), rng.mat(1.0));
    for (e, nu) in [
        (1e2, 0.0),
        (1e9, 0.0),
        (1e2, 0.499),
        (1e9, 0.499),
        (3e5, 0.3),
    ] {
        let lame = pipe_mpm::lame(e, nu).unwrap();
        let mut worst = 0.0f64;
        for amp in [1e-6, 1e-3, 0.1, 0.4] {
            for _ in 0..200 {
                let f = rng.rotation() * (DMat3::IDENTITY + rng.mat(amp));
                let tau = stress_with(&FixedCorotated, &f, lame);
                worst = worst.max(both_with(&FixedCorotated, &f, &tau, &g, lame));
            }
        }
        assert!(worst < 1e-10, "E = {e:e}, nu = {nu}: {worst:e}");
    }
}
