//! The PhysDreamer layout (ARCHITECTURE §6; PhysDreamer, Zhang et al. 2024, as its code reads
//! a scene): a trained 3DGS of a static scene, the points that select the object and its
//! moving part, the cameras, and a video per camera.
//!
//! ```text
//! <scene>/
//!   transforms_train.json       Blender cameras (else sparse/0: COLMAP, PINHOLE cameras)
//!   videos/<view>/<frame>.png   the frames of each camera (<view>: the stem of its file_path)
//!   videos/<view>.mp4           or its video (.mp4, .mov, .webm, .mkv; read with FFmpeg)
//!   masks/<view>/<frame>.png    optional object masks, 0/255 (ingest `matte: gt` reads them)
//!   point_cloud.ply             the trained 3DGS (every Gaussian of the scene)
//!   clean_object_points.ply     optional: points of the object (the rest is clutter)
//!   moving_part_points.ply      optional: points of the part that moves
//! ```
//!
//! `transforms_train.json`: `frames`, a list of cameras `{file_path, transform_matrix}` (4×4 or
//! 3×4 camera-to-world, OpenGL axes: the camera looks down −z, +y up; converted once, here, to
//! OpenCV axes as PAC-NeRF's), and the intrinsics, at the top level or per camera:
//! `camera_angle_x` (radians, horizontal field of view; `camera_angle_y` optional) or `fl_x`
//! (`fl_y`, `cx`, `cy` optional: pixels; the principal point defaults to the image centre),
//! with `w`/`h` (pixels) checked against the frames when given. Optional: a top-level `fps`
//! (frames per second of the videos; 24, PAC-NeRF's, when absent) and a per-camera `time`
//! (s) of its first frame (0 when absent; every camera must start at the same time). Other
//! keys are ignored. The image `file_path` names is not read (the 3DGS is already trained on
//! it): the stem of its file name names the camera's video folder, as PhysDreamer matches
//! videos to cameras by name. Cameras without a video folder are skipped (PhysDreamer does the
//! same) and listed in [`PhysdreamerScene::skipped`].
//!
//! A video folder's frames are its `*.png` files sorted by number when every name is one
//! (`0.png` … `12.png`), else by name; every camera must have as many. A camera without a
//! folder may have a video file instead (`ffprobe` counts its frames, `ffmpeg` decodes them;
//! both must be on `PATH`); its rate is the frame rate when the camera file gives no `fps`, and
//! its masks, if any, are the PNGs of `masks/<view>/` in the same order.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use super::capture::{Capture, CaptureImage, DatasetFile};
use super::colmap::{self, ColmapError};

/// Frames per second assumed when `transforms_train.json` gives no `fps` (PAC-NeRF's).
pub const DEFAULT_FPS: f64 = 24.0;

/// The scene's files, read and checked.
#[derive(Debug, Clone, PartialEq)]
pub struct PhysdreamerScene {
    /// The scene folder.
    pub root: PathBuf,
    /// The cameras' frames (view = the camera's index in `transforms_train.json` or, for
    /// COLMAP, in the images sorted by name) and masks; no plates.
    pub capture: Capture,
    /// Each view's name (the stem of its image), by view index.
    pub view_names: BTreeMap<u16, String>,
    /// Cameras listed without a video folder (their names), skipped.
    pub skipped: Vec<String>,
    /// Frames per second, and whether the dataset gave it (the camera file, else a video).
    pub fps: f64,
    pub fps_given: bool,
    /// `point_cloud.ply`.
    pub point_cloud: DatasetFile,
    /// `clean_object_points.ply`, if present.
    pub clean_object: Option<DatasetFile>,
    /// `moving_part_points.ply`, if present.
    pub moving_part: Option<DatasetFile>,
}

