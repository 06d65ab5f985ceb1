//! Reverse-mode conformance with PAC-NeRF's Taichi autodiff on the five fixture scenes.
//! Loss `L = Σ x_final · W` after 10 substeps (README §3). Every gradient array must match to
//! `1e-6 · max|g_ref|` and each scalar (E, ν, τ_Y, η, α, fluid μ, κ) to `rtol 1e-6`; the run
//! uses a checkpoint every 3 substeps so segment recomputation is part of what is checked.

mod common;

use pipe_mpm::{
    BackwardOptions, Constitutive, DruckerPrager, Gradients, NeoHookean, Newtonian, Simulator,
    VonMises,
};

fn run<M: Constitutive>(fx: &common::Fixture, model: M) -> Gradients {
    let sim = Simulator::new(model, fx.config()).unwrap();
    let mut s = fx.initial.clone();
    let tape = sim
        .forward_tape(&mut s, &fx.material, 0.0, fx.n_substeps, 3)
        .unwrap();
    let loss: f64 = s.x.iter().zip(&fx.loss_w).map(|(x, w)| x.dot(*w)).sum();
    let lref = fx.json["loss"]["value"].as_f64().unwrap();
    assert!((loss - lref).abs() < 1e-12, "loss {loss} vs {lref}");
    let seed = fx.seed();
    sim.backward(
        &tape,
        &fx.material,
        |k, _| (k == fx.n_substeps).then(|| seed.clone()),
        BackwardOptions::default(),
    )
    .unwrap()
}

fn arrays(name: &str, fx: &common::Fixture, g: &Gradients) {
    let checks = [
        (
            "x0",
            common::max_diff_v(&g.state.x, &fx.grads.x),
            common::max_abs_v(&fx.grads.x),
        ),
        (
            "v0",
            common::max_diff_v(&g.state.v, &fx.grads.v),
            common::max_abs_v(&fx.grads.v),
        ),
        (
            "C0",
            common::max_diff_m(&g.state.c, &fx.grads.c),
            common::max_abs_m(&fx.grads.c),
        ),
        (
            "F0/J0",
            common::max_diff_m(&g.state.f, &fx.grads.f),
            common::max_abs_m(&fx.grads.f),
        ),
        (
            "mass",
            common::max_diff_s(&g.material.mass, &fx.grad_mass),
            common::max_abs_s(&fx.grad_mass),
        ),
        (
            "mu_p",
            common::max_diff_s(&g.material.mu, &fx.grad_mu),
            common::max_abs_s(&fx.grad_mu),
        ),
        (
            "lam_p",
            common::max_diff_s(&g.material.lam, &fx.grad_lam),
            common::max_abs_s(&fx.grad_lam),
        ),
    ];
    for (q, diff, scale) in checks {
        let rel = diff / scale;
        println!("{name} grad {q}: max diff {diff:.2e} = {rel:.2e} of max");
        assert!(rel < 1e-6, "{name}: grad {q} rel {rel:e}");
    }
}

fn scalar(name: &str, q: &str, got: f64, want: f64) {
    let rel = (got - want).abs() / want.abs();
    println!("{name} grad {q}: {got:e} vs {want:e}, rel {rel:.2e}");
    assert!(
        rel < 1e-6,
        "{name}: grad {q} {got:e} vs {want:e} rel {rel:e}"
    );
}

fn e_nu(name: &str, fx: &common::Fixture, g: &Gradients) {
    let (ge, gn) = g.material.e_nu(fx.param("E"), fx.param("nu"));
    scalar(name, "E", ge, fx.grad("E"));
    scalar(name, "nu", gn, fx.grad("nu"));
}

#[test]
fn elastic() {
    let fx = common::load("elastic");
    let g = run(&fx, NeoHookean);
    arrays("elastic", &fx, &g);
    e_nu("elastic", &fx, &g);
}

fn von_mises(name: &str) {
    let fx = common::load(name);
    let g = run(
        &fx,
        VonMises {
            yield_stress: fx.param("yield_stress"),
            eta: fx.param("eta"),
        },
    );
    arrays(name, &fx, &g);
    e_nu(name, &fx, &g);
    scalar(
        name,
        "yield_stress",
        g.material.family.yield_stress,
        fx.grad("yield_stress"),
    );
    scalar(name, "eta", g.material.family.eta, fx.grad("eta"));
}

#[test]
fn plasticine() {
    von_mises("plasticine");
}

#[test]
fn viscoplastic() {
    von_mises("viscoplastic");
}

#[test]
fn newtonian() {
    let fx = common::load("newtonian");
    let g = run(&fx, Newtonian);
    arrays("newtonian", &fx, &g);
    let (gm, gk) = g.material.fluid_mu_kappa();
    scalar("newtonian", "fluid_mu", gm, fx.grad("fluid_mu"));
    scalar("newtonian", "fluid_kappa", gk, fx.grad("fluid_kappa"));
}

#[test]
fn sand() {
    let fx = common::load("sand");
    let g = run(
        &fx,
        DruckerPrager {
            alpha: fx.param("friction_alpha"),
        },
    );
    arrays("sand", &fx, &g);
    e_nu("sand", &fx, &g);
    scalar(
        "sand",
        "friction_alpha",
        g.material.family.friction_alpha,
        fx.grad("friction_alpha"),
    );
    let phi = fx.param("friction_angle_deg");
    let g_phi = g.material.family.friction_alpha * DruckerPrager::dalpha_dphi_deg(phi);
    scalar(
        "sand",
        "friction_angle_deg",
        g_phi,
        fx.grad("friction_angle_deg"),
    );
}
