//! `ingest` on the repo's fixture scene (`tests/fixtures/torus-elastic-small`: the public
//! torus-elastic scene down-scaled 2× by `datasets-tools downscale`, 11 cameras × 14 frames,
//! 100×100, with its ground-truth masks). Cameras, frames, times, intrinsics and a camera centre
//! are checked against values read independently from the JSON; the masks against the ground
//! truth (mean IoU ≥ 0.965, min ≥ 0.935, measured 0.9685 and 0.9433; the single-view matte
//! makes 0.9611 and 0.9192: the torus casts a dark shadow on a textured floor, which a
//! plain colour difference mistakes for object), also with a camera's noise in every image.
//! The composite scenes of `tests/fixtures/composite-*` (made by `datasets-tools composite`)
//! hold the matting's hard cases (the targets, mean IoU ≥ 0.95 and min ≥ 0.92; a blob
//! lying on its shadow in its tones and an object of the floor's own colour are not solved, and
//! their torn masks are named); a torn mask is reported in a warning naming its camera and
//! frame, and a capture of few cameras is not warned about. Then each kind of
//! broken capture must give an error naming the file and value.

use crate::support::{BuiltinRun, fixture_scene};
use std::path::{Path, PathBuf};

use pipe::scene::frames::{Frames, Role};
use pipe::scene::metrics::Metrics;
use pipe::scene::table;

fn fixture() -> PathBuf {
    fixture_scene()
}

/// Run `ingest` on `scene` in a fresh work dir; returns the run (keeps the dir) and the entry.
fn ingest(scene: &Path, test_views: &str) -> (BuiltinRun, Result<PathBuf, String>) {
    let run = BuiltinRun::new(scene, test_views, "standard", "  ingest: {}\n");
    let res = run.run().map(|_| run.entry("ingest"));
    (run, res)
}

fn gray(path: &Path) -> Vec<u8> {
    image::open(path).unwrap().into_luma8().into_raw()
}

