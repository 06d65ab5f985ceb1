//! Checkpoints and resume: a stage interrupted mid-run (Ctrl-C, or `kill -9` of the `pipe`
//! process) leaves no valid-looking entry, and the next run continues from its last checkpoint
//! when its key is unchanged, says so (also with `--quiet`), and produces exactly what an
//! uninterrupted run does; the checkpoint is gone once the entry is committed. A corrupt
//! checkpoint is a warning and a fresh start, another key's checkpoint is never resumed, and
//! `pipe clean` removes the checkpoints no pipeline references.
//! The `train` test stage (support.rs) checkpoints after every one of its epochs.

use std::path::Path;
use std::process::Output;

use pipe::pipeline::cache::hash_file;
use pipe::pipeline::checkpoint::STATE_FILE;
use pipe::pipeline::runner::{RunOptions, StageState};

use crate::support::{Fixture, registry, train_pipeline, wait_for};

const EPOCHS: u32 = 6;

/// The train entry's outputs `out.txt`, `history.bin`, `metrics.arrow`: name, blake3, size.
type Outputs = Vec<(String, String, u64)>;

fn train_key(f: &Fixture) -> (String, StageState) {
    let (_, planned) = f.ws().plan(&f.load(), &registry()).unwrap();
    let p = planned.into_iter().find(|p| p.name == "train").unwrap();
    (p.key, p.state)
}

fn outputs(f: &Fixture) -> Outputs {
    let (key, state) = train_key(f);
    assert!(matches!(state, StageState::Cached(_)), "{state:?}");
    let dir = f.ws().store.entry_dir("train", &key);
    ["out.txt", "history.bin", "metrics.arrow"]
        .iter()
        .map(|n| {
            let (hash, size) = hash_file(&dir.join(n)).unwrap();
            (n.to_string(), hash, size)
        })
        .collect()
}

/// What an uninterrupted run produces.
fn reference(rate: f64) -> Outputs {
    let f = Fixture::new(&train_pipeline(EPOCHS, rate));
    assert_eq!(
        f.run(&RunOptions::default()).unwrap().executed(),
        ["source", "train"]
    );
    let (key, _) = train_key(&f);
    let history = std::fs::read(f.ws().store.entry_dir("train", &key).join("history.bin")).unwrap();
    assert_eq!(history.len(), 8 * EPOCHS as usize);
    assert!(
        history
            .chunks(8)
            .all(|c| f64::from_le_bytes(c.try_into().unwrap()).is_finite())
    );
    outputs(&f)
}

fn checkpoint_dirs(f: &Fixture) -> Vec<String> {
    f.ws().store.checkpoints().unwrap()
}

fn epochs_in(log: &Path) -> Vec<u32> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .map(|l| l.parse().unwrap())
        .collect()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).to_string()
}

/// `pipe run` in a child process that stops after the checkpoint of epoch `epoch` and gets
/// `signal` (`-INT`: Ctrl-C, `-9`: killed). Returns its output and the epochs it ran.
fn interrupt(
    f: &Fixture,
    tag: &str,
    extra: &[&str],
    epoch: u32,
    signal: &str,
) -> (Output, Vec<u32>) {
    let hold = f.dir.path().join(format!("release-{tag}"));
    let log = f.dir.path().join(format!("epochs-{tag}.log"));
    let file = f.file().display().to_string();
    let mut args = vec!["run", file.as_str()];
    args.extend_from_slice(extra);
    let epoch_text = epoch.to_string();
    let child = f.child(
        &args,
        &[
            ("PIPE_TEST_HOLD_STAGE", "train"),
            ("PIPE_TEST_HOLD_EPOCH", &epoch_text),
            ("PIPE_TEST_HOLD", hold.to_str().unwrap()),
            ("PIPE_TEST_EPOCH_LOG", log.to_str().unwrap()),
        ],
    );
    wait_for(&hold.with_extension("started"));
    let pid = child.id().to_string();
    assert!(
        std::process::Command::new("kill")
            .args([signal, &pid])
            .status()
            .unwrap()
            .success()
    );
    let out = child.wait_with_output().unwrap();
    (out, epochs_in(&log))
}

/// `pipe [global] run FILE` to completion in a child process; its output and the epochs it ran.
fn run_child(f: &Fixture, tag: &str, global: &[&str]) -> (Output, Vec<u32>) {
    let log = f.dir.path().join(format!("epochs-{tag}.log"));
    let file = f.file().display().to_string();
    let mut args = global.to_vec();
    args.extend(["run", file.as_str()]);
    let out = f.child_output(&args, &[("PIPE_TEST_EPOCH_LOG", log.to_str().unwrap())]);
    assert!(out.status.success(), "{}", stderr(&out));
    (out, epochs_in(&log))
}

