//! The report as data (`report.json`), assembled from the stages' cache entries: settings,
//! timings, the parameter table, per-epoch curves, parameter paths against the truth, per-frame
//! scores per test view, image strips, and the figures drawn from them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;
use serde_json::Value;

use crate::ReportError;
use crate::input::{RunSummary, StageRun};
use crate::plot::{Figure, Series};
use crate::published::{Published, table1};
use crate::tables::Metrics;

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// `pipe-report <version>`.
    pub tool: String,
    /// One per pipeline file, in command-line order.
    pub scenes: Vec<SceneReport>,
    /// The seed paper's reference figures (published, other data).
    pub published: Published,
}

/// One pipeline file's results.
#[derive(Debug, Clone, Serialize)]
pub struct SceneReport {
    /// Pipeline name.
    pub name: String,
    /// Pipeline file.
    pub file: PathBuf,
    /// Effective preset.
    pub preset: String,
    /// The resolved `scene:` section.
    pub scene: Value,
    /// Every stage.
    pub stages: Vec<StageRow>,
    /// Sum of the cached stages' wall times, s.
    pub total_wall_s: f64,
    /// Largest peak resident memory of the cached stages, bytes (0: unknown).
    pub peak_rss_bytes: u64,
    /// `evaluation.json` of the `evaluate` stage, verbatim.
    pub evaluation: Option<Value>,
    /// Learned parameters against the ground truth.
    pub parameters: Vec<ParameterRow>,
    /// Per-epoch losses and training PSNR of each stage.
    pub curves: Vec<Curve>,
    /// Per-epoch values of every learned parameter, with the truth when known.
    pub parameter_paths: Vec<ParameterPath>,
    /// Per test view, PSNR (dB) and SSIM at every evaluated frame.
    pub view_scores: Vec<ViewScores>,
    /// Mean test-view PSNR (dB) per frame, aggregated from `evaluate`'s metrics table.
    pub test_psnr_per_frame: Vec<(u16, f64)>,
    /// Mean training-view PSNR (dB) per frame.
    pub train_psnr_per_frame: Vec<(u16, f64)>,
    /// Image strips (captured | ours | 4× error), paths relative to the report folder.
    pub strips: Vec<StripRef>,
    /// `evaluate`'s GIF per test view, relative to the report folder.
    pub gifs: Vec<GifRef>,
    /// Figures: id and file, relative to the report folder.
    pub figures: Vec<FigureRef>,
}

impl SceneReport {
    /// Every stage's warnings as (stage, warning), in stage order: the *Warnings* list and
    /// the summary's count in both reports.
    pub fn warnings(&self) -> Vec<(&str, &str)> {
        self.stages
            .iter()
            .flat_map(|st| st.warnings.iter().map(|w| (st.name.as_str(), w.as_str())))
            .collect()
    }

    /// The "Scene and settings" table's rows (setting, value), shared by the HTML and
    /// Markdown reports.
    pub fn settings_rows(&self) -> Vec<(&'static str, String)> {
        let field = |k: &str| crate::text::compact(self.scene.get(k).unwrap_or(&Value::Null));
        let substeps = match self.scene.get("prefer_substeps").and_then(Value::as_u64) {
            Some(n) => format!("{n} a frame where a fixed count may (the maker's step)"),
            None => "automatic (the stability limit)".into(),
        };
        vec![
            ("pipeline file", self.file.display().to_string()),
            ("preset", self.preset.clone()),
            ("dataset", field("dataset")),
            ("scene folder", field("path")),
            ("material family", field("material")),
            ("test views", field("test_views")),
            ("density (kg/m³)", field("density")),
            ("gravity (m/s²)", field("gravity")),
            ("boundaries", field("boundaries")),
            ("MPM substeps", substeps),
        ]
    }
}

/// One stage's state and cost.
#[derive(Debug, Clone, Serialize)]
pub struct StageRow {
    /// Name.
    pub name: String,
    /// Kind.
    pub kind: String,
    /// `done` (its result is in the cache for the current parameters), `stale` or `not run`.
    pub state: String,
    /// Why stale.
    pub reasons: Vec<String>,
    /// Cache key.
    pub key: String,
    /// Wall time, s.
    pub wall_s: Option<f64>,
    /// Peak resident memory while it ran, bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Threads.
    pub threads: Option<usize>,
    /// Resolved parameters.
    pub params: Value,
    /// The warnings it gave when it ran.
    pub warnings: Vec<String>,
}

