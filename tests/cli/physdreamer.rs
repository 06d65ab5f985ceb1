//! The PhysDreamer layout (issue 25, check 3): `tests/fixtures/physdreamer-leaf` (made by
//! `datasets-tools physdreamer`) ingests through `pipelines/physdreamer-leaf.yaml`, and under a
//! force only the moving part (the leaf) moves: every other Gaussian is bit-identical in every
//! frame's PLY. Malformed or inconsistent files are errors naming the file, field and value.

use std::path::{Path, PathBuf};

use glam::DVec3;
use pipe::pipeline::progress::{Mode, Reporter};
use pipe::pipeline::runner::{RunOptions, Workspace};
use pipe::pipeline::spec::{self, Overrides, Pipeline};
use pipe::scene::frames::Frames;
use pipe::scene::gaussians::Gaussians;
use serde_json::Value;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fixture() -> PathBuf {
    repo().join("tests/fixtures/physdreamer-leaf")
}

/// Loads `file` with `sets` and runs it (up to `until`) in `workdir`; the error as the CLI
/// prints it.
fn run(
    file: &Path,
    workdir: &Path,
    sets: &[&str],
    until: Option<&str>,
) -> Result<Pipeline, String> {
    let reg = pipe::stages::builtin();
    let overrides = Overrides {
        preset: None,
        sets: sets.iter().map(|s| s.to_string()).collect(),
    };
    let p = spec::load(file, &reg, &overrides).map_err(|e| e.to_string())?;
    Workspace::new(workdir)
        .run(
            &p,
            &reg,
            &RunOptions {
                until: until.map(String::from),
                ..Default::default()
            },
            &Reporter::new(Mode::Quiet),
            &std::sync::atomic::AtomicBool::new(false),
            "test",
        )
        .map_err(|e| e.to_string())?;
    Ok(p)
}

fn entry(p: &Pipeline, workdir: &Path, stage: &str) -> PathBuf {
    Workspace::new(workdir)
        .cached_entry(p, &pipe::stages::builtin(), stage)
        .unwrap()
}

/// The construction of the fixture: the leaf is the Gaussians with |x| ≤ 1.5 cm above the pot
/// (y > 0.10 m), the stone those beyond x = 0.12 m.
fn is_leaf(p: [f32; 3]) -> bool {
    p[0].abs() <= 0.015 && p[1] > 0.10
}

/// Every field of Gaussian `i` of `a` equals Gaussian `j` of `b`, bit for bit.
fn same_gaussian(a: &Gaussians, i: usize, b: &Gaussians, j: usize) -> bool {
    let k = a.sh.len() / a.len();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    bits(&a.position[i]) == bits(&b.position[j])
        && bits(&a.log_scale[i]) == bits(&b.log_scale[j])
        && bits(&a.rotation[i]) == bits(&b.rotation[j])
        && a.opacity_logit[i].to_bits() == b.opacity_logit[j].to_bits()
        && bits(&a.sh[i * k..(i + 1) * k]) == bits(&b.sh[j * k..(j + 1) * k])
}

