//! The physics stages' gradient, checked end to end by central finite differences in `f64`:
//! material parameters and initial velocity → MPM (every frame) → particles' `x` and `F` →
//! posed Gaussians (`F Σ Fᵀ`, SH turned by the polar rotation of `F`) → rasterizer → loss.
//!
//! The scene is tiny so that f64 finite differences of whole rollouts are cheap: a 4×4×4 block
//! of Gaussians thrown sideways and spinning over a sticky ground, seen by one 24×20 camera,
//! two frames of ten fixed substeps (fixed, so that a change of E does not change the step
//! count and put a jump into the differences). The loss is linear in the image and the alpha
//! with fixed pseudo-random weights, so every pixel's gradient is exercised.

use std::collections::BTreeMap;
use std::path::PathBuf;

use glam::DVec3;
use pipe::physics::object::{Object, ObjectSettings, Resolution};
use pipe::physics::params::{MaterialValues, Param};
use pipe::physics::pose::Pose;
use pipe::physics::rollout::{FrameLoss, Moduli, Rollout, RolloutError, Truncate, Wants};
use pipe::pipeline::spec::{MaterialFamily, SceneSpec};
use pipe::scene::gaussians::Gaussians;
use pipe::simulate::SimulateError;
use pipe_mpm::{Precision, State, StateGrad};

use crate::support::hash;

/// A 4×4×4 block of Gaussians 2 cm apart, SH degree 1.
fn block() -> Gaussians {
    block_of(false)
}

/// [`block`], or with `pairs` 32 sites 2 cm apart holding two Gaussians 2 mm apart each, so
/// that Gaussians share voxels of the filling and ride one particle.
fn block_of(pairs: bool) -> Gaussians {
    let n = 64;
    let mut g = Gaussians {
        sh_degree: 1,
        ..Default::default()
    };
    for i in 0..n {
        let (a, b, c) = (i / 16, (i / 4) % 4, i % 4);
        g.id.push(i as u32);
        let (c, d) = if pairs {
            (c / 2, (i % 2) as f32 * 0.001)
        } else {
            (c, 0.0)
        };
        g.position.push([
            -0.03 + 0.02 * a as f32 + 1.5 * d,
            0.06 + 0.02 * b as f32 + d,
            -0.03 + 0.02 * c as f32 - d,
        ]);
        g.log_scale.push([
            (0.011 * (1.0 + 0.3 * hash(i, 0))).ln() as f32,
            (0.009f64).ln() as f32,
            (0.012 * (1.0 + 0.2 * hash(i, 1))).ln() as f32,
        ]);
        let q = [1.0, 0.3 * hash(i, 2), -0.2 * hash(i, 3), 0.1];
        g.rotation.push(q.map(|v| v as f32));
        g.opacity_logit.push((1.0 + hash(i, 4)) as f32);
        for k in 0..12 {
            g.sh.push((0.6 * hash(i, 10 + k) - 0.2) as f32);
        }
        g.simulated.push(true);
    }
    g
}

fn scene() -> SceneSpec {
    serde_json::from_value(serde_json::json!({
        "dataset": "pacnerf",
        "path": "unused",
        "material": "elastic",
    }))
    .unwrap()
}

fn camera() -> pipe_render::Camera<f64> {
    // Looking along +z at the block from 0.45 m, OpenCV axes (y down).
    pipe_render::Camera {
        camera_from_world_rotation: [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
        camera_from_world_translation: [0.0, 0.07, 0.45],
        fx: 60.0,
        fy: 60.0,
        cx: 12.0,
        cy: 10.0,
        width: 24,
        height: 20,
        near: 0.01,
    }
}

/// `L = Σ w·image + Σ a·alpha` of the Gaussians posed at each frame, rendered in f64.
struct LinearLoss<'a> {
    object: &'a Object,
    means: Vec<[f64; 3]>,
    log_scales: Vec<[f64; 3]>,
    quats: Vec<[f64; 4]>,
    logits: Vec<f64>,
    sh: Vec<[f64; 3]>,
    cam: pipe_render::Camera<f64>,
}

impl<'a> LinearLoss<'a> {
    fn new(object: &'a Object) -> Self {
        let g = &object.gaussians;
        let f = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<_>>();
        Self {
            object,
            means: g.position.iter().map(|p| p.map(f64::from)).collect(),
            log_scales: g.log_scale.iter().map(|p| p.map(f64::from)).collect(),
            quats: g.rotation.iter().map(|p| p.map(f64::from)).collect(),
            logits: f(&g.opacity_logit),
            sh: f(&g.sh).chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            cam: camera(),
        }
    }
}

impl FrameLoss for LinearLoss<'_> {
    fn frame(
        &mut self,
        frame: u16,
        state: &State,
        grad: Option<&mut StateGrad>,
    ) -> Result<f64, RolloutError> {
        let pose = Pose::<f64>::of(state, self.object.skin(), false);
        let base = pipe_render::Gaussians {
            means: &self.means,
            scales: pipe_render::Scales::Log(&self.log_scales),
            quats: &self.quats,
            opacities: pipe_render::Opacities::Logit(&self.logits),
            colors: pipe_render::Colors::Sh {
                degree: 1,
                coeffs: &self.sh,
            },
            deformation: None,
        };
        let g = pose.apply(base);
        let opts = pipe_render::RenderOptions {
            background: [0.0; 3],
            ..Default::default()
        };
        let out = pipe_render::render(&g, &self.cam, &opts).unwrap();
        let n = out.alpha.len();
        let w: Vec<[f64; 3]> = (0..n)
            .map(|p| [0, 1, 2].map(|c| hash(p + 1000 * usize::from(frame), c) - 0.3))
            .collect();
        let a: Vec<f64> = (0..n)
            .map(|p| hash(p + 1000 * usize::from(frame), 7) - 0.5)
            .collect();
        let loss = out
            .image
            .iter()
            .zip(&w)
            .map(|(i, w)| i[0] * w[0] + i[1] * w[1] + i[2] * w[2])
            .sum::<f64>()
            + out.alpha.iter().zip(&a).map(|(x, a)| x * a).sum::<f64>();
        if let Some(grad) = grad {
            let gr = pipe_render::backward(&g, &self.cam, &opts, &out, &w, Some(&a)).unwrap();
            pose.seed(self.object.skin(), &gr, grad);
        }
        Ok(loss)
    }
}

/// An elastic material of Young's modulus `e` (Pa), ν 0.3, density 1000 kg/m³.
fn elastic(e: f64) -> MaterialValues {
    MaterialValues::guess(
        MaterialFamily::Elastic,
        1000.0,
        &BTreeMap::from([(Param::E, e), (Param::Nu, 0.3)]),
    )
}

fn object() -> Object {
    object_of(&block())
}

fn object_of(gaussians: &Gaussians) -> Object {
    object_on(gaussians, Resolution::Cells(4.0)).unwrap()
}

fn object_on(gaussians: &Gaussians, grid: Resolution) -> Result<Object, SimulateError> {
    let scene = scene();
    let material = elastic(5e3);
    let mut o = Object::build(
        gaussians,
        &ObjectSettings {
            scene: &scene,
            frame_dt: 0.01,
            grid,
            material: material.spec(),
            frames: 3,
            label: PathBuf::from("tiny"),
            splat_filter: 0.0,
            anchor: None,
        },
    )?;
    o.spec.substeps = Some(10);
    Ok(o)
}

fn velocity(object: &Object, shift: DVec3) -> Vec<DVec3> {
    let c = object.centre_of_mass();
    object
        .body
        .state
        .x
        .iter()
        .map(|x| DVec3::new(0.4, 0.2, -0.1) + DVec3::new(0.0, 0.0, 8.0).cross(*x - c) + shift)
        .collect()
}

/// The f64 rollout of the tiny scene under `values` (and per-particle `moduli`).
fn rollout_of<'a>(
    object: &'a Object,
    values: &'a MaterialValues,
    v0: &'a [DVec3],
    frames: u16,
    moduli: Option<&'a Moduli>,
) -> Rollout<'a> {
    Rollout {
        object,
        material: values,
        v0,
        frames,
        precision: Precision::F64,
        interrupt: None,
        moduli,
        free: None,
        work: None,
    }
}

