//! `warmup` on the fixture scene with the `draft` preset: the held-out camera 10 (the highest
//! of the spiral, never seen in training) at frame 0 must reach the PSNR floor below, the loss
//! must fall, and the outputs (canonical Gaussians, metrics, test renders) must be there. A
//! short run with 1 and with 2 threads must give bit-identical Gaussians (fixed-order
//! reductions everywhere).

use crate::support::{BuiltinRun, fixture_scene};

use pipe::scene::gaussians::Gaussians;
use pipe::scene::metrics::Metrics;
use pipe::scene::table;

fn draft(warmup: &str) -> BuiltinRun {
    BuiltinRun::new(
        &fixture_scene(),
        "[10]",
        "draft",
        &format!("  ingest: {{frames: [0]}}\n  init: {{}}\n  warmup: {{{warmup}}}\n"),
    )
}

#[test]
fn draft_warmup_fits_frame_zero_and_generalises_to_the_held_out_view() {
    let run = draft("");
    run.run().unwrap();
    let entry = run.entry("warmup");
    let g: Gaussians = table::read(&entry.join("gaussians.arrow")).unwrap();
    assert!(g.len() > 1000, "{} Gaussians", g.len());
    assert!(g.position.iter().flatten().all(|v| v.is_finite()));
    let m: Metrics = table::read(&entry.join("metrics.arrow")).unwrap();
    let value = |name: &str| {
        m.rows
            .iter()
            .find(|r| r.metric == name)
            .unwrap_or_else(|| panic!("{name}"))
            .value
    };
    let losses: Vec<f64> = m
        .rows
        .iter()
        .filter(|r| r.metric == "loss")
        .map(|r| r.value)
        .collect();
    assert_eq!(losses.len(), 100, "one loss per draft epoch");
    assert!(
        losses[0] > 2.0 * losses[99],
        "loss {} → {}",
        losses[0],
        losses[99]
    );
    let test_psnr = value("test_psnr_mean");
    let train_psnr = value("train_psnr_mean");
    // The render over camera 10's plate against its capture: measured 36.5 dB (the issue
    // asks for >= 30; held-out cameras 0, 5 and 6 give 30.0, 34.0 and 33.5 dB).
    assert!(test_psnr >= 35.0, "held-out PSNR {test_psnr:.2} dB");
    assert!(train_psnr >= 40.0, "train PSNR {train_psnr:.2} dB");
    assert!(value("test_ssim_mean") > 0.985);
    // On white, the capture's anti-aliased edge (object mixed with the plate) caps it: 29.7 dB.
    assert!(value("test_psnr_solid_mean") >= 29.0);
    // Against the capture inside the ground-truth mask (the scene ships gt/masks) the matte's
    // errors cost: measured 36.43 dB on camera 10 (36.50 against our matte); the training
    // views, fitted to our matte's edges, 39.1 dB (43.6 against our matte).
    let test_gt = value("test_psnr_gtmask_mean");
    let per_view: Vec<f64> = m
        .rows
        .iter()
        .filter(|r| r.metric == "test_psnr_gtmask")
        .map(|r| r.value)
        .collect();
    assert_eq!(per_view, [test_gt], "one held-out view");
    println!(
        "held-out PSNR {test_psnr:.2} dB against our matte, {test_gt:.2} dB against the ground-truth mask; train {train_psnr:.2} / {:.2} dB",
        value("train_psnr_gtmask_mean")
    );
    assert!(test_gt >= 35.0 && test_gt <= test_psnr + 1.0, "{test_gt}");
    assert!(value("train_psnr_gtmask_mean") >= 38.0);
    let render = image::open(entry.join("renders/test_v10_f0.png")).unwrap();
    assert_eq!((render.width(), render.height()), (100, 100));
    let compare = image::open(entry.join("renders/compare_v10_f0.png")).unwrap();
    assert_eq!((compare.width(), compare.height()), (300, 100));
    let object = image::open(entry.join("renders/object_v10_f0.png"))
        .unwrap()
        .to_rgb8();
    assert_eq!(
        object.get_pixel(0, 0).0,
        [255, 255, 255],
        "object render on white"
    );
}

