//! A grid that follows the particles ([`Domain::Follow`]): each substep's grid is the window of
//! nodes the particles' stencils reach, so nothing but the declared colliders acts on them.
//!
//! The scene is a soft block thrown sideways and up over a sticky ground: it flies ~14 cells
//! from where it started, lands, and slides and tips, so the window moves, grows and shrinks
//! during the run. Against a fixed domain large enough never to be reached (no walls), the
//! positions, the gradients and the per-substep work must agree to rounding (the two measure
//! positions from different nodes); the gradients through the moving window are also checked by
//! central finite differences, and must be bit-identical for 1 and 2 threads. A budget too
//! small for particles flying apart is an error that names the substep, the extent and the
//! budget.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, BackwardOptions, BoundaryKind, Collider, Domain, Material, MpmError, NeoHookean,
    Precision, SimConfig, Simulator, State, StateGrad,
};

const DX: f64 = 0.05;
const DT: f64 = 4e-4;

/// A 4×4×4 block (two particles per cell and axis) 0.1 m above the ground, thrown at
/// `(2.5, 1.5, −1.0)` m/s and spinning.
fn block() -> State {
    let mut x = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            for k in 0..4 {
                let h = ((i * 16 + j * 4 + k) as f64 * 0.618_033_988_75).fract();
                x.push(
                    DVec3::new(0.2, 0.1, 0.3)
                        + DVec3::new(i as f64, j as f64, k as f64) * (DX / 2.0)
                        + DVec3::splat(0.002 * (h - 0.5)),
                );
            }
        }
    }
    let mut s = State::at_rest(x);
    let centre = DVec3::new(0.2375, 0.1375, 0.3375);
    for (v, x) in s.v.iter_mut().zip(&s.x) {
        *v = DVec3::new(2.5, 1.5, -1.0) + DVec3::new(0.0, 0.0, 6.0).cross(*x - centre);
    }
    s
}

fn material(n: usize) -> Material {
    Material::from_e_nu(n, (DX / 2.0).powi(3), 1000.0, 3e4, 0.3).unwrap()
}

/// The scene's settings: a following grid, or a fixed box far larger than the motion.
fn config(follow: bool, precision: Precision) -> SimConfig {
    let mut cfg = if follow {
        SimConfig::following(DX, DT)
    } else {
        let mut c = SimConfig::new(
            Aabb::new(DVec3::new(-3.0, -1.0, -3.0), DVec3::new(3.0, 3.0, 3.0)),
            DX,
            DT,
        );
        c.boundaries.walls = None;
        c
    };
    cfg.boundaries.colliders = vec![Collider::ground(0.0, BoundaryKind::Sticky)];
    cfg.precision = precision;
    cfg
}

fn max_diff(a: &[DVec3], b: &[DVec3]) -> f64 {
    assert_eq!(a.len(), b.len(), "particle counts differ");
    a.iter().zip(b).fold(0.0, |m, (p, q)| {
        let d = (*p - *q).abs().max_element();
        assert!(d.is_finite(), "non-finite position {p:?} or {q:?}");
        m.max(d)
    })
}

#[test]
fn a_following_grid_moves_as_a_fixed_one_too_large_to_reach() {
    for (precision, tol) in [(Precision::F64, 1e-10), (Precision::F32, 2e-5)] {
        let mut runs = Vec::new();
        for follow in [true, false] {
            let sim = Simulator::new(NeoHookean, config(follow, precision)).unwrap();
            let mut s = block();
            let mat = material(s.len());
            let mut stepper = sim.stepper(&mut s, &mat).unwrap();
            let mut spans = Vec::new();
            let mut frames = Vec::new();
            for f in 0..6 {
                let rep = stepper.advance(f as f64 * 100.0 * DT, DT, 100).unwrap();
                assert_eq!(rep.held, 0, "no particle is held");
                spans.push(stepper.grid_span().unwrap());
                frames.push(stepper.state().x);
            }
            runs.push((frames, spans));
        }
        let (follow, fixed) = (&runs[0], &runs[1]);
        for (f, (a, b)) in follow.0.iter().zip(&fixed.0).enumerate() {
            let d = max_diff(a, b);
            assert!(d <= tol, "{precision:?} frame {f}: {d:e} m apart");
        }
        // The block travelled: its last frame lies well away from its first.
        let c = |x: &[DVec3]| x.iter().sum::<DVec3>() / x.len() as f64;
        let travel = (c(&follow.0[5]) - c(&block().x)).length();
        assert!(travel > 0.5, "the block moved {travel} m");
        // The windows followed it: each frame's is small, they moved, and the fixed grid is the
        // same in every frame.
        let size = |b: &Aabb| b.hi - b.lo;
        for (f, s) in follow.1.iter().enumerate() {
            assert!(
                size(s).max_element() < 0.6,
                "frame {f}: window {s:?} larger than the block's reach in a frame"
            );
        }
        assert!((follow.1[5].lo - follow.1[0].lo).length() > 0.4);
        assert!(fixed.1.iter().all(|s| *s == fixed.1[0]));
        assert!(size(&fixed.1[0]).min_element() > 4.0);
    }
}

