//! Central finite differences (f64) of the whole simulator over 12 substeps, per material,
//! against the hand-written reverse mode. The scene is a jittered 3×3×3 block with random v, C,
//! F resting 1.5 cells above a slip ground, with a box collider to its side, a force on some
//! particles and checkpoints every 5 substeps (so the gradient crosses two checkpoint
//! boundaries). The loss touches x, v, C and F at the end so every adjoint path is used.
//! Fixed-corotated has no PAC-NeRF fixture: this test is its reference.

use glam::{DMat3, DVec3};
use pipe_mpm::math::{ddot, from_rows};
use pipe_mpm::{
    Aabb, BackwardOptions, BoundaryKind, Collider, Constitutive, DruckerPrager, FamilyGrad,
    FixedCorotated, Gradients, Material, NeoHookean, Newtonian, ParticleForce, SimConfig,
    Simulator, State, StateGrad, VonMises,
};

struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn sym(&mut self) -> f64 {
        2.0 * self.uniform() - 1.0
    }
    fn vec(&mut self) -> DVec3 {
        DVec3::new(self.sym(), self.sym(), self.sym())
    }
    fn mat(&mut self) -> DMat3 {
        DMat3::from_cols(self.vec(), self.vec(), self.vec())
    }
}

const N_SUB: usize = 12;

fn scene(fluid: bool) -> (SimConfig, State, Material, [Vec<DVec3>; 2], [Vec<DMat3>; 2]) {
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let dx = 0.05;
    let mut x = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let p = DVec3::new(0.3, 0.125, 0.3)
                    + DVec3::new(i as f64, j as f64, k as f64) * (dx / 2.0);
                x.push(p + rng.vec() * 0.004);
            }
        }
    }
    let n = x.len();
    let v: Vec<DVec3> = (0..n)
        .map(|_| DVec3::new(0.3, -0.6, 0.1) + rng.vec() * 0.2)
        .collect();
    let c: Vec<DMat3> = (0..n).map(|_| rng.mat() * 2.0).collect();
    let f: Vec<DMat3> = (0..n)
        .map(|_| {
            if fluid {
                DMat3::from_diagonal(DVec3::new(1.0 + 0.02 * rng.sym(), 1.0, 1.0))
            } else {
                DMat3::IDENTITY + rng.mat() * 0.05
            }
        })
        .collect();
    let vol = (dx / 2.0f64).powi(3);
    let mat = Material {
        mass: (0..n).map(|_| vol * (1000.0 + 100.0 * rng.sym())).collect(),
        volume: vec![vol; n],
        mu: (0..n).map(|_| 4000.0 * (1.0 + 0.1 * rng.sym())).collect(),
        lam: (0..n).map(|_| 6000.0 * (1.0 + 0.1 * rng.sym())).collect(),
        family: Vec::new(),
    };
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, 4e-4);
    cfg.boundaries.colliders = vec![
        Collider::ground(0.05, BoundaryKind::Slip),
        Collider::Box {
            aabb: Aabb::new(DVec3::new(0.45, 0.0, 0.0), DVec3::new(0.6, 0.3, 1.0)),
            kind: BoundaryKind::Separate,
        },
    ];
    cfg.forces = vec![ParticleForce::Force {
        particles: vec![0, 5, 13],
        force: DVec3::new(0.0, 0.2, 0.05),
        start: 0.0,
        end: 3e-3,
    }];
    let w = [
        (0..n).map(|_| rng.vec()).collect(),
        (0..n).map(|_| rng.vec()).collect(),
    ];
    let wm = [
        (0..n).map(|_| rng.mat()).collect(),
        (0..n).map(|_| rng.mat()).collect(),
    ];
    (cfg, State { x, v, c, f }, mat, w, wm)
}

fn loss(s: &State, w: &[Vec<DVec3>; 2], wm: &[Vec<DMat3>; 2]) -> f64 {
    (0..s.len())
        .map(|p| {
            s.x[p].dot(w[0][p])
                + 0.1 * s.v[p].dot(w[1][p])
                + 0.01 * ddot(&s.c[p], &wm[0][p])
                + ddot(&s.f[p], &wm[1][p])
        })
        .sum()
}

