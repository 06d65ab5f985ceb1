//! `pipe render` reads only the entries of the camera it renders: a camera file with one entry
//! and no background plate renders. The output size is the camera's image size when its image
//! file exists; `--size WxH` sets it without touching the intrinsics; with neither, the size is
//! unknown and the command says so (naming `--size`) instead of guessing it from the principal
//! point.

use std::path::{Path, PathBuf};

use glam::DVec3;
use pipe::io::ply;
use pipe::preview::{self, OutputSize, PreviewRequest};
use pipe::scene::gaussians::Gaussians;
use serde_json::json;

use crate::support::fixture_scene;

/// One white, nearly opaque Gaussian of 5 cm standard deviation at `centre` (m), as a 3DGS PLY.
fn one_gaussian(dir: &Path, centre: DVec3) -> PathBuf {
    let white_dc = 0.5 / 0.282_094_8;
    let g = Gaussians {
        sh_degree: 0,
        id: vec![0],
        position: vec![centre.as_vec3().to_array()],
        log_scale: vec![[0.05f32.ln(); 3]],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]],
        opacity_logit: vec![5.0],
        sh: vec![white_dc; 3],
        simulated: vec![true],
    };
    let path = dir.join("one.ply");
    ply::write_gaussians(&path, &g).unwrap();
    path
}

/// A camera file of one entry (`./data/r_0_0.png`, no plate listed): camera 0 at the origin
/// looking down −z (OpenGL axes, as PAC-NeRF writes them), fx = fy = 100 px, principal point
/// `(cx, cy)`.
fn one_entry_file(dir: &Path, cx: f64, cy: f64) -> PathBuf {
    let entry = json!([{
        "file_path": "./data/r_0_0.png",
        "time": 0.0,
        "c2w": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
        "intrinsic": [[100.0, 0.0, cx], [0.0, 100.0, cy], [0.0, 0.0, 1.0]],
    }]);
    let path = dir.join("all_data.json");
    std::fs::write(&path, serde_json::to_string_pretty(&entry).unwrap()).unwrap();
    path
}

/// `pipe render` with `args` after the PLY; returns the exit code.
fn render_cli(ply: &Path, args: &[&str]) -> u8 {
    pipe::cli::run(
        ["pipe", "render", ply.to_str().unwrap()]
            .into_iter()
            .chain(args.iter().copied()),
        pipe::stages::builtin(),
    )
}

/// The red-weighted centroid of the image in continuous pixel coordinates (pixel `(i, j)`
/// covers `[i, i + 1) × [j, j + 1)`) and the largest red value.
fn centroid(img: &image::RgbImage) -> ((f64, f64), u8) {
    let (mut sx, mut sy, mut sw, mut best) = (0.0, 0.0, 0.0, 0);
    for (x, y, p) in img.enumerate_pixels() {
        let w = f64::from(p.0[0]);
        sx += w * (f64::from(x) + 0.5);
        sy += w * (f64::from(y) + 0.5);
        sw += w;
        best = best.max(p.0[0]);
    }
    ((sx / sw, sy / sw), best)
}

/// Asserts the single Gaussian is drawn and centred on `(x, y)` (to 0.05 px).
fn assert_centred(img: &image::RgbImage, (x, y): (f64, f64)) {
    let ((cx, cy), best) = centroid(img);
    assert!(best > 200, "the Gaussian is drawn (brightest {best})");
    assert!(
        (cx - x).abs() < 0.05 && (cy - y).abs() < 0.05,
        "centred on ({cx:.3}, {cy:.3}), expected ({x}, {y})"
    );
}

/// The case: a camera file listing camera 3's frame-0 image and no plate renders, at
/// that image's size (100×100), and the Gaussian placed on the camera's optical axis is
/// centred on the principal point (50, 50).
#[test]
fn a_camera_file_without_plates_renders_at_its_image_size() {
    let tmp = tempfile::tempdir().unwrap();
    let all: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture_scene().join("all_data.json")).unwrap(),
    )
    .unwrap();
    let entry = all
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["file_path"] == "./data/r_3_0.png")
        .unwrap()
        .clone();
    let cams = tmp.path().join("all_data.json");
    std::fs::write(&cams, serde_json::to_string(&json!([entry])).unwrap()).unwrap();
    std::fs::create_dir_all(tmp.path().join("data")).unwrap();
    std::fs::copy(
        fixture_scene().join("data/r_3_0.png"),
        tmp.path().join("data/r_3_0.png"),
    )
    .unwrap();
    // 1.5 m in front of the camera: OpenGL cameras look down their −z column.
    let c2w = &entry["c2w"];
    let col = |j: usize| DVec3::from_array([0, 1, 2].map(|i| c2w[i][j].as_f64().unwrap()));
    let ply = one_gaussian(tmp.path(), col(3) - 1.5 * col(2));
    let out = tmp.path().join("v3.png");
    let code = render_cli(
        &ply,
        &[
            "--cameras",
            cams.to_str().unwrap(),
            "--view",
            "3",
            "--background",
            "0,0,0",
            "--out",
            out.to_str().unwrap(),
        ],
    );
    assert_eq!(code, 0);
    let img = image::open(&out).unwrap().into_rgb8();
    assert_eq!(img.dimensions(), (100, 100));
    assert_centred(&img, (50.0, 50.0));
}