/// Why a PhysDreamer scene cannot be read. Every message names the file or folder.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhysdreamerError {
    /// A file cannot be read.
    #[error("{path}: cannot read: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// A field of a JSON file is missing or invalid.
    #[error("{path}: `{field}`: {message}")]
    Field {
        /// The file.
        path: PathBuf,
        /// The field (`frames[2].transform_matrix`).
        field: String,
        /// What is wrong, with the value.
        message: String,
    },
    /// Files or folders that are missing or do not agree.
    #[error("{path}: {message}")]
    Layout {
        /// The file or folder.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The COLMAP model is invalid.
    #[error(transparent)]
    Colmap(#[from] ColmapError),
}

/// One camera before its frames are listed.
struct ViewCamera {
    /// Index in the camera file.
    index: usize,
    /// Stem of its image name.
    name: String,
    /// `world_from_camera`, OpenCV axes.
    world_from_camera: [f64; 12],
    /// Time of its first frame (s).
    time0: f64,
    /// Intrinsics once the image size is known.
    intrinsics: Box<dyn Fn(u32, u32) -> Result<[f64; 4], PhysdreamerError>>,
}

/// Reads and checks the scene at `root`.
pub fn read_scene(root: &Path) -> Result<PhysdreamerScene, PhysdreamerError> {
    let transforms = root.join("transforms_train.json");
    let sparse = root.join("sparse").join("0");
    let (cameras, fps, camera_files) = if transforms.is_file() {
        let (cameras, fps) = blender_cameras(&transforms)?;
        let file = DatasetFile {
            logical_name: "transforms_train.json".into(),
            path: transforms.clone(),
        };
        (cameras, fps, vec![file])
    } else if sparse.is_dir() {
        let (cameras, files) = colmap_cameras(&sparse)?;
        (cameras, None, files)
    } else {
        return Err(PhysdreamerError::Layout {
            path: root.to_path_buf(),
            message: "no cameras: neither transforms_train.json nor sparse/0/ exists".into(),
        });
    };
    // Each camera's frames: a folder of PNGs, else one video file.
    let mut sources = Vec::new();
    let mut skipped = Vec::new();
    for cam in &cameras {
        let folder = root.join("videos").join(&cam.name);
        if folder.is_dir() {
            let names = frame_names(&folder)?;
            let size = image_size(&folder.join(&names[0]))?;
            sources.push((cam, Frames::Pngs { folder, names }, size));
        } else if let Some((rel, path)) = video_file(root, &cam.name) {
            let info = super::video::probe(&path).map_err(|e| PhysdreamerError::Read {
                path: path.clone(),
                message: e.to_string(),
            })?;
            let size = (info.width, info.height);
            sources.push((cam, Frames::Video { rel, path, info }, size));
        } else {
            skipped.push(cam.name.clone());
        }
    }
    // Frames per second: the camera file's, else the first video's own, else PAC-NeRF's.
    let video_fps = sources.iter().find_map(|(_, f, _)| match f {
        Frames::Video { info, .. } => info.fps,
        Frames::Pngs { .. } => None,
    });
    let fps_given = fps.is_some() || video_fps.is_some();
    let fps = fps.or(video_fps).unwrap_or(DEFAULT_FPS);
    let mut images = Vec::new();
    let mut view_names = BTreeMap::new();
    // (source, frame count, size) of the first camera with frames, to compare the others with.
    let mut first: Option<(PathBuf, usize, (u32, u32))> = None;
    let camera_file = camera_files[0].path.clone();
    for (cam, frames, size) in &sources {
        let (source, count) = match frames {
            Frames::Pngs { folder, names } => (folder.clone(), names.len()),
            Frames::Video { path, info, .. } => (path.clone(), info.frames),
        };
        let size = *size;
        match &first {
            None => first = Some((source.clone(), count, size)),
            Some((f0, n0, s0)) => {
                if count != *n0 {
                    return Err(PhysdreamerError::Layout {
                        path: source,
                        message: format!(
                            "{count} frames, but {} has {n0}: every camera must have as many frames",
                            f0.display()
                        ),
                    });
                }
                if size != *s0 {
                    return Err(PhysdreamerError::Layout {
                        path: source,
                        message: format!(
                            "{}×{} pixels, but the frames of {} are {}×{}: all images of a \
                             capture must have one size",
                            size.0,
                            size.1,
                            f0.display(),
                            s0.0,
                            s0.1
                        ),
                    });
                }
            }
        }
        let view = u16::try_from(cam.index).map_err(|_| PhysdreamerError::Layout {
            path: camera_file.clone(),
            message: format!("more than {} cameras", u16::MAX),
        })?;
        if count > usize::from(u16::MAX) {
            return Err(PhysdreamerError::Layout {
                path: source,
                message: format!("{count} frames: at most {}", u16::MAX),
            });
        }
        let intrinsics = (cam.intrinsics)(size.0, size.1)?;
        view_names.insert(view, cam.name.clone());
        // A video's masks: the PNGs of masks/<view>/ in frame order, when the folder exists.
        let video_masks = match frames {
            Frames::Video { .. } => {
                let folder = root.join("masks").join(&cam.name);
                match folder.is_dir() {
                    false => None,
                    true => {
                        let names = frame_names(&folder)?;
                        if names.len() != count {
                            return Err(PhysdreamerError::Layout {
                                path: folder,
                                message: format!(
                                    "{} masks, but the video {} has {count} frames",
                                    names.len(),
                                    source.display()
                                ),
                            });
                        }
                        Some(names)
                    }
                }
            }
            Frames::Pngs { .. } => None,
        };
        for frame in 0..count {
            let (file, video_frame, mask_name) = match frames {
                Frames::Pngs { names, .. } => {
                    let rel = format!("videos/{}/{}", cam.name, names[frame]);
                    (
                        DatasetFile {
                            path: root.join(&rel),
                            logical_name: rel,
                        },
                        None,
                        names[frame].clone(),
                    )
                }
                Frames::Video { rel, path, .. } => (
                    DatasetFile {
                        path: path.clone(),
                        logical_name: rel.clone(),
                    },
                    Some(frame),
                    match &video_masks {
                        Some(names) => names[frame].clone(),
                        None => format!("{frame:05}.png"),
                    },
                ),
            };
            let mask = format!("masks/{}/{mask_name}", cam.name);
            images.push(CaptureImage {
                view,
                frame: frame as u16,
                time_s: cam.time0 + frame as f64 / fps,
                world_from_camera: cam.world_from_camera,
                intrinsics,
                file,
                video_frame,
                mask: DatasetFile {
                    path: root.join(&mask),
                    logical_name: mask,
                },
            });
        }
    }
    if images.is_empty() {
        return Err(PhysdreamerError::Layout {
            path: root.join("videos"),
            message: format!(
                "no camera has a video (expected videos/<view>/ with PNG frames, or a video \
                 videos/<view>.mp4, for the cameras of {}: {})",
                camera_file.display(),
                cameras
                    .iter()
                    .map(|c| c.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        });
    }
    let t0 = cameras
        .iter()
        .find(|c| view_names.values().any(|n| *n == c.name))
        .expect("a camera has frames");
    if let Some(c) = cameras
        .iter()
        .find(|c| view_names.values().any(|n| *n == c.name) && (c.time0 - t0.time0).abs() > 1e-9)
    {
        return Err(PhysdreamerError::Field {
            path: camera_file,
            field: format!("frames[{}].time", c.index),
            message: format!(
                "{} s, but camera `{}` starts at {} s: the videos must start together",
                c.time0, t0.name, t0.time0
            ),
        });
    }
    let ply = |name: &str| {
        let path = root.join(name);
        path.is_file().then(|| DatasetFile {
            logical_name: name.into(),
            path,
        })
    };
    let point_cloud = ply("point_cloud.ply").ok_or_else(|| PhysdreamerError::Layout {
        path: root.join("point_cloud.ply"),
        message: "missing: the layout's trained 3DGS (every Gaussian of the scene)".into(),
    })?;
    Ok(PhysdreamerScene {
        root: root.to_path_buf(),
        capture: Capture {
            images,
            plates: BTreeMap::new(),
            camera_files,
        },
        view_names,
        skipped,
        fps,
        fps_given,
        point_cloud,
        clean_object: ply("clean_object_points.ply"),
        moving_part: ply("moving_part_points.ply"),
    })
}

/// Where a camera's frames are.
enum Frames {
    /// `videos/<view>/`: its PNG names, in frame order.
    Pngs { folder: PathBuf, names: Vec<String> },
    /// `videos/<view>.mp4` (or another [`VIDEO_EXTENSIONS`] file), decoded by FFmpeg.
    Video {
        rel: String,
        path: PathBuf,
        info: super::video::VideoInfo,
    },
}

/// Video files read for a camera without a PNG folder (with FFmpeg).
pub const VIDEO_EXTENSIONS: [&str; 4] = ["mp4", "mov", "webm", "mkv"];

/// `videos/<name>.<ext>` for the first [`VIDEO_EXTENSIONS`] that exists: (logical name, path).
fn video_file(root: &Path, name: &str) -> Option<(String, PathBuf)> {
    VIDEO_EXTENSIONS.iter().find_map(|ext| {
        let rel = format!("videos/{name}.{ext}");
        let path = root.join(&rel);
        path.is_file().then_some((rel, path))
    })
}

/// The PNG frames of a video folder, in frame order.
fn frame_names(folder: &Path) -> Result<Vec<String>, PhysdreamerError> {
    let read_err = |e: std::io::Error| PhysdreamerError::Read {
        path: folder.to_path_buf(),
        message: e.to_string(),
    };
    let mut names = Vec::new();
    for e in std::fs::read_dir(folder).map_err(read_err)? {
        let e = e.map_err(read_err)?;
        let name = e.file_name().to_string_lossy().into_owned();
        if name.to_ascii_lowercase().ends_with(".png") && e.path().is_file() {
            names.push(name);
        }
    }
    if names.is_empty() {
        return Err(PhysdreamerError::Layout {
            path: folder.to_path_buf(),
            message: "holds no PNG frames".into(),
        });
    }
    let number = |n: &String| n[..n.len() - 4].parse::<u64>().ok();
    if names.iter().all(|n| number(n).is_some()) {
        names.sort_by_key(|n| (number(n), n.clone()));
        if let Some(w) = names.windows(2).find(|w| number(&w[0]) == number(&w[1])) {
            return Err(PhysdreamerError::Layout {
                path: folder.to_path_buf(),
                message: format!("`{}` and `{}` are the same frame number", w[0], w[1]),
            });
        }
    } else {
        names.sort();
    }
    Ok(names)
}

/// Width and height (pixels) of an image, from its header.
fn image_size(path: &Path) -> Result<(u32, u32), PhysdreamerError> {
    image::image_dimensions(path).map_err(|e| PhysdreamerError::Read {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// A finite number at `obj[key]`, if present.
fn number(
    obj: &Map<String, Value>,
    key: &str,
    field: &str,
    path: &Path,
) -> Result<Option<f64>, PhysdreamerError> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => match v.as_f64().filter(|x| x.is_finite()) {
            Some(x) => Ok(Some(x)),
            None => Err(PhysdreamerError::Field {
                path: path.to_path_buf(),
                field: field.to_string(),
                message: format!("expected a finite number, found {v}"),
            }),
        },
    }
}

/// Intrinsics of a Blender camera: the entry's keys over the file's.
#[derive(Debug, Clone, Copy, Default)]
struct BlenderIntrinsics {
    angle_x: Option<(f64, &'static str)>,
    angle_y: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
}

/// Reads the intrinsic keys of `obj` (`prefix` names it in messages) over `base`.
fn blender_intrinsics(
    obj: &Map<String, Value>,
    prefix: &str,
    path: &Path,
    base: BlenderIntrinsics,
) -> Result<BlenderIntrinsics, PhysdreamerError> {
    let get = |key: &str| number(obj, key, &format!("{prefix}{key}"), path);
    let field = |key: &str| format!("{prefix}{key}");
    let bad = |key: &str, message: String| PhysdreamerError::Field {
        path: path.to_path_buf(),
        field: field(key),
        message,
    };
    let mut k = base;
    if let Some(a) = get("camera_angle_x")? {
        if !(a > 0.0 && a < std::f64::consts::PI) {
            return Err(bad(
                "camera_angle_x",
                format!("{a}: a field of view in radians must be in (0, π)"),
            ));
        }
        k.angle_x = Some((a, if prefix.is_empty() { "file" } else { "entry" }));
    }
    if let Some(a) = get("camera_angle_y")? {
        if !(a > 0.0 && a < std::f64::consts::PI) {
            return Err(bad(
                "camera_angle_y",
                format!("{a}: a field of view in radians must be in (0, π)"),
            ));
        }
        k.angle_y = Some(a);
    }
    for (key, slot) in [("fl_x", &mut k.fl_x), ("fl_y", &mut k.fl_y)] {
        if let Some(f) = get(key)? {
            if f <= 0.0 {
                return Err(bad(key, format!("{f}: a focal length must be > 0 pixels")));
            }
            *slot = Some(f);
        }
    }
    for (key, slot) in [("cx", &mut k.cx), ("cy", &mut k.cy)] {
        if let Some(c) = get(key)? {
            *slot = Some(c);
        }
    }
    for (key, slot) in [("w", &mut k.w), ("h", &mut k.h)] {
        if let Some(s) = get(key)? {
            if !(s >= 1.0 && s.fract() == 0.0) {
                return Err(bad(
                    key,
                    format!("{s}: an image size must be a whole number ≥ 1"),
                ));
            }
            *slot = Some(s);
        }
    }
    Ok(k)
}

impl BlenderIntrinsics {
    /// `[fx, fy, cx, cy]` for frames of `width × height`, checked against `w`/`h`; `index` is
    /// the camera's entry (for messages).
    fn resolve(
        &self,
        width: u32,
        height: u32,
        index: usize,
        path: &Path,
    ) -> Result<[f64; 4], PhysdreamerError> {
        let (w, h) = (f64::from(width), f64::from(height));
        for (key, given, actual) in [("w", self.w, w), ("h", self.h, h)] {
            if let Some(g) = given
                && g != actual
            {
                return Err(PhysdreamerError::Field {
                    path: path.to_path_buf(),
                    field: key.into(),
                    message: format!(
                        "{g} pixels, but the frames of camera {index} are {width}×{height}"
                    ),
                });
            }
        }
        let fx = match (self.fl_x, self.angle_x) {
            (Some(f), _) => f,
            (None, Some((a, _))) => 0.5 * w / (0.5 * a).tan(),
            (None, None) => {
                return Err(PhysdreamerError::Field {
                    path: path.to_path_buf(),
                    field: "camera_angle_x".into(),
                    message: format!(
                        "missing (for camera {index}): give `camera_angle_x` (radians) or \
                         `fl_x` (pixels), at the top level or in the camera's entry"
                    ),
                });
            }
        };
        let fy = match (self.fl_y, self.angle_y) {
            (Some(f), _) => f,
            (None, Some(a)) => 0.5 * h / (0.5 * a).tan(),
            (None, None) => fx,
        };
        let (cx, cy) = (self.cx.unwrap_or(0.5 * w), self.cy.unwrap_or(0.5 * h));
        for (key, c, size) in [("cx", cx, w), ("cy", cy, h)] {
            if !(0.0..=size).contains(&c) {
                return Err(PhysdreamerError::Field {
                    path: path.to_path_buf(),
                    field: key.into(),
                    message: format!(
                        "{c} lies outside the {width}×{height} frames of camera {index}: are \
                         the intrinsics for another resolution?"
                    ),
                });
            }
        }
        Ok([fx, fy, cx, cy])
    }
}

/// The cameras of a Blender `transforms_train.json`, and its `fps` if given.
fn blender_cameras(path: &Path) -> Result<(Vec<ViewCamera>, Option<f64>), PhysdreamerError> {
    let text = std::fs::read_to_string(path).map_err(|e| PhysdreamerError::Read {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let root: Value = serde_json::from_str(&text).map_err(|e| PhysdreamerError::Read {
        path: path.to_path_buf(),
        message: format!("not valid JSON: {e}"),
    })?;
    let field = |field: &str, message: String| PhysdreamerError::Field {
        path: path.to_path_buf(),
        field: field.to_string(),
        message,
    };
    let top = root
        .as_object()
        .ok_or_else(|| field("(top level)", "expected an object with `frames`".into()))?;
    let fps = number(top, "fps", "fps", path)?;
    if let Some(f) = fps
        && f <= 0.0
    {
        return Err(field("fps", format!("{f}: frames per second must be > 0")));
    }
    let base = blender_intrinsics(top, "", path, BlenderIntrinsics::default())?;
    let frames = match top.get("frames") {
        Some(Value::Array(a)) if !a.is_empty() => a,
        Some(Value::Array(_)) => {
            return Err(field("frames", "the list of cameras is empty".into()));
        }
        Some(v) => {
            return Err(field(
                "frames",
                format!("expected a list of cameras, found {v}"),
            ));
        }
        None => return Err(field("frames", "missing: the list of cameras".into())),
    };
    let mut cameras: Vec<ViewCamera> = Vec::with_capacity(frames.len());
    for (index, entry) in frames.iter().enumerate() {
        let prefix = format!("frames[{index}].");
        let obj = entry.as_object().ok_or_else(|| {
            field(
                &format!("frames[{index}]"),
                format!("expected an object, found {entry}"),
            )
        })?;
        let file_path = match obj.get("file_path") {
            Some(Value::String(s)) => s.clone(),
            Some(v) => {
                return Err(field(
                    &format!("{prefix}file_path"),
                    format!("expected a string, found {v}"),
                ));
            }
            None => return Err(field(&format!("{prefix}file_path"), "missing".into())),
        };
        let name = view_name(&file_path).ok_or_else(|| {
            field(
                &format!("{prefix}file_path"),
                format!("`{file_path}` has no file name"),
            )
        })?;
        if let Some(other) = cameras.iter().find(|c| c.name == name) {
            return Err(field(
                &format!("{prefix}file_path"),
                format!(
                    "`{file_path}` names camera `{name}`, as frames[{}] does: each camera needs \
                     its own video folder videos/<name>/",
                    other.index
                ),
            ));
        }
        let matrix = matrix_rows(obj.get("transform_matrix"))
            .map_err(|m| field(&format!("{prefix}transform_matrix"), m))?;
        let world_from_camera = super::pacnerf::convert_c2w(&matrix)
            .map_err(|m| field(&format!("{prefix}transform_matrix"), m))?;
        let time0 = number(obj, "time", &format!("{prefix}time"), path)?.unwrap_or(0.0);
        let k = blender_intrinsics(obj, &prefix, path, base)?;
        let owned = path.to_path_buf();
        cameras.push(ViewCamera {
            index,
            name,
            world_from_camera,
            time0,
            intrinsics: Box::new(move |w, h| k.resolve(w, h, index, &owned)),
        });
    }
    Ok((cameras, fps))
}

/// A JSON matrix as rows of numbers (shape checked by the conversion).
fn matrix_rows(v: Option<&Value>) -> Result<Vec<Vec<f64>>, String> {
    let rows = match v {
        None => return Err("missing: the 4×4 camera-to-world matrix".into()),
        Some(Value::Array(rows)) => rows,
        Some(v) => return Err(format!("expected a 4×4 matrix (a list of rows), found {v}")),
    };
    rows.iter()
        .enumerate()
        .map(|(i, r)| match r {
            Value::Array(xs) => xs
                .iter()
                .enumerate()
                .map(|(j, x)| {
                    x.as_f64()
                        .ok_or_else(|| format!("element [{i}][{j}] is not a number: {x}"))
                })
                .collect(),
            _ => Err(format!("row {i} is not a list of numbers: {r}")),
        })
        .collect()
}

/// The camera's name: the stem of the file name of its image path.
fn view_name(file_path: &str) -> Option<String> {
    let file = file_path.rsplit(['/', '\\']).next()?;
    let stem = match file.rsplit_once('.') {
        Some((stem, _)) if !stem.is_empty() => stem,
        _ => file,
    };
    (!stem.is_empty() && stem != "." && stem != "..").then(|| stem.to_string())
}

/// The cameras of a COLMAP model (PINHOLE or SIMPLE_PINHOLE: undistorted), images sorted by
/// name; the model's files.
fn colmap_cameras(dir: &Path) -> Result<(Vec<ViewCamera>, Vec<DatasetFile>), PhysdreamerError> {
    let model = colmap::read_model(dir)?;
    let mut files = Vec::new();
    for stem in ["cameras", "images", "points3D"] {
        for ext in ["bin", "txt"] {
            let name = format!("{stem}.{ext}");
            if dir.join(&name).is_file() {
                files.push(DatasetFile {
                    logical_name: format!("sparse/0/{name}"),
                    path: dir.join(&name),
                });
            }
        }
    }
    let mut images: Vec<&colmap::ColmapImage> = model.images.iter().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let mut cameras: Vec<ViewCamera> = Vec::with_capacity(images.len());
    for (index, im) in images.into_iter().enumerate() {
        let cam = model
            .cameras
            .iter()
            .find(|c| c.id == im.camera_id)
            .expect("read_model checks every image's camera");
        let cam_file = files
            .iter()
            .find(|f| f.logical_name.starts_with("sparse/0/cameras"))
            .map_or_else(|| dir.to_path_buf(), |f| f.path.clone());
        let [fx, fy, cx, cy] = match (cam.model.as_str(), cam.params.as_slice()) {
            ("PINHOLE", &[fx, fy, cx, cy]) => [fx, fy, cx, cy],
            ("SIMPLE_PINHOLE", &[f, cx, cy]) => [f, f, cx, cy],
            (model, _) => {
                return Err(PhysdreamerError::Field {
                    path: cam_file,
                    field: format!("camera {}", cam.id),
                    message: format!(
                        "model {model}: only undistorted PINHOLE or SIMPLE_PINHOLE cameras are \
                         read (run COLMAP's image_undistorter first)"
                    ),
                });
            }
        };
        let name = view_name(&im.name).ok_or_else(|| PhysdreamerError::Field {
            path: dir.to_path_buf(),
            field: format!("image {}", im.id),
            message: format!("`{}` has no file name", im.name),
        })?;
        if let Some(other) = cameras.iter().find(|c| c.name == name) {
            return Err(PhysdreamerError::Field {
                path: dir.to_path_buf(),
                field: format!("image {}", im.id),
                message: format!(
                    "`{}` names camera `{name}` as image {} does",
                    im.name, other.index
                ),
            });
        }
        // cam_from_world (R, t) → world_from_camera (Rᵀ, −Rᵀt), already OpenCV axes.
        let r = im.camera_from_world_rotation();
        let c = im.camera_center_world();
        let mut world_from_camera = [0.0; 12];
        for i in 0..3 {
            for j in 0..3 {
                world_from_camera[i * 4 + j] = r[j][i];
            }
            world_from_camera[i * 4 + 3] = c[i];
        }
        if world_from_camera.iter().any(|v| !v.is_finite()) {
            return Err(PhysdreamerError::Field {
                path: dir.to_path_buf(),
                field: format!("image {}", im.id),
                message: format!("pose of `{}` is not finite", im.name),
            });
        }
        let (cw, ch, id) = (cam.width, cam.height, cam.id);
        cameras.push(ViewCamera {
            index,
            name,
            world_from_camera,
            time0: 0.0,
            intrinsics: Box::new(move |w, h| {
                if (u64::from(w), u64::from(h)) != (cw, ch) {
                    return Err(PhysdreamerError::Field {
                        path: cam_file.clone(),
                        field: format!("camera {id}"),
                        message: format!(
                            "{cw}×{ch} pixels, but the frames of camera {index} are {w}×{h}"
                        ),
                    });
                }
                Ok([fx, fy, cx, cy])
            }),
        });
    }
    if cameras.is_empty() {
        return Err(PhysdreamerError::Layout {
            path: dir.to_path_buf(),
            message: "the COLMAP model has no images".into(),
        });
    }
    Ok((cameras, files))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_names_are_file_stems() {
        assert_eq!(
            view_name("./images/frame_00001.png").as_deref(),
            Some("frame_00001")
        );
        assert_eq!(view_name("train/r_0").as_deref(), Some("r_0"));
        assert_eq!(view_name("images/").as_deref(), None);
    }
}
