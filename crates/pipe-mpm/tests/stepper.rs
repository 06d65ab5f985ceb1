//! A state kept in the engine between runs ([`Stepper`]) must step as [`Simulator::run`]
//! does: bit for bit over one run (both load and sort the same way), to rounding over many
//! (a kept state keeps its particle groups where each run sorts afresh), for any thread count
//! bit for bit, and it must read back exactly what it holds.

#[path = "common/rng.rs"]
mod rng;

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, Material, MpmError, NeoHookean, ParticleForce, Precision, SimConfig, Simulator, State,
};
use rng::Rng;

/// A falling, spinning block of `n` random particles with an impulse on some of them, in
/// `precision`.
fn scene(precision: Precision) -> (Simulator<NeoHookean>, State, Material) {
    let mut rng = Rng::seeded("stepper");
    let mut r = move || rng.unit();
    let n = 3000;
    let x: Vec<DVec3> = (0..n)
        .map(|_| DVec3::new(0.3 + 0.3 * r(), 0.15 + 0.3 * r(), 0.3 + 0.3 * r()))
        .collect();
    let mut s = State::at_rest(x);
    for p in 0..n {
        let d = s.x[p] - DVec3::new(0.45, 0.3, 0.45);
        s.v[p] = DVec3::new(-3.0 * d.z, -0.5, 3.0 * d.x);
        s.c[p] = DMat3::from_diagonal(DVec3::new(r() - 0.5, r() - 0.5, r() - 0.5));
    }
    let mat = Material::from_e_nu(n, 1e-6, 1000.0, 2e4, 0.3).unwrap();
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.03, 1e-4);
    cfg.precision = precision;
    cfg.forces = vec![
        ParticleForce::Impulse {
            particles: (0..n).step_by(7).collect(),
            impulse: DVec3::new(2e-6, 0.0, 0.0),
            time: 1.5e-3,
        },
        ParticleForce::Force {
            particles: (0..n).step_by(5).collect(),
            force: DVec3::new(0.0, 0.0, 1e-3),
            start: 1e-3,
            end: 3e-3,
        },
    ];
    (Simulator::new(NeoHookean, cfg).unwrap(), s, mat)
}

/// Frames of different substeps (s) and counts, as `pipe simulate` takes them.
const FRAMES: [(f64, usize); 4] = [(1e-4, 10), (0.8e-4, 12), (1.2e-4, 7), (1e-4, 11)];

/// The state after [`FRAMES`], stepped by `Simulator::run` frame after frame.
fn by_runs(precision: Precision) -> State {
    let (mut sim, mut s, mat) = scene(precision);
    let mut t = 0.0;
    for (dt, n) in FRAMES {
        sim.set_dt(dt).unwrap();
        sim.run(&mut s, &mat, t, n).unwrap();
        t += dt * n as f64;
    }
    s
}

/// The state after [`FRAMES`] in one stepper, reading the motion after every frame (as the
/// command does); and the held-particle reports.
fn by_stepper(precision: Precision, threads: usize) -> (State, usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let (sim, mut s, mat) = scene(precision);
        let mut stepper = sim.stepper(&mut s, &mat).unwrap();
        let (mut t, mut held) = (0.0, 0);
        for (dt, n) in FRAMES {
            let rep = stepper.advance(t, dt, n).unwrap();
            assert_eq!(rep.substeps, n);
            held += rep.held;
            stepper.read_motion(&mut s).unwrap();
            t += dt * n as f64;
        }
        let whole = stepper.state();
        assert_eq!((whole.x.clone(), whole.v.clone()), (s.x, s.v));
        (whole, held)
    })
}

fn max_dist(a: &[DVec3], b: &[DVec3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0, f64::max)
}

#[test]
fn one_run_is_bit_identical_to_simulator_run() {
    for precision in [Precision::F64, Precision::F32] {
        let (sim, s0, mat) = scene(precision);
        let mut a = s0.clone();
        let rep_a = sim.run(&mut a, &mat, 0.0, 25).unwrap();
        let mut b = s0.clone();
        let mut stepper = sim.stepper(&mut b, &mat).unwrap();
        let rep_b = stepper.advance(0.0, 1e-4, 25).unwrap();
        stepper.read(&mut b).unwrap();
        assert_eq!(rep_a, rep_b, "{precision:?}");
        assert_eq!(a, b, "{precision:?}");
    }
}

#[test]
fn frames_match_runs_frame_by_frame_to_rounding() {
    for (precision, tol) in [(Precision::F64, 1e-12), (Precision::F32, 2e-6)] {
        let runs = by_runs(precision);
        let (kept, _) = by_stepper(precision, 1);
        let d = max_dist(&runs.x, &kept.x);
        assert!(d < tol, "{precision:?}: positions differ by {d:e} m");
        let dv = max_dist(&runs.v, &kept.v);
        assert!(
            dv < 1e3 * tol,
            "{precision:?}: velocities differ by {dv:e} m/s"
        );
        // The block moved: the comparison is not of two unmoved states.
        let (_, s0, _) = scene(precision);
        assert!(max_dist(&s0.x, &kept.x) > 1e-3);
    }
}

#[test]
fn thread_counts_give_the_same_bits() {
    for precision in [Precision::F64, Precision::F32] {
        let a = by_stepper(precision, 1);
        let b = by_stepper(precision, 2);
        assert_eq!(a, b, "{precision:?}");
    }
}

#[test]
fn read_motion_leaves_c_and_f() {
    let (sim, mut s, mat) = scene(Precision::F64);
    let mut stepper = sim.stepper(&mut s, &mat).unwrap();
    stepper.advance(0.0, 1e-4, 5).unwrap();
    let mut motion = s.clone();
    motion
        .c
        .iter_mut()
        .for_each(|c| *c = DMat3::from_diagonal(DVec3::splat(7.0)));
    stepper.read_motion(&mut motion).unwrap();
    let whole = stepper.state();
    assert_eq!(motion.x, whole.x);
    assert_eq!(motion.v, whole.v);
    assert!(
        motion
            .c
            .iter()
            .all(|c| *c == DMat3::from_diagonal(DVec3::splat(7.0)))
    );
    assert_eq!(motion.f, s.f, "F was written");
    assert_ne!(whole.f, s.f, "F did not change");
}

#[test]
fn bad_substep_length_and_non_finite_values_are_errors() {
    let (sim, mut s, mat) = scene(Precision::F64);
    let mut stepper = sim.stepper(&mut s, &mat).unwrap();
    for dt in [0.0, -1e-4, f64::NAN] {
        let e = stepper.advance(0.0, dt, 1).unwrap_err();
        assert!(
            matches!(e, MpmError::InvalidParameter { field: "dt", .. }),
            "{e}"
        );
    }
    let mut short = State::at_rest(vec![DVec3::ZERO; 10]);
    let e = stepper.read_motion(&mut short).unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::LengthMismatch {
                field: "x",
                len: 10,
                expected: 3000
            }
        ),
        "{e}"
    );
    drop(stepper);

    // det F < 0 for one particle: ln J is NaN at the first substep.
    s.f[17] = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0));
    let mut stepper = sim.stepper(&mut s, &mat).unwrap();
    match stepper.advance(0.0, 1e-4, 3) {
        Err(MpmError::NonFinite { substep, .. }) => assert_eq!(substep, 0),
        other => panic!("{other:?}"),
    }
    let after = stepper.state();
    assert!(after.first_non_finite().is_some());
}
