//! `pipe sweep`: every combination of `--over` values, run through the runner one after the
//! other. The cache is content-addressed, so variants whose upstream parameters are equal share
//! those stages' entries (five `material` variants share one `warmup`), and a sweep that was
//! interrupted continues where it stopped: finished variants are all cached, an unfinished
//! stage resumes from its checkpoint. Each variant's result row comes from its cache entries
//! (`evaluation.json` and the manifests), never from the process that ran it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::pipeline::progress::Reporter;
use crate::pipeline::runner::{Outcome, RunError, RunOptions, StageState, Workspace};
use crate::pipeline::spec::{self, Overrides, Pipeline, Preset};
use crate::pipeline::stage::Registry;

/// One `--over KEY=V1,V2,...`: `preset` or a `stage.key` (as `--set` takes it).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Axis {
    /// `preset` or `stage.key[.subkey]`.
    pub key: String,
    /// The values, as written (YAML for parameters).
    pub values: Vec<String>,
}

impl Axis {
    /// Parse `KEY=V1,V2,...`. Commas inside brackets, braces or quotes belong to the value
    /// (`material.learn=[E,nu],[E]`).
    pub fn parse(raw: &str) -> Result<Self, String> {
        let hint = "write it as --over stage.key=v1,v2,... or --over preset=draft,standard";
        let (key, rhs) = raw
            .split_once('=')
            .ok_or_else(|| format!("--over {raw}: missing `=`; {hint}"))?;
        let key = key.trim().to_string();
        let valid_key = key == "preset"
            || (key.split('.').count() >= 2 && key.split('.').all(|p| !p.trim().is_empty()));
        if !valid_key {
            return Err(format!(
                "--over {raw}: `{key}` is neither `preset` nor stage.key; {hint}"
            ));
        }
        let values = split_top_level(rhs);
        if values.iter().any(|v| v.trim().is_empty()) {
            return Err(format!("--over {raw}: an empty value; {hint}"));
        }
        if key == "preset"
            && let Some(bad) = values.iter().find(|v| Preset::parse(v.trim()).is_none())
        {
            return Err(format!(
                "--over {raw}: unknown preset `{bad}`; expected draft, standard or paper"
            ));
        }
        let mut seen = Vec::new();
        for v in &values {
            if seen.contains(v) {
                return Err(format!("--over {raw}: the value `{v}` is listed twice"));
            }
            seen.push(v.clone());
        }
        Ok(Self {
            key,
            values: values.into_iter().map(|v| v.trim().to_string()).collect(),
        })
    }
}

/// Split at commas outside `[]`, `{}` and quotes.
fn split_top_level(s: &str) -> Vec<String> {
    let (mut out, mut cur, mut depth, mut quote) = (Vec::new(), String::new(), 0i32, None);
    for c in s.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '"' | '\'') => quote = Some(c),
            (None, '[' | '{') => depth += 1,
            (None, ']' | '}') => depth -= 1,
            (None, ',') if depth == 0 => {
                out.push(std::mem::take(&mut cur));
                continue;
            }
            _ => {}
        }
        cur.push(c);
    }
    out.push(cur);
    out
}

/// One variant: a value per axis.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Variant {
    /// 0-based, in grid order (the first axis varies slowest).
    pub index: usize,
    /// Axis key → value.
    pub settings: BTreeMap<String, String>,
}