#[test]
fn fixture_scene_cameras_frames_and_masks() {
    let (_dir, entry) = ingest(&fixture(), "[10]");
    let entry = entry.unwrap();
    let frames: Frames = table::read(&entry.join("frames.arrow")).unwrap();
    let json: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(fixture().join("all_data.json")).unwrap()).unwrap();
    let objects: Vec<&serde_json::Value> = json
        .iter()
        .filter(|e| !e["file_path"].as_str().unwrap().ends_with("_-1.png"))
        .collect();
    assert_eq!(frames.rows.len(), objects.len());
    assert_eq!(frames.rows.len(), 11 * 14);
    let views: std::collections::BTreeSet<u16> = frames.rows.iter().map(|r| r.view).collect();
    assert_eq!(views.len(), 11);
    for e in &objects {
        let name = e["file_path"].as_str().unwrap();
        let stem = name
            .trim_start_matches("./data/r_")
            .trim_end_matches(".png");
        let (v, f) = stem.split_once('_').unwrap();
        let (v, f): (u16, u16) = (v.parse().unwrap(), f.parse().unwrap());
        let row = frames
            .rows
            .iter()
            .find(|r| r.view == v && r.frame == f)
            .unwrap();
        assert_eq!(row.time_s, e["time"].as_f64().unwrap());
        assert!((row.time_s - f64::from(f) / 24.0).abs() < 1e-9);
        let k = &e["intrinsic"];
        assert_eq!(row.fx, k[0][0].as_f64().unwrap());
        assert_eq!(row.fy, k[1][1].as_f64().unwrap());
        assert_eq!(row.cx, k[0][2].as_f64().unwrap());
        assert_eq!(row.cy, k[1][2].as_f64().unwrap());
        assert_eq!((row.width, row.height), (100, 100));
        assert_eq!(row.role, if v == 10 { Role::Test } else { Role::Train });
        let c2w = &e["c2w"];
        for i in 0..3 {
            // Camera centre unchanged; OpenCV forward (+z) = OpenGL −z; OpenCV y = OpenGL −y.
            assert_eq!(
                row.world_from_camera[i * 4 + 3],
                c2w[i][3].as_f64().unwrap()
            );
            assert_eq!(
                row.world_from_camera[i * 4 + 2],
                -c2w[i][2].as_f64().unwrap()
            );
            assert_eq!(
                row.world_from_camera[i * 4 + 1],
                -c2w[i][1].as_f64().unwrap()
            );
        }
    }
    // One camera centre, written out: camera 0's position from the JSON.
    let r0 = frames
        .rows
        .iter()
        .find(|r| r.view == 0 && r.frame == 0)
        .unwrap();
    let c = [
        r0.world_from_camera[3],
        r0.world_from_camera[7],
        r0.world_from_camera[11],
    ];
    assert!((c[0] - 1.5428721795140405).abs() < 1e-12 && (c[1] - 0.6779698757234115).abs() < 1e-12);

    // Masks against ground truth, computed here from the written PNGs.
    let mut ious = Vec::new();
    for row in &frames.rows {
        let ours = gray(&entry.join(&row.mask));
        let gt = gray(&fixture().join(format!("gt/masks/m_{}_{}.png", row.view, row.frame)));
        let (mut i, mut u) = (0u32, 0u32);
        for (a, b) in ours.iter().zip(&gt) {
            let (a, b) = (*a >= 128, *b >= 128);
            i += u32::from(a && b);
            u += u32::from(a || b);
        }
        ious.push(f64::from(i) / f64::from(u.max(1)));
        // The camera's plate is copied byte for byte in its decoded pixels.
        let plate = row.plate.as_deref().expect("PAC-NeRF captures have plates");
        assert_eq!(plate, format!("plates/p_{}.png", row.view));
        assert_eq!(
            image::open(entry.join(plate)).unwrap().into_rgb8(),
            image::open(fixture().join(format!("data/r_{}_-1.png", row.view)))
                .unwrap()
                .into_rgb8()
        );
        // The composited image is white wherever the mask is empty.
        let img = image::open(entry.join(&row.image)).unwrap().into_rgb8();
        for (px, m) in img.pixels().zip(&ours) {
            if *m == 0 {
                assert_eq!(px.0, [255, 255, 255]);
            }
        }
    }
    let mean = ious.iter().sum::<f64>() / ious.len() as f64;
    let min = ious.iter().cloned().fold(1.0, f64::min);
    assert!(mean >= 0.965, "mean IoU {mean:.4}");
    assert!(min >= 0.935, "min IoU {min:.4}");
    // The stage reports the same numbers in its metrics.
    let m: Metrics = table::read(&entry.join("metrics.arrow")).unwrap();
    let reported = m
        .rows
        .iter()
        .find(|r| r.metric == "mask_iou_mean")
        .unwrap()
        .value;
    assert!((reported - mean).abs() < 1e-9, "{reported} vs {mean}");
    // Every image has its agreement with the other cameras, in [0, 1], and its consistency,
    // none low enough to be named.
    for (metric, low) in [("mask_agreement", 0.0), ("mask_consistency", 0.9)] {
        let values: Vec<f64> = m
            .rows
            .iter()
            .filter(|r| r.metric == metric)
            .map(|r| r.value)
            .collect();
        assert_eq!(values.len(), frames.rows.len(), "{metric}");
        assert!(
            values.iter().all(|a| (low..=1.0).contains(a)),
            "{metric}: {values:?}"
        );
    }
}

/// Runs `run`'s pipeline with `pipe --quiet run`; it must succeed. Returns its stderr.
fn quiet_run(run: &BuiltinRun) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_pipe"))
        .arg("--workdir")
        .arg(run.dir.path())
        .args(["--quiet", "run"])
        .arg(&run.file)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{stderr}");
    stderr
}

