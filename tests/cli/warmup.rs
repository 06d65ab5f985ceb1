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
