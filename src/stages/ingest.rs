//! Stage `ingest`: read a PAC-NeRF capture, matte the object out of every image against its
//! camera's background plate, and write masks, white-composited images and `frames.arrow`.
//!
//! When the dataset ships ground-truth masks (`gt/masks/m_<cam>_<frame>.png`), the mask IoU of
//! every image is recorded in `metrics.arrow` (`mask_iou`), so the matte's quality is visible.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::io::image::{self, Rgb8};
use crate::io::pacnerf::{self, PacnerfImage, PacnerfScene};
use crate::pipeline::spec::{DatasetKind, Preset, SceneSpec};
use crate::pipeline::stage::{
    InputFile, MetricRow, ParamError, StageContext, StageError, TypedStage,
};
use crate::scene::frames::{FrameRow, Frames, Role};
use crate::scene::table::{self, Table};

/// How the object mask of each image is obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum MatteMode {
    /// Background subtraction against `r_<cam>_-1.png`, robust to the object's shadow.
    Plate,
    /// Use the dataset's ground-truth masks (`gt/masks/`), for ablations.
    Gt,
    /// No matting: the whole image is the object.
    None,
}

/// Parameters of `ingest`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IngestParams {
    /// How masks are made.
    #[serde(default = "default_matte")]
    pub matte: MatteMode,
    /// Frame indices to ingest; all frames when absent.
    #[serde(default)]
    pub frames: Option<Vec<u16>>,
    /// Colour behind the object in the composited images, RGB in [0, 1].
    #[serde(default = "default_background")]
    pub background: [f32; 3],
}

fn default_matte() -> MatteMode {
    MatteMode::Plate
}

fn default_background() -> [f32; 3] {
    [1.0, 1.0, 1.0]
}