/// A learned parameter against the truth.
#[derive(Debug, Clone, Serialize)]
pub struct ParameterRow {
    /// Name (`E`, `nu`, …, `v0`).
    pub name: String,
    /// Unit.
    pub unit: String,
    /// Learned value (a number, or `[x, y, z]` for v0).
    pub learned: Value,
    /// Ground truth, when the scene has one.
    pub truth: Value,
    /// Error as `evaluate` computes it.
    pub error: Option<f64>,
    /// What the error measures.
    pub error_kind: String,
    /// How closely the frames bound it (`material.json` `profile`; empty when not profiled).
    pub bounded: String,
}

/// One per-epoch curve.
#[derive(Debug, Clone, Serialize)]
pub struct Curve {
    /// Stage.
    pub stage: String,
    /// Metric.
    pub metric: String,
    /// `(epoch, value)`.
    pub points: Vec<(f64, f64)>,
}

/// A parameter's path over the epochs.
#[derive(Debug, Clone, Serialize)]
pub struct ParameterPath {
    /// Stage.
    pub stage: String,
    /// Parameter (`E`, `vx`, …).
    pub parameter: String,
    /// Unit.
    pub unit: String,
    /// `(epoch, value)`.
    pub points: Vec<(f64, f64)>,
    /// Ground truth.
    pub truth: Option<f64>,
}

/// Per-frame scores of one view.
#[derive(Debug, Clone, Serialize)]
pub struct ViewScores {
    /// Camera.
    pub view: u16,
    /// `(frame, PSNR dB)`.
    pub psnr: Vec<(u16, f64)>,
    /// `(frame, SSIM)`.
    pub ssim: Vec<(u16, f64)>,
}

/// A strip image.
#[derive(Debug, Clone, Serialize)]
pub struct StripRef {
    /// Camera.
    pub view: u16,
    /// Frame.
    pub frame: u16,
    /// `first`, `middle`, `last`.
    pub position: String,
    /// PNG, relative to the report folder.
    pub file: PathBuf,
}

/// An animation.
#[derive(Debug, Clone, Serialize)]
pub struct GifRef {
    /// Camera.
    pub view: u16,
    /// GIF, relative to the report folder.
    pub file: PathBuf,
}

/// A figure file.
#[derive(Debug, Clone, Serialize)]
pub struct FigureRef {
    /// Identifier (also the HTML element id).
    pub id: String,
    /// Caption.
    pub title: String,
    /// SVG, relative to the report folder.
    pub file: PathBuf,
}

/// A figure with its rendered SVG.
#[derive(Debug, Clone)]
pub struct Drawn {
    /// Where it is listed.
    pub reference: FigureRef,
    /// The SVG document.
    pub svg: String,
}

/// Unit of a learned quantity.
pub fn unit(name: &str) -> &'static str {
    match name {
        "E" | "yield_stress" | "bulk_modulus" => "Pa",
        "viscosity" => "Pa s",
        "friction_angle" => "deg",
        "vx" | "vy" | "vz" | "v0" => "m/s",
        "wx" | "wy" | "wz" => "rad/s",
        _ => "",
    }
}

/// Material parameters the `material` stage learns (its per-epoch metric names).
const MATERIAL: [&str; 6] = [
    "E",
    "nu",
    "yield_stress",
    "viscosity",
    "bulk_modulus",
    "friction_angle",
];

/// Parameters spanning decades: plotted on a log axis, their error in decades.
fn spans_decades(name: &str) -> bool {
    matches!(name, "E" | "yield_stress" | "viscosity" | "bulk_modulus")
}

fn read_json(path: &Path) -> Result<Value, ReportError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| ReportError::Json {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

fn entry<'a>(run: &'a RunSummary, kind: &str) -> Option<(&'a StageRun, &'a Path)> {
    run.stages
        .iter()
        .find(|s| s.kind == kind)
        .and_then(|s| s.dir.as_deref().map(|d| (s, d)))
}

fn number(v: &Value, key: &str) -> Option<f64> {
    v.get(key).and_then(Value::as_f64)
}

