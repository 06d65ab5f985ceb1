//! Plans and runs a pipeline: keys, cache look-ups, stale reasons, execution, records.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::cache::{self, EntryProblem, KEY_FORMAT, KeyMaterial, Manifest, StatCache, Store};
use super::checkpoint::{CheckpointProblem, Checkpoints, Saved};
use super::graph::Graph;
use super::lock::{LockError, WorkdirLock};
use super::progress::Reporter;
use super::spec::{Pipeline, SpecError};
use super::stage::{Registry, StageContext, StageError, UpstreamEntry};

/// What `pipe run` was asked to do besides the default (run what is stale).
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Re-run this stage and everything downstream of it, cached or not.
    pub from: Option<String>,
    /// Run only this stage and what it needs.
    pub until: Option<String>,
    /// Re-run these stages even if cached.
    pub force: Vec<String>,
}

/// A stage's situation before a run.
#[derive(Debug, Clone, PartialEq)]
pub enum StageState {
    /// A valid entry exists for the current key.
    Cached(Box<Manifest>),
    /// No valid entry; the reasons say what changed since the last run.
    Stale(Vec<String>),
    /// Never run in this work directory.
    NotRun,
}

/// One stage of the plan.
#[derive(Debug, Clone)]
pub struct PlannedStage {
    /// Stage name.
    pub name: String,
    /// What the key is computed from.
    pub key_material: KeyMaterial,
    /// The key.
    pub key: String,
    /// Cached, stale (why) or not run.
    pub state: StageState,
    /// The external files the stage reads (hashed into the key).
    pub inputs: Vec<super::stage::InputFile>,
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The pipeline file is invalid.
    #[error(transparent)]
    Spec(#[from] SpecError),
    /// Another runner holds the work directory.
    #[error(transparent)]
    Lock(#[from] LockError),
    /// Cache I/O failed.
    #[error(transparent)]
    Cache(#[from] cache::CacheError),
    /// A stage's external input could not be read.
    #[error("stage `{stage}`: cannot read input {path}: {source}")]
    Input {
        /// The stage.
        stage: String,
        /// The input file.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// A stage failed.
    #[error("stage `{stage}` failed: {source}")]
    Stage {
        /// The stage.
        stage: String,
        /// What went wrong.
        source: StageError,
    },
    /// The user interrupted the run.
    #[error("interrupted during stage `{0}`; nothing was committed for it, re-run to continue")]
    Interrupted(String),
    /// `--from`, `--until` or `--force` name a stage the pipeline does not have.
    #[error("{0}")]
    Selection(String),
    /// A command-line value is malformed (e.g. `--background 1,1`).
    #[error("{0}")]
    Usage(String),
    /// A command other than `run` (export, render, …) could not produce its output.
    #[error("{0}")]
    Output(String),
}

/// What happened to one stage in a run.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Reused from the cache.
    Cached,
    /// Executed and committed.
    Ran {
        /// Wall time, seconds.
        wall_s: f64,
    },
    /// Not selected (`--until`).
    Skipped,
}

/// The result of a run: per stage, its key and outcome.
#[derive(Debug, Clone, Default)]
pub struct RunReport {
    /// (stage, key, outcome) in execution order.
    pub stages: Vec<(String, String, Outcome)>,
}

impl RunReport {
    /// Names of the stages that executed.
    pub fn executed(&self) -> Vec<&str> {
        self.stages
            .iter()
            .filter(|(_, _, o)| matches!(o, Outcome::Ran { .. }))
            .map(|(n, _, _)| n.as_str())
            .collect()
    }
}

/// What `pipe clean` removed: names `<stage>-<key>`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Cleaned {
    /// Cache entries.
    pub entries: Vec<String>,
    /// Checkpoint directories.
    pub checkpoints: Vec<String>,
}

/// Last-run record of one pipeline file: which key each stage had.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct RunRecord {
    /// The pipeline file (absolute).
    pub file: PathBuf,
    /// Stage → key material of its last successful run.
    pub stages: BTreeMap<String, KeyMaterial>,
}

/// A work directory: `.pipe/` with the cache, records and lock.
#[derive(Debug, Clone)]
pub struct Workspace {
    /// The cache store.
    pub store: Store,
}

impl Workspace {
    /// The work directory `dir` (its `.pipe/` is created on first run).
    pub fn new(dir: &Path) -> Self {
        Self {
            store: Store::new(dir),
        }
    }

