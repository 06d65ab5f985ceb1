//! `pipe simulate` (library side, `pipe::simulate::run`): a particle PLY and a `SIM.yaml` in,
//! one PLY per frame, `particles.arrow` and `summary.json` out.
//!
//! Why these tests: the command is where users meet the simulator directly, so it must (1) take
//! the documented `SIM.yaml` verbatim and produce exactly the promised files, (2) reproduce
//! PAC-NeRF's own trajectories when given a PAC-NeRF scene's parameters (checked against the
//! dataset ground truth in `crates/pipe-mpm/tests/fixtures/trajectories`, reused, not copied),
//! (3) choose sane defaults (spacing, dx, particle volume, domain, substeps) and say why in the
//! summary, and (4) refuse bad files with messages naming the file, key, line:column and value.
//!
//! The full 14-frame torus check takes about 30 s in a debug build and is ignored; run it with
//! `cargo test -p pipe --test cli simulate::torus -- --ignored --nocapture`.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use glam::DVec3;
use pipe::io::ply;
use pipe::pipeline::progress::{Mode, Progress, Reporter};
use pipe::scene::neighbors::mean_chamfer;
use pipe::scene::table;
use pipe::simulate::{self, SimulateError, Summary, Trajectories};

const FRAME_DT: f64 = 0.041666666666666664;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/simulate")
        .join(name)
}

fn pacnerf(scene: &str, file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("crates/pipe-mpm/tests/fixtures/trajectories")
        .join(scene)
        .join(file)
}

fn quiet() -> Reporter {
    Reporter::new(Mode::Quiet)
}

/// Records log lines (warnings).
#[derive(Default)]
struct Log(Mutex<Vec<String>>);

impl Progress for Log {
    fn start(&self, _: &str, _: u64) {}
    fn inc(&self, _: u64) {}
    fn message(&self, _: &str) {}
    fn log(&self, line: &str) {
        self.0.lock().unwrap().push(line.to_string());
    }
}

/// A `k × k × k` block of particles `spacing` apart with its lowest corner at `lo`.
fn lattice(k: usize, spacing: f32, lo: [f32; 3]) -> Vec<[f32; 3]> {
    let mut out = Vec::with_capacity(k * k * k);
    for i in 0..k {
        for j in 0..k {
            for l in 0..k {
                out.push([
                    lo[0] + i as f32 * spacing,
                    lo[1] + j as f32 * spacing,
                    lo[2] + l as f32 * spacing,
                ]);
            }
        }
    }
    out
}

fn write_ply(dir: &Path, name: &str, pts: &[[f32; 3]]) -> PathBuf {
    let p = dir.join(name);
    ply::write_points(&p, pts, None).unwrap();
    p
}

fn write_sim(dir: &Path, text: &str) -> PathBuf {
    let p = dir.join("sim.yaml");
    std::fs::write(&p, text).unwrap();
    p
}

fn read(path: &Path) -> Vec<DVec3> {
    ply::read_points(path)
        .unwrap()
        .positions
        .iter()
        .map(|p| DVec3::new(p[0].into(), p[1].into(), p[2].into()))
        .collect()
}

fn centroid(x: &[DVec3]) -> DVec3 {
    x.iter().copied().sum::<DVec3>() / x.len() as f64
}

/// The names in folder `dir`, sorted.
fn names_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    names
}

/// The documented SIM.yaml, verbatim, on a 10³ lattice 1 cm apart (8 particles per 2 cm cell,
/// as the file's `particle_volume` and `grid_dx` assume), 10 cm above the ground.
#[test]
fn example_sim_yaml_on_a_lattice() {
    let tmp = tempfile::tempdir().unwrap();
    let input = lattice(10, 0.01, [0.0, 0.1, 0.0]);
    let ply_in = write_ply(tmp.path(), "block.ply", &input);
    let out = tmp.path().join("out");
    let s = simulate::run(&ply_in, &fixture("example.sim.yaml"), 14, &out, &quiet()).unwrap();

    // Files: frame_0000 … frame_0013, the table, the summary; nothing else, no temporaries.
    let names = names_in(&out);
    let mut expected: Vec<String> = (0..14).map(|k| format!("frame_{k:04}.ply")).collect();
    expected.extend(["particles.arrow".into(), "summary.json".into()]);
    assert_eq!(names, expected);

    // Frame 0 is the input, bit for bit; every frame keeps every particle.
    assert_eq!(
        ply::read_points(&out.join("frame_0000.ply"))
            .unwrap()
            .positions,
        input
    );
    let frames: Vec<Vec<DVec3>> = (0..14)
        .map(|k| read(&out.join(format!("frame_{k:04}.ply"))))
        .collect();
    assert!(frames.iter().all(|f| f.len() == 1000));

    // Frame 1 is free flight: the centroid moves by v0 t + g t²/2.
    let t = FRAME_DT;
    let want = DVec3::new(0.5 * t, -0.5 * 9.8 * t * t, -0.3 * t);
    let got = centroid(&frames[1]) - centroid(&frames[0]);
    assert!((got - want).length() < 2e-4, "{got} vs {want}");
    // The block lands on the sticky ground and stays above it.
    let lowest = frames[13].iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
    assert!(
        lowest > -0.02 && lowest < 0.03,
        "lowest particle at y = {lowest}"
    );

    // The summary, as returned and as written.
    let on_disk: Summary =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(on_disk, s);
    assert_eq!(
        (s.particles_in, s.particles_out, s.frames),
        (1000, 1000, 14)
    );
    assert_eq!((s.dx_m, s.dx_source.as_str()), (0.02, "file"));
    assert_eq!(s.particle_volume_m3, 1e-6);
    assert!((s.particle_mass_kg - 1e-3).abs() < 1e-15 && (s.total_mass_kg - 1.0).abs() < 1e-9);
    // The spacing is measured only to tell a volume from a surface (`fill_interior` unset).
    assert!((s.spacing_m.unwrap() - 0.01).abs() < 1e-6);
    assert_eq!(
        (s.fill.as_str(), s.fill_particles),
        ("no: the cloud is volumetric", 0)
    );
    assert_eq!(s.frame_stats.len(), 13);
    for f in &s.frame_stats {
        assert_eq!(f.substeps_reason, "elastic wave (CFL)");
        assert!(!f.unstable && f.dt_s <= f.stable_dt_s, "{f:?}");
        assert!(
            f.cfl_number <= 0.3 + 1e-12 && f.stable_dt_s < f.max_fixed_dt_s,
            "{f:?}"
        );
        assert!(
            (f.dt_s * f.substeps as f64 - FRAME_DT).abs() < 1e-12,
            "{f:?}"
        );
        // c = sqrt((λ + 2μ)/ρ) ≈ 20.1 m/s → dt ≈ 0.3 · 0.02 / 20.7 s → about 140 per frame.
        assert!((120..200).contains(&f.substeps), "{f:?}");
    }
    assert_eq!(
        s.substeps_total,
        s.frame_stats.iter().map(|f| f.substeps).sum::<usize>()
    );
    // Without `domain:` the grid follows the block: no walls, nothing held, and each frame's
    // particles lie inside the grid its substeps stored.
    assert_eq!(s.held_total, 0);
    assert!(
        s.domain.is_none() && s.grid_nodes.is_none(),
        "{:?}",
        s.domain
    );
    assert!(s.domain_source.starts_with("none: the grid follows"));
    assert_eq!(s.boundaries.len(), 1);
    assert!(s.boundaries[0].contains("sticky"));
    for (f, stats) in s.frame_stats.iter().enumerate() {
        let g = stats.grid.expect("every frame reports its grid");
        let (lo, hi) = (DVec3::from_array(g.min), DVec3::from_array(g.max));
        assert!(
            frames[f + 1]
                .iter()
                .all(|p| p.cmpge(lo).all() && p.cmple(hi).all()),
            "frame {}: particles outside {g:?}",
            f + 1
        );
        // The grid is the block's reach, not a box around the whole flight.
        assert!((hi - lo).max_element() < 0.4, "frame {}: {g:?}", f + 1);
        assert_eq!(stats.contacts.len(), 1, "one count per boundary");
        assert!(stats.contacts[0] <= 1000);
    }
    // The ground acts on nothing in free flight and on the landed block.
    assert_eq!(s.frame_stats[0].contacts, vec![0]);
    assert!(s.frame_stats[12].contacts[0] > 0, "{:?}", s.frame_stats[12]);
    assert!(s.wall_time_s > 0.0 && s.pipe_version == env!("CARGO_PKG_VERSION"));
    // The wall time by part: setup, the substeps alone, output; they add up to the whole.
    let t = s.timing_s;
    assert!(t.setup > 0.0 && t.substeps > 0.0 && t.output > 0.0, "{t:?}");
    assert!(
        (t.setup + t.substeps + t.output - s.wall_time_s).abs() < 1e-9,
        "{t:?} vs {}",
        s.wall_time_s
    );
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let report = s.report(&out);
    println!("{report}");
    assert!(
        report.contains("simulated 13 frame(s) of 1000 particles (elastic)")
            && report.contains("set by: elastic wave (CFL)"),
        "{report}"
    );

    // particles.arrow: 14 000 rows, frame-major, one batch per frame, matching the PLYs;
    // frame-0 velocity = v0.
    let batches = arrow_ipc::reader::FileReader::try_new(
        std::fs::File::open(out.join("particles.arrow")).unwrap(),
        None,
    )
    .unwrap()
    .map(|b| b.unwrap().num_rows())
    .collect::<Vec<_>>();
    assert_eq!(batches, [1000; 14]);
    let tab: Trajectories = table::read(&out.join("particles.arrow")).unwrap();
    assert_eq!(tab.len(), 14_000);
    assert_eq!(tab.frame[999], 0);
    assert_eq!((tab.frame[1000], tab.id[1000]), (1, 0));
    assert_eq!(tab.v[0], [0.5, 0.0, -0.3]);
    assert_eq!(
        tab.positions(13),
        ply::read_points(&out.join("frame_0013.ply"))
            .unwrap()
            .positions
    );
}

