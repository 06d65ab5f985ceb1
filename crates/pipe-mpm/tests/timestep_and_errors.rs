//! Time-step control and typed errors: the stability limits follow their formulas, a
//! user-fixed substep count beyond a limit is rejected naming that limit, a blow-up is reported
//! with the substep and quantity, and invalid inputs name the field and value.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, Material, MpmError, NeoHookean, Newtonian, SimConfig, Simulator, State, StepLimits, lame,
    stable_step, substeps_per_frame,
};

fn cfg(dt: f64) -> SimConfig {
    SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.05, dt)
}

#[test]
fn wave_limit_matches_formula_and_sets_substeps() {
    let (e, nu, rho, dx) = (1e6, 0.3, 1000.0, 0.05);
    let mut s = State::at_rest(vec![DVec3::splat(0.5); 4]);
    s.v[2] = DVec3::new(3.0, 4.0, 0.0);
    let mat = Material::from_e_nu(4, 1e-5, rho, e, nu).unwrap();
    let st = stable_step(&NeoHookean, &s, &mat, dx, StepLimits::default());
    let (mu, lam) = lame(e, nu).unwrap();
    let want = 0.3 * dx / (5.0 + ((lam + 2.0 * mu) / rho).sqrt());
    assert!((st.wave - want).abs() < 1e-15 * want);
    // A fixed step may go up to CFL number 0.5; automatic steps use 0.3.
    assert!((st.wave_max - want * 0.5 / 0.3).abs() < 1e-15 * want);
    assert!((st.cfl_number(st.wave) - 0.3).abs() < 1e-15);
    assert!((st.cfl_number(st.wave_max) - 0.5).abs() < 1e-15);
    assert_eq!(st.max_fixed_dt(), st.wave_max);
    assert!(st.check(0.99 * st.wave_max).is_ok() && st.check(1.01 * st.wave_max).is_err());
    assert_eq!(st.viscous, f64::INFINITY);
    assert_eq!(st.limit(), "elastic wave (CFL)");
    let frame = 1.0 / 24.0;
    let n = substeps_per_frame(&st, frame, None).unwrap();
    assert!(frame / n as f64 <= st.dt() && frame / (n - 1) as f64 > st.dt());
    let m = st.fixed_substeps_needed(frame);
    assert!(m < n && frame / m as f64 <= st.wave_max && frame / (m - 1) as f64 > st.wave_max);
    assert_eq!(substeps_per_frame(&st, frame, Some(m)).unwrap(), m);
    assert!(substeps_per_frame(&st, frame, Some(m - 1)).is_err());
    match substeps_per_frame(&st, frame, Some(n / 2)) {
        Err(MpmError::StepTooLarge { limit, dt, max_dt }) => {
            assert_eq!(limit, "elastic wave (CFL)");
            assert!(dt > max_dt);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(substeps_per_frame(&st, frame, Some(n)).unwrap(), n);
}

#[test]
fn viscous_limit_binds_for_a_thick_fluid() {
    let s = State::at_rest(vec![DVec3::splat(0.5); 2]);
    let mat = Material::fluid(2, 1e-5, 1000.0, 1e4, 1e4).unwrap();
    let st = stable_step(&Newtonian, &s, &mat, 0.05, StepLimits::default());
    assert_eq!(st.limit(), "viscous");
    let err = st.check(st.viscous * 1.01).unwrap_err();
    assert!(err.to_string().contains("viscous"), "{err}");
}

#[test]
fn blow_up_names_substep_and_quantity() {
    let sim = Simulator::new(NeoHookean, cfg(1e-4)).unwrap();
    let mut s = State::at_rest(vec![DVec3::splat(0.5), DVec3::new(0.52, 0.5, 0.5)]);
    s.f[1] = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0)); // det F < 0: ln J is NaN
    let mat = Material::from_e_nu(2, 1e-5, 1000.0, 1e4, 0.3).unwrap();
    match sim.run(&mut s, &mat, 0.0, 5) {
        Err(MpmError::NonFinite {
            substep, quantity, ..
        }) => {
            assert_eq!(substep, 0);
            assert!(["x", "v", "C"].contains(&quantity), "{quantity}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn invalid_inputs_name_field_and_value() {
    let e = Material::from_e_nu(1, 1e-5, 1000.0, 1e5, 0.5).unwrap_err();
    assert!(matches!(e, MpmError::InvalidParameter { field: "nu", value, .. } if value == 0.5));
    assert!(
        e.to_string().contains("nu") && e.to_string().contains("0.5"),
        "{e}"
    );
    let e = Material::from_e_nu(1, 1e-5, 1000.0, -3.0, 0.3).unwrap_err();
    assert!(
        matches!(e, MpmError::InvalidParameter { field: "E", value, .. } if value == -3.0),
        "{e}"
    );
    let e = Material::from_e_nu(1, 1e-5, 1000.0, 0.0, 0.3).unwrap_err();
    assert!(
        matches!(e, MpmError::InvalidParameter { field: "E", .. }),
        "{e}"
    );
    let sim = Simulator::new(NeoHookean, cfg(1e-4)).unwrap();
    let mut empty = State::at_rest(vec![]);
    let mat = Material {
        mass: vec![],
        volume: vec![],
        mu: vec![],
        lam: vec![],
        family: Vec::new(),
    };
    assert_eq!(
        sim.run(&mut empty, &mat, 0.0, 1).unwrap_err(),
        MpmError::EmptyParticles
    );
    let mut s = State::at_rest(vec![DVec3::splat(0.5), DVec3::new(0.5, f64::NAN, 0.5)]);
    let mat = Material::from_e_nu(2, 1e-5, 1000.0, 1e4, 0.3).unwrap();
    let e = sim.run(&mut s, &mat, 0.0, 1).unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::NonFiniteInput {
                field: "x",
                index: 1,
                ..
            }
        ),
        "{e}"
    );
    let mut bad = mat.clone();
    bad.mass[0] = 0.0;
    let mut s = State::at_rest(vec![DVec3::splat(0.5); 2]);
    let e = sim.run(&mut s, &bad, 0.0, 1).unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::InvalidParticleParameter {
                field: "mass",
                index: 0,
                ..
            }
        ),
        "{e}"
    );
    let mut short = mat.clone();
    short.mu.pop();
    let e = sim.run(&mut s, &short, 0.0, 1).unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::LengthMismatch {
                field: "mu",
                len: 1,
                expected: 2
            }
        ),
        "{e}"
    );
    let e = Simulator::new(NeoHookean, cfg(0.0)).unwrap_err();
    assert!(
        matches!(e, MpmError::InvalidParameter { field: "dt", .. }),
        "{e}"
    );
    let e = Simulator::new(
        pipe_mpm::VonMises {
            yield_stress: -1.0,
            eta: 0.0,
        },
        cfg(1e-4),
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::InvalidParameter {
                field: "yield_stress",
                ..
            }
        ),
        "{e}"
    );
}