/// The parameter table: `evaluation.json` when `evaluate` ran, else `material.json` and
/// `velocity.json` (no truth then).
fn parameters(
    run: &RunSummary,
    evaluation: Option<&Value>,
) -> Result<Vec<ParameterRow>, ReportError> {
    let error_kind = |name: &str| {
        if name == "v0" {
            "|v0 − v0_true| (m/s)"
        } else if spans_decades(name) {
            "|log10 learned − log10 true|"
        } else {
            "|learned − true|"
        }
        .to_string()
    };
    let mut rows = Vec::new();
    if let Some(e) = evaluation {
        let truth = e.get("ground_truth").cloned().unwrap_or(Value::Null);
        let errors = e.get("errors").cloned().unwrap_or(Value::Null);
        if let Some(learned) = e.get("learned").and_then(Value::as_object) {
            for (name, v) in learned {
                rows.push(ParameterRow {
                    name: name.clone(),
                    unit: unit(name).into(),
                    learned: v.clone(),
                    truth: truth.get(name).cloned().unwrap_or(Value::Null),
                    error: number(&errors, name),
                    error_kind: error_kind(name),
                    bounded: String::new(),
                });
            }
        }
        if let Some(v0) = e.get("initial_velocity") {
            rows.push(ParameterRow {
                name: "v0".into(),
                unit: "m/s".into(),
                learned: v0.clone(),
                truth: e.get("ground_truth_v0").cloned().unwrap_or(Value::Null),
                error: number(&errors, "v0_m_s"),
                error_kind: error_kind("v0"),
                bounded: String::new(),
            });
        }
        if let Some(w) = e.get("angular_velocity") {
            rows.push(ParameterRow {
                name: "ω".into(),
                unit: "rad/s".into(),
                learned: w.clone(),
                truth: e
                    .get("ground_truth_angular_velocity")
                    .cloned()
                    .unwrap_or(Value::Null),
                error: number(&errors, "angular_velocity_rad_s"),
                error_kind: "|ω − ω_true| (rad/s)".into(),
                bounded: String::new(),
            });
        }
        with_bounds(run, &mut rows)?;
        rows.extend(field_part_rows(run)?);
        return Ok(rows);
    }
    if let Some((_, dir)) = entry(run, "material") {
        let m = read_json(&dir.join("material.json"))?;
        for (name, key) in [
            ("E", "youngs_modulus"),
            ("nu", "poisson_ratio"),
            ("yield_stress", "yield_stress"),
            ("viscosity", "viscosity"),
            ("bulk_modulus", "bulk_modulus"),
            ("friction_angle", "friction_angle_deg"),
        ] {
            if let Some(v) = m.get(key).filter(|v| !v.is_null()) {
                rows.push(ParameterRow {
                    name: name.into(),
                    unit: unit(name).into(),
                    learned: v.clone(),
                    truth: Value::Null,
                    error: None,
                    error_kind: error_kind(name),
                    bounded: String::new(),
                });
            }
        }
    }
    if let Some((_, dir)) = entry(run, "velocity") {
        let v = read_json(&dir.join("velocity.json"))?;
        if let Some(v0) = v.get("initial_velocity") {
            rows.push(ParameterRow {
                name: "v0".into(),
                unit: "m/s".into(),
                learned: v0.clone(),
                truth: Value::Null,
                error: None,
                error_kind: error_kind("v0"),
                bounded: String::new(),
            });
        }
    }
    with_bounds(run, &mut rows)?;
    rows.extend(field_part_rows(run)?);
    Ok(rows)
}

/// A row per part of a kept material field (`material.json` `field.parts`): the part's median
/// E and how closely the frames bound it.
fn field_part_rows(run: &RunSummary) -> Result<Vec<ParameterRow>, ReportError> {
    let Some((_, dir)) = entry(run, "material") else {
        return Ok(Vec::new());
    };
    let m = read_json(&dir.join("material.json"))?;
    let Some(parts) = m.pointer("/field/parts/parts").and_then(Value::as_array) else {
        return Ok(Vec::new());
    };
    let k = parts.len();
    Ok(parts
        .iter()
        .enumerate()
        .map(|(i, part)| {
            let share = part
                .get("volume_share")
                .and_then(Value::as_f64)
                .unwrap_or(f64::NAN);
            ParameterRow {
                name: format!(
                    "E, field part {} of {k} ({:.0} % of the volume)",
                    i + 1,
                    100.0 * share
                ),
                unit: unit("E").into(),
                learned: part
                    .get("youngs_modulus_median")
                    .cloned()
                    .unwrap_or(Value::Null),
                truth: Value::Null,
                error: None,
                error_kind: "median of the part's particles".into(),
                bounded: part.get("profile").map(bounds_text).unwrap_or_default(),
            }
        })
        .collect())
}