/// PAC-NeRF's droplet (7207 particles, Newtonian fluid) from its parameters: frames 1 and 2
/// against the dataset's ground truth. Particles keep their order, so besides the Chamfer
/// distance the per-particle error is checked too (measured at frame 2: mean Chamfer 5.5e-7 m,
/// max per-particle error 7.5e-7 m; the reference ran in float32).
#[test]
fn droplet_frames_1_2_reproduce_pacnerf() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let sim = fixture("droplet-newtonian.sim.yaml");
    let s = simulate::run(
        &pacnerf("droplet-newtonian", "0.ply"),
        &sim,
        3,
        &out,
        &quiet(),
    )
    .unwrap();
    assert_eq!((s.particles_in, s.particles_out), (7207, 7207));
    assert_eq!(s.held_total, 0);
    for f in &s.frame_stats {
        assert_eq!((f.substeps, f.substeps_reason.as_str()), (200, "user"));
    }
    let dx = 0.02;
    for k in 1..=2u32 {
        let got = read(&out.join(format!("frame_{k:04}.ply")));
        let gt = read(&pacnerf("droplet-newtonian", &format!("{k}.ply")));
        assert_eq!(got.len(), gt.len());
        let chamfer = mean_chamfer(&got, &gt).unwrap();
        let max_err = got
            .iter()
            .zip(&gt)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        println!("droplet frame {k}: mean Chamfer {chamfer:.3e} m, max |x - x_gt| {max_err:.3e} m");
        assert!(chamfer < dx / 2.0, "frame {k}: {chamfer}");
        assert!(max_err < 1e-5, "frame {k}: {max_err}");
    }
}

/// `--precision f32`: the torus (14137 particles, neo-Hookean, PAC-NeRF's 200 substeps per
/// frame) through frame 4 in f32 stays within 1e-4 m mean Chamfer of PAC-NeRF's own frame (a
/// float32 simulator) and of the f64 run, loses nothing, and the summary says f32.
#[test]
fn f32_precision_reproduces_the_torus() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = fixture("torus-elastic.sim.yaml");
    let ply = pacnerf("torus-elastic", "0.ply");
    let run = |p: pipe_mpm::Precision, dir: &str| {
        let out = tmp.path().join(dir);
        let opts = simulate::Options {
            splats: false,
            precision: p,
        };
        let s = simulate::run_with(&ply, &sim, 5, &out, &quiet(), opts).unwrap();
        (s, read(&out.join("frame_0004.ply")))
    };
    let (s32, x32) = run(pipe_mpm::Precision::F32, "f32");
    let (s64, x64) = run(pipe_mpm::Precision::F64, "f64");
    assert_eq!(
        (s32.precision.as_str(), s64.precision.as_str()),
        ("f32", "f64")
    );
    assert_eq!((s32.particles_out, s32.held_total), (14137, 0));
    let gt = read(&pacnerf("torus-elastic", "4.ply"));
    let (to_gt, to_f64) = (
        mean_chamfer(&x32, &gt).unwrap(),
        mean_chamfer(&x32, &x64).unwrap(),
    );
    println!("torus frame 4 in f32: mean Chamfer {to_gt:.3e} m to PAC-NeRF, {to_f64:.3e} m to f64");
    assert!(to_gt < 1e-4 && to_f64 < 1e-4, "{to_gt} {to_f64}");
}

/// The PAC-NeRF scenes and their particle counts.
const PACNERF_SCENES: [(&str, usize); 3] = [
    ("torus-elastic", 14137),
    ("blob-plasticine", 8678),
    ("droplet-newtonian", 7207),
];

/// Runs PAC-NeRF scene `scene` (`n` particles) for 14 frames with the SIM.yaml text `sim`;
/// returns the summary and the mean Chamfer distance (m) to the ground truth at frames 4, 7,
/// 10, 13. No particle may be lost or reach the domain walls.
fn pacnerf_run(scene: &str, n: usize, sim: &str) -> (Summary, Vec<(u32, f64)>) {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let sim = write_sim(tmp.path(), sim);
    let s = simulate::run(&pacnerf(scene, "0.ply"), &sim, 14, &out, &quiet()).unwrap();
    assert_eq!((s.particles_in, s.particles_out), (n, n), "{scene}");
    assert_eq!(
        s.held_total, 0,
        "{scene}: no particle reached the domain walls"
    );
    println!(
        "{scene}: {} substeps in {:.1} s; per frame {:?}",
        s.substeps_total,
        s.wall_time_s,
        s.frame_stats.iter().map(|f| f.substeps).collect::<Vec<_>>()
    );
    let mut res = Vec::new();
    for k in [4u32, 7, 10, 13] {
        let got = read(&out.join(format!("frame_{k:04}.ply")));
        let gt = read(&pacnerf(scene, &format!("{k}.ply")));
        let chamfer = mean_chamfer(&got, &gt).unwrap();
        println!("{scene} frame {k}: mean Chamfer {chamfer:.3e} m");
        res.push((k, chamfer));
    }
    (s, res)
}

/// The three PAC-NeRF scenes, 0 → 13, from the shipped simulation files as they are: the
/// ground-truth material and PAC-NeRF's own 200 substeps per frame (CFL number 0.18–0.43, so
/// accepted without `allow_unstable`). The issue bounds the mean Chamfer distance by dx/2 =
/// 1e-2 m; at PAC-NeRF's own step it must stay under 1e-4 m at frames 4, 7, 10 and 13.
/// Measured at frame 13: torus 1.3e-5 m, blob 4.2e-5 m, droplet 1.5e-6 m. About 15 s.
#[test]
fn pacnerf_scenes_all_frames_match_at_their_substeps() {
    for (scene, n) in PACNERF_SCENES {
        let text = std::fs::read_to_string(fixture(&format!("{scene}.sim.yaml"))).unwrap();
        let (s, res) = pacnerf_run(scene, n, &text);
        for f in &s.frame_stats {
            assert!(
                f.substeps == 200
                    && f.substeps_reason == "user"
                    && !f.unstable
                    && (0.15..0.5).contains(&f.cfl_number),
                "{scene}: {f:?}"
            );
        }
        for (k, c) in res {
            assert!(c < 1e-4, "{scene} frame {k}: {c}");
        }
    }
}

/// The same scenes with automatic substeps (the files' `substeps` removed; CFL number 0.3):
/// within dx/2. Measured mean Chamfer at frame 13: torus 5.5e-3 m, blob 2.7e-3 m, droplet
/// 1.2e-4 m. Each transfer damps a little, so the step changes the trajectory: the torus'
/// bounce shows it most. About 40 s in a debug build; run it with
/// `cargo test -p pipe --test cli simulate::pacnerf_scenes -- --ignored --nocapture`.
#[test]
#[ignore = "about 40 s in a debug build: 3 scenes x 14 frames x 115-290 substeps"]
fn pacnerf_scenes_all_frames_with_automatic_substeps() {
    for (scene, n) in PACNERF_SCENES {
        let text = std::fs::read_to_string(fixture(&format!("{scene}.sim.yaml"))).unwrap();
        let (s, res) = pacnerf_run(scene, n, &text.replace("substeps: 200\n", ""));
        for f in &s.frame_stats {
            assert!(
                f.substeps_reason != "user" && f.cfl_number <= 0.3 + 1e-12,
                "{scene}: {f:?}"
            );
        }
        for (k, c) in res {
            assert!(c < 0.02 / 2.0, "{scene} automatic substeps, frame {k}: {c}");
        }
    }
}