/// `(mean, min)` of the `mask_iou` metrics `ingest` reports for a composite fixture of
/// `images` images, and all per-image values.
fn composite_ious(name: &str, images: usize) -> (f64, f64, Vec<f64>) {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name);
    let (_dir, entry) = ingest(&scene, "[]");
    let m: Metrics = table::read(&entry.unwrap().join("metrics.arrow")).unwrap();
    let get = |k: &str| m.rows.iter().find(|r| r.metric == k).unwrap().value;
    let per_image: Vec<f64> = m
        .rows
        .iter()
        .filter(|r| r.metric == "mask_iou")
        .map(|r| r.value)
        .collect();
    assert_eq!(per_image.len(), images);
    assert!(per_image.iter().all(|v| v.is_finite()), "{per_image:?}");
    (get("mask_iou_mean"), get("mask_iou_min"), per_image)
}

/// A dark grey torus (its levels those of the floor's grout) over the tiled floor, with its
/// shadow, at the sample scenes' 200×200: measured mean 0.9846, min 0.9736 (single-view matte:
/// 0.9778, 0.8900).
#[test]
fn dark_object_over_grout_lines_meets_the_iou_target() {
    let (mean, min, all) = composite_ious("composite-dark-grey", 44);
    assert!(
        mean >= 0.95 && min >= 0.92,
        "mean {mean:.4}, min {min:.4}: {all:?}"
    );
}

/// A torus textured with the floor's colour dimmed to shadow tones (every object pixel over the
/// floor passes the per-pixel shadow test), at the sample scenes' 200×200: measured mean
/// 0.9672, min 0.9222 (single-view matte: 0.0161, 0.0; the multi-view matte before the reach
/// test, the texture term and the witnesses' vote: 0.9426, 0.8807).
#[test]
fn shadow_toned_object_meets_the_iou_target() {
    let (mean, min, all) = composite_ious("composite-shadow-greys", 44);
    assert!(
        mean >= 0.95 && min >= 0.92,
        "mean {mean:.4}, min {min:.4}: {all:?}"
    );
}

/// The cream and pink object over the beige floor (light cream blotches, whose shaded
/// sides fall to the floor's levels, and pale pink; over torus-elastic's plates, 100×100,
/// frames 0, 5, 9 and 13): measured mean 0.9541, min 0.9340 (at 200×200 0.9763 / 0.9633;
/// under lights (−0.5, −1, 0.3) and (0.1, −1, −0.6) 0.957 / 0.934 and 0.956 / 0.923).
#[test]
fn cream_and_pink_object_meets_the_iou_target() {
    let (mean, min, all) = composite_ious("composite-cream", 44);
    assert!(
        mean >= 0.95 && min >= 0.92,
        "mean {mean:.4}, min {min:.4}: {all:?}"
    );
}

/// What the matting does not solve is reported: a plasticine blob in the floor's shadow tones
/// (100×100, light (−0.5, −1, 0.3)) falls, then lies flattened on its own shadow, which no
/// camera sees past it. In the air (frame 0) its masks are found (measured mean 0.975); on the
/// ground (frames 6 and 12) they are torn (0.20 and 0.15), and every torn frame is named in the
/// warning by the masks' low consistency with the other cameras.
#[test]
fn a_shadow_toned_blob_on_its_shadow_is_torn_and_named() {
    let scene =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/composite-blob-shadow-greys");
    let run = BuiltinRun::new(&scene, "[]", "standard", "  ingest: {}\n");
    let stderr = quiet_run(&run);
    let m: Metrics = table::read(&run.entry("ingest").join("metrics.arrow")).unwrap();
    let of = |metric: &str, frame: u16| -> Vec<(u16, f64)> {
        m.rows
            .iter()
            .filter(|r| r.metric == metric && r.frame == Some(frame))
            .map(|r| (r.view.unwrap(), r.value))
            .collect()
    };
    let iou0 = of("mask_iou", 0);
    assert_eq!(iou0.len(), 11);
    let mean0 = iou0.iter().map(|v| v.1).sum::<f64>() / 11.0;
    assert!(mean0 >= 0.95, "frame 0: {iou0:?}");
    assert!(of("mask_consistency", 0).iter().all(|a| a.1 >= 0.9));
    for frame in [6, 12] {
        let torn: Vec<u16> = of("mask_consistency", frame)
            .iter()
            .filter(|a| a.1 < 0.9)
            .map(|a| a.0)
            .collect();
        assert!(torn.len() >= 6, "frame {frame}: {torn:?}");
        assert!(
            stderr.contains("frames 6, 12: at least half of the cameras' masks disagree"),
            "{stderr}"
        );
        for view in torn {
            assert!(
                stderr.contains(&format!("camera {view} frame {frame}:")),
                "camera {view} frame {frame} not named: {stderr}"
            );
        }
    }
}