/// One f64 rollout of the tiny scene under `values` (and per-particle `moduli`), scored by
/// [`LinearLoss`].
fn run_rollout(
    object: &Object,
    values: &MaterialValues,
    v0: &[DVec3],
    frames: u16,
    moduli: Option<&Moduli>,
    wants: Wants,
) -> Result<pipe::physics::rollout::Outcome, RolloutError> {
    rollout_of(object, values, v0, frames, moduli).run(&mut LinearLoss::new(object), wants)
}

fn rollout_loss(object: &Object, values: &MaterialValues, v0: &[DVec3], frames: u16) -> f64 {
    run_rollout(object, values, v0, frames, None, Wants::Loss)
        .unwrap()
        .loss()
}

/// A non-negative frame loss: the square of [`LinearLoss`]'s (losses only).
struct SquaredLoss<'a>(LinearLoss<'a>);

impl FrameLoss for SquaredLoss<'_> {
    fn frame(
        &mut self,
        frame: u16,
        state: &State,
        grad: Option<&mut StateGrad>,
    ) -> Result<f64, RolloutError> {
        assert!(grad.is_none(), "losses only");
        Ok(self.0.frame(frame, state, None)?.powi(2))
    }

    fn non_negative(&self) -> bool {
        true
    }
}

/// A search's trial stops after the frame whose loss takes the sum above the bound it is
/// rejected at (`Wants::LossUpTo`): the frames up to there are bit-identical to the whole
/// rollout's, the partial loss is above the bound, and a bound never exceeded, or a loss that
/// may be negative, runs every frame.
#[test]
fn a_trial_rollout_stops_once_its_loss_exceeds_the_bound() {
    let object = object();
    let values = elastic(5e3);
    let v0 = velocity(&object, DVec3::ZERO);
    let run = |wants: Wants| {
        rollout_of(&object, &values, &v0, 3, None)
            .run(&mut SquaredLoss(LinearLoss::new(&object)), wants)
            .unwrap()
    };
    let full = run(Wants::Loss);
    assert_eq!(full.frame_loss.len(), 3);
    assert!(!full.cut_short);
    assert!(
        full.frame_loss.iter().all(|l| l.is_finite() && *l > 0.0),
        "{:?}",
        full.frame_loss
    );
    let bound = full.frame_loss[0] + 0.5 * full.frame_loss[1];
    let short = run(Wants::LossUpTo(bound));
    assert!(short.cut_short);
    assert_eq!(short.frame_loss, full.frame_loss[..2].to_vec());
    assert_eq!(short.substeps, full.substeps[..2].to_vec());
    assert!(short.loss() > bound && short.loss() < full.loss());
    let whole = run(Wants::LossUpTo(full.loss()));
    assert!(!whole.cut_short);
    assert_eq!(whole.frame_loss, full.frame_loss);
    // A loss that may be negative is never cut short: a later frame could lower the sum.
    let out = run_rollout(
        &object,
        &values,
        &v0,
        3,
        None,
        Wants::LossUpTo(f64::NEG_INFINITY),
    )
    .unwrap();
    assert!(!out.cut_short);
    assert_eq!(out.frame_loss.len(), 3);
}

/// Faint splats strewn far around the body (a loose visual hull's leftovers) neither weigh
/// nor set the grid: the cells go across the filled solid, as without them, not across the
/// faint splats' box ten times larger (it was, and the grid was that much coarser).
#[test]
fn faint_splats_around_the_body_do_not_coarsen_its_grid() {
    let alone = object_of(&block());
    let mut g = block();
    for i in 0..31 {
        g.id.push(1000 + i as u32);
        g.position.push([-0.3 + 0.02 * i as f32, 0.1, 0.0]);
        g.log_scale.push([0.005f32.ln(); 3]);
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logit.push((0.01f32 / 0.99).ln());
        g.sh.extend([0.1f32; 12]);
        g.simulated.push(true);
    }
    let with = object_of(&g);
    let (a, b) = (alone.body.setup.dx, with.body.setup.dx);
    println!(
        "dx {a} alone, {b} with faint splats; mass {} / {} kg; {} / {} particles",
        alone.mass(),
        with.mass(),
        alone.particles(),
        with.particles()
    );
    assert!(a.is_finite() && b.is_finite());
    // The faint splats' box is 0.6 m across: 0.15 m cells for 4 cells across.
    assert!(b < 0.03, "the grid follows the faint splats: dx {b}");
    assert!(
        (b / a - 1.0).abs() < 0.25,
        "dx {b} against {a} without them"
    );
    assert!(
        (with.mass() / alone.mass() - 1.0).abs() < 0.25,
        "mass {} against {}",
        with.mass(),
        alone.mass()
    );
    assert_eq!(with.gaussians.len() + with.floaters, g.len());
}

/// A given cell (m) is the grid's, whatever the object's size (and `cells` is ignored); one
/// that would put more than `MAX_CELLS` across the object is refused, naming `dx`.
#[test]
fn a_given_cell_sets_the_grid_and_a_too_fine_one_is_refused() {
    let g = block();
    for dx in [0.02, 0.035] {
        let o = object_on(&g, Resolution::Dx(dx)).unwrap();
        assert_eq!(o.body.setup.dx, dx);
        assert!(o.particles() > 0 && o.mass().is_finite());
    }
    let coarse = object_on(&g, Resolution::Dx(0.035)).unwrap();
    let fine = object_on(&g, Resolution::Dx(0.02)).unwrap();
    assert!(fine.particles() > coarse.particles());
    let err = object_on(&g, Resolution::Dx(1e-5)).unwrap_err().to_string();
    assert!(
        err.contains("tiny.dx") && err.contains("at most 512"),
        "{err}"
    );
}

/// A grid cell that is not a positive length is refused by name when the pipeline loads.
#[test]
fn a_grid_cell_that_is_not_a_length_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let reg = pipe::stages::builtin();
    for (velocity, material, want) in [
        (
            "{}",
            "{dx: -1}",
            "stages.material.dx: must be a cell edge > 0 m, found -1",
        ),
        (
            "{dx: 0}",
            "{}",
            "stages.velocity.dx: must be a cell edge > 0 m, found 0",
        ),
    ] {
        let file = demo_pipeline(
            dir.path(),
            "draft",
            &format!(
                "  ingest: {{}}\n  init: {{}}\n  warmup: {{}}\n  velocity: {velocity}\n  material: {material}\n"
            ),
        );
        let e = pipe::pipeline::spec::load(&file, &reg, &Default::default())
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains(want), "{e}");
    }
}

#[test]
fn material_and_velocity_gradients_match_finite_differences_through_render_and_mpm() {
    let object = object();
    assert!(object.particles() >= 64, "{}", object.particles());
    check_material_and_velocity_gradients(&object);
}

/// As above, with Gaussians that share voxels riding one particle (`simulate::skin`): the
/// gradients reach the carriers through `x_g = x_c + F_c d_g`.
#[test]
fn gradients_through_gaussians_that_ride_one_particle_match_finite_differences() {
    let object = object_of(&block_of(true));
    assert_eq!(object.rendered(), 64);
    assert!(
        object.carriers() < 48 && !object.skin().is_identity(),
        "{} carriers",
        object.carriers()
    );
    assert!(object.skin().offset().iter().any(|d| d.length() > 1e-3));
    check_material_and_velocity_gradients(&object);
}