/// Fills each row's `bounded` from the `material` entry's profile.
fn with_bounds(run: &RunSummary, rows: &mut [ParameterRow]) -> Result<(), ReportError> {
    let Some((_, dir)) = entry(run, "material") else {
        return Ok(());
    };
    let m = read_json(&dir.join("material.json"))?;
    let Some(profile) = m.get("profile").and_then(Value::as_array) else {
        return Ok(());
    };
    // With a field kept, E's row holds the particles' median while the profile was taken
    // about the one-material fit the field started from: the bounds say so.
    let field = m.get("model").and_then(Value::as_str) == Some("field");
    for p in profile {
        let Some(name) = p.get("param").and_then(Value::as_str) else {
            continue;
        };
        if let Some(row) = rows.iter_mut().find(|r| r.name == name) {
            row.bounded = if field && name == "E" {
                let at = p
                    .get("value")
                    .and_then(Value::as_f64)
                    .map_or_else(|| "—".to_string(), crate::text::num);
                format!("the one-material fit ({at}): {}", bounds_text(p))
            } else {
                bounds_text(p)
            };
        }
    }
    Ok(())
}

/// One side of a parameter's profile in words: `from 5.73e5` / `to 1.81e6` where the frames
/// bound it, else how far it was tried.
fn bounds_text(p: &Value) -> String {
    let side = |k: usize| -> String {
        let (key, bound, open) = if k == 0 {
            ("below", "from", "down to")
        } else {
            ("above", "to", "up to")
        };
        let end = p
            .get("ends")
            .and_then(|e| e.get(k))
            .and_then(Value::as_str)
            .unwrap_or("");
        let moves = p.get(key).and_then(Value::as_array);
        let value = |m: &Value| m.get("value").and_then(Value::as_f64);
        let rise = |m: &Value| m.get("rise_pct").and_then(Value::as_f64).unwrap_or(0.0);
        // A better side shows its best move, the others their last.
        let last = match end {
            "better" => moves
                .and_then(|m| m.iter().min_by(|a, b| rise(a).total_cmp(&rise(b))))
                .and_then(value),
            _ => moves.and_then(|m| m.last()).and_then(value),
        };
        match (end, last) {
            ("bounded", Some(v)) => format!("{bound} {}", crate::text::num(v)),
            ("better", Some(v)) => format!("{} is better (fit stopped short)", crate::text::num(v)),
            ("range", _) => format!("{open} the end of its range"),
            (_, Some(v)) => format!("not bounded {open} {}", crate::text::num(v)),
            _ => "not profiled".into(),
        }
    };
    format!("{}; {}", side(0), side(1))
}

