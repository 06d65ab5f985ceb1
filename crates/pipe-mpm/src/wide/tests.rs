//! The vectorised engine in `f32` against `f64` (every family, forces, boundaries, walls): the
//! same physics to `f32` precision; bit-identical for any thread count and instruction set,
//! and whether its buffers are fresh or kept from another run. (The `f64` results themselves
//! are checked against the PAC-NeRF fixtures and by finite differences in `tests/`.)

use glam::{DMat3, DVec3};

use crate::isa::CapGuard;
use crate::{
    Aabb, Boundaries, BoundaryKind, Collider, Constitutive, DruckerPrager, FixedCorotated,
    Material, NeoHookean, Newtonian, ParticleForce, Precision, RunReport, SimConfig, Simulator,
    State, VonMises,
};

/// A spinning, sheared blob over a sticky ground inside separating walls, particles near each
/// wall moving out of it, an impulse on a set of particles; `n` particles in random order.
fn scene(n: usize) -> (SimConfig, State) {
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.04, 2e-4);
    cfg.boundaries = Boundaries {
        colliders: vec![Collider::ground(0.05, BoundaryKind::Slip)],
        walls: Some(BoundaryKind::Separate),
    };
    cfg.forces = vec![ParticleForce::Impulse {
        particles: (0..n).step_by(7).collect(),
        impulse: DVec3::new(0.0, 2e-6, 1e-6),
        time: 3e-4,
    }];
    let mut x = Vec::new();
    for i in 0..n as u32 {
        let h = |k: u32| (i.wrapping_mul(2_654_435_761).rotate_left(k) % 10007) as f64 / 10007.0;
        x.push(DVec3::new(
            0.3 + 0.3 * h(0),
            0.06 + 0.3 * h(11),
            0.35 + 0.3 * h(22),
        ));
    }
    let mut s = State::at_rest(x);
    for (k, (x, v)) in s.x.iter().zip(s.v.iter_mut()).enumerate() {
        let r = *x - DVec3::new(0.45, 0.2, 0.5);
        *v = DVec3::new(
            2.0 * r.y - 0.5,
            -1.5 * r.x - 0.2 * (k % 3) as f64,
            0.3 - r.z,
        );
    }
    for (k, dir) in [DVec3::NEG_X, DVec3::X, DVec3::Y, DVec3::NEG_Z]
        .into_iter()
        .enumerate()
    {
        let p = DVec3::splat(0.5) + dir * 0.5;
        s.x[k] = p - dir * 1e-4;
        s.v[k] = dir * 3.0;
    }
    for (k, c) in s.c.iter_mut().enumerate() {
        *c = DMat3::from_cols_array(&[0.1, 0.0, 0.2, 0.0, -0.3, 0.1, 0.05, 0.0, 0.2])
            * (k % 4) as f64;
    }
    (cfg, s)
}

fn run_with<M: Constitutive>(
    model: M,
    mat: &Material,
    steps: usize,
    f32_: bool,
) -> (State, RunReport) {
    let (mut cfg, mut s) = scene(mat.len());
    cfg.precision = if f32_ { Precision::F32 } else { Precision::F64 };
    let sim = Simulator::new(model, cfg).unwrap();
    let rep = sim.run(&mut s, mat, 0.0, steps).unwrap();
    (s, rep)
}

/// Largest difference of positions (m), velocities (m/s) and `F`.
fn diff(a: &State, b: &State) -> (f64, f64, f64) {
    let mut d = (0f64, 0f64, 0f64);
    for i in 0..a.len() {
        d.0 = d.0.max((a.x[i] - b.x[i]).abs().max_element());
        d.1 = d.1.max((a.v[i] - b.v[i]).abs().max_element());
        d.2 = d.2.max(crate::math::max_abs(&(a.f[i] - b.f[i])));
    }
    d
}

fn materials(n: usize) -> Material {
    let mut m = Material::from_e_nu(n, 1e-6, 1000.0, 3e4, 0.3).unwrap();
    for (i, (mu, lam)) in m.mu.iter_mut().zip(m.lam.iter_mut()).enumerate() {
        *mu *= 1.0 + 0.5 * (i % 5) as f64;
        *lam *= 1.0 + 0.3 * (i % 3) as f64;
    }
    m
}

fn compare<M: Constitutive>(model: M, tol: (f64, f64, f64)) {
    let n = 3000;
    let mat = if M::NAME == "newtonian" {
        Material::fluid(n, 1e-6, 1000.0, 0.5, 2e4).unwrap()
    } else {
        materials(n)
    };
    let steps = 40;
    let (s64, rep64) = run_with(model.clone(), &mat, steps, false);
    let (s32, rep32) = run_with(model.clone(), &mat, steps, true);
    let d = diff(&s64, &s32);
    assert_eq!(rep64, rep32, "{}", M::NAME);
    assert!(rep64.held > 0, "the scene holds particles at the walls");
    assert!(
        d.0 <= tol.0 && d.1 <= tol.1 && d.2 <= tol.2,
        "{} f32 against f64: {d:?}",
        M::NAME
    );
    // Something moved: the comparison is not of two states at rest.
    assert!(diff(&s64, &scene(n).1).0 > 1e-3);
}

#[test]
fn f32_matches_f64_for_every_family() {
    let tol = (2e-6, 2e-3, 2e-5);
    compare(NeoHookean, tol);
    compare(FixedCorotated, tol);
    compare(
        VonMises {
            yield_stress: 300.0,
            eta: 0.5,
        },
        tol,
    );
    compare(Newtonian, tol);
    compare(DruckerPrager::from_friction_angle_deg(30.0), tol);
}

/// Same bits with 1 and 2 threads, and with AVX2 and the portable lanes.
#[test]
fn bit_identical_across_threads_and_instruction_sets() {
    let n = 2500;
    let mat = materials(n);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let isa = CapGuard::lock();
    for f32_ in [true, false] {
        isa.set(0);
        let a = one.install(|| run_with(FixedCorotated, &mat, 12, f32_));
        let b = two.install(|| run_with(FixedCorotated, &mat, 12, f32_));
        assert_eq!(a, b, "threads, f32 {f32_}");
        for cap in [1, 2] {
            isa.set(cap);
            let c = two.install(|| run_with(FixedCorotated, &mat, 12, f32_));
            assert_eq!(a, c, "instruction set cap {cap}, f32 {f32_}");
        }
    }
}

/// A simulator reuses its buffers from one run to the next: the results are those of a fresh
/// simulator (a clone starts with none), also after a run with another particle count.
#[test]
fn reused_buffers_give_the_same_bits() {
    let n = 1500;
    let mat = materials(n);
    let (mut cfg, s0) = scene(n);
    cfg.precision = crate::Precision::F32;
    cfg.forces.clear();
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let (mut a, mut b) = (s0.clone(), s0.clone());
    for _ in 0..3 {
        sim.run(&mut a, &mat, 0.0, 5).unwrap();
        sim.clone().run(&mut b, &mat, 0.0, 5).unwrap();
        assert_eq!(a, b);
    }
    let (_, small) = scene(700);
    let mut c = small.clone();
    sim.run(&mut c, &materials(700), 0.0, 5).unwrap();
    sim.run(&mut a, &mat, 0.0, 5).unwrap();
    sim.clone().run(&mut b, &mat, 0.0, 5).unwrap();
    assert_eq!(a, b);
}