fn check_material_and_velocity_gradients(object: &Object) {
    let object = object.clone();
    let values = elastic(5e3);
    let v0 = velocity(&object, DVec3::ZERO);
    let frames = 2;
    let mut loss = LinearLoss::new(&object);
    let run = rollout_of(&object, &values, &v0, frames, None);
    let out = run.run(&mut loss, Wants::Velocity).unwrap();
    assert_eq!(out.substeps, vec![10, 10]);
    let grad = out.material.clone().unwrap();
    let l0 = out.loss();
    assert!(l0.is_finite() && l0.abs() > 1e-3, "loss {l0}");
    // Material: E and ν.
    for (p, h) in [(Param::E, 5e3 * 1e-5), (Param::Nu, 1e-5)] {
        let at = |d: f64| {
            let mut v = values.clone();
            *v.values.get_mut(&p).unwrap() += d;
            rollout_loss(&object, &v, &v0, frames)
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let ad = grad[&p];
        println!(
            "dL/d{}: adjoint {ad:.6e}, central difference {fd:.6e}",
            p.name()
        );
        assert!(fd.abs() > 1e-12, "{}: a gradient to check", p.name());
        assert!(
            (ad - fd).abs() <= 2e-4 * fd.abs().max(1e-9),
            "dL/d{}: adjoint {ad:e} vs central difference {fd:e}",
            p.name()
        );
    }
    // Initial velocity: a uniform change along each axis.
    let g_v0 = out.v0.as_ref().unwrap();
    assert_eq!(g_v0.len(), object.particles());
    for a in 0..3 {
        let h = 1e-6;
        let mut e = DVec3::ZERO;
        e[a] = h;
        let fd = (rollout_loss(&object, &values, &velocity(&object, e), frames)
            - rollout_loss(&object, &values, &velocity(&object, -e), frames))
            / (2.0 * h);
        let ad: f64 = g_v0.iter().map(|g| g[a]).sum();
        println!("dL/dv0[{a}]: adjoint {ad:.6e}, central difference {fd:.6e}");
        assert!(
            (ad - fd).abs() <= 2e-4 * fd.abs().max(1e-6),
            "dL/dv0[{a}]: adjoint {ad:e} vs central difference {fd:e}"
        );
    }
    // Through one frame, truncation changes nothing: the two modes agree.
    let one = |wants| {
        let mut l = LinearLoss::new(&object);
        Rollout { frames: 1, ..run }
            .run(&mut l, wants)
            .unwrap()
            .material
            .unwrap()
    };
    let (a, b) = (
        one(Wants::Material(Truncate::Frame)),
        one(Wants::Material(Truncate::None)),
    );
    for p in [Param::E, Param::Nu] {
        assert!(
            (a[&p] - b[&p]).abs() <= 1e-12 * b[&p].abs().max(1e-30),
            "{p:?}"
        );
    }
}

/// Per-particle `E` and `ν` (a material field's output): each particle's gradient, through
/// both frames (and the truncated mode's), matches central differences of the whole rollout;
/// uniform moduli give the global material's loss and, summed, its gradient.
/// A parts model ([`pipe::physics::field_parts::Parts`]: a field's values cut into a few
/// materials) gives each part's `∂L/∂(log10 E_k)` as the sum of its particles' `∂L/∂E_p`
/// times `E_k ln 10`: checked against central differences of the whole rollout (render and
/// MPM) in each part's `log10 E`.
#[test]
fn parts_gradients_match_finite_differences() {
    use pipe::physics::field_parts::{Parts, natural_breaks};
    let object = object();
    let n = object.particles();
    let values = elastic(5e3);
    let v0 = velocity(&object, DVec3::ZERO);
    // A field's values rising along x; three parts by natural breaks.
    let c = object.centre_of_mass();
    let field: Vec<f64> = object
        .body
        .state
        .x
        .iter()
        .map(|x| 3.6 + 2.0 * (x.x - c.x) + 0.05 * (x.y - c.y))
        .collect();
    let start = natural_breaks(&field, &object.body.material.volume, 3).unwrap();
    let field_e: Vec<f64> = field.iter().map(|l| 10f64.powf(*l)).collect();
    let part = start.assign(&field_e);
    for k in 0..3 {
        assert!(part.contains(&k), "part {k} is empty: {start:?}");
    }
    let moduli_of = |parts: &Parts| {
        let mut m = Moduli {
            e: field_e.clone(),
            nu: vec![0.3; n],
        };
        parts.apply(&part, &mut m);
        m
    };
    let run = |parts: &Parts, wants| {
        run_rollout(&object, &values, &v0, 2, Some(&moduli_of(parts)), wants).unwrap()
    };
    let out = run(&start, Wants::Material(Truncate::None));
    let g = start.gradient(&part, &out.moduli.as_ref().unwrap().e);
    assert_eq!(g.len(), 3);
    let h = 1e-4;
    for k in 0..3 {
        let at = |d: f64| {
            let mut p = start.clone();
            p.log10_e[k] += d;
            run(&p, Wants::Loss).loss()
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        println!(
            "part {k} dL/dlog10 E: adjoint {:.6e}, central difference {fd:.6e}",
            g[k]
        );
        assert!(fd.abs() > 1e-12, "part {k}: a gradient to check");
        assert!(
            (g[k] - fd).abs()
                <= 2e-4 * fd.abs() + 1e-6 * g.iter().fold(0.0f64, |m, v| m.max(v.abs())),
            "part {k}: adjoint {} vs central difference {fd}",
            g[k]
        );
    }
}

#[test]
fn per_particle_moduli_gradients_match_finite_differences() {
    let object = object();
    let n = object.particles();
    let values = elastic(5e3);
    let v0 = velocity(&object, DVec3::ZERO);
    // Two halves of different stiffness (split along x at the body's centre).
    let c = object.centre_of_mass();
    let moduli = Moduli {
        e: object
            .body
            .state
            .x
            .iter()
            .map(|x| if x.x < c.x { 3e3 } else { 9e3 })
            .collect(),
        nu: (0..n).map(|i| 0.2 + 0.2 * hash(i, 3)).collect(),
    };
    let run = |moduli: &Moduli, wants| {
        run_rollout(&object, &values, &v0, 2, Some(moduli), wants).unwrap()
    };
    for wants in [
        Wants::Material(Truncate::None),
        Wants::Material(Truncate::Frame),
    ] {
        let out = run(&moduli, wants);
        let g = out.moduli.as_ref().expect("per-particle gradients");
        assert_eq!((g.e.len(), g.nu.len()), (n, n));
        assert!(g.e.iter().chain(&g.nu).all(|v| v.is_finite()));
        if wants == Wants::Material(Truncate::Frame) {
            // The truncated gradient is not the rollout's derivative: only its shape is checked.
            continue;
        }
        // Largest per-particle gradient of each kind: the error floor is relative to it.
        let largest = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let (scale_e, scale_nu) = (largest(&g.e), largest(&g.nu));
        for p in [0, n / 3, n - 1] {
            for (which, h) in [("E", 1e-2), ("nu", 1e-6)] {
                let at = |d: f64| {
                    let mut m = moduli.clone();
                    if which == "E" {
                        m.e[p] += d;
                    } else {
                        m.nu[p] += d;
                    }
                    run(&m, Wants::Loss).loss()
                };
                let fd = (at(h) - at(-h)) / (2.0 * h);
                let ad = if which == "E" { g.e[p] } else { g.nu[p] };
                println!("particle {p} dL/d{which}: adjoint {ad:.6e}, central difference {fd:.6e}");
                assert!(
                    fd.abs() > 1e-14,
                    "particle {p} {which}: a gradient to check"
                );
                let scale = if which == "E" { scale_e } else { scale_nu };
                assert!(
                    (ad - fd).abs() <= 2e-4 * fd.abs() + 1e-4 * scale,
                    "particle {p} dL/d{which}: adjoint {ad:e} vs central difference {fd:e} (largest {scale:e})"
                );
            }
        }
    }
    // Uniform moduli are the global material.
    let uniform = Moduli {
        e: vec![5e3; n],
        nu: vec![0.3; n],
    };
    let with = run(&uniform, Wants::Material(Truncate::None));
    let global = run_rollout(
        &object,
        &values,
        &v0,
        2,
        None,
        Wants::Material(Truncate::None),
    )
    .unwrap();
    assert!((with.loss() - global.loss()).abs() <= 1e-12 * global.loss().abs());
    let (a, b) = (with.material.unwrap(), global.material.unwrap());
    for p in [Param::E, Param::Nu] {
        assert!(
            (a[&p] - b[&p]).abs() <= 1e-9 * b[&p].abs(),
            "{p:?}: summed {} vs global {}",
            a[&p],
            b[&p]
        );
    }
    // Lengths that do not match the particles are an error, not a panic.
    let short = Moduli {
        e: vec![5e3; n - 1],
        nu: vec![0.3; n - 1],
    };
    let err = run_rollout(&object, &values, &v0, 1, Some(&short), Wants::Loss).unwrap_err();
    assert!(err.to_string().contains("expected"), "{err}");
}

/// A material field's weights → per-particle E and ν → MPM → render → loss: the field's
/// gradient from the rollout's per-particle gradients (`MaterialField::output_gradient`, then
/// the field's backward) matches central differences of whole rollouts for a plane feature, a
/// hidden weight and the output bias of each output.
#[test]
fn material_field_gradients_match_finite_differences_through_render_and_mpm() {
    use pipe::physics::material_field::{FieldSettings, MaterialField};
    let object = object();
    let values = elastic(5e3);
    let v0 = velocity(&object, DVec3::ZERO);
    let settings = FieldSettings {
        resolution: 4,
        channels: 2,
        hidden: 8,
        layers: 1,
        ..FieldSettings::default()
    };
    let points: Vec<[f64; 3]> = object.body.state.x.iter().map(|x| x.to_array()).collect();
    let mut field =
        MaterialField::starting_at(&settings, points, vec![Param::E, Param::Nu], &values).unwrap();
    // Away from the constant start, so that every weight kind has a gradient: outputs vary by
    // about ±0.1 around the global values.
    let mut w = field.field.to_flat();
    for (i, x) in w.iter_mut().enumerate() {
        *x += 0.3 * (hash(i, 11) - 0.5);
    }
    field.field.set_flat(&w).unwrap();
    let loss_at = |f: &MaterialField, wants| {
        let moduli = f.moduli(&values).unwrap();
        let out = run_rollout(&object, &values, &v0, 2, Some(&moduli), wants).unwrap();
        (out, moduli)
    };
    let (out, moduli) = loss_at(&field, Wants::Material(Truncate::None));
    let e = &moduli.e;
    let spread = e.iter().fold(0.0f64, |m, x| m.max((x / 5e3).log10().abs()));
    assert!(spread > 0.01 && spread < 0.5, "log10 E spread {spread}");
    let d = field.output_gradient(&moduli, out.moduli.as_ref().unwrap());
    let grad = field.field.backward(&field.points, &d).unwrap().to_flat();
    assert_eq!(grad.len(), w.len());
    assert!(grad.iter().all(|g| g.is_finite()));
    let planes = field.field.triplane().values().len();
    let mlp = field.field.mlp().params().len();
    // A plane feature, a first-layer weight, and the two output biases (the MLP's last two).
    let largest_plane = (0..planes)
        .max_by(|a, b| grad[*a].abs().total_cmp(&grad[*b].abs()))
        .unwrap();
    for (kind, k) in [
        ("plane", largest_plane),
        ("hidden weight", planes + 3),
        ("log10 E bias", planes + mlp - 2),
        ("nu bias", planes + mlp - 1),
    ] {
        let h = 1e-6;
        let at = |delta: f64| {
            let mut f = field.clone();
            let mut w = w.clone();
            w[k] += delta;
            f.field.set_flat(&w).unwrap();
            loss_at(&f, Wants::Loss).0.loss()
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let ad = grad[k];
        println!("{kind} (weight {k}): adjoint {ad:.6e}, central difference {fd:.6e}");
        assert!(fd.abs() > 1e-9, "{kind}: a gradient to check");
        assert!(
            (ad - fd).abs() <= 2e-4 * fd.abs(),
            "{kind}: adjoint {ad:e} vs central difference {fd:e}"
        );
    }
}

/// A velocity field's weights → per-particle residual velocity (added to a rigid motion) →
/// MPM → render → loss: the field's backward from the rollout's `∂L/∂v0` matches central
/// differences of whole rollouts for a plane feature, a hidden weight and the three output
/// biases (vx, vy, vz); `initial_velocities` rebuilds the same velocities from the written
/// weights.
#[test]
fn velocity_field_gradients_match_finite_differences_through_render_and_mpm() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::velocity_field::{
        VelocityField, VelocityFieldSettings, initial_velocities, write_weights,
    };
    let object = object();
    let values = elastic(5e3);
    let rigid = RigidVelocity {
        linear: [0.1, -0.2, 0.05],
        angular: [0.0, 1.0, 0.5],
        centre: object.centre_of_mass().to_array(),
    };
    let base = rigid.field(&object);
    let settings = VelocityFieldSettings {
        resolution: 4,
        channels: 2,
        hidden: 8,
        layers: 1,
        ..VelocityFieldSettings::default()
    };
    let points: Vec<[f64; 3]> = object.body.state.x.iter().map(|x| x.to_array()).collect();
    let mut field = VelocityField::zero(&settings, points).unwrap();
    assert!(field.residual().unwrap().iter().all(|r| *r == DVec3::ZERO));
    let mut w = field.field.to_flat();
    for (i, x) in w.iter_mut().enumerate() {
        *x += 0.3 * (hash(i, 17) - 0.5);
    }
    field.field.set_flat(&w).unwrap();
    let v0_of = |f: &VelocityField| -> Vec<DVec3> {
        base.iter()
            .zip(f.residual().unwrap())
            .map(|(b, r)| *b + r)
            .collect()
    };
    let v0 = v0_of(&field);
    let out = run_rollout(&object, &values, &v0, 2, None, Wants::Velocity).unwrap();
    let grad = field.backward(out.v0.as_ref().unwrap()).unwrap().to_flat();
    assert_eq!(grad.len(), w.len());
    assert!(grad.iter().all(|g| g.is_finite()));
    let planes = field.field.triplane().values().len();
    let mlp = field.field.mlp().params().len();
    let largest_plane = (0..planes)
        .max_by(|a, b| grad[*a].abs().total_cmp(&grad[*b].abs()))
        .unwrap();
    for (kind, k) in [
        ("plane", largest_plane),
        ("hidden weight", planes + 3),
        ("vx bias", planes + mlp - 3),
        ("vy bias", planes + mlp - 2),
        ("vz bias", planes + mlp - 1),
    ] {
        let h = 1e-6;
        let at = |delta: f64| {
            let mut f = field.clone();
            let mut w = w.clone();
            w[k] += delta;
            f.field.set_flat(&w).unwrap();
            rollout_loss(&object, &values, &v0_of(&f), 2)
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let ad = grad[k];
        println!("{kind} (weight {k}): adjoint {ad:.6e}, central difference {fd:.6e}");
        assert!(fd.abs() > 1e-9, "{kind}: a gradient to check");
        assert!(
            (ad - fd).abs() <= 2e-4 * fd.abs(),
            "{kind}: adjoint {ad:e} vs central difference {fd:e}"
        );
    }
    // Written and read back: the same velocities at the same particles.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("field.velocity.arrow");
    write_weights(&path, &field).unwrap();
    let back = initial_velocities(&object, &rigid, Some(&path)).unwrap();
    assert_eq!(back.len(), v0.len());
    for (a, b) in back.iter().zip(&v0) {
        assert!((*a - *b).length() < 1e-12, "{a} vs {b}");
    }
    // A missing table is an error naming it.
    let err =
        initial_velocities(&object, &rigid, Some(&dir.path().join("none.arrow"))).unwrap_err();
    assert!(err.contains("none.arrow"), "{err}");
}

#[test]
fn a_newtonian_scene_learns_only_the_fluids_parameters() {
    let fluid = MaterialValues::guess(MaterialFamily::Newtonian, 1000.0, &BTreeMap::new());
    assert_eq!(fluid.spec().mpm_family(), pipe_mpm::Family::Newtonian);
    assert_eq!(
        Param::learned_by_default(MaterialFamily::Newtonian),
        &[Param::Viscosity, Param::BulkModulus]
    );
    let mut object = object();
    // The fluid's bulk modulus needs more substeps than the solid's fixed ten.
    object.spec.substeps = None;
    let v0 = velocity(&object, DVec3::ZERO);
    let mut l = LinearLoss::new(&object);
    let out = rollout_of(&object, &fluid, &v0, 1, None)
        .run(&mut l, Wants::Material(Truncate::Frame))
        .unwrap();
    let keys: Vec<Param> = out.material.unwrap().into_keys().collect();
    assert_eq!(keys, vec![Param::Viscosity, Param::BulkModulus]);
}

/// A pipeline over the fixture scene (the demo's torus) in `dir`: `stages` is the `stages:`
/// body (lines indented by two spaces).
fn demo_pipeline(dir: &std::path::Path, preset: &str, stages: &str) -> PathBuf {
    let file = dir.join("p.yaml");
    std::fs::write(
        &file,
        format!(
            "name: t\nscene:\n  dataset: pacnerf\n  path: {}\n  test_views: [10]\n  material: elastic\npreset: {preset}\nstages:\n{stages}",
            crate::support::fixture_scene().display()
        ),
    )
    .unwrap();
    file
}

/// Runs `file` in this process with the built-in stages.
fn run_builtin(dir: &std::path::Path, file: &std::path::Path, until: Option<&str>) {
    let reg = pipe::stages::builtin();
    let p = pipe::pipeline::spec::load(file, &reg, &Default::default()).unwrap();
    let stop = std::sync::atomic::AtomicBool::new(false);
    pipe::pipeline::runner::Workspace::new(dir)
        .run(
            &p,
            &reg,
            &pipe::pipeline::runner::RunOptions {
                until: until.map(str::to_string),
                ..Default::default()
            },
            &pipe::pipeline::progress::Reporter::new(pipe::pipeline::progress::Mode::Quiet),
            &stop,
            "test",
        )
        .unwrap();
}

/// The committed entry of `stage`.
fn entry(dir: &std::path::Path, file: &std::path::Path, stage: &str) -> PathBuf {
    let reg = pipe::stages::builtin();
    let p = pipe::pipeline::spec::load(file, &reg, &Default::default()).unwrap();
    pipe::pipeline::runner::Workspace::new(dir)
        .cached_entry(&p, &reg, stage)
        .unwrap()
}

/// The demo with `draft`, its material started 10× too stiff: the learned Young's modulus ends
/// within 2× of the truth (1e6 Pa) and the initial velocity within 0.05 m/s of (0.15, −0.3,
/// 0.1) m/s. Shortened to fit the test suite: a warm-up of 60 epochs and at most 6 000
/// Gaussians, 4 material epochs.
#[test]
fn the_demo_at_draft_learns_velocity_and_e_from_ten_times_too_stiff() {
    let dir = tempfile::tempdir().unwrap();
    let file = demo_pipeline(
        dir.path(),
        "draft",
        "  ingest: {}\n  init: {}\n  warmup: {epochs: 60, max_gaussians: 6000}\n  velocity: {}\n  \
         material: {model: global, epochs: 4, guess: {E: 1.0e7}}\n",
    );
    run_builtin(dir.path(), &file, None);
    let m: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(entry(dir.path(), &file, "material").join("material.json"))
            .unwrap(),
    )
    .unwrap();
    let e = m["youngs_modulus"].as_f64().unwrap();
    let nu = m["poisson_ratio"].as_f64().unwrap();
    println!("learned E {e:.4e} Pa, nu {nu:.4}; material.json: {m}");
    assert!(e > 0.5e6 && e < 2e6, "E = {e:e} Pa, truth 1e6");
    assert!(nu > 0.0 && nu < 0.49);
    let v: [f64; 3] = serde_json::from_value(m["initial_velocity"].clone()).unwrap();
    let err = (DVec3::from_array(v) - DVec3::new(0.15, -0.3, 0.1)).length();
    assert!(err <= 0.05, "v0 {v:?}: {err} m/s off");
    assert!(m["loss_final"].as_f64().unwrap() < m["loss_guess"].as_f64().unwrap());
    // The profile of the fit: E and ν, each moved alone. E is pinned by the frames on both
    // sides (the torus's bounce: a quarter decade moves the loss by a third), its bounds about
    // the profiled value and the result; every move's statistics are finite.
    let profile: Vec<pipe::physics::profile::ParamProfile> =
        serde_json::from_value(m["profile"].clone()).unwrap();
    let names: Vec<&str> = profile.iter().map(|p| p.param.as_str()).collect();
    assert_eq!(names, ["E", "nu"], "{}", m["profile"]);
    let pe = &profile[0];
    // The fit may then take the parabola's vertex, within half a step (0.125 decades).
    assert!(
        (e / pe.value).log10().abs() <= 0.125 + 1e-12,
        "{e} {}",
        pe.summary()
    );
    assert_eq!(
        pe.ends,
        [pipe::physics::profile::SideEnd::Bounded; 2],
        "{}",
        pe.summary()
    );
    let [lo, hi] = pe.bounds.map(Option::unwrap);
    assert!(
        lo < pe.value && pe.value < hi && lo < e && e < hi && hi / lo <= 100.0,
        "{}",
        pe.summary()
    );
    for p in &profile {
        for mv in p.below.iter().chain(&p.above) {
            assert!(
                mv.rise_pct.is_finite() && mv.t.is_finite(),
                "{}",
                p.summary()
            );
        }
        assert!(
            !p.below.is_empty() && !p.above.is_empty(),
            "{}",
            p.summary()
        );
    }
    // Only the family's parameters: no fluid or plastic ones.
    assert!(m["viscosity"].is_null() && m["yield_stress"].is_null());
    for f in ["scene.sim.yaml", "particles.arrow", "metrics.arrow"] {
        assert!(
            entry(dir.path(), &file, "material").join(f).is_file(),
            "{f}"
        );
    }
    // One shared path: `pipe simulate` of the warm-up's Gaussians with the learned
    // `scene.sim.yaml`, as its header says, builds the stage's particles (the Gaussians of a
    // voxel riding one particle).
    let pipe = |args: &[&std::ffi::OsStr]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_pipe"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let (ply, sim) = (dir.path().join("object.ply"), dir.path().join("sim"));
    let os = |s: &str| std::ffi::OsString::from(s);
    pipe(&[
        os("export").as_os_str(),
        file.as_os_str(),
        os("--workdir").as_os_str(),
        dir.path().as_os_str(),
        os("--stage").as_os_str(),
        os("warmup").as_os_str(),
        os("--format").as_os_str(),
        os("ply").as_os_str(),
        os("--out").as_os_str(),
        ply.as_os_str(),
    ]);
    let yaml = entry(dir.path(), &file, "material").join("scene.sim.yaml");
    pipe(&[
        os("simulate").as_os_str(),
        ply.as_os_str(),
        os("--material").as_os_str(),
        yaml.as_os_str(),
        os("--frames").as_os_str(),
        os("2").as_os_str(),
        os("--out").as_os_str(),
        sim.as_os_str(),
        os("--splats").as_os_str(),
    ]);
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sim.join("summary.json")).unwrap()).unwrap();
    let (carriers, fill) = (
        s["carrier_particles"].as_u64().unwrap(),
        s["fill_particles"].as_u64().unwrap(),
    );
    assert_eq!(carriers + fill, m["particles"].as_u64().unwrap(), "{s}");
    // The learned spin travels with the file: the same angular velocity, about the stage
    // body's centre of mass, which `pipe simulate`'s body shares.
    let w: [f64; 3] = serde_json::from_value(m["angular_velocity"].clone()).unwrap();
    assert!(
        w.iter().any(|w| *w != 0.0),
        "a learned rigid motion turns a little: {w:?}"
    );
    let sw: [f64; 3] = serde_json::from_value(s["angular_velocity"].clone()).unwrap();
    assert_eq!(sw, w, "{s}");
    let c: [f64; 3] = serde_json::from_value(s["spin_centre"].clone()).unwrap();
    let v: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(entry(dir.path(), &file, "velocity").join("velocity.json"))
            .unwrap(),
    )
    .unwrap();
    let com: [f64; 3] = serde_json::from_value(v["centre_of_mass"].clone()).unwrap();
    let off = (DVec3::from_array(c) - DVec3::from_array(com)).length();
    assert!(off < 1e-4, "spin centre {c:?} against the stage's {com:?}");
    assert!(carriers < s["particles_out"].as_u64().unwrap(), "{s}");
    // Every Gaussian is written, carried by its particle: moved by the fall, none left behind.
    let g0 = pipe::io::ply::read_gaussians(&ply).unwrap();
    let g1 = pipe::io::ply::read_gaussians(&sim.join("splats_0001.ply")).unwrap();
    assert_eq!(g1.len(), g0.len());
    let shift: Vec<f32> = g0
        .position
        .iter()
        .zip(&g1.position)
        .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt())
        .collect();
    assert!(
        shift
            .iter()
            .all(|d| d.is_finite() && *d > 0.005 && *d < 0.03),
        "{:?}",
        &shift[..8]
    );
}