    fn record_path(&self, pipeline_file: &Path) -> PathBuf {
        let abs = absolute(pipeline_file);
        let h = blake3::hash(abs.to_string_lossy().as_bytes()).to_hex();
        self.store
            .root()
            .join("runs")
            .join(format!("{}.json", &h[..16]))
    }

    /// The last-run record of a pipeline file.
    pub fn record(&self, pipeline_file: &Path) -> RunRecord {
        fs::read(self.record_path(pipeline_file))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_else(|| RunRecord {
                file: absolute(pipeline_file),
                stages: BTreeMap::new(),
            })
    }

    fn save_record(&self, record: &RunRecord) -> Result<(), cache::CacheError> {
        let p = self.record_path(&record.file);
        cache::write_atomic(&p, &serde_json::to_vec_pretty(record).expect("serialises"))
            .map_err(|source| cache::CacheError::Io { path: p, source })
    }

    /// Keep a copy of `pipeline_file`'s last-run record under `tag` (a sweep's variant), so
    /// `pipe clean` keeps the entries of every variant while the file exists, not only the
    /// last one's.
    pub fn pin_record(&self, pipeline_file: &Path, tag: &str) -> Result<(), cache::CacheError> {
        let record = self.record(pipeline_file);
        let base = self.record_path(pipeline_file);
        let stem = base
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        let h = blake3::hash(tag.as_bytes()).to_hex();
        let p = base.with_file_name(format!("{stem}-{}.json", &h[..16]));
        cache::write_atomic(&p, &serde_json::to_vec_pretty(&record).expect("serialises"))
            .map_err(|source| cache::CacheError::Io { path: p, source })
    }

    /// All last-run records in this work directory.
    pub fn records(&self) -> Vec<RunRecord> {
        let dir = self.store.root().join("runs");
        let Ok(rd) = fs::read_dir(dir) else {
            return Vec::new();
        };
        rd.filter_map(|e| e.ok())
            .filter_map(|e| fs::read(e.path()).ok())
            .filter_map(|b| serde_json::from_slice(&b).ok())
            .collect()
    }

    /// Compute every stage's key and state, without running anything.
    pub fn plan(
        &self,
        pipeline: &Pipeline,
        registry: &Registry,
    ) -> Result<(Graph, Vec<PlannedStage>), RunError> {
        let graph = Graph::build(pipeline, registry)?;
        let stat_path = self.store.root().join("stat-cache.json");
        let mut stat = StatCache::load(&stat_path);
        let record = self.record(&pipeline.file);
        let mut planned: Vec<PlannedStage> = Vec::new();
        for name in &graph.order {
            let spec = pipeline
                .stage(name)
                .expect("graph names come from the pipeline");
            let stage = registry.get(&spec.kind).expect("spec validated the kind");
            let mut inputs = BTreeMap::new();
            let files = stage
                .inputs(&spec.params, &pipeline.scene)
                .map_err(|source| RunError::Stage {
                    stage: name.clone(),
                    source,
                })?;
            for f in &files {
                let h = stat.hash(&f.path).map_err(|source| RunError::Input {
                    stage: name.clone(),
                    path: f.path.clone(),
                    source,
                })?;
                inputs.insert(f.logical_name.clone(), h);
            }
            let upstream = graph.upstream[name]
                .iter()
                .map(|u| {
                    let key = planned
                        .iter()
                        .find(|p| &p.name == u)
                        .expect("topological order")
                        .key
                        .clone();
                    (u.clone(), key)
                })
                .collect();
            let km = KeyMaterial {
                key_format: KEY_FORMAT,
                kind: stage.kind().to_string(),
                version: stage.version(),
                params: spec.params.clone(),
                scene: stage.scene_key(&pipeline.scene),
                upstream,
                inputs,
                schemas: stage
                    .output_schemas()
                    .into_iter()
                    .map(|(t, v)| (t.to_string(), v))
                    .collect(),
            };
            let key = km.key();
            let state = match self.store.verify(name, &key) {
                Ok(m) => StageState::Cached(Box::new(m)),
                Err(problem) => match record.stages.get(name) {
                    None if problem == EntryProblem::Missing => StageState::NotRun,
                    None => StageState::Stale(vec![problem.to_string()]),
                    Some(prev) => {
                        let mut reasons = explain(name, prev, &km, &planned);
                        if reasons.is_empty() {
                            reasons.push(match problem {
                                EntryProblem::Missing => "its cache entry was removed".to_string(),
                                other => other.to_string(),
                            });
                        }
                        StageState::Stale(reasons)
                    }
                },
            };
            planned.push(PlannedStage {
                name: name.clone(),
                key_material: km,
                key,
                state,
                inputs: files,
            });
        }
        stat.save(&stat_path);
        Ok((graph, planned))
    }