/// `prefer_substeps` re-simulates a synthetic scene at its maker's step: PAC-NeRF's torus
/// (automatic count 258–287 a frame) and plasticine blob (~120) at `prefer_substeps: 200` take
/// exactly 200 a frame, named `prefer_substeps`, and follow the ground truth within 1e-4 m
/// (their automatic steps end 5.5e-3 and 2.7e-3 m off,
/// `pacnerf_scenes_all_frames_with_automatic_substeps`). Where a fixed count may not take the
/// preferred step (CFL number above 0.5), the automatic count does; with `substeps`, or out of
/// range, it is refused by name.
#[test]
fn prefer_substeps_takes_the_makers_step_where_a_fixed_count_may() {
    for (scene, n) in &PACNERF_SCENES[..2] {
        let text = std::fs::read_to_string(fixture(&format!("{scene}.sim.yaml"))).unwrap();
        assert!(text.contains("substeps: 200\n"));
        let (s, res) = pacnerf_run(
            scene,
            *n,
            &text.replace("substeps: 200\n", "prefer_substeps: 200\n"),
        );
        for f in &s.frame_stats {
            assert!(
                f.substeps == 200 && f.substeps_reason == "prefer_substeps" && !f.unstable,
                "{scene}: {f:?}"
            );
        }
        for (k, c) in res {
            assert!(c < 1e-4, "{scene} frame {k}: {c}");
        }
    }

    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let sim = write_sim(tmp.path(), &format!("{EXAMPLE}prefer_substeps: 2\n"));
    let s = simulate::run(&block, &sim, 2, &tmp.path().join("out"), &quiet()).unwrap();
    let f = &s.frame_stats[0];
    assert!(
        f.substeps > 2 && f.substeps_reason != "prefer_substeps" && f.cfl_number <= 0.3 + 1e-12,
        "{f:?}"
    );

    let (msg, _) = run_err(|t| format!("{t}substeps: 50\nprefer_substeps: 60\n"), 2);
    assert!(
        msg.contains("invalid `prefer_substeps` = 60") && msg.contains("with `substeps`"),
        "{msg}"
    );
    let (msg, _) = run_err(|t| format!("{t}prefer_substeps: 0\n"), 2);
    assert!(
        msg.contains("invalid `prefer_substeps` = 0") && msg.contains("from 1 to 100000"),
        "{msg}"
    );
}

/// PAC-NeRF's droplet at 70 fixed substeps per frame with `allow_unstable` (CFL number 0.79):
/// during frame 9 it blows up without a NaN (speeds ~1e19 m/s, the fluid pushed through the
/// ground). The run stops in that frame, naming it, as soon as a grid node moves more than a
/// cell in a substep, instead of writing 13 frames of nonsense.
#[test]
fn a_fixed_step_divergence_without_nan_is_stopped() {
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(fixture("droplet-newtonian.sim.yaml")).unwrap();
    let text = text.replace("substeps: 200\n", "substeps: 70\nallow_unstable: true\n");
    assert!(text.contains("substeps: 70"));
    let sim = write_sim(tmp.path(), &text);
    let e = simulate::run(
        &pacnerf("droplet-newtonian", "0.ply"),
        &sim,
        14,
        &tmp.path().join("out"),
        &quiet(),
    )
    .unwrap_err();
    let msg = e.to_string();
    let SimulateError::Diverged { frame, cells, .. } = e else {
        panic!("{msg}")
    };
    assert!((2..14).contains(&frame) && cells > 1.0, "{msg}");
    assert!(msg.contains(&format!("diverged by frame {frame}")), "{msg}");
    // The frames before it stay; the table, written as the run went, is not left behind,
    // complete-looking or temporary.
    let names = names_in(&tmp.path().join("out"));
    assert!(names.contains(&"frame_0001.ply".to_string()), "{names:?}");
    assert!(
        names
            .iter()
            .all(|n| n.starts_with("frame_") && n.ends_with(".ply")),
        "{names:?}"
    );
}

/// The frames are written on a thread of their own while the next frame simulates. When a
/// frame cannot be written (here `frame_0003.ply` is taken by a folder), the run stops with
/// that file's error, and leaves no `particles.arrow` and no temporary file.
#[test]
fn a_frame_that_cannot_be_written_stops_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let input = lattice(6, 0.01, [0.0, 0.1, 0.0]);
    let ply_in = write_ply(tmp.path(), "block.ply", &input);
    let out = tmp.path().join("out");
    std::fs::create_dir_all(out.join("frame_0003.ply").join("taken")).unwrap();
    let e = simulate::run(&ply_in, &fixture("example.sim.yaml"), 8, &out, &quiet()).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("frame_0003.ply"), "{msg}");
    let names = names_in(&out);
    assert_eq!(
        names,
        [
            "frame_0000.ply",
            "frame_0001.ply",
            "frame_0002.ply",
            "frame_0003.ply"
        ],
        "{msg}"
    );
}

/// Defaults from the particles: a PAC-NeRF cloud (8 random particles per 2 cm cell) gives
/// dx ≈ 0.02 m and particle volume ≈ 1e-6 m³ although its median nearest-neighbour distance is
/// only ≈ 6 mm; a lattice gives its spacing exactly.
#[test]
fn spacing_defaults() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = write_sim(
        tmp.path(),
        "material: {family: newtonian, viscosity: 200, bulk_modulus: 1.0e5, density: 1000}\n\
         frame_dt: 0.041666666666666664\n",
    );
    let s = simulate::run(
        &pacnerf("droplet-newtonian", "0.ply"),
        &sim,
        1,
        &tmp.path().join("a"),
        &quiet(),
    )
    .unwrap();
    println!(
        "droplet: spacing {:?} m, median NN {:?} m, dx {} m, volume {:e} m^3",
        s.spacing_m, s.median_nn_distance_m, s.dx_m, s.particle_volume_m3
    );
    assert_eq!(
        (s.dx_source.as_str(), s.particle_volume_source.as_str()),
        ("2 x spacing", "spacing^3")
    );
    assert!((s.dx_m - 0.02).abs() < 0.03 * 0.02, "{}", s.dx_m);
    assert!(
        (s.particle_volume_m3 - 1e-6).abs() < 0.1e-6,
        "{}",
        s.particle_volume_m3
    );
    assert!(s.median_nn_distance_m.unwrap() < 0.008);
    assert!(s.frame_stats.is_empty() && s.warnings.is_empty());

    let block = write_ply(
        tmp.path(),
        "block.ply",
        &lattice(12, 0.005, [0.0, 0.2, 0.0]),
    );
    let s = simulate::run(&block, &sim, 1, &tmp.path().join("b"), &quiet()).unwrap();
    assert!((s.dx_m - 0.01).abs() < 1e-6, "{}", s.dx_m);
    assert!((s.particle_volume_m3 - 1.25e-7).abs() < 1e-12);
}

/// A 3DGS `point_cloud.ply` (ASCII here, with the usual extra properties) is read through its
/// `x y z`, one particle per Gaussian.
#[test]
fn gaussian_splatting_ply_input() {
    let tmp = tempfile::tempdir().unwrap();
    let pts = lattice(5, 0.01, [0.0, 0.3, 0.0]);
    let props = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
        "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let mut text = format!("ply\nformat ascii 1.0\nelement vertex {}\n", pts.len());
    for p in props {
        text += &format!("property float {p}\n");
    }
    text += "end_header\n";
    for p in &pts {
        text += &format!(
            "{} {} {} 0 0 0 0.1 0.2 0.3 2.0 -4.6 -4.6 -4.6 1 0 0 0\n",
            p[0], p[1], p[2]
        );
    }
    let path = tmp.path().join("point_cloud.ply");
    std::fs::write(&path, text).unwrap();
    let out = tmp.path().join("out");
    let s = simulate::run(&path, &fixture("example.sim.yaml"), 2, &out, &quiet()).unwrap();
    assert_eq!((s.particles_in, s.particles_out), (125, 125));
    assert_eq!(read(&out.join("frame_0001.ply")).len(), 125);
}

