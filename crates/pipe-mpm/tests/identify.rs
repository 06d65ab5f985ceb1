//! What the adjoint is for: recovering a material and an initial velocity from observed
//! particle trajectories by gradient descent, as the `velocity` and `material` stages will do
//! through the renderer. The loss is the squared distance to the observed positions at every
//! frame boundary (checkpoints at frame boundaries, seeds added in place); gradient descent
//! with a line search steps `ln E` and `v0`.
//!
//! The fast test recovers E and v0 of a block that hits a slip ground from a start 3× off in
//! E and 0.3 m/s off in v0. The ignored one recovers PAC-NeRF's torus (E = 1e6 Pa, from 1e5)
//! from the dataset's own ground-truth trajectories, simulated by PAC-NeRF's simulator:
//! `cargo test -p pipe-mpm --release --test identify -- --ignored --nocapture` (~2 min).

use glam::DVec3;
use pipe_mpm::{
    Aabb, BackwardOptions, Boundaries, BoundaryKind, Collider, Material, NeoHookean, SimConfig,
    Simulator, State,
};

/// A scene to identify: initial positions, the material for a given E, and the simulator.
struct Scene {
    sim: Simulator<NeoHookean>,
    x0: Vec<DVec3>,
    volume: f64,
    density: f64,
    nu: f64,
    frames: usize,
    substeps_per_frame: usize,
}

impl Scene {
    fn material(&self, e: f64) -> Material {
        Material::from_e_nu(self.x0.len(), self.volume, self.density, e, self.nu).unwrap()
    }

    /// `(frame, positions)` at every frame boundary `1..=frames`.
    fn observe(&self, e: f64, v0: DVec3) -> Vec<(usize, Vec<DVec3>)> {
        let mat = self.material(e);
        let mut s = State::at_rest(self.x0.clone());
        s.v.iter_mut().for_each(|v| *v = v0);
        (0..self.frames)
            .map(|f| {
                let t0 = (f * self.substeps_per_frame) as f64 * self.sim.config().dt;
                self.sim
                    .run(&mut s, &mat, t0, self.substeps_per_frame)
                    .unwrap();
                (f + 1, s.x.clone())
            })
            .collect()
    }

    /// Loss `Σ_frames Σ_p |x_p − x̂_p|²` (m²) over the observed frames `seen` and its
    /// gradient w.r.t. `(ln E, v0)`.
    fn loss_and_grad(&self, e: f64, v0: DVec3, seen: &[(usize, Vec<DVec3>)]) -> (f64, [f64; 4]) {
        let frames = seen.iter().map(|(f, _)| *f).max().unwrap_or(0);
        let mat = self.material(e);
        let mut s = State::at_rest(self.x0.clone());
        s.v.iter_mut().for_each(|v| *v = v0);
        let spf = self.substeps_per_frame;
        let tape = self
            .sim
            .forward_tape(&mut s, &mat, 0.0, frames * spf, spf)
            .unwrap();
        let mut loss = 0.0;
        let g = self
            .sim
            .backward_into(
                &tape,
                &mat,
                |k, state, g| {
                    let Some((_, obs)) = seen.iter().find(|(f, _)| f * spf == k) else {
                        return Ok(());
                    };
                    let x = &state.get().x;
                    for (p, (xp, seen)) in x.iter().zip(obs).enumerate() {
                        let d = *xp - *seen;
                        loss += d.length_squared();
                        g.add_x(p, 2.0 * d);
                    }
                    Ok(())
                },
                BackwardOptions::default(),
            )
            .unwrap();
        let (d_e, _) = g.material.e_nu(e, self.nu);
        let d_v0 = g.state.v.iter().fold(DVec3::ZERO, |a, &b| a + b);
        (loss, [d_e * e, d_v0.x, d_v0.y, d_v0.z])
    }

    /// Gradient descent with a backtracking line search (Armijo) on the parameters of
    /// `(ln E, v0)` that `learn` selects, against the observed frames `seen`, until the loss
    /// stops shrinking (at most `iters` steps); returns `(E, v0, loss)`.
    fn identify(
        &self,
        (e, v0): (f64, DVec3),
        seen: &[(usize, Vec<DVec3>)],
        learn: [bool; 4],
        iters: usize,
    ) -> (f64, DVec3, f64) {
        let eval = |x: &[f64; 4]| {
            let (l, g) = self.loss_and_grad(x[0].exp(), DVec3::new(x[1], x[2], x[3]), seen);
            assert!(l.is_finite() && g.iter().all(|v| v.is_finite()));
            (
                l,
                std::array::from_fn::<f64, 4, _>(|i| if learn[i] { g[i] } else { 0.0 }),
            )
        };
        let mut x = [e.ln(), v0.x, v0.y, v0.z];
        let (mut loss, mut g) = eval(&x);
        let mut step = 1e-3;
        for it in 0..iters {
            println!(
                "iter {it:2}: loss {loss:.4e} m^2, E {:.4e} Pa, v0 [{:.4}, {:.4}, {:.4}] m/s",
                x[0].exp(),
                x[1],
                x[2],
                x[3]
            );
            let g2: f64 = g.iter().map(|v| v * v).sum();
            let mut accepted = false;
            for _ in 0..40 {
                let trial: [f64; 4] = std::array::from_fn(|i| x[i] - step * g[i]);
                let (l, gt) = eval(&trial);
                if l <= loss - 1e-4 * step * g2 {
                    (x, loss, g) = (trial, l, gt);
                    step *= 2.0;
                    accepted = true;
                    break;
                }
                step *= 0.5;
            }
            if !accepted || loss < 1e-12 {
                break;
            }
        }
        (x[0].exp(), DVec3::new(x[1], x[2], x[3]), loss)
    }
}

