//! CLI-level MPM benchmark at the anchor workloads (`../shared/anchors/README.md`, relative to
//! the repository): the
//! `pipe simulate` command on the anchors' cube (domain [0,1]³, dx = 1/G, dt = 1e-4 s, E = 1e3
//! Pa, ν = 0.2, ρ = 1 kg/m³, gravity, 8 particles per cell in a cube placed as the anchors
//! place it, uniform random positions in random order, at rest), for fixed corotated
//! (`elastic_fcr`) and neo-Hookean (`elastic`) at 20k particles / G = 32 and 100k / G = 64,
//! with 1 and 2 threads. Each run writes its inputs (a PLY and a simulation file) to a
//! temporary directory, runs the `pipe` binary on them and reports the whole command's time per
//! substep from its `summary.json` (reading, setup, the frame PLYs and `particles.arrow`
//! included), one JSON line per case and thread count.
//!
//! `cargo bench -p pipe --bench simulate_anchor`
//!
//! * Ours is the median of `PIPE_BENCH_REPEATS` runs (default 3, as the anchors' medians of
//!   3 repeats), every run's time listed too; `substeps_only_ms_per_substep` is the median of
//!   the substeps' own time (`summary.json`'s `timing_s.substeps`, without the setup and the
//!   output), the part the anchors' timed loops correspond to.
//! * `PIPE_BENCH_CASES=fcr_20k,nh_100k` runs some cases; `PIPE_BENCH_THREADS=2` some thread
//!   counts; `PIPE_BENCH_PRECISION=f64` runs `pipe simulate --precision f64` (default `f32`,
//!   the anchors' precision).
//! * `ANCHORS_PY=$ANCHORS_VENV/bin/python` (a Python with taichi and warp-lang, set up as the
//!   anchors' README says; with `ANCHORS_DIR`, default `../shared/anchors` relative to the
//!   repository) also runs the anchors' Taichi script on the same workload right
//!   after each of ours (same thread count), and Warp's after our 1-thread run, through the
//!   anchors' `bench_runner.py`, printing their JSON lines: the side-by-side comparison in one
//!   run.

use std::path::Path;
use std::process::Command;

#[path = "../crates/pipe-mpm/benches/anchor_cube.rs"]
mod anchor_cube;

use anchor_cube::anchor_cube;
use pipe::io::ply::write_points;

/// One workload: material family, particle count, grid size, frames × substeps per frame, and
/// the anchor scripts' `--steps` for the same workload (Taichi, Warp).
struct Case {
    name: &'static str,
    family: &'static str,
    taichi_material: &'static str,
    n: usize,
    g: usize,
    frames: u32,
    substeps_per_frame: u32,
    taichi_steps: u32,
    warp_steps: u32,
}

const CASES: [Case; 4] = [
    Case {
        name: "fcr_20k",
        family: "elastic_fcr",
        taichi_material: "fcr",
        n: 20_000,
        g: 32,
        frames: 11,
        substeps_per_frame: 50,
        taichi_steps: 100,
        warp_steps: 50,
    },
    Case {
        name: "nh_20k",
        family: "elastic",
        taichi_material: "nh",
        n: 20_000,
        g: 32,
        frames: 11,
        substeps_per_frame: 50,
        taichi_steps: 100,
        warp_steps: 50,
    },
    Case {
        name: "fcr_100k",
        family: "elastic_fcr",
        taichi_material: "fcr",
        n: 100_000,
        g: 64,
        frames: 11,
        substeps_per_frame: 20,
        taichi_steps: 20,
        warp_steps: 10,
    },
    Case {
        name: "nh_100k",
        family: "elastic",
        taichi_material: "nh",
        n: 100_000,
        g: 64,
        frames: 11,
        substeps_per_frame: 20,
        taichi_steps: 20,
        warp_steps: 10,
    },
];

/// Substep (s) of the anchors.
const DT: f64 = 1e-4;