/// An object of the floor's own hue and brightness (the floor's median colour over the mean
/// shading, 60 %, and pale pink blotches; over torus-elastic's plates, 100×100, frames 0, 5, 9
/// and 13): camouflage no single pixel reveals. The block test (`pipe-matte`'s `score.rs`)
/// finds part of it, but the masks stay torn (measured mean IoU 0.755, min 0.488; 0.609 and
/// 0.379 before the block test). No torn mask passes in silence: every mask under 0.9 IoU
/// against the truth is inconsistent with the other cameras (consistency under 0.92), and all
/// but one of them are named in the warning (measured: 42 under 0.9, 41 named; the one not
/// named, IoU 0.67, scores 0.903).
#[test]
fn a_floor_coloured_object_is_torn_and_its_torn_masks_named() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/composite-floor-tone");
    let run = BuiltinRun::new(&scene, "[]", "standard", "  ingest: {}\n");
    let stderr = quiet_run(&run);
    let m: Metrics = table::read(&run.entry("ingest").join("metrics.arrow")).unwrap();
    let value = |metric: &str, view: u16, frame: u16| -> f64 {
        m.rows
            .iter()
            .find(|r| r.metric == metric && r.view == Some(view) && r.frame == Some(frame))
            .map(|r| r.value)
            .unwrap_or_else(|| panic!("{metric} of camera {view} frame {frame}"))
    };
    let (mut torn, mut named) = (0, 0);
    for frame in [0u16, 5, 9, 13] {
        for view in 0..11u16 {
            let (iou, consistency) = (
                value("mask_iou", view, frame),
                value("mask_consistency", view, frame),
            );
            assert!(
                iou.is_finite() && (0.0..=1.0).contains(&consistency),
                "{iou} {consistency}"
            );
            if iou < 0.9 {
                torn += 1;
                assert!(
                    consistency < 0.92,
                    "camera {view} frame {frame}: IoU {iou}, consistency {consistency}"
                );
                named += usize::from(stderr.contains(&format!("camera {view} frame {frame}:")));
            }
        }
    }
    println!("{named} of the {torn} masks under 0.9 IoU named");
    // Every frame is torn in most cameras, and the warning says what that suggests.
    assert!(
        stderr.contains("frames 0, 5, 9, 13: at least half of the cameras' masks disagree"),
        "{stderr}"
    );
    assert!(
        torn >= 30,
        "{torn} torn: the matte mends this scene now; update the test"
    );
    assert!(named + 1 >= torn, "{named} of {torn} named: {stderr}");
}

