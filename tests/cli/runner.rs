//! The runner's promises: resume (nothing re-runs when nothing changed), exactly the changed
//! stage and its descendants re-run (and `status` says why beforehand), a killed or interrupted
//! run leaves no valid-looking entry, a corrupted output is detected and re-made, one runner per
//! work directory, and `--from` / `--until` / `--force` / `clean` do what they say.
//! The three test stages (source → double → sum, sum also reading source) make every edge
//! kind appear: a chain, a fan-in and a leaf.

use pipe::pipeline::runner::{RunError, RunOptions, StageState};

use crate::support::{Fixture, pipeline_text, registry, wait_for};

fn states(f: &Fixture) -> Vec<(String, StageState)> {
    let (_, planned) = f.ws().plan(&f.load(), &registry()).unwrap();
    planned.into_iter().map(|p| (p.name, p.state)).collect()
}

fn value_of(f: &Fixture, stage: &str) -> i64 {
    let (_, planned) = f.ws().plan(&f.load(), &registry()).unwrap();
    let p = planned.iter().find(|p| p.name == stage).unwrap();
    let dir = f.ws().store.entry_dir(stage, &p.key);
    std::fs::read_to_string(dir.join("out.txt"))
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

#[test]
fn second_run_executes_nothing_and_a_param_change_reruns_exactly_its_descendants() {
    let f = Fixture::new(&pipeline_text(5, 2));
    assert!(states(&f).iter().all(|(_, s)| *s == StageState::NotRun));
    let first = f.run(&RunOptions::default()).unwrap();
    assert_eq!(first.executed(), ["source", "double", "sum"]);
    assert_eq!(value_of(&f, "sum"), 15);
    let second = f.run(&RunOptions::default()).unwrap();
    assert!(second.executed().is_empty(), "{:?}", second.executed());

    f.write(&pipeline_text(5, 3));
    let st = states(&f);
    assert!(matches!(st[0].1, StageState::Cached(_)), "{st:?}");
    match &st[1].1 {
        StageState::Stale(r) => assert_eq!(r, &["param `double.factor` changed 2 → 3"]),
        other => panic!("double should be stale, is {other:?}"),
    }
    match &st[2].1 {
        StageState::Stale(r) => assert_eq!(r, &["upstream `double` will re-run"]),
        other => panic!("sum should be stale, is {other:?}"),
    }
    let third = f.run(&RunOptions::default()).unwrap();
    assert_eq!(third.executed(), ["double", "sum"]);
    assert_eq!(value_of(&f, "sum"), 20);

    // Going back to the old value reuses the old entries: nothing runs.
    f.write(&pipeline_text(5, 2));
    assert!(f.run(&RunOptions::default()).unwrap().executed().is_empty());
}

#[test]
fn cosmetic_edits_rerun_nothing() {
    let f = Fixture::new(&pipeline_text(5, 2));
    f.run(&RunOptions::default()).unwrap();
    // Comments, key order, flow style and the pipeline's name are not part of any key.
    f.write(
        "# a comment\nname: renamed\nscene: {path: ., dataset: pacnerf}\nstages:\n  source: {value: 5}\n  double: {factor: 2}\n  sum:\n",
    );
    assert!(f.run(&RunOptions::default()).unwrap().executed().is_empty());
}

#[test]
fn aborted_stage_leaves_no_valid_entry_and_the_rerun_completes() {
    let f = Fixture::new(&pipeline_text(5, 2));
    let file = f.file().display().to_string();
    let out = f.child_output(&["run", &file], &[("PIPE_TEST_ABORT", "double")]);
    assert!(!out.status.success(), "the child should have aborted");
    let st = states(&f);
    assert!(
        matches!(st[0].1, StageState::Cached(_)),
        "source committed before the abort: {st:?}"
    );
    assert!(
        !matches!(st[1].1, StageState::Cached(_)),
        "double must not look cached: {st:?}"
    );
    // No entry directory for double exists at all, valid or not.
    let entries = f.ws().store.entries().unwrap();
    assert!(
        entries.iter().all(|e| !e.starts_with("double-")),
        "{entries:?}"
    );
    let rerun = f.run(&RunOptions::default()).unwrap();
    assert_eq!(rerun.executed(), ["double", "sum"]);
    assert_eq!(value_of(&f, "sum"), 15);
    // The temp directory of the killed run was cleared.
    assert!(
        !f.dir.path().join(".pipe/tmp").exists()
            || std::fs::read_dir(f.dir.path().join(".pipe/tmp"))
                .unwrap()
                .next()
                .is_none()
    );
}

#[test]
fn corrupted_output_is_detected_named_and_rerun() {
    let f = Fixture::new(&pipeline_text(5, 2));
    f.run(&RunOptions::default()).unwrap();
    let (_, planned) = f.ws().plan(&f.load(), &registry()).unwrap();
    let out = f
        .ws()
        .store
        .entry_dir("source", &planned[0].key)
        .join("out.txt");
    let mut bytes = std::fs::read(&out).unwrap();
    bytes[0] ^= 0x01;
    std::fs::write(&out, bytes).unwrap();
    match &states(&f)[0].1 {
        StageState::Stale(r) => {
            assert_eq!(r.len(), 1);
            assert!(
                r[0].contains("out.txt") && r[0].contains("does not match the manifest"),
                "{r:?}"
            );
        }
        other => panic!("source should be stale, is {other:?}"),
    }
    let rerun = f.run(&RunOptions::default()).unwrap();
    // Descendants' keys depend on source's key, not its bytes: they stay cached.
    assert_eq!(rerun.executed(), ["source"]);
    assert_eq!(value_of(&f, "source"), 5);
}

#[test]
fn a_second_runner_on_the_same_workdir_is_refused() {
    let f = Fixture::new(&pipeline_text(5, 2));
    let hold = f.dir.path().join("release");
    let file = f.file().display().to_string();
    let mut child = f.child(
        &["run", &file],
        &[
            ("PIPE_TEST_HOLD_STAGE", "source"),
            ("PIPE_TEST_HOLD", hold.to_str().unwrap()),
        ],
    );
    wait_for(&hold.with_extension("started"));
    let err = f.run(&RunOptions::default()).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, RunError::Lock(_)), "{msg}");
    assert!(msg.contains(&format!("pid {}", child.id())), "{msg}");
    assert!(msg.contains("another pipe runner"), "{msg}");
    std::fs::write(&hold, "go").unwrap();
    assert!(child.wait().unwrap().success());
    assert!(f.run(&RunOptions::default()).unwrap().executed().is_empty());
}