/// An off-centre principal point (cx = 83.5 at a true width of 160) without an image file: the
/// size is unknown, and guessing 2·cx would render 167 px wide. Without `--size` it is an
/// error naming `--size` (also for `--width/--height`, which rescale from the unknown size);
/// with `--size 160x120` the image is 160×120 with the intrinsics untouched, so the Gaussian
/// on the optical axis is centred on the principal point (83.5, 40.5).
#[test]
fn without_an_image_file_the_size_comes_from_size_or_is_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let cams = one_entry_file(tmp.path(), 83.5, 40.5);
    let ply = one_gaussian(tmp.path(), DVec3::new(0.0, 0.0, -2.0));
    let request = |size| PreviewRequest {
        ply: ply.clone(),
        cameras: cams.clone(),
        view: 0,
        frame: 0,
        size,
        background: [0.0; 3],
    };
    for size in [OutputSize::Native, OutputSize::Rescaled(320, 240)] {
        let e = preview::render(&request(size)).unwrap_err().to_string();
        assert!(
            e.contains("image size of camera 0 is unknown")
                && e.contains("r_0_0.png does not exist")
                && e.contains("--size WxH"),
            "{size:?}: {e}"
        );
    }
    let out = tmp.path().join("v0.png");
    let base = [
        "--cameras",
        cams.to_str().unwrap(),
        "--view",
        "0",
        "--background",
        "0,0,0",
        "--out",
        out.to_str().unwrap(),
    ];
    assert_ne!(render_cli(&ply, &base), 0);
    assert!(!out.exists(), "no image is written on error");
    // --size and --width/--height are exclusive; a malformed size is a usage error.
    let both = [
        &base[..],
        &["--size", "160x120", "--width", "8", "--height", "8"],
    ]
    .concat();
    assert_eq!(render_cli(&ply, &both), 2);
    for bad in ["160", "160x", "0x120", "160x-1"] {
        let args = [&base[..], &["--size", bad]].concat();
        assert_eq!(render_cli(&ply, &args), 2, "--size {bad}");
    }

    let args = [&base[..], &["--size", "160x120"]].concat();
    assert_eq!(render_cli(&ply, &args), 0);
    let img = image::open(&out).unwrap().into_rgb8();
    assert_eq!(img.dimensions(), (160, 120));
    assert_centred(&img, (83.5, 40.5));
}

/// With the image file present, `--width/--height` rescale the intrinsics from its size: at
/// twice the size the principal point (83.5, 40.5) moves to (167, 81).
#[test]
fn width_and_height_rescale_from_the_image_size() {
    let tmp = tempfile::tempdir().unwrap();
    let cams = one_entry_file(tmp.path(), 83.5, 40.5);
    std::fs::create_dir_all(tmp.path().join("data")).unwrap();
    image::RgbImage::new(160, 120)
        .save(tmp.path().join("data/r_0_0.png"))
        .unwrap();
    let ply = one_gaussian(tmp.path(), DVec3::new(0.0, 0.0, -2.0));
    let request = |size| PreviewRequest {
        ply: ply.clone(),
        cameras: cams.clone(),
        view: 0,
        frame: 0,
        size,
        background: [0.0; 3],
    };
    let native = preview::render(&request(OutputSize::Native)).unwrap();
    assert_eq!((native.image.width, native.image.height), (160, 120));
    let twice = preview::render(&request(OutputSize::Rescaled(320, 240))).unwrap();
    assert_eq!((twice.image.width, twice.image.height), (320, 240));
    let img = image::RgbImage::from_raw(320, 240, twice.image.data).unwrap();
    assert_centred(&img, (167.0, 81.0));
}
