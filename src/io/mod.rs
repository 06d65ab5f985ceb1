//! File formats: where outside data enters, and is validated.

pub mod capture;
pub mod colmap;
pub mod exr;
pub mod image;
pub mod pacnerf;
pub mod parquet;
pub mod physdreamer;
pub mod ply;
pub mod resample;
pub mod video;

/// A JSON file that cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum JsonError {
    /// File-system failure.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// Not the JSON expected.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: std::path::PathBuf,
        /// What serde found.
        source: serde_json::Error,
    },
}

/// Writes `value` as pretty JSON (with a final newline) to `path`.
pub fn write_json<T: serde::Serialize>(path: &std::path::Path, value: &T) -> Result<(), JsonError> {
    let mut text = serde_json::to_string_pretty(value).map_err(|source| JsonError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    text.push('\n');
    std::fs::write(path, text).map_err(|source| JsonError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads the JSON file `path` as a `T`.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &std::path::Path) -> Result<T, JsonError> {
    let text = std::fs::read_to_string(path).map_err(|source| JsonError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|source| JsonError::Json {
        path: path.to_path_buf(),
        source,
    })
}