    /// Run the pipeline: every selected stage that is not cached (or is forced).
    pub fn run(
        &self,
        pipeline: &Pipeline,
        registry: &Registry,
        options: &RunOptions,
        reporter: &Reporter,
        interrupt: &AtomicBool,
        command: &str,
    ) -> Result<RunReport, RunError> {
        let _lock = WorkdirLock::acquire(self.store.root(), command)?;
        self.store.clear_tmp()?;
        let (graph, planned) = self.plan(pipeline, registry)?;
        let check = |s: &String, flag: &str| {
            if graph.order.contains(s) {
                Ok(())
            } else {
                Err(RunError::Selection(format!(
                    "{flag} {s}: the pipeline has no stage `{s}` (stages: {})",
                    graph.order.join(", ")
                )))
            }
        };
        let selected: BTreeSet<String> = match &options.until {
            Some(u) => {
                check(u, "--until")?;
                graph.ancestors(u)
            }
            None => graph.order.iter().cloned().collect(),
        };
        let mut forced: BTreeSet<String> = BTreeSet::new();
        for f in &options.force {
            check(f, "--force")?;
            forced.insert(f.clone());
        }
        if let Some(f) = &options.from {
            check(f, "--from")?;
            forced.extend(graph.descendants(f));
        }

        let mut record = self.record(&pipeline.file);
        record.file = absolute(&pipeline.file);
        let mut report = RunReport::default();
        let mut entries: BTreeMap<String, UpstreamEntry> = BTreeMap::new();
        let n = graph.order.len();
        for (i, p) in planned.iter().enumerate() {
            if !selected.contains(&p.name) {
                report
                    .stages
                    .push((p.name.clone(), p.key.clone(), Outcome::Skipped));
                continue;
            }
            if interrupt.load(std::sync::atomic::Ordering::SeqCst) {
                return Err(RunError::Interrupted(p.name.clone()));
            }
            let stage = registry.get(&p.key_material.kind).expect("validated");
            if let (StageState::Cached(m), false) = (&p.state, forced.contains(&p.name)) {
                reporter.stage_finished(i, n, &p.name, &format!("cached ({})", short(&p.key)));
                entries.insert(
                    p.name.clone(),
                    UpstreamEntry {
                        kind: stage.kind().to_string(),
                        dir: self.store.entry_dir(&p.name, &p.key),
                        manifest: (**m).clone(),
                    },
                );
                report
                    .stages
                    .push((p.name.clone(), p.key.clone(), Outcome::Cached));
                continue;
            }
            if let StageState::Stale(reasons) = &p.state {
                reporter.println(&format!(
                    "[{}/{}] {}: stale: {}",
                    i + 1,
                    n,
                    p.name,
                    reasons.join("; ")
                ));
            }
            reporter.stage_started(i, n, &p.name);
            let upstream: BTreeMap<String, UpstreamEntry> = graph.upstream[&p.name]
                .iter()
                .filter_map(|u| entries.get(u).map(|e| (u.clone(), e.clone())))
                .collect();
            let spec = pipeline.stage(&p.name).expect("validated");
            let inputs = &p.inputs;
            let tmp = self.store.begin(&p.name, &p.key)?;
            // The manifest's peak memory is this stage's, not the process's so far.
            cache::reset_peak_rss();
            let start = Instant::now();
            let checkpoints = self.checkpoints(&p.name, &p.key);
            let recording = super::progress::Recording::new(reporter);
            let mut ctx = StageContext::new(
                &p.name,
                &pipeline.scene,
                &upstream,
                inputs,
                &tmp,
                &recording,
                interrupt,
            )
            .with_checkpoints(&checkpoints)
            .with_file(&pipeline.file);
            let result = stage.run(&spec.params, &mut ctx).and_then(|()| {
                if ctx.metrics.is_empty() {
                    Ok(())
                } else {
                    crate::scene::metrics::write(&tmp.join("metrics.arrow"), &p.name, &ctx.metrics)
                        .map_err(StageError::failed)
                }
            });
            let resumed = ctx.resumed().is_some();
            if let Err(e) = result {
                let _ = fs::remove_dir_all(&tmp);
                reporter.stage_finished(i, n, &p.name, "FAILED");
                if let Ok(Some(saved)) = checkpoints.latest() {
                    reporter.println(&format!(
                        "    `{}` keeps its checkpoint ({}); the next run with the same parameters continues from it",
                        p.name, saved.progress
                    ));
                }
                return Err(match e {
                    StageError::Interrupted => RunError::Interrupted(p.name.clone()),
                    source => RunError::Stage {
                        stage: p.name.clone(),
                        source,
                    },
                });
            }
            let run_s = start.elapsed().as_secs_f64();
            let wall_s = if resumed { checkpoints.wall_s() } else { run_s };
            let manifest = Manifest {
                key: p.key.clone(),
                stage: p.name.clone(),
                key_material: p.key_material.clone(),
                outputs: BTreeMap::new(),
                wall_s,
                peak_rss_bytes: cache::peak_rss_bytes(),
                pipe_version: env!("CARGO_PKG_VERSION").to_string(),
                threads: rayon::current_num_threads(),
                created_unix_s: std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_secs())
                    .unwrap_or(0),
                warnings: recording.warnings(),
            };
            let manifest = self.store.commit(&tmp, manifest)?;
            if let Err(e) = checkpoints.remove() {
                // The entry is committed; a leftover checkpoint only takes space (`pipe clean`).
                reporter.println(&format!(
                    "    warning: could not remove the checkpoint of `{}`: {e}",
                    p.name
                ));
            }
            record.stages.insert(p.name.clone(), p.key_material.clone());
            self.save_record(&record)?;
            let total = if resumed {
                format!(", {wall_s:.2} s with the runs it resumed")
            } else {
                String::new()
            };
            reporter.stage_finished(
                i,
                n,
                &p.name,
                &format!("done in {run_s:.2} s{total} ({})", short(&p.key)),
            );
            entries.insert(
                p.name.clone(),
                UpstreamEntry {
                    kind: stage.kind().to_string(),
                    dir: self.store.entry_dir(&p.name, &p.key),
                    manifest,
                },
            );
            report.stages.push((
                p.name.clone(),
                p.key.clone(),
                Outcome::Ran { wall_s: run_s },
            ));
        }
        // Cached stages count as this pipeline's current state too.
        for p in &planned {
            if selected.contains(&p.name) {
                record.stages.insert(p.name.clone(), p.key_material.clone());
            }
        }
        self.save_record(&record)?;
        Ok(report)
    }