fn seed(w: &[Vec<DVec3>; 2], wm: &[Vec<DMat3>; 2], fluid: bool) -> StateGrad {
    let n = w[0].len();
    let mut g = StateGrad::zeros(n);
    for p in 0..n {
        g.x[p] = w[0][p];
        g.v[p] = 0.1 * w[1][p];
        g.c[p] = 0.01 * wm[0][p];
        g.f[p] = if fluid {
            DMat3::from_diagonal(DVec3::new(wm[1][p].x_axis.x, 0.0, 0.0))
        } else {
            wm[1][p]
        };
    }
    g
}

/// Perturbation target.
#[derive(Clone, Copy, Debug)]
enum Q {
    X(usize, usize),
    V(usize, usize),
    C(usize, usize, usize),
    F(usize, usize, usize),
    Mass(usize),
    Vol(usize),
    Mu(usize),
    Lam(usize),
    Family(usize),
}

fn check<M: Constitutive>(
    name: &str,
    fluid: bool,
    family: &[f64],
    mk: impl Fn(&[f64]) -> M,
    fam_grad: impl Fn(&FamilyGrad) -> Vec<f64>,
) {
    let (cfg, s0, mat, w, wm) = scene(fluid);
    let sim = Simulator::new(mk(family), cfg.clone()).unwrap();
    let mut s = s0.clone();
    let tape = sim.forward_tape(&mut s, &mat, 0.0, N_SUB, 5).unwrap();
    let g0 = seed(&w, &wm, fluid);
    let g = sim
        .backward(
            &tape,
            &mat,
            |k, _| (k == N_SUB).then(|| g0.clone()),
            BackwardOptions::default(),
        )
        .unwrap();
    let fg = fam_grad(&g.material.family);
    let mut qs = vec![
        Q::X(0, 0),
        Q::X(7, 1),
        Q::X(26, 2),
        Q::V(3, 0),
        Q::V(11, 1),
        Q::C(4, 0, 1),
        Q::C(19, 2, 2),
        Q::F(8, 0, 0),
        Q::Mass(2),
        Q::Mass(13),
        Q::Vol(6),
        Q::Mu(9),
        Q::Lam(21),
    ];
    if !fluid {
        qs.push(Q::F(15, 1, 2));
    }
    qs.extend((0..family.len()).map(Q::Family));
    for q in qs {
        let eval = |h: f64| {
            let mut s = s0.clone();
            let mut m = mat.clone();
            let mut fam = family.to_vec();
            match q {
                Q::X(p, a) => s.x[p][a] += h,
                Q::V(p, a) => s.v[p][a] += h,
                Q::C(p, r, c) => s.c[p].col_mut(c)[r] += h,
                Q::F(p, r, c) => s.f[p].col_mut(c)[r] += h,
                Q::Mass(p) => m.mass[p] += h,
                Q::Vol(p) => m.volume[p] += h,
                Q::Mu(p) => m.mu[p] += h,
                Q::Lam(p) => m.lam[p] += h,
                Q::Family(i) => fam[i] += h,
            }
            let sim = Simulator::new(mk(&fam), cfg.clone()).unwrap();
            sim.run(&mut s, &m, 0.0, N_SUB).unwrap();
            loss(&s, &w, &wm)
        };
        let (scale, ad) = match q {
            Q::X(p, a) => (1e-6, g.state.x[p][a]),
            Q::V(p, a) => (1e-5, g.state.v[p][a]),
            Q::C(p, r, c) => (1e-4, g.state.c[p].col(c)[r]),
            Q::F(p, r, c) => (1e-6, g.state.f[p].col(c)[r]),
            Q::Mass(p) => (mat.mass[p] * 1e-5, g.material.mass[p]),
            Q::Vol(p) => (mat.volume[p] * 1e-5, g.material.volume[p]),
            Q::Mu(p) => (mat.mu[p] * 1e-5, g.material.mu[p]),
            Q::Lam(p) => (mat.lam[p] * 1e-5, g.material.lam[p]),
            Q::Family(i) => (family[i].abs().max(1.0) * 1e-5, fg[i]),
        };
        let fd = (eval(scale) - eval(-scale)) / (2.0 * scale);
        let err = (fd - ad).abs();
        let tol = 1e-5 * fd.abs().max(ad.abs()) + 1e-9;
        println!("{name} {q:?}: reverse {ad:.9e} fd {fd:.9e} err {err:.1e}");
        assert!(err <= tol, "{name} {q:?}: reverse {ad:e} vs fd {fd:e}");
    }
}

