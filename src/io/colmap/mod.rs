//! COLMAP sparse models (`sparse/0`): `cameras`, `images`, `points3D` as `.bin` or `.txt`.
//!
//! Hand-written readers (`binary`, `text`): no maintained crate reads the `.bin` layout.
//! Poses are `cam_from_world` (X_cam = R(q)·X_world + t, q = (w, x, y, z) Hamilton), camera axes
//! as OpenCV (x right, y down, z forward), metres as reconstructed (COLMAP's scale is
//! arbitrary unless the model was geo-registered). `rigs` and `frames` (COLMAP ≥ 3.12) are not
//! read. Records are counted from 0 in error messages; byte offsets are from the file start.

mod binary;
mod text;

use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// One camera: intrinsics in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    /// `CAMERA_ID`.
    pub id: u32,
    /// Model name (`PINHOLE`, `SIMPLE_RADIAL`, ...).
    pub model: String,
    /// Image width, pixels.
    pub width: u64,
    /// Image height, pixels.
    pub height: u64,
    /// The model's parameters (e.g. PINHOLE: fx, fy, cx, cy), pixels; centre of the top-left
    /// pixel at (0.5, 0.5).
    pub params: Vec<f64>,
}

/// One registered image: its pose and keypoints.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    /// `IMAGE_ID`.
    pub id: u32,
    /// File name relative to the image folder (may contain `/`).
    pub name: String,
    /// The camera it was taken with.
    pub camera_id: u32,
    /// Rotation of `cam_from_world`, (w, x, y, z), non-zero (normalised when used).
    pub qvec_wxyz: [f64; 4],
    /// Translation of `cam_from_world`, metres.
    pub tvec: [f64; 3],
    /// Keypoints (pixels) and the 3D point each observes, if any.
    pub points2d: Vec<([f64; 2], Option<u64>)>,
}

impl ColmapImage {
    /// Rotation of `cam_from_world` (row-major), from the normalised `qvec_wxyz`.
    pub fn camera_from_world_rotation(&self) -> [[f64; 3]; 3] {
        let [w, x, y, z] = self.qvec_wxyz;
        let n = (w * w + x * x + y * y + z * z).sqrt();
        let (w, x, y, z) = (w / n, x / n, y / n, z / n);
        [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ]
    }

    /// Camera centre in world coordinates, metres: −Rᵀ·t.
    pub fn camera_center_world(&self) -> [f64; 3] {
        let r = self.camera_from_world_rotation();
        let t = self.tvec;
        std::array::from_fn(|j| -(r[0][j] * t[0] + r[1][j] * t[1] + r[2][j] * t[2]))
    }
}

/// One triangulated point.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapPoint {
    /// `POINT3D_ID`.
    pub id: u64,
    /// Position, world, metres.
    pub xyz: [f64; 3],
    /// Colour, 0..=255.
    pub rgb: [u8; 3],
    /// Mean reprojection error, pixels.
    pub error: f64,
    /// Observations: (image id, index into that image's `points2d`).
    pub track: Vec<(u32, u32)>,
}

/// A sparse model, records in file order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ColmapModel {
    /// Cameras.
    pub cameras: Vec<ColmapCamera>,
    /// Images.
    pub images: Vec<ColmapImage>,
    /// 3D points.
    pub points: Vec<ColmapPoint>,
}

