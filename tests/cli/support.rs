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
use pipe::pipeline::stage::{MetricRow, Registry, StageContext, StageError, TypedStage};
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
        hold(ctx)?;
    }
    std::fs::remove_file(ctx.out_dir.join("partial.txt")).map_err(StageError::failed)?;
    Ok(())
}

/// Create `<PIPE_TEST_HOLD>.started` and wait until the file `PIPE_TEST_HOLD` exists,
/// honouring interrupts.
fn hold(ctx: &StageContext<'_>) -> Result<(), StageError> {
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

/// `train` parameters.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TrainParams {
    /// Epochs to run.
    pub epochs: u32,
    /// Step size (part of the key and of the result).
    pub rate: f64,
}

/// Everything a `train` run depends on after an epoch (its history goes to a checkpoint file).
#[derive(Debug, Serialize, Deserialize)]
struct TrainState {
    /// Epochs done.
    epoch: u32,
    /// The value being "trained".
    x: f64,
    /// splitmix64 state.
    rng: u64,
}

/// Train stage: a toy optimisation of `x` (starting at the source's value) over `epochs`,
/// drawing a random number per epoch, recording `x` as a metric and in a history; it
/// checkpoints after every epoch (state, metrics, and the history as a checkpoint file) and
/// resumes. Outputs: `out.txt` (the bits of the final `x`), `history.bin` (every epoch's `x`,
/// f64 little-endian), `metrics.arrow`.
///
/// Hooks: after the checkpoint of epoch `PIPE_TEST_HOLD_EPOCH` (epochs done) it holds as
/// [`hold`] does when `PIPE_TEST_HOLD_STAGE` is `train`; it appends each epoch it runs to the
/// file `PIPE_TEST_EPOCH_LOG`.
#[derive(Debug)]
pub struct Train;
impl TypedStage for Train {
    type Params = TrainParams;
    const KIND: &'static str = "train";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test: a resumable training loop";
    const UPSTREAM: &'static [&'static str] = &["source"];
    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![]
    }
    fn run(&self, p: &TrainParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let start = read_value(&ctx.upstream("source")?.dir) as f64;
        let (mut state, mut history) = match ctx.resume::<TrainState>() {
            Some(state) => {
                let file = ctx
                    .resumed_file("history.bin")
                    .ok_or_else(|| StageError::Failed("checkpoint without history.bin".into()))?;
                (state, std::fs::read(file).map_err(StageError::failed)?)
            }
            None => (
                TrainState {
                    epoch: 0,
                    x: start,
                    rng: 0x853c_49e6_748f_ea9b,
                },
                Vec::new(),
            ),
        };
        let hold_epoch = std::env::var("PIPE_TEST_HOLD_EPOCH")
            .ok()
            .filter(|_| std::env::var("PIPE_TEST_HOLD_STAGE").ok().as_deref() == Some(ctx.name))
            .map(|e| e.parse::<u32>().expect("PIPE_TEST_HOLD_EPOCH is a number"));
        let epoch_log = std::env::var("PIPE_TEST_EPOCH_LOG").ok();
        while state.epoch < p.epochs {
            ctx.check_interrupted()?;
            if let Some(log) = &epoch_log {
                use std::io::Write;
                let mut f = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(log)
                    .map_err(StageError::failed)?;
                writeln!(f, "{}", state.epoch).map_err(StageError::failed)?;
            }
            // splitmix64, then a bounded non-linear update that no float slip survives.
            state.rng = state.rng.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state.rng;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            let u = (z >> 11) as f64 / (1u64 << 53) as f64;
            state.x = (state.x * (1.0 + p.rate) + u).sin() * 10.0;
            history.extend_from_slice(&state.x.to_le_bytes());
            ctx.metric(MetricRow {
                epoch: Some(state.epoch),
                view: None,
                frame: None,
                metric: "x".into(),
                value: state.x,
            });
            state.epoch += 1;
            std::fs::write(ctx.checkpoint_file("history.bin")?, &history)
                .map_err(StageError::failed)?;
            ctx.checkpoint(&format!("epoch {}", state.epoch), &state)?;
            if hold_epoch == Some(state.epoch) {
                hold(ctx)?;
            }
        }
        std::fs::write(ctx.out_dir.join("history.bin"), &history).map_err(StageError::failed)?;
        std::fs::write(
            ctx.out_dir.join("out.txt"),
            format!("{:016x}\n", state.x.to_bits()),
        )
        .map_err(StageError::failed)
    }
}

/// Registry of the test stages.
pub fn registry() -> Registry {
    Registry::new()
        .with(Source)
        .with(Double)
        .with(Sum)
        .with(Train)
}

/// A pipeline of source(5) → train(epochs, rate).
pub fn train_pipeline(epochs: u32, rate: f64) -> String {
    format!(
        "name: test\nscene:\n  dataset: pacnerf\n  path: .\nstages:\n  source:\n    value: 5\n  train:\n    epochs: {epochs}\n    rate: {rate}\n"
    )
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
        Self::with_family(scene, test_views, None, preset, stages)
    }

    /// As [`BuiltinRun::new`], with `scene.material: family` when given.
    pub fn with_family(
        scene: &Path,
        test_views: &str,
        family: Option<&str>,
        preset: &str,
        stages: &str,
    ) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("p.yaml");
        let family = family
            .map(|f| format!("  material: {f}\n"))
            .unwrap_or_default();
        std::fs::write(
            &file,
            format!(
                "name: t\nscene:\n  dataset: pacnerf\n  path: {}\n  test_views: {test_views}\n{family}preset: {preset}\nstages:\n{stages}",
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

/// A deterministic number in `[0, 1)` from two indices (test weights and jitter).
pub fn hash(i: usize, k: usize) -> f64 {
    let h = (i as u64)
        .wrapping_mul(0x9e37_79b9_7f4a_7c15)
        .wrapping_add((k as u64).wrapping_mul(0xbf58_476d_1ce4_e5b9))
        .rotate_left(17)
        .wrapping_mul(0x94d0_49bb_1331_11eb);
    (h >> 11) as f64 / (1u64 << 53) as f64
}