/// `material: {model: field}` on the demo (shortened; the field stepped after every frame,
/// `field.truncate: frame`, as the default searched step may rightly refuse every step on
/// four frames): the global fit, then the field from it;
/// `material.json` reports the field (percentiles, colour map, the global fit's loss),
/// `particles.arrow` holds each particle's E and ν, the weights table rebuilds the same field,
/// `field_E.ply` has one Gaussian per rendered particle (a fluid's refusal: the lib's unit test
/// `a_field_needs_a_solid_and_e_or_nu_among_the_learned`).
#[test]
fn a_material_field_is_learned_from_the_global_fit_and_written() {
    use pipe::physics::material_field::FieldTable;
    use pipe::physics::particles::MaterialParticles;
    // Frames 1–4 are the torus's free flight: `closed_form: false` simulates them, so that
    // the field has a gradient to follow (in closed form they say nothing of the material).
    let stages = "  ingest: {frames: [0, 1, 2, 3, 4]}\n  init: {}\n  warmup: {epochs: 20}\n  \
                  velocity: {epochs: 2, frames: 3, cells: 10}\n  \
                  material: {model: field, epochs: 2, cells: 10, guess: {E: 3.0e5}, \
                  closed_form: false, \
                  field: {epochs: 2, resolution: 8, channels: 4, hidden: 16, truncate: frame}}\n";
    let dir = tempfile::tempdir().unwrap();
    let file = demo_pipeline(dir.path(), "draft", stages);
    run_builtin(dir.path(), &file, None);
    let out = entry(dir.path(), &file, "material");
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("material.json")).unwrap()).unwrap();
    println!("{m}");
    assert_eq!(m["model"], "field");
    let f = &m["field"];
    let pe: [f64; 3] =
        serde_json::from_value(f["log10_youngs_modulus_p05_p50_p95"].clone()).unwrap();
    assert!(
        pe[0] <= pe[1] && pe[1] <= pe[2] && pe[0].is_finite(),
        "{pe:?}"
    );
    let e = m["youngs_modulus"].as_f64().unwrap();
    assert!((e.log10() - pe[1]).abs() < 1e-9, "E is the median");
    assert!(f["loss_global"].as_f64().unwrap().is_finite());
    let parts: MaterialParticles = pipe::scene::table::read(&out.join("particles.arrow")).unwrap();
    let es: Vec<f64> = parts.youngs_pa.iter().map(|v| v.unwrap()).collect();
    assert!(es.iter().all(|v| v.is_finite() && *v > 0.0));
    let (lo, hi) = es
        .iter()
        .fold((f64::MAX, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
    assert!(hi > lo, "a field: E varies over the particles ({lo}..{hi})");
    // The weights table rebuilds the field: its E at the particles is particles.arrow's.
    let t: FieldTable = pipe::scene::table::read(&out.join("field.material.arrow")).unwrap();
    let field = pipe_field::Field::from_weights(&t.weights).unwrap();
    assert_eq!(field.param_count(), f["weights"].as_u64().unwrap() as usize);
    let pts: Vec<[f64; 3]> = parts.x.iter().map(|p| p.map(f64::from)).collect();
    let y = field.forward(&pts).unwrap();
    assert_eq!(t.outputs, vec!["E".to_string()], "E varies, ν stays global");
    let c = t.log10_e_centre.unwrap();
    let bound = pipe::physics::material_field::E_RANGE_DECADES;
    for (i, e) in es.iter().enumerate().step_by(97) {
        // particles.arrow keeps f32 positions: E agrees to the field's slope over 1e-7 m.
        let log_e = c + bound * ((y[i] - c) / bound).tanh();
        assert!((log_e - e.log10()).abs() < 1e-4, "particle {i}");
        assert!(
            (e.log10() - c).abs() < bound,
            "E within the bounded map's range"
        );
    }
    let g = pipe::io::ply::read_gaussians(&out.join("field_E.ply")).unwrap();
    assert_eq!(g.len() as u64, m["gaussians"].as_u64().unwrap());
}

/// `kill -9` of `pipe run` during `material`: the next run resumes from the last checkpoint,
/// says so, and writes the same `material.json` and `particles.arrow` as an uninterrupted run.
#[test]
fn a_killed_material_stage_resumes_to_the_same_result() {
    let stages = "  ingest: {frames: [0, 1, 2, 3, 4]}\n  init: {}\n  warmup: {epochs: 20}\n  \
                  velocity: {epochs: 2, frames: 3, cells: 10}\n  \
                  material: {model: global, epochs: 4, cells: 10, guess: {E: 3.0e5}}\n";
    // Uninterrupted.
    let a = tempfile::tempdir().unwrap();
    let file_a = demo_pipeline(a.path(), "draft", stages);
    run_builtin(a.path(), &file_a, None);
    let read = |dir: &std::path::Path, file: &std::path::Path, name: &str| {
        std::fs::read(entry(dir, file, "material").join(name)).unwrap()
    };
    // Killed once its first checkpoint exists, then run again.
    let b = tempfile::tempdir().unwrap();
    let file_b = demo_pipeline(b.path(), "draft", stages);
    run_builtin(b.path(), &file_b, Some("velocity"));
    let pipe_bin = env!("CARGO_BIN_EXE_pipe");
    let mut child = std::process::Command::new(pipe_bin)
        .args(["--quiet", "--workdir"])
        .arg(b.path())
        .arg("run")
        .arg(&file_b)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let checkpoints = b.path().join(".pipe/checkpoints");
    let started = std::time::Instant::now();
    // A complete generation: not the `next/` one being assembled (killed there, nothing
    // would be resumed).
    let has_checkpoint = || {
        walk(&checkpoints).iter().any(|p| {
            p.ends_with("checkpoint.json")
                && p.to_string_lossy().contains("material-")
                && p.parent().and_then(|d| d.file_name()) != Some("next".as_ref())
        })
    };
    while !has_checkpoint() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before its first checkpoint"
        );
        assert!(
            started.elapsed().as_secs() < 300,
            "no checkpoint after 300 s"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let status = std::process::Command::new("kill")
        .args(["-9", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    child.wait().unwrap();
    let out = std::process::Command::new(pipe_bin)
        .args(["--quiet", "--workdir"])
        .arg(b.path())
        .arg("run")
        .arg(&file_b)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("resuming `material` from its checkpoint"),
        "the re-run says it resumed: {stderr}"
    );
    for name in ["material.json", "particles.arrow", "scene.sim.yaml"] {
        assert_eq!(
            read(a.path(), &file_a, name),
            read(b.path(), &file_b, name),
            "{name} differs from the uninterrupted run's"
        );
    }
}

/// `material.budget`: no epoch starts once the stage's simulation work passes the budget
/// (here any work, so one epoch runs), the stage keeps what that epoch learned and records its
/// work, and the same run without a budget goes on: the same first epoch, more work. (Frames
/// 1–4 of the demo are in free flight: `closed_form: false` simulates them, so that the
/// material has a gradient.)
#[test]
fn a_material_budget_stops_the_descent_once_spent() {
    let stages = |budget: &str| {
        format!(
            "  ingest: {{frames: [0, 1, 2, 3, 4]}}\n  init: {{}}\n  warmup: {{epochs: 20}}\n  \
             velocity: {{epochs: 2, frames: 3, cells: 10}}\n  \
             material: {{model: global, epochs: 3, cells: 10, probe: 0, closed_form: false, \
             guess: {{E: 3.0e5}}{budget}}}\n"
        )
    };
    let metrics = |budget: &str| {
        let dir = tempfile::tempdir().unwrap();
        let file = demo_pipeline(dir.path(), "draft", &stages(budget));
        run_builtin(dir.path(), &file, None);
        let m: pipe::scene::metrics::Metrics =
            pipe::scene::table::read(&entry(dir.path(), &file, "material").join("metrics.arrow"))
                .unwrap();
        m.rows
    };
    let epochs = |rows: &[pipe::pipeline::stage::MetricRow]| -> Vec<(u32, f64)> {
        rows.iter()
            .filter(|r| r.metric == "loss")
            .map(|r| (r.epoch.unwrap(), r.value))
            .collect()
    };
    let work = |rows: &[pipe::pipeline::stage::MetricRow]| {
        rows.iter()
            .find(|r| r.metric == "work_particle_substeps")
            .map(|r| r.value)
            .unwrap()
    };
    let (free, spent) = (metrics(""), metrics(", budget: 1.0e-12"));
    let (e_free, e_spent) = (epochs(&free), epochs(&spent));
    println!("epochs without a budget {e_free:?}, with one {e_spent:?}");
    assert_eq!(e_spent.len(), 1, "one epoch under the budget: {e_spent:?}");
    assert!(e_free.len() > 1, "more without it: {e_free:?}");
    assert_eq!(e_spent[0], e_free[0], "the same first epoch");
    let (w_free, w_spent) = (work(&free), work(&spent));
    println!("work {w_spent:.4e} / {w_free:.4e} particle-substeps");
    assert!(
        w_spent.is_finite() && w_spent > 0.0 && w_spent < w_free,
        "work {w_spent} against {w_free}"
    );
}

/// Every file under `dir`.
fn walk(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
    }
    out
}

/// The closed-form free flight (`physics::free_flight`): its `(∂L/∂v, ∂L/∂ω)` through the
/// posed Gaussians and the renderer (f64) match central differences of its loss, and its
/// particles are where an MPM rollout of the same throw puts them while nothing touches it.
#[test]
fn free_flight_in_closed_form_matches_finite_differences_and_the_simulation() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::free_flight;
    let object = object();
    let rigid = RigidVelocity {
        linear: [0.3, -0.2, 0.1],
        angular: [2.0, -4.0, 3.0],
        centre: object.centre_of_mass().to_array(),
    };
    let frames = 2;
    let loss_at = |r: &RigidVelocity| {
        let mut l = LinearLoss::new(&object);
        free_flight::run(&object, r, frames, false, &mut l, false)
            .unwrap()
            .0
    };
    let mut l = LinearLoss::new(&object);
    let (value, grad) = free_flight::run(&object, &rigid, frames, false, &mut l, true).unwrap();
    let (gv, gw) = grad.unwrap();
    assert!(value.is_finite() && (value - loss_at(&rigid)).abs() < 1e-12);
    for k in 0..6 {
        let h = 1e-6;
        let at = |d: f64| {
            let mut r = rigid;
            if k < 3 {
                r.linear[k] += d;
            } else {
                r.angular[k - 3] += d;
            }
            loss_at(&r)
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let ad = if k < 3 { gv[k] } else { gw[k - 3] };
        println!("coordinate {k}: closed form {ad:.6e}, central difference {fd:.6e}");
        assert!(fd.abs() > 1e-9, "coordinate {k}: a gradient to check");
        assert!(
            (ad - fd).abs() <= 1e-5 * fd.abs() + 1e-10,
            "coordinate {k}: {ad:e} vs {fd:e}"
        );
    }
    // MPM rollouts of the same throw of a stiff body (nothing in reach within two frames),
    // spinning and not: symplectic Euler's substeps put a falling body ½·g·t·Δt lower than the
    // parabola (~1e-5 m here); the closed form turns the body with the inertia APIC's affine
    // velocities add (it spun 4 % of the travel off when it turned at ω itself).
    let values = elastic(1e6);
    let mut stiff = object.clone();
    stiff.spec.substeps = None;
    struct Last(Vec<DVec3>);
    impl FrameLoss for Last {
        fn frame(
            &mut self,
            _: u16,
            s: &State,
            _: Option<&mut StateGrad>,
        ) -> Result<f64, RolloutError> {
            self.0 = s.x.clone();
            Ok(0.0)
        }
    }
    let largest = |a: &[DVec3], b: &[DVec3]| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max)
    };
    for (motion, tolerance) in [
        (
            RigidVelocity {
                angular: [0.0; 3],
                ..rigid
            },
            0.005,
        ),
        (rigid, 0.005),
    ] {
        let out = run_rollout(
            &stiff,
            &values,
            &motion.field(&stiff),
            frames,
            None,
            Wants::Loss,
        )
        .unwrap();
        let mut last = Last(Vec::new());
        free_flight::run(&stiff, &motion, frames, false, &mut last, false).unwrap();
        let travelled = largest(&stiff.body.state.x, &last.0);
        let off = largest(&out.last.x, &last.0);
        println!(
            "ω {:?}: largest travel {travelled:.3e} m, MPM against closed form {off:.3e} m",
            motion.angular
        );
        assert!(travelled > 5e-3, "{travelled}");
        assert!(
            off <= tolerance * travelled,
            "ω {:?}: {off} m off after {travelled} m",
            motion.angular
        );
    }
}

