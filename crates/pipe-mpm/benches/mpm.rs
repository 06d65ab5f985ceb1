//! MPM throughput at the anchor workload (`../shared/anchors/README.md`): domain [0,1]³,
//! dx = 1/G, dt = 1e-4 s, E = 1e3 Pa, ν = 0.2, ρ = 1 kg/m³, gravity, the 3 outermost cells
//! stop outward motion; N particles uniform in a cube of side (N/8)^(1/3)·dx (8 per cell),
//! centred in x/z, raised in y, at rest. Counter = particles, so divan's items/s is
//! particle-substeps/s. Differences from the anchors: f64 unless `MPM_PRECISION=f32` (theirs
//! is f32), and the particle positions come from our own generator (same distribution, not
//! numpy's stream). The cube
//! placement is the anchors' exactly: side = min((N/8)^(1/3)·dx, 1 − 10·dx), lower corner
//! (0.5 − side/2, 0.5 − side/2 + 0.1·(1 − side), 0.5 − side/2); warm-up 10 substeps (Taichi's).
//!
//! `cargo bench -p pipe-mpm --bench mpm`
//!
//! Extra modes (run before divan, printing one JSON line each, then exit if set):
//! * `MPM_AD=1`: forward (checkpointed tape) and backward timed separately, 16 substeps,
//!   N = 20k, G = 32, nh and fcr, threads from `MPM_AD_THREADS` (default 1), median of
//!   `MPM_AD_REPS` (default 3) after one warm-up; `MPM_AD_N` changes N, `MPM_AD_CASE=nh|fcr`
//!   runs one model, `MPM_SNAPSHOTS` sets [`BackwardOptions::snapshots`]. Loss = mean final y,
//!   its gradient added in place ([`Simulator::backward_into`]).
//! * `MPM_ROLLOUT=run|tape|tape+bwd`: one differentiable rollout of `MPM_FRAMES` (14) frames of
//!   `MPM_SUBSTEPS_PER_FRAME` (50) substeps, N = 20k, G = 32, nh, checkpoint per frame; for
//!   peak-memory measurements (`run` = plain forward, no tape). Frames count as `pipe simulate
//!   --frames` counts them: 14 frames are the states 0..13, 13 frame intervals, and the tape
//!   keeps those 14 frame-boundary states (13 checkpoints and the last). Prints the peak RSS
//!   before and after, and both over `14 × state` (state = x, v, C, F in the run's precision);
//!   `MPM_SNAPSHOTS` sets [`BackwardOptions::snapshots`] (default
//!   [`pipe_mpm::adjoint::SEGMENT_SNAPSHOTS`]); the loss (mean y at every frame) is seeded in
//!   place ([`Simulator::backward_into`]).
//! * `MPM_SWEEP_THREADS` (default 2): threads of the `sweep_fcr` and `sweep_nh`
//!   particle-count sweeps.
//! * `MPM_PRECISION=f32`: every case in `f32` ([`Precision::F32`]); `MPM_STEPS`: substeps per
//!   timed call of the forward cases (default 10).
//! * The forward cases keep the state in the engine between timed calls (a
//!   [`pipe_mpm::Stepper`], as the anchors keep theirs in their fields and as `pipe simulate`
//!   runs its frames); `MPM_PER_RUN=1` times one [`Simulator::run`] per call instead, loading
//!   the state into the engine, sorting it and writing it back each time.

#[path = "anchor_cube.rs"]
mod anchor_cube;

use anchor_cube::anchor_cube;
use divan::Bencher;
use divan::counter::ItemsCount;
use glam::DVec3;
use pipe_mpm::{
    Aabb, BackwardOptions, Boundaries, BoundaryKind, Constitutive, FixedCorotated, Material,
    NeoHookean, Precision, SimConfig, Simulator, State, StateGrad,
};

