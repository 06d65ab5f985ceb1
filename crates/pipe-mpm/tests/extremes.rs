//! Extremes (ARCHITECTURE §10): E from 1e2 to 1e9 Pa and ν from 0 to 0.499 for every solid
//! model, each run at the step the stability limit allows, a block dropped onto sticky ground
//! with a particle starting exactly on the domain edge. Every run must stay finite, keep every
//! particle inside the domain and not gain energy (max speed stays below the free-fall bound).

mod common;

use glam::DVec3;
use pipe_mpm::{
    Aabb, Constitutive, DruckerPrager, FixedCorotated, Material, NeoHookean, SimConfig, Simulator,
    StepLimits, VonMises, stable_step,
};

fn drop_block<M: Constitutive + Clone>(model: M, e: f64, nu: f64) {
    let dx = 0.05;
    let mut s = common::thrown_block(dx);
    let mat = Material::from_e_nu(s.len(), (dx / 2.0f64).powi(3), 1000.0, e, nu).unwrap();
    let dt = stable_step(&model, &s, &mat, dx, StepLimits::default()).dt();
    let sim = Simulator::new(
        model,
        SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, dt),
    )
    .unwrap();
    let n = 100;
    sim.run(&mut s, &mat, 0.0, n)
        .unwrap_or_else(|err| panic!("{} E={e} nu={nu}: {err}", M::NAME));
    let vmax = s.v.iter().map(|v| v.length()).fold(0.0, f64::max);
    let bound = 1.0 + 9.8 * n as f64 * dt + 1e-9;
    assert!(
        vmax <= bound * 1.5,
        "{} E={e} nu={nu}: speed {vmax} m/s",
        M::NAME
    );
    assert!(s.x.iter().all(|x| sim.grid().domain.contains(*x)));
}

#[test]
fn every_solid_model_over_the_parameter_range() {
    for e in [1e2, 1e5, 1e9] {
        for nu in [0.0, 0.3, 0.499] {
            drop_block(NeoHookean, e, nu);
            drop_block(FixedCorotated, e, nu);
            drop_block(
                VonMises {
                    yield_stress: 1e-3 * e,
                    eta: 0.0,
                },
                e,
                nu,
            );
            drop_block(DruckerPrager::from_friction_angle_deg(30.0), e, nu);
        }
    }
}
