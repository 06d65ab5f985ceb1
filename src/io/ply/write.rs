//! Atomic writes: a temporary file in the same folder, synced, then renamed over the target.

use std::fs::{self, File};
use std::io::{self, BufWriter};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use super::PlyError;

/// Writes `path` through `fill`; on any error the temporary file is removed and `path` is left
/// as it was.
pub(crate) fn write_atomic(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<File>) -> io::Result<()>,
) -> Result<(), PlyError> {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let Some(name) = path.file_name() else {
        return Err(PlyError::Invalid {
            path: path.to_path_buf(),
            message: "the path has no file name".into(),
        });
    };
    let tmp = path.with_file_name(format!(
        ".{}.tmp-{}-{}",
        name.to_string_lossy(),
        std::process::id(),
        SEQ.fetch_add(1, Ordering::Relaxed)
    ));
    let result = (|| {
        let file = File::create_new(&tmp).map_err(|e| ("create", e))?;
        let mut w = BufWriter::with_capacity(1 << 16, file);
        fill(&mut w).map_err(|e| ("write", e))?;
        let file = w.into_inner().map_err(|e| ("write", e.into_error()))?;
        file.sync_all().map_err(|e| ("sync", e))?;
        fs::rename(&tmp, path).map_err(|e| ("rename", e))
    })();
    result.map_err(|(action, e)| {
        let _ = fs::remove_file(&tmp);
        PlyError::Io {
            path: path.to_path_buf(),
            action,
            message: e.to_string(),
        }
    })
}
