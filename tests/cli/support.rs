//! Test stages and helpers shared by the CLI tests.
//!
//! The stages are tiny (they read and write integers in text files) so the runner's
//! behaviour — keys, resume, staleness, atomic commits — is tested without any numerics.
//! Runs that must happen in another process (abort, lock, Ctrl-C) re-execute this test binary
//! on the ignored test `support::child_main` with the CLI arguments in `PIPE_CHILD_ARGS`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use pipe::pipeline::progress::{Mode, Reporter};
use pipe::pipeline::runner::{RunError, RunOptions, RunReport, Workspace};
use pipe::pipeline::spec::{self, Overrides, Pipeline};
use pipe::pipeline::stage::{Registry, StageContext, StageError, TypedStage};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// `source`: writes `value` (times 1) to `out.txt`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SourceParams {
    /// The number written.
    pub value: i64,
}

/// `double` and `sum` parameters.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FactorParams {
    /// Multiplier.
    #[serde(default = "one")]
    pub factor: i64,
}

fn one() -> i64 {
    1
}

/// Abort the process inside the stage named by `PIPE_TEST_ABORT`; hold inside the stage named
/// by `PIPE_TEST_HOLD_STAGE` until the file `PIPE_TEST_HOLD` exists (after creating
/// `<file>.started`), honouring interrupts.
fn test_hooks(ctx: &StageContext<'_>) -> Result<(), StageError> {
    std::fs::write(ctx.out_dir.join("partial.txt"), "half-written").map_err(StageError::failed)?;
    if std::env::var("PIPE_TEST_ABORT").ok().as_deref() == Some(ctx.name) {
        std::process::abort();
    }
    if std::env::var("PIPE_TEST_HOLD_STAGE").ok().as_deref() == Some(ctx.name) {
        let release = PathBuf::from(std::env::var("PIPE_TEST_HOLD").expect("hold file"));
        std::fs::write(
            release.with_extension("started"),
            std::process::id().to_string(),
        )
        .map_err(StageError::failed)?;
        while !release.exists() {
            ctx.check_interrupted()?;
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    std::fs::remove_file(ctx.out_dir.join("partial.txt")).map_err(StageError::failed)?;
    Ok(())
}

fn read_value(dir: &Path) -> i64 {
    std::fs::read_to_string(dir.join("out.txt"))
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

/// Source stage.
#[derive(Debug)]
pub struct Source;
impl TypedStage for Source {
    type Params = SourceParams;
    const KIND: &'static str = "source";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test: write a number";
    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![]
    }
    fn run(&self, p: &SourceParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        test_hooks(ctx)?;
        std::fs::write(ctx.out_dir.join("out.txt"), p.value.to_string()).map_err(StageError::failed)
    }
}

/// Double stage: upstream value × factor.
#[derive(Debug)]
pub struct Double;
impl TypedStage for Double {
    type Params = FactorParams;
    const KIND: &'static str = "double";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test: multiply the source";
    const UPSTREAM: &'static [&'static str] = &["source"];
    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![]
    }
    fn preset_params(&self, preset: spec::Preset) -> Value {
        match preset {
            spec::Preset::Draft => serde_json::json!({"factor": 2}),
            _ => serde_json::json!({}),
        }
    }
    fn run(&self, p: &FactorParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        test_hooks(ctx)?;
        let v = read_value(&ctx.upstream("source")?.dir);
        std::fs::write(ctx.out_dir.join("out.txt"), (v * p.factor).to_string())
            .map_err(StageError::failed)
    }
}

/// Sum stage: sum of all upstream values × factor.
#[derive(Debug)]
pub struct Sum;
impl TypedStage for Sum {
    type Params = FactorParams;
    const KIND: &'static str = "sum";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test: add upstream values";
    const UPSTREAM: &'static [&'static str] = &["source", "double"];
    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![]
    }
    fn run(&self, p: &FactorParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        test_hooks(ctx)?;
        let total: i64 = ctx.upstream.values().map(|u| read_value(&u.dir)).sum();
        std::fs::write(ctx.out_dir.join("out.txt"), (total * p.factor).to_string())
            .map_err(StageError::failed)
    }
}

/// Registry of the test stages.
pub fn registry() -> Registry {
    Registry::new().with(Source).with(Double).with(Sum)
}

/// The standard test pipeline: source(value) → double(factor) → sum (reads both).
pub fn pipeline_text(value: i64, factor: i64) -> String {
    format!(
        "name: test\nscene:\n  dataset: pacnerf\n  path: .\nstages:\n  source:\n    value: {value}\n  double:\n    factor: {factor}\n  sum: {{}}\n"
    )
}

