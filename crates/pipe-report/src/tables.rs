//! A stage's `metrics.arrow` (stage, epoch, view, frame, metric, value) read and aggregated
//! with polars: per-epoch curves, per-(view, frame) scores and their per-frame means.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::ReportError;

/// One stage's metrics.
#[derive(Debug, Clone)]
pub struct Metrics {
    path: PathBuf,
    df: DataFrame,
}

fn table_error(path: &Path, e: PolarsError) -> ReportError {
    ReportError::Table {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// The metric rows that have an epoch and no view or frame.
fn per_epoch(metric: &str) -> Expr {
    col("metric")
        .eq(lit(metric))
        .and(col("epoch").is_not_null())
        .and(col("view").is_null())
        .and(col("frame").is_null())
}

/// The metric rows that have a view and a frame and no epoch.
fn per_view_frame(metric: &str) -> Expr {
    col("metric")
        .eq(lit(metric))
        .and(col("epoch").is_null())
        .and(col("view").is_not_null())
        .and(col("frame").is_not_null())
}

impl Metrics {
    /// Read an Arrow IPC `metrics` file, checking its columns.
    pub fn read(path: &Path) -> Result<Self, ReportError> {
        let file = std::fs::File::open(path).map_err(|source| ReportError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let df = IpcReader::new(file)
            .finish()
            .map_err(|e| table_error(path, e))?;
        for (name, dtype) in [
            ("epoch", DataType::UInt32),
            ("view", DataType::UInt16),
            ("frame", DataType::UInt16),
            ("metric", DataType::String),
            ("value", DataType::Float64),
        ] {
            let found = df
                .schema()
                .get(name)
                .cloned()
                .ok_or_else(|| ReportError::Table {
                    path: path.to_path_buf(),
                    message: format!("no column `{name}` (a metrics table has stage, epoch, view, frame, metric, value)"),
                })?;
            if found != dtype {
                return Err(ReportError::Table {
                    path: path.to_path_buf(),
                    message: format!("column `{name}` is {found}, expected {dtype}"),
                });
            }
        }
        Ok(Self {
            path: path.to_path_buf(),
            df,
        })
    }

    fn collect(&self, lf: LazyFrame) -> Result<DataFrame, ReportError> {
        lf.collect().map_err(|e| table_error(&self.path, e))
    }

    fn f64s(&self, df: &DataFrame, name: &str) -> Result<Vec<f64>, ReportError> {
        let c = df
            .column(name)
            .and_then(|c| c.cast(&DataType::Float64))
            .map_err(|e| table_error(&self.path, e))?;
        let ca = c.f64().map_err(|e| table_error(&self.path, e))?;
        Ok(ca.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
    }

    /// Names of the metrics recorded per epoch, in first-seen order.
    pub fn epoch_metrics(&self) -> Result<Vec<String>, ReportError> {
        let df = self.collect(
            self.df
                .clone()
                .lazy()
                .filter(col("epoch").is_not_null().and(col("view").is_null()))
                .select([col("metric")]),
        )?;
        let ca = df
            .column("metric")
            .and_then(|c| c.str().cloned())
            .map_err(|e| table_error(&self.path, e))?;
        let mut out: Vec<String> = Vec::new();
        for name in ca.iter().flatten() {
            if !out.iter().any(|n| n == name) {
                out.push(name.to_string());
            }
        }
        Ok(out)
    }

    /// `(epoch, value)` of a per-epoch metric, by epoch.
    pub fn epoch_curve(&self, metric: &str) -> Result<Vec<(f64, f64)>, ReportError> {
        let df = self.collect(
            self.df
                .clone()
                .lazy()
                .filter(per_epoch(metric))
                .select([col("epoch"), col("value")])
                .sort(["epoch"], SortMultipleOptions::default()),
        )?;
        let (e, v) = (self.f64s(&df, "epoch")?, self.f64s(&df, "value")?);
        Ok(e.into_iter().zip(v).collect())
    }

    /// Per view, `(frame, value)` of a per-(view, frame) metric, by frame.
    pub fn view_frame_scores(
        &self,
        metric: &str,
    ) -> Result<BTreeMap<u16, Vec<(u16, f64)>>, ReportError> {
        let df = self.collect(
            self.df
                .clone()
                .lazy()
                .filter(per_view_frame(metric))
                .select([col("view"), col("frame"), col("value")])
                .sort(["view", "frame"], SortMultipleOptions::default()),
        )?;
        let (v, f, x) = (
            self.f64s(&df, "view")?,
            self.f64s(&df, "frame")?,
            self.f64s(&df, "value")?,
        );
        let mut out: BTreeMap<u16, Vec<(u16, f64)>> = BTreeMap::new();
        for ((v, f), x) in v.into_iter().zip(f).zip(x) {
            out.entry(v as u16).or_default().push((f as u16, x));
        }
        Ok(out)
    }

    /// `(frame, mean over views)` of a per-(view, frame) metric, by frame.
    pub fn frame_means(&self, metric: &str) -> Result<Vec<(u16, f64)>, ReportError> {
        let df = self.collect(
            self.df
                .clone()
                .lazy()
                .filter(per_view_frame(metric))
                .group_by([col("frame")])
                .agg([col("value").mean().alias("value")])
                .sort(["frame"], SortMultipleOptions::default()),
        )?;
        let (f, x) = (self.f64s(&df, "frame")?, self.f64s(&df, "value")?);
        Ok(f.into_iter().map(|f| f as u16).zip(x).collect())
    }

    /// Rows with neither epoch, view nor frame (the stage's summary values).
    pub fn summary(&self) -> Result<BTreeMap<String, f64>, ReportError> {
        let df = self.collect(
            self.df
                .clone()
                .lazy()
                .filter(
                    col("epoch")
                        .is_null()
                        .and(col("view").is_null())
                        .and(col("frame").is_null()),
                )
                .select([col("metric"), col("value")]),
        )?;
        let names = df
            .column("metric")
            .and_then(|c| c.str().cloned())
            .map_err(|e| table_error(&self.path, e))?;
        let values = self.f64s(&df, "value")?;
        Ok(names
            .iter()
            .zip(values)
            .filter_map(|(n, v)| n.map(|n| (n.to_string(), v)))
            .collect())
    }
}
