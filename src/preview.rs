//! `pipe render`: render any standard 3DGS PLY (ours or another tool's) from a camera of a
//! PAC-NeRF camera JSON, for previews and tests.

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
    /// `all_data.json` (PAC-NeRF layout).
    pub cameras: PathBuf,
    /// Camera index.
    pub view: u16,
    /// Frame whose entry gives the camera (cameras are static in PAC-NeRF captures).
    pub frame: i32,
    /// Output size; the intrinsics are scaled to it. Default: the image's own size.
    pub size: Option<(u32, u32)>,
    /// Background RGB in [0, 1].
    pub background: [f32; 3],
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

/// Image size of a camera entry: from its image file when present, else (2·cx, 2·cy).
fn native_size(img: &pacnerf::PacnerfImage) -> (u32, u32) {
    if let Ok((w, h)) = image::image_dimensions(&img.path) {
        return (w, h);
    }
    let [_, _, cx, cy] = img.intrinsics;
    (
        (2.0 * cx).round().max(1.0) as u32,
        (2.0 * cy).round().max(1.0) as u32,
    )
}

/// The scene camera of `view` / `frame` in a PAC-NeRF JSON, optionally resized.
pub fn camera(
    path: &Path,
    view: u16,
    frame: i32,
    size: Option<(u32, u32)>,
) -> Result<Camera, PreviewError> {
    let scene = pacnerf::read_cameras(path)?;
    let entry = scene
        .images
        .iter()
        .chain(scene.plates.values())
        .find(|i| i.view == view && i.frame == frame)
        .or_else(|| {
            scene
                .images
                .iter()
                .chain(scene.plates.values())
                .find(|i| i.view == view)
        })
        .ok_or_else(|| {
            let mut views: Vec<u16> = scene.images.iter().map(|i| i.view).collect();
            views.sort_unstable();
            views.dedup();
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
    let (w0, h0) = native_size(entry);
    let (w, h) = size.unwrap_or((w0, h0));
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(PreviewError::Invalid(format!(
            "image size {w}×{h} is outside 1..=16384"
        )));
    }
    let (sx, sy) = (f64::from(w) / f64::from(w0), f64::from(h) / f64::from(h0));
    let [fx, fy, cx, cy] = entry.intrinsics;
    let m = &entry.world_from_camera;
    let row = crate::scene::frames::FrameRow {
        view,
        frame: 0,
        time_s: entry.time_s,
        world_from_camera: *m,
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
