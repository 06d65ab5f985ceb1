//! Forward conformance with PAC-NeRF's own simulator (Taichi, f64) on the five fixture scenes:
//! 64 jittered particles with random v, C and F, so every term of the substep (APIC affine
//! transfer, stress, gravity, each return-mapping branch) is exercised and visible in x, v, C, F.
//! Checked after 1 substep (isolates one step) and after 10 (accumulation), f64 `atol 1e-8`.

mod common;

use pipe_mpm::{Constitutive, DruckerPrager, NeoHookean, Newtonian, Simulator, State, VonMises};

fn check<M: Constitutive>(name: &str, model: impl Fn(&common::Fixture) -> M) {
    let fx = common::load(name);
    let sim = Simulator::new(model(&fx), fx.config()).unwrap();
    let mut s = fx.initial.clone();
    let rep = sim.run(&mut s, &fx.material, 0.0, 1).unwrap();
    assert_eq!(rep.held, 0);
    report(name, "after 1", &s, &fx.after1);
    sim.run(&mut s, &fx.material, fx.dt, fx.n_substeps - 1)
        .unwrap();
    report(name, "after 10", &s, &fx.final_);
}

fn report(name: &str, when: &str, s: &State, r: &State) {
    let ex = common::max_diff_v(&s.x, &r.x);
    let ev = common::max_diff_v(&s.v, &r.v);
    let ec = common::max_diff_m(&s.c, &r.c);
    let ef = common::max_diff_m(&s.f, &r.f);
    println!("{name} {when}: |dx| {ex:.2e} |dv| {ev:.2e} |dC| {ec:.2e} |dF| {ef:.2e}");
    for (q, e) in [("x", ex), ("v", ev), ("C", ec), ("F", ef)] {
        assert!(e < 1e-8, "{name} {when}: {q} differs by {e:e}");
    }
}

#[test]
fn elastic_neo_hookean() {
    check("elastic", |_| NeoHookean);
}

#[test]
fn plasticine_von_mises() {
    check("plasticine", |f| VonMises {
        yield_stress: f.param("yield_stress"),
        eta: f.param("eta"),
    });
}

#[test]
fn viscoplastic_von_mises() {
    check("viscoplastic", |f| VonMises {
        yield_stress: f.param("yield_stress"),
        eta: f.param("eta"),
    });
}

#[test]
fn newtonian_fluid() {
    check("newtonian", |_| Newtonian);
}

#[test]
fn sand_drucker_prager() {
    check("sand", |f| DruckerPrager {
        alpha: f.param("friction_alpha"),
    });
}

/// The comparison helpers fail on a NaN (which `f64::max` would drop) and on arrays of
/// different lengths (a missing particle or gradient), instead of passing a tolerance check.
mod helpers_refuse {
    use glam::{DMat3, DVec3};

    use super::common::{max_abs_m, max_abs_s, max_abs_v, max_diff_m, max_diff_s, max_diff_v};

    #[test]
    fn agree_on_finite_equal_length_arrays() {
        let a = [DVec3::new(1.0, -2.0, 0.5), DVec3::ZERO];
        let b = [DVec3::new(1.0, -1.5, 0.5), DVec3::ZERO];
        assert_eq!(max_diff_v(&a, &b), 0.5);
        assert_eq!(max_abs_v(&a), 2.0);
        assert_eq!(max_diff_s(&[1.0, 3.0], &[1.0, 1.0]), 2.0);
        assert_eq!(max_abs_s(&[-4.0, 3.0]), 4.0);
        assert_eq!(max_diff_m(&[DMat3::IDENTITY], &[DMat3::ZERO]), 1.0);
        assert_eq!(max_abs_m(&[DMat3::IDENTITY * -3.0]), 3.0);
    }

    #[test]
    #[should_panic(expected = "max_diff_v: element 1 is NaN")]
    fn a_nan_component_fails_max_diff_v() {
        let a = [DVec3::ZERO, DVec3::new(0.0, f64::NAN, 0.0)];
        max_diff_v(&a, &[DVec3::ZERO; 2]);
    }

    #[test]
    #[should_panic(expected = "max_diff_m: element 0 is NaN")]
    fn a_nan_entry_fails_max_diff_m() {
        let mut m = DMat3::IDENTITY;
        m.z_axis.x = f64::NAN;
        max_diff_m(&[m], &[DMat3::IDENTITY]);
    }

    #[test]
    #[should_panic(expected = "max_abs_s: element 2 is NaN")]
    fn a_nan_fails_max_abs_s() {
        max_abs_s(&[0.0, 1.0, f64::NAN]);
    }

    #[test]
    #[should_panic(expected = "the arrays have 3 and 2 elements")]
    fn a_missing_element_fails_max_diff_s() {
        max_diff_s(&[0.0; 3], &[0.0; 2]);
    }

    #[test]
    #[should_panic(expected = "max_diff_v: the arrays have 1 and 2 elements")]
    fn a_missing_particle_fails_max_diff_v() {
        max_diff_v(&[DVec3::ZERO], &[DVec3::ZERO; 2]);
    }
}