#[test]
fn neo_hookean_fd() {
    check("neo_hookean", false, &[], |_| NeoHookean, |_| vec![]);
}

#[test]
fn fixed_corotated_fd() {
    check(
        "fixed_corotated",
        false,
        &[],
        |_| FixedCorotated,
        |_| vec![],
    );
}

#[test]
fn von_mises_fd() {
    check(
        "von_mises",
        false,
        &[60.0, 2.0],
        |p| VonMises {
            yield_stress: p[0],
            eta: p[1],
        },
        |g| vec![g.yield_stress, g.eta],
    );
}

#[test]
fn drucker_prager_fd() {
    check(
        "drucker_prager",
        false,
        &[0.3],
        |p| DruckerPrager { alpha: p[0] },
        |g| vec![g.friction_alpha],
    );
}

#[test]
fn newtonian_fd() {
    check("newtonian", true, &[], |_| Newtonian, |_| vec![]);
}

/// `a` and `b` agree to a relative `tol` in every state and Lamé gradient.
fn assert_grads_close(a: &Gradients, b: &Gradients, tol: f64, what: &str) {
    let close = |x: f64, y: f64, field: &str| {
        assert!(
            (x - y).abs() <= tol * x.abs().max(y.abs()).max(1e-30),
            "{what}, {field}: {x:e} vs {y:e}"
        );
    };
    for p in 0..a.state.len() {
        for (x, y) in a.state.x[p].to_array().iter().zip(b.state.x[p].to_array()) {
            close(*x, y, "dL/dx");
        }
        for (x, y) in a.state.v[p].to_array().iter().zip(b.state.v[p].to_array()) {
            close(*x, y, "dL/dv");
        }
        for (x, y) in a.state.f[p]
            .to_cols_array()
            .iter()
            .zip(b.state.f[p].to_cols_array())
        {
            close(*x, y, "dL/dF");
        }
        close(a.material.mu[p], b.material.mu[p], "dL/dmu");
        close(a.material.lam[p], b.material.lam[p], "dL/dlam");
    }
}

/// Checkpoint interval, snapshots and truncation. Every interval gives the same gradients: bit
/// for bit where the taped runs re-sort at the same substeps (one segment: only at its start),
/// to rounding otherwise (a taped run re-sorts at checkpoints when its groups have broken up,
/// which changes the order of the grid sums; this scene's fast particles make it re-sort
/// within 12 substeps). Every number of recomputed snapshots gives the same gradients of one
/// tape, bit for bit. A gradient truncated to the last `k` substeps equals a fresh run started
/// at substep `n − k` (to rounding: the fresh run orders its particles by their cells at
/// `n − k`).
#[test]
fn checkpoint_interval_and_truncation() {
    let (cfg, s0, mat, w, wm) = scene(false);
    let sim = Simulator::new(FixedCorotated, cfg).unwrap();
    let g0 = seed(&w, &wm, false);
    let grads = |every: usize| {
        let mut s = s0.clone();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, N_SUB, every).unwrap();
        assert_eq!(tape.checkpoint_count(), N_SUB.div_ceil(every));
        sim.backward(
            &tape,
            &mat,
            |k, _| (k == N_SUB).then(|| g0.clone()),
            BackwardOptions::default(),
        )
        .unwrap()
    };
    let reference = grads(N_SUB);
    let one_segment = grads(100);
    assert_eq!(
        reference.state, one_segment.state,
        "one segment, every = 100"
    );
    assert_eq!(reference.material, one_segment.material, "every = 100");
    for every in [1, 4, 5] {
        assert_grads_close(
            &reference,
            &grads(every),
            1e-11,
            &format!("every = {every}"),
        );
    }
    // Any number of recomputed snapshots gives the same gradients, bit for bit; 0 is refused.
    let mut s = s0.clone();
    let tape = sim.forward_tape(&mut s, &mat, 0.0, N_SUB, 5).unwrap();
    let by_default = sim
        .backward(
            &tape,
            &mat,
            |k, _| (k == N_SUB).then(|| g0.clone()),
            BackwardOptions::default(),
        )
        .unwrap();
    for snapshots in [0, 1, 2, 3, 11, 40] {
        let g = sim.backward(
            &tape,
            &mat,
            |k, _| (k == N_SUB).then(|| g0.clone()),
            BackwardOptions {
                snapshots,
                ..Default::default()
            },
        );
        if snapshots == 0 {
            let e = g.expect_err("0 snapshots is refused").to_string();
            assert!(e.contains("snapshots") && e.contains(">= 1"), "{e}");
            continue;
        }
        let g = g.unwrap_or_else(|e| panic!("snapshots = {snapshots}: {e}"));
        assert_eq!(by_default.state, g.state, "snapshots = {snapshots}");
        assert_eq!(by_default.material, g.material, "snapshots = {snapshots}");
    }
    let k = 4;
    let gt = sim
        .backward(
            &tape,
            &mat,
            |kk, _| (kk == N_SUB).then(|| g0.clone()),
            BackwardOptions {
                truncate: Some(k),
                ..Default::default()
            },
        )
        .unwrap();
    assert_eq!(gt.start, N_SUB - k);
    let mut mid = s0.clone();
    sim.run(&mut mid, &mat, 0.0, N_SUB - k).unwrap();
    let t_mid = (N_SUB - k) as f64 * sim.config().dt;
    let tape2 = sim.forward_tape(&mut mid, &mat, t_mid, k, 2).unwrap();
    let g2 = sim
        .backward(
            &tape2,
            &mat,
            |kk, _| (kk == k).then(|| g0.clone()),
            BackwardOptions::default(),
        )
        .unwrap();
    assert_grads_close(&gt, &g2, 1e-10, "truncated vs fresh run");
}