impl Variant {
    /// `material.grid=24, preset=draft`.
    pub fn label(&self, axes: &[Axis]) -> String {
        axes.iter()
            .map(|a| format!("{}={}", a.key, self.settings[&a.key]))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The overrides of this variant on top of the command line's.
    pub fn overrides(&self, base: &Overrides) -> Overrides {
        let mut o = base.clone();
        for (k, v) in &self.settings {
            if k == "preset" {
                o.preset = Preset::parse(v);
            } else {
                o.sets.push(format!("{k}={v}"));
            }
        }
        o
    }
}

/// The grid: every combination of the axes' values.
pub fn variants(axes: &[Axis]) -> Vec<Variant> {
    let mut out = vec![BTreeMap::new()];
    for a in axes {
        out = out
            .into_iter()
            .flat_map(|s: BTreeMap<String, String>| {
                a.values.iter().map(move |v| {
                    let mut s = s.clone();
                    s.insert(a.key.clone(), v.clone());
                    s
                })
            })
            .collect();
    }
    out.into_iter()
        .enumerate()
        .map(|(index, settings)| Variant { index, settings })
        .collect()
}

/// The result of one variant, read from its cache entries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VariantResult {
    /// The variant.
    pub variant: Variant,
    /// `material.grid=24, preset=draft`.
    pub label: String,
    /// Effective preset.
    pub preset: String,
    /// Sum of the stages' wall times (s): what the variant costs from scratch, cached
    /// stages counted with the time they took when they ran.
    pub wall_s: f64,
    /// Each stage's wall time (s).
    pub stage_wall_s: BTreeMap<String, f64>,
    /// Largest peak resident memory of its stages, bytes (0: unknown).
    pub peak_rss_bytes: u64,
    /// Stages executed by this `pipe sweep` invocation (the others came from the cache).
    pub ran: Vec<String>,
    /// Each stage's cache key.
    pub keys: BTreeMap<String, String>,
    /// The variant's `evaluation.json`, when the pipeline has an `evaluate` stage.
    pub evaluation: Option<Value>,
}

/// A finished sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepSummary {
    /// `name:` of the pipeline file.
    pub name: String,
    /// The pipeline file.
    pub file: PathBuf,
    /// The axes, in command-line order.
    pub axes: Vec<Axis>,
    /// One per variant, in grid order.
    pub variants: Vec<VariantResult>,
}

/// The axes of a sweep: the pipeline file's `sweep:` block, each replaced by a command-line
/// `--over` of the same key, then the other `--over` axes in their order.
pub fn axes(
    file: &Path,
    registry: &Registry,
    base: &Overrides,
    over: &[Axis],
) -> Result<Vec<Axis>, RunError> {
    let from_file = spec::load(file, registry, base)?.sweep;
    let mut axes: Vec<Axis> = from_file
        .into_iter()
        .map(|a| over.iter().find(|o| o.key == a.key).cloned().unwrap_or(a))
        .collect();
    for o in over {
        if !axes.iter().any(|a| a.key == o.key) {
            axes.push(o.clone());
        }
    }
    if axes.is_empty() {
        return Err(RunError::Usage(format!(
            "nothing to sweep: {} has no `sweep:` block and no --over was given \
             (e.g. --over material.cells=12,16,24)",
            file.display()
        )));
    }
    Ok(axes)
}

/// Load every variant's pipeline (so a bad value is reported before anything runs).
pub fn plan(
    file: &Path,
    registry: &Registry,
    base: &Overrides,
    axes: &[Axis],
) -> Result<Vec<(Variant, Pipeline)>, RunError> {
    let mut keys = std::collections::BTreeSet::new();
    for a in axes {
        if !keys.insert(a.key.clone()) {
            return Err(RunError::Usage(format!(
                "--over {}: the key is given twice; list all its values in one --over",
                a.key
            )));
        }
    }
    variants(axes)
        .into_iter()
        .map(|v| {
            let p = spec::load(file, registry, &v.overrides(base)).map_err(|mut e| {
                e.message = format!("variant {}: {}", v.label(axes), e.message);
                e
            })?;
            Ok((v, p))
        })
        .collect()
}

/// What to sweep: a pipeline file, the command line's `--preset`/`--set`, and the axes.
#[derive(Debug, Clone)]
pub struct SweepRequest {
    /// The pipeline file.
    pub file: PathBuf,
    /// `--preset` and `--set` shared by every variant (a variant's values win).
    pub base: Overrides,
    /// The `--over` axes (merged with the file's `sweep:` block by [`axes`]).
    pub axes: Vec<Axis>,
}