/// A 6×6×6 block (dx = 5 cm, 8 particles per cell) thrown sideways onto a slip ground: E sets
/// how it compresses and rebounds on impact, v0 where it flies.
fn block() -> Scene {
    let dx = 0.05;
    let x0: Vec<DVec3> = (0..216)
        .map(|i| {
            let (a, b, c) = (i / 36, (i / 6) % 6, i % 6);
            DVec3::new(0.3, 0.12, 0.4) + DVec3::new(a as f64, b as f64, c as f64) * (dx / 2.0)
        })
        .collect();
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, 1.0 / 24.0 / 40.0);
    cfg.boundaries = Boundaries {
        colliders: vec![Collider::ground(0.05, BoundaryKind::Slip)],
        walls: Some(BoundaryKind::Separate),
    };
    Scene {
        sim: Simulator::new(NeoHookean, cfg).unwrap(),
        x0,
        volume: (dx / 2.0f64).powi(3),
        density: 1000.0,
        nu: 0.3,
        frames: 6,
        substeps_per_frame: 40,
    }
}

/// As the pipeline will: the initial velocity from the frames before contact (where the
/// material does not act), then E from all frames with that velocity.
#[test]
fn initial_velocity_then_young_modulus_from_trajectories() {
    let scene = block();
    let (e_true, v_true) = (3.0e4, DVec3::new(0.6, 0.4, -0.2));
    let seen = scene.observe(e_true, v_true);
    let e0 = 1.0e4;
    let (_, v0, loss) = scene.identify(
        (e0, DVec3::new(0.3, 0.2, 0.0)),
        &seen[..2],
        [false, true, true, true],
        30,
    );
    println!("v0 {v0} (true {v_true}), loss {loss:.3e} m^2");
    assert!((v0 - v_true).length() < 2e-3, "v0 {v0} vs {v_true}");
    let (e, _, loss) = scene.identify((e0, v0), &seen, [true, false, false, false], 30);
    println!("E {e:.4e} Pa (true {e_true:e}), loss {loss:.3e} m^2");
    assert!((e / e_true - 1.0).abs() < 0.02, "E {e} vs {e_true}");
}

/// PAC-NeRF's torus from its own simulator's trajectories (`tests/fixtures/trajectories`, 14 137
/// particles, 200 substeps per frame, sticky ground): v0 from frame 4 (before the bounce), then
/// E from frames 4 and 7 (across it), starting 10× low.
#[test]
#[ignore = "about 3 minutes: ~20 forward + backward passes of 1 400 substeps"]
fn pacnerf_torus_from_its_ground_truth_trajectories() {
    let dir = format!(
        "{}/tests/fixtures/trajectories/torus-elastic",
        env!("CARGO_MANIFEST_DIR")
    );
    let p: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(format!("{dir}/params.json")).unwrap())
            .unwrap();
    let f = |k: &str| p[k].as_f64().unwrap();
    let v3 = |v: &serde_json::Value| {
        DVec3::new(
            v[0].as_f64().unwrap(),
            v[1].as_f64().unwrap(),
            v[2].as_f64().unwrap(),
        )
    };
    let dom = &p["domain"];
    let mut cfg = SimConfig::new(
        Aabb::new(v3(&dom["xyz_min"]), v3(&dom["xyz_max"])),
        f("dx"),
        f("dt"),
    );
    cfg.boundaries = Boundaries {
        colliders: vec![Collider::ground(0.0, BoundaryKind::Sticky)],
        walls: None,
    };
    let scene = Scene {
        sim: Simulator::new(NeoHookean, cfg).unwrap(),
        x0: read_ply(&format!("{dir}/0.ply")),
        volume: f("p_vol"),
        density: f("rho"),
        nu: f("nu"),
        frames: 7,
        substeps_per_frame: p["substeps"].as_u64().unwrap() as usize,
    };
    let seen: Vec<(usize, Vec<DVec3>)> = [4, 7]
        .into_iter()
        .map(|fr| (fr, read_ply(&format!("{dir}/{fr}.ply"))))
        .collect();
    let (e_true, v_true) = (f("E"), v3(&p["v0"]));
    let (_, v0, _) = scene.identify((1e5, DVec3::ZERO), &seen[..1], [false, true, true, true], 8);
    println!("v0 {v0} (true {v_true})");
    assert!((v0 - v_true).length() < 5e-3, "v0 {v0} vs {v_true}");
    let (e, _, loss) = scene.identify((1e5, v0), &seen, [true, false, false, false], 10);
    println!("E {e:.4e} Pa (true {e_true:e}), loss {loss:.3e} m^2");
    assert!((e / e_true - 1.0).abs() < 0.05, "E {e} vs {e_true}");
}

/// Binary little-endian PLY with exactly `float x, y, z` per vertex.
fn read_ply(path: &str) -> Vec<DVec3> {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let pos = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..pos]).unwrap();
    let n: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let data = &bytes[pos..];
    let f = |i: usize| {
        f64::from(f32::from_le_bytes(
            data[4 * i..4 * i + 4].try_into().unwrap(),
        ))
    };
    (0..n)
        .map(|p| DVec3::new(f(3 * p), f(3 * p + 1), f(3 * p + 2)))
        .collect()
}