#[test]
fn per_particle_e_nu_errors_name_the_particle_and_chain_rule_sums() {
    let e = Material::from_e_nu_per_particle(
        vec![1e-3; 3],
        vec![1e-6; 3],
        &[1e5, 2e5, 3e5],
        &[0.3, 0.2, 0.55],
    )
    .unwrap_err();
    assert!(
        matches!(e, MpmError::InvalidParticleParameter { field: "nu", index: 2, value, .. } if value == 0.55),
        "{e}"
    );
    assert!(e.to_string().contains("particle 2"), "{e}");
    let m =
        Material::from_e_nu_per_particle(vec![1e-3; 2], vec![1e-6; 2], &[1e5, 1e5], &[0.3, 0.3])
            .unwrap();
    let (mu, lam) = lame(1e5, 0.3).unwrap();
    assert_eq!(m.mu, vec![mu; 2]);
    assert_eq!(m.lam, vec![lam; 2]);
    let g = pipe_mpm::MaterialGrad {
        mass: vec![0.0; 2],
        volume: vec![0.0; 2],
        mu: vec![1.5, -0.5],
        lam: vec![0.25, 2.0],
        family: Default::default(),
        family_per_particle: Vec::new(),
    };
    let (ge, gn) = g.e_nu_per_particle(&[1e5, 1e5], &[0.3, 0.3]);
    let (se, sn) = g.e_nu(1e5, 0.3);
    assert!((ge[0] + ge[1] - se).abs() < 1e-15 * se.abs());
    assert!((gn[0] + gn[1] - sn).abs() < 1e-12 * sn.abs());
    // FD of the Lamé map itself.
    let h = 1e-6;
    let l = |e: f64, nu: f64| {
        let (m, l) = lame(e, nu).unwrap();
        1.5 * m + 0.25 * l
    };
    let fd_nu = (l(1e5, 0.3 + h) - l(1e5, 0.3 - h)) / (2.0 * h);
    assert!(
        (fd_nu - gn[0]).abs() < 1e-6 * fd_nu.abs(),
        "{fd_nu} vs {}",
        gn[0]
    );
}