    /// The checkpoints of stage `name` at `key` (see [`super::checkpoint`]).
    pub fn checkpoints(&self, name: &str, key: &str) -> Checkpoints {
        Checkpoints::new(self.store.checkpoint_dir(name, key), name, key)
    }

    /// The checkpoint a run of stage `name` at `key` would resume, if any; a problem means it
    /// would be ignored (with a warning) and the stage would start over.
    pub fn checkpoint(&self, name: &str, key: &str) -> Result<Option<Saved>, CheckpointProblem> {
        self.checkpoints(name, key).latest()
    }

    /// Remove cache entries that no pipeline references, and checkpoints that no pipeline
    /// references or whose stage has committed its entry. With `all`, remove every entry and
    /// every checkpoint.
    pub fn clean(&self, registry: &Registry, all: bool) -> Result<Cleaned, RunError> {
        let _lock = WorkdirLock::acquire(self.store.root(), "pipe clean")?;
        self.store.clear_tmp()?;
        let mut keep = BTreeSet::new();
        if !all {
            for rec in self.records() {
                if !rec.file.exists() {
                    continue;
                }
                for (stage, km) in &rec.stages {
                    keep.insert(format!("{stage}-{}", km.key()));
                }
                // Also what the file would produce now, with its own preset.
                if let Ok(p) = super::spec::load(&rec.file, registry, &Default::default())
                    && let Ok((_, planned)) = self.plan(&p, registry)
                {
                    keep.extend(planned.iter().map(|s| format!("{}-{}", s.name, s.key)));
                }
            }
        }
        let remove = |dir: PathBuf| {
            fs::remove_dir_all(&dir).map_err(|source| cache::CacheError::Io { path: dir, source })
        };
        let mut cleaned = Cleaned::default();
        for e in self.store.entries()? {
            if !keep.contains(&e) {
                remove(self.store.cache_dir().join(&e))?;
                cleaned.entries.push(e);
            }
        }
        for c in self.store.checkpoints()? {
            if !keep.contains(&c) || self.store.cache_dir().join(&c).is_dir() {
                remove(self.store.checkpoints_dir().join(&c))?;
                cleaned.checkpoints.push(c);
            }
        }
        Ok(cleaned)
    }
}

