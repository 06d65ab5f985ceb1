//! `datasets-tools scene`: every material family the pipeline learns makes a scene in the
//! PAC-NeRF layout that the pipeline's own reader reads, with its truth; the truth's keys are
//! the ones `evaluate` compares with; bad arguments are named and leave nothing.

use std::process::Command;

use serde_json::Value;

fn make(dst: &std::path::Path, args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
        .arg("scene")
        .arg(dst)
        .args([
            "--size",
            "24",
            "--frames",
            "3",
            "--views",
            "3",
            "--supersample",
            "1",
        ])
        .args(["--extent", "0.12,0.12,0.12", "--spacing", "0.02"])
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn every_family_makes_a_scene_with_its_truth() {
    let dir = tempfile::tempdir().unwrap();
    for (family, args, key, value) in [
        (
            "elastic",
            &["--youngs-modulus", "1e5", "--poisson-ratio", "0.3"][..],
            "E",
            1e5,
        ),
        (
            "plasticine",
            &[
                "--youngs-modulus",
                "2e5",
                "--poisson-ratio",
                "0.3",
                "--yield-stress",
                "2e3",
                "--shape",
                "bar",
            ][..],
            "yield_stress",
            2e3,
        ),
        (
            "non_newtonian",
            &[
                "--youngs-modulus",
                "1e4",
                "--poisson-ratio",
                "0.3",
                "--yield-stress",
                "300",
                "--viscosity",
                "2",
                "--shape",
                "blob",
            ][..],
            "plastic_viscosity_eta",
            2.0,
        ),
        (
            "newtonian",
            &["--viscosity", "50", "--bulk-modulus", "1e5"][..],
            "mu",
            50.0,
        ),
        (
            "sand",
            &[
                "--youngs-modulus",
                "1e6",
                "--poisson-ratio",
                "0.3",
                "--friction-angle-deg",
                "30",
            ][..],
            "friction_angle_deg",
            30.0,
        ),
    ] {
        let dst = dir.path().join(family);
        let o = make(&dst, &[&["--family", family][..], args].concat());
        assert!(
            o.status.success(),
            "{family}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let scene = pipe::io::pacnerf::read_scene(&dst).unwrap();
        assert_eq!(scene.images.len(), 3 * 3, "{family}");
        for img in &scene.images {
            assert!(img.path.exists(), "{}", img.path.display());
            assert!(pipe::io::pacnerf::gt_mask_path(&dst, img.view, img.frame).exists());
        }
        let gt: Value =
            serde_json::from_slice(&std::fs::read(dst.join("gt/params.json")).unwrap()).unwrap();
        assert_eq!(gt["family"], family);
        assert_eq!(gt[key].as_f64(), Some(value), "{family}: {gt}");
        assert_eq!(gt["n_frames"], 3);
        let n = gt["n_particles"].as_u64().unwrap() as usize;
        for f in 0..3 {
            let c = pipe::io::ply::read_points(&dst.join(format!("gt/particles/{f}.ply"))).unwrap();
            assert_eq!(c.positions.len(), n, "{family} frame {f}");
            assert!(c.positions.iter().flatten().all(|v| v.is_finite()));
        }
        // The object moved (dropped with v0), and the simulation file that moved it is kept.
        let y = |f: usize| {
            let c = pipe::io::ply::read_points(&dst.join(format!("gt/particles/{f}.ply"))).unwrap();
            c.positions.iter().map(|p| f64::from(p[1])).sum::<f64>() / n as f64
        };
        assert!(y(2) < y(0) - 0.01, "{family}: {} -> {}", y(0), y(2));
        assert!(dst.join("gt/scene.sim.yaml").exists() && !dst.join(".simulate").exists());
    }
}

#[test]
fn bad_arguments_are_named_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let dst = dir.path().join("scene");
    for (args, want) in [
        (&["--family", "sand"][..], "friction_angle_deg"),
        (&["--family", "jelly"][..], "jelly"),
        (
            &[
                "--family",
                "elastic",
                "--youngs-modulus",
                "1e5",
                "--poisson-ratio",
                "0.3",
                "--extent",
                "0.01,0.1,0.1",
            ][..],
            "--extent",
        ),
    ] {
        let o = make(&dst, args);
        assert!(!o.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(want), "{args:?}: {err}");
        assert!(!dst.exists(), "{args:?} left {}", dst.display());
    }
}
