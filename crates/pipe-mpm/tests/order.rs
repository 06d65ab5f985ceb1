//! A run reorders the particles by grid cell internally (`order.rs`); callers must never see
//! it. A randomly ordered cloud with an impulse on some particles is simulated and
//! backpropagated twice, once as given and once reversed: positions, gradients and the seed
//! states must agree particle for particle (to rounding, since the internal order of the grid
//! sums differs), the states handed to seeds must be the tape's checkpoints in the caller's
//! order, and a NaN must be reported against the caller's index.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, BackwardOptions, Material, MpmError, NeoHookean, ParticleForce, SimConfig, Simulator,
    State, StateGrad,
};

const N: usize = 600;
const STEPS: usize = 10;

fn scene() -> (Simulator<NeoHookean>, State, Material) {
    let mut seed = 987654321u64;
    let mut r = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let x: Vec<DVec3> = (0..N)
        .map(|_| DVec3::new(0.3 + 0.4 * r(), 0.2 + 0.3 * r(), 0.3 + 0.4 * r()))
        .collect();
    let mut s = State::at_rest(x);
    for p in 0..N {
        s.v[p] = DVec3::new(r() - 0.5, r() - 0.5, r() - 0.5);
    }
    let mat = Material::from_e_nu(N, 2e-6, 1000.0, 1e5, 0.3).unwrap();
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.05, 1e-4);
    cfg.forces = vec![ParticleForce::Impulse {
        particles: kicked(&s),
        impulse: DVec3::new(1e-4, 0.0, 0.0),
        time: 3.5e-4,
    }];
    (Simulator::new(NeoHookean, cfg).unwrap(), s, mat)
}

/// The particles the impulse acts on: those left of x = 0.45 m, in the caller's numbering.
fn kicked(s: &State) -> Vec<usize> {
    (0..s.len()).filter(|&p| s.x[p].x < 0.45).collect()
}

/// The state with its particles in reverse order.
fn reversed(s: &State) -> State {
    let rev = |v: &[DVec3]| v.iter().rev().copied().collect::<Vec<_>>();
    let revm = |v: &[DMat3]| v.iter().rev().copied().collect::<Vec<_>>();
    State {
        x: rev(&s.x),
        v: rev(&s.v),
        c: revm(&s.c),
        f: revm(&s.f),
    }
}

fn close(a: f64, b: f64, scale: f64, what: &str) {
    assert!(
        (a - b).abs() <= 1e-11 * scale,
        "{what}: {a:e} vs {b:e} (scale {scale:e})"
    );
}

#[test]
fn callers_order_is_kept_everywhere() {
    let (sim, s0, mat) = scene();
    let every = 4;
    let run = |sim: &Simulator<NeoHookean>, s0: &State| {
        let mut s = s0.clone();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, STEPS, every).unwrap();
        // Seeds: y of particle 5 at substep 4 (read from the seed state) and final x of all.
        let mut seen = None;
        let g = sim
            .backward(
                &tape,
                &mat,
                |k, st| {
                    let mut g = StateGrad::zeros(N);
                    match k {
                        STEPS => g.x.iter_mut().for_each(|gx| gx.x = 1.0),
                        4 => {
                            let st = st.get();
                            assert_eq!(st.x, tape.checkpoint(1).unwrap().x);
                            seen = Some(st.x.clone());
                            g.x[5].y = 1.0;
                        }
                        _ => return None,
                    }
                    Some(g)
                },
                BackwardOptions::default(),
            )
            .unwrap();
        (s, g, seen.unwrap())
    };
    let (a, ga, seen_a) = run(&sim, &s0);
    // Same scene, particles listed in reverse (forces renumbered accordingly).
    let mut sim_r = sim.clone();
    sim_r.set_forces(vec![ParticleForce::Impulse {
        particles: kicked(&s0).iter().map(|p| N - 1 - p).collect(),
        impulse: DVec3::new(1e-4, 0.0, 0.0),
        time: 3.5e-4,
    }]);
    let s0_r = reversed(&s0);
    let mut s_r = s0_r.clone();
    let tape_r = sim_r
        .forward_tape(&mut s_r, &mat, 0.0, STEPS, every)
        .unwrap();
    let g_r = sim_r
        .backward(
            &tape_r,
            &mat,
            |k, _| {
                let mut g = StateGrad::zeros(N);
                match k {
                    STEPS => g.x.iter_mut().for_each(|gx| gx.x = 1.0),
                    4 => g.x[N - 1 - 5].y = 1.0,
                    _ => return None,
                }
                Some(g)
            },
            BackwardOptions::default(),
        )
        .unwrap();
    let b = s_r.clone();
    let gv_scale = ga
        .state
        .v
        .iter()
        .map(|v| v.abs().max_element())
        .fold(0.0, f64::max);
    for p in 0..N {
        let q = N - 1 - p;
        for ax in 0..3 {
            close(a.x[p][ax], b.x[q][ax], 1.0, "x");
            close(a.v[p][ax], b.v[q][ax], 1.0, "v");
            close(ga.state.v[p][ax], g_r.state.v[q][ax], gv_scale, "dL/dv0");
        }
        close(ga.material.mu[p], g_r.material.mu[q], 1e-12, "dL/dmu");
    }
    // The impulse moved the particles it names (in the caller's numbering) most.
    let mut free = sim.clone();
    free.set_forces(vec![]);
    let mut no = s0.clone();
    free.run(&mut no, &mat, 0.0, STEPS).unwrap();
    let set = kicked(&s0);
    let mean_dv = |inside: bool| {
        let ps: Vec<usize> = (0..N).filter(|p| set.contains(p) == inside).collect();
        ps.iter().map(|&p| a.v[p].x - no.v[p].x).sum::<f64>() / ps.len() as f64
    };
    assert!(
        mean_dv(true) > 5.0 * mean_dv(false).abs(),
        "kicked {:e}, others {:e}",
        mean_dv(true),
        mean_dv(false)
    );
    // The seed state was the tape's checkpoint in the caller's order.
    assert_eq!(seen_a.len(), N);
    assert_eq!(a, {
        let mut s = s0.clone();
        sim.run(&mut s, &mat, 0.0, STEPS).unwrap();
        s
    });
}