fn main() {
    if std::env::var("MPM_AD").is_ok() {
        ad_split();
        return;
    }
    if let Ok(mode) = std::env::var("MPM_ROLLOUT") {
        rollout(&mode);
        return;
    }
    divan::main();
}

fn env_usize(k: &str, d: usize) -> usize {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Forward (checkpointed tape, `every` substeps per checkpoint) and backward, timed apart.
fn ad_case<M: Constitutive + Clone>(
    name: &str,
    model: M,
    steps: usize,
    every: usize,
    threads: usize,
) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let n = env_usize("MPM_AD_N", 20_000);
    let (sim, s0, mat) = scene(model, n, 32);
    let (mut plain, mut tf, mut tb) = (vec![], vec![], vec![]);
    let mut check = 0.0;
    for rep in 0..=env_usize("MPM_AD_REPS", 3) {
        pool.install(|| {
            let mut s = s0.clone();
            let t = std::time::Instant::now();
            sim.run(&mut s, &mat, 0.0, steps).unwrap();
            let t_plain = t.elapsed().as_secs_f64();
            let mut s = s0.clone();
            let t = std::time::Instant::now();
            let tape = sim.forward_tape(&mut s, &mat, 0.0, steps, every).unwrap();
            let t_f = t.elapsed().as_secs_f64();
            // loss = mean final y, its gradient added in place at the last substep (as the
            // Taichi anchor's `compute_loss.grad()` adds into `x.grad`)
            let d_mean_y = DVec3::new(0.0, 1.0 / n as f64, 0.0);
            let t = std::time::Instant::now();
            let gr = sim
                .backward_into(
                    &tape,
                    &mat,
                    |k, _, g| {
                        if k == steps {
                            (0..n).for_each(|p| g.add_x(p, d_mean_y));
                        }
                        Ok(())
                    },
                    BackwardOptions {
                        snapshots: env_usize("MPM_SNAPSHOTS", pipe_mpm::adjoint::SEGMENT_SNAPSHOTS),
                        ..BackwardOptions::default()
                    },
                )
                .unwrap();
            let t_b = t.elapsed().as_secs_f64();
            check = gr.state.v.iter().map(|g| g.y).sum::<f64>();
            if rep > 0 {
                plain.push(t_plain);
                tf.push(t_f);
                tb.push(t_b);
            }
        });
    }
    let (p, f, b) = (median(plain), median(tf), median(tb));
    println!(
        "{{\"case\":\"{name}\",\"N\":{n},\"G\":32,\"substeps\":{steps},\"every\":{every},\"threads\":{threads},\"fwd_plain_s\":{p:.4},\"fwd_tape_s\":{f:.4},\"bwd_s\":{b:.4},\"bwd_over_fwd_plain\":{:.3},\"bwd_over_fwd_tape\":{:.3},\"fwd_plus_bwd_over_fwd_plain\":{:.3},\"check_sum_dL_dv0y\":{check:.6e},\"check_expected\":{:.1e}}}",
        b / p,
        b / f,
        (f + b) / p,
        steps as f64 * 1e-4
    );
}

fn ad_split() {
    let threads = env_usize("MPM_AD_THREADS", 1);
    let steps = env_usize("MPM_AD_STEPS", 16);
    let every = env_usize("MPM_AD_EVERY", 4);
    let case = std::env::var("MPM_AD_CASE").unwrap_or_default();
    if case.is_empty() || case == "nh" {
        ad_case("nh", NeoHookean, steps, every, threads);
    }
    if case.is_empty() || case == "fcr" {
        ad_case("fcr", FixedCorotated, steps, every, threads);
    }
}

fn rss_kib() -> usize {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
        })
        .unwrap_or(0)
}