/// Build one scene's report; strips and GIFs are referenced relative to `out`, figures are
/// named `plots/<prefix><id>.svg`.
pub fn scene(
    run: &RunSummary,
    out: &Path,
    prefix: &str,
) -> Result<(SceneReport, Vec<Drawn>), ReportError> {
    let evaluation = match entry(run, "evaluate") {
        Some((_, dir)) => Some(read_json(&dir.join("evaluation.json"))?),
        None => None,
    };
    let truth_of = |name: &str| -> Option<f64> {
        let e = evaluation.as_ref()?;
        match name {
            "vx" | "vy" | "vz" => {
                let i = ["vx", "vy", "vz"].iter().position(|n| *n == name)?;
                e.get("ground_truth_v0")?.get(i)?.as_f64()
            }
            _ => e.get("ground_truth")?.get(name)?.as_f64(),
        }
    };
    let mut curves = Vec::new();
    let mut paths = Vec::new();
    let mut view_scores = Vec::new();
    let (mut test_means, mut train_means) = (Vec::new(), Vec::new());
    for s in &run.stages {
        let Some(dir) = &s.dir else { continue };
        let table = dir.join("metrics.arrow");
        if !table.is_file() {
            continue;
        }
        let m = Metrics::read(&table)?;
        let names = m.epoch_metrics()?;
        for metric in ["loss", "train_psnr"] {
            if names.iter().any(|n| n == metric) {
                curves.push(Curve {
                    stage: s.name.clone(),
                    metric: metric.into(),
                    points: m.epoch_curve(metric)?,
                });
            }
        }
        let learned: Vec<&str> = match s.kind.as_str() {
            "velocity" => vec!["vx", "vy", "vz", "wx", "wy", "wz"],
            "material" => MATERIAL.to_vec(),
            _ => Vec::new(),
        };
        for p in learned {
            if names.iter().any(|n| n == p) {
                paths.push(ParameterPath {
                    stage: s.name.clone(),
                    parameter: p.into(),
                    unit: unit(p).into(),
                    points: m.epoch_curve(p)?,
                    truth: truth_of(p),
                });
            }
        }
        if s.kind == "evaluate" {
            let psnr = m.view_frame_scores("test_psnr")?;
            let mut ssim = m.view_frame_scores("test_ssim")?;
            for (view, psnr) in psnr {
                view_scores.push(ViewScores {
                    view,
                    psnr,
                    ssim: ssim.remove(&view).unwrap_or_default(),
                });
            }
            test_means = m.frame_means("test_psnr")?;
            train_means = m.frame_means("train_psnr")?;
        }
    }
    let rel = |p: &Path| -> PathBuf { p.strip_prefix(out).unwrap_or(p).to_path_buf() };
    let mut gifs = Vec::new();
    for g in &run.gifs {
        let dest = out.join("images").join(format!("{prefix}v{}.gif", g.view));
        copy(&g.path, &dest)?;
        gifs.push(GifRef {
            view: g.view,
            file: rel(&dest),
        });
    }
    let stages: Vec<StageRow> = run
        .stages
        .iter()
        .map(|s| StageRow {
            name: s.name.clone(),
            kind: s.kind.clone(),
            state: s.state.clone(),
            reasons: s.reasons.clone(),
            key: s.key.clone(),
            wall_s: s.wall_s,
            peak_rss_bytes: s.peak_rss_bytes,
            threads: s.threads,
            params: s.params.clone(),
            // A stage's own name leads many of its messages; the report names the stage.
            warnings: s
                .warnings
                .iter()
                .map(|w| {
                    w.strip_prefix(&format!("{}: ", s.kind))
                        .unwrap_or(w)
                        .to_string()
                })
                .collect(),
        })
        .collect();
    let mut report = SceneReport {
        name: run.name.clone(),
        file: run.file.clone(),
        preset: run.preset.clone(),
        scene: run.scene.clone(),
        total_wall_s: stages.iter().filter_map(|s| s.wall_s).sum(),
        peak_rss_bytes: stages
            .iter()
            .filter_map(|s| s.peak_rss_bytes)
            .max()
            .unwrap_or(0),
        stages,
        parameters: parameters(run, evaluation.as_ref())?,
        evaluation,
        curves,
        parameter_paths: paths,
        view_scores,
        test_psnr_per_frame: test_means,
        train_psnr_per_frame: train_means,
        strips: run
            .strips
            .iter()
            .map(|s| StripRef {
                view: s.view,
                frame: s.frame,
                position: s.position.clone(),
                file: rel(&s.path),
            })
            .collect(),
        gifs,
        figures: Vec::new(),
    };
    let drawn = figures(&report, prefix)?;
    report.figures = drawn.iter().map(|d| d.reference.clone()).collect();
    Ok((report, drawn))
}