#[test]
fn non_finite_names_the_callers_particle() {
    let (sim, mut s, mat) = scene();
    let bad = 123;
    s.v[bad] = DVec3::new(1e300, 0.0, 0.0);
    s.c[bad] = DMat3::from_diagonal(DVec3::splat(1e300));
    match sim.run(&mut s, &mat, 0.0, STEPS) {
        Err(MpmError::NonFinite { particle, .. }) => {
            // The blow-up spreads to the neighbours within a substep; the reported one must be
            // the first in the caller's order among those that are non-finite.
            let first = (0..N)
                .find(|&p| !(s.x[p].is_finite() && s.v[p].is_finite() && s.c[p].is_finite()))
                .unwrap();
            assert_eq!(particle, first);
        }
        other => panic!("expected a NaN report, got {other:?}"),
    }
}

/// Seeds added in place ([`Simulator::backward_into`], per particle and per quantity) give
/// the same bits as the same seeds returned as gradients ([`Simulator::backward`]), for a
/// reordered cloud (the random one) and one already in cell order.
#[test]
fn seeds_added_in_place_match_returned_seeds() {
    let (sim, s0, mat) = scene();
    let mut sorted = s0.clone();
    let mut idx: Vec<usize> = (0..N).collect();
    // Stencil base cells (dx = 0.05 m) in x-major order: the run keeps this order as is.
    let cell = |p: usize| {
        let b = (s0.x[p] / 0.05 - DVec3::splat(0.5)).floor();
        (b.x as i64, b.y as i64, b.z as i64)
    };
    idx.sort_by_key(|&p| cell(p));
    for (i, &p) in idx.iter().enumerate() {
        sorted.x[i] = s0.x[p];
        sorted.v[i] = s0.v[p];
    }
    for start in [s0, sorted] {
        let mut s = start.clone();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, STEPS, 4).unwrap();
        let term = |p: usize| DVec3::new(1.0, p as f64 / N as f64, -0.5);
        let gc = DMat3::from_cols_array(&[0.1, 0.0, 0.2, 0.0, -0.3, 0.0, 0.0, 0.0, 0.4]);
        let returned = sim
            .backward(
                &tape,
                &mat,
                |k, _| {
                    (k == STEPS || k == 6).then(|| {
                        let mut g = StateGrad::zeros(N);
                        for p in (0..N).step_by(7) {
                            g.x[p] = term(p);
                            g.v[p] = term(p) * 0.5;
                            g.c[p] = gc;
                            g.f[p] = gc * 2.0;
                        }
                        g
                    })
                },
                BackwardOptions::default(),
            )
            .unwrap();
        let in_place = sim
            .backward_into(
                &tape,
                &mat,
                |k, _, g| {
                    if k == STEPS || k == 6 {
                        assert_eq!(g.len(), N);
                        for p in (0..N).step_by(7) {
                            g.add_x(p, term(p));
                            g.add_v(p, term(p) * 0.5);
                            g.add_c(p, gc);
                            g.add_f(p, gc * 2.0);
                        }
                    }
                    Ok(())
                },
                BackwardOptions::default(),
            )
            .unwrap();
        assert_eq!(returned.state, in_place.state);
        assert_eq!(returned.material, in_place.material);
        assert!(in_place.state.x.iter().any(|g| g.length() > 0.0));
        // An error of the seed stops the pass and is returned.
        let stopped = sim.backward_into(
            &tape,
            &mat,
            |k, _, g| {
                if k == 6 {
                    g.add(&StateGrad::zeros(N + 1))
                } else {
                    Ok(())
                }
            },
            BackwardOptions::default(),
        );
        assert!(matches!(stopped, Err(MpmError::GradientMismatch(_))));
    }
}
