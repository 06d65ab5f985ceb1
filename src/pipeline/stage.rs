//! The interface between the runner and the stages.
//!
//! The runner knows stages only through [`Stage`] trait objects held in a [`Registry`]; the
//! concrete stages live in `crate::stages` and implement the typed [`TypedStage`], which gets
//! [`Stage`] for free (parameter validation, defaults, JSON Schema).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::Value;

use super::cache::Manifest;
use super::checkpoint::{Checkpoints, Saved};
use super::progress::Progress;
use super::spec::{Preset, SceneSpec};

/// Why a stage did not produce its outputs.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// The user pressed Ctrl-C (or the run was otherwise asked to stop).
    #[error("interrupted")]
    Interrupted,
    /// The stage needs an upstream stage's entry that is not available.
    #[error("stage needs the output of `{0}`, which is not part of this run")]
    MissingUpstream(String),
    /// Anything the stage itself reports (bad input data, numerical trouble, I/O).
    #[error(transparent)]
    Failed(Box<dyn std::error::Error + Send + Sync>),
}

impl StageError {
    /// Wrap any error as a stage failure.
    pub fn failed(e: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self::Failed(Box::new(e))
    }
}

/// An external file a stage reads, under a logical name that does not depend on where the
/// dataset sits on disk (the cache key hashes its content, never its absolute path).
#[derive(Debug, Clone)]
pub struct InputFile {
    /// Stable name, e.g. `data/r_0_3.png`.
    pub logical_name: String,
    /// Where it is now.
    pub path: PathBuf,
}

/// An upstream stage's committed cache entry.
#[derive(Debug, Clone)]
pub struct UpstreamEntry {
    /// Stage kind of the upstream.
    pub kind: String,
    /// Directory holding its outputs.
    pub dir: PathBuf,
    /// Its manifest.
    pub manifest: Manifest,
}

/// One metric row: what a stage measured (becomes `metrics.arrow` in its entry).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct MetricRow {
    /// Training epoch, if the value belongs to one.
    pub epoch: Option<u32>,
    /// Camera index, if the value belongs to one view.
    pub view: Option<u16>,
    /// Frame index, if the value belongs to one frame.
    pub frame: Option<u16>,
    /// Metric name, e.g. `psnr`, `mask_iou`.
    pub metric: String,
    /// Value (units given by the metric's name and docs).
    #[serde(with = "number_or_text")]
    pub value: f64,
}

impl MetricRow {
    /// A value of the whole stage (no epoch, view or frame).
    pub fn of_stage(metric: &str, value: f64) -> Self {
        Self {
            epoch: None,
            view: None,
            frame: None,
            metric: metric.into(),
            value,
        }
    }
}

/// An `f64` in JSON: a number when finite, `"NaN"`, `"inf"` or `"-inf"` otherwise (a metric
/// such as the PSNR of identical images is infinite; a checkpoint must keep it).
mod number_or_text {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else if v.is_nan() {
            s.serialize_str("NaN")
        } else if *v > 0.0 {
            s.serialize_str("inf")
        } else {
            s.serialize_str("-inf")
        }
    }

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Repr {
        Number(f64),
        Text(String),
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        match Repr::deserialize(d)? {
            Repr::Number(v) => Ok(v),
            Repr::Text(t) => match t.as_str() {
                "NaN" => Ok(f64::NAN),
                "inf" => Ok(f64::INFINITY),
                "-inf" => Ok(f64::NEG_INFINITY),
                other => Err(serde::de::Error::custom(format!(
                    "expected a number, \"NaN\", \"inf\" or \"-inf\", found \"{other}\""
                ))),
            },
        }
    }
}

/// What a running stage can see and do.
pub struct StageContext<'a> {
    /// Stage name in the pipeline file.
    pub name: &'a str,
    /// The pipeline's scene section.
    pub scene: &'a SceneSpec,
    /// Upstream entries by stage name.
    pub upstream: &'a BTreeMap<String, UpstreamEntry>,
    /// External inputs the stage declared, with their content hashes already in the key.
    pub inputs: &'a [InputFile],
    /// The (temporary) directory the stage writes its outputs into.
    pub out_dir: &'a Path,
    /// Progress reporting.
    pub progress: &'a dyn Progress,
    /// Metrics recorded so far.
    pub metrics: Vec<MetricRow>,
    interrupt: &'a AtomicBool,
    checkpoints: Option<&'a Checkpoints>,
    resumed: Option<Saved>,
    file: Option<&'a Path>,
}

