//! `pipe-report`: the tables and plots of `pipe report` and `pipe sweep`.
//!
//! Reads a pipeline's cached stage outputs (each stage's `metrics.arrow`, `evaluation.json`,
//! `material.json`, `velocity.json`, the strips and GIFs) as the `pipe` library describes them
//! ([`input::RunSummary`]), aggregates them with polars ([`tables`]), draws SVG plots
//! ([`plot`]) and writes `report.html` (self-contained: images as `data:` URIs, plots as inline
//! SVG, no network request), `report.md` (images and plots beside it) and `report.json`. For a
//! sweep it writes `sweep.parquet`, Pareto plots and `sweep.md` ([`sweep`]).
//!
//! polars lives here only: the `pipe` library, its tests and the kernel crates never link it.

pub mod html;
pub mod input;
pub mod markdown;
pub mod model;
pub mod plot;
pub mod published;
pub mod sweep;
pub mod tables;
pub mod text;

use std::path::{Path, PathBuf};

pub use input::{RunSummary, SweepSummary};

/// Why a report or sweep could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A table could not be read, aggregated or written.
    #[error("{path}: {message}")]
    Table {
        /// The table.
        path: PathBuf,
        /// What polars said.
        message: String,
    },
    /// A JSON output of a stage could not be read.
    #[error("{path}: {message}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error.
        message: String,
    },
    /// A plot could not be drawn.
    #[error("plot `{title}`: {message}")]
    Plot {
        /// Its title.
        title: String,
        /// What failed.
        message: String,
    },
    /// The description handed over by `pipe` does not have the expected shape.
    #[error("report input: {0}")]
    Input(String),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ReportError + '_ {
    move |source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Write `report.html`, `report.md`, `report.json` and `plots/*.svg` of `runs` (side by side)
/// into `out`; images referenced by `runs` are read, GIFs copied into `out/images`.
pub fn write_report(runs: &[RunSummary], out: &Path) -> Result<Vec<PathBuf>, ReportError> {
    if runs.is_empty() {
        return Err(ReportError::Input("no pipeline to report".into()));
    }
    std::fs::create_dir_all(out.join("plots")).map_err(io(out))?;
    let (report, drawn) = model::build(runs, out)?;
    let mut written = Vec::new();
    for d in drawn.iter().flatten() {
        let p = out.join(&d.reference.file);
        std::fs::write(&p, &d.svg).map_err(io(&p))?;
    }
    let html = out.join("report.html");
    std::fs::write(&html, html::page(&report, &drawn, out)?).map_err(io(&html))?;
    written.push(html);
    let md = out.join("report.md");
    std::fs::write(&md, markdown::document(&report)).map_err(io(&md))?;
    written.push(md);
    let json = out.join("report.json");
    let mut text = serde_json::to_string_pretty(&report).map_err(|e| ReportError::Json {
        path: json.clone(),
        message: e.to_string(),
    })?;
    text.push('\n');
    std::fs::write(&json, text).map_err(io(&json))?;
    written.push(json);
    Ok(written)
}

/// [`write_report`] of the JSON form of `pipe::report::RunSummary` values.
pub fn write_report_value(
    runs: serde_json::Value,
    out: &Path,
) -> Result<Vec<PathBuf>, ReportError> {
    let runs: Vec<RunSummary> = serde_path_to_error::deserialize(runs)
        .map_err(|e| ReportError::Input(format!("at `{}`: {}", e.path(), e.inner())))?;
    write_report(&runs, out)
}

/// Write `sweep.parquet`, `sweep.md` and the Pareto plots into `out`.
pub fn write_sweep(sweep: &SweepSummary, out: &Path) -> Result<Vec<PathBuf>, ReportError> {
    sweep::write(sweep, out)
}

/// [`write_sweep`] of the JSON form of a `pipe::sweep::SweepSummary`.
pub fn write_sweep_value(
    sweep: serde_json::Value,
    out: &Path,
) -> Result<Vec<PathBuf>, ReportError> {
    let sweep: SweepSummary = serde_path_to_error::deserialize(sweep)
        .map_err(|e| ReportError::Input(format!("at `{}`: {}", e.path(), e.inner())))?;
    write_sweep(&sweep, out)
}
