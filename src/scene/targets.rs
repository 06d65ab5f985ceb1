//! The captured views a stage fits or scores, and the image loss against them.
//!
//! A view's target is the capture inside the object's mask and the camera's background plate
//! outside it (the plate equals the capture there except for the object's shadow, which the
//! Gaussians do not model). Renders are made over black and composited over the same plate,
//! `I = C + (1 − α)·plate`, so the object's anti-aliased edge, where the camera saw object and
//! floor mixed, is consistent between render and target. The loss is the 3DGS one,
//! `λ·L1 + (1 − λ)·D-SSIM` (paper eq. 7), plus a silhouette term `w·mean|α − mask|`.

use std::path::Path;

use crate::io::image;
use crate::scene::camera::Camera;
use crate::scene::frames::FrameRow;
use crate::scene::splat;

/// Why a target could not be loaded or scored.
#[derive(Debug, thiserror::Error)]
pub enum TargetError {
    /// Reading an image failed.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// A plate of another size than its image.
    #[error("{plate}: plate is {pw}×{ph}, image {image} is {iw}×{ih}")]
    PlateSize {
        /// The plate.
        plate: String,
        /// Its size.
        pw: u32,
        ph: u32,
        /// The image.
        image: String,
        /// Its size.
        iw: u32,
        ih: u32,
    },
    /// The loss refused its input.
    #[error("loss: {0}")]
    Loss(#[from] pipe_loss::LossError),
}

/// A training or test image in memory.
#[derive(Debug, Clone)]
pub struct Target {
    /// Its `frames.arrow` row.
    pub row: FrameRow,
    /// The rasterizer's camera.
    pub camera: pipe_render::Camera<f32>,
    /// The object composited over the ingest background colour, RGB in [0, 1].
    pub pixels: Vec<f32>,
    /// Object mask in [0, 1].
    pub mask: Vec<f32>,
    /// The camera's background plate, RGB in [0, 1], when the capture has one.
    pub plate: Option<Vec<f32>>,
}

impl Target {
    /// Width and height (pixels).
    pub fn size(&self) -> (usize, usize) {
        (self.row.width as usize, self.row.height as usize)
    }

    /// The capture with everything outside the object mask replaced by `backdrop`
    /// (3 values per pixel): `m·image + (1 − m)·backdrop`.
    pub fn over(&self, backdrop: &[f32]) -> Vec<f32> {
        self.pixels
            .chunks_exact(3)
            .zip(&self.mask)
            .zip(backdrop.chunks_exact(3))
            .flat_map(|((px, m), b)| [0, 1, 2].map(|c| m * px[c] + (1.0 - m) * b[c]))
            .collect()
    }

    /// The plate, or the uniform colour `solid` where the capture has none.
    pub fn backdrop(&self, solid: [f32; 3]) -> std::borrow::Cow<'_, [f32]> {
        match &self.plate {
            Some(p) => p.as_slice().into(),
            None => {
                let (w, h) = self.size();
                solid.repeat(w * h).into()
            }
        }
    }
}

fn to_unit(v: &[u8]) -> Vec<f32> {
    v.iter().map(|v| f32::from(*v) / 255.0).collect()
}

/// The targets of `rows`, whose image, mask and plate paths are relative to `dir` (an
/// `ingest` entry).
pub fn load(dir: &Path, rows: &[&FrameRow]) -> Result<Vec<Target>, TargetError> {
    rows.iter()
        .map(|r| {
            let img = image::read_rgb8(&dir.join(&r.image))?;
            let (_, _, mask) = image::read_gray8(&dir.join(&r.mask))?;
            let plate = match &r.plate {
                Some(rel) => {
                    let pl = image::read_rgb8(&dir.join(rel))?;
                    if (pl.width, pl.height) != (img.width, img.height) {
                        return Err(TargetError::PlateSize {
                            plate: dir.join(rel).display().to_string(),
                            pw: pl.width,
                            ph: pl.height,
                            image: r.image.clone(),
                            iw: img.width,
                            ih: img.height,
                        });
                    }
                    Some(to_unit(&pl.data))
                }
                None => None,
            };
            Ok(Target {
                row: (*r).clone(),
                camera: splat::render_camera(&Camera::from_row(r)),
                pixels: to_unit(&img.data),
                mask: to_unit(&mask),
                plate,
            })
        })
        .collect()
}

