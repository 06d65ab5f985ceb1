//! Scoring against the ground-truth mask. The warm-up's own score compares the render with the
//! capture inside *our* matte (the plate outside it), so a part of the object the matte missed
//! in every view is missing from both render and target and costs nothing. When the scene ships
//! ground-truth masks (`gt/masks/m_<cam>_<frame>.png`), the render is also compared with the
//! capture inside the true mask: `m_gt·capture + (1 − m_gt)·backdrop`.

use crate::io::pacnerf::{self, PacnerfError};
use crate::io::{image, resample};
use crate::pipeline::spec::{DatasetKind, SceneSpec};
use crate::pipeline::stage::InputFile;

/// The capture and ground-truth mask of one image.
#[derive(Debug, Clone)]
pub(super) struct GtFiles {
    /// Camera.
    pub view: u16,
    /// Frame.
    pub frame: u16,
    /// The raw capture (`data/r_<cam>_<frame>.png`).
    pub capture: InputFile,
    /// Its ground-truth mask.
    pub mask: InputFile,
}

/// The images of `frames` that have a ground-truth mask, in a PAC-NeRF scene (none in other
/// layouts).
pub(super) fn files(frames: &[u16], scene: &SceneSpec) -> Result<Vec<GtFiles>, PacnerfError> {
    if scene.dataset != DatasetKind::Pacnerf {
        return Ok(Vec::new());
    }
    let ds = pacnerf::read_cameras(&scene.path.join("all_data.json"))?;
    Ok(ds
        .images
        .iter()
        .filter_map(|img| {
            let frame = u16::try_from(img.frame).ok()?;
            let mask = pacnerf::gt_mask_path(&scene.path, img.view, img.frame);
            (frames.contains(&frame) && mask.is_file()).then(|| GtFiles {
                view: img.view,
                frame,
                capture: InputFile {
                    logical_name: img.logical_name.clone(),
                    path: img.path.clone(),
                },
                mask: InputFile {
                    logical_name: format!("gt/masks/m_{}_{}.png", img.view, img.frame),
                    path: mask,
                },
            })
        })
        .collect())
}

/// The capture inside the ground-truth mask over `backdrop` (RGB in [0, 1], 3 values per
/// pixel of a `width × height` image): `m·capture + (1 − m)·backdrop` with `m` = mask ≥ 128.
pub(super) fn target(
    f: &GtFiles,
    width: u32,
    height: u32,
    backdrop: &[f32],
) -> Result<Vec<f32>, String> {
    let capture = image::read_rgb8(&f.capture.path).map_err(|e| e.to_string())?;
    let (mw, mh, mask) = image::read_gray8(&f.mask.path).map_err(|e| e.to_string())?;
    for (path, w, h) in [
        (&f.capture.path, capture.width, capture.height),
        (&f.mask.path, mw, mh),
    ] {
        if (w, h) != (capture.width, capture.height) || w < width || h < height {
            return Err(format!(
                "{}: is {w}×{h}, but camera {} frame {} is {width}×{height}",
                path.display(),
                f.view,
                f.frame
            ));
        }
    }
    // `ingest.scale` made the images smaller: resample as ingest did.
    let (w, h) = (capture.width, capture.height);
    let binary: Vec<u8> = mask
        .iter()
        .map(|v| if *v >= 128 { 255 } else { 0 })
        .collect();
    let mask = resample::mask(&binary, w, h, width, height);
    let capture = image::Rgb8 {
        width,
        height,
        data: resample::area(&capture.data, w, h, 3, width, height),
    };
    Ok(capture
        .data
        .chunks_exact(3)
        .zip(&mask)
        .zip(backdrop.chunks_exact(3))
        .flat_map(|((px, m), b)| {
            [0, 1, 2].map(|c| {
                if *m >= 128 {
                    f32::from(px[c]) / 255.0
                } else {
                    b[c]
                }
            })
        })
        .collect())
}
