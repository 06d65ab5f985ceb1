//! The PAC-NeRF dataset layout (ARCHITECTURE §6): `all_data.json` listing
//! `{file_path "./data/r_<cam>_<frame>.png", time, c2w (3×4 or 4×4, OpenGL axes), intrinsic 3×3}`,
//! frame −1 being each camera's background plate.
//!
//! Cameras are converted once, here, from OpenGL axes (x right, y up, looking down −z) to the
//! OpenCV axes the rasterizer uses (x right, y down, z forward):
//! `world_from_camera_cv = world_from_camera_gl · diag(1, −1, −1)` on the rotation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::capture::{Capture, CaptureImage, DatasetFile};

/// One image listed in `all_data.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct PacnerfImage {
    /// Camera index.
    pub view: u16,
    /// Frame index; −1 is the background plate.
    pub frame: i32,
    /// Time, seconds.
    pub time_s: f64,
    /// 3×4 row-major `world_from_camera`, OpenCV axes, metres.
    pub world_from_camera: [f64; 12],
    /// fx, fy, cx, cy in pixels.
    pub intrinsics: [f64; 4],
    /// Path as written in the JSON, normalised (`data/r_0_3.png`): the logical name.
    pub logical_name: String,
    /// Where the file is.
    pub path: PathBuf,
}

/// The parsed `all_data.json` of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct PacnerfScene {
    /// The scene folder.
    pub root: PathBuf,
    /// Object images (frame ≥ 0), sorted by (view, frame).
    pub images: Vec<PacnerfImage>,
    /// The background plate of each camera.
    pub plates: BTreeMap<u16, PacnerfImage>,
}