#[test]
fn torn_mask_is_reported_by_camera_and_frame() {
    let dir = tempfile::tempdir().unwrap();
    let json: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(fixture().join("all_data.json")).unwrap()).unwrap();
    let keep: Vec<serde_json::Value> = json
        .into_iter()
        .filter(|e| {
            let n = e["file_path"].as_str().unwrap();
            n.ends_with("_-1.png") || n.ends_with("_0.png")
        })
        .collect();
    std::fs::create_dir_all(dir.path().join("data")).unwrap();
    std::fs::create_dir_all(dir.path().join("gt/masks")).unwrap();
    for e in &keep {
        let rel = e["file_path"].as_str().unwrap().trim_start_matches("./");
        std::fs::copy(fixture().join(rel), dir.path().join(rel)).unwrap();
    }
    for v in 0..11 {
        let rel = format!("gt/masks/m_{v}_0.png");
        let mut g = image::open(fixture().join(&rel)).unwrap().into_luma8();
        if v == 3 {
            // Erase the lower half of the object.
            let rows: Vec<u32> = g
                .enumerate_pixels()
                .filter(|p| p.2[0] >= 128)
                .map(|p| p.1)
                .collect();
            let middle = (rows.iter().min().unwrap() + rows.iter().max().unwrap()) / 2;
            for (_, y, p) in g.enumerate_pixels_mut() {
                if y > middle {
                    p.0[0] = 0;
                }
            }
        }
        g.save(dir.path().join(&rel)).unwrap();
    }
    std::fs::write(
        dir.path().join("all_data.json"),
        serde_json::to_string(&keep).unwrap(),
    )
    .unwrap();
    let run = BuiltinRun::new(dir.path(), "[]", "standard", "  ingest: {matte: gt}\n");
    let stderr = quiet_run(&run);
    assert!(
        stderr.contains("warning:") && stderr.contains("camera 3 frame 0"),
        "{stderr}"
    );
    let m: Metrics = table::read(&run.entry("ingest").join("metrics.arrow")).unwrap();
    let agreement: Vec<(u16, f64)> = m
        .rows
        .iter()
        .filter(|r| r.metric == "mask_agreement")
        .map(|r| (r.view.unwrap(), r.value))
        .collect();
    let lowest = agreement.iter().min_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
    assert_eq!(lowest.0, 3, "{agreement:?}");
    // Only the torn mask is named: the other true masks are consistent.
    let consistency: Vec<(u16, f64)> = m
        .rows
        .iter()
        .filter(|r| r.metric == "mask_consistency")
        .map(|r| (r.view.unwrap(), r.value))
        .collect();
    assert_eq!(consistency.len(), 11);
    for (view, c) in &consistency {
        assert_eq!(*view == 3, *c < 0.9, "{consistency:?}");
    }
    assert_eq!(stderr.matches("consistency 0.").count(), 1, "{stderr}");
    assert!(!stderr.contains("at least half of the cameras"), "{stderr}");
}

/// A capture of four cameras around the object (the fixture's cameras 0, 3, 6 and 9, frames 0
/// and 7): the other three cameras' hull is loose, so even true masks agree with it at 0.4–0.8,
/// but as well as consistent masks can: their consistency is 0.95 and more and no mask is
/// named.
#[test]
fn a_four_camera_capture_is_not_warned_about() {
    let dir = subset_copy(
        &["r_0_", "r_3_", "r_6_", "r_9_"],
        &["_-1.png", "_0.png", "_7.png"],
    );
    let run = BuiltinRun::new(dir.path(), "[]", "standard", "  ingest: {}\n");
    let stderr = quiet_run(&run);
    assert!(!stderr.contains("warning:"), "{stderr}");
    let m: Metrics = table::read(&run.entry("ingest").join("metrics.arrow")).unwrap();
    let of = |metric: &str| -> Vec<f64> {
        m.rows
            .iter()
            .filter(|r| r.metric == metric && r.view.is_some())
            .map(|r| r.value)
            .collect()
    };
    let (agreement, consistency) = (of("mask_agreement"), of("mask_consistency"));
    assert_eq!((agreement.len(), consistency.len()), (8, 8));
    println!("four cameras: agreement {agreement:?}, consistency {consistency:?}");
    assert!(
        consistency.iter().all(|c| (0.9..=1.0).contains(c)),
        "{consistency:?}"
    );
}