/// A 3DGS PLY (ASCII) of a ball of radius `r` (m) at `centre`: Fibonacci points 4 mm apart,
/// each a flat splat (σ = 4 mm along the surface, 0.5 mm across it, as a 3DGS fit makes them),
/// opacity sigmoid(3); returns its path and splat count.
fn splat_ball(dir: &Path, r: f64, centre: DVec3) -> (PathBuf, usize) {
    let n = (4.0 * std::f64::consts::PI * r * r / 1.6e-5) as usize;
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut text = format!("ply\nformat ascii 1.0\nelement vertex {n}\n");
    for p in [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        text += &format!("property float {p}\n");
    }
    text += "end_header\n";
    let (log_sigma, log_thin) = (0.004f64.ln(), 0.0005f64.ln());
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let rho = (1.0 - y * y).sqrt();
        let phi = golden * i as f64;
        let normal = DVec3::new(rho * phi.cos(), y, rho * phi.sin());
        let p = centre + r * normal;
        let q = glam::DQuat::from_rotation_arc(DVec3::Z, normal);
        text += &format!(
            "{} {} {} 0.5 0.5 0.5 3 {log_sigma} {log_sigma} {log_thin} {} {} {} {}\n",
            p.x, p.y, p.z, q.w, q.x, q.y, q.z
        );
    }
    let ply = dir.join("ball.ply");
    std::fs::write(&ply, text).unwrap();
    (ply, n)
}

/// A 3DGS PLY of a closed surface (a ball's splats, none inside) gets a grid from its size, is
/// filled, and falls as a solid ball: the fillers are simulated, not written.
#[test]
fn a_splatted_surface_is_filled_and_falls_as_a_solid() {
    let tmp = tempfile::tempdir().unwrap();
    let (r, centre) = (0.1f64, DVec3::new(0.0, 0.3, 0.0));
    let (ply, n) = splat_ball(tmp.path(), r, centre);
    let yaml = "material: {family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3, density: 1000}\n\
                frame_dt: 0.041666666666666664\n\
                boundaries: [{kind: ground, y: 0.0}]\n";
    let sim = write_sim(tmp.path(), yaml);
    let out = tmp.path().join("filled");
    let s = simulate::run(&ply, &sim, 3, &out, &quiet()).unwrap();
    println!(
        "ball: dx {} m, {} fillers, volume {:e} m^3 per splat, mass {} kg, {} substeps, {}",
        s.dx_m, s.fill_particles, s.particle_volume_m3, s.total_mass_kg, s.substeps_total, s.fill
    );
    assert!(
        s.dx_source.starts_with("largest extent / 24"),
        "{}",
        s.dx_source
    );
    assert!((s.dx_m - 0.2 / 24.0).abs() < 0.01 * s.dx_m, "{}", s.dx_m);
    assert!(
        s.fill_particles > 10_000
            && s.fill
                .starts_with(&format!("{} particle", s.fill_particles))
    );
    assert!((s.fill_particle_volume_m3 - (s.dx_m / 2.0).powi(3)).abs() < 1e-15);
    // The ball's mass, to a few per cent.
    let ball = 1000.0 * 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    assert!(
        (s.total_mass_kg / ball - 1.0).abs() < 0.05,
        "{} vs {ball}",
        s.total_mass_kg
    );
    assert!(
        s.warnings.iter().any(|w| w.contains("surface-like")),
        "{:?}",
        s.warnings
    );
    assert_eq!((s.particles_in, s.particles_out), (n, n));
    let x2 = read(&out.join("frame_0002.ply"));
    assert_eq!(x2.len(), n);
    // It falls (free fall for 1/12 s: 3.4 cm) and stays a ball of radius 0.1 m.
    let c2 = centroid(&x2);
    assert!((c2.y - (0.3 - 0.5 * 9.8 / 144.0)).abs() < 2e-3, "{c2}");
    let mean_r = x2.iter().map(|p| (*p - c2).length()).sum::<f64>() / n as f64;
    assert!((mean_r - r).abs() < 2e-3, "{mean_r}");

    // Told not to fill, the same splats are a hollow shell of the surface layer's mass.
    let sim = write_sim(tmp.path(), &format!("{yaml}fill_interior: false\n"));
    let s = simulate::run(&ply, &sim, 1, &tmp.path().join("shell"), &quiet()).unwrap();
    assert_eq!((s.fill_particles, s.fill.as_str()), (0, "off (file)"));
    assert!(s.total_mass_kg < 0.5 * ball, "{}", s.total_mass_kg);
}