/// Constitutive adjoints alone, including repeated singular values (F = I, F = diag(a, a, b)),
/// where the SVD derivative is guarded: the gradient must stay finite and match differences.
#[test]
fn model_adjoints_at_repeated_singular_values() {
    let fs = [
        DMat3::IDENTITY,
        DMat3::from_diagonal(DVec3::new(1.1, 1.1, 0.9)),
        from_rows([[1.05, 0.02, 0.0], [0.01, 0.97, 0.03], [-0.02, 0.01, 1.01]]),
    ];
    let c = from_rows([[0.3, -0.2, 0.1], [0.05, 0.2, -0.4], [0.1, 0.3, -0.1]]);
    let gf = from_rows([[0.3, -0.7, 0.2], [0.5, 0.1, -0.3], [-0.6, 0.4, 0.8]]);
    let gt = from_rows([[1e-4, 2e-4, -1e-4], [3e-5, -2e-4, 1e-4], [2e-4, 1e-4, 3e-4]]);
    fn one<M: Constitutive>(m: &M, f: &DMat3, c: &DMat3, gf: &DMat3, gt: &DMat3) {
        let (mu, lam, dt) = (4000.0, 6000.0, 1e-3);
        let l = |f: &DMat3| {
            let (fo, tau) = m.update(f, c, mu, lam, dt);
            ddot(&fo, gf) + ddot(&tau, gt)
        };
        let g = m.update_adjoint(f, c, mu, lam, dt, gf, gt);
        assert!(g.f_tmp.is_finite(), "{} at {f:?}", M::NAME);
        let h = 1e-7;
        for r in 0..3 {
            for cc in 0..3 {
                let mut fp = *f;
                let mut fm = *f;
                fp.col_mut(cc)[r] += h;
                fm.col_mut(cc)[r] -= h;
                let fd = (l(&fp) - l(&fm)) / (2.0 * h);
                let ad = g.f_tmp.col(cc)[r];
                assert!(
                    (fd - ad).abs() < 1e-5 * fd.abs().max(1.0),
                    "{} F[{r}][{cc}] at {f:?}: {ad} vs {fd}",
                    M::NAME
                );
            }
        }
    }
    for f in &fs {
        one(&NeoHookean, f, &c, &gf, &gt);
        one(&FixedCorotated, f, &c, &gf, &gt);
        one(
            &VonMises {
                yield_stress: 30.0,
                eta: 1.0,
            },
            f,
            &c,
            &gf,
            &gt,
        );
        // DP separates at tr ln σ = 0 (a kink at F = I): test it under compression.
        one(&DruckerPrager { alpha: 0.3 }, &(*f * 0.95), &c, &gf, &gt);
    }
}