/// A bar tumbling about no principal axis: its angular velocity wanders (Euler's equations)
/// and the simulator turns it with APIC's affine inertia added. The closed form follows the MPM
/// rollout of the same throw to within 0.2 % of the travel (measured 0.16 mm after 19 cm),
/// where a steady turn at `ω` is more than ten times further off (measured 30 mm).
#[test]
fn a_tumbling_bar_in_closed_form_follows_the_simulation() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::free_flight;
    let mut g = Gaussians {
        sh_degree: 1,
        ..Default::default()
    };
    let mut i = 0;
    for a in 0..9 {
        for b in 0..2 {
            for c in 0..3 {
                g.id.push(i);
                g.position.push([
                    -0.08 + 0.02 * a as f32,
                    0.5 + 0.02 * b as f32,
                    -0.02 + 0.02 * c as f32,
                ]);
                g.log_scale.push([0.011f32.ln(); 3]);
                g.rotation.push([1.0, 0.0, 0.0, 0.0]);
                g.opacity_logit.push(2.0);
                g.sh.extend([0.5f32; 12]);
                g.simulated.push(true);
                i += 1;
            }
        }
    }
    let mut object = object_on(&g, Resolution::Cells(8.0)).unwrap();
    object.spec.substeps = None;
    let c = object.centre_of_mass();
    let rigid = RigidVelocity {
        linear: [0.2, 0.1, 0.0],
        angular: [4.0, 12.0, 16.0],
        centre: c.to_array(),
    };
    let frames = 10;
    let values = elastic(3e6);
    let mpm = run_rollout(
        &object,
        &values,
        &rigid.field(&object),
        frames,
        None,
        Wants::Loss,
    )
    .unwrap();
    let closed = free_flight::positions(&object, &rigid, frames);
    // A steady turn at ω about the same falling centre.
    let t = f64::from(frames) * object.spec.frame_dt;
    let w = DVec3::from_array(rigid.angular);
    let steady = glam::DMat3::from_axis_angle(w.normalize(), w.length() * t);
    let centre = c
        + DVec3::from_array(rigid.linear) * t
        + 0.5 * DVec3::from_array(object.spec.gravity) * t * t;
    let largest = |a: &[DVec3], b: &[DVec3]| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max)
    };
    let rest = &object.body.state.x;
    let steady_x: Vec<DVec3> = rest.iter().map(|x| centre + steady * (*x - c)).collect();
    let travelled = largest(rest, &mpm.last.x);
    let off = largest(&mpm.last.x, &closed);
    let off_steady = largest(&mpm.last.x, &steady_x);
    println!(
        "travel {travelled:.3e} m; MPM against the closed form {off:.3e} m, against a steady turn {off_steady:.3e} m"
    );
    assert!(travelled > 0.05 && off.is_finite(), "{travelled}");
    assert!(off <= 0.002 * travelled, "{off} m off after {travelled} m");
    assert!(off_steady > 10.0 * off, "{off_steady} against {off}");
}