/// With `--splats` the 3DGS input is written every frame as splats carried by the motion:
/// frame 0 is the input, the centres are the frame's positions, and a ball in free fall (no
/// deformation) keeps every splat's shape. A plain point cloud is refused with `--splats`, and
/// a later run without it removes the splat files.
#[test]
fn splats_follow_the_particles() {
    let tmp = tempfile::tempdir().unwrap();
    let (ply, n) = splat_ball(tmp.path(), 0.1, DVec3::new(0.0, 0.3, 0.0));
    let yaml = "material: {family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3, density: 1000}\n\
                frame_dt: 0.041666666666666664\n";
    let sim = write_sim(tmp.path(), yaml);
    let out = tmp.path().join("out");
    let opts = simulate::Options {
        splats: true,
        precision: pipe_mpm::Precision::F64,
    };
    let s = simulate::run_with(&ply, &sim, 3, &out, &quiet(), opts).unwrap();
    assert!(s.splats && s.report(&out).contains("3 splat PLYs"));
    let input = ply::read_gaussians(&ply).unwrap();
    assert_eq!(
        ply::read_gaussians(&out.join("splats_0000.ply")).unwrap(),
        input
    );
    let cov = |g: &pipe::scene::gaussians::Gaussians, i: usize| {
        let [w, x, y, z] = g.rotation[i].map(f64::from);
        let q = glam::DQuat::from_xyzw(x, y, z, w).normalize();
        let r = glam::DMat3::from_quat(q);
        let s2 = DVec3::from_array(g.log_scale[i].map(|v| (2.0 * f64::from(v)).exp()));
        r * glam::DMat3::from_diagonal(s2) * r.transpose()
    };
    for k in 1..3 {
        let g = ply::read_gaussians(&out.join(format!("splats_{k:04}.ply"))).unwrap();
        let x = read(&out.join(format!("frame_{k:04}.ply")));
        assert_eq!(g.len(), n);
        for (i, xi) in x.iter().enumerate() {
            let p = DVec3::from_array(g.position[i].map(f64::from));
            assert!((p - *xi).length() < 1e-6, "{k} {i}");
            // Free fall: F = I to within the solver's noise, so Σ is unchanged.
            let (a, b) = (cov(&g, i), cov(&input, i));
            let err = (a - b)
                .to_cols_array()
                .iter()
                .map(|e| e.abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-2 * 0.004f64.powi(2), "{k} {i}: {a:?} vs {b:?}");
        }
        assert_eq!(g.opacity_logit, input.opacity_logit);
        assert_eq!(g.sh, input.sh);
    }
    // A plain point cloud has no splats.
    let cloud = write_ply(tmp.path(), "cloud.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let e =
        simulate::run_with(&cloud, &sim, 2, &tmp.path().join("o2"), &quiet(), opts).unwrap_err();
    assert!(matches!(e, SimulateError::NotSplats { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("cloud.ply: --splats needs a 3DGS PLY"),
        "{e}"
    );
    // Without `--splats`, the folder keeps no splat file of the earlier run.
    let s = simulate::run(&ply, &sim, 2, &out, &quiet()).unwrap();
    assert!(!s.splats);
    assert!(!out.join("splats_0000.ply").exists() && !out.join("splats_0002.ply").exists());
}

/// `merge_splats: true`: the splats that share a voxel of the filling ride one particle. The
/// ball keeps its mass and falls as with one particle per splat, every splat is still written,
/// and forces named by splat index act on those splats' carriers (an index past the input's
/// splats is named against their count, not the carriers').
#[test]
fn merged_splats_ride_fewer_particles_and_fall_the_same() {
    let tmp = tempfile::tempdir().unwrap();
    let (ply, n) = splat_ball(tmp.path(), 0.1, DVec3::new(0.0, 0.3, 0.0));
    let yaml = "material: {family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3, density: 1000}\n\
                frame_dt: 0.041666666666666664\n";
    let each = simulate::run(
        &ply,
        &write_sim(tmp.path(), yaml),
        3,
        &tmp.path().join("each"),
        &quiet(),
    )
    .unwrap();
    let merged_yaml = format!("{yaml}merge_splats: true\n");
    let merged = simulate::run(
        &ply,
        &write_sim(tmp.path(), &merged_yaml),
        3,
        &tmp.path().join("merged"),
        &quiet(),
    )
    .unwrap();
    println!(
        "{n} splats: {} carriers, {} fillers (one each: {} fillers)",
        merged.carrier_particles, merged.fill_particles, each.fill_particles
    );
    assert_eq!(each.carrier_particles, n);
    assert!(merged.carrier_particles < n, "{}", merged.carrier_particles);
    assert_eq!((merged.particles_in, merged.particles_out), (n, n));
    assert!((merged.total_mass_kg / each.total_mass_kg - 1.0).abs() < 1e-9);
    let (a, b) = (
        read(&tmp.path().join("each/frame_0002.ply")),
        read(&tmp.path().join("merged/frame_0002.ply")),
    );
    assert_eq!(b.len(), n);
    let (ca, cb) = (centroid(&a), centroid(&b));
    assert!((ca - cb).length() < 1e-3, "{ca} vs {cb}");
    let worst = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0, f64::max);
    assert!(
        worst < 3e-3,
        "a splat {worst} m from where one particle per splat puts it"
    );

    // Forces by splat index act on their carriers; an index past the splats is named.
    let pushed = format!(
        "{merged_yaml}gravity: [0, 0, 0]\nforces:\n  - {{kind: impulse, particles: [0, 1, 2, 3], impulse: [1.0e-3, 0, 0], time: 0.0}}\n"
    );
    let s = simulate::run(
        &ply,
        &write_sim(tmp.path(), &pushed),
        2,
        &tmp.path().join("p"),
        &quiet(),
    )
    .unwrap();
    assert_eq!(s.forces, 1);
    let x1 = read(&tmp.path().join("p/frame_0001.ply"));
    let x0 = read(&ply);
    assert!(
        x1[0].x - x0[0].x > 1e-4,
        "the pushed splat moves: {} -> {}",
        x0[0].x,
        x1[0].x
    );
    let bad = format!(
        "{merged_yaml}forces:\n  - {{kind: impulse, particles: [{n}], impulse: [1.0e-3, 0, 0], time: 0.0}}\n"
    );
    let e = simulate::run(
        &ply,
        &write_sim(tmp.path(), &bad),
        2,
        &tmp.path().join("q"),
        &quiet(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains(&format!("the input has {n} particles")), "{e}");
}

/// Faint splats outside the solid (a fit's leftovers: under a thin object no camera sees,
/// the warm-up leaves splats of opacity ~0.01 up to 10 cm below it) are appearance, not
/// matter: with `merge_splats: true` they ride the nearest particle at no volume. The body is
/// the same as without them (mass, particles, every other splat's path bit for bit), and
/// they move with it. Before, each was a particle of an eighth of a voxel hanging off the body.
#[test]
fn faint_splats_outside_the_solid_ride_the_body_and_weigh_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let (ply, n) = splat_ball(tmp.path(), 0.1, DVec3::new(0.0, 0.3, 0.0));
    let text = std::fs::read_to_string(&ply).unwrap();
    // 60 faint splats (alpha 0.02) in the box's lower corner, ~1 cm outside the ball (inside
    // its bounding box, so that the grid and the filling's voxels stay the same).
    let faint = 60;
    let mut rows = String::new();
    for i in 0..faint {
        let (a, b, c) = ((i % 4) as f64, ((i / 4) % 3) as f64, (i / 12) as f64);
        rows += &format!(
            "{} {} {} 0.5 0.5 0.5 {} {} {} {} 1 0 0 0\n",
            0.075 + 0.005 * a,
            0.21 + 0.005 * b,
            -0.03 + 0.015 * c,
            (0.02f64 / 0.98).ln(),
            0.004f64.ln(),
            0.004f64.ln(),
            0.004f64.ln()
        );
    }
    let with_faint = tmp.path().join("faint.ply");
    std::fs::write(
        &with_faint,
        text.replace(
            &format!("element vertex {n}\n"),
            &format!("element vertex {}\n", n + faint),
        ) + &rows,
    )
    .unwrap();
    let yaml = "material: {family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3, density: 1000}\n\
                frame_dt: 0.041666666666666664\nmerge_splats: true\n\
                boundaries: [{kind: ground, y: 0.0}]\n";
    let sim = write_sim(tmp.path(), yaml);
    let clean = simulate::run(&ply, &sim, 4, &tmp.path().join("clean"), &quiet()).unwrap();
    let both = simulate::run(&with_faint, &sim, 4, &tmp.path().join("both"), &quiet()).unwrap();
    assert_eq!(both.particles_in, n + faint);
    assert_eq!(both.particles_out, n + faint, "every splat is written");
    assert_eq!(
        (both.carrier_particles, both.fill_particles),
        (clean.carrier_particles, clean.fill_particles),
        "the faint splats add no particle"
    );
    assert_eq!(both.total_mass_kg, clean.total_mass_kg, "and no mass");
    let (a, b) = (
        read(&tmp.path().join("clean/frame_0003.ply")),
        read(&tmp.path().join("both/frame_0003.ply")),
    );
    assert_eq!(b.len(), n + faint);
    assert_eq!(
        a[..],
        b[..n],
        "the ball's splats move bit for bit as without them"
    );
    let start = read(&with_faint);
    let fall = centroid(&a) - centroid(&start[..n]);
    assert!(fall.y < -0.05, "the ball falls: {fall}");
    for (g, (p, q)) in start[n..].iter().zip(&b[n..]).enumerate() {
        let moved = *q - *p;
        assert!(
            (moved - fall).length() < 0.01,
            "faint splat {g} moved {moved}, the ball {fall}"
        );
    }
}

/// A stiff ring (R = 0.15 m, r = 0.04 m) standing almost upright 2 cm above a sticky ground:
/// it lands, tips over sideways and rolls away from where it fell, motion that starts only
/// after contact. Without `domain:` the grid follows it, so its frames equal those of a run
/// inside a domain far too large to reach (≤ 1e-6 m), and no wall is reported. A declared
/// domain whose side the ring reaches changes the motion, and the summary counts the particles
/// its walls acted on and warns.
fn upright_ring() -> Vec<[f32; 3]> {
    let (big_r, small_r, h) = (0.15f64, 0.04f64, 0.01f64);
    let tilt = 10f64.to_radians();
    let mut out = Vec::new();
    let n = (0.25 / h) as i32;
    for i in -n..=n {
        for j in -n..=n {
            for k in -n..=n {
                // The ring lies in the x-y plane (its axis along z), then tilts about x.
                let p = DVec3::new(i as f64, j as f64, k as f64) * h;
                let q = (p.x * p.x + p.y * p.y).sqrt() - big_r;
                if q * q + p.z * p.z <= small_r * small_r {
                    let (c, sn) = (tilt.cos(), tilt.sin());
                    let r = DVec3::new(p.x, c * p.y - sn * p.z, sn * p.y + c * p.z);
                    out.push([
                        r.x as f32,
                        (r.y + big_r + small_r + 0.02) as f32,
                        r.z as f32,
                    ]);
                }
            }
        }
    }
    out
}

#[test]
fn a_ring_that_tips_over_moves_as_without_walls() {
    let tmp = tempfile::tempdir().unwrap();
    let ring = write_ply(tmp.path(), "ring.ply", &upright_ring());
    let base = "material: {family: elastic, youngs_modulus: 1.0e5, poisson_ratio: 0.3, density: 1000}\n\
                frame_dt: 0.041666666666666664\n\
                grid_dx: 0.02\n\
                particle_volume: 1.0e-6\n\
                boundaries: [{kind: ground, y: 0.0, condition: sticky}]\n";
    let frames = 16;
    let run = |name: &str, domain: &str| {
        let path = tmp.path().join(format!("{name}.sim.yaml"));
        std::fs::write(&path, format!("{base}{domain}")).unwrap();
        let out = tmp.path().join(name);
        let s = simulate::run(&ring, &path, frames, &out, &quiet()).unwrap();
        let x: Vec<Vec<DVec3>> = (0..frames)
            .map(|k| read(&out.join(format!("frame_{k:04}.ply"))))
            .collect();
        (s, x)
    };
    let (follow, x_follow) = run("follow", "");
    let (huge, x_huge) = run(
        "huge",
        "domain: {min: [-1.5, -0.1, -1.5], max: [1.5, 2.0, 1.5]}
",
    );
    // The ring tipped: its axis (z at rest, tilted 10°) is close to vertical at the end, and
    // its top came down from ~0.4 m.
    let top = |x: &[DVec3]| x.iter().map(|p| p.y).fold(f64::MIN, f64::max);
    assert!(top(&x_follow[0]) > 0.35);
    assert!(
        top(&x_follow[frames as usize - 1]) < 0.2,
        "the ring did not fall over: top at {} m",
        top(&x_follow[frames as usize - 1])
    );
    let mut worst = 0.0f64;
    for (f, (a, b)) in x_follow.iter().zip(&x_huge).enumerate() {
        assert_eq!(a.len(), b.len());
        let d = a
            .iter()
            .zip(b)
            .map(|(p, q)| (*p - *q).abs().max_element())
            .fold(0.0, f64::max);
        assert!(d <= 1e-6, "frame {f}: {d:e} m from the huge domain's run");
        worst = worst.max(d);
    }
    println!(
        "ring: top {:.3} -> {:.3} m; follow vs huge domain: {worst:e} m",
        top(&x_follow[0]),
        top(&x_follow[frames as usize - 1])
    );
    assert!(follow.warnings.is_empty(), "{:?}", follow.warnings);
    assert!(follow.frame_stats.iter().all(|f| f.contacts.len() == 1));
    assert!(
        huge.frame_stats
            .iter()
            .all(|f| f.contacts.len() == 2 && f.contacts[1] == 0)
    );
    // A declared side wall the falling ring reaches: counted, warned, and the motion differs.
    let (walled, x_walled) = run(
        "walled",
        "domain: {min: [-0.3, -0.1, -0.3], max: [0.3, 0.6, 0.12]}
",
    );
    let hits: usize = walled
        .frame_stats
        .iter()
        .map(|f| f.contacts[1])
        .max()
        .unwrap();
    assert!(hits > 0, "{:?}", walled.frame_stats);
    assert!(
        walled
            .warnings
            .iter()
            .any(|w| w.contains("the domain walls acted on")),
        "{:?}",
        walled.warnings
    );
    let last = frames as usize - 1;
    let moved = x_walled[last]
        .iter()
        .zip(&x_follow[last])
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0, f64::max);
    assert!(moved > 1e-3, "the wall changed nothing ({moved} m)");
    println!("walled: {hits} particles on the walls, {moved:.3} m off at the last frame");
}

/// Forces and impulses reach the particles they select, and the automatic domain covers a
/// thrown block without gravity (no ground).
#[test]
fn impulse_on_a_box_and_force_on_indices() {
    let tmp = tempfile::tempdir().unwrap();
    // 8³ block from x = 0 to 0.07; the impulse hits the half with x > 0.035.
    let block = write_ply(tmp.path(), "block.ply", &lattice(8, 0.01, [0.0, 0.5, 0.0]));
    let sim = write_sim(
        tmp.path(),
        "material: {family: elastic, youngs_modulus: 1.0e4, poisson_ratio: 0.3, density: 1000}\n\
         gravity: [0, 0, 0]\n\
         frame_dt: 0.02\n\
         grid_dx: 0.02\n\
         particle_volume: 1.0e-6\n\
         forces:\n  \
           - {kind: impulse, particles: {min: [0.035, 0, 0], max: [1, 1, 1]}, impulse: [1.0e-4, 0, 0], time: 0.0}\n  \
           - {kind: force, particles: [0, 1], force: [0, 0, 1.0e-3], start: 0.0, end: 0.02}\n",
    );
    let s = simulate::run(&block, &sim, 3, &tmp.path().join("out"), &quiet()).unwrap();
    assert_eq!(s.forces, 2);
    assert_eq!(s.held_total, 0);
    let tab: Trajectories = table::read(&tmp.path().join("out/particles.arrow")).unwrap();
    // Momentum: 256 particles × 1e-4 N·s in x over 512 × 1e-3 kg → mean vx = 0.05 m/s;
    // force 2 × 1e-3 N for 0.02 s in z → mean vz = 4e-5 / 0.512 m/s.
    let n = 512;
    let v2: Vec<[f32; 3]> = tab.v[2 * n..3 * n].to_vec();
    let mean = |a: usize| v2.iter().map(|v| f64::from(v[a])).sum::<f64>() / n as f64;
    assert!((mean(0) - 0.05).abs() < 1e-4, "{}", mean(0));
    assert!((mean(2) - 4e-5 / 0.512).abs() < 1e-6, "{}", mean(2));
}

/// A push in the middle of a frame: that frame's substeps hold for the speed the impulse gives
/// (20 m/s on a soft block whose waves travel at 3.7 m/s: from the speed at the frame's start
/// alone it would take 13 substeps at CFL number 1.8), and the automatic domain covers the
/// 1.4 m the block then travels, so no particle is held. An impulse far too strong for the
/// material is refused, naming the frame, instead of running for hours; so is a force whose
/// reach no grid could hold (not blamed on `grid_dx`).
#[test]
fn a_push_mid_frame_sets_the_substeps_and_the_domain() {
    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(8, 0.01, [0.0, 0.5, 0.0]));
    let sim = |impulse: f64| {
        format!(
            "material: {{family: elastic, youngs_modulus: 1.0e4, poisson_ratio: 0.3, density: 1000}}\n\
             gravity: [0, 0, 0]\n\
             frame_dt: 0.02\n\
             grid_dx: 0.02\n\
             particle_volume: 1.0e-6\n\
             forces:\n  \
               - {{kind: impulse, particles: all, impulse: [{impulse:e}, 0, 0], time: 0.03}}\n"
        )
    };
    let path = write_sim(tmp.path(), &sim(0.02));
    let s = simulate::run(&block, &path, 6, &tmp.path().join("out"), &quiet()).unwrap();
    let f1 = &s.frame_stats[0];
    assert_eq!(f1.speed_bound_m_s, f1.max_speed_m_s, "{f1:?}");
    let f2 = &s.frame_stats[1];
    assert!(f2.max_speed_m_s < 1e-9, "{f2:?}");
    assert!((f2.speed_bound_m_s - 20.0).abs() < 1e-9, "{f2:?}");
    assert!(f2.substeps >= 79 && f2.cfl_number <= 0.3 + 1e-12, "{f2:?}");
    assert_eq!(s.held_total, 0, "{:?}", s.frame_stats);
    let tab: Trajectories = table::read(&tmp.path().join("out/particles.arrow")).unwrap();
    let n = 512;
    let mean_x = |frame: usize| {
        tab.x[frame * n..(frame + 1) * n]
            .iter()
            .map(|p| f64::from(p[0]))
            .sum::<f64>()
            / n as f64
    };
    // 20 m/s from t = 0.03 s to 0.1 s: 1.4 m (to within the substep the impulse lands in).
    assert!((mean_x(5) - mean_x(0) - 1.4).abs() < 0.01, "{}", mean_x(5));

    let path = write_sim(tmp.path(), &sim(1e3));
    let e = simulate::run(&block, &path, 6, &tmp.path().join("out2"), &quiet()).unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(e, SimulateError::TooManySubsteps { frame: 2, .. })
            && msg.contains("frame 2 would need")
            && msg.contains("a force or impulse is too strong"),
        "{msg}"
    );
    // A force no substep count can follow: refused on its substeps (not on `grid_dx`, which
    // is not the problem).
    let text = sim(0.02).replace(
        "{kind: impulse, particles: all, impulse: [2e-2, 0, 0], time: 0.03}",
        "{kind: force, particles: all, force: [1e150, 0, 0], start: 0.0}",
    );
    assert!(text.contains("1e150"), "{text}");
    let path = write_sim(tmp.path(), &text);
    let e = simulate::run(&block, &path, 6, &tmp.path().join("out3"), &quiet()).unwrap_err();
    assert!(
        matches!(e, SimulateError::TooManySubsteps { frame: 1, .. }),
        "{e}"
    );
}

