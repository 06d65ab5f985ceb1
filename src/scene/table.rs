//! Arrow IPC files with a checked schema (ARCHITECTURE §5).
//!
//! Each table type declares its schema; reading a file checks it column by column and names
//! the first missing column or wrong type. The same schema is written as JSON into `schemas/`
//! (the contract other tools read), and a test keeps the two in agreement.

use std::fs::File;
use std::io::BufWriter;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use arrow_array::{Array, RecordBatch};
use arrow_ipc::reader::FileReader;
use arrow_ipc::writer::FileWriter;
use arrow_schema::{DataType, Schema};

/// Problems reading or writing a table file.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// File-system failure.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// Not a readable Arrow IPC file.
    #[error("{path}: not a readable Arrow IPC file: {message}")]
    Arrow {
        /// The file.
        path: PathBuf,
        /// Arrow's message.
        message: String,
    },
    /// A column the table needs is absent.
    #[error("{path}: column `{column}` is missing (expected {expected})")]
    MissingColumn {
        /// The file.
        path: PathBuf,
        /// Column name.
        column: String,
        /// Its expected type.
        expected: String,
    },
    /// A column has the wrong type.
    #[error("{path}: column `{column}` has type {found}, expected {expected}")]
    WrongType {
        /// The file.
        path: PathBuf,
        /// Column name.
        column: String,
        /// Type in the file.
        found: String,
        /// Type required.
        expected: String,
    },
    /// Values that the schema allows but the table does not (e.g. a bad SH length).
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// A table type stored as one Arrow IPC file.
pub trait Table: Sized {
    /// Table name (`frames`, `gaussians`, `metrics`).
    const NAME: &'static str;
    /// Schema version; part of every producing stage's cache key.
    const VERSION: u32;
    /// How the file holds the rows (the contract's `format`).
    const FORMAT: &'static str = "Arrow IPC file, one record batch";
    /// The Arrow schema.
    fn schema() -> Schema;
    /// To one record batch.
    fn to_batch(&self) -> RecordBatch;
    /// From a record batch whose schema has been checked.
    fn from_batch(batch: &RecordBatch, path: &Path) -> Result<Self, TableError>;
}

/// Check `found` against `expected`: every expected column present with the same type.
pub fn check_schema(path: &Path, expected: &Schema, found: &Schema) -> Result<(), TableError> {
    for f in expected.fields() {
        match found.field_with_name(f.name()) {
            Err(_) => {
                return Err(TableError::MissingColumn {
                    path: path.to_path_buf(),
                    column: f.name().clone(),
                    expected: type_name(f.data_type()),
                });
            }
            Ok(g) if !same_type(f.data_type(), g.data_type()) => {
                return Err(TableError::WrongType {
                    path: path.to_path_buf(),
                    column: f.name().clone(),
                    found: type_name(g.data_type()),
                    expected: type_name(f.data_type()),
                });
            }
            Ok(_) => {}
        }
    }
    Ok(())
}

/// Types equal up to the names of list item fields.
fn same_type(a: &DataType, b: &DataType) -> bool {
    match (a, b) {
        (DataType::FixedSizeList(fa, na), DataType::FixedSizeList(fb, nb)) => {
            (na == nb || *na < 0) && same_type(fa.data_type(), fb.data_type())
        }
        (DataType::List(fa), DataType::List(fb)) => same_type(fa.data_type(), fb.data_type()),
        _ => a == b,
    }
}

/// A readable name for a type (`Float64`, `FixedSizeList<Float32, 3>`).
pub fn type_name(t: &DataType) -> String {
    match t {
        DataType::FixedSizeList(f, n) if *n < 0 => {
            format!(
                "FixedSizeList<{}, 3·(sh_degree+1)²>",
                type_name(f.data_type())
            )
        }
        DataType::FixedSizeList(f, n) => {
            format!("FixedSizeList<{}, {n}>", type_name(f.data_type()))
        }
        DataType::List(f) => format!("List<{}>", type_name(f.data_type())),
        other => format!("{other:?}"),
    }
}

/// Write a table atomically (temp file + rename).
pub fn write<T: Table>(path: &Path, table: &T) -> Result<(), TableError> {
    let mut w = Writer::<T>::create(path)?;
    w.write(&table.to_batch())?;
    w.finish()
}