/// Why a COLMAP model cannot be read. Every message names the file (or folder).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ColmapError {
    /// The OS refused to read a file.
    #[error("{path}: cannot {action}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was attempted.
        action: &'static str,
        /// OS message.
        message: String,
    },
    /// Neither `<name>.bin` nor `<name>.txt` exists.
    #[error("{dir}: no `{name}.bin` or `{name}.txt` (not a COLMAP sparse model folder?)")]
    Missing {
        /// The model folder.
        dir: PathBuf,
        /// `cameras`, `images` or `points3D`.
        name: &'static str,
    },
    /// A binary file ends inside a record.
    #[error(
        "{path}: truncated: {record} needs {needed} bytes at byte {offset}, file has {file_len} bytes"
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Which record (`camera record 1 of 3`).
        record: String,
        /// Bytes the next field needs.
        needed: u64,
        /// Where that field starts.
        offset: u64,
        /// File length, bytes.
        file_len: u64,
    },
    /// A camera model id COLMAP does not define (binary files).
    #[error("{path}: {record} at byte {offset}: unknown camera model id {id}")]
    UnknownModelId {
        /// The file.
        path: PathBuf,
        /// Which record.
        record: String,
        /// Where the id is.
        offset: u64,
        /// The id.
        id: i32,
    },
    /// Any other problem in a binary file (count too large, bad name, trailing bytes).
    #[error("{path}: {record} at byte {offset}: {message}")]
    Binary {
        /// The file.
        path: PathBuf,
        /// Which record, or `header`.
        record: String,
        /// Where.
        offset: u64,
        /// What is wrong.
        message: String,
    },
    /// A bad line in a text file (unknown model names included).
    #[error("{path}: line {line}: {message}")]
    Text {
        /// The file.
        path: PathBuf,
        /// Line number, from 1.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// Records that contradict each other (duplicate ids, an image of an unknown camera).
    #[error("{path}: {message}")]
    Inconsistent {
        /// The file holding the offending record.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// COLMAP's camera models: (model id, name, number of parameters).
const MODELS: [(i32, &str, usize); 12] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

/// Name and parameter count of model id `id`.
fn model_by_id(id: i32) -> Option<(&'static str, usize)> {
    MODELS.iter().find(|m| m.0 == id).map(|m| (m.1, m.2))
}

/// Name and parameter count of model `name`.
fn model_by_name(name: &str) -> Option<(&'static str, usize)> {
    MODELS.iter().find(|m| m.1 == name).map(|m| (m.1, m.2))
}

/// A quaternion a rotation can be made of: finite and not zero.
fn valid_quaternion(q: &[f64; 4]) -> bool {
    let n = q.iter().map(|v| v * v).sum::<f64>();
    n.is_finite() && n > 0.0
}

/// Reads the model in `dir`; for each of `cameras`, `images`, `points3D` the `.bin` file is used
/// if present, else the `.txt`.
pub fn read_model(dir: &Path) -> Result<ColmapModel, ColmapError> {
    let pick = |name: &'static str| -> Result<(PathBuf, bool), ColmapError> {
        let bin = dir.join(format!("{name}.bin"));
        if bin.is_file() {
            return Ok((bin, true));
        }
        let txt = dir.join(format!("{name}.txt"));
        if txt.is_file() {
            return Ok((txt, false));
        }
        Err(ColmapError::Missing {
            dir: dir.to_path_buf(),
            name,
        })
    };
    let (cam_path, bin) = pick("cameras")?;
    let cameras = if bin {
        binary::cameras(&cam_path)?
    } else {
        text::cameras(&cam_path)?
    };
    let (img_path, bin) = pick("images")?;
    let images = if bin {
        binary::images(&img_path)?
    } else {
        text::images(&img_path)?
    };
    let (pts_path, bin) = pick("points3D")?;
    let points = if bin {
        binary::points(&pts_path)?
    } else {
        text::points(&pts_path)?
    };
    let model = ColmapModel {
        cameras,
        images,
        points,
    };
    check(&model, &cam_path, &img_path, &pts_path)?;
    Ok(model)
}

/// Unique ids, and every image's camera exists.
fn check(
    m: &ColmapModel,
    cam_path: &Path,
    img_path: &Path,
    pts_path: &Path,
) -> Result<(), ColmapError> {
    let inconsistent = |path: &Path, message: String| ColmapError::Inconsistent {
        path: path.to_path_buf(),
        message,
    };
    let mut cams = HashSet::new();
    for c in &m.cameras {
        if !cams.insert(c.id) {
            return Err(inconsistent(
                cam_path,
                format!("camera id {} appears twice", c.id),
            ));
        }
    }
    let mut imgs = HashSet::new();
    for im in &m.images {
        if !imgs.insert(im.id) {
            return Err(inconsistent(
                img_path,
                format!("image id {} appears twice", im.id),
            ));
        }
        if !cams.contains(&im.camera_id) {
            return Err(inconsistent(
                img_path,
                format!(
                    "image {} (`{}`) uses camera {}, which is not in the cameras file",
                    im.id, im.name, im.camera_id
                ),
            ));
        }
    }
    let mut pts = HashSet::new();
    for p in &m.points {
        if !pts.insert(p.id) {
            return Err(inconsistent(
                pts_path,
                format!("point id {} appears twice", p.id),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(q: [f64; 4], t: [f64; 3]) -> ColmapImage {
        ColmapImage {
            id: 1,
            name: "a.png".into(),
            camera_id: 1,
            qvec_wxyz: q,
            tvec: t,
            points2d: Vec::new(),
        }
    }

    #[test]
    fn rotation_and_centre() {
        // 90° about z, unnormalised: x_cam = (−y, x, z) of the world point.
        let h = std::f64::consts::FRAC_1_SQRT_2 * 2.0;
        let im = image([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]);
        let r = im.camera_from_world_rotation();
        let want = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        for (a, b) in r.iter().flatten().zip(want.iter().flatten()) {
            assert!((a - b).abs() < 1e-15, "{r:?}");
        }
        // Centre c satisfies R·c + t = 0.
        let c = im.camera_center_world();
        for (row, t) in r.iter().zip(im.tvec) {
            let v: f64 = row.iter().zip(c).map(|(a, b)| a * b).sum::<f64>() + t;
            assert!(v.abs() < 1e-13);
        }
        assert_eq!(model_by_id(11), Some(("RAD_TAN_THIN_PRISM_FISHEYE", 16)));
        assert_eq!(model_by_name("OPENCV"), Some(("OPENCV", 8)));
        assert!(!valid_quaternion(&[0.0; 4]));
    }
}