/// The closed form is used only where nothing but gravity acts: a body clear of the default
/// ground passes, one thrown into it within the frames or resting on it does not.
#[test]
fn free_flight_needs_a_body_clear_of_every_boundary() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::free_flight::touches_nothing;
    let mut object = object();
    let low = object
        .body
        .state
        .x
        .iter()
        .map(|x| x.y)
        .fold(f64::MAX, f64::min);
    let dx = object.body.setup.dx;
    // Lift the block to four cells above the ground (y = 0, the scene's default).
    let lift = 4.0 * dx - low;
    object.body.state.x.iter_mut().for_each(|x| x.y += lift);
    let centre = object.centre_of_mass().to_array();
    let at = |v: [f64; 3]| RigidVelocity {
        linear: v,
        angular: [0.0; 3],
        centre,
    };
    assert!(touches_nothing(&object, &at([0.0; 3]), 2));
    // Thrown down at 3 m/s it covers 6 cm in two frames of 0.01 s: into the ground.
    assert!(!touches_nothing(&object, &at([0.0, -3.0, 0.0]), 2));
    // Resting on the ground.
    object
        .body
        .state
        .x
        .iter_mut()
        .for_each(|x| x.y -= 4.0 * dx - 0.2 * dx);
    assert!(!touches_nothing(&object, &at([0.0; 3]), 2));
}