/// Run every variant (cached ones cost nothing) and read their results.
pub fn run(
    ws: &Workspace,
    registry: &Registry,
    request: &SweepRequest,
    reporter: &Reporter,
    interrupt: &AtomicBool,
    command: &str,
) -> Result<SweepSummary, RunError> {
    let file = &request.file;
    let axes = &axes(file, registry, &request.base, &request.axes)?;
    let planned = plan(file, registry, &request.base, axes)?;
    let name = planned
        .first()
        .map(|(_, p)| p.name.clone())
        .unwrap_or_default();
    let n = planned.len();
    let mut results = Vec::new();
    for (variant, pipeline) in &planned {
        let label = variant.label(axes);
        reporter.println(&format!("sweep {}/{n}: {label}", variant.index + 1));
        let report = ws.run(
            pipeline,
            registry,
            &RunOptions::default(),
            reporter,
            interrupt,
            command,
        )?;
        ws.pin_record(&pipeline.file, &label)?;
        let ran = report
            .stages
            .iter()
            .filter(|(_, _, o)| matches!(o, Outcome::Ran { .. }))
            .map(|(s, _, _)| s.clone())
            .collect();
        results.push(result_of(ws, registry, pipeline, variant, &label, ran)?);
    }
    Ok(SweepSummary {
        name,
        file: file.clone(),
        axes: axes.clone(),
        variants: results,
    })
}

/// A variant's row from its cache entries.
fn result_of(
    ws: &Workspace,
    registry: &Registry,
    pipeline: &Pipeline,
    variant: &Variant,
    label: &str,
    ran: Vec<String>,
) -> Result<VariantResult, RunError> {
    let (_, planned) = ws.plan(pipeline, registry)?;
    let mut out = VariantResult {
        variant: variant.clone(),
        label: label.to_string(),
        preset: pipeline.preset.name().to_string(),
        wall_s: 0.0,
        stage_wall_s: BTreeMap::new(),
        peak_rss_bytes: 0,
        ran,
        keys: BTreeMap::new(),
        evaluation: None,
    };
    for p in &planned {
        let StageState::Cached(m) = &p.state else {
            return Err(RunError::Output(format!(
                "variant {label}: stage `{}` is not cached after its run",
                p.name
            )));
        };
        out.wall_s += m.wall_s;
        out.stage_wall_s.insert(p.name.clone(), m.wall_s);
        out.peak_rss_bytes = out.peak_rss_bytes.max(m.peak_rss_bytes);
        out.keys.insert(p.name.clone(), p.key.clone());
        let kind = p.key_material.kind.as_str();
        if kind == "evaluate" {
            let path = ws.store.entry_dir(&p.name, &p.key).join("evaluation.json");
            out.evaluation =
                Some(crate::io::read_json(&path).map_err(|e| RunError::Output(e.to_string()))?);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn over_splits_at_top_level_commas_only() {
        let a = Axis::parse("material.learn=[E,nu],[E], 'a,b'").unwrap();
        assert_eq!(a.key, "material.learn");
        assert_eq!(a.values, vec!["[E,nu]", "[E]", "'a,b'"]);
        let p = Axis::parse("preset=draft,standard").unwrap();
        assert_eq!(p.values, vec!["draft", "standard"]);
    }

    #[test]
    fn bad_over_values_are_named() {
        for (raw, needle) in [
            ("material.grid", "missing `=`"),
            ("grid=1,2", "neither `preset` nor stage.key"),
            ("preset=draft,fast", "unknown preset `fast`"),
            ("material.grid=24,,32", "an empty value"),
            ("material.grid=24,24", "listed twice"),
        ] {
            let e = Axis::parse(raw).unwrap_err();
            assert!(e.contains(needle), "{raw}: {e}");
        }
    }

    #[test]
    fn the_grid_is_the_product_with_the_first_axis_slowest() {
        let axes = [
            Axis::parse("material.grid=24,32,48").unwrap(),
            Axis::parse("preset=draft,standard").unwrap(),
        ];
        let v = variants(&axes);
        assert_eq!(v.len(), 6);
        assert_eq!(v[1].label(&axes), "material.grid=24, preset=standard");
        assert_eq!(v[5].label(&axes), "material.grid=48, preset=standard");
        let o = v[1].overrides(&Overrides {
            preset: Some(Preset::Paper),
            sets: vec!["warmup.epochs=5".into()],
        });
        assert_eq!(o.preset, Some(Preset::Standard));
        assert_eq!(o.sets, vec!["warmup.epochs=5", "material.grid=24"]);
    }
}
