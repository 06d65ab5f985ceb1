//! MPM throughput at the anchor workload (`/work/shared/anchors/README.md`): domain [0,1]³,
//! dx = 1/G, dt = 1e-4 s, E = 1e3 Pa, ν = 0.2, ρ = 1 kg/m³, gravity, the 3 outermost cells
//! stop outward motion; N particles uniform in a cube of side (N/8)^(1/3)·dx (8 per cell),
//! centred in x/z, raised in y, at rest. Counter = particles, so divan's items/s is
//! particle-substeps/s. Differences from the anchors: f64 instead of f32, and the particle
//! positions come from our own generator (same distribution, not numpy's stream).
//!
//! `CARGO_TARGET_DIR=/work/target-mpm cargo bench -p pipe-mpm --bench mpm`

use divan::Bencher;
use divan::counter::ItemsCount;
use glam::DVec3;
use pipe_mpm::{
    Aabb, BackwardOptions, Boundaries, BoundaryKind, Constitutive, FixedCorotated, Material,
    NeoHookean, SimConfig, Simulator, State, StateGrad,
};

fn main() {
    divan::main();
}

fn scene<M: Constitutive>(model: M, n: usize, g: usize) -> (Simulator<M>, State, Material) {
    let dx = 1.0 / g as f64;
    let side = (n as f64 / 8.0).cbrt() * dx;
    let mut seed = 0x2545F4914F6CDD1Du64;
    let mut r = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let lo = DVec3::new(0.5 - side / 2.0, 0.6 - side / 2.0, 0.5 - side / 2.0);
    let x = (0..n)
        .map(|_| lo + DVec3::new(r(), r(), r()) * side)
        .collect();
    let vol = dx * dx * dx / 8.0;
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
    (Simulator::new(model, cfg).unwrap(), State::at_rest(x), mat)
}

fn forward<M: Constitutive + Clone>(b: Bencher, model: M, n: usize, g: usize, threads: usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let (sim, mut s, mat) = scene(model, n, g);
    pool.install(|| sim.run(&mut s, &mat, 0.0, 5).unwrap());
    // 10 substeps per iteration so per-call buffer setup is amortised as in real runs.
    b.counter(ItemsCount::new(n * 10)).bench_local(|| {
        pool.install(|| sim.run(&mut s, &mat, 0.0, 10).unwrap());
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