/// The `material` stage's rollouts start where the free flight ends: a block thrown down and
/// sideways, clear of the ground for its first frames, then landing on it (sticky). Started
/// from the closed form, the rollout's frames are the simulated ones' up to the integrator's
/// own lag behind the parabola, its closed-form frames take no substep, and its material
/// gradient is the whole one's (no stress acts in free flight). A spin stresses the body: a
/// fast one gets no closed-form frame.
#[test]
fn a_rollout_started_where_the_free_flight_ends_matches_the_one_from_frame_0() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::free_flight::{FreeFrames, frames_in_flight};
    let mut object = object();
    object.spec.substeps = None;
    let dx = object.body.setup.dx;
    object.body.state.x.iter_mut().for_each(|x| x.y += 2.0 * dx);
    let rigid = RigidVelocity {
        linear: [0.3, -2.0, 0.0],
        angular: [0.0; 3],
        centre: object.centre_of_mass().to_array(),
    };
    let frames = 8;
    let spinning = RigidVelocity {
        angular: [0.0, 0.0, 5.0],
        ..rigid
    };
    assert!(frames_in_flight(&object, &spinning, frames) >= 1);
    assert!(FreeFrames::of(&object, &spinning, frames, false).is_none());
    let free = FreeFrames::of(&object, &rigid, frames, false).expect("a free flight");
    let k = free.frames();
    println!("dx {dx:.4} m: in free flight until frame {k} of {frames}");
    assert!(k >= 1 && k < frames - 2, "{k}");
    assert_eq!(k, frames_in_flight(&object, &rigid, frames));
    let values = elastic(5e3);
    let v0 = rigid.field(&object);
    struct Kept<'a>(LinearLoss<'a>, Vec<State>);
    impl FrameLoss for Kept<'_> {
        fn frame(
            &mut self,
            frame: u16,
            s: &State,
            g: Option<&mut StateGrad>,
        ) -> Result<f64, RolloutError> {
            self.1.push(s.clone());
            self.0.frame(frame, s, g)
        }
    }
    let run = |free: Option<&FreeFrames>, wants: Wants| {
        let mut loss = Kept(LinearLoss::new(&object), Vec::new());
        let out = Rollout {
            free,
            ..rollout_of(&object, &values, &v0, frames, None)
        }
        .run(&mut loss, wants)
        .unwrap();
        (out, loss.1)
    };
    let (whole, whole_states) = run(None, Wants::Material(Truncate::Frame));
    let (started, started_states) = run(Some(&free), Wants::Material(Truncate::Frame));
    assert_eq!(started.frame_loss.len(), usize::from(frames));
    assert_eq!(started_states.len(), whole_states.len());
    assert!(started.substeps[..usize::from(k)].iter().all(|&n| n == 0));
    assert!(started.substeps[usize::from(k)..].iter().all(|&n| n > 0));
    let travel = (whole_states.last().unwrap().x[0] - object.body.state.x[0]).length();
    // Symplectic Euler's substeps put a falling body ½·g·t·Δt below the parabola: the
    // simulated start is that far from the exact one at frame k.
    let dt = object.spec.frame_dt / *whole.substeps[..usize::from(k)].iter().min().unwrap() as f64;
    let t_k = f64::from(k) * object.spec.frame_dt;
    let lag = 0.5 * DVec3::from_array(object.spec.gravity).length() * t_k * dt;
    println!(
        "substeps {:?}; the integrator's lag at frame {k}: {lag:.3e} m",
        whole.substeps
    );
    for (f, (a, b)) in whole_states.iter().zip(&started_states).enumerate() {
        assert!(b.x.iter().chain(&b.v).all(|v| v.is_finite()));
        let off =
            a.x.iter()
                .zip(&b.x)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f64::max);
        println!("frame {}: {off:.3e} m apart (travel {travel:.3e} m)", f + 1);
        assert!(off <= 1.1 * lag + 1e-6, "frame {}: {off} m", f + 1);
    }
    let (ge, gs) = (
        whole.material.as_ref().unwrap()[&Param::E],
        started.material.as_ref().unwrap()[&Param::E],
    );
    println!("∂L/∂E: from frame 0 {ge:.6e}, from frame {k} {gs:.6e}");
    assert!(ge.abs() > 0.0 && gs.is_finite());
    assert!((gs - ge).abs() <= 0.002 * ge.abs(), "{gs:e} against {ge:e}");
    // The velocity's gradient needs every frame: the closed form is not used for it.
    let (vel, _) = run(Some(&free), Wants::Velocity);
    assert!(vel.substeps.iter().all(|&n| n > 0));
    assert!(vel.v0.is_some_and(|g| g.len() == object.particles()));
    // A trial cut short within the closed-form frames simulates nothing.
    let mut squared = SquaredLoss(LinearLoss::new(&object));
    let cut = Rollout {
        free: Some(&free),
        work: None,
        ..rollout_of(&object, &values, &v0, frames, None)
    }
    .run(&mut squared, Wants::LossUpTo(0.0))
    .unwrap();
    assert!(cut.cut_short && cut.frame_loss.len() == 1 && cut.substeps == [0]);
}

