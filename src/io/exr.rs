//! OpenEXR output: depth maps as a single 32-bit float `Z` channel (metres).

use std::path::{Path, PathBuf};

/// Writing the EXR failed.
#[derive(Debug, thiserror::Error)]
#[error("{path}: cannot write EXR: {message}")]
pub struct ExrError {
    /// The file.
    pub path: PathBuf,
    /// Why.
    pub message: String,
}

/// Write a `width × height` row-major depth map (metres) as channel `Z`, atomically.
pub fn write_depth(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<(), ExrError> {
    write_channel(path, "Z", width, height, depth)
}

/// Write a `width × height` row-major single-channel float image (channel `name`, e.g. `A`
/// for alpha), atomically.
pub fn write_channel(
    path: &Path,
    name: &str,
    width: u32,
    height: u32,
    depth: &[f32],
) -> Result<(), ExrError> {
    use exr::prelude::*;
    let err = |message: String| ExrError {
        path: path.to_path_buf(),
        message,
    };
    if depth.len() != (width as usize) * (height as usize) {
        return Err(err(format!(
            "{} values for a {width}×{height} image",
            depth.len()
        )));
    }
    let w = width as usize;
    let pixels = SpecificChannels::build()
        .with_channel(name)
        .with_pixel_fn(|p: Vec2<usize>| (depth[p.1 * w + p.0],));
    let image = Image::from_channels((w, height as usize), pixels);
    let tmp = path.with_extension(format!("exr.{}.tmp", std::process::id()));
    image
        .write()
        .to_file(&tmp)
        .map_err(|e| err(e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_round_trips_through_a_z_channel() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.exr");
        let depth: Vec<f32> = (0..12).map(|i| i as f32 * 0.25).collect();
        write_depth(&path, 4, 3, &depth).unwrap();
        let img = exr::prelude::read_first_flat_layer_from_file(&path).unwrap();
        let layer = &img.layer_data;
        assert_eq!((layer.size.0, layer.size.1), (4, 3));
        let ch = &layer.channel_data.list[0];
        assert_eq!(ch.name.to_string(), "Z");
        let values: Vec<f32> = ch.sample_data.values_as_f32().collect();
        assert_eq!(values, depth);
        assert!(write_depth(&path, 5, 3, &depth).is_err());
    }
}
