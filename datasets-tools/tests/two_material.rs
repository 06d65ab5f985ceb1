//! `tests/fixtures/two-material-bar` is what its README's command makes: the command is read
//! from the README, run into a temporary folder on one thread (the fixture was made on the
//! machine's default), and every file compared byte for byte.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/two-material-bar")
}

/// Every file under `root` (relative path → bytes).
fn files(root: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p
                    .strip_prefix(root)
                    .unwrap()
                    .to_string_lossy()
                    .replace('\\', "/");
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

#[test]
fn fixture_is_what_the_readme_command_makes() {
    let readme = std::fs::read_to_string(fixture().join("README.md")).unwrap();
    let prefix = "cargo run -p datasets-tools -- ";
    let line = readme
        .lines()
        .find(|l| l.starts_with(prefix))
        .expect("the README names the command");
    let mut args: Vec<String> = line[prefix.len()..]
        .split_whitespace()
        .map(String::from)
        .collect();
    assert_eq!(args[0], "two-material");
    assert_eq!(args[1], "tests/fixtures/two-material-bar");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scene");
    args[1] = out.to_string_lossy().into_owned();
    let run = Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
        .args(&args)
        .env("RAYON_NUM_THREADS", "1")
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let mut want = files(&fixture());
    assert!(want.remove("README.md").is_some());
    let got = files(&out);
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        want.keys().collect::<Vec<_>>()
    );
    for (name, bytes) in &want {
        assert!(got[name] == *bytes, "{name} differs from the fixture's");
    }
    // A second run into the same folder is refused rather than mixing two scenes.
    let again = Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
        .args(&args)
        .output()
        .unwrap();
    assert!(!again.status.success());
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(err.contains("exists and is not empty"), "{err}");
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