/// Adds sensor-like noise to 8-bit data: per value the sum of four uniform draws of a fixed
/// hash, scaled to standard deviation `sigma` levels, rounded and clamped.
fn add_noise(data: &mut [u8], sigma: f64, seed: u64) {
    let uniform = |i: u64| {
        let mut h = (i ^ seed.rotate_left(17)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        (h >> 11) as f64 / (1u64 << 53) as f64
    };
    // Four uniforms on [0, 1) sum to mean 2, variance 4/12.
    let scale = sigma / (4.0f64 / 12.0).sqrt();
    for (i, v) in data.iter_mut().enumerate() {
        let n: f64 = (0..4).map(|k| uniform(4 * i as u64 + k)).sum::<f64>() - 2.0;
        *v = (f64::from(*v) + scale * n).round().clamp(0.0, 255.0) as u8;
    }
}

/// The fixture's frames 0, 5, 9 and 13 and plates, each image with its own noise of 3 levels
/// (a camera's frames and a plate shot apart), and their true masks.
fn noisy_copy() -> tempfile::TempDir {
    let frames = ["_-1.png", "_0.png", "_5.png", "_9.png", "_13.png"];
    let dir = subset_copy(&["r_"], &frames);
    std::fs::create_dir_all(dir.path().join("gt/masks")).unwrap();
    let keep: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(dir.path().join("all_data.json")).unwrap()).unwrap();
    for (seed, e) in keep.iter().enumerate() {
        let rel = e["file_path"].as_str().unwrap().trim_start_matches("./");
        let mut img = image::open(dir.path().join(rel)).unwrap().into_rgb8();
        add_noise(&mut img, 3.0, seed as u64);
        img.save(dir.path().join(rel)).unwrap();
        let stem = rel.trim_start_matches("data/r_").trim_end_matches(".png");
        if !stem.ends_with("_-1") {
            let mask = format!("gt/masks/m_{stem}.png");
            std::fs::copy(fixture().join(&mask), dir.path().join(&mask)).unwrap();
        }
    }
    dir
}

/// A camera's noise: the fixture with 3 levels of noise in every frame and plate. The matte
/// measures the noise against each plate and raises its thresholds with it, and the shadow
/// test reads 3×3 block means, so a dark shadow's noisy hue does not make it object: measured
/// mean 0.9558, min 0.9174 (0.7104 and 0.5582 before, the noise-free fixture 0.9691, 0.9418).
#[test]
fn noisy_frames_and_plates_keep_the_masks() {
    let scene = noisy_copy();
    let (_dir, entry) = ingest(scene.path(), "[]");
    let m: Metrics = table::read(&entry.unwrap().join("metrics.arrow")).unwrap();
    let get = |k: &str| m.rows.iter().find(|r| r.metric == k).unwrap().value;
    let n = m.rows.iter().filter(|r| r.metric == "mask_iou").count();
    assert_eq!(n, 44);
    let (mean, min) = (get("mask_iou_mean"), get("mask_iou_min"));
    assert!(mean >= 0.945 && min >= 0.9, "mean {mean:.4}, min {min:.4}");
}

/// A writable copy of the fixture with only cameras 0 and 1, frames 0 and 1.
fn small_copy() -> tempfile::TempDir {
    subset_copy(&["r_0_", "r_1_"], &["_-1.png", "_0.png", "_1.png"])
}

/// A writable copy of the fixture with the images whose names hold one of `cameras` (`r_<cam>_`)
/// and end with one of `frames` (`_<frame>.png`, `_-1.png` for the plates).
fn subset_copy(cameras: &[&str], frames: &[&str]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("data")).unwrap();
    let json: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(fixture().join("all_data.json")).unwrap()).unwrap();
    let keep: Vec<serde_json::Value> = json
        .into_iter()
        .filter(|e| {
            let n = e["file_path"].as_str().unwrap();
            cameras.iter().any(|p| n.contains(p)) && frames.iter().any(|s| n.ends_with(s))
        })
        .collect();
    for e in &keep {
        let rel = e["file_path"].as_str().unwrap().trim_start_matches("./");
        std::fs::copy(fixture().join(rel), dir.path().join(rel)).unwrap();
    }
    std::fs::write(
        dir.path().join("all_data.json"),
        serde_json::to_string(&keep).unwrap(),
    )
    .unwrap();
    dir
}

fn ingest_err(scene: &Path) -> String {
    let (_d, r) = ingest(scene, "[1]");
    r.expect_err("should fail")
}

fn edit_json(dir: &Path, f: impl FnOnce(&mut Vec<serde_json::Value>)) {
    let p = dir.join("all_data.json");
    let mut v: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
}

#[test]
fn small_copy_ingests() {
    let d = small_copy();
    let (_w, r) = ingest(d.path(), "[1]");
    assert!(r.is_ok(), "{:?}", r.err().map(|e| e.to_string()));
}

