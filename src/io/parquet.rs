//! Arrow IPC table → Parquet, for analysis tools (polars, pandas, DuckDB).

use std::fs::File;
use std::path::{Path, PathBuf};

use arrow_ipc::reader::FileReader;
use parquet::arrow::ArrowWriter;

/// Conversion failed.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct ParquetError {
    /// The file involved.
    pub path: PathBuf,
    /// What went wrong.
    pub message: String,
}

/// Write every record batch of the Arrow IPC file `src` to the Parquet file `dst` (atomically).
pub fn arrow_to_parquet(src: &Path, dst: &Path) -> Result<(), ParquetError> {
    let err = |path: &Path| {
        let path = path.to_path_buf();
        move |e: &dyn std::fmt::Display| ParquetError {
            path: path.clone(),
            message: e.to_string(),
        }
    };
    let (e_src, e_dst) = (err(src), err(dst));
    let reader = FileReader::try_new(File::open(src).map_err(|e| e_src(&e))?, None)
        .map_err(|e| e_src(&e))?;
    let schema = reader.schema();
    if let Some(dir) = dst.parent() {
        std::fs::create_dir_all(dir).map_err(|e| e_dst(&e))?;
    }
    let tmp = dst.with_extension(format!("parquet.{}.tmp", std::process::id()));
    {
        let file = File::create(&tmp).map_err(|e| e_dst(&e))?;
        let mut w = ArrowWriter::try_new(file, schema, None).map_err(|e| e_dst(&e))?;
        for batch in reader {
            let batch = batch.map_err(|e| e_src(&e))?;
            w.write(&batch).map_err(|e| e_dst(&e))?;
        }
        w.close().map_err(|e| e_dst(&e))?;
    }
    std::fs::rename(&tmp, dst).map_err(|e| e_dst(&e))
}
