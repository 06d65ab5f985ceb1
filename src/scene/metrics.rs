//! The `metrics` table: (stage, epoch, view, frame, metric, value) rows a stage measured.

use std::path::Path;
use std::sync::Arc;

use arrow_array::{Float64Array, RecordBatch, StringArray, UInt16Array, UInt32Array};
use arrow_schema::{DataType, Field, Schema};

use super::table::{self, Table, TableError, column};
use crate::pipeline::stage::MetricRow;

/// The `metrics` table of one stage.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Metrics {
    /// Stage name that measured them.
    pub stage: String,
    /// Rows in the order recorded.
    pub rows: Vec<MetricRow>,
}

impl Table for Metrics {
    const NAME: &'static str = "metrics";
    const VERSION: u32 = 1;

    fn schema() -> Schema {
        Schema::new(vec![
            Field::new("stage", DataType::Utf8, false),
            Field::new("epoch", DataType::UInt32, true),
            Field::new("view", DataType::UInt16, true),
            Field::new("frame", DataType::UInt16, true),
            Field::new("metric", DataType::Utf8, false),
            Field::new("value", DataType::Float64, false),
        ])
        .with_metadata([("schema_version".to_string(), Self::VERSION.to_string())])
    }

    fn to_batch(&self) -> RecordBatch {
        let r = &self.rows;
        RecordBatch::try_new(
            Arc::new(Self::schema()),
            vec![
                Arc::new(StringArray::from_iter_values(
                    r.iter().map(|_| self.stage.as_str()),
                )),
                Arc::new(UInt32Array::from_iter(r.iter().map(|x| x.epoch))),
                Arc::new(UInt16Array::from_iter(r.iter().map(|x| x.view))),
                Arc::new(UInt16Array::from_iter(r.iter().map(|x| x.frame))),
                Arc::new(StringArray::from_iter_values(
                    r.iter().map(|x| x.metric.as_str()),
                )),
                Arc::new(Float64Array::from_iter_values(r.iter().map(|x| x.value))),
            ],
        )
        .expect("columns match the schema")
    }

    fn from_batch(b: &RecordBatch, _path: &Path) -> Result<Self, TableError> {
        use arrow_array::Array;
        let stage = column::<StringArray>(b, "stage");
        let epoch = column::<UInt32Array>(b, "epoch");
        let view = column::<UInt16Array>(b, "view");
        let frame = column::<UInt16Array>(b, "frame");
        let metric = column::<StringArray>(b, "metric");
        let value = column::<Float64Array>(b, "value");
        fn opt<T>(valid: bool, v: T) -> Option<T> {
            valid.then_some(v)
        }
        Ok(Self {
            stage: if b.num_rows() > 0 {
                stage.value(0).to_string()
            } else {
                String::new()
            },
            rows: (0..b.num_rows())
                .map(|i| MetricRow {
                    epoch: opt(epoch.is_valid(i), epoch.value(i)),
                    view: opt(view.is_valid(i), view.value(i)),
                    frame: opt(frame.is_valid(i), frame.value(i)),
                    metric: metric.value(i).to_string(),
                    value: value.value(i),
                })
                .collect(),
        })
    }
}

/// Write a stage's metrics to `path`.
pub fn write(path: &Path, stage: &str, rows: &[MetricRow]) -> Result<(), TableError> {
    table::write(
        path,
        &Metrics {
            stage: stage.to_string(),
            rows: rows.to_vec(),
        },
    )
}