#[test]
fn missing_image_is_named() {
    let d = small_copy();
    std::fs::remove_file(d.path().join("data/r_1_1.png")).unwrap();
    let e = ingest_err(d.path());
    assert!(
        e.contains("data/r_1_1.png") && e.contains("No such file"),
        "{e}"
    );
}

#[test]
fn image_of_another_size_is_named() {
    let d = small_copy();
    image::RgbImage::new(64, 48)
        .save(d.path().join("data/r_0_1.png"))
        .unwrap();
    let e = ingest_err(d.path());
    assert!(
        e.contains("r_0_1.png: image is 64×48, but the plate of camera 0 is 100×100"),
        "{e}"
    );
}

#[test]
fn camera_without_plate_is_refused() {
    let d = small_copy();
    edit_json(d.path(), |v| {
        v.retain(|e| e["file_path"] != "./data/r_1_-1.png")
    });
    let e = ingest_err(d.path());
    assert!(e.contains("camera 1 has no background plate"), "{e}");
}

#[test]
fn bad_matrices_and_json_are_named() {
    let d = small_copy();
    edit_json(d.path(), |v| v[2]["c2w"][1][3] = serde_json::json!("x"));
    let e = ingest_err(d.path());
    assert!(e.contains("all_data.json") && e.contains("c2w"), "{e}");

    let d = small_copy();
    edit_json(d.path(), |v| {
        v[2]["c2w"] = serde_json::json!([[1, 0, 0, 0], [0, 1, 0, 0]])
    });
    let e = ingest_err(d.path());
    assert!(
        e.contains("field `c2w`: expected a 3×4 or 4×4 matrix, found 2 rows"),
        "{e}"
    );

    let d = small_copy();
    let p = d.path().join("all_data.json");
    let text = std::fs::read_to_string(&p).unwrap();
    // Python's json.dump writes NaN for a non-finite float; that is not JSON.
    let bad = text.replacen("\"time\":0.0", "\"time\":NaN", 1);
    assert_ne!(bad, text);
    std::fs::write(&p, bad).unwrap();
    let e = ingest_err(d.path());
    assert!(e.contains("all_data.json") && e.contains("line 1"), "{e}");

    let d = small_copy();
    edit_json(d.path(), |v| {
        v[0]["intrinsic"][0][0] = serde_json::json!(0.0)
    });
    let e = ingest_err(d.path());
    assert!(
        e.contains("field `intrinsic`: focal lengths must be positive, found fx = 0"),
        "{e}"
    );
}

#[test]
fn four_by_four_poses_are_accepted() {
    let d = small_copy();
    edit_json(d.path(), |v| {
        for e in v.iter_mut() {
            e["c2w"]
                .as_array_mut()
                .unwrap()
                .push(serde_json::json!([0, 0, 0, 1]));
        }
    });
    let (_w, r) = ingest(d.path(), "[1]");
    assert!(r.is_ok(), "{:?}", r.err().map(|e| e.to_string()));
}

#[test]
fn unknown_test_view_is_refused() {
    let d = small_copy();
    let (_w, r) = ingest(d.path(), "[10]");
    let e = r.unwrap_err();
    assert!(
        e.contains("scene.test_views: camera 10 is not in") && e.contains("cameras: 0, 1"),
        "{e}"
    );
}

