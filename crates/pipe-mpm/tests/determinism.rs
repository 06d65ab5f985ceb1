//! Parallel P2G (and the adjoint's grid scatter) must not depend on the thread count: a few
//! thousand random particles spread over many x-slabs (12 equal-count slabs) are stepped forward
//! and backward in 1-, 2- and 3-thread rayon pools and the results compared bit for bit.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, BackwardOptions, DruckerPrager, Material, SimConfig, Simulator, State, StateGrad,
};

fn scene() -> (Simulator<DruckerPrager>, State, Material) {
    let mut seed = 12345u64;
    let mut r = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let n = 4000;
    let x: Vec<DVec3> = (0..n)
        .map(|_| DVec3::new(0.1 + 0.8 * r(), 0.1 + 0.5 * r(), 0.1 + 0.8 * r()))
        .collect();
    let mut s = State::at_rest(x);
    for p in 0..n {
        s.v[p] = DVec3::new(r() - 0.5, r() - 0.5, r() - 0.5);
        s.c[p] = DMat3::from_diagonal(DVec3::new(r() - 0.5, r() - 0.5, r() - 0.5));
    }
    let mat = Material::from_e_nu(n, 1e-6, 1500.0, 1e5, 0.3).unwrap();
    let cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.025, 1e-4);
    (
        Simulator::new(DruckerPrager { alpha: 0.3 }, cfg).unwrap(),
        s,
        mat,
    )
}

fn run(threads: usize) -> (State, StateGrad, Vec<f64>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let (sim, mut s, mat) = scene();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, 4, 2).unwrap();
        let mut seed = StateGrad::zeros(s.len());
        for (g, x) in seed.x.iter_mut().zip(&s.x) {
            *g = *x;
        }
        let g = sim
            .backward(
                &tape,
                &mat,
                |k, _| (k == 4).then(|| seed.clone()),
                BackwardOptions::default(),
            )
            .unwrap();
        let (state, material) = g.into_parts();
        (s, state, material.mu)
    })
}

#[test]
fn one_two_and_three_threads_are_bit_identical() {
    let a = run(1);
    for threads in [2, 3] {
        let b = run(threads);
        assert_eq!(a.0, b.0, "forward states differ ({threads} threads)");
        assert_eq!(a.1, b.1, "state gradients differ ({threads} threads)");
        assert_eq!(a.2, b.2, "material gradients differ ({threads} threads)");
    }
}

/// A dropped tape's checkpoint buffers go back to its simulator and the next tape reuses them:
/// a second differentiable pass (f32 and f64, one simulator) must give the same bits as the
/// first, whose tape was built in fresh memory, also when the second tape is shorter or longer.
#[test]
fn reused_tape_buffers_give_the_same_bits() {
    for precision in [pipe_mpm::Precision::F64, pipe_mpm::Precision::F32] {
        let (sim, s0, mat) = scene();
        let mut cfg = sim.config().clone();
        cfg.precision = precision;
        let sim = Simulator::new(DruckerPrager { alpha: 0.3 }, cfg).unwrap();
        let pass = |substeps: usize| {
            let mut s = s0.clone();
            let tape = sim.forward_tape(&mut s, &mat, 0.0, substeps, 2).unwrap();
            let first = tape.checkpoint(1).unwrap();
            let g = sim
                .backward(
                    &tape,
                    &mat,
                    |k, st| {
                        (k == substeps).then(|| {
                            let mut seed = StateGrad::zeros(st.get().len());
                            seed.x.clone_from(&st.get().x);
                            seed
                        })
                    },
                    BackwardOptions::default(),
                )
                .unwrap();
            // Cloned, so that `g` drops and its arrays go back for the next pass to fill.
            (s, first, g.state.clone(), g.material.mu.clone())
        };
        let fresh = pass(6);
        assert_eq!(fresh, pass(6), "{precision:?}: a reused tape differs");
        let (short, long) = (pass(4), pass(8));
        assert_eq!(
            short.1, fresh.1,
            "{precision:?}: checkpoint 1 of a shorter tape"
        );
        assert_eq!(
            long.1, fresh.1,
            "{precision:?}: checkpoint 1 of a longer tape"
        );
        assert_eq!(
            fresh,
            pass(6),
            "{precision:?}: after shorter and longer tapes"
        );
    }
}