/// A force or impulse outside the simulated time is reported: it would otherwise do nothing
/// without a word.
#[test]
fn forces_outside_the_simulated_time_are_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let sim = write_sim(
        tmp.path(),
        &format!(
            "{EXAMPLE}forces:\n  \
             - {{kind: impulse, particles: all, impulse: [1.0e-4, 0, 0], time: -1}}\n  \
             - {{kind: force, particles: all, force: [1.0e-4, 0, 0], start: 0.01}}\n  \
             - {{kind: force, particles: all, force: [1.0e-4, 0, 0], start: 0.09}}\n"
        ),
    );
    let s = simulate::run(&block, &sim, 3, &tmp.path().join("out"), &quiet()).unwrap();
    let about = |i: usize| {
        s.warnings
            .iter()
            .filter(|w| w.contains(&format!("`forces[{i}]`")))
            .count()
    };
    assert_eq!(
        (about(0), about(1), about(2)),
        (1, 0, 1),
        "{:?}",
        s.warnings
    );
    assert_eq!(
        s.warnings[0],
        "`forces[0]` acts at t = -1 s, outside the simulated time [0, 0.0833) s: it has no effect"
    );
}

/// A run into a folder of an earlier, longer run leaves only this run's frames.
#[test]
fn stale_frames_are_removed() {
    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let out = tmp.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    for k in 0..5 {
        std::fs::write(out.join(format!("frame_{k:04}.ply")), "old").unwrap();
    }
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let log = Log::default();
    simulate::run(&block, &fixture("example.sim.yaml"), 2, &out, &log).unwrap();
    assert!(out.join("frame_0001.ply").exists() && !out.join("frame_0002.ply").exists());
    assert!(!out.join("frame_0004.ply").exists() && out.join("notes.txt").exists());
    assert!(
        log.0
            .lock()
            .unwrap()
            .iter()
            .any(|l| l.contains("3 stale frame"))
    );
}