impl std::fmt::Debug for StageContext<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StageContext")
            .field("name", &self.name)
            .field("out_dir", &self.out_dir)
            .finish_non_exhaustive()
    }
}

impl<'a> StageContext<'a> {
    /// Build a context (used by the runner and by tests of single stages).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        name: &'a str,
        scene: &'a SceneSpec,
        upstream: &'a BTreeMap<String, UpstreamEntry>,
        inputs: &'a [InputFile],
        out_dir: &'a Path,
        progress: &'a dyn Progress,
        interrupt: &'a AtomicBool,
    ) -> Self {
        Self {
            name,
            scene,
            upstream,
            inputs,
            out_dir,
            progress,
            metrics: Vec::new(),
            interrupt,
            checkpoints: None,
            resumed: None,
            file: None,
        }
    }

    /// The pipeline file the stage belongs to, for messages (the runner sets it).
    pub fn with_file(mut self, file: &'a Path) -> Self {
        self.file = Some(file);
        self
    }

    /// Where a parameter of this stage is written, for messages: `FILE: stages.NAME` (the
    /// file when known).
    pub fn location(&self) -> String {
        match self.file {
            Some(f) => format!("{}: stages.{}", f.display(), self.name),
            None => format!("stages.{}", self.name),
        }
    }

    /// Keep this stage's checkpoints in `checkpoints` (the runner does; without it
    /// [`Self::resume`] finds nothing, [`Self::checkpoint`] keeps nothing and
    /// [`Self::checkpoint_file`] is an error).
    pub fn with_checkpoints(mut self, checkpoints: &'a Checkpoints) -> Self {
        self.checkpoints = Some(checkpoints);
        self
    }

    /// The state saved by the last [`Self::checkpoint`] of a run of this stage name with this
    /// same cache key that did not finish (Ctrl-C, `kill -9`, a crash, a failure), if any.
    ///
    /// On `Some`, it also restores [`Self::metrics`] to the rows recorded up to that checkpoint
    /// and tells the user, even with `--quiet`: ``resuming `material` from its checkpoint
    /// (epoch 12)`` (the progress text given to [`Self::checkpoint`]). A checkpoint that is
    /// unreadable, of another checkpoint format, stage or key, whose files do not match their
    /// hashes, or whose state does not deserialize as `T` is reported as a warning and ignored
    /// (`None`: the stage starts over); it is never an error.
    ///
    /// Call it once, before training and before recording metrics. The key covers parameters,
    /// code `VERSION`, upstream keys and inputs, so a checkpoint is only ever resumed by the same
    /// computation; change `VERSION` when the state's layout or meaning changes.
    pub fn resume<T: DeserializeOwned>(&mut self) -> Option<T> {
        let checkpoints = self.checkpoints?;
        match checkpoints.load::<T>() {
            Ok(None) => None,
            Ok(Some(loaded)) => {
                self.progress.notice(&format!(
                    "resuming `{}` from its checkpoint ({})",
                    self.name, loaded.saved.progress
                ));
                self.metrics = loaded.metrics;
                self.resumed = Some(loaded.saved);
                Some(loaded.state)
            }
            Err(problem) => {
                self.progress.notice(&format!(
                    "warning: ignoring the checkpoint of `{}` and starting over: {problem}",
                    self.name
                ));
                None
            }
        }
    }

    /// Save `state` so that a later run continues from it: atomically (written beside,
    /// fsync'd, renamed), in `.pipe/checkpoints/<stage>-<key>/`, together with
    /// [`Self::metrics`] and the files written through [`Self::checkpoint_file`] since the
    /// previous checkpoint. `progress` is a short position shown on resume and by
    /// `pipe status`, e.g. `epoch 12`. The runner deletes the checkpoints once the stage's entry
    /// is committed.
    ///
    /// A resumed run must produce the same outputs as an uninterrupted one, bit for bit, so
    /// `state` must hold everything the rest of the run depends on: the epoch (or step) to
    /// continue from, the parameters being learnt, the optimiser's moments and step count, the
    /// learning-rate schedule's position, every random generator's state (e.g. a serde-enabled
    /// `rand_pcg::Pcg64`, or its seed and the draws made), and anything accumulated (best
    /// value so far, early-stopping counters, densification statistics). Save at an epoch
    /// boundary, after the epoch's updates, and make the loop start from `state.epoch`.
    /// The state is JSON: floats survive exactly (checked here: a state that does not read
    /// back equal, e.g. one holding NaN or infinity, fails the stage with a clear error); keep
    /// large arrays in [`Self::checkpoint_file`] instead. Checkpoint every few epochs, not
    /// every step: it costs a JSON encode and decode, a hash of the files and a few fsyncs.
    pub fn checkpoint<T: Serialize + DeserializeOwned>(
        &self,
        progress: &str,
        state: &T,
    ) -> Result<(), StageError> {
        match self.checkpoints {
            None => Ok(()),
            Some(c) => c
                .save(progress, &self.metrics, state)
                .map(|_| ())
                .map_err(StageError::failed),
        }
    }

    /// A path where the stage writes file `name` (a plain file name) of its next checkpoint,
    /// e.g. a large array in binary; [`Self::checkpoint`] hashes and commits it with the state.
    /// Each checkpoint holds the files written since the previous one: write them all each time.
    pub fn checkpoint_file(&self, name: &str) -> Result<PathBuf, StageError> {
        let c = self.checkpoints.ok_or_else(|| {
            StageError::failed(super::checkpoint::CheckpointError::NoStore(
                self.name.to_string(),
            ))
        })?;
        c.file(name).map_err(StageError::failed)
    }

    /// The checkpoint [`Self::resume`] continued from, if it did.
    pub fn resumed(&self) -> Option<&Saved> {
        self.resumed.as_ref()
    }

    /// File `name` of the checkpoint [`Self::resume`] returned (its hash already checked), if
    /// it holds one. Read it before the next [`Self::checkpoint`], which supersedes it.
    pub fn resumed_file(&self, name: &str) -> Option<PathBuf> {
        let saved = self.resumed.as_ref()?;
        saved
            .files
            .iter()
            .any(|f| f == name)
            .then(|| saved.dir.join(name))
    }

    /// Return `Err(Interrupted)` once the user asked to stop; call it in every loop.
    pub fn check_interrupted(&self) -> Result<(), StageError> {
        if self.interrupt.load(Ordering::SeqCst) {
            Err(StageError::Interrupted)
        } else {
            Ok(())
        }
    }

    /// The entry of the upstream stage named (or of kind) `name`.
    pub fn upstream(&self, name: &str) -> Result<&UpstreamEntry, StageError> {
        self.upstream
            .get(name)
            .or_else(|| self.upstream.values().find(|u| u.kind == name))
            .ok_or_else(|| StageError::MissingUpstream(name.to_string()))
    }

    /// Record one metric value.
    pub fn metric(&mut self, row: MetricRow) {
        self.metrics.push(row);
    }

    /// The flag that turns true when the user asks to stop (for loops inside kernels that
    /// cannot call [`Self::check_interrupted`]).
    pub fn interrupt_flag(&self) -> &'a AtomicBool {
        self.interrupt
    }
}

