//! `pipe export`: a cached stage's Gaussians as a standard 3DGS PLY, or its tables as Parquet.

use std::path::{Path, PathBuf};

use crate::io::{parquet, ply};
use crate::pipeline::cache::list_files;
use crate::scene::gaussians::Gaussians;
use crate::scene::table;

/// Export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// `gaussians.arrow` → 3DGS PLY (`x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*`).
    Ply,
    /// Every `*.arrow` table → `<name>.parquet` in a folder.
    Parquet,
}

/// Export failed; the message names the file or the stage.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ExportError(String);

/// Export the entry `entry` of stage `stage` to `out` (a file for PLY, a folder for Parquet).
/// Returns the files written, with a one-line description each.
pub fn export(
    entry: &Path,
    stage: &str,
    format: Format,
    out: &Path,
) -> Result<Vec<(PathBuf, String)>, ExportError> {
    let fail = |m: String| ExportError(m);
    match format {
        Format::Ply => {
            let src = entry.join("gaussians.arrow");
            if !src.exists() {
                return Err(fail(format!(
                    "stage `{stage}` has no Gaussians to export ({} holds no gaussians.arrow)",
                    entry.display()
                )));
            }
            let g: Gaussians = table::read(&src).map_err(|e| fail(e.to_string()))?;
            if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .map_err(|e| fail(format!("{}: {e}", dir.display())))?;
            }
            ply::write_gaussians(out, &g).map_err(|e| fail(e.to_string()))?;
            Ok(vec![(
                out.to_path_buf(),
                format!("{} Gaussians (SH degree {})", g.len(), g.sh_degree),
            )])
        }
        Format::Parquet => {
            let tables: Vec<String> = list_files(entry)
                .map_err(|e| fail(format!("{}: {e}", entry.display())))?
                .into_iter()
                .filter(|f| f.ends_with(".arrow"))
                .collect();
            if tables.is_empty() {
                return Err(fail(format!("stage `{stage}` wrote no tables")));
            }
            tables
                .iter()
                .map(|t| {
                    let dst = out.join(t.replace(".arrow", ".parquet"));
                    parquet::arrow_to_parquet(&entry.join(t), &dst)
                        .map_err(|e| fail(e.to_string()))?;
                    Ok((dst, format!("table {t}")))
                })
                .collect()
        }
    }
}
