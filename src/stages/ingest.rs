//! Stage `ingest`: read a capture, matte the object out of every image against its camera's
//! background plate (or take the dataset's masks), and write masks, white-composited images
//! and `frames.arrow`.
//!
//! Layouts (`scene.dataset`): PAC-NeRF ([`pacnerf`]) and PhysDreamer ([`physdreamer`]), both
//! read into one [`Capture`] that the rest of the stage works on. A PhysDreamer scene has no
//! background plates (its trained Gaussians hold the background themselves): its masks are the
//! dataset's (`matte: gt`) or the whole image (`none`), its frames have no plate, and the
//! stages that composite over a plate use a uniform colour instead (the edit's `background`;
//! `warmup` asks for `background: white | random`). It also
//! carries trained Gaussians: they are written to `gaussians.arrow` with `simulated` true
//! exactly for the moving part ([`crate::scene::parts`]), which `init {source: dataset}`
//! takes as the canonical Gaussians.
//!
//! All cameras of a frame are matted together (`pipe_matte::matte_frame`): a shadow lies on the
//! ground and darkens it for every camera, and the object is where the cameras agree in 3D.
//! Each mask's agreement with the other cameras (`mask_agreement`: IoU with the reprojection of
//! the other cameras' visual hull) and its consistency (`mask_consistency`: that agreement
//! against what consistent masks reach in the same camera layout, `pipe_matte::consistency`)
//! are recorded in `metrics.arrow`, and masks whose consistency is below
//! [`CONSISTENCY_WARNING`] are named in a warning, ground truth or not. When the dataset ships ground-truth masks
//! (`gt/masks/m_<cam>_<frame>.png`), the mask IoU of every image is recorded too (`mask_iou`).

pub mod trained;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::io::capture::{Capture, CaptureImage, DatasetFile};
use crate::io::image::{self, Rgb8};
use crate::io::physdreamer::{self, PhysdreamerScene};
use crate::io::{pacnerf, ply, resample};
use crate::pipeline::spec::{DatasetKind, Preset, SceneSpec};
use crate::pipeline::stage::{
    InputFile, MetricRow, ParamError, StageContext, StageError, TypedStage,
};
use crate::scene::camera::Camera;
use crate::scene::frames::{FrameRow, Frames, Role};
use crate::scene::table::{self, Table};

/// How the object mask of each image is obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum MatteMode {
    /// Background subtraction against `r_<cam>_-1.png`, robust to the object's shadow.
    Plate,
    /// Use the dataset's own masks: PAC-NeRF's ground truth (`gt/masks/`, for ablations),
    /// PhysDreamer's `masks/<view>/<frame>.png`.
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
    /// Image scale in (0, 1]: every image, plate and ground-truth mask is area-resampled to
    /// `round(scale·size)` and the intrinsics follow (`fx, cx` by the width's ratio, `fy, cy`
    /// by the height's), so every later stage works on the smaller images (about `scale²` of
    /// the pixels and of the rendering time).
    #[serde(default = "default_scale")]
    pub scale: f64,
    /// Longest image side (pixels) after `scale`: larger captures are resampled further
    /// down to it, so a preset's cost does not grow with the camera's resolution. The preset
    /// sets it (`draft` 200, `standard` 400, `paper` none: full size); `null` never resamples.
    #[serde(default)]
    pub max_size: Option<u32>,
}

impl IngestParams {
    /// The scale applied to a `w`×`h` capture: `scale`, made smaller when the longest side
    /// would still exceed `max_size`.
    pub fn effective_scale(&self, w: u32, h: u32) -> f64 {
        let longest = f64::from(w.max(h)) * self.scale;
        match self.max_size {
            Some(m) if longest > f64::from(m) => self.scale * f64::from(m) / longest,
            _ => self.scale,
        }
    }
}

