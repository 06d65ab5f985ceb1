//! What the `pipe` library hands over: a pipeline file's stages and cache entries
//! (`pipe::report::RunSummary`) and a finished sweep (`pipe::sweep::SweepSummary`), as JSON
//! values of the same shape. Unknown or missing fields are errors, so the two sides cannot drift
//! apart silently.

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use serde_json::Value;

/// One pipeline file's run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSummary {
    /// `name:` of the pipeline file.
    pub name: String,
    /// The pipeline file.
    pub file: PathBuf,
    /// Effective preset.
    pub preset: String,
    /// The resolved `scene:` section.
    pub scene: Value,
    /// Every stage in execution order.
    pub stages: Vec<StageRun>,
    /// PNG strips (captured | ours | 4× error) of the evaluated test views.
    pub strips: Vec<Strip>,
    /// The animated GIFs `evaluate` wrote, one per rendered view.
    pub gifs: Vec<ViewFile>,
}

/// One stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageRun {
    /// Name in the pipeline file.
    pub name: String,
    /// Stage kind.
    pub kind: String,
    /// Cache key.
    pub key: String,
    /// `done` (its result is in the cache for the current parameters), `stale` or `not run`.
    pub state: String,
    /// Why it is stale.
    pub reasons: Vec<String>,
    /// Its cache entry, when cached.
    pub dir: Option<PathBuf>,
    /// Resolved parameters.
    pub params: Value,
    /// Wall time, s.
    pub wall_s: Option<f64>,
    /// Peak resident memory while it ran, bytes (0: unknown).
    pub peak_rss_bytes: Option<u64>,
    /// Worker threads.
    pub threads: Option<usize>,
    /// The warnings it gave when it ran.
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// A strip image of one view at one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Strip {
    /// Camera.
    pub view: u16,
    /// Frame.
    pub frame: u16,
    /// `first`, `middle` or `last`.
    pub position: String,
    /// The PNG.
    pub path: PathBuf,
}

/// A file of one view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewFile {
    /// Camera.
    pub view: u16,
    /// The file.
    pub path: PathBuf,
}

/// A sweep axis (`--over KEY=V1,V2`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Axis {
    /// `preset` or `stage.key`.
    pub key: String,
    /// Values as written.
    pub values: Vec<String>,
}

/// One variant's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// Grid index.
    pub index: usize,
    /// Axis key → value.
    pub settings: BTreeMap<String, String>,
}

/// One variant's result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantResult {
    /// Its settings.
    pub variant: Variant,
    /// `key=value, …`.
    pub label: String,
    /// Effective preset.
    pub preset: String,
    /// Sum of its stages' wall times, s.
    pub wall_s: f64,
    /// Per stage, s.
    pub stage_wall_s: BTreeMap<String, f64>,
    /// Largest peak resident memory of its stages, bytes.
    pub peak_rss_bytes: u64,
    /// Stages the sweep executed (the others were cached).
    pub ran: Vec<String>,
    /// Cache key per stage.
    pub keys: BTreeMap<String, String>,
    /// Its `evaluation.json`.
    pub evaluation: Option<Value>,
}

/// A finished sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepSummary {
    /// Pipeline name.
    pub name: String,
    /// The pipeline file.
    pub file: PathBuf,
    /// The axes.
    pub axes: Vec<Axis>,
    /// One per variant.
    pub variants: Vec<VariantResult>,
}