/// A dropped `Gradients` returns its arrays to its simulator and the next backward pass fills
/// them (no fresh memory), with the same bits as into fresh arrays; `into_parts` keeps them.
#[test]
fn dropped_gradients_are_recycled() {
    let (sim, s0, mat) = scene();
    let grads = || {
        let mut s = s0.clone();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, 4, 2).unwrap();
        sim.backward(
            &tape,
            &mat,
            |k, st| {
                (k == 4).then(|| {
                    let mut seed = StateGrad::zeros(st.get().len());
                    seed.x.clone_from(&st.get().x);
                    seed
                })
            },
            BackwardOptions::default(),
        )
        .unwrap()
    };
    let first = grads();
    let (x_at, mu_at) = (first.state.x.as_ptr(), first.material.mu.as_ptr());
    let (state, mu) = (first.state.clone(), first.material.mu.clone());
    drop(first);
    let second = grads();
    assert_eq!(second.state.x.as_ptr(), x_at, "state arrays not recycled");
    assert_eq!(
        second.material.mu.as_ptr(),
        mu_at,
        "material arrays not recycled"
    );
    assert_eq!((&second.state, &second.material.mu), (&state, &mu));
    let (kept, _) = second.into_parts();
    assert_eq!(kept, state);
    assert_eq!(grads().state, state);
}

/// The forward pass keeps the start of the last segment's reversal (its first recomputed
/// states and, in a short segment, each substep's intermediates) and the first backward pass
/// takes it instead of recomputing: that pass must give the same bits as a second pass through
/// the same tape (which recomputes everything), in short and long segments, f64 and f32, whole
/// and truncated, with the default and other snapshot counts.
#[test]
fn the_forward_passs_lead_gives_the_same_bits_as_recomputing() {
    for precision in [pipe_mpm::Precision::F64, pipe_mpm::Precision::F32] {
        let (sim, s0, mat) = scene();
        let mut cfg = sim.config().clone();
        cfg.precision = precision;
        let sim = Simulator::new(DruckerPrager { alpha: 0.3 }, cfg).unwrap();
        let substeps = 9;
        // every = 3: short segments (intermediates kept); 10: one long one.
        for (every, snapshots) in [(3, 4), (10, 4), (10, 2), (3, 1)] {
            for truncate in [None, Some(2), Some(5)] {
                let mut s = s0.clone();
                let tape = sim
                    .forward_tape(&mut s, &mat, 0.0, substeps, every)
                    .unwrap();
                let pass = || {
                    let g = sim
                        .backward(
                            &tape,
                            &mat,
                            |k, st| {
                                (k == substeps || k == 7).then(|| {
                                    let mut seed = StateGrad::zeros(st.get().len());
                                    seed.x.clone_from(&st.get().x);
                                    seed.v.clone_from(&st.get().x);
                                    seed
                                })
                            },
                            BackwardOptions {
                                truncate,
                                snapshots,
                            },
                        )
                        .unwrap();
                    (g.state.clone(), g.material.clone())
                };
                let with_lead = pass();
                let recomputed = pass();
                let what = format!(
                    "{precision:?}, every {every}, {snapshots} snapshots, truncate {truncate:?}"
                );
                assert_eq!(with_lead.0, recomputed.0, "state gradients: {what}");
                assert_eq!(with_lead.1, recomputed.1, "material gradients: {what}");
                assert!(
                    with_lead.0.x.iter().any(|g| *g != DVec3::ZERO),
                    "no gradient: {what}"
                );
            }
        }
    }
}