/// The `train` line of `pipe status`.
fn status_line(f: &Fixture) -> String {
    let file = f.file().display().to_string();
    let out = f.child_output(&["status", &file], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .find(|l| l.trim_start().starts_with("train "))
        .unwrap()
        .to_string()
}

/// Nothing of `train` looks committed: no entry directory, state not cached.
fn assert_no_train_entry(f: &Fixture) {
    let entries = f.ws().store.entries().unwrap();
    assert!(
        entries.iter().all(|e| !e.starts_with("train-")),
        "{entries:?}"
    );
    assert!(!matches!(train_key(f).1, StageState::Cached(_)));
}

#[test]
fn ctrl_c_then_a_quiet_rerun_resumes_and_matches_an_uninterrupted_run() {
    let reference = reference(0.5);
    let f = Fixture::new(&train_pipeline(EPOCHS, 0.5));
    let (out, ran) = interrupt(&f, "a", &["--quiet"], 3, "-INT");
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert_eq!(ran, [0, 1, 2]);
    assert!(err.contains("interrupted during stage `train`"), "{err}");
    assert!(
        err.contains("`train` keeps its checkpoint (epoch 3); the next run"),
        "{err}"
    );
    assert_no_train_entry(&f);
    assert_eq!(train_key(&f).1, StageState::NotRun);
    let key = train_key(&f).0;
    assert_eq!(checkpoint_dirs(&f), [format!("train-{key}")]);
    let line = status_line(&f);
    assert!(
        line.contains("not run (checkpoint from epoch 3 will be resumed)"),
        "{line}"
    );

    let (out, ran) = run_child(&f, "b", &["--quiet"]);
    let err = stderr(&out);
    assert!(
        err.contains("resuming `train` from its checkpoint (epoch 3)"),
        "{err}"
    );
    assert!(err.contains("with the runs it resumed"), "{err}");
    assert_eq!(ran, [3, 4, 5], "{err}");
    assert_eq!(outputs(&f), reference);
    assert!(checkpoint_dirs(&f).is_empty(), "{:?}", checkpoint_dirs(&f));
    assert!(status_line(&f).contains("cached"), "{}", status_line(&f));
}

#[test]
fn kill_9_mid_stage_then_a_rerun_resumes_from_the_last_complete_checkpoint() {
    let reference = reference(0.5);
    let f = Fixture::new(&train_pipeline(EPOCHS, 0.5));
    let (out, ran) = interrupt(&f, "a", &[], 2, "-9");
    assert_eq!(
        out.status.code(),
        None,
        "killed by a signal: {}",
        stderr(&out)
    );
    assert_eq!(ran, [0, 1]);
    assert_no_train_entry(&f);
    // The killed run's temporary entry is still there (cleared by the next run).
    let tmp = f.dir.path().join(".pipe/tmp");
    assert!(std::fs::read_dir(&tmp).unwrap().any(|e| {
        e.unwrap()
            .file_name()
            .to_string_lossy()
            .starts_with("train-")
    }),);
    // As if it had been killed while writing the next checkpoint: a half-written `next/`.
    let key = train_key(&f).0;
    let next = f.ws().store.checkpoint_dir("train", &key).join("next");
    std::fs::create_dir_all(&next).unwrap();
    std::fs::write(next.join(STATE_FILE), "{\"format\": 1, \"sta").unwrap();
    std::fs::write(next.join("history.bin"), [0u8; 5]).unwrap();

    let (out, ran) = run_child(&f, "b", &[]);
    let err = stderr(&out);
    assert!(
        err.contains("resuming `train` from its checkpoint (epoch 2)"),
        "{err}"
    );
    assert!(!err.contains("warning"), "{err}");
    assert_eq!(ran, [2, 3, 4, 5]);
    assert_eq!(outputs(&f), reference);
    assert!(checkpoint_dirs(&f).is_empty());
    assert!(!tmp.exists() || std::fs::read_dir(&tmp).unwrap().next().is_none());
}

/// Damages the checkpoint generation in the folder given.
type Corrupt = fn(&Path);

#[test]
fn a_corrupt_checkpoint_is_a_warning_and_the_stage_starts_over() {
    let reference = reference(0.5);
    let corruptions: [(&str, Corrupt); 2] = [
        ("checkpoint.json", |dir| {
            let p = dir.join(STATE_FILE);
            let text = std::fs::read(&p).unwrap();
            std::fs::write(&p, &text[..text.len() / 2]).unwrap();
        }),
        ("history.bin", |dir| {
            let p = dir.join("history.bin");
            let mut bytes = std::fs::read(&p).unwrap();
            bytes[3] ^= 0x10;
            std::fs::write(&p, bytes).unwrap();
        }),
    ];
    for (name, corrupt) in corruptions {
        let f = Fixture::new(&train_pipeline(EPOCHS, 0.5));
        interrupt(&f, "a", &[], 3, "-9");
        let key = train_key(&f).0;
        let root = f.ws().store.checkpoint_dir("train", &key);
        let generations: Vec<_> = std::fs::read_dir(&root)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(generations.len(), 1, "{generations:?}");
        corrupt(&generations[0]);
        let line = status_line(&f);
        assert!(
            line.contains("its checkpoint will be ignored") && line.contains(name),
            "{line}"
        );

        let (out, ran) = run_child(&f, "b", &["--quiet"]);
        let err = stderr(&out);
        assert!(
            err.contains("warning: ignoring the checkpoint of `train` and starting over")
                && err.contains(name),
            "{name}: {err}"
        );
        assert!(!err.contains("resuming"), "{err}");
        assert_eq!(ran, (0..EPOCHS).collect::<Vec<_>>(), "{name}");
        assert_eq!(outputs(&f), reference, "{name}");
        assert!(checkpoint_dirs(&f).is_empty());
    }
}

#[test]
fn another_keys_checkpoint_is_never_resumed_and_clean_removes_orphans() {
    let f = Fixture::new(&train_pipeline(EPOCHS, 0.5));
    interrupt(&f, "a", &[], 3, "-9");
    let key_a = train_key(&f).0;

    // New parameters, new key: a fresh start that leaves the old key's checkpoint alone.
    f.write(&train_pipeline(EPOCHS, 0.25));
    let key_b = train_key(&f).0;
    assert_ne!(key_a, key_b);
    let line = status_line(&f);
    assert!(
        line.contains("not run") && !line.contains("checkpoint"),
        "{line}"
    );
    let (out, ran) = interrupt(&f, "b", &[], 2, "-9");
    assert!(!stderr(&out).contains("resuming"), "{}", stderr(&out));
    assert_eq!(ran, [0, 1]);
    let mut both = vec![format!("train-{key_a}"), format!("train-{key_b}")];
    both.sort();
    assert_eq!(checkpoint_dirs(&f), both);

    // `clean` drops the checkpoint no pipeline references and keeps the current one.
    let cleaned = f.ws().clean(&registry(), false).unwrap();
    assert_eq!(cleaned.checkpoints, [format!("train-{key_a}")]);
    assert!(cleaned.entries.is_empty(), "{cleaned:?}");
    assert_eq!(checkpoint_dirs(&f), [format!("train-{key_b}")]);
    let (out, ran) = run_child(&f, "c", &[]);
    assert!(
        stderr(&out).contains("resuming `train` from its checkpoint (epoch 2)"),
        "{}",
        stderr(&out)
    );
    assert_eq!(ran, [2, 3, 4, 5]);
    assert_eq!(outputs(&f), reference(0.25));
    assert!(checkpoint_dirs(&f).is_empty());

    // A forced re-run killed mid-stage leaves a checkpoint of a committed key: `clean`
    // removes it (the entry is there).
    interrupt(&f, "d", &["--force", "train"], 1, "-9");
    assert_eq!(checkpoint_dirs(&f), [format!("train-{key_b}")]);
    let cleaned = f.ws().clean(&registry(), false).unwrap();
    assert_eq!(cleaned.checkpoints, [format!("train-{key_b}")]);
    assert!(checkpoint_dirs(&f).is_empty());

    // `clean --all` removes every entry and every checkpoint.
    f.write(&train_pipeline(EPOCHS, 0.5));
    interrupt(&f, "e", &[], 1, "-9");
    let out = f.child_output(&["clean", "--all"], &[]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        text.contains("removed 2 cache entries and 1 checkpoint\n"),
        "{text}"
    );
    assert!(
        text.contains(&format!("checkpoint train-{key_a}")),
        "{text}"
    );
    assert!(checkpoint_dirs(&f).is_empty());
    assert!(f.ws().store.entries().unwrap().is_empty());
}