// ---------------------------------------------------------------------------------------------
// Errors

const EXAMPLE: &str = include_str!("../fixtures/simulate/example.sim.yaml");

/// Runs the example file edited by `edit` on a small block; returns the error message.
fn run_err(edit: impl Fn(&str) -> String, frames: u32) -> (String, SimulateError) {
    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let sim = write_sim(tmp.path(), &edit(EXAMPLE));
    let out = tmp.path().join("out");
    let e = simulate::run(&block, &sim, frames, &out, &quiet()).unwrap_err();
    let msg = e.to_string();
    println!("{msg}");
    assert!(
        msg.contains("sim.yaml") || msg.starts_with("--frames"),
        "{msg}"
    );
    assert!(
        !out.join("frame_0000.ply").exists(),
        "nothing written on a refused file"
    );
    (msg, e)
}

#[test]
fn unknown_key_names_line_and_suggests() {
    let (msg, e) = run_err(|t| t.replace("  youngs_modulus:", "  youngs_modulos:"), 2);
    assert!(matches!(e, SimulateError::Spec(_)));
    assert!(
        msg.contains("unknown key `youngs_modulos` in material at line 3:3"),
        "{msg}"
    );
    assert!(msg.contains("did you mean `youngs_modulus`?"), "{msg}");
    let (msg, _) = run_err(|t| t.replace("grid_dx:", "gird_dx:"), 2);
    assert!(
        msg.contains("unknown key `gird_dx` at the top level at line 12:1")
            && msg.contains("did you mean `grid_dx`?"),
        "{msg}"
    );
}

#[test]
fn impossible_material_values() {
    let (msg, _) = run_err(|t| t.replace("poisson_ratio: 0.3", "poisson_ratio: 0.5"), 2);
    assert!(
        msg.contains("invalid `material.poisson_ratio` = 0.5 at line 4:18")
            && msg.contains("(-1, 0.5)"),
        "{msg}"
    );
    let (msg, _) = run_err(
        |t| t.replace("youngs_modulus: 3.0e5", "youngs_modulus: 0"),
        2,
    );
    assert!(
        msg.contains("invalid `material.youngs_modulus` = 0 at line 3:19")
            && msg.contains("must be > 0"),
        "{msg}"
    );
    let (msg, _) = run_err(|t| t.replace("density: 1000 ", "density: -5 "), 2);
    assert!(
        msg.contains("invalid `material.density` = -5 at line 5:12"),
        "{msg}"
    );
}

/// A `frame_dt` no material can step in a million substeps is refused before anything is
/// written, naming `frame_dt`, the file and the longest frame that works.
#[test]
fn a_frame_dt_far_too_long_is_named() {
    let (msg, e) = run_err(
        |t| t.replace("frame_dt: 0.041666666666666664", "frame_dt: 1.0e9"),
        2,
    );
    assert!(matches!(e, SimulateError::TooManySubsteps { frame: 1, .. }));
    assert!(
        msg.contains("`frame_dt` = 1e9 s in ")
            && msg.contains("sim.yaml is too long for this material, grid and initial speed")
            && msg.contains("a frame may last at most "),
        "{msg}"
    );
}

#[test]
fn family_parameter_mismatch() {
    // A newtonian fluid given elastic parameters: the message says which families use them.
    let (msg, _) = run_err(|t| t.replace("family: elastic ", "family: newtonian "), 2);
    assert!(
        msg.contains(
            "`material.youngs_modulus` is not a parameter of the newtonian family at line 3:3"
        ),
        "{msg}"
    );
    assert!(
        msg.contains("used by elastic, elastic_fcr, plasticine, non_newtonian, sand")
            && msg.contains("newtonian takes viscosity, bulk_modulus"),
        "{msg}"
    );
    // Sand without its friction angle.
    let (msg, _) = run_err(|t| t.replace("family: elastic ", "family: sand "), 2);
    assert!(
        msg.contains("missing key `friction_angle_deg` in material: the sand family needs it")
            && msg.contains("at line 1:1"),
        "{msg}"
    );
    // Elastic given a yield stress.
    let (msg, _) = run_err(
        |t| t.replace("  density: 1000", "  yield_stress: 100\n  density: 1000"),
        2,
    );
    assert!(
        msg.contains("`material.yield_stress` is not a parameter of the elastic family")
            && msg.contains("used by plasticine, non_newtonian"),
        "{msg}"
    );
}

/// A fixed `substeps` above the stability limit of a fixed step (CFL number 0.5) is refused,
/// naming the limit, the CFL number and how many are needed; with `allow_unstable: true` it
/// runs and the summary says so. Between the automatic 0.3 and 0.5 a fixed count is taken.
#[test]
fn user_substeps_above_the_limit() {
    let (msg, e) = run_err(|t| format!("{t}substeps: 50\n"), 2);
    let SimulateError::UnstableSubsteps {
        limit,
        max_dt,
        needed,
        ..
    } = e
    else {
        panic!("{msg}")
    };
    assert_eq!(limit, "elastic wave (CFL)");
    assert!(needed > 50 && max_dt < FRAME_DT / 50.0);
    assert!(
        msg.contains(
            "`substeps` = 50 at line 15:11 is above the elastic wave (CFL) stability limit"
        ) && msg.contains("(CFL number 0.8")
            && msg.contains(&format!("at least {needed} substeps"))
            && msg.contains("allow_unstable: true"),
        "{msg}"
    );

    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(4, 0.01, [0.0, 0.5, 0.0]));
    let sim = write_sim(
        tmp.path(),
        &format!("{EXAMPLE}substeps: 50\nallow_unstable: true\n"),
    );
    let log = Log::default();
    let s = simulate::run(&block, &sim, 2, &tmp.path().join("out"), &log).unwrap();
    let f = &s.frame_stats[0];
    assert_eq!((f.substeps, f.substeps_reason.as_str()), (50, "user"));
    assert!(
        f.unstable && f.dt_s > f.max_fixed_dt_s && f.cfl_number > 0.5,
        "{f:?}"
    );
    assert!(
        s.warnings.iter().any(|w| w.contains("allow_unstable")),
        "{:?}",
        s.warnings
    );
    assert!(
        log.0
            .lock()
            .unwrap()
            .iter()
            .any(|l| l.starts_with("warning:"))
    );

    // A fixed count within the limit is taken as given: the fewest the message asked for
    // (CFL number just under 0.5, above the automatic 0.3), and a few more.
    for n in [needed, needed + 5] {
        let sim = write_sim(tmp.path(), &format!("{EXAMPLE}substeps: {n}\n"));
        let s = simulate::run(&block, &sim, 2, &tmp.path().join("out2"), &quiet()).unwrap();
        let f = &s.frame_stats[0];
        assert_eq!(f.substeps, n);
        assert!(!f.unstable && f.dt_s <= f.max_fixed_dt_s, "{f:?}");
        assert!(f.dt_s > f.stable_dt_s, "{f:?}");
    }
    let (_, e) = run_err(|t| format!("{t}substeps: {}\n", needed - 1), 2);
    assert!(matches!(e, SimulateError::UnstableSubsteps { .. }), "{e}");
}