/// The free flight is checked between frames too: a bar spinning half a turn per frame about
/// its middle, lying clear of the ground at every frame, dips a tip into it between two.
#[test]
fn a_tip_that_swings_into_the_ground_between_two_frames_ends_the_free_flight() {
    use pipe::physics::fit::RigidVelocity;
    use pipe::physics::free_flight::{frames_in_flight, positions};
    use pipe::physics::torque_free::FreeRotation;
    let mut g = Gaussians {
        sh_degree: 1,
        ..Default::default()
    };
    for a in 0..16 {
        g.id.push(a);
        g.position.push([-0.15 + 0.02 * a as f32, 0.16, 0.0]);
        g.log_scale.push([0.011f32.ln(); 3]);
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logit.push(2.0);
        g.sh.extend([0.5f32; 12]);
        g.simulated.push(true);
    }
    let mut object = object_on(&g, Resolution::Cells(16.0)).unwrap();
    object.spec.gravity = [0.0; 3];
    let c = object.centre_of_mass();
    // Half a turn per frame about z at the simulator's rate, from the rate it turns ω₀ at.
    let body = FreeRotation::of_simulated(
        &object.body.state.x,
        &object.body.material.mass,
        c,
        object.body.setup.dx,
    );
    let per = body.orientations(DVec3::Z, &[1.0], false)[0].omega.z;
    let omega = std::f64::consts::PI / object.spec.frame_dt / per;
    let rigid = RigidVelocity {
        linear: [0.0; 3],
        angular: [0.0, 0.0, omega],
        centre: c.to_array(),
    };
    let dx = object.body.setup.dx;
    let lowest = |x: &[DVec3]| x.iter().map(|x| x.y).fold(f64::MAX, f64::min);
    let reach = object
        .body
        .state
        .x
        .iter()
        .map(|x| (*x - c).length())
        .fold(0.0, f64::max);
    println!("dx {dx:.4} m, centre {:.3} m up, reach {reach:.3} m", c.y);
    assert!(c.y - reach < 1.5 * dx, "the swing reaches the ground");
    for frame in 0..=2 {
        let low = lowest(&positions(&object, &rigid, frame));
        println!("frame {frame}: lowest particle {low:.4} m");
        assert!(
            low > 2.0 * dx,
            "frame {frame} is clear of the ground: {low}"
        );
    }
    assert_eq!(frames_in_flight(&object, &rigid, 2), 0);
    // At rest the same bar is in free flight over both frames.
    let still = RigidVelocity {
        angular: [0.0; 3],
        ..rigid
    };
    assert_eq!(frames_in_flight(&object, &still, 2), 2);
}
