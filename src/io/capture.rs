//! A multi-view capture as `ingest` reads it, whatever the dataset layout (PAC-NeRF's
//! `all_data.json`, PhysDreamer's `transforms_train.json` or COLMAP `sparse/0`): the images of
//! every camera and frame with their cameras in OpenCV axes, each camera's background plate
//! when the layout has them, and where the dataset keeps each image's own object mask.

use std::collections::BTreeMap;
use std::path::PathBuf;

/// A file of the dataset: its logical name (relative to the scene folder, `/`-separated: what
/// the cache key hashes) and where it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetFile {
    /// Relative to the scene folder.
    pub logical_name: String,
    /// Where the file is.
    pub path: PathBuf,
}

/// One image of the capture.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureImage {
    /// Camera index.
    pub view: u16,
    /// Frame index, from 0.
    pub frame: u16,
    /// Time, seconds.
    pub time_s: f64,
    /// 3×4 row-major `world_from_camera`, OpenCV axes (x right, y down, z forward), metres.
    pub world_from_camera: [f64; 12],
    /// fx, fy, cx, cy in pixels at the image's own size (pixel centres at i + 0.5).
    pub intrinsics: [f64; 4],
    /// The image: a PNG, or with `video_frame` a video holding it.
    pub file: DatasetFile,
    /// Which frame of the video `file` is this image (from 0), when the layout stores a
    /// camera's frames as one video file.
    pub video_frame: Option<usize>,
    /// Where the dataset keeps this image's object mask (0/255, ≥ 128 = object), whether or
    /// not the file exists: PAC-NeRF `gt/masks/m_<cam>_<frame>.png`, PhysDreamer
    /// `masks/<view>/<frame>.png`.
    pub mask: DatasetFile,
}

impl CaptureImage {
    /// The image's pixels (a PNG read, or a video's frame decoded by `ffmpeg`).
    pub fn read_rgb8(&self) -> Result<super::image::Rgb8, super::image::ImageError> {
        match self.video_frame {
            None => super::image::read_rgb8(&self.file.path),
            Some(k) => super::video::frame(&self.file.path, k).map_err(|e| {
                super::image::ImageError::Decode {
                    path: self.file.path.clone(),
                    message: format!("frame {k}: {e}"),
                }
            }),
        }
    }

    /// Where the image is, for messages: the file, and the frame of a video.
    pub fn describe(&self) -> String {
        match self.video_frame {
            None => self.file.path.display().to_string(),
            Some(k) => format!("{} (frame {k})", self.file.path.display()),
        }
    }
}

/// A capture: images sorted by (view, frame), plates, and the files that describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    /// The images, sorted by (view, frame).
    pub images: Vec<CaptureImage>,
    /// Each camera's background plate (the scene without the object), if the layout has them.
    pub plates: BTreeMap<u16, DatasetFile>,
    /// The files holding the cameras (hashed into the cache key).
    pub camera_files: Vec<DatasetFile>,
}