/// `λ` of `λ·L1 + (1 − λ)·D-SSIM`: every fitting stage's default (3DGS weighs D-SSIM 0.2;
/// these fits weigh it more, 0.9).
pub const DEFAULT_LAMBDA: f64 = 0.1;

/// The rasterizer's options for a render composited afterwards: over black.
pub fn over_black() -> pipe_render::RenderOptions<f32> {
    pipe_render::RenderOptions {
        background: [0.0; 3],
        ..Default::default()
    }
}

/// The rendered object (rendered over black) composited over a per-pixel backdrop:
/// `I = C + (1 − α)·B`.
pub fn composite(out: &pipe_render::Rendered<f32>, backdrop: &[f32]) -> Vec<f32> {
    out.image
        .iter()
        .zip(&out.alpha)
        .zip(backdrop.chunks_exact(3))
        .flat_map(|((c, a), b)| [0, 1, 2].map(|k| c[k] + (1.0 - a) * b[k]))
        .collect()
}

/// ∂L/∂α contributed by the backdrop term of [`composite`]: `−Σ_c ∂L/∂I_c · B_c`.
pub fn backdrop_alpha_grad(d_image: &[[f32; 3]], backdrop: &[f32]) -> impl Iterator<Item = f32> {
    d_image
        .iter()
        .zip(backdrop.chunks_exact(3))
        .map(|(d, b)| -(d[0] * b[0] + d[1] * b[1] + d[2] * b[2]))
}

/// The loss of one render against its target, with what the rasterizer's backward needs.
#[derive(Debug, Clone)]
pub struct ViewLoss {
    /// `λ·L1 + (1 − λ)·D-SSIM + w·mean|α − mask|`.
    pub loss: f64,
    /// PSNR (dB) of the composite against the target.
    pub psnr: f64,
    /// `∂L/∂C` per pixel (the render over black).
    pub d_image: Vec<[f32; 3]>,
    /// `∂L/∂α` per pixel.
    pub d_alpha: Vec<f32>,
}

/// The loss of `out` (rendered over black) composited over `backdrop` against `target`
/// (its capture over the same backdrop): `λ·L1 + (1 − λ)·D-SSIM` plus the silhouette term
/// `alpha_weight·mean|α − mask|` (gradient `w·sign(α − mask)/n`).
pub fn view_loss(
    out: &pipe_render::Rendered<f32>,
    target: &Target,
    backdrop: &[f32],
    lambda: f64,
    alpha_weight: f64,
) -> Result<ViewLoss, TargetError> {
    let (w, h) = target.size();
    let composited = composite(out, backdrop);
    let truth = target.over(backdrop);
    let rendered = pipe_loss::Image::new("render", &composited, w, h)?;
    let gt = pipe_loss::Image::new("target", &truth, w, h)?;
    let (mut loss, d_flat) = pipe_loss::l1_dssim(rendered, gt, lambda)?;
    let psnr = pipe_loss::psnr(rendered, gt)?;
    let (d_image, _) = d_flat.as_chunks::<3>();
    let mut d_alpha: Vec<f32> = backdrop_alpha_grad(d_image, backdrop).collect();
    if alpha_weight > 0.0 {
        let n = out.alpha.len() as f64;
        let wgt = (alpha_weight / n) as f32;
        loss += alpha_weight
            * out
                .alpha
                .iter()
                .zip(&target.mask)
                .map(|(a, m)| f64::from((a - m).abs()))
                .sum::<f64>()
            / n;
        for ((d, a), m) in d_alpha.iter_mut().zip(&out.alpha).zip(&target.mask) {
            *d += wgt * (a - m).signum();
        }
    }
    Ok(ViewLoss {
        loss,
        psnr,
        d_image: d_image.to_vec(),
        d_alpha,
    })
}
