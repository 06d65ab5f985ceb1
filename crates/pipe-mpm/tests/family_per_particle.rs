//! Per-particle family scalars (`Material::family`: yield stress, viscosity, friction), as a
//! learned field would drive them: the same bits as the model's own scalars when uniform, their
//! per-particle gradients against central finite differences (f64) over 12 substeps across two
//! checkpoints, and refusals that name the particle.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, BackwardOptions, BoundaryKind, Collider, Constitutive, DruckerPrager, FamilyGrad,
    FamilyParams, Material, MpmError, NeoHookean, SimConfig, Simulator, State, StateGrad, VonMises,
};

const N_SUB: usize = 12;

/// A jittered 3×3×3 block (dx = 5 cm, two particles per cell along each axis) with random v,
/// C and F above a slip ground; the loss weights `w` for x and F.
fn scene() -> (SimConfig, State, Material, Vec<DVec3>, Vec<DMat3>) {
    let mut seed = 0x2545F4914F6CDD1Du64;
    let mut r = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    let dx = 0.05;
    let mut x = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let p = DVec3::new(0.3, 0.125, 0.3)
                    + DVec3::new(i as f64, j as f64, k as f64) * (dx / 2.0);
                x.push(p + DVec3::new(r(), r(), r()) * 0.004);
            }
        }
    }
    let n = x.len();
    let mut s = State::at_rest(x);
    for p in 0..n {
        s.v[p] = DVec3::new(0.3, -0.6, 0.1) + DVec3::new(r(), r(), r()) * 0.2;
        s.c[p] = DMat3::from_cols_array(&std::array::from_fn(|_| 2.0 * r()));
        s.f[p] = DMat3::IDENTITY + DMat3::from_cols_array(&std::array::from_fn(|_| 0.05 * r()));
    }
    let vol = (dx / 2.0f64).powi(3);
    let mat = Material {
        mass: vec![vol * 1000.0; n],
        volume: vec![vol; n],
        mu: vec![4000.0; n],
        lam: vec![6000.0; n],
        family: Vec::new(),
    };
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, 4e-4);
    cfg.boundaries.colliders = vec![Collider::ground(0.05, BoundaryKind::Slip)];
    let wx = (0..n).map(|_| DVec3::new(r(), r(), r())).collect();
    let wf = (0..n)
        .map(|_| DMat3::from_cols_array(&std::array::from_fn(|_| r())))
        .collect();
    (cfg, s, mat, wx, wf)
}

fn loss(s: &State, wx: &[DVec3], wf: &[DMat3]) -> f64 {
    (0..s.len())
        .map(|p| s.x[p].dot(wx[p]) + pipe_mpm::math::ddot(&s.f[p], &wf[p]))
        .sum()
}

/// Final state and gradients of a taped run of `model` on `mat`.
fn forward_backward<M: Constitutive>(model: M, mat: &Material) -> (State, pipe_mpm::Gradients) {
    let (cfg, mut s, _, wx, wf) = scene();
    let sim = Simulator::new(model, cfg).unwrap();
    let tape = sim.forward_tape(&mut s, mat, 0.0, N_SUB, 5).unwrap();
    let mut seed = StateGrad::zeros(s.len());
    seed.x = wx;
    seed.f = wf;
    let g = sim
        .backward(
            &tape,
            mat,
            |k, _| (k == N_SUB).then(|| seed.clone()),
            BackwardOptions::default(),
        )
        .unwrap();
    (s, g)
}

/// The loss after a plain run of `model` on `mat`.
fn run_loss<M: Constitutive>(model: M, mat: &Material) -> f64 {
    let (cfg, mut s, _, wx, wf) = scene();
    Simulator::new(model, cfg)
        .unwrap()
        .run(&mut s, mat, 0.0, N_SUB)
        .unwrap();
    loss(&s, &wx, &wf)
}

/// Per-particle gradients of the scalars `get`/`set` picks, at particles `ps`, against central
/// differences; the uniform case must equal the model's own scalars bit for bit.
fn check<M: Constitutive>(
    model: M,
    vary: impl Fn(usize) -> FamilyParams,
    pick: impl Fn(&FamilyGrad) -> f64,
    bump: impl Fn(&mut FamilyParams, f64),
    ps: &[usize],
) {
    let (_, s, mat, _, _) = scene();
    let n = s.len();
    // Uniform per-particle scalars equal to the model's: the same bits as none.
    let own = forward_backward(model.clone(), &mat);
    let mut uniform = mat.clone();
    uniform.family = vec![model.params(); n];
    let same = forward_backward(model.clone(), &uniform);
    assert_eq!(own.0, same.0, "{}: states differ", M::NAME);
    assert_eq!(
        own.1.state,
        same.1.state,
        "{}: state gradients differ",
        M::NAME
    );
    assert_eq!(own.1.material.family, same.1.material.family);
    let total = same
        .1
        .material
        .family_per_particle
        .iter()
        .fold(FamilyGrad::default(), |a, &b| a + b);
    assert!((pick(&total) - pick(&own.1.material.family)).abs() <= 1e-12 * pick(&total).abs());

    // Varied scalars: per-particle gradients against central differences.
    let mut varied = mat.clone();
    varied.family = (0..n).map(&vary).collect();
    let (_, g) = forward_backward(model.clone(), &varied);
    assert_eq!(g.material.family_per_particle.len(), n);
    for &p in ps {
        let ad = pick(&g.material.family_per_particle[p]);
        let h = 1e-5 * pick_param(&varied.family[p], &bump).abs().max(1e-3);
        let mut v = [0.0; 2];
        for (side, sign) in v.iter_mut().zip([1.0, -1.0]) {
            let mut m = varied.clone();
            bump(&mut m.family[p], sign * h);
            *side = run_loss(model.clone(), &m);
        }
        let fd = (v[0] - v[1]) / (2.0 * h);
        println!("{} particle {p}: reverse {ad:.9e} fd {fd:.9e}", M::NAME);
        assert!(ad != 0.0, "{}: particle {p} does not yield", M::NAME);
        assert!(
            (fd - ad).abs() <= 1e-5 * fd.abs().max(ad.abs()) + 1e-9,
            "{} particle {p}: reverse {ad:e} vs fd {fd:e}",
            M::NAME
        );
    }
}