/// Loss `Σ w_p · x_p` at the end of `substeps` substeps from `s`, checkpointed every 7.
fn loss_and_grad(
    sim: &Simulator<NeoHookean>,
    s: &State,
    mat: &Material,
    substeps: usize,
) -> (f64, StateGrad, f64) {
    let mut s = s.clone();
    let tape = sim.forward_tape(&mut s, mat, 0.0, substeps, 7).unwrap();
    let w = |p: usize| DVec3::new(1.0, 0.3 * (p % 3) as f64, -0.5);
    let loss = s.x.iter().enumerate().map(|(p, x)| w(p).dot(*x)).sum();
    let mut seed = StateGrad::zeros(s.len());
    for (p, g) in seed.x.iter_mut().enumerate() {
        *g = w(p);
    }
    let g = sim
        .backward(
            &tape,
            mat,
            |k, _| (k == substeps).then(|| seed.clone()),
            BackwardOptions::default(),
        )
        .unwrap();
    let g_mu: f64 = g.material.mu.iter().sum();
    (loss, g.state.clone(), g_mu)
}

#[test]
fn gradients_follow_the_moving_grid() {
    // 160 substeps: the block flies 0.16 m (three cells) and the window moves with it.
    let n_sub = 160;
    let s0 = block();
    let mat = material(s0.len());
    let follow = Simulator::new(NeoHookean, config(true, Precision::F64)).unwrap();
    let fixed = Simulator::new(NeoHookean, config(false, Precision::F64)).unwrap();
    let (l_a, g_a, mu_a) = loss_and_grad(&follow, &s0, &mat, n_sub);
    let (l_b, g_b, mu_b) = loss_and_grad(&fixed, &s0, &mat, n_sub);
    assert!((l_a - l_b).abs() < 1e-9, "losses {l_a} vs {l_b}");
    let scale = g_b
        .v
        .iter()
        .fold(0.0f64, |m, g| m.max(g.abs().max_element()));
    assert!(scale > 0.01, "a gradient to compare: {scale}");
    assert!(max_diff(&g_a.v, &g_b.v) <= 1e-9 * scale);
    assert!(max_diff(&g_a.x, &g_b.x) <= 1e-9 * scale.max(1.0));
    assert!(
        (mu_a - mu_b).abs() <= 1e-9 * mu_b.abs().max(1e-12),
        "{mu_a} vs {mu_b}"
    );

    // Central differences through the moving window: the initial velocity of the whole block
    // (each axis) and the shear modulus of every particle.
    let h = 1e-6;
    let loss_at = |dv: DVec3, dmu: f64| {
        let mut s = s0.clone();
        for v in &mut s.v {
            *v += dv;
        }
        let mut m = mat.clone();
        for mu in &mut m.mu {
            *mu += dmu;
        }
        follow.run(&mut s, &m, 0.0, n_sub).unwrap();
        (0..s.len())
            .map(|p| DVec3::new(1.0, 0.3 * (p % 3) as f64, -0.5).dot(s.x[p]))
            .sum::<f64>()
    };
    for a in 0..3 {
        let mut e = DVec3::ZERO;
        e[a] = h;
        let fd = (loss_at(e, 0.0) - loss_at(-e, 0.0)) / (2.0 * h);
        let ad: f64 = g_a.v.iter().map(|g| g[a]).sum();
        assert!(
            (fd - ad).abs() <= 1e-5 * fd.abs().max(1.0),
            "dL/dv0[{a}]: adjoint {ad} vs central difference {fd}"
        );
    }
    let hm = 1e-3 * mat.mu[0];
    let fd = (loss_at(DVec3::ZERO, hm) - loss_at(DVec3::ZERO, -hm)) / (2.0 * hm);
    assert!(
        (fd - mu_a).abs() <= 1e-4 * fd.abs().max(1e-9),
        "dL/dmu: adjoint {mu_a:e} vs central difference {fd:e}"
    );

    // The same bits on one and two threads.
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| loss_and_grad(&follow, &s0, &mat, n_sub))
    };
    let (one, two) = (on(1), on(2));
    assert_eq!(one.0.to_bits(), two.0.to_bits());
    assert_eq!(one.1.x, two.1.x);
    assert_eq!(one.1.v, two.1.v);
    assert_eq!(one.1.f, two.1.f);
    assert_eq!(one.2.to_bits(), two.2.to_bits());
    let _ = DMat3::IDENTITY;
}