#[test]
fn public_substep_backward_checks_inputs() {
    let sim = Simulator::new(NeoHookean, cfg(1e-4)).unwrap();
    let s = State::at_rest(vec![DVec3::splat(0.5), DVec3::new(1.5, 0.5, 0.5)]);
    let mat = Material::from_e_nu(2, 1e-5, 1000.0, 1e4, 0.3).unwrap();
    let mut gm = pipe_mpm::MaterialGrad::zeros(2);
    let e = sim
        .substep_backward(&s, &mat, 0.0, &pipe_mpm::StateGrad::zeros(2), &mut gm)
        .unwrap_err();
    assert!(matches!(e, MpmError::OutsideDomain { index: 1, .. }), "{e}");
    let s = State::at_rest(vec![DVec3::splat(0.5), DVec3::new(0.52, 0.5, 0.5)]);
    let e = sim
        .substep_backward(&s, &mat, 0.0, &pipe_mpm::StateGrad::zeros(3), &mut gm)
        .unwrap_err();
    assert!(matches!(e, MpmError::GradientMismatch(_)), "{e}");
    assert!(
        sim.substep_backward(&s, &mat, 0.0, &pipe_mpm::StateGrad::zeros(2), &mut gm)
            .is_ok()
    );
}

#[test]
fn non_finite_gradient_names_substep() {
    let sim = Simulator::new(NeoHookean, cfg(1e-4)).unwrap();
    let mut s = State::at_rest(vec![DVec3::splat(0.5), DVec3::new(0.52, 0.5, 0.5)]);
    let mat = Material::from_e_nu(2, 1e-5, 1000.0, 1e4, 0.3).unwrap();
    let tape = sim.forward_tape(&mut s, &mat, 0.0, 6, 3).unwrap();
    let mut seed = pipe_mpm::StateGrad::zeros(2);
    seed.v[1] = DVec3::new(f64::NAN, 0.0, 0.0);
    let e = sim
        .backward(
            &tape,
            &mat,
            |k, _| (k == 6).then(|| seed.clone()),
            Default::default(),
        )
        .unwrap_err();
    match e {
        MpmError::NonFinite {
            substep, quantity, ..
        } => {
            assert_eq!(substep, 5);
            assert!(quantity.starts_with("dL/d"), "{quantity}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn family_dispatch_runs_the_named_model() {
    struct Name;
    impl pipe_mpm::ModelVisitor for Name {
        type Output = &'static str;
        fn visit<M: pipe_mpm::Constitutive + Clone + 'static>(self, _m: M) -> &'static str {
            M::NAME
        }
    }
    use pipe_mpm::Family;
    for (name, want) in [
        ("elastic", "neo_hookean"),
        ("fixed_corotated", "fixed_corotated"),
        ("plasticine", "von_mises"),
        ("non_newtonian", "von_mises"),
        ("newtonian", "newtonian"),
        ("sand", "drucker_prager"),
    ] {
        assert_eq!(Family::from_name(name).unwrap().visit(Name), want);
    }
    let e = Family::from_name("jelly").unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::InvalidParameter {
                field: "material",
                ..
            }
        ),
        "{e}"
    );
}

/// A seed gradient whose arrays do not all hold one entry per particle is refused with
/// `GradientMismatch`, whether the run reordered the particles or not, and at the final
/// substep as well as inside the tape.
#[test]
fn malformed_seed_gradient_is_refused() {
    let sim = Simulator::new(NeoHookean, cfg(1e-4)).unwrap();
    let in_cell_order = vec![DVec3::new(0.3, 0.5, 0.5), DVec3::new(0.7, 0.5, 0.5)];
    let reordered = vec![DVec3::new(0.7, 0.5, 0.5), DVec3::new(0.3, 0.5, 0.5)];
    for x in [in_cell_order, reordered] {
        let mat = Material::from_e_nu(2, 1e-5, 1000.0, 1e4, 0.3).unwrap();
        let mut s = State::at_rest(x);
        let tape = sim.forward_tape(&mut s, &mat, 0.0, 4, 2).unwrap();
        let mut short_v = pipe_mpm::StateGrad::zeros(2);
        short_v.v.pop();
        for at in [4, 2] {
            let e = sim
                .backward(
                    &tape,
                    &mat,
                    |k, _| (k == at).then(|| short_v.clone()),
                    Default::default(),
                )
                .unwrap_err();
            assert!(matches!(e, MpmError::GradientMismatch(_)), "{e}");
        }
        let ok = sim.backward(
            &tape,
            &mat,
            |k, _| (k == 2).then(|| pipe_mpm::StateGrad::zeros(2)),
            Default::default(),
        );
        assert!(ok.is_ok());
    }
}

/// The speed bound adds what the forces and impulses acting in the window can give each
/// particle, and the limits at that speed are those of a state moving that fast.
#[test]
fn speed_bound_counts_the_forces_in_the_window() {
    use pipe_mpm::{ParticleForce, speed_bound, stable_step_at_speed};
    let v = vec![
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::ZERO,
        DVec3::new(0.0, 0.0, -0.5),
    ];
    let mass = vec![1e-3, 2e-3, 1e-3];
    let forces = vec![
        // 1e-3 N·s on particles 1 and 2 at t = 0.05 s: +0.5 and +1 m/s.
        ParticleForce::Impulse {
            particles: vec![1, 2],
            impulse: DVec3::new(0.0, 1e-3, 0.0),
            time: 0.05,
        },
        // 4e-2 N on particle 2 from 0.09 s on: +0.4 m/s over the 0.01 s it overlaps [0.04, 0.1).
        ParticleForce::Force {
            particles: vec![2],
            force: DVec3::new(4e-2, 0.0, 0.0),
            start: 0.09,
            end: f64::MAX,
        },
    ];
    let none = speed_bound(&v, &mass, &[], 0.04, 0.1);
    assert_eq!(none, 1.0);
    let b = speed_bound(&v, &mass, &forces, 0.04, 0.1);
    assert!((b - (0.5 + 1.0 + 0.4)).abs() < 1e-12, "{b}");
    // Outside the window nothing acts (an impulse at the window's end belongs to the next).
    assert_eq!(speed_bound(&v, &mass, &forces, 0.0, 0.05), 1.0);
    // Particle 2 under the force for all of [0.1, 0.2): +4 m/s.
    let late = speed_bound(&v, &mass, &forces, 0.1, 0.2);
    assert!((late - (0.5 + 4.0)).abs() < 1e-12, "{late}");

    let mat = Material::from_e_nu(3, 1e-6, 1000.0, 1e5, 0.3).unwrap();
    let mut fast = State::at_rest(vec![DVec3::splat(0.5); 3]);
    fast.v[0] = DVec3::new(0.0, b, 0.0);
    let want = stable_step(&NeoHookean, &fast, &mat, 0.02, StepLimits::default());
    let got = stable_step_at_speed(&NeoHookean, &mat, b, 0.02, StepLimits::default());
    assert_eq!(got, want);
}