/// The value `bump` changes in `p` (found by bumping a copy by 1).
fn pick_param(p: &FamilyParams, bump: &impl Fn(&mut FamilyParams, f64)) -> f64 {
    let mut q = *p;
    bump(&mut q, 1.0);
    let d = [
        q.yield_stress - p.yield_stress,
        q.eta - p.eta,
        q.friction_alpha - p.friction_alpha,
    ];
    let vals = [p.yield_stress, p.eta, p.friction_alpha];
    (0..3).find(|&i| d[i] != 0.0).map_or(1.0, |i| vals[i])
}

#[test]
fn von_mises_yield_stress_and_viscosity_per_particle() {
    let model = VonMises {
        yield_stress: 60.0,
        eta: 2.0,
    };
    let vary = |p: usize| FamilyParams {
        yield_stress: 40.0 + 10.0 * (p % 5) as f64,
        eta: 1.0 + 0.5 * (p % 3) as f64,
        ..FamilyParams::default()
    };
    check(
        model,
        vary,
        |g| g.yield_stress,
        |q, h| q.yield_stress += h,
        &[2, 13],
    );
    check(model, vary, |g| g.eta, |q, h| q.eta += h, &[7, 20]);
}

#[test]
fn drucker_prager_friction_per_particle() {
    check(
        DruckerPrager { alpha: 0.3 },
        |p| FamilyParams {
            friction_alpha: 0.2 + 0.05 * (p % 4) as f64,
            ..FamilyParams::default()
        },
        |g| g.friction_alpha,
        |q, h| q.friction_alpha += h,
        &[5, 22],
    );
}

#[test]
fn bad_per_particle_scalars_are_refused_naming_the_particle() {
    let (cfg, s, mut mat, _, _) = scene();
    let n = s.len();
    let sim = Simulator::new(
        VonMises {
            yield_stress: 60.0,
            eta: 2.0,
        },
        cfg.clone(),
    )
    .unwrap();
    mat.family = vec![sim.model().params(); n];
    mat.family[4].yield_stress = -1.0;
    let e = sim.validate(&s, &mat).unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::InvalidParticleParameter {
                index: 4,
                field: "yield_stress",
                ..
            }
        ),
        "{e}"
    );
    mat.family[4].yield_stress = f64::NAN;
    assert!(matches!(
        sim.validate(&s, &mat).unwrap_err(),
        MpmError::NonFiniteInput { index: 4, .. }
    ));
    mat.family.pop();
    assert!(matches!(
        sim.validate(&s, &mat).unwrap_err(),
        MpmError::LengthMismatch {
            field: "family",
            ..
        }
    ));
    // A model without family scalars refuses them rather than ignoring them.
    mat.family = vec![FamilyParams::default(); n];
    let e = Simulator::new(NeoHookean, cfg)
        .unwrap()
        .validate(&s, &mat)
        .unwrap_err();
    assert!(
        matches!(
            e,
            MpmError::InvalidParameter {
                field: "family",
                ..
            }
        ),
        "{e}"
    );
}

/// The viscous step limit follows the most viscous particle, not the model's own η.
#[test]
fn the_viscous_limit_follows_per_particle_viscosity() {
    let (cfg, s, mut mat, _, _) = scene();
    let model = VonMises {
        yield_stress: 60.0,
        eta: 2.0,
    };
    let limits = pipe_mpm::StepLimits::default();
    let own = pipe_mpm::stable_step_at_speed(&model, &mat, 0.0, cfg.dx, limits);
    mat.family = vec![model.params(); s.len()];
    mat.family[9].eta = 2000.0;
    let one = pipe_mpm::stable_step_at_speed(&model, &mat, 0.0, cfg.dx, limits);
    assert!(
        (one.viscous * 1000.0 / own.viscous - 1.0).abs() < 1e-12,
        "{} vs {}",
        one.viscous,
        own.viscous
    );
}