#[test]
fn ctrl_c_stops_cleanly_without_committing_the_stage() {
    let f = Fixture::new(&pipeline_text(5, 2));
    let hold = f.dir.path().join("release");
    let file = f.file().display().to_string();
    let child = f.child(
        &["run", &file],
        &[
            ("PIPE_TEST_HOLD_STAGE", "double"),
            ("PIPE_TEST_HOLD", hold.to_str().unwrap()),
        ],
    );
    wait_for(&hold.with_extension("started"));
    let pid = child.id().to_string();
    assert!(
        std::process::Command::new("kill")
            .args(["-INT", &pid])
            .status()
            .unwrap()
            .success()
    );
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{stderr}");
    assert!(
        stderr.contains("interrupted during stage `double`"),
        "{stderr}"
    );
    let st = states(&f);
    assert!(matches!(st[0].1, StageState::Cached(_)));
    assert_eq!(st[1].1, StageState::NotRun);
    assert_eq!(
        f.run(&RunOptions::default()).unwrap().executed(),
        ["double", "sum"]
    );
}

#[test]
fn from_until_and_force_select_the_right_stages() {
    let f = Fixture::new(&pipeline_text(5, 2));
    let until = f
        .run(&RunOptions {
            until: Some("double".into()),
            ..Default::default()
        })
        .unwrap();
    assert_eq!(until.executed(), ["source", "double"]);
    let all = f.run(&RunOptions::default()).unwrap();
    assert_eq!(all.executed(), ["sum"]);
    let from = f
        .run(&RunOptions {
            from: Some("double".into()),
            ..Default::default()
        })
        .unwrap();
    assert_eq!(from.executed(), ["double", "sum"]);
    let force = f
        .run(&RunOptions {
            force: vec!["source".into()],
            ..Default::default()
        })
        .unwrap();
    assert_eq!(force.executed(), ["source"]);
    let bad = f
        .run(&RunOptions {
            from: Some("dubble".into()),
            ..Default::default()
        })
        .unwrap_err();
    assert!(bad.to_string().contains("no stage `dubble`"), "{bad}");
}

#[test]
fn clean_drops_only_unreferenced_entries() {
    let f = Fixture::new(&pipeline_text(5, 2));
    f.run(&RunOptions::default()).unwrap();
    f.write(&pipeline_text(5, 3));
    f.run(&RunOptions::default()).unwrap();
    assert_eq!(f.ws().store.entries().unwrap().len(), 5);
    let removed = f.ws().clean(&registry(), false).unwrap();
    assert_eq!(removed.entries.len(), 2, "{removed:?}");
    assert!(
        removed
            .entries
            .iter()
            .all(|r| r.starts_with("double-") || r.starts_with("sum-"))
    );
    assert!(removed.checkpoints.is_empty(), "{removed:?}");
    assert!(f.run(&RunOptions::default()).unwrap().executed().is_empty());
    let all = f.ws().clean(&registry(), true).unwrap();
    assert_eq!(all.entries.len(), 3);
}

#[test]
fn status_and_run_through_the_cli() {
    let f = Fixture::new(&pipeline_text(5, 2));
    let file = f.file().display().to_string();
    let out = f.child_output(&["status", &file], &[]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert_eq!(
        text.lines().filter(|l| l.contains("not run")).count(),
        3,
        "{text}"
    );
    let out = f.child_output(&["run", &file, "--set", "double.factor=4"], &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = f.child_output(&["status", &file], &[]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.lines()
            .any(|l| l.contains("source") && l.contains("cached")),
        "{text}"
    );
    assert!(
        text.contains("param `double.factor` changed 4 → 2"),
        "{text}"
    );
    let out = f.child_output(&["run", &file, "--preset", "nope"], &[]);
    assert_eq!(out.status.code(), Some(2));
}