fn main() {
    let cases = std::env::var("PIPE_BENCH_CASES").ok();
    let threads: Vec<usize> = std::env::var("PIPE_BENCH_THREADS")
        .ok()
        .map(|t| t.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![1, 2]);
    let anchors_py = std::env::var("ANCHORS_PY").ok();
    let anchors_dir = std::env::var("ANCHORS_DIR")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/anchors").into());
    for case in &CASES {
        if cases
            .as_deref()
            .is_some_and(|c| !c.split(',').any(|n| n.trim() == case.name))
        {
            continue;
        }
        let dir = tempfile::tempdir().expect("temporary directory");
        write_inputs(case, dir.path());
        for &t in &threads {
            run_ours(case, dir.path(), t);
            if let Some(py) = &anchors_py {
                let steps = case.taichi_steps.to_string();
                let threads = t.to_string();
                run_anchor(
                    case,
                    py,
                    &anchors_dir,
                    "mpm_taichi.py",
                    &steps,
                    Some(&threads),
                );
                // Warp's CPU backend is single-threaded: once, next to our 1-thread run.
                if t == 1 {
                    let steps = case.warp_steps.to_string();
                    run_anchor(case, py, &anchors_dir, "mpm_warp.py", &steps, None);
                }
            }
        }
    }
}

/// The anchors' cube (`particles.ply`) and the simulation file (`sim.yaml`) in `dir`.
fn write_inputs(case: &Case, dir: &Path) {
    let dx = 1.0 / case.g as f64;
    let (x, volume) = anchor_cube(case.n, case.g);
    let positions: Vec<[f32; 3]> = x.iter().map(|p| p.as_vec3().to_array()).collect();
    write_points(&dir.join("particles.ply"), &positions, None).expect("particles.ply");
    let sim = format!(
        "material:\n  family: {family}\n  youngs_modulus: 1.0e3\n  poisson_ratio: 0.2\n  \
         density: 1.0\ninitial_velocity: [0, 0, 0]\nparticle_volume: {volume:e}\n\
         gravity: [0, -9.8, 0]\nframe_dt: {frame_dt:e}\nsubsteps: {substeps}\n\
         grid_dx: {dx:e}\ndomain: {{min: [0, 0, 0], max: [1, 1, 1]}}\n",
        family = case.family,
        frame_dt = DT * f64::from(case.substeps_per_frame),
        substeps = case.substeps_per_frame,
    );
    std::fs::write(dir.join("sim.yaml"), sim).expect("sim.yaml");
}

/// The precision of our runs (`PIPE_BENCH_PRECISION`, default `f32`).
fn precision() -> String {
    std::env::var("PIPE_BENCH_PRECISION").unwrap_or_else(|_| "f32".into())
}

/// Times of our runs per case and thread count (`PIPE_BENCH_REPEATS`, default 3, as the
/// anchors' `--repeats 3`).
fn repeats() -> usize {
    std::env::var("PIPE_BENCH_REPEATS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&r| r > 0)
        .unwrap_or(3)
}

/// One run's times (s): the whole command's and its substeps' alone (from its
/// `summary.json`), and the process's wall time.
struct Times {
    wall: f64,
    substeps: f64,
    process: f64,
}

/// One `pipe --threads t simulate` run: its times, substeps and output particle count.
fn run_once(case: &Case, dir: &Path, threads: usize) -> (Times, u64, serde_json::Value) {
    let out = dir.join(format!("out-{threads}"));
    // Every run writes into an empty folder: replacing the last run's files would add the
    // file system's unlinking of them (~20 ms for a 100k run's 32 MB particles.arrow).
    if out.exists() {
        std::fs::remove_dir_all(&out).expect("remove the last run's output");
    }
    let started = std::time::Instant::now();
    let status = Command::new(env!("CARGO_BIN_EXE_pipe"))
        .arg("--threads")
        .arg(threads.to_string())
        .arg("simulate")
        .arg(dir.join("particles.ply"))
        .arg("--material")
        .arg(dir.join("sim.yaml"))
        .arg("--frames")
        .arg(case.frames.to_string())
        .arg("--out")
        .arg(&out)
        .arg("--precision")
        .arg(precision())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .expect("run pipe");
    let process_s = started.elapsed().as_secs_f64();
    assert!(status.success(), "pipe simulate failed for {}", case.name);
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).expect("summary.json"))
            .expect("summary.json is JSON");
    let times = Times {
        wall: summary["wall_time_s"].as_f64().expect("wall_time_s"),
        substeps: summary["timing_s"]["substeps"]
            .as_f64()
            .expect("timing_s.substeps"),
        process: process_s,
    };
    let substeps = summary["substeps_total"].as_u64().expect("substeps_total");
    (times, substeps, summary["particles_out"].clone())
}