/// A problem with the dataset's JSON or files.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PacnerfError {
    /// The file cannot be read.
    #[error("{path}: cannot read: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// OS message.
        message: String,
    },
    /// Not valid JSON, or the wrong shape.
    #[error("{path}: {message}")]
    Json {
        /// The file.
        path: PathBuf,
        /// serde's message with line and column.
        message: String,
    },
    /// One entry is invalid.
    #[error("{path}: entry {index} (`{file_path}`): field `{field}`: {message}")]
    Entry {
        /// `all_data.json`.
        path: PathBuf,
        /// Index in the list.
        index: usize,
        /// Its `file_path`.
        file_path: String,
        /// The bad field.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// Cameras or frames do not add up.
    #[error("{path}: {message}")]
    Layout {
        /// `all_data.json`.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEntry {
    file_path: String,
    time: f64,
    c2w: Vec<Vec<f64>>,
    intrinsic: Vec<Vec<f64>>,
}

/// Read and check `root/all_data.json`: every entry valid, one plate per camera.
pub fn read_scene(root: &Path) -> Result<PacnerfScene, PacnerfError> {
    read_json(&root.join("all_data.json"))
}

/// Read and check a PAC-NeRF camera JSON at `path` (image paths resolve against its folder),
/// requiring a background plate for every camera (for the stages that composite over them).
pub fn read_json(path: &Path) -> Result<PacnerfScene, PacnerfError> {
    let scene = read_cameras(path)?;
    let views: std::collections::BTreeSet<u16> = scene.images.iter().map(|i| i.view).collect();
    for v in &views {
        if !scene.plates.contains_key(v) {
            return Err(PacnerfError::Layout {
                path: path.to_path_buf(),
                message: format!(
                    "camera {v} has no background plate (./data/r_{v}_-1.png is not listed)"
                ),
            });
        }
    }
    Ok(scene)
}

/// Read the entries of a PAC-NeRF camera JSON, every entry checked, without requiring plates
/// (e.g. to render); images sorted by (view, frame).
pub fn read_cameras(path: &Path) -> Result<PacnerfScene, PacnerfError> {
    let root = path.parent().unwrap_or(Path::new("."));
    let path = path.to_path_buf();
    let text = std::fs::read_to_string(&path).map_err(|e| PacnerfError::Read {
        path: path.clone(),
        message: e.to_string(),
    })?;
    let de = &mut serde_json::Deserializer::from_str(&text);
    let raw: Vec<RawEntry> =
        serde_path_to_error::deserialize(de).map_err(|e| PacnerfError::Json {
            path: path.clone(),
            message: format!("at {}: {}", e.path(), e.inner()),
        })?;
    if raw.is_empty() {
        return Err(PacnerfError::Layout {
            path,
            message: "the list of images is empty".into(),
        });
    }
    let mut images = Vec::new();
    let mut plates = BTreeMap::new();
    for (index, e) in raw.into_iter().enumerate() {
        let bad = |field: &str, message: String| PacnerfError::Entry {
            path: path.clone(),
            index,
            file_path: e.file_path.clone(),
            field: field.to_string(),
            message,
        };
        let logical_name = e.file_path.trim_start_matches("./").to_string();
        let (view, frame) = parse_name(&logical_name).ok_or_else(|| {
            bad(
                "file_path",
                "expected a name like ./data/r_<camera>_<frame>.png".into(),
            )
        })?;
        if frame > i32::from(u16::MAX) {
            return Err(bad(
                "file_path",
                format!(
                    "frame {frame} is beyond the largest frame index {}",
                    u16::MAX
                ),
            ));
        }
        if !e.time.is_finite() {
            return Err(bad("time", format!("not a finite number: {}", e.time)));
        }
        let world_from_camera = convert_c2w(&e.c2w).map_err(|m| bad("c2w", m))?;
        let intrinsics = convert_intrinsic(&e.intrinsic).map_err(|m| bad("intrinsic", m))?;
        let img = PacnerfImage {
            view,
            frame,
            time_s: e.time,
            world_from_camera,
            intrinsics,
            path: root.join(&logical_name),
            logical_name,
        };
        if frame < 0 {
            if plates.insert(view, img).is_some() {
                return Err(bad(
                    "file_path",
                    format!("camera {view} has two background plates"),
                ));
            }
        } else {
            if images
                .iter()
                .any(|i: &PacnerfImage| i.view == view && i.frame == frame)
            {
                return Err(bad(
                    "file_path",
                    format!("camera {view} frame {frame} is listed twice"),
                ));
            }
            images.push(img);
        }
    }
    images.sort_by_key(|i| (i.view, i.frame));
    Ok(PacnerfScene {
        root: root.to_path_buf(),
        images,
        plates,
    })
}

/// Where a scene at `root` keeps the ground-truth object mask of camera `view`, frame
/// `frame`, when it has one: `gt/masks/m_<cam>_<frame>.png` (0/255, ≥ 128 = object).
pub fn gt_mask_path(root: &Path, view: u16, frame: i32) -> PathBuf {
    root.join("gt")
        .join("masks")
        .join(format!("m_{view}_{frame}.png"))
}

/// The scene as the layout-independent [`Capture`] `ingest` reads: its object images with
/// their ground-truth mask locations, its plates and `all_data.json`.
pub fn capture(scene: &PacnerfScene, camera_file: &Path) -> Capture {
    let file = |img: &PacnerfImage| DatasetFile {
        logical_name: img.logical_name.clone(),
        path: img.path.clone(),
    };
    Capture {
        images: scene
            .images
            .iter()
            .map(|img| CaptureImage {
                view: img.view,
                frame: u16::try_from(img.frame).expect("plates are not images"),
                time_s: img.time_s,
                world_from_camera: img.world_from_camera,
                intrinsics: img.intrinsics,
                file: file(img),
                video_frame: None,
                mask: DatasetFile {
                    logical_name: format!("gt/masks/m_{}_{}.png", img.view, img.frame),
                    path: gt_mask_path(&scene.root, img.view, img.frame),
                },
            })
            .collect(),
        plates: scene.plates.iter().map(|(v, p)| (*v, file(p))).collect(),
        camera_files: vec![DatasetFile {
            logical_name: "all_data.json".into(),
            path: camera_file.to_path_buf(),
        }],
    }
}

/// `data/r_<cam>_<frame>.png` → (cam, frame).
fn parse_name(name: &str) -> Option<(u16, i32)> {
    let file = name.rsplit('/').next()?;
    let stem = file.strip_prefix("r_")?.strip_suffix(".png")?;
    let (cam, frame) = stem.split_once('_')?;
    Some((cam.parse().ok()?, frame.parse().ok()?))
}

/// A 3×4 or 4×4 camera-to-world matrix in OpenGL axes (finite, orthonormal rotation, last row
/// `[0, 0, 0, 1]` when 4×4) as a row-major 3×4 `world_from_camera` in OpenCV axes; the error
/// says what is wrong with it.
pub(crate) fn convert_c2w(m: &[Vec<f64>]) -> Result<[f64; 12], String> {
    let rows = m.len();
    if !(rows == 3 || rows == 4) || m.iter().any(|r| r.len() != 4) {
        return Err(format!(
            "expected a 3×4 or 4×4 matrix, found {rows} rows of lengths {:?}",
            m.iter().map(Vec::len).collect::<Vec<_>>()
        ));
    }
    if let Some((i, j)) = (0..rows)
        .flat_map(|i| (0..4).map(move |j| (i, j)))
        .find(|&(i, j)| !m[i][j].is_finite())
    {
        return Err(format!("element [{i}][{j}] is not finite ({})", m[i][j]));
    }
    if rows == 4 {
        let last = &m[3];
        if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > 1e-6 {
            return Err(format!(
                "the last row of a 4×4 pose must be [0, 0, 0, 1], found {last:?}"
            ));
        }
    }
    // Rotation must be orthonormal.
    let r = |i: usize, j: usize| m[i][j];
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|k| r(k, a) * r(k, b)).sum();
            let want = if a == b { 1.0 } else { 0.0 };
            if (dot - want).abs() > 1e-4 {
                return Err(format!(
                    "the 3×3 rotation block is not orthonormal (column {a}·column {b} = {dot:.6})"
                ));
            }
        }
    }
    let mut out = [0.0; 12];
    for i in 0..3 {
        // OpenGL → OpenCV: negate the camera's y and z axes (columns 1 and 2).
        out[i * 4] = m[i][0];
        out[i * 4 + 1] = -m[i][1];
        out[i * 4 + 2] = -m[i][2];
        out[i * 4 + 3] = m[i][3];
    }
    Ok(out)
}