impl Workspace {
    /// The committed entry of stage `name` for the pipeline's current parameters.
    pub fn cached_entry(
        &self,
        pipeline: &Pipeline,
        registry: &Registry,
        name: &str,
    ) -> Result<PathBuf, RunError> {
        let (graph, planned) = self.plan(pipeline, registry)?;
        let p = planned.iter().find(|p| p.name == name).ok_or_else(|| {
            RunError::Selection(format!(
                "the pipeline has no stage `{name}` (stages: {})",
                graph.order.join(", ")
            ))
        })?;
        match &p.state {
            StageState::Cached(_) => Ok(self.store.entry_dir(name, &p.key)),
            StageState::Stale(why) => Err(RunError::Selection(format!(
                "stage `{name}` is not cached for the current parameters ({}); run `pipe run {} --until {name}` first",
                why.join("; "),
                pipeline.file.display()
            ))),
            StageState::NotRun => Err(RunError::Selection(format!(
                "stage `{name}` has not run yet; run `pipe run {} --until {name}` first",
                pipeline.file.display()
            ))),
        }
    }
}

/// First 12 hex digits of a key.
pub fn short(key: &str) -> &str {
    &key[..12.min(key.len())]
}

fn absolute(p: &Path) -> PathBuf {
    fs::canonicalize(p).unwrap_or_else(|_| {
        std::env::current_dir()
            .map(|d| d.join(p))
            .unwrap_or_else(|_| p.to_path_buf())
    })
}

/// Human reasons why `cur` differs from `prev` (the last run's key material of stage `name`).
fn explain(
    name: &str,
    prev: &KeyMaterial,
    cur: &KeyMaterial,
    planned: &[PlannedStage],
) -> Vec<String> {
    let mut out = Vec::new();
    if prev.key_format != cur.key_format {
        out.push(format!(
            "cache key format changed {} → {}",
            prev.key_format, cur.key_format
        ));
    }
    if prev.version != cur.version {
        out.push(format!(
            "code version of `{}` changed {} → {}",
            cur.kind, prev.version, cur.version
        ));
    }
    diff_values(
        &format!("param `{name}"),
        &prev.params,
        &cur.params,
        &mut out,
    );
    diff_values("scene `scene", &prev.scene, &cur.scene, &mut out);
    for (u, key) in &cur.upstream {
        match prev.upstream.get(u) {
            Some(k) if k == key => {}
            _ => {
                let verb = match planned.iter().find(|p| &p.name == u).map(|p| &p.state) {
                    Some(StageState::Cached(_)) => "changed",
                    _ => "will re-run",
                };
                out.push(format!("upstream `{u}` {verb}"));
            }
        }
    }
    for u in prev
        .upstream
        .keys()
        .filter(|u| !cur.upstream.contains_key(*u))
    {
        out.push(format!("upstream `{u}` no longer used"));
    }
    let mut changed: Vec<String> = Vec::new();
    for (f, h) in &cur.inputs {
        match prev.inputs.get(f) {
            Some(p) if p == h => {}
            Some(_) => changed.push(format!("input file `{f}` changed")),
            None => changed.push(format!("new input file `{f}`")),
        }
    }
    for f in prev.inputs.keys().filter(|f| !cur.inputs.contains_key(*f)) {
        changed.push(format!("input file `{f}` no longer used"));
    }
    if changed.len() > 3 {
        let more = changed.len() - 3;
        changed.truncate(3);
        changed.push(format!("and {more} more input changes"));
    }
    out.extend(changed);
    if prev.schemas != cur.schemas {
        out.push("output schema version changed".into());
    }
    out
}

fn diff_values(prefix: &str, a: &Value, b: &Value, out: &mut Vec<String>) {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            for (k, va) in x {
                let p = format!("{prefix}.{k}");
                match y.get(k) {
                    Some(vb) => diff_values(&p, va, vb, out),
                    None => out.push(format!(
                        "{}` removed (was {va})",
                        p.replacen("`scene.", "`", 1)
                    )),
                }
            }
            for (k, vb) in y.iter().filter(|(k, _)| !x.contains_key(*k)) {
                out.push(format!(
                    "{}` added ({vb})",
                    format!("{prefix}.{k}").replacen("`scene.", "`", 1)
                ));
            }
        }
        (a, b) if a != b => {
            out.push(format!(
                "{}` changed {a} → {b}",
                prefix.replacen("`scene.", "`", 1)
            ));
        }
        _ => {}
    }
}