/// Runs `pipe --threads t simulate` [`repeats`] times and prints the median time per substep
/// of the whole command and of its substeps alone (and every run's).
fn run_ours(case: &Case, dir: &Path, threads: usize) {
    let mut runs: Vec<(Times, u64, serde_json::Value)> = (0..repeats())
        .map(|_| run_once(case, dir, threads))
        .collect();
    let per_substep = |r: &(Times, u64, serde_json::Value), t: f64| t * 1e3 / r.1 as f64;
    let list = |v: Vec<f64>| {
        v.iter()
            .map(|x| format!("{x:.4}"))
            .collect::<Vec<_>>()
            .join(",")
    };
    let all_ms = list(runs.iter().map(|r| per_substep(r, r.0.wall)).collect());
    let mut kernel_ms: Vec<f64> = runs.iter().map(|r| per_substep(r, r.0.substeps)).collect();
    let all_kernel_ms = list(kernel_ms.clone());
    kernel_ms.sort_by(f64::total_cmp);
    let kernel_median = kernel_ms[kernel_ms.len() / 2];
    runs.sort_by(|a, b| a.0.wall.total_cmp(&b.0.wall));
    let (times, substeps, particles_out) = runs.swap_remove(runs.len() / 2);
    let per_substep_ms = times.wall * 1e3 / substeps as f64;
    println!(
        "{{\"who\":\"pipe simulate\",\"case\":\"{}\",\"N\":{},\"G\":{},\"threads\":{threads},\
         \"precision\":\"{}\",\"substeps\":{substeps},\"wall_s\":{:.4},\"process_s\":{:.4},\
         \"ms_per_substep\":{per_substep_ms:.4},\"runs_ms_per_substep\":[{all_ms}],\
         \"substeps_only_ms_per_substep\":{kernel_median:.4},\"runs_substeps_only_ms\":[{all_kernel_ms}],\
         \"Mpart_substeps_per_s\":{:.3},\"particles_out\":{particles_out}}}",
        case.name,
        case.n,
        case.g,
        precision(),
        times.wall,
        times.process,
        case.n as f64 / per_substep_ms / 1e3,
    );
}

/// Runs one of the anchors' scripts (through `bench_runner.py`, which waits for an idle machine)
/// on the same workload and prints its JSON line.
fn run_anchor(
    case: &Case,
    py: &str,
    anchors_dir: &str,
    script: &str,
    steps: &str,
    threads: Option<&str>,
) {
    let mut cmd = Command::new(py);
    cmd.current_dir(anchors_dir)
        .args(["bench_runner.py", "/dev/null", "--", py, script])
        .args(["--material", case.taichi_material])
        .args(["--n", &case.n.to_string()])
        .args(["--grid", &case.g.to_string()])
        .args(["--steps", steps])
        .args(["--repeats", "3"]);
    if let Some(t) = threads {
        cmd.args(["--threads", t]);
    }
    let out = cmd.output().expect("run an anchor script");
    let text = String::from_utf8_lossy(&out.stdout);
    match text.lines().rev().find(|l| l.trim_start().starts_with('{')) {
        Some(line) => println!("{}", line.trim()),
        None => println!(
            "{{\"who\":\"{script}\",\"case\":\"{}\",\"error\":{:?}}}",
            case.name,
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
    }
}