/// `scale: 0.5` halves every image, plate and mask and the intrinsics with them; the masks stay
/// as good against the (equally resampled) ground truth (measured mean 0.9516, min 0.9149 at
/// 50×50; 0.9680, 0.9406 at 100×100), and the plate is the 2×2 box mean.
#[test]
fn scale_halves_images_intrinsics_and_masks() {
    let run = BuiltinRun::new(
        &fixture(),
        "[10]",
        "standard",
        "  ingest: {scale: 0.5, frames: [0, 7]}\n",
    );
    run.run().unwrap();
    let entry = run.entry("ingest");
    let frames: Frames = table::read(&entry.join("frames.arrow")).unwrap();
    assert_eq!(frames.rows.len(), 11 * 2);
    let json: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(fixture().join("all_data.json")).unwrap()).unwrap();
    for row in &frames.rows {
        assert_eq!((row.width, row.height), (50, 50));
        let e = json
            .iter()
            .find(|e| {
                e["file_path"].as_str().unwrap()
                    == format!("./data/r_{}_{}.png", row.view, row.frame)
            })
            .unwrap();
        let k = &e["intrinsic"];
        assert_eq!(row.fx, k[0][0].as_f64().unwrap() / 2.0);
        assert_eq!(row.cx, k[0][2].as_f64().unwrap() / 2.0);
        assert_eq!(row.cy, k[1][2].as_f64().unwrap() / 2.0);
        let img = image::open(entry.join(&row.image)).unwrap().into_rgb8();
        assert_eq!(img.dimensions(), (50, 50));
    }
    // The plate: each pixel the rounded mean of its 2×2 block.
    let full = image::open(fixture().join("data/r_3_-1.png"))
        .unwrap()
        .into_rgb8();
    let half = image::open(entry.join("plates/p_3.png"))
        .unwrap()
        .into_rgb8();
    for (x, y, px) in half.enumerate_pixels() {
        for c in 0..3 {
            let s: u32 = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .map(|(dx, dy)| u32::from(full.get_pixel(2 * x + dx, 2 * y + dy)[c]))
                .sum();
            assert_eq!(u32::from(px[c]), (s + 2) / 4, "({x}, {y})");
        }
    }
    let m: Metrics = table::read(&entry.join("metrics.arrow")).unwrap();
    let get = |k: &str| m.rows.iter().find(|r| r.metric == k).unwrap().value;
    let (mean, min) = (get("mask_iou_mean"), get("mask_iou_min"));
    eprintln!("mask IoU at half size: mean {mean:.4}, min {min:.4}");
    assert!(
        mean >= 0.93 && min >= 0.85,
        "IoU at half size: mean {mean:.4}, min {min:.4}"
    );
    // Out of range is refused, naming the key.
    let bad = BuiltinRun::new(&fixture(), "[10]", "standard", "  ingest: {scale: 1.5}\n");
    let e = bad.run().unwrap_err();
    assert!(e.contains("scale") && e.contains("1.5"), "{e}");
}

/// `max_size` caps the longest side (the presets set it: a 100×100 capture is left alone by
/// `draft`'s 200); it combines with `scale`; below 16 pixels it is refused by name.
#[test]
fn max_size_caps_the_longest_side_and_presets_leave_small_captures_alone() {
    let size = |preset: &str, ingest: &str| {
        let run = BuiltinRun::new(&fixture(), "[10]", preset, ingest);
        run.run().unwrap();
        let frames: Frames = table::read(&run.entry("ingest").join("frames.arrow")).unwrap();
        let r = &frames.rows[0];
        let img = image::open(run.entry("ingest").join(&r.image))
            .unwrap()
            .into_rgb8();
        assert_eq!(img.dimensions(), (r.width, r.height));
        (r.width, r.height, r.fx)
    };
    let json: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(fixture().join("all_data.json")).unwrap()).unwrap();
    let fx = json[0]["intrinsic"][0][0].as_f64().unwrap();
    let (w, h, f) = size("draft", "  ingest: {frames: [0]}\n");
    assert_eq!((w, h), (100, 100));
    assert_eq!(f, fx);
    let (w, h, f) = size("draft", "  ingest: {frames: [0], max_size: 60}\n");
    assert_eq!((w, h), (60, 60));
    assert!((f - 0.6 * fx).abs() < 1e-9 * fx, "{f} against {fx}");
    let (w, h, _) = size(
        "draft",
        "  ingest: {frames: [0], scale: 0.5, max_size: 40}\n",
    );
    assert_eq!((w, h), (40, 40));
    let (w, h, _) = size("paper", "  ingest: {frames: [0], scale: 0.5}\n");
    assert_eq!((w, h), (50, 50));
    let bad = BuiltinRun::new(&fixture(), "[10]", "draft", "  ingest: {max_size: 8}\n");
    let e = bad.run().unwrap_err();
    assert!(e.contains("max_size") && e.contains('8'), "{e}");
}
