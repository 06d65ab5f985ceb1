//! `pipe render`: render any standard 3DGS PLY (ours or another tool's) from a camera of a
//! PAC-NeRF camera JSON, for previews and tests. Only the rendered camera's entries are read:
//! plates play no part in rendering over a given background.

use std::path::{Path, PathBuf};

use crate::io::image::Rgb8;
use crate::io::{pacnerf, ply};
use crate::scene::camera::Camera;
use crate::scene::splat;

/// What to render.
#[derive(Debug, Clone, PartialEq)]
pub struct PreviewRequest {
    /// A 3DGS PLY file.
    pub ply: PathBuf,
    /// `all_data.json` (PAC-NeRF layout). Only the entries of `view` are used: no background
    /// plate is needed.
    pub cameras: PathBuf,
    /// Camera index.
    pub view: u16,
    /// Frame whose entry gives the camera (cameras are static in PAC-NeRF captures).
    pub frame: i32,
    /// Output size.
    pub size: OutputSize,
    /// Background RGB in [0, 1].
    pub background: [f32; 3],
}

/// The size of a rendered preview, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OutputSize {
    /// The camera's image size, read from its image file.
    #[default]
    Native,
    /// `(width, height)` with the intrinsics scaled from the image size by `width / w₀` and
    /// `height / h₀` (the same view at another resolution; needs the image file).
    Rescaled(u32, u32),
    /// `(width, height)` with the intrinsics as the camera file gives them (the image size the
    /// intrinsics belong to, when no image file says it).
    Exact(u32, u32),
}

/// A rendered preview.
#[derive(Debug, Clone)]
pub struct Preview {
    /// RGB image.
    pub image: Rgb8,
    /// Expected depth per pixel, metres (0 where nothing was blended).
    pub depth: Vec<f32>,
    /// Number of Gaussians read.
    pub gaussians: usize,
}

/// Why a preview could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PreviewError {
    /// Reading the PLY failed.
    #[error(transparent)]
    Ply(#[from] ply::PlyError),
    /// Reading the cameras failed.
    #[error(transparent)]
    Cameras(#[from] pacnerf::PacnerfError),
    /// The request does not fit the data.
    #[error("{0}")]
    Invalid(String),
    /// The rasterizer refused its input.
    #[error("rendering failed: {0}")]
    Render(#[from] pipe_render::RenderError),
}

/// The image size of camera `view`: that of the first of its entries' image files that
/// exists (the entry of `frame` first); `Ok(None)` when none exists.
fn native_size(
    scene: &pacnerf::PacnerfScene,
    view: u16,
    entry: &pacnerf::PacnerfImage,
) -> Result<Option<(u32, u32)>, PreviewError> {
    let same_camera = scene
        .images
        .iter()
        .chain(scene.plates.values())
        .filter(|i| i.view == view);
    for img in std::iter::once(entry).chain(same_camera) {
        if img.path.is_file() {
            return image::image_dimensions(&img.path).map(Some).map_err(|e| {
                PreviewError::Invalid(format!(
                    "{}: cannot read the image size of camera {view}: {e}",
                    img.path.display()
                ))
            });
        }
    }
    Ok(None)
}

/// The scene camera of `view` / `frame` in a PAC-NeRF JSON, at the requested size. Only the
/// entries of `view` are used; background plates are not required.
pub fn camera(
    path: &Path,
    view: u16,
    frame: i32,
    size: OutputSize,
) -> Result<Camera, PreviewError> {
    let scene = pacnerf::read_cameras(path)?;
    let all = || scene.images.iter().chain(scene.plates.values());
    let entry = all()
        .find(|i| i.view == view && i.frame == frame)
        .or_else(|| all().find(|i| i.view == view))
        .ok_or_else(|| {
            let views: std::collections::BTreeSet<u16> = all().map(|i| i.view).collect();
            PreviewError::Invalid(format!(
                "{}: there is no camera {view} (cameras: {})",
                path.display(),
                views
                    .iter()
                    .map(u16::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            ))
        })?;
    let unknown = |what: &str| {
        PreviewError::Invalid(format!(
            "{}: the image size of camera {view} is unknown ({} does not exist); {what}",
            path.display(),
            entry.path.display()
        ))
    };
    let [fx, fy, cx, cy] = entry.intrinsics;
    let ((w, h), (sx, sy)) = match size {
        OutputSize::Native => {
            let wh = native_size(&scene, view, entry)?
                .ok_or_else(|| unknown("give the size its intrinsics belong to with --size WxH"))?;
            (wh, (1.0, 1.0))
        }
        OutputSize::Rescaled(w, h) => {
            let (w0, h0) = native_size(&scene, view, entry)?.ok_or_else(|| {
                unknown("--width/--height rescale from that size; use --size WxH to set the size without rescaling the intrinsics")
            })?;
            (
                (w, h),
                (f64::from(w) / f64::from(w0), f64::from(h) / f64::from(h0)),
            )
        }
        OutputSize::Exact(w, h) => ((w, h), (1.0, 1.0)),
    };
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(PreviewError::Invalid(format!(
            "image size {w}×{h} is outside 1..=16384"
        )));
    }
    let row = crate::scene::frames::FrameRow {
        view,
        frame: 0,
        time_s: entry.time_s,
        world_from_camera: entry.world_from_camera,
        fx: fx * sx,
        fy: fy * sy,
        cx: cx * sx,
        cy: cy * sy,
        width: w,
        height: h,
        image: String::new(),
        mask: String::new(),
        plate: None,
        role: crate::scene::frames::Role::Test,
    };
    Ok(Camera::from_row(&row))
}

/// Render the request.
pub fn render(req: &PreviewRequest) -> Result<Preview, PreviewError> {
    let g = ply::read_gaussians(&req.ply)?;
    let cam = camera(&req.cameras, req.view, req.frame, req.size)?;
    if let Some(c) = req.background.iter().find(|c| !(0.0..=1.0).contains(*c)) {
        return Err(PreviewError::Invalid(format!(
            "--background: {c} is outside [0, 1]"
        )));
    }
    let rcam = splat::render_camera(&cam);
    let opts = pipe_render::RenderOptions {
        background: req.background,
        ..Default::default()
    };
    let out = pipe_render::render(&splat::render_gaussians(&g), &rcam, &opts)?;
    Ok(Preview {
        image: Rgb8 {
            width: cam.width,
            height: cam.height,
            data: splat::to_rgb8(&out.image),
        },
        depth: out.depth,
        gaussians: g.len(),
    })
}