/// A temp work directory holding `p.yaml`.
pub struct Fixture {
    /// Keeps the directory alive.
    pub dir: tempfile::TempDir,
}

impl Fixture {
    /// A work directory with the pipeline text written to `p.yaml`.
    pub fn new(text: &str) -> Self {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("p.yaml"), text).unwrap();
        Self { dir }
    }
    /// `p.yaml`.
    pub fn file(&self) -> PathBuf {
        self.dir.path().join("p.yaml")
    }
    /// Replace `p.yaml`.
    pub fn write(&self, text: &str) {
        std::fs::write(self.file(), text).unwrap();
    }
    /// The work directory.
    pub fn ws(&self) -> Workspace {
        Workspace::new(self.dir.path())
    }
    /// Load `p.yaml` with the test registry.
    pub fn load(&self) -> Pipeline {
        spec::load(&self.file(), &registry(), &Overrides::default()).unwrap()
    }
    /// Run in this process.
    pub fn run(&self, options: &RunOptions) -> Result<RunReport, RunError> {
        let stop = std::sync::atomic::AtomicBool::new(false);
        self.ws().run(
            &self.load(),
            &registry(),
            options,
            &Reporter::new(Mode::Quiet),
            &stop,
            "test",
        )
    }
    /// Run `pipe ARGS` (test registry) in a child process with extra environment.
    pub fn child(&self, args: &[&str], env: &[(&str, &str)]) -> std::process::Child {
        let mut all = vec![
            "pipe".to_string(),
            "--workdir".into(),
            self.dir.path().display().to_string(),
        ];
        all.extend(args.iter().map(|s| s.to_string()));
        let mut cmd = Command::new(std::env::current_exe().unwrap());
        cmd.args([
            "--exact",
            "support::child_main",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("PIPE_CHILD_ARGS", all.join("\u{1f}"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
        for (k, v) in env {
            cmd.env(k, v);
        }
        cmd.spawn().unwrap()
    }
    /// Run a child to completion.
    pub fn child_output(&self, args: &[&str], env: &[(&str, &str)]) -> Output {
        self.child(args, env).wait_with_output().unwrap()
    }
}

/// Wait until `path` exists (panics after 60 s).
pub fn wait_for(path: &Path) {
    let t = Instant::now();
    while !path.exists() {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "timed out waiting for {}",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Entry point of child processes (see module docs); ignored in normal runs.
#[test]
#[ignore = "entry point for child processes of other tests"]
fn child_main() {
    if let Ok(args) = std::env::var("PIPE_CHILD_ARGS") {
        let code = pipe::cli::run(args.split('\u{1f}'), registry());
        std::process::exit(i32::from(code));
    }
}

/// The repo's fixture scene (torus-elastic down-scaled 2×).
pub fn fixture_scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/torus-elastic-small")
}

/// A temp work directory with a pipeline over a scene, run with the built-in stages.
pub struct BuiltinRun {
    /// Keeps the directory alive.
    pub dir: tempfile::TempDir,
    /// `p.yaml` inside it.
    pub file: PathBuf,
}

impl BuiltinRun {
    /// Write `p.yaml`: `scene` (PAC-NeRF), `test_views` (YAML list), `preset`, and the
    /// `stages:` body (YAML lines indented by two spaces).
    pub fn new(scene: &Path, test_views: &str, preset: &str, stages: &str) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("p.yaml");
        std::fs::write(
            &file,
            format!(
                "name: t\nscene:\n  dataset: pacnerf\n  path: {}\n  test_views: {test_views}\npreset: {preset}\nstages:\n{stages}",
                scene.display()
            ),
        )
        .unwrap();
        Self { dir, file }
    }

    /// The work directory.
    pub fn ws(&self) -> Workspace {
        Workspace::new(self.dir.path())
    }

    /// Load and run the pipeline; the error as the CLI would print it.
    pub fn run(&self) -> Result<Pipeline, String> {
        let reg = pipe::stages::builtin();
        let p = spec::load(&self.file, &reg, &Overrides::default()).map_err(|e| e.to_string())?;
        let stop = std::sync::atomic::AtomicBool::new(false);
        self.ws()
            .run(
                &p,
                &reg,
                &RunOptions::default(),
                &Reporter::new(Mode::Quiet),
                &stop,
                "test",
            )
            .map_err(|e| e.to_string())?;
        Ok(p)
    }

    /// The committed entry of `stage` (after [`Self::run`]).
    pub fn entry(&self, stage: &str) -> PathBuf {
        let reg = pipe::stages::builtin();
        let p = spec::load(&self.file, &reg, &Overrides::default()).unwrap();
        self.ws().cached_entry(&p, &reg, stage).unwrap()
    }
}
