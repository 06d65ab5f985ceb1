//! PLY files: point clouds and 3D Gaussian splatting (3DGS) `point_cloud.ply`.
//!
//! A small hand-written reader: the header is parsed first (`header`), every size is checked
//! against the file length before anything is allocated, then the records of the one element
//! wanted (`vertex`) are decoded from ASCII, binary little- or big-endian (`body`). Other
//! elements and properties are skipped. Writers emit binary little-endian through a temporary
//! file renamed into place ([`write`]), so a reader never sees half a file.
//!
//! Records are counted from 0 in error messages; byte offsets are from the start of the file.

mod body;
mod gaussians;
mod header;
mod points;
mod scalars;
mod write;

use std::path::PathBuf;

pub use gaussians::{read_gaussians, write_gaussians};
pub use points::{read_points, write_points};
pub use scalars::{PointScalars, read_point_scalars, write_point_scalars};

/// Points with optional colours.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PointCloud {
    /// Positions, metres.
    pub positions: Vec<[f32; 3]>,
    /// RGB in [0, 1], one per position, if the file has `red green blue`.
    pub colors: Option<Vec<[f32; 3]>>,
}

/// Why a PLY file cannot be read or written. Every message names the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlyError {
    /// The OS refused an operation.
    #[error("{path}: cannot {action}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was attempted (`open`, `read`, `write`, `rename`, ...).
        action: &'static str,
        /// OS message.
        message: String,
    },
    /// A zero-byte file.
    #[error("{path}: empty file (0 bytes), expected a PLY header")]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// The first line is not `ply`.
    #[error("{path}: not a PLY file: first line is {found:?}, expected `ply`")]
    NotPly {
        /// The file.
        path: PathBuf,
        /// The first line (at most 40 characters, lossy UTF-8).
        found: String,
    },
    /// A malformed header line.
    #[error("{path}: header line {line}: {message}")]
    Header {
        /// The file.
        path: PathBuf,
        /// Line number, from 1.
        line: usize,
        /// What is wrong, quoting the line.
        message: String,
    },
    /// A `format` other than ascii / binary_little_endian / binary_big_endian 1.0.
    #[error(
        "{path}: header line {line}: unknown format `{format}` \
         (expected `ascii`, `binary_little_endian` or `binary_big_endian`, version 1.0)"
    )]
    UnknownFormat {
        /// The file.
        path: PathBuf,
        /// Line number, from 1.
        line: usize,
        /// The format (and version) as written.
        format: String,
    },
    /// A property type that is not one of the eight PLY scalar types.
    #[error("{path}: header line {line}: property `{property}` has unknown type `{ty}`")]
    UnknownType {
        /// The file.
        path: PathBuf,
        /// Line number, from 1.
        line: usize,
        /// The property.
        property: String,
        /// The type as written.
        ty: String,
    },
    /// Binary data ends inside a record.
    #[error(
        "{path}: truncated: element `{element}` record {record} of {count} ends at byte {end}, \
         file has {file_len} bytes"
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
        /// The first incomplete record, from 0.
        record: u64,
        /// Records the header declares.
        count: u64,
        /// Byte offset the record needs to reach.
        end: u64,
        /// File length, bytes.
        file_len: u64,
    },
    /// A declared record count that cannot fit in the rest of the file (checked before reading).
    #[error(
        "{path}: element `{element}` declares {count} records of at least {min_record_bytes} bytes, \
         but only {available} bytes follow byte {offset}"
    )]
    TooManyRecords {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
        /// Records the header declares.
        count: u64,
        /// Fewest bytes one record can take.
        min_record_bytes: u64,
        /// Where the element's data starts.
        offset: u64,
        /// Bytes from there to the end of the file.
        available: u64,
    },
    /// A bad ASCII data line.
    #[error("{path}: line {line}: element `{element}` record {record}: {message}")]
    Ascii {
        /// The file.
        path: PathBuf,
        /// Line number, from 1 (header lines included).
        line: usize,
        /// The element.
        element: String,
        /// The record, from 0.
        record: u64,
        /// What is wrong.
        message: String,
    },
    /// The element the reader needs is absent.
    #[error("{path}: no element `{element}` in the header")]
    MissingElement {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
    },
    /// A required property is absent.
    #[error("{path}: element `{element}` has no property `{property}`")]
    MissingProperty {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
        /// The property.
        property: String,
    },
    /// A property has a type the reader cannot use.
    #[error(
        "{path}: element `{element}` property `{property}` has type `{found}`, expected {expected}"
    )]
    PropertyType {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
        /// The property.
        property: String,
        /// Its type as in the header.
        found: String,
        /// What would be accepted.
        expected: &'static str,
    },
    /// The `f_rest_*` properties do not form an SH degree 0..=3 set.
    #[error("{path}: element `vertex`: {message}")]
    ShRest {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A value the reader rejects (NaN coordinate, colour out of range, negative list length).
    #[error("{path}: element `{element}` record {record} property `{property}`: {message}")]
    Value {
        /// The file.
        path: PathBuf,
        /// The element.
        element: String,
        /// The record, from 0.
        record: u64,
        /// The property.
        property: String,
        /// What is wrong, with the value.
        message: String,
    },
    /// The data handed to a writer is inconsistent; nothing was written.
    #[error("{path}: not written: {message}")]
    Invalid {
        /// The file that was to be written.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}