/// The object-safe interface the runner uses. Implement [`TypedStage`] instead.
pub trait Stage: Send + Sync {
    /// Stage kind; also its name in the pipeline file.
    fn kind(&self) -> &'static str;
    /// One line saying what the stage does.
    fn description(&self) -> &'static str;
    /// Hand-bumped code version: change it when outputs would change for the same inputs.
    fn version(&self) -> u32;
    /// Stage kinds whose outputs this stage reads when the file does not say `needs:`.
    fn default_upstream(&self) -> &'static [&'static str];
    /// Whether the file gives a map of named instances (`edit: {press: {...}, drop: {...}}`),
    /// each its own stage `<kind>.<name>` with its own parameters and cache entry, rather than
    /// one set of parameters.
    fn named_instances(&self) -> bool;
    /// Output tables and their schema versions (part of the cache key).
    fn output_schemas(&self) -> Vec<(&'static str, u32)>;
    /// JSON Schema of the parameters.
    fn params_schema(&self) -> schemars::Schema;
    /// Parameter values a preset sets (merged under the file's own values).
    fn preset_params(&self, preset: Preset) -> Value;
    /// Validate raw parameters and return them resolved (defaults filled in, canonical).
    fn resolve_params(&self, raw: &Value) -> Result<Value, ParamError>;
    /// The part of the scene section this stage depends on (goes into the cache key).
    fn scene_key(&self, scene: &SceneSpec) -> Value;
    /// External files read by the stage (content-hashed into the key).
    fn inputs(&self, params: &Value, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError>;
    /// Run with resolved parameters, writing outputs into `ctx.out_dir`.
    fn run(&self, params: &Value, ctx: &mut StageContext<'_>) -> Result<(), StageError>;
}

/// A parameter that failed validation: the JSON path inside the stage's parameters and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParamError {
    /// Dotted path inside the stage's parameters (`grid`, `learn[1]`); empty for the whole.
    pub path: String,
    /// serde's message (e.g. "invalid type: string \"x\", expected u32").
    pub message: String,
}

/// A stage with typed parameters. Implementing it gives a [`Stage`].
pub trait TypedStage: Send + Sync {
    /// Parameters as written in the pipeline file (`deny_unknown_fields`, serde defaults).
    type Params: Serialize + DeserializeOwned + schemars::JsonSchema;
    /// See [`Stage::kind`].
    const KIND: &'static str;
    /// See [`Stage::version`].
    const VERSION: u32;
    /// See [`Stage::description`].
    const DESCRIPTION: &'static str;
    /// See [`Stage::default_upstream`].
    const UPSTREAM: &'static [&'static str] = &[];
    /// See [`Stage::named_instances`].
    const NAMED_INSTANCES: bool = false;
    /// See [`Stage::output_schemas`].
    fn output_schemas(&self) -> Vec<(&'static str, u32)>;
    /// See [`Stage::preset_params`].
    fn preset_params(&self, _preset: Preset) -> Value {
        Value::Object(Default::default())
    }
    /// Checks across parameters that serde cannot express (ranges, combinations).
    fn validate(&self, _params: &Self::Params) -> Result<(), ParamError> {
        Ok(())
    }
    /// See [`Stage::scene_key`].
    fn scene_key(&self, _scene: &SceneSpec) -> Value {
        Value::Null
    }
    /// See [`Stage::inputs`].
    fn inputs(
        &self,
        _params: &Self::Params,
        _scene: &SceneSpec,
    ) -> Result<Vec<InputFile>, StageError> {
        Ok(Vec::new())
    }
    /// See [`Stage::run`].
    fn run(&self, params: &Self::Params, ctx: &mut StageContext<'_>) -> Result<(), StageError>;
}

fn typed<P: DeserializeOwned>(raw: &Value) -> Result<P, ParamError> {
    serde_path_to_error::deserialize(raw).map_err(|e| ParamError {
        path: e.path().to_string().trim_start_matches('.').to_string(),
        message: e.inner().to_string(),
    })
}

impl<T: TypedStage> Stage for T {
    fn kind(&self) -> &'static str {
        T::KIND
    }
    fn description(&self) -> &'static str {
        T::DESCRIPTION
    }
    fn version(&self) -> u32 {
        T::VERSION
    }
    fn default_upstream(&self) -> &'static [&'static str] {
        T::UPSTREAM
    }
    fn named_instances(&self) -> bool {
        T::NAMED_INSTANCES
    }
    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        TypedStage::output_schemas(self)
    }
    fn params_schema(&self) -> schemars::Schema {
        schemars::schema_for!(T::Params)
    }
    fn preset_params(&self, preset: Preset) -> Value {
        TypedStage::preset_params(self, preset)
    }
    fn resolve_params(&self, raw: &Value) -> Result<Value, ParamError> {
        let p: T::Params = typed(raw)?;
        self.validate(&p)?;
        serde_json::to_value(&p).map_err(|e| ParamError {
            path: String::new(),
            message: e.to_string(),
        })
    }
    fn scene_key(&self, scene: &SceneSpec) -> Value {
        TypedStage::scene_key(self, scene)
    }
    fn inputs(&self, params: &Value, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError> {
        let p: T::Params = typed(params).map_err(|e| StageError::Failed(e.message.into()))?;
        TypedStage::inputs(self, &p, scene)
    }
    fn run(&self, params: &Value, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let p: T::Params = typed(params).map_err(|e| StageError::Failed(e.message.into()))?;
        TypedStage::run(self, &p, ctx)
    }
}

/// The table of stage kinds a pipeline file may use.
#[derive(Clone, Default)]
pub struct Registry {
    stages: Vec<Arc<dyn Stage>>,
}

impl std::fmt::Debug for Registry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.kinds()).finish()
    }
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add a stage kind (builder style).
    pub fn with(mut self, stage: impl Stage + 'static) -> Self {
        self.stages.push(Arc::new(stage));
        self
    }

    /// Look a kind up.
    pub fn get(&self, kind: &str) -> Option<&Arc<dyn Stage>> {
        self.stages.iter().find(|s| s.kind() == kind)
    }

    /// All kinds, in registration order (the natural pipeline order).
    pub fn kinds(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.kind()).collect()
    }

    /// All stages, in registration order.
    pub fn iter(&self) -> impl Iterator<Item = &Arc<dyn Stage>> {
        self.stages.iter()
    }
}