#[test]
fn empty_and_missing_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = fixture("example.sim.yaml");
    // A PLY with zero vertices.
    let empty = write_ply(tmp.path(), "empty.ply", &[]);
    let e = simulate::run(&empty, &sim, 2, &tmp.path().join("o"), &quiet()).unwrap_err();
    assert!(matches!(e, SimulateError::NoParticles { .. }));
    assert!(e.to_string().contains("empty.ply: no particles"), "{e}");
    // A zero-byte file.
    let zero = tmp.path().join("zero.ply");
    std::fs::write(&zero, "").unwrap();
    let e = simulate::run(&zero, &sim, 2, &tmp.path().join("o"), &quiet()).unwrap_err();
    assert!(e.to_string().contains("zero.ply: empty file"), "{e}");
    // Missing particle file and missing simulation file.
    let block = write_ply(tmp.path(), "block.ply", &lattice(3, 0.01, [0.0, 0.5, 0.0]));
    let e = simulate::run(
        &tmp.path().join("nope.ply"),
        &sim,
        2,
        &tmp.path().join("o"),
        &quiet(),
    )
    .unwrap_err();
    assert!(
        matches!(e, SimulateError::Ply(_)) && e.to_string().contains("nope.ply"),
        "{e}"
    );
    let e = simulate::run(
        &block,
        &tmp.path().join("nope.yaml"),
        2,
        &tmp.path().join("o"),
        &quiet(),
    )
    .unwrap_err();
    assert!(
        e.to_string()
            .contains("nope.yaml: cannot read the simulation file"),
        "{e}"
    );
    // --frames 0.
    let e = simulate::run(&block, &sim, 0, &tmp.path().join("o"), &quiet()).unwrap_err();
    assert!(e.to_string().starts_with("--frames 0"), "{e}");
    assert!(!tmp.path().join("o").exists());
}

#[test]
fn force_selections_are_checked_against_the_particles() {
    let (msg, _) = run_err(
        |t| format!("{t}forces:\n  - {{kind: force, particles: [1, 64], force: [0, 1, 0]}}\n"),
        2,
    );
    assert!(
        msg.contains("invalid `forces[0].particles[1]` = 64 at line 16:")
            && msg.contains("the input has 64 particles (indices 0 to 63)"),
        "{msg}"
    );
    let (msg, _) = run_err(
        |t| {
            format!(
                "{t}forces:\n  - {{kind: impulse, particles: {{min: [5, 5, 5], max: [6, 6, 6]}}, impulse: [0, 1, 0], time: 0}}\n"
            )
        },
        2,
    );
    assert!(
        msg.contains("selects no particle") && msg.contains("line 16:"),
        "{msg}"
    );
}

/// `schemas/particles.arrow.json` is the contract of `particles.arrow`; regenerate with
/// `PIPE_WRITE_SCHEMAS=1 cargo test -p pipe --test cli simulate::particles_schema`.
#[test]
fn particles_schema_contract() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/particles.arrow.json");
    let text = serde_json::to_string_pretty(&table::schema_json::<Trajectories>()).unwrap() + "\n";
    if std::env::var_os("PIPE_WRITE_SCHEMAS").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    assert_eq!(
        std::fs::read_to_string(&path).unwrap_or_default(),
        text,
        "{} is out of date; regenerate with PIPE_WRITE_SCHEMAS=1 cargo test -p pipe --test cli simulate::particles_schema",
        path.display()
    );
}

/// A stiff block thrown with a spin in free fall (no gravity, no boundary): frame 0 holds the
/// rigid motion `v + ω × (x − c)` about the centre of mass `c` (the summary names both), and
/// after a fifth of a second the block has turned about its moving centre as fast as its
/// particles' own inertia lets it (below) and kept its shape (a rigid fit leaves under
/// 0.1 mm).
/// A given `spin_centre` is used as given; a NaN is refused with its line.
#[test]
fn a_spinning_block_turns_about_its_centre_of_mass() {
    let tmp = tempfile::tempdir().unwrap();
    let block = write_ply(tmp.path(), "block.ply", &lattice(8, 0.01, [0.0, 0.5, 0.0]));
    let text = "material: {family: elastic, youngs_modulus: 1.0e7, poisson_ratio: 0.3, density: 1000}\n\
         gravity: [0, 0, 0]\n\
         frame_dt: 0.05\n\
         grid_dx: 0.02\n\
         particle_volume: 1.0e-6\n\
         initial_velocity: [0.2, 0, 0]\n\
         angular_velocity: [0, 0, 3]\n";
    let sim = write_sim(tmp.path(), text);
    let out = tmp.path().join("out");
    let s = simulate::run(&block, &sim, 5, &out, &quiet()).unwrap();
    let x0 = read(&out.join("frame_0000.ply"));
    let c = centroid(&x0);
    assert!(
        (DVec3::from_array(s.spin_centre) - c).length() < 1e-6,
        "{s:?}"
    );
    assert_eq!(s.angular_velocity, [0.0, 0.0, 3.0]);
    let tab: Trajectories = table::read(&out.join("particles.arrow")).unwrap();
    let (v, w) = (DVec3::new(0.2, 0.0, 0.0), DVec3::new(0.0, 0.0, 3.0));
    for (x, vp) in x0.iter().zip(&tab.v[..x0.len()]) {
        let want = v + w.cross(*x - c);
        let got = DVec3::from_array(vp.map(f64::from));
        assert!((got - want).length() < 1e-5, "{got} against {want}");
    }
    // Frame 4 (t = 0.2 s): the centre moved v t; the best rotation about it (in the xy plane,
    // the spin's) is 0.6 rad, and it explains every particle to 0.1 mm.
    let t = 0.2;
    let x4 = read(&out.join("frame_0004.ply"));
    assert_eq!(x4.len(), x0.len());
    let c4 = centroid(&x4);
    assert!(
        (c4 - (c + v * t)).length() < 1e-4,
        "centre {c4} against {}",
        c + v * t
    );
    let (mut s_cos, mut s_sin) = (0.0, 0.0);
    for (a, b) in x0.iter().zip(&x4) {
        let (p, q) = (*a - c, *b - c4);
        s_cos += p.x * q.x + p.y * q.y;
        s_sin += p.x * q.y - p.y * q.x;
    }
    // APIC's `C` starts at 0 (PAC-NeRF's convention, which the stages and the generated
    // scenes share): each particle's own inertia, `m dx²/4` per axis, adds to the block's, so it
    // turns at `ω I / (I + M dx²/2)`: side 0.08 m, `I/M` = 2 · 0.08² / 12, `dx` = 0.02 m.
    let angle = s_sin.atan2(s_cos);
    let inertia = 2.0 * 0.08f64.powi(2) / 12.0;
    let expected = 3.0 * t * inertia / (inertia + 0.02f64.powi(2) / 2.0);
    assert!(
        (angle - expected).abs() < 0.01,
        "turned {angle} rad, not {expected}"
    );
    let (cos, sin) = (angle.cos(), angle.sin());
    let worst = x0
        .iter()
        .zip(&x4)
        .map(|(a, b)| {
            let p = *a - c;
            let turned = DVec3::new(cos * p.x - sin * p.y, sin * p.x + cos * p.y, p.z);
            (c4 + turned - *b).length()
        })
        .fold(
            0.0f64,
            |m, d| if d.is_nan() { f64::INFINITY } else { m.max(d) },
        );
    assert!(worst < 1e-4, "a rigid turn leaves {worst} m");

    // A given centre: the corner of the block stands still at frame 0.
    let sim = write_sim(
        tmp.path(),
        &format!("{text}spin_centre: [0, 0.5, 0]\n").replace("[0.2, 0, 0]", "[0, 0, 0]"),
    );
    let out2 = tmp.path().join("out2");
    let s = simulate::run(&block, &sim, 2, &out2, &quiet()).unwrap();
    assert_eq!(s.spin_centre, [0.0, 0.5, 0.0]);
    let tab: Trajectories = table::read(&out2.join("particles.arrow")).unwrap();
    let corner = x0
        .iter()
        .position(|x| (*x - DVec3::new(0.0, 0.5, 0.0)).length() < 1e-6)
        .unwrap();
    assert!(DVec3::from_array(tab.v[corner].map(f64::from)).length() < 1e-7);

    let (msg, e) = run_err(|t| format!("{t}angular_velocity: [1, .nan, 0]\n"), 2);
    assert!(matches!(e, SimulateError::Spec(_)));
    assert!(msg.contains("NaN") && msg.contains("line 15"), "{msg}");
}