/// Problems specific to ingest (each names the file and the value).
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// The dataset JSON is invalid.
    #[error(transparent)]
    Dataset(#[from] pacnerf::PacnerfError),
    /// An image could not be read or written.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// Sizes, views or frames do not add up.
    #[error("{0}")]
    Invalid(String),
    /// Writing the table failed.
    #[error(transparent)]
    Table(#[from] table::TableError),
    /// The matte kernel refused its input.
    #[error("{path}: {source}")]
    Matte {
        /// The image.
        path: PathBuf,
        /// Why.
        source: pipe_matte::MatteError,
    },
}

/// The `ingest` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Ingest;

impl TypedStage for Ingest {
    type Params = IngestParams;
    const KIND: &'static str = "ingest";
    const VERSION: u32 = 2;
    const DESCRIPTION: &'static str = "Read a PAC-NeRF capture, matte the object against each camera's background plate, write masks, composited images, the plates and frames.arrow";

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![(Frames::NAME, Frames::VERSION)]
    }

    fn preset_params(&self, _preset: Preset) -> Value {
        json!({})
    }

    fn validate(&self, p: &IngestParams) -> Result<(), ParamError> {
        if let Some(c) = p.background.iter().position(|c| !(0.0..=1.0).contains(c)) {
            return Err(ParamError {
                path: format!("background[{c}]"),
                message: format!("must be in [0, 1], found {}", p.background[c]),
            });
        }
        if p.frames.as_ref().is_some_and(Vec::is_empty) {
            return Err(ParamError {
                path: "frames".into(),
                message: "an empty list selects no frame; omit the key to ingest all frames".into(),
            });
        }
        Ok(())
    }

    fn scene_key(&self, scene: &SceneSpec) -> Value {
        json!({"dataset": scene.dataset, "test_views": scene.test_views})
    }

    fn inputs(&self, p: &IngestParams, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError> {
        let ds = open(scene)?;
        let mut out = vec![InputFile {
            logical_name: "all_data.json".into(),
            path: scene.path.join("all_data.json"),
        }];
        for img in selected(&ds, p).into_iter().chain(ds.plates.values()) {
            out.push(InputFile {
                logical_name: img.logical_name.clone(),
                path: img.path.clone(),
            });
        }
        for img in selected(&ds, p) {
            let gt = gt_mask_path(&scene.path, img);
            if gt.exists() {
                out.push(InputFile {
                    logical_name: format!("gt/masks/m_{}_{}.png", img.view, img.frame),
                    path: gt,
                });
            }
        }
        Ok(out)
    }

    fn run(&self, p: &IngestParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let scene = ctx.scene;
        let ds = open(scene)?;
        let views: BTreeSet<u16> = ds.images.iter().map(|i| i.view).collect();
        if let Some(v) = scene.test_views.iter().find(|v| !views.contains(v)) {
            return Err(StageError::failed(IngestError::Invalid(format!(
                "scene.test_views: camera {v} is not in {} (cameras: {})",
                scene.path.join("all_data.json").display(),
                views
                    .iter()
                    .map(u16::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            ))));
        }
        let images = selected(&ds, p);
        if images.is_empty() {
            return Err(StageError::failed(IngestError::Invalid(format!(
                "stages.ingest.frames: none of the frames {:?} exists in {}",
                p.frames.as_deref().unwrap_or_default(),
                scene.path.display()
            ))));
        }
        std::fs::create_dir_all(ctx.out_dir.join("images")).map_err(StageError::failed)?;
        std::fs::create_dir_all(ctx.out_dir.join("masks")).map_err(StageError::failed)?;
        std::fs::create_dir_all(ctx.out_dir.join("plates")).map_err(StageError::failed)?;

        // Plates first: they fix each camera's image size.
        let plates: Vec<(u16, Rgb8)> = ds
            .plates
            .iter()
            .filter(|(v, _)| images.iter().any(|i| i.view == **v))
            .map(|(v, img)| image::read_rgb8(&img.path).map(|r| (*v, r)))
            .collect::<Result<_, _>>()
            .map_err(|e| StageError::failed(IngestError::from(e)))?;
        let (w0, h0) = (plates[0].1.width, plates[0].1.height);
        for (v, pl) in &plates {
            if (pl.width, pl.height) != (w0, h0) {
                return Err(StageError::failed(IngestError::Invalid(format!(
                    "{}: plate is {}×{}, but {} is {w0}×{h0}; all images of a capture must have one size",
                    ds.plates[v].path.display(),
                    pl.width,
                    pl.height,
                    ds.plates[&plates[0].0].path.display()
                ))));
            }
            image::write_rgb8(&ctx.out_dir.join(plate_rel(*v)), pl)
                .map_err(|e| StageError::failed(IngestError::from(e)))?;
        }

        ctx.progress.start("matte", images.len() as u64);
        let out_dir = ctx.out_dir.to_path_buf();
        let progress = ctx.progress;
        let interrupted = &*ctx;
        let results: Vec<Result<(FrameRow, Option<f64>), StageError>> = images
            .par_iter()
            .map(|img| {
                interrupted.check_interrupted()?;
                let plate = &plates
                    .iter()
                    .find(|(v, _)| *v == img.view)
                    .expect("plate per view")
                    .1;
                let r = process(img, plate, p, &scene.path, &scene.test_views, &out_dir)
                    .map_err(StageError::failed);
                progress.inc(1);
                r
            })
            .collect();
        let mut rows = Vec::with_capacity(results.len());
        let mut ious = Vec::new();
        for r in results {
            let (row, iou) = r?;
            if let Some(iou) = iou {
                ious.push(iou);
                ctx.metric(MetricRow {
                    epoch: None,
                    view: Some(row.view),
                    frame: Some(row.frame),
                    metric: "mask_iou".into(),
                    value: iou,
                });
            }
            rows.push(row);
        }
        if !ious.is_empty() {
            let mean = ious.iter().sum::<f64>() / ious.len() as f64;
            let min = ious.iter().cloned().fold(f64::INFINITY, f64::min);
            for (metric, value) in [("mask_iou_mean", mean), ("mask_iou_min", min)] {
                ctx.metric(MetricRow {
                    epoch: None,
                    view: None,
                    frame: None,
                    metric: metric.into(),
                    value,
                });
            }
            ctx.progress.log(&format!(
                "mask IoU against gt/masks: mean {mean:.4}, min {min:.4} over {} images",
                ious.len()
            ));
        }
        ctx.progress.log(&format!(
            "{} images from {} cameras ({} test), {}×{} px",
            rows.len(),
            views.len(),
            scene.test_views.len(),
            w0,
            h0
        ));
        table::write(&ctx.out_dir.join("frames.arrow"), &Frames { rows })
            .map_err(StageError::failed)?;
        Ok(())
    }
}

fn open(scene: &SceneSpec) -> Result<PacnerfScene, StageError> {
    if scene.dataset != DatasetKind::Pacnerf {
        return Err(StageError::failed(IngestError::Invalid(format!(
            "scene.dataset: ingest reads the `pacnerf` layout; `{:?}` is not supported yet",
            scene.dataset
        ))));
    }
    pacnerf::read_scene(&scene.path).map_err(|e| StageError::failed(IngestError::from(e)))
}

fn selected<'a>(ds: &'a PacnerfScene, p: &IngestParams) -> Vec<&'a PacnerfImage> {
    ds.images
        .iter()
        .filter(|i| match &p.frames {
            None => true,
            Some(f) => f.iter().any(|f| i32::from(*f) == i.frame),
        })
        .collect()
}

