//! `tests/fixtures/two-material-bar` is what its README's command makes
//! ([`support::fixture_is_what_the_readme_command_makes`]).

mod support;

use std::process::Command;

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