fn copy(from: &Path, to: &Path) -> Result<(), ReportError> {
    if let Some(dir) = to.parent() {
        std::fs::create_dir_all(dir).map_err(|source| ReportError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    std::fs::copy(from, to)
        .map(|_| ())
        .map_err(|source| ReportError::Io {
            path: from.to_path_buf(),
            source,
        })
}

fn frames_f64(v: &[(u16, f64)]) -> Vec<(f64, f64)> {
    v.iter().map(|(f, x)| (f64::from(*f), *x)).collect()
}

/// The figures of a scene, drawn.
fn figures(r: &SceneReport, prefix: &str) -> Result<Vec<Drawn>, ReportError> {
    let mut figs: Vec<(String, Figure)> = Vec::new();
    for c in r.curves.iter().filter(|c| c.metric == "loss") {
        figs.push((
            format!("loss_{}", c.stage),
            Figure {
                title: format!("{}: loss per epoch", c.stage),
                x_label: "epoch".into(),
                y_label: "loss".into(),
                series: vec![Series::line(&c.stage, c.points.clone(), 0)],
                log_y: true,
                log_x: false,
            },
        ));
    }
    for c in r.curves.iter().filter(|c| c.metric == "train_psnr") {
        figs.push((
            format!("train_psnr_{}", c.stage),
            Figure {
                title: format!("{}: training-view PSNR per epoch", c.stage),
                x_label: "epoch".into(),
                y_label: "PSNR (dB)".into(),
                series: vec![Series::line(&c.stage, c.points.clone(), 0)],
                log_y: false,
                log_x: false,
            },
        ));
    }
    // Parameter paths: one figure per material parameter, one for the initial velocity's
    // components and one for the angular velocity.
    let extent = |p: &ParameterPath| {
        let xs: Vec<f64> = p.points.iter().map(|q| q.0).collect();
        let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        (lo, hi.max(lo + 1.0))
    };
    let mut groups: BTreeMap<(String, String), Vec<&ParameterPath>> = BTreeMap::new();
    for p in &r.parameter_paths {
        let group = match p.parameter.as_str() {
            "vx" | "vy" | "vz" => "v0".to_string(),
            "wx" | "wy" | "wz" => "omega".to_string(),
            other => other.to_string(),
        };
        groups.entry((p.stage.clone(), group)).or_default().push(p);
    }
    for ((stage, group), members) in groups {
        let mut series = Vec::new();
        for (i, p) in members.iter().enumerate() {
            series.push(Series::line(&p.parameter, p.points.clone(), i));
            if let Some(t) = p.truth {
                let (x0, x1) = extent(p);
                series.push(Series::reference(
                    format!("{} true", p.parameter),
                    t,
                    x0,
                    x1,
                    i,
                ));
            }
        }
        let (title, y_label) = match group.as_str() {
            "v0" => (
                format!("{stage}: initial velocity per epoch"),
                "v0 (m/s)".to_string(),
            ),
            "omega" => (
                format!("{stage}: angular velocity per epoch"),
                "ω (rad/s)".to_string(),
            ),
            name => (
                format!("{stage}: {name} per epoch"),
                match unit(name) {
                    "" => name.to_string(),
                    u => format!("{name} ({u})"),
                },
            ),
        };
        figs.push((
            format!("param_{stage}_{group}"),
            Figure {
                title,
                x_label: "epoch".into(),
                y_label,
                series,
                log_y: spans_decades(&group),
                log_x: false,
            },
        ));
    }
    if !r.view_scores.is_empty() {
        let mut psnr: Vec<Series> = r
            .view_scores
            .iter()
            .enumerate()
            .map(|(i, v)| Series::line(format!("view {}", v.view), frames_f64(&v.psnr), i))
            .collect();
        if !r.train_psnr_per_frame.is_empty() {
            psnr.push(Series {
                dashed: true,
                ..Series::line(
                    "training views (mean)",
                    frames_f64(&r.train_psnr_per_frame),
                    7,
                )
            });
        }
        figs.push((
            "psnr_per_frame".into(),
            Figure {
                title: "PSNR per frame (test views)".into(),
                x_label: "frame".into(),
                y_label: "PSNR (dB)".into(),
                series: psnr,
                log_y: false,
                log_x: false,
            },
        ));
        figs.push((
            "ssim_per_frame".into(),
            Figure {
                title: "SSIM per frame (test views)".into(),
                x_label: "frame".into(),
                y_label: "SSIM".into(),
                series: r
                    .view_scores
                    .iter()
                    .enumerate()
                    .map(|(i, v)| Series::line(format!("view {}", v.view), frames_f64(&v.ssim), i))
                    .collect(),
                log_y: false,
                log_x: false,
            },
        ));
    }
    let mut out = Vec::new();
    for (id, fig) in figs {
        if let Some(svg) = fig.svg()? {
            out.push(Drawn {
                reference: FigureRef {
                    id: format!("{prefix}{id}"),
                    title: fig.title.clone(),
                    file: PathBuf::from("plots").join(format!("{prefix}{id}.svg")),
                },
                svg,
            });
        }
    }
    Ok(out)
}

/// Assemble the report of `runs` (strips already in `out/images`).
pub fn build(runs: &[RunSummary], out: &Path) -> Result<(Report, Vec<Vec<Drawn>>), ReportError> {
    let mut scenes = Vec::new();
    let mut drawn = Vec::new();
    for (i, run) in runs.iter().enumerate() {
        let prefix = if runs.len() > 1 {
            format!("{}_", i + 1)
        } else {
            String::new()
        };
        let (s, d) = scene(run, out, &prefix)?;
        scenes.push(s);
        drawn.push(d);
    }
    Ok((
        Report {
            tool: format!("pipe-report {}", env!("CARGO_PKG_VERSION")),
            scenes,
            published: table1(),
        },
        drawn,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kept_fields_parts_get_rows_and_es_bounds_name_the_one_material_fit() {
        let dir = std::env::temp_dir().join(format!("pipe-report-parts-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let profile = |value: f64, lo: f64, hi: f64| {
            serde_json::json!({
                "param": "E", "unit": "decades", "value": value,
                "below": [{"step": -0.25, "value": lo, "rise_pct": 90.0, "t": 8.0}],
                "above": [{"step": 0.25, "value": hi, "rise_pct": 160.0, "t": 12.0}],
                "ends": ["bounded", "bounded"], "bounds": [lo, hi]
            })
        };
        let material = serde_json::json!({
            "model": "field",
            "youngs_modulus": 4.73e4,
            "profile": [profile(2.33e4, 1.31e4, 4.14e4)],
            "field": {"parts": {"thresholds": [4.93], "parts": [
                {"volume_share": 0.527, "particles": 2340, "youngs_modulus_median": 2.39e4,
                 "profile": profile(2.39e4, 1.34e4, 4.25e4)},
                {"volume_share": 0.473, "particles": 2099, "youngs_modulus_median": 3.99e5,
                 "profile": profile(3.99e5, 2.24e5, 7.10e5)}
            ]}}
        });
        std::fs::write(dir.join("material.json"), material.to_string()).unwrap();
        let run = RunSummary {
            name: "bar".into(),
            file: "bar.yaml".into(),
            preset: "draft".into(),
            scene: Value::Null,
            stages: vec![crate::input::StageRun {
                name: "material".into(),
                kind: "material".into(),
                key: "k".into(),
                state: "done".into(),
                reasons: Vec::new(),
                dir: Some(dir.clone()),
                params: Value::Null,
                wall_s: None,
                peak_rss_bytes: None,
                threads: None,
                warnings: Vec::new(),
            }],
            strips: Vec::new(),
            gifs: Vec::new(),
        };
        let rows = parameters(&run, None).unwrap();
        std::fs::remove_dir_all(&dir).ok();
        let e = rows.iter().find(|r| r.name == "E").unwrap();
        assert_eq!(
            e.bounded,
            "the one-material fit (23300.0): from 13100.0; to 41400.0"
        );
        let parts: Vec<&ParameterRow> = rows
            .iter()
            .filter(|r| r.name.contains("field part"))
            .collect();
        assert_eq!(parts.len(), 2);
        assert_eq!(parts[1].name, "E, field part 2 of 2 (47 % of the volume)");
        assert_eq!(parts[1].learned, serde_json::json!(3.99e5));
        assert_eq!(parts[1].bounded, "from 2.240e5; to 7.100e5");
    }

    #[test]
    fn a_profile_reads_as_the_values_that_bound_the_parameter() {
        let p = serde_json::json!({
            "param": "E", "unit": "decades", "value": 1.0e6,
            "below": [{"step": -0.25, "value": 5.6234e5, "rise_pct": 30.0, "t": 12.0}],
            "above": [
                {"step": 0.25, "value": 1.7783e6, "rise_pct": 0.1, "t": 0.4},
                {"step": 0.5, "value": 3.1623e6, "rise_pct": 0.2, "t": 1.1},
                {"step": 1.0, "value": 1.0e7, "rise_pct": 0.3, "t": 1.5}
            ],
            "ends": ["bounded", "open"], "bounds": [5.6234e5, null]
        });
        assert_eq!(bounds_text(&p), "from 5.623e5; not bounded up to 1.000e7");
        let short = serde_json::json!({
            "below": [
                {"step": -0.025, "value": 0.275, "rise_pct": -1.0, "t": -5.0},
                {"step": -0.05, "value": 0.25, "rise_pct": -0.5, "t": -3.0}
            ],
            "above": [], "ends": ["better", "range"]
        });
        assert_eq!(
            bounds_text(&short),
            "0.2750 is better (fit stopped short); up to the end of its range"
        );
        assert_eq!(
            bounds_text(&serde_json::json!({})),
            "not profiled; not profiled"
        );
    }
}