fn rollout(mode: &str) {
    let frames = env_usize("MPM_FRAMES", 14).max(2);
    let spf = env_usize("MPM_SUBSTEPS_PER_FRAME", 50);
    let substeps = (frames - 1) * spf;
    let n = 20_000;
    let (sim, mut s, mat) = scene(NeoHookean, n, 32);
    let bytes = if std::env::var("MPM_PRECISION").as_deref() == Ok("f32") {
        4
    } else {
        8
    };
    let state_bytes = n * (3 + 3 + 9 + 9) * bytes;
    let hwm0 = rss_kib();
    let t = std::time::Instant::now();
    let mut kept = 0;
    match mode {
        "run" => {
            sim.run(&mut s, &mat, 0.0, substeps).unwrap();
        }
        "tape" | "tape+bwd" => {
            let tape = sim.forward_tape(&mut s, &mat, 0.0, substeps, spf).unwrap();
            kept = tape.checkpoint_count() + 1;
            if mode == "tape+bwd" {
                // Loss: mean y at every frame, added in place (no gradient state per seed).
                let d_mean_y = DVec3::new(0.0, 1.0 / n as f64, 0.0);
                sim.backward_into(
                    &tape,
                    &mat,
                    |k, _, g| {
                        if k % spf == 0 && k > 0 {
                            (0..n).for_each(|p| g.add_x(p, d_mean_y));
                        }
                        Ok(())
                    },
                    BackwardOptions {
                        snapshots: env_usize("MPM_SNAPSHOTS", pipe_mpm::adjoint::SEGMENT_SNAPSHOTS),
                        ..Default::default()
                    },
                )
                .unwrap();
            }
            drop(tape);
        }
        m => panic!("MPM_ROLLOUT={m}: expected run, tape or tape+bwd"),
    }
    let hwm1 = rss_kib();
    let budget = (frames * state_bytes) as f64;
    println!(
        "{{\"mode\":\"{mode}\",\"N\":{n},\"frames\":{frames},\"substeps\":{substeps},\"states_kept\":{kept},\"state_bytes\":{state_bytes},\"vmhwm_before_kib\":{hwm0},\"vmhwm_after_kib\":{hwm1},\"peak_over_frames_x_state\":{:.3},\"rollout_over_frames_x_state\":{:.3},\"wall_s\":{:.4}}}",
        hwm1 as f64 * 1024.0 / budget,
        (hwm1 - hwm0) as f64 * 1024.0 / budget,
        t.elapsed().as_secs_f64()
    );
}

fn scene<M: Constitutive>(model: M, n: usize, g: usize) -> (Simulator<M>, State, Material) {
    let dx = 1.0 / g as f64;
    let (mut x, vol) = anchor_cube(n, g);
    if std::env::var("MPM_SORTED").is_ok() {
        let key = |p: &DVec3| {
            let c = (*p * g as f64).floor();
            (c.x as usize * (g + 1) + c.y as usize) * (g + 1) + c.z as usize
        };
        x.sort_by_key(key);
    }
    let mat = Material::from_e_nu(n, vol, 1.0, 1e3, 0.2).unwrap();
    let mut cfg = SimConfig::new(
        Aabb::new(DVec3::splat(3.0 * dx), DVec3::splat(1.0 - 3.0 * dx)),
        dx,
        1e-4,
    );
    cfg.boundaries = Boundaries {
        colliders: vec![],
        walls: Some(BoundaryKind::Separate),
    };
    if std::env::var("MPM_PRECISION").as_deref() == Ok("f32") {
        cfg.precision = Precision::F32;
    }
    (Simulator::new(model, cfg).unwrap(), State::at_rest(x), mat)
}