/// A table written one record batch at a time (e.g. one per simulated frame, so a run never
/// holds all its rows) into a temporary file beside `path` that becomes `path` only at
/// [`Writer::finish`]. Dropped unfinished (an error, an interrupted run), it removes the
/// temporary file: no file that looks complete is left.
pub struct Writer<T: Table> {
    path: PathBuf,
    tmp: PathBuf,
    /// The open file until the first batch gives the schema (a table's declared schema may
    /// leave a list length open, e.g. the Gaussians' SH).
    file: Option<BufWriter<File>>,
    ipc: Option<FileWriter<BufWriter<File>>>,
    table: PhantomData<T>,
}

impl<T: Table> Writer<T> {
    /// Starts `path` (its temporary file).
    pub fn create(path: &Path) -> Result<Self, TableError> {
        let tmp = path.with_extension(format!("arrow.{}.tmp", std::process::id()));
        let file = File::create(&tmp).map_err(|source| TableError::Io {
            path: tmp.clone(),
            source,
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp,
            file: Some(BufWriter::with_capacity(1 << 20, file)),
            ipc: None,
            table: PhantomData,
        })
    }

    /// Appends one record batch (`T`'s schema; the first batch's is the file's).
    pub fn write(&mut self, batch: &RecordBatch) -> Result<(), TableError> {
        let written = self.ipc(&batch.schema()).and_then(|w| w.write(batch));
        written.map_err(|e| self.arrow(e))
    }

    /// Closes the file and moves it to `path`.
    pub fn finish(mut self) -> Result<(), TableError> {
        let closed = self.ipc(&T::schema()).and_then(|w| w.finish());
        let closed = closed.and_then(|()| {
            let ipc = self.ipc.take().expect("opened above");
            let buffered = ipc.into_inner()?;
            buffered.into_inner().map_err(|e| e.into_error().into())
        });
        let renamed = match closed {
            Err(e) => Err(self.arrow(e)),
            Ok(file) => {
                drop(file);
                std::fs::rename(&self.tmp, &self.path).map_err(|source| TableError::Io {
                    path: self.path.clone(),
                    source,
                })
            }
        };
        if renamed.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        renamed
    }

    /// The IPC writer, started with `schema` if no batch has been written yet.
    fn ipc(
        &mut self,
        schema: &Schema,
    ) -> Result<&mut FileWriter<BufWriter<File>>, arrow_schema::ArrowError> {
        if let Some(file) = self.file.take() {
            self.ipc = Some(FileWriter::try_new(file, schema)?);
        }
        Ok(self.ipc.as_mut().expect("the file is open until finished"))
    }

    fn arrow(&self, e: arrow_schema::ArrowError) -> TableError {
        TableError::Arrow {
            path: self.path.clone(),
            message: e.to_string(),
        }
    }
}

impl<T: Table> std::fmt::Debug for Writer<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Writer")
            .field("table", &T::NAME)
            .field("path", &self.path)
            .field("open", &(self.ipc.is_some() || self.file.is_some()))
            .finish()
    }
}

impl<T: Table> Drop for Writer<T> {
    fn drop(&mut self) {
        if self.ipc.take().is_some() || self.file.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Read a table, checking its schema.
pub fn read<T: Table>(path: &Path) -> Result<T, TableError> {
    let file = File::open(path).map_err(|source| TableError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let arrow = |e: arrow_schema::ArrowError| TableError::Arrow {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let reader = FileReader::try_new(file, None).map_err(arrow)?;
    let schema = reader.schema();
    check_schema(path, &T::schema(), &schema)?;
    let batches = reader.collect::<Result<Vec<_>, _>>().map_err(arrow)?;
    let batch = match batches.as_slice() {
        [one] => one.clone(),
        _ => arrow_select::concat::concat_batches(&schema, &batches).map_err(arrow)?,
    };
    T::from_batch(&batch, path)
}

/// The column `name` of `batch`, downcast to `A` (the schema was checked, so this holds).
pub fn column<'b, A: Array + 'static>(batch: &'b RecordBatch, name: &str) -> &'b A {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_any().downcast_ref::<A>())
        .unwrap_or_else(|| panic!("column `{name}` was checked against the schema"))
}

/// The contract form of a schema: `{table, version, columns: [{name, type, nullable}], metadata}`.
pub fn schema_json<T: Table>() -> serde_json::Value {
    let s = T::schema();
    serde_json::json!({
        "table": T::NAME,
        "version": T::VERSION,
        "format": T::FORMAT,
        "columns": s.fields().iter().map(|f| serde_json::json!({
            "name": f.name(),
            "type": type_name(f.data_type()),
            "nullable": f.is_nullable(),
        })).collect::<Vec<_>>(),
        "metadata": s.metadata().iter().collect::<std::collections::BTreeMap<_, _>>(),
    })
}
