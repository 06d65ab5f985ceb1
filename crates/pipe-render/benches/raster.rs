//! Forward and forward+backward timings on the anchor workload (`../shared/anchors`
//! README): camera at the origin looking down +z, hfov 50°, square image, means uniform in
//! [-1.6,1.6]²×[3,5], log-uniform scales in [0.005, 0.03], random unit quaternions, opacity
//! U(0.1, 0.9), RGB colours, black background; the loss weights of the backward are fixed
//! pseudo-random numbers in [-1, 1]. Run with
//! `cargo bench -p pipe-render --bench raster`;
//! set `RASTER_PHASES=all` (or e.g. `=100000:800`) to also print the per-phase split of one run per configuration.

#[path = "../tests/common/mod.rs"]
mod common;

use common::{Rng, Scene, anchor_scene, simple_camera};
use divan::Bencher;
use pipe_render::{Camera, RenderOptions, backward, render};

const CONFIGS: [(usize, u32); 4] = [(10_000, 256), (10_000, 800), (100_000, 256), (100_000, 800)];

struct Setup {
    scene: Scene<f32>,
    cam: Camera<f32>,
    d_image: Vec<[f32; 3]>,
}

fn setup(n: usize, res: u32) -> Setup {
    let cam = simple_camera::<f32>(res, res, 50.0);
    let mut rng = Rng(42);
    let d_image = (0..cam.n_pixels())
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0) as f32))
        .collect();
    Setup {
        scene: anchor_scene(n, 2026, 0),
        cam,
        d_image,
    }
}

#[divan::bench(args = CONFIGS, sample_count = 5, sample_size = 1)]
fn forward(b: Bencher, (n, res): (usize, u32)) {
    let s = setup(n, res);
    let opts = RenderOptions::default();
    b.bench_local(|| render(&s.scene.gaussians_rgb(), &s.cam, &opts).unwrap());
}

#[divan::bench(args = CONFIGS, sample_count = 5, sample_size = 1)]
fn forward_backward(b: Bencher, (n, res): (usize, u32)) {
    let s = setup(n, res);
    let opts = RenderOptions::default();
    b.bench_local(|| {
        let g = s.scene.gaussians_rgb();
        let out = render(&g, &s.cam, &opts).unwrap();
        backward(&g, &s.cam, &opts, &out, &s.d_image, None).unwrap()
    });
}

/// Process CPU time (all threads, ns resolution) in ms: the sum of the on-CPU times in
/// `/proc/self/task/*/schedstat` (threads that exited are not counted, so keep the rayon pool
/// alive), NaN where unavailable. Unlike wall time it does not count waiting for a CPU while
/// other processes share the machine.
fn cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return f64::NAN;
    };
    let mut ns = 0u64;
    for t in tasks.flatten() {
        let Ok(s) = std::fs::read_to_string(t.path().join("schedstat")) else {
            return f64::NAN;
        };
        ns += s
            .split_whitespace()
            .next()
            .and_then(|x| x.parse().ok())
            .unwrap_or(0);
    }
    ns as f64 * 1e-6
}

fn main() {
    if let Ok(which) = std::env::var("RASTER_PHASES") {
        let opts = RenderOptions::default();
        println!(
            "phase split (ms), per phase min of RASTER_RUNS (5) runs: N res | project sort blend | bwd: blend reduce project | isects max/tile | CPU ms (all threads, min over runs): fwd bwd fwd+bwd"
        );
        for (n, res) in CONFIGS {
            if which != "all" && which != format!("{n}:{res}") {
                continue;
            }
            let s = setup(n, res);
            let g = s.scene.gaussians_rgb();
            let mut runs: Vec<[f64; 6]> = Vec::new();
            let mut isects = (0, 0);
            let mut cpu = [f64::INFINITY; 3];
            let runs_n: usize = std::env::var("RASTER_RUNS")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(5);
            for _ in 0..runs_n {
                let c0 = cpu_ms();
                let out = render(&g, &s.cam, &opts).unwrap();
                let c1 = cpu_ms();
                let gr = backward(&g, &s.cam, &opts, &out, &s.d_image, None).unwrap();
                let c2 = cpu_ms();
                let (f, bw) = (out.timings, gr.timings);
                let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
                runs.push([
                    ms(f.project),
                    ms(f.sort),
                    ms(f.blend),
                    ms(bw.blend),
                    ms(bw.reduce),
                    ms(bw.project),
                ]);
                isects = (out.bins.n_intersections(), out.bins.max_per_tile());
                drop((out, gr));
                for (m, d) in cpu.iter_mut().zip([c1 - c0, c2 - c1, c2 - c0]) {
                    *m = m.min(d);
                }
            }
            let r: [f64; 6] =
                std::array::from_fn(|k| runs.iter().map(|x| x[k]).fold(f64::INFINITY, f64::min));
            println!(
                "{n:>6} {res:>4} | {:7.1} {:7.1} {:7.1} | {:7.1} {:7.1} {:7.1} | {} {} | {:.0} {:.0} {:.0}",
                r[0], r[1], r[2], r[3], r[4], r[5], isects.0, isects.1, cpu[0], cpu[1], cpu[2]
            );
        }
    }
    divan::main();
}
