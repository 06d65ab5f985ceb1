//! The check every generated fixture passes: it is what its README's command makes. The
//! command is read from the README, run into a temporary folder on one thread (the fixture was
//! made on the machine's default), and every file compared byte for byte; a second run into
//! the same folder is refused.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

/// `tests/fixtures/<name>`.
pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/fixtures")
        .join(name)
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

/// `tests/fixtures/<name>` is what `datasets-tools <subcommand> tests/fixtures/<name> ...`, as
/// its README gives it, makes.
pub fn fixture_is_what_the_readme_command_makes(name: &str, subcommand: &str) {
    let readme = std::fs::read_to_string(fixture(name).join("README.md")).unwrap();
    let prefix = "cargo run -p datasets-tools -- ";
    let line = readme
        .lines()
        .find(|l| l.starts_with(prefix))
        .expect("the README names the command");
    let mut args: Vec<String> = line[prefix.len()..]
        .split_whitespace()
        .map(String::from)
        .collect();
    assert_eq!(args[0], subcommand);
    assert_eq!(args[1], format!("tests/fixtures/{name}"));
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
    let mut want = files(&fixture(name));
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
