//! The generated two-material scene (`tests/fixtures/two-material-bar`, made by
//! `datasets-tools two-material`; its README has the command) ingests like a capture: `ingest`
//! (plate matte) finds masks that match the renderer's coverage (`gt/masks`), and `init`'s
//! visual hull of frame 0 is not smaller than the bar nor much larger (measured: IoU mean
//! 0.9680, min 0.9391; hull 0.0230 m³, 1.7× the bar's 0.0135 m³: a ring of cameras at 20–30°
//! elevation leaves the hull loose above and below the bar).

use crate::support::BuiltinRun;
use std::path::{Path, PathBuf};

use pipe::scene::frames::Frames;
use pipe::scene::metrics::Metrics;
use pipe::scene::table;

fn scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/two-material-bar")
}

fn gray(path: &Path) -> Vec<u8> {
    image::open(path).unwrap().into_luma8().into_raw()
}

#[test]
fn two_material_scene_ingests_with_masks_matching_the_renderers_coverage() {
    let run = BuiltinRun::new(
        &scene(),
        "[10]",
        "draft",
        "  ingest: {matte: plate}\n  init: {source: visual_hull}\n",
    );
    run.run().unwrap();
    let entry = run.entry("ingest");
    let frames: Frames = table::read(&entry.join("frames.arrow")).unwrap();
    assert_eq!(frames.rows.len(), 11 * 10);
    let mut ious = Vec::new();
    for row in &frames.rows {
        assert_eq!((row.width, row.height), (80, 80));
        let ours = gray(&entry.join(&row.mask));
        let gt = gray(&scene().join(format!("gt/masks/m_{}_{}.png", row.view, row.frame)));
        assert_eq!(ours.len(), gt.len());
        let (mut i, mut u) = (0u32, 0u32);
        for (a, b) in ours.iter().zip(&gt) {
            let (a, b) = (*a >= 128, *b >= 128);
            i += u32::from(a && b);
            u += u32::from(a || b);
        }
        assert!(
            u > 0,
            "camera {} frame {}: empty masks",
            row.view,
            row.frame
        );
        ious.push(f64::from(i) / f64::from(u));
    }
    let mean = ious.iter().sum::<f64>() / ious.len() as f64;
    let min = ious.iter().copied().fold(1.0, f64::min);
    println!("two-material masks: IoU mean {mean:.4}, min {min:.4}");
    assert!(
        mean >= 0.95 && min >= 0.9,
        "mean {mean:.4}, min {min:.4}: {ious:?}"
    );

    // The hull of frame 0 is at least the bar (0.6 × 0.15 × 0.15 m = 0.0135 m³), at most twice.
    let init = run.entry("init");
    let m: Metrics = table::read(&init.join("metrics.arrow")).unwrap();
    let volume = m
        .rows
        .iter()
        .find(|r| r.metric == "hull_volume_m3")
        .unwrap()
        .value;
    println!("two-material hull volume {volume:.5} m^3 (bar 0.0135)");
    assert!(
        (0.0135..=2.0 * 0.0135).contains(&volume),
        "hull volume {volume} m^3"
    );
}