#[test]
fn particles_flying_apart_past_the_budget_are_an_error() {
    let mut cfg = SimConfig::following(DX, DT);
    cfg.gravity = DVec3::ZERO;
    cfg.domain = Domain::Follow { max_nodes: 2_000 };
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let mut s = State::at_rest(vec![DVec3::new(0.0, 1.0, 0.0), DVec3::new(0.5, 1.0, 0.0)]);
    s.v = vec![DVec3::new(-20.0, 0.0, 0.0), DVec3::new(20.0, 0.0, 0.0)];
    let mat = material(2);
    let err = sim.run(&mut s, &mat, 0.0, 1000).unwrap_err();
    match err {
        MpmError::GridTooLarge {
            substep,
            lo,
            hi,
            nodes,
            budget,
            ..
        } => {
            assert_eq!(budget, 2_000);
            assert!(nodes > budget);
            assert!(substep > 10 && substep < 1000, "substep {substep}");
            assert!(hi[0] - lo[0] > 1.0, "extent {lo:?} to {hi:?}");
        }
        other => panic!("expected GridTooLarge, got {other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("budget of 2000 nodes") && msg.contains("substep"),
        "{msg}"
    );
    // A budget below one stencil is refused when the simulator is built.
    let mut cfg = SimConfig::following(DX, DT);
    cfg.domain = Domain::Follow { max_nodes: 8 };
    assert!(Simulator::new(NeoHookean, cfg).is_err());
}

#[test]
fn contacts_count_the_particles_each_boundary_acts_on() {
    // A fixed domain whose +x wall the thrown block reaches, over the ground.
    let mut cfg = SimConfig::new(
        Aabb::new(DVec3::new(-1.0, -0.5, -1.0), DVec3::new(0.45, 2.0, 1.0)),
        DX,
        DT,
    );
    cfg.boundaries.colliders = vec![
        Collider::ground(0.0, BoundaryKind::Sticky),
        Collider::Box {
            aabb: Aabb::new(DVec3::new(-1.0, 0.0, 5.0), DVec3::new(1.0, 1.0, 6.0)),
            kind: BoundaryKind::Slip,
        },
    ];
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let mut s = block();
    let n = s.len();
    let mat = material(n);
    let mut stepper = sim.stepper(&mut s, &mat).unwrap();
    stepper.watch_contacts();
    // In flight before it reaches anything: no contact.
    stepper.advance(0.0, DT, 20).unwrap();
    assert_eq!(stepper.take_contacts(), vec![0, 0, 0]);
    let mut seen = vec![0usize; 3];
    for f in 0..12 {
        stepper
            .advance((20 + f * 100) as f64 * DT, DT, 100)
            .unwrap();
        for (s, c) in seen.iter_mut().zip(stepper.take_contacts()) {
            assert!(c <= n);
            *s = (*s).max(c);
        }
    }
    assert!(seen[0] > 0, "the ground acts on the landed block: {seen:?}");
    assert_eq!(seen[1], 0, "the far box never does: {seen:?}");
    assert!(seen[2] > 0, "the +x wall stops the block: {seen:?}");
}
