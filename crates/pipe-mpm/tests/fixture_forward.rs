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