/// Check 3: the fixture ingests (cameras, frames, masks, the trained Gaussians with exactly the
/// leaf simulated), and the pipeline's `flick` edit (0.4 N along +x on the leaf's top for
/// 0.25 s, no gravity, the leaf clamped by a sticky box over the pot) moves only the leaf:
/// the pot's and the stone's 1 584 Gaussians are bit-identical in all 13 frames' PLYs, the
/// leaf's top layer moves at least 4 cm along +x (measured 6.3 cm), its clamped
/// foot less than 1 mm (measured 2 µm).
#[test]
fn the_physdreamer_fixture_ingests_and_under_a_force_only_the_leaf_moves() {
    let dir = tempfile::tempdir().unwrap();
    let file = repo().join("pipelines/physdreamer-leaf.yaml");
    let p = run(&file, dir.path(), &["edit.flick.frames=13"], None).unwrap();

    // Cameras and frames: 4 cameras with videos (the 5th has none) × 6 frames at 24 fps.
    let ingest = entry(&p, dir.path(), "ingest");
    let frames: Frames = pipe::scene::table::read(&ingest.join("frames.arrow")).unwrap();
    assert_eq!(frames.rows.len(), 4 * 6);
    let transforms: Value = serde_json::from_str(
        &std::fs::read_to_string(fixture().join("transforms_train.json")).unwrap(),
    )
    .unwrap();
    let fov = transforms["camera_angle_x"].as_f64().unwrap();
    for r in &frames.rows {
        assert!(r.view < 4 && r.frame < 6);
        assert_eq!(r.time_s, f64::from(r.frame) / 24.0);
        assert_eq!(r.plate, None);
        assert_eq!((r.width, r.height), (80, 80));
        assert!((r.fx - 40.0 / (0.5 * fov).tan()).abs() < 1e-9, "{}", r.fx);
        assert_eq!((r.cx, r.cy), (40.0, 40.0));
        // OpenGL c2w → OpenCV: the camera's y and z axes negated, the centre kept.
        let m = &transforms["frames"][usize::from(r.view)]["transform_matrix"];
        for i in 0..3 {
            let gl = |j: usize| m[i][j].as_f64().unwrap();
            let cv = &r.world_from_camera[i * 4..i * 4 + 4];
            assert_eq!([cv[0], cv[1], cv[2], cv[3]], [gl(0), -gl(1), -gl(2), gl(3)]);
        }
        // The masks are the dataset's; outside them the image is the white background.
        let mask = image::open(ingest.join(&r.mask)).unwrap().into_luma8();
        let want =
            image::open(fixture().join(format!("masks/frame_{:05}/{:05}.png", r.view, r.frame)))
                .unwrap()
                .into_luma8();
        assert_eq!(mask.as_raw(), want.as_raw());
        let img = image::open(ingest.join(&r.image)).unwrap().into_rgb8();
        for (px, m) in img.pixels().zip(mask.pixels()) {
            if m.0[0] == 0 {
                assert_eq!(px.0, [255, 255, 255]);
            }
        }
    }

    // The trained Gaussians, exactly the leaf simulated; `init` passes them on unchanged.
    let g: Gaussians = pipe::scene::table::read(&ingest.join("gaussians.arrow")).unwrap();
    assert_eq!(g.len(), 2151);
    for (x, s) in g.position.iter().zip(&g.simulated) {
        assert_eq!(*s, is_leaf(*x), "{x:?}");
    }
    let init: Gaussians =
        pipe::scene::table::read(&entry(&p, dir.path(), "init").join("gaussians.arrow")).unwrap();
    assert_eq!(init, g);
    // The cameras see the object where its masks are: ≥ 95 % of the object's Gaussian centres
    // project inside frame 0's mask in every view.
    for r in frames.rows.iter().filter(|r| r.frame == 0) {
        let cam = pipe::scene::camera::Camera::from_row(r);
        let mask = image::open(ingest.join(&r.mask)).unwrap().into_luma8();
        let object: Vec<DVec3> = g
            .position
            .iter()
            .filter(|p| p[0] < 0.1)
            .map(|p| DVec3::from_array(p.map(f64::from)))
            .collect();
        let inside = object
            .iter()
            .filter(|x| {
                cam.pixel(**x)
                    .is_some_and(|(u, v)| mask.get_pixel(u, v).0[0] == 255)
            })
            .count();
        assert!(
            inside as f64 >= 0.95 * object.len() as f64,
            "view {}: {inside} of {}",
            r.view,
            object.len()
        );
    }

    // The edit: the held Gaussians follow the simulated ones in each PLY, in their order.
    let edit = entry(&p, dir.path(), "edit.flick");
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(edit.join("edit.json")).unwrap()).unwrap();
    assert_eq!(report["applied"]["gaussians"], 567);
    assert_eq!(report["applied"]["fixed_gaussians"], 1584);
    let moving: Vec<usize> = (0..g.len()).filter(|&i| g.simulated[i]).collect();
    let held: Vec<usize> = (0..g.len()).filter(|&i| !g.simulated[i]).collect();
    let top: Vec<usize> = (0..moving.len())
        .filter(|&k| g.position[moving[k]][1] > 0.30)
        .collect();
    let foot: Vec<usize> = (0..moving.len())
        .filter(|&k| g.position[moving[k]][1] < 0.11)
        .collect();
    assert!(!top.is_empty() && !foot.is_empty());
    let (mut peak_top, mut peak_foot) = (0.0f64, 0.0f64);
    for f in 0..13 {
        let s =
            pipe::io::ply::read_gaussians(&edit.join(format!("splats/splats_{f:04}.ply"))).unwrap();
        assert_eq!(s.len(), g.len());
        for (k, &i) in held.iter().enumerate() {
            assert!(
                same_gaussian(&s, moving.len() + k, &g, i),
                "frame {f}: held Gaussian {i} changed"
            );
        }
        let dx = |k: usize| f64::from(s.position[k][0] - g.position[moving[k]][0]);
        let mean = |ks: &[usize]| ks.iter().map(|&k| dx(k)).sum::<f64>() / ks.len() as f64;
        assert!(s.position.iter().flatten().all(|v| v.is_finite()));
        peak_top = peak_top.max(mean(&top));
        peak_foot = peak_foot.max(foot.iter().map(|&k| dx(k).abs()).fold(0.0, f64::max));
    }
    println!("leaf top: peak mean x displacement {peak_top:.4} m; clamped foot: {peak_foot:.2e} m");
    assert!(peak_top >= 0.04, "the leaf's top moved {peak_top} m");
    assert!(
        peak_foot < 1e-3,
        "the leaf's clamped foot moved {peak_foot} m"
    );
}