#[test]
fn warmup_is_bit_identical_with_one_and_two_threads() {
    let hashes: Vec<String> = [1usize, 2]
        .iter()
        .map(|&threads| {
            let run = draft("epochs: 8, densify_every: 20");
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| run.run()).unwrap();
            let entry = run.entry("warmup");
            let bytes = std::fs::read(entry.join("gaussians.arrow")).unwrap();
            blake3::hash(&bytes).to_hex().to_string()
        })
        .collect();
    assert_eq!(hashes[0], hashes[1]);
}

#[test]
fn bad_warmup_parameters_are_refused() {
    let e = draft("lambda: 1.5").run().unwrap_err();
    assert!(
        e.contains("stages.warmup.lambda: must be in [0, 1], found 1.5"),
        "{e}"
    );
}

#[test]
fn a_diverging_run_stops_and_says_where() {
    let run = draft("epochs: 3, lr_scale: 1.0e30");
    let e = run.run().unwrap_err();
    assert!(e.contains("stage `warmup` failed: non-finite"), "{e}");
    assert!(e.contains("at epoch 0, iteration "), "{e}");
    assert!(e.contains("lower stages.warmup."), "{e}");
    // Nothing was committed for the failed stage.
    assert!(
        run.ws()
            .store
            .entries()
            .unwrap()
            .iter()
            .all(|e| !e.starts_with("warmup-"))
    );
}

/// `*_psnr_gtmask` scores against the ground-truth mask, not our matte: on a copy of the scene
/// whose ground truth says camera 10 sees no object (an empty `gt/masks/m_10_0.png`), the
/// same render scores over 5 dB lower there than against our matte (measured 24.5 against
/// 32.3 dB after 10 epochs), while training views with their true masks score within 1.5 dB of
/// their own (our matte's IoU is ~0.95). Views without a ground-truth mask get no such row.
#[test]
fn the_gtmask_score_uses_the_ground_truth_mask() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    let src = fixture_scene();
    std::fs::create_dir_all(scene.join("gt/masks")).unwrap();
    std::fs::copy(src.join("all_data.json"), scene.join("all_data.json")).unwrap();
    copy_dir(&src.join("data"), &scene.join("data"));
    for view in [0, 1, 2, 10] {
        let name = format!("m_{view}_0.png");
        std::fs::copy(
            src.join("gt/masks").join(&name),
            scene.join("gt/masks").join(&name),
        )
        .unwrap();
    }
    image::GrayImage::new(100, 100)
        .save(scene.join("gt/masks/m_10_0.png"))
        .unwrap();
    let run = BuiltinRun::new(
        &scene,
        "[10]",
        "draft",
        "  ingest: {frames: [0]}\n  init: {}\n  warmup: {epochs: 10}\n",
    );
    run.run().unwrap();
    let m: Metrics = table::read(&run.entry("warmup").join("metrics.arrow")).unwrap();
    let at = |name: &str, view: u16| {
        m.rows
            .iter()
            .find(|r| r.metric == name && r.view == Some(view))
            .map(|r| r.value)
    };
    let (own, gt) = (
        at("test_psnr", 10).unwrap(),
        at("test_psnr_gtmask", 10).unwrap(),
    );
    println!("camera 10: {own:.2} dB against our matte, {gt:.2} dB against an empty mask");
    assert!(gt < own - 5.0, "{gt} vs {own}");
    for view in [0, 1, 2] {
        let (own_t, gt_t) = (
            at("train_psnr", view).unwrap(),
            at("train_psnr_gtmask", view).unwrap(),
        );
        println!(
            "camera {view}: {own_t:.2} dB against our matte, {gt_t:.2} dB against its true mask"
        );
        assert!(
            (gt_t - own_t).abs() < 1.5,
            "camera {view}: {gt_t} vs {own_t}"
        );
    }
    assert_eq!(
        at("train_psnr_gtmask", 3),
        None,
        "no ground-truth mask, no score"
    );
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}
