//! `tests/fixtures/physdreamer-leaf` is what its README's command makes
//! ([`support::fixture_is_what_the_readme_command_makes`]); bad arguments are named.

mod support;

use std::process::Command;

#[test]
fn fixture_is_what_the_readme_command_makes() {
    support::fixture_is_what_the_readme_command_makes("physdreamer-leaf", "physdreamer");
}

#[test]
fn bad_arguments_are_named_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scene");
    for (args, want) in [
        (
            &["--size", "8"][..],
            "--size 8: must be from 16 to 1024 pixels",
        ),
        (&["--fps", "0"][..], "--fps 0: must be a finite number > 0"),
        (
            &["--amplitude", "0.5"][..],
            "--amplitude 0.5: must be within ±0.1 m",
        ),
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
            .arg("physdreamer")
            .arg(&out)
            .args(args)
            .output()
            .unwrap();
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(want), "{err}");
        assert!(!out.exists());
    }
}