/// Copies the fixture into `dir/scene` and writes `dir/p.yaml` reading it with `stages`.
fn scene_copy(dir: &Path, stages: &str) -> PathBuf {
    let dst = dir.join("scene");
    let mut stack = vec![fixture()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let to = dst.join(p.strip_prefix(fixture()).unwrap());
            if p.is_dir() {
                stack.push(p);
            } else {
                std::fs::create_dir_all(to.parent().unwrap()).unwrap();
                std::fs::copy(&p, &to).unwrap();
            }
        }
    }
    let file = dir.join("p.yaml");
    std::fs::write(
        &file,
        format!(
            "name: t\nscene:\n  dataset: physdreamer\n  path: scene\npreset: draft\nstages:\n{stages}"
        ),
    )
    .unwrap();
    file
}

/// Malformed or inconsistent files: the error names the file, the field and the value.
#[test]
fn malformed_physdreamer_files_name_the_file_field_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let file = scene_copy(
        dir.path(),
        "  ingest: {matte: gt}\n  init: {source: dataset}\n",
    );
    let scene = dir.path().join("scene");
    let ingest = |what: &str| {
        let e = run(&file, dir.path(), &[], Some("ingest")).expect_err(what);
        assert!(
            e.contains(&scene.display().to_string()),
            "{what}: the message names no file of the scene: {e}"
        );
        e
    };
    let transforms = scene.join("transforms_train.json");
    let original = std::fs::read_to_string(&transforms).unwrap();
    let edit_json = |f: &dyn Fn(&mut Value)| {
        let mut v: Value = serde_json::from_str(&original).unwrap();
        f(&mut v);
        std::fs::write(&transforms, v.to_string()).unwrap();
    };

    // A camera matrix of the wrong shape.
    edit_json(&|v| {
        v["frames"][1]["transform_matrix"] = serde_json::json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    });
    let e = ingest("matrix shape");
    assert!(
        e.contains("transforms_train.json: `frames[1].transform_matrix`: expected a 3×4 or 4×4 matrix, found 3 rows of lengths [3, 3, 3]"),
        "{e}"
    );
    // No intrinsics.
    edit_json(&|v| {
        v.as_object_mut().unwrap().remove("camera_angle_x");
    });
    let e = ingest("no intrinsics");
    assert!(
        e.contains("transforms_train.json: `camera_angle_x`: missing (for camera 0)"),
        "{e}"
    );
    // A field of view that is not one.
    edit_json(&|v| v["frames"][2]["camera_angle_x"] = serde_json::json!(4.0));
    let e = ingest("angle");
    assert!(
        e.contains("`frames[2].camera_angle_x`: 4: a field of view in radians must be in (0, π)"),
        "{e}"
    );
    // `w` that disagrees with the frames.
    edit_json(&|v| v["w"] = serde_json::json!(100));
    let e = ingest("w");
    assert!(
        e.contains("`w`: 100 pixels, but the frames of camera 0 are 80×80"),
        "{e}"
    );
    // Cameras whose videos do not start together.
    edit_json(&|v| v["frames"][3]["time"] = serde_json::json!(0.5));
    let e = ingest("time");
    assert!(
        e.contains("`frames[3].time`: 0.5 s, but camera `frame_00000` starts at 0 s"),
        "{e}"
    );
    // No cameras at all.
    std::fs::remove_file(&transforms).unwrap();
    let e = ingest("no cameras");
    assert!(
        e.contains("no cameras: neither transforms_train.json nor sparse/0/ exists"),
        "{e}"
    );
    std::fs::write(&transforms, &original).unwrap();

    // Frame counts that differ between cameras.
    let dropped = scene.join("videos/frame_00002/00005.png");
    let kept = std::fs::read(&dropped).unwrap();
    std::fs::remove_file(&dropped).unwrap();
    let e = ingest("frame counts");
    assert!(
        e.contains("videos/frame_00002: 5 frames, but ") && e.contains("videos/frame_00000 has 6"),
        "{e}"
    );
    std::fs::write(&dropped, kept).unwrap();

    // A moving-part point far from every Gaussian, one outside the object, a PLY that is none.
    let moving = scene.join("moving_part_points.ply");
    let pts = pipe::io::ply::read_points(&moving).unwrap().positions;
    let mut far = pts.clone();
    far[3][1] += 1.0;
    pipe::io::ply::write_points(&moving, &far, None).unwrap();
    let e = ingest("far point");
    assert!(
        e.contains("moving_part_points.ply: point 3 at (")
            && e.contains("m from the nearest Gaussian, beyond the reach 0.0225 m (1.5 × the points' spacing 0.0150 m)")
            && e.contains("point_cloud.ply"),
        "{e}"
    );
    let mut stone = pts.clone();
    stone[5] = [0.15, 0.02, 0.0];
    pipe::io::ply::write_points(&moving, &stone, None).unwrap();
    let e = ingest("moving point in the clutter");
    assert!(
        e.contains("moving_part_points.ply: point 5 at (0.1500, 0.0200, 0.0000) m is not part of the object")
            && e.contains("clean_object_points.ply"),
        "{e}"
    );
    std::fs::write(&moving, "hello\n").unwrap();
    let e = ingest("not a PLY");
    assert!(e.contains("moving_part_points.ply: not a PLY file"), "{e}");
    pipe::io::ply::write_points(&moving, &pts, None).unwrap();

    // No trained Gaussians.
    let cloud = scene.join("point_cloud.ply");
    std::fs::rename(&cloud, dir.path().join("cloud.ply")).unwrap();
    let e = ingest("no point cloud");
    assert!(e.contains("point_cloud.ply: missing"), "{e}");
    std::fs::rename(dir.path().join("cloud.ply"), &cloud).unwrap();

    // Plate matting without plates.
    let e = run(&file, dir.path(), &["ingest.matte=plate"], Some("ingest")).unwrap_err();
    assert!(
        e.contains("stages.ingest.matte: `plate` mattes against background plates, and the physdreamer layout"),
        "{e}"
    );
    // The scene as shipped ingests; `source: dataset` takes no path.
    run(&file, dir.path(), &[], Some("init")).unwrap();
    let e = run(&file, dir.path(), &["init.path=x.ply"], Some("init")).unwrap_err();
    assert!(e.contains("path"), "{e}");
}

/// Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method).
fn quaternion(r: [[f64; 3]; 3]) -> [f64; 4] {
    let t = r[0][0] + r[1][1] + r[2][2];
    if t > 0.0 {
        let s = 2.0 * (1.0 + t).sqrt();
        [
            0.25 * s,
            (r[2][1] - r[1][2]) / s,
            (r[0][2] - r[2][0]) / s,
            (r[1][0] - r[0][1]) / s,
        ]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = 2.0 * (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt();
        [
            (r[2][1] - r[1][2]) / s,
            0.25 * s,
            (r[0][1] + r[1][0]) / s,
            (r[0][2] + r[2][0]) / s,
        ]
    } else if r[1][1] > r[2][2] {
        let s = 2.0 * (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt();
        [
            (r[0][2] - r[2][0]) / s,
            (r[0][1] + r[1][0]) / s,
            0.25 * s,
            (r[1][2] + r[2][1]) / s,
        ]
    } else {
        let s = 2.0 * (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt();
        [
            (r[1][0] - r[0][1]) / s,
            (r[0][2] + r[2][0]) / s,
            (r[1][2] + r[2][1]) / s,
            0.25 * s,
        ]
    }
}

/// The same cameras as a COLMAP text model in `sparse/0` (no `transforms_train.json`) ingest
/// to the same frames (poses within 1e-12, intrinsics exactly); a distorted camera model is
/// refused by name.
#[test]
fn colmap_cameras_ingest_as_the_blender_ones() {
    let dir = tempfile::tempdir().unwrap();
    let file = scene_copy(dir.path(), "  ingest: {matte: gt}\n");
    let blender = run(&file, dir.path(), &[], None).unwrap();
    let want: Frames =
        pipe::scene::table::read(&entry(&blender, dir.path(), "ingest").join("frames.arrow"))
            .unwrap();
    let scene = dir.path().join("scene");
    std::fs::remove_file(scene.join("transforms_train.json")).unwrap();
    let sparse = scene.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    let r0 = &want.rows[0];
    let cameras = |model: &str| {
        format!(
            "# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n1 {model} 80 80 {} {} {} {}\n",
            r0.fx, r0.fy, r0.cx, r0.cy
        )
    };
    std::fs::write(sparse.join("cameras.txt"), cameras("PINHOLE")).unwrap();
    let mut images = String::new();
    // Listed out of order: views are numbered by image name.
    for r in want.rows.iter().filter(|r| r.frame == 0).rev() {
        let m = &r.world_from_camera;
        // cam_from_world: R = R_wcᵀ, t = −R·c.
        let rot: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[j * 4 + i]));
        let c = [m[3], m[7], m[11]];
        let t: [f64; 3] = std::array::from_fn(|i| -(0..3).map(|j| rot[i][j] * c[j]).sum::<f64>());
        let q = quaternion(rot);
        images += &format!(
            "{} {} {} {} {} {} {} {} 1 frame_{:05}.png\n\n",
            r.view + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t[0],
            t[1],
            t[2],
            r.view
        );
    }
    std::fs::write(sparse.join("images.txt"), images).unwrap();
    std::fs::write(sparse.join("points3D.txt"), "# no points\n").unwrap();
    let colmap = run(&file, dir.path(), &[], None).unwrap();
    let got: Frames =
        pipe::scene::table::read(&entry(&colmap, dir.path(), "ingest").join("frames.arrow"))
            .unwrap();
    assert_eq!(got.rows.len(), want.rows.len());
    for (a, b) in got.rows.iter().zip(&want.rows) {
        assert_eq!((a.view, a.frame, a.time_s), (b.view, b.frame, b.time_s));
        assert_eq!([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy]);
        for (x, y) in a.world_from_camera.iter().zip(&b.world_from_camera) {
            assert!((x - y).abs() < 1e-12, "view {}: {x} vs {y}", a.view);
        }
    }
    std::fs::write(
        sparse.join("cameras.txt"),
        cameras("OPENCV").replace("\n1 OPENCV 80 80", "\n1 OPENCV 80 80 0 0 0 0"),
    )
    .unwrap();
    let e = run(&file, dir.path(), &[], None).unwrap_err();
    assert!(
        e.contains("sparse/0/cameras.txt: `camera 1`: model OPENCV: only undistorted PINHOLE or SIMPLE_PINHOLE cameras are read"),
        "{e}"
    );
}

/// A still capture (one frame per camera) gives no frame interval: an edit without
/// `frame_dt` is refused naming the field, one with it runs.
#[test]
fn a_single_frame_capture_edits_with_its_stated_frame_dt() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |dt: &str| {
        format!(
            "  ingest: {{matte: gt}}\n  init: {{source: dataset}}\n  edit:\n    push:\n      \
             material: {{family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3}}\n      \
             gravity: [0, 0, 0]\n      boundaries: [{{kind: box, min: [-0.07, -0.01, -0.07], max: [0.07, 0.11, 0.07]}}]\n      \
             interactions: [{{kind: force, select: {{box: {{min: [-0.02, 0.26, -0.05], max: [0.02, 0.32, 0.05]}}}}, force: [0.4, 0, 0], start: 0.0}}]\n      \
             frames: 3\n{dt}      cameras: [{{view: 0}}]\n"
        )
    };
    let file = scene_copy(dir.path(), &edit(""));
    for kind in ["videos", "masks"] {
        for view in 0..4 {
            for frame in 1..6 {
                std::fs::remove_file(
                    dir.path()
                        .join(format!("scene/{kind}/frame_{view:05}/{frame:05}.png")),
                )
                .unwrap();
            }
        }
    }
    let e = run(&file, dir.path(), &[], None).unwrap_err();
    assert!(
        e.contains("stages.edit.push.frame_dt: the capture has a single frame"),
        "{e}"
    );
    let p = run(&file, dir.path(), &["edit.push.frame_dt=0.02"], None).unwrap();
    let report: Value = serde_json::from_str(
        &std::fs::read_to_string(entry(&p, dir.path(), "edit.push").join("edit.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        report["applied"]["frame_dt_s"].as_f64(),
        Some(0.02),
        "{report}"
    );
}

/// Cameras whose frames are one video file each (`videos/<view>.mp4`, as PhysDreamer's
/// generated videos are) ingest to the same frames as the PNG folders they were encoded
/// from (lossless H.264 RGB, 24 frames/s: the rate comes from the videos, the camera file
/// gives none), masks from `masks/<view>/`; without FFmpeg on PATH the error says what to
/// install or do.
#[test]
fn mp4_videos_ingest_as_their_png_frames() {
    let dir = tempfile::tempdir().unwrap();
    let stages = "  ingest: {matte: gt}\n  init: {source: dataset}\n";
    let pngs = dir.path().join("pngs");
    std::fs::create_dir_all(&pngs).unwrap();
    let png_file = scene_copy(&pngs, stages);
    let mp4s = dir.path().join("mp4s");
    std::fs::create_dir_all(&mp4s).unwrap();
    let mp4_file = scene_copy(&mp4s, stages);
    for view in 0..4 {
        let folder = mp4s.join(format!("scene/videos/frame_{view:05}"));
        let out = std::process::Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-nostdin", "-y"])
            .args(["-framerate", "24", "-i"])
            .arg(folder.join("%05d.png"))
            .args(["-c:v", "libx264rgb", "-qp", "0", "-pix_fmt", "rgb24"])
            .arg(folder.with_extension("mp4"))
            .output()
            .expect("ffmpeg on PATH (CI installs it)");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        std::fs::remove_dir_all(&folder).unwrap();
    }
    let a = run(&png_file, &pngs, &[], Some("ingest")).unwrap();
    let b = run(&mp4_file, &mp4s, &[], Some("ingest")).unwrap();
    let (ea, eb) = (entry(&a, &pngs, "ingest"), entry(&b, &mp4s, "ingest"));
    let fa: Frames = pipe::scene::table::read(&ea.join("frames.arrow")).unwrap();
    let fb: Frames = pipe::scene::table::read(&eb.join("frames.arrow")).unwrap();
    assert_eq!(fa.rows.len(), 24);
    assert_eq!(fa.rows, fb.rows);
    for r in &fa.rows {
        for rel in [&r.image, &r.mask] {
            let (x, y) = (
                std::fs::read(ea.join(rel)).unwrap(),
                std::fs::read(eb.join(rel)).unwrap(),
            );
            assert!(x == y, "{rel} differs between the PNG and MP4 ingests");
        }
    }

    // Without FFmpeg.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_pipe"))
        .args(["--quiet", "--workdir"])
        .arg(&mp4s)
        .args(["run", "--force", "ingest", "--until", "ingest"])
        .arg(&mp4_file)
        .env("PATH", "")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("frame_00000.mp4")
            && stderr.contains("reading videos needs `ffprobe` (FFmpeg) on PATH"),
        "{stderr}"
    );
}

/// Without a declared clamp, the edit anchors the leaf where it meets the pot (`anchor`, on by
/// default): under the push its top bends while its foot stays; with `anchor: false` the
/// whole leaf slides away.
#[test]
fn the_moving_part_is_anchored_to_the_still_object_without_a_declared_clamp() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |name: &str, anchor: bool| {
        format!(
            "    {name}:\n      material: {{family: elastic, youngs_modulus: 2.0e4, poisson_ratio: 0.3}}\n      \
             gravity: [0, 0, 0]\n      boundaries: [{{kind: ground}}]\n      anchor: {anchor}\n      \
             interactions: [{{kind: force, select: {{box: {{min: [-0.02, 0.26, -0.05], max: [0.02, 0.32, 0.05]}}}}, force: [0.4, 0, 0], start: 0.0, end: 0.25}}]\n      \
             frames: 9\n      cameras: []\n"
        )
    };
    let file = scene_copy(
        dir.path(),
        &format!(
            "  ingest: {{matte: gt}}\n  init: {{source: dataset}}\n  edit:\n{}{}",
            edit("held", true),
            edit("free", false)
        ),
    );
    let p = run(&file, dir.path(), &[], None).unwrap();
    let g: Gaussians =
        pipe::scene::table::read(&entry(&p, dir.path(), "init").join("gaussians.arrow")).unwrap();
    let moving: Vec<usize> = (0..g.len()).filter(|&i| g.simulated[i]).collect();
    let pick = |lo: f32, hi: f32| -> Vec<usize> {
        (0..moving.len())
            .filter(|&k| (lo..hi).contains(&g.position[moving[k]][1]))
            .collect()
    };
    let (top, foot) = (pick(0.30, 1.0), pick(0.0, 0.11));
    assert!(!top.is_empty() && !foot.is_empty());
    let peaks = |name: &str| {
        let dir = entry(&p, dir.path(), name);
        let (mut top_peak, mut foot_peak) = (0.0f64, 0.0f64);
        for f in 0..9 {
            let s = pipe::io::ply::read_gaussians(&dir.join(format!("splats/splats_{f:04}.ply")))
                .unwrap();
            let dx = |k: usize| f64::from(s.position[k][0] - g.position[moving[k]][0]);
            let mean = |ks: &[usize]| ks.iter().map(|&k| dx(k)).sum::<f64>() / ks.len() as f64;
            top_peak = top_peak.max(mean(&top));
            foot_peak = foot_peak.max(mean(&foot).abs());
        }
        let report: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("edit.json")).unwrap()).unwrap();
        (top_peak, foot_peak, report)
    };
    let (top_held, foot_held, report) = peaks("edit.held");
    let (top_free, foot_free, _) = peaks("edit.free");
    println!(
        "anchored: top {top_held:.4} m, foot {foot_held:.2e} m; free: top {top_free:.4} m, foot {foot_free:.4} m"
    );
    assert!(
        report["applied"]["boundaries"]
            .as_array()
            .unwrap()
            .iter()
            .any(|b| b
                .as_str()
                .unwrap()
                .starts_with("anchor: the grid next to 1584 Gaussians")),
        "{}",
        report["applied"]["boundaries"]
    );
    assert!(top_held > 0.02, "anchored top moved {top_held} m");
    assert!(foot_held < 2e-3, "anchored foot moved {foot_held} m");
    assert!(
        foot_free > 5.0 * foot_held.max(1e-4),
        "free foot moved {foot_free} m"
    );
}