fn convert_intrinsic(k: &[Vec<f64>]) -> Result<[f64; 4], String> {
    if k.len() != 3 || k.iter().any(|r| r.len() != 3) {
        return Err("expected a 3×3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]".into());
    }
    if k.iter().flatten().any(|v| !v.is_finite()) {
        return Err("contains a non-finite value".into());
    }
    let (fx, fy, cx, cy) = (k[0][0], k[1][1], k[0][2], k[1][2]);
    if fx <= 0.0 || fy <= 0.0 {
        return Err(format!(
            "focal lengths must be positive, found fx = {fx}, fy = {fy}"
        ));
    }
    if k[2] != [0.0, 0.0, 1.0] {
        return Err(format!("the last row must be [0, 0, 1], found {:?}", k[2]));
    }
    Ok([fx, fy, cx, cy])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse() {
        assert_eq!(parse_name("data/r_10_-1.png"), Some((10, -1)));
        assert_eq!(parse_name("data/r_3_13.png"), Some((3, 13)));
        assert_eq!(parse_name("data/x_3_13.png"), None);
    }

    #[test]
    fn opengl_pose_becomes_opencv() {
        let c2w = vec![
            vec![1.0, 0.0, 0.0, 1.0],
            vec![0.0, 1.0, 0.0, 2.0],
            vec![0.0, 0.0, 1.0, 3.0],
        ];
        let w = convert_c2w(&c2w).unwrap();
        // Camera looks down world −z in OpenGL; in OpenCV its forward (+z) axis is world −z.
        assert_eq!([w[2], w[6], w[10]], [0.0, 0.0, -1.0]);
        assert_eq!([w[1], w[5], w[9]], [0.0, -1.0, 0.0]);
        assert_eq!([w[3], w[7], w[11]], [1.0, 2.0, 3.0]);
    }

    #[test]
    fn bad_matrices_are_named() {
        let e = convert_c2w(&[vec![1.0, 0.0, 0.0], vec![0.0; 4], vec![0.0; 4]]).unwrap_err();
        assert!(e.contains("3×4"), "{e}");
        let e = convert_c2w(&[
            vec![2.0, 0.0, 0.0, 0.0],
            vec![0.0, 1.0, 0.0, 0.0],
            vec![0.0, 0.0, 1.0, 0.0],
        ])
        .unwrap_err();
        assert!(e.contains("orthonormal"), "{e}");
        let e = convert_intrinsic(&[
            vec![-1.0, 0.0, 1.0],
            vec![0.0, 1.0, 1.0],
            vec![0.0, 0.0, 1.0],
        ])
        .unwrap_err();
        assert!(e.contains("fx = -1"), "{e}");
    }
}