/// Where a camera's background plate is copied, relative to the entry.
fn plate_rel(view: u16) -> String {
    format!("plates/p_{view}.png")
}

fn gt_mask_path(root: &Path, img: &PacnerfImage) -> PathBuf {
    pacnerf::gt_mask_path(root, img.view, img.frame)
}

/// Matte, composite and write one image; returns its row and the IoU against ground truth.
fn process(
    img: &PacnerfImage,
    plate: &Rgb8,
    p: &IngestParams,
    root: &Path,
    test_views: &[u16],
    out_dir: &Path,
) -> Result<(FrameRow, Option<f64>), IngestError> {
    let rgb = image::read_rgb8(&img.path)?;
    let (w, h) = (rgb.width, rgb.height);
    if (w, h) != (plate.width, plate.height) {
        return Err(IngestError::Invalid(format!(
            "{}: image is {w}×{h}, but the plate of camera {} is {}×{}",
            img.path.display(),
            img.view,
            plate.width,
            plate.height
        )));
    }
    let [fx, fy, cx, cy] = img.intrinsics;
    if !(0.0..=f64::from(w)).contains(&cx) || !(0.0..=f64::from(h)).contains(&cy) {
        return Err(IngestError::Invalid(format!(
            "{}: principal point ({cx}, {cy}) lies outside the {w}×{h} image; are the intrinsics for another resolution?",
            img.path.display()
        )));
    }
    let gt_path = gt_mask_path(root, img);
    let gt = if gt_path.exists() {
        let (gw, gh, g) = image::read_gray8(&gt_path)?;
        if (gw, gh) != (w, h) {
            return Err(IngestError::Invalid(format!(
                "{}: mask is {gw}×{gh}, image is {w}×{h}",
                gt_path.display()
            )));
        }
        Some(
            g.into_iter()
                .map(|v| if v >= 128 { 255 } else { 0 })
                .collect::<Vec<u8>>(),
        )
    } else {
        None
    };
    let mask: Vec<u8> = match p.matte {
        MatteMode::None => vec![255; (w * h) as usize],
        MatteMode::Gt => gt.clone().ok_or_else(|| {
            IngestError::Invalid(format!(
                "stages.ingest.matte is `gt` but {} does not exist",
                gt_path.display()
            ))
        })?,
        MatteMode::Plate => {
            fn view(
                d: &[u8],
                w: u32,
                h: u32,
            ) -> Result<pipe_matte::RgbImageView<'_>, pipe_matte::MatteError> {
                pipe_matte::RgbImageView::new(d, w as usize, h as usize)
            }
            let to_err = |source| IngestError::Matte {
                path: img.path.clone(),
                source,
            };
            let m = pipe_matte::matte(
                &view(&rgb.data, w, h).map_err(to_err)?,
                &view(&plate.data, w, h).map_err(to_err)?,
                &pipe_matte::MatteParams::default(),
            )
            .map_err(to_err)?;
            m.into_data()
        }
    };
    let iou = gt.as_ref().map(|g| iou(&mask, g));
    let bg = p.background.map(|c| c * 255.0);
    let composite: Vec<u8> = rgb
        .data
        .chunks_exact(3)
        .zip(&mask)
        .flat_map(|(px, m)| {
            let a = f32::from(*m) / 255.0;
            [0, 1, 2].map(|c| (f32::from(px[c]) * a + bg[c] * (1.0 - a)).round() as u8)
        })
        .collect();
    let image_rel = format!("images/r_{}_{}.png", img.view, img.frame);
    let mask_rel = format!("masks/m_{}_{}.png", img.view, img.frame);
    image::write_rgb8(
        &out_dir.join(&image_rel),
        &Rgb8 {
            width: w,
            height: h,
            data: composite,
        },
    )?;
    image::write_gray8(&out_dir.join(&mask_rel), w, h, &mask)?;
    let row = FrameRow {
        view: img.view,
        frame: u16::try_from(img.frame).expect("plates are not frames"),
        time_s: img.time_s,
        world_from_camera: img.world_from_camera,
        fx,
        fy,
        cx,
        cy,
        width: w,
        height: h,
        image: image_rel,
        mask: mask_rel,
        plate: Some(plate_rel(img.view)),
        role: if test_views.contains(&img.view) {
            Role::Test
        } else {
            Role::Train
        },
    };
    Ok((row, iou))
}

/// Intersection over union of two 0/255 masks (1 when both are empty).
pub fn iou(a: &[u8], b: &[u8]) -> f64 {
    let (mut inter, mut union) = (0u64, 0u64);
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (*x >= 128, *y >= 128);
        inter += u64::from(x && y);
        union += u64::from(x || y);
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}