fn default_scale() -> f64 {
    1.0
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
    /// The PhysDreamer layout is invalid.
    #[error(transparent)]
    Physdreamer(#[from] physdreamer::PhysdreamerError),
    /// A PLY of the dataset is invalid.
    #[error(transparent)]
    Ply(#[from] ply::PlyError),
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
    const VERSION: u32 = 8;
    const DESCRIPTION: &'static str = "Read a PAC-NeRF or PhysDreamer capture, matte the object against each camera's background plate (or take the dataset's masks), write masks, composited images, the plates and frames.arrow (and a PhysDreamer scene's trained Gaussians, the moving part simulated)";

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![(Frames::NAME, Frames::VERSION)]
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            Preset::Draft => json!({"max_size": 200}),
            Preset::Standard => json!({"max_size": 400}),
            Preset::Paper => json!({"max_size": null}),
        }
    }

    fn validate(&self, p: &IngestParams) -> Result<(), ParamError> {
        if let Some(c) = p.background.iter().position(|c| !(0.0..=1.0).contains(c)) {
            return Err(ParamError {
                path: format!("background[{c}]"),
                message: format!("must be in [0, 1], found {}", p.background[c]),
            });
        }
        if !(p.scale > 0.0 && p.scale <= 1.0) {
            return Err(ParamError {
                path: "scale".into(),
                message: format!(
                    "must be in (0, 1] (images are only ever made smaller), found {}",
                    p.scale
                ),
            });
        }
        if p.max_size.is_some_and(|m| m < 16) {
            return Err(ParamError {
                path: "max_size".into(),
                message: format!(
                    "must be at least 16 pixels (or null: full size), found {}",
                    p.max_size.unwrap_or(0)
                ),
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
        let (ds, trained) = open(scene)?;
        let input = |f: &DatasetFile| InputFile {
            logical_name: f.logical_name.clone(),
            path: f.path.clone(),
        };
        let mut out: Vec<InputFile> = ds.camera_files.iter().map(input).collect();
        let images = selected(&ds, p);
        out.extend(
            images
                .iter()
                .map(|i| &i.file)
                .chain(ds.plates.values())
                .map(input),
        );
        out.extend(
            images
                .iter()
                .filter(|i| i.mask.path.exists())
                .map(|i| input(&i.mask)),
        );
        if let Some(t) = &trained {
            out.extend(
                std::iter::once(&t.point_cloud)
                    .chain(&t.clean_object)
                    .chain(&t.moving_part)
                    .map(input),
            );
        }
        // The frames of a video share its file: hash it once.
        let mut seen = BTreeSet::new();
        out.retain(|f| seen.insert(f.logical_name.clone()));
        Ok(out)
    }

    fn run(&self, p: &IngestParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let out = run_ingest(p, ctx);
        // Videos are decoded once per ingest (their frames are read camera by camera).
        crate::io::video::forget_decoded();
        out
    }
}

/// The ingest: images matted (or masked) and resampled, frames table, and a PhysDreamer
/// scene's trained Gaussians.
fn run_ingest(p: &IngestParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
    let scene = ctx.scene;
    let (ds, trained) = open(scene)?;
    let views: BTreeSet<u16> = ds.images.iter().map(|i| i.view).collect();
    if let Some(v) = scene.test_views.iter().find(|v| !views.contains(v)) {
        return Err(StageError::failed(IngestError::Invalid(format!(
            "scene.test_views: camera {v} is not in {} (cameras: {})",
            ds.camera_files[0].path.display(),
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

    if p.matte == MatteMode::Plate && ds.plates.is_empty() {
        return Err(StageError::failed(IngestError::Invalid(format!(
            "stages.ingest.matte: `plate` mattes against background plates, and the {} \
             layout of {} has none: use `gt` (the dataset's masks) or `none` (the whole \
             image is the object)",
            scene.dataset.name(),
            scene.path.display()
        ))));
    }
    // Plates first: they fix each camera's image size (else the first image does).
    let plates: Vec<(u16, Rgb8)> = ds
        .plates
        .iter()
        .filter(|(v, _)| images.iter().any(|i| i.view == **v))
        .map(|(v, img)| image::read_rgb8(&img.path).map(|r| (*v, r)))
        .collect::<Result<_, _>>()
        .map_err(|e| StageError::failed(IngestError::from(e)))?;
    let full = match plates.first() {
        Some((_, pl)) => (pl.width, pl.height),
        None => images[0]
            .read_rgb8()
            .map(|r| (r.width, r.height))
            .map_err(|e| StageError::failed(IngestError::from(e)))?,
    };
    let (w0, h0) = full;
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
    }
    let scale = p.effective_scale(w0, h0);
    let (w2, h2) = resample::scaled_size(w0, h0, scale);
    let plates: Vec<(u16, Rgb8)> = plates
        .into_iter()
        .map(|(v, pl)| {
            let data = resample::area(&pl.data, w0, h0, 3, w2, h2);
            let small = Rgb8 {
                width: w2,
                height: h2,
                data,
            };
            image::write_rgb8(&ctx.out_dir.join(plate_rel(v)), &small)
                .map(|()| (v, small))
                .map_err(|e| StageError::failed(IngestError::from(e)))
        })
        .collect::<Result<_, _>>()?;

    ctx.progress.start("matte", images.len() as u64);
    let out_dir = ctx.out_dir.to_path_buf();
    let mut by_frame: BTreeMap<u16, Vec<&CaptureImage>> = BTreeMap::new();
    for img in &images {
        by_frame.entry(img.frame).or_default().push(img);
    }
    let mut rows = Vec::with_capacity(images.len());
    let mut ious = Vec::new();
    let mut agreements = Vec::new();
    let mut consistencies = Vec::new();
    let mut warnings = Vec::new();
    // Frames in which at least half of the cameras' masks are named.
    let mut torn_frames = Vec::new();
    for frame_images in by_frame.values() {
        ctx.check_interrupted()?;
        let source = match plates.is_empty() {
            true => SizeSource::Image(&images[0].file.path),
            false => SizeSource::Plates,
        };
        let done = ingest_frame(
            frame_images,
            &plates,
            ((full, source), (w2, h2)),
            p,
            scene,
            &out_dir,
        )
        .map_err(StageError::failed)?;
        ctx.progress.inc(frame_images.len() as u64);
        let (cameras, this_frame) = (done.len(), done.first().map(|d| d.row.frame));
        // Masks of this frame named in the warning.
        let mut named = 0;
        for d in done {
            let mut flagged = false;
            let (view, frame) = (Some(d.row.view), Some(d.row.frame));
            if let Some(iou) = d.iou {
                ious.push(iou);
                ctx.metric(metric(view, frame, "mask_iou", iou));
            }
            if let Some((a, c)) = d.agreement {
                agreements.push(a);
                consistencies.push(c);
                ctx.metric(metric(view, frame, "mask_agreement", a));
                ctx.metric(metric(view, frame, "mask_consistency", c));
                if c < CONSISTENCY_WARNING {
                    warnings.push(format!(
                        "camera {} frame {}: consistency {c:.2} (agreement {a:.2})",
                        d.row.view, d.row.frame
                    ));
                    flagged = true;
                }
            }
            if d.empty {
                warnings.push(format!(
                    "camera {} frame {}: the mask is empty",
                    d.row.view, d.row.frame
                ));
                flagged = true;
            }
            named += usize::from(flagged);
            rows.push(d.row);
        }
        if let Some(frame) = this_frame
            && cameras >= 2
            && 2 * named >= cameras
        {
            torn_frames.push(frame.to_string());
        }
    }
    rows.sort_by_key(|r| (r.view, r.frame));
    for (name, values) in [
        ("mask_iou", &ious),
        ("mask_agreement", &agreements),
        ("mask_consistency", &consistencies),
    ] {
        if values.is_empty() {
            continue;
        }
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        let min = values.iter().cloned().fold(f64::INFINITY, f64::min);
        ctx.metric(metric(None, None, &format!("{name}_mean"), mean));
        ctx.metric(metric(None, None, &format!("{name}_min"), min));
    }
    if !ious.is_empty() {
        let mean = ious.iter().sum::<f64>() / ious.len() as f64;
        let min = ious.iter().cloned().fold(f64::INFINITY, f64::min);
        ctx.progress.log(&format!(
            "mask IoU against {}: mean {mean:.4}, min {min:.4} over {} images",
            match scene.dataset {
                DatasetKind::Pacnerf => "gt/masks",
                DatasetKind::Physdreamer => "masks/",
            },
            ious.len()
        ));
    }
    if !warnings.is_empty() {
        ctx.progress.warn(&format!(
            "{} of {} masks disagree with the other cameras (consistency below {CONSISTENCY_WARNING}: the IoU of the mask with the other cameras' visual hull, against what consistent masks reach with these cameras) or are empty; check these images and masks/: {}",
            warnings.len(),
            rows.len(),
            warnings.join("; ")
        ));
    }
    if !torn_frames.is_empty() {
        ctx.progress.warn(&format!(
            "frames {}: at least half of the cameras' masks disagree; masks torn alike in every camera are what an object coloured like the floor, or like its own shadow, gives the matte (README, the multi-view matte); masks made elsewhere can be given as gt/masks/m_<cam>_<frame>.png with `ingest: {{matte: gt}}`",
            torn_frames.join(", ")
        ));
    }
    let resized = if (w2, h2) == full {
        String::new()
    } else {
        format!(" (scale {scale:.4}: from {w0}×{h0})")
    };
    ctx.progress.log(&format!(
        "{} images from {} cameras ({} test), {w2}×{h2} px{resized}",
        rows.len(),
        views.len(),
        scene.test_views.len(),
    ));
    table::write(&ctx.out_dir.join("frames.arrow"), &Frames { rows })
        .map_err(StageError::failed)?;
    if let Some(t) = &trained {
        if !t.skipped.is_empty() {
            ctx.progress.warn(&format!(
                "{}: {} camera(s) of {} have no video (videos/<name>/ or videos/<name>.mp4) and are skipped: {}",
                scene.path.display(),
                t.skipped.len(),
                t.capture.camera_files[0].logical_name,
                t.skipped.join(", ")
            ));
        }
        if !t.fps_given {
            ctx.progress.log(&format!(
                "{} gives no `fps`: frames {:.4} s apart ({} frames/s assumed)",
                t.capture.camera_files[0].logical_name,
                1.0 / t.fps,
                t.fps
            ));
        }
        trained::write(t, ctx)?;
    }
    Ok(())
}

/// The scene's capture, and for a PhysDreamer scene its trained Gaussians' files.
fn open(scene: &SceneSpec) -> Result<(Capture, Option<PhysdreamerScene>), StageError> {
    let failed = |e: IngestError| StageError::failed(e);
    match scene.dataset {
        DatasetKind::Pacnerf => {
            let ds = pacnerf::read_scene(&scene.path).map_err(|e| failed(e.into()))?;
            Ok((
                pacnerf::capture(&ds, &scene.path.join("all_data.json")),
                None,
            ))
        }
        DatasetKind::Physdreamer => {
            let ds = physdreamer::read_scene(&scene.path).map_err(|e| failed(e.into()))?;
            Ok((ds.capture.clone(), Some(ds)))
        }
    }
}

fn selected<'a>(ds: &'a Capture, p: &IngestParams) -> Vec<&'a CaptureImage> {
    ds.images
        .iter()
        .filter(|i| match &p.frames {
            None => true,
            Some(f) => f.contains(&i.frame),
        })
        .collect()
}

/// Where a camera's background plate is copied, relative to the entry.
fn plate_rel(view: u16) -> String {
    format!("plates/p_{view}.png")
}

/// Masks whose consistency with the other cameras (`pipe_matte::consistency`) is below this
/// are reported: `MultiViewParams::consistency_threshold` (the sample scenes' masks, true or
/// matted, score 0.95 and more with 3, 4, 6 or all 11 of their cameras).
pub const CONSISTENCY_WARNING: f64 = 0.9;

fn metric(view: Option<u16>, frame: Option<u16>, name: &str, value: f64) -> MetricRow {
    MetricRow {
        epoch: None,
        view,
        frame,
        metric: name.into(),
        value,
    }
}

/// One image read and checked against its plate and camera.
struct Loaded<'a> {
    img: &'a CaptureImage,
    rgb: Rgb8,
    /// The ground-truth mask binarised to 0/255, when the scene has one.
    gt: Option<Vec<u8>>,
    camera: pipe_matte::Pinhole,
    /// `[fx, fy, cx, cy]` at the ingested size (pixels).
    intrinsics: [f64; 4],
}

/// What one image gave.
struct Ingested {
    row: FrameRow,
    iou: Option<f64>,
    /// Agreement and consistency with the other cameras.
    agreement: Option<(f64, f64)>,
    empty: bool,
}

/// What fixes the capture's image size: the plates, or (without plates) its first image.
#[derive(Debug, Clone, Copy)]
enum SizeSource<'a> {
    Plates,
    Image(&'a Path),
}

/// Read one image, check it against the capture's size `full` (and what set it), read the
/// dataset's mask of it if any, and resample both to the ingested size `small`.
fn load<'a>(
    img: &'a CaptureImage,
    full: ((u32, u32), SizeSource<'_>),
    small: (u32, u32),
) -> Result<Loaded<'a>, IngestError> {
    let rgb = img.read_rgb8()?;
    let (w, h) = (rgb.width, rgb.height);
    if (w, h) != full.0 {
        return Err(IngestError::Invalid(format!(
            "{}: image is {w}×{h}, but {} is {}×{}",
            img.describe(),
            match full.1 {
                SizeSource::Plates => format!("the plate of camera {}", img.view),
                SizeSource::Image(p) => p.display().to_string(),
            },
            full.0.0,
            full.0.1
        )));
    }
    let [fx, fy, cx, cy] = img.intrinsics;
    if !(0.0..=f64::from(w)).contains(&cx) || !(0.0..=f64::from(h)).contains(&cy) {
        return Err(IngestError::Invalid(format!(
            "{}: principal point ({cx}, {cy}) lies outside the {w}×{h} image; are the intrinsics for another resolution?",
            img.describe()
        )));
    }
    let (w2, h2) = small;
    let gt_path = &img.mask.path;
    let gt = if gt_path.exists() {
        let (gw, gh, g) = image::read_gray8(gt_path)?;
        if (gw, gh) != (w, h) {
            return Err(IngestError::Invalid(format!(
                "{}: mask is {gw}×{gh}, image is {w}×{h}",
                gt_path.display()
            )));
        }
        let binary: Vec<u8> = g
            .into_iter()
            .map(|v| if v >= 128 { 255 } else { 0 })
            .collect();
        Some(resample::mask(&binary, w, h, w2, h2))
    } else {
        None
    };
    let (sx, sy) = (f64::from(w2) / f64::from(w), f64::from(h2) / f64::from(h));
    let intrinsics = [fx * sx, fy * sy, cx * sx, cy * sy];
    let rgb = Rgb8 {
        width: w2,
        height: h2,
        data: resample::area(&rgb.data, w, h, 3, w2, h2),
    };
    let camera = Camera::new(&img.world_from_camera, intrinsics, w2, h2).pinhole();
    Ok(Loaded {
        img,
        rgb,
        gt,
        camera,
        intrinsics,
    })
}

/// One frame's masks (0/255 bytes, in the images' order) and their agreements and
/// consistencies, if computed.
type FrameMasks = (Vec<Vec<u8>>, Option<(Vec<f64>, Vec<f64>)>);

/// The masks of one frame's images: all cameras matted together against their plates
/// (`pipe_matte::matte_frame`), or the ground truth, or everything; with each mask's
/// agreement with the other cameras' (none for `matte: none`).
fn frame_masks(
    loaded: &[Loaded<'_>],
    plates: &[(u16, Rgb8)],
    mode: MatteMode,
) -> Result<FrameMasks, IngestError> {
    let size = |l: &Loaded<'_>| (l.rgb.width as usize, l.rgb.height as usize);
    let to_err = |l: &Loaded<'_>| {
        let path = l.img.file.path.clone();
        move |source| IngestError::Matte { path, source }
    };
    match mode {
        MatteMode::None => Ok((
            loaded
                .iter()
                .map(|l| vec![255; l.rgb.data.len() / 3])
                .collect(),
            None,
        )),
        MatteMode::Gt => {
            let mut masks = Vec::with_capacity(loaded.len());
            let mut wrapped = Vec::with_capacity(loaded.len());
            for l in loaded {
                let gt = l.gt.clone().ok_or_else(|| {
                    IngestError::Invalid(format!(
                        "stages.ingest.matte is `gt` but {} does not exist",
                        l.img.mask.path.display()
                    ))
                })?;
                let (w, h) = size(l);
                wrapped.push(pipe_matte::Mask::from_threshold(w, h, &gt, 128).map_err(to_err(l))?);
                masks.push(gt);
            }
            let cameras: Vec<_> = loaded.iter().map(|l| l.camera).collect();
            let scores = pipe_matte::agreement_and_consistency(
                &cameras,
                &wrapped,
                &pipe_matte::MultiViewParams::default(),
            );
            Ok((masks, Some(scores)))
        }
        MatteMode::Plate => {
            let views = loaded
                .iter()
                .map(|l| {
                    let (w, h) = size(l);
                    let plate = &plates
                        .iter()
                        .find(|(v, _)| *v == l.img.view)
                        .expect("plate per view")
                        .1;
                    Ok(pipe_matte::View {
                        camera: l.camera,
                        image: pipe_matte::RgbImageView::new(&l.rgb.data, w, h)
                            .map_err(to_err(l))?,
                        plate: pipe_matte::RgbImageView::new(&plate.data, w, h)
                            .map_err(to_err(l))?,
                    })
                })
                .collect::<Result<Vec<_>, IngestError>>()?;
            let matte = pipe_matte::matte_frame(&views, &pipe_matte::MultiViewParams::default())
                .map_err(to_err(&loaded[0]))?;
            Ok((
                matte
                    .masks
                    .into_iter()
                    .map(pipe_matte::Mask::into_data)
                    .collect(),
                Some((matte.agreement, matte.consistency)),
            ))
        }
    }
}

/// Matte, composite and write the images of one frame (all cameras); their rows, IoUs
/// against ground truth and agreements.
///
/// `sizes`: the capture's image size (and what set it) and the ingested one (pixels).
fn ingest_frame(
    images: &[&CaptureImage],
    plates: &[(u16, Rgb8)],
    sizes: (((u32, u32), SizeSource<'_>), (u32, u32)),
    p: &IngestParams,
    scene: &SceneSpec,
    out_dir: &Path,
) -> Result<Vec<Ingested>, IngestError> {
    let loaded: Vec<Loaded<'_>> = images
        .par_iter()
        .map(|img| load(img, sizes.0, sizes.1))
        .collect::<Result<_, _>>()?;
    let (masks, agreement) = frame_masks(&loaded, plates, p.matte)?;
    loaded
        .par_iter()
        .zip(&masks)
        .enumerate()
        .map(|(i, (l, mask))| {
            let plate = plates.iter().any(|(v, _)| *v == l.img.view);
            let row = write_outputs(l, mask, p, (&scene.test_views, plate), out_dir)?;
            Ok(Ingested {
                row,
                iou: l.gt.as_ref().map(|g| iou(mask, g)),
                agreement: agreement.as_ref().map(|(a, c)| (a[i], c[i])),
                empty: p.matte == MatteMode::Plate && mask.iter().all(|m| *m == 0),
            })
        })
        .collect()
}

/// Composite one image on the background and write it with its mask; its `frames` row.
///
/// `(test_views, plate)`: the held-out cameras, and whether this camera has a plate.
fn write_outputs(
    l: &Loaded<'_>,
    mask: &[u8],
    p: &IngestParams,
    (test_views, plate): (&[u16], bool),
    out_dir: &Path,
) -> Result<FrameRow, IngestError> {
    let (img, rgb) = (l.img, &l.rgb);
    let (w, h) = (rgb.width, rgb.height);
    let [fx, fy, cx, cy] = l.intrinsics;
    let bg = p.background.map(|c| c * 255.0);
    let composite: Vec<u8> = rgb
        .data
        .chunks_exact(3)
        .zip(mask)
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
    image::write_gray8(&out_dir.join(&mask_rel), w, h, mask)?;
    Ok(FrameRow {
        view: img.view,
        frame: img.frame,
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
        plate: plate.then(|| plate_rel(img.view)),
        role: if test_views.contains(&img.view) {
            Role::Test
        } else {
            Role::Train
        },
    })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The warning names the masks that `pipe_matte::consistency` ranks inconsistent: one
    /// threshold, not two that may drift apart.
    #[test]
    fn the_warning_threshold_is_the_matte_s() {
        assert_eq!(
            CONSISTENCY_WARNING,
            pipe_matte::MultiViewParams::default().consistency_threshold
        );
    }
}
