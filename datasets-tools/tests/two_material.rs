//! `tests/fixtures/two-material-bar` is what its README's command makes
//! ([`support::fixture_is_what_the_readme_command_makes`]).

mod generated;
mod support;

use std::process::Command;

use generated::{Run, generate};

#[test]
fn fixture_is_what_the_readme_command_makes() {
    support::fixture_is_what_the_readme_command_makes("two-material-bar", "two-material");
}

/// Bad values are named; a scene that cannot be made (the bar flies out of view) leaves no
/// folder behind.
#[test]
fn bad_arguments_are_named_and_a_failed_run_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scene");
    let run = |extra: &[&str]| {
        let o = Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
            .arg("two-material")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        assert!(!o.status.success());
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let err = run(&["--nu", "0.6"]);
    assert!(err.contains("--nu 0.6: must be in (-1, 0.5)"), "{err}");
    let err = run(&["--ratio", "-1"]);
    assert!(
        err.contains("--ratio -1: must be a finite number > 0"),
        "{err}"
    );
    let err = run(&["--v0", "1,2"]);
    assert!(
        err.contains("--v0 [1.0, 2.0]: expected three values"),
        "{err}"
    );
    let err = run(&["--v0", "3,-1,0", "--size", "16", "--frames", "5"]);
    assert!(
        err.contains("leaves camera") && err.contains("at frame"),
        "{err}"
    );
    assert!(!out.exists());
}

/// The two-material bar rendered at 160² (`two-material DIR --size 160 --frames 10`), `draft`
/// with warm-up seed 1: the field wins held out by 86 % but keeps only 39 % of that on the grid
/// 1.2× coarser, where one E for both halves had been kept (the stiff half 1.5 decades off);
/// the field's three parts keep 55 % and `auto` keeps them: both halves within 0.15 decades
/// (measured 0.031 / 0.119, test PSNR 33.55 dB, 2026-12-02). About 4 min in release:
/// `cargo test --release -p datasets-tools --test two_material -- --ignored`.
#[test]
#[ignore = "about 4 min in release: a 160² scene through every stage"]
fn auto_keeps_the_parts_of_a_field_the_second_grid_rejects() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    generate(
        "two-material",
        &root.join("scene"),
        &["--size", "160", "--frames", "10"],
    );
    let run = Run::new(
        root,
        "name: bar160\nscene:\n  dataset: pacnerf\n  path: scene\n  test_views: [10]\n  \
         material: elastic\npreset: draft\nstages:\n  ingest: {}\n  init: {}\n  \
         warmup: {seed: 1}\n  velocity: {dx: 0.03}\n  material: {model: auto, dx: 0.03}\n  \
         evaluate: {renders: false}\n",
        "bar160",
    );
    let m = run.json("material", "material.json");
    let sel = &m["selection"];
    println!("{}", sel["reason"]);
    assert_eq!(sel["kept"], "parts", "{sel}");
    assert_eq!(m["model"], "field", "a parts model is a field's: {sel}");
    // The field alone would not have passed the second grid.
    let (lg, lf) = (
        sel["loss_global_held_out"].as_f64().unwrap(),
        sel["loss_field_held_out"].as_f64().unwrap(),
    );
    let (ls2, lf2) = (
        sel["loss_simple_regrid_held_out"].as_f64().unwrap(),
        sel["loss_field_regrid_held_out"].as_f64().unwrap(),
    );
    let keep = (1.0 - lf2 / ls2) / (1.0 - lf / lg);
    assert!(keep < 0.5, "the field keeps {keep} of its gain: {sel}");
    let parts = sel["parts"].as_array().unwrap();
    assert!(!parts.is_empty(), "{sel}");
    for p in parts {
        let n = p["parts"].as_u64().unwrap() as usize;
        assert_eq!(p["log10_e"].as_array().unwrap().len(), n, "{p}");
        assert_eq!(p["thresholds"].as_array().unwrap().len(), n - 1, "{p}");
        assert!(p["loss_held_out"].as_f64().unwrap().is_finite(), "{p}");
    }
    let e = run.json("evaluate", "evaluation.json");
    let halves = e["material_truth"]["parts"].as_array().unwrap();
    println!("{}", e["material_truth"]);
    for (k, half) in ["soft", "stiff"].into_iter().enumerate() {
        let err = halves[k]["log10_youngs_modulus_error"].as_f64().unwrap();
        assert!(err < 0.15, "the {half} half's median is {err} decades off");
    }
}