fn forward<M: Constitutive + Clone>(b: Bencher, model: M, n: usize, g: usize, threads: usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let (sim, mut s, mat) = scene(model, n, g);
    // 10 substeps per iteration (`MPM_STEPS` changes it: the anchors time 100 at 20k and 20 at
    // 100k in one go).
    let steps = env_usize("MPM_STEPS", 10);
    let dt = sim.config().dt;
    if std::env::var("MPM_PER_RUN").is_ok() {
        // One `Simulator::run` per iteration: loading, sorting and writing back count.
        pool.install(|| sim.run(&mut s, &mat, 0.0, 10).unwrap());
        b.counter(ItemsCount::new(n * steps)).bench_local(|| {
            pool.install(|| sim.run(&mut s, &mat, 0.0, steps).unwrap());
        });
        return;
    }
    // The state stays in the engine between iterations, as the anchors' fields stay on their
    // device between their timed loops (a `Stepper`, as `pipe simulate` runs its frames).
    let mut stepper = pool.install(|| sim.stepper(&mut s, &mat)).unwrap();
    let mut t = 0.0;
    pool.install(|| stepper.advance(t, dt, 10).unwrap());
    t += 10.0 * dt;
    b.counter(ItemsCount::new(n * steps)).bench_local(|| {
        pool.install(|| stepper.advance(t, dt, steps).unwrap());
        t += steps as f64 * dt;
    });
}

#[divan::bench(args = [1, 2], sample_count = 10, sample_size = 1)]
fn fcr_20k_g32(b: Bencher, threads: usize) {
    forward(b, FixedCorotated, 20_000, 32, threads);
}

#[divan::bench(args = [1, 2], sample_count = 10, sample_size = 1)]
fn nh_20k_g32(b: Bencher, threads: usize) {
    forward(b, NeoHookean, 20_000, 32, threads);
}

#[divan::bench(args = [1, 2], sample_count = 3, sample_size = 1)]
fn fcr_100k_g64(b: Bencher, threads: usize) {
    forward(b, FixedCorotated, 100_000, 64, threads);
}

#[divan::bench(args = [1, 2], sample_count = 3, sample_size = 1)]
fn nh_100k_g64(b: Bencher, threads: usize) {
    forward(b, NeoHookean, 100_000, 64, threads);
}

/// Particle-count sweep, fcr, 8 particles per cell; G scaled with the cube so the cube spans
/// the same ~42% of the domain as the 20k / G = 32 anchor case (G = round(2.4·(N/8)^(1/3))).
/// Threads from `MPM_SWEEP_THREADS` (default 2). Items = particle-substeps.
#[divan::bench(args = [10_000, 30_000, 100_000, 300_000, 1_000_000], sample_count = 3, sample_size = 1)]
fn sweep_fcr(b: Bencher, n: usize) {
    let g = (2.4 * (n as f64 / 8.0).cbrt()).round() as usize;
    forward(b, FixedCorotated, n, g, env_usize("MPM_SWEEP_THREADS", 2));
}

/// [`sweep_fcr`] for neo-Hookean.
#[divan::bench(args = [10_000, 30_000, 100_000, 300_000, 1_000_000], sample_count = 3, sample_size = 1)]
fn sweep_nh(b: Bencher, n: usize) {
    let g = (2.4 * (n as f64 / 8.0).cbrt()).round() as usize;
    forward(b, NeoHookean, n, g, env_usize("MPM_SWEEP_THREADS", 2));
}

/// Forward (with checkpoints) + backward over 8 substeps, fcr, N = 20k, G = 32; items = particle-substeps.
#[divan::bench(args = [1, 2], sample_count = 3, sample_size = 1)]
fn fcr_20k_g32_fwd_bwd_8(b: Bencher, threads: usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let (sim, s0, mat) = scene(FixedCorotated, 20_000, 32);
    let seed = StateGrad::zeros(s0.len());
    b.counter(ItemsCount::new(20_000usize * 8)).bench_local(|| {
        pool.install(|| {
            let mut s = s0.clone();
            let tape = sim.forward_tape(&mut s, &mat, 0.0, 8, 4).unwrap();
            let mut seed = seed.clone();
            seed.x.iter_mut().for_each(|g| *g = DVec3::ONE);
            sim.backward(
                &tape,
                &mat,
                |k, _| (k == 8).then(|| seed.clone()),
                BackwardOptions::default(),
            )
            .unwrap()
        })
    });
}
