//! PNG reading and writing with errors that name the file.

use std::path::{Path, PathBuf};

/// An 8-bit RGB image, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rgb8 {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width·height·3` bytes.
    pub data: Vec<u8>,
}

/// An image could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The file does not exist.
    #[error("{0}: image file not found")]
    NotFound(PathBuf),
    /// Unreadable or undecodable.
    #[error("{path}: cannot decode image: {message}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// Decoder message.
        message: String,
    },
    /// Could not be written.
    #[error("{path}: cannot write image: {message}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// Encoder message.
        message: String,
    },
}

/// Read a PNG as RGB8 (grey, alpha and 16-bit images are converted; alpha is dropped).
pub fn read_rgb8(path: &Path) -> Result<Rgb8, ImageError> {
    if !path.exists() {
        return Err(ImageError::NotFound(path.to_path_buf()));
    }
    let img = image::open(path).map_err(|e| ImageError::Decode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let rgb = img.into_rgb8();
    Ok(Rgb8 {
        width: rgb.width(),
        height: rgb.height(),
        data: rgb.into_raw(),
    })
}

/// Read an 8-bit grey PNG (colour images are converted to luma).
pub fn read_gray8(path: &Path) -> Result<(u32, u32, Vec<u8>), ImageError> {
    if !path.exists() {
        return Err(ImageError::NotFound(path.to_path_buf()));
    }
    let img = image::open(path).map_err(|e| ImageError::Decode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let g = img.into_luma8();
    Ok((g.width(), g.height(), g.into_raw()))
}

fn encode_err(path: &Path) -> impl Fn(String) -> ImageError + '_ {
    move |message| ImageError::Encode {
        path: path.to_path_buf(),
        message,
    }
}

/// Write an RGB8 PNG atomically.
pub fn write_rgb8(path: &Path, img: &Rgb8) -> Result<(), ImageError> {
    write_png(
        path,
        img.width,
        img.height,
        &img.data,
        image::ExtendedColorType::Rgb8,
    )
}

/// Write an 8-bit grey PNG atomically.
pub fn write_gray8(path: &Path, width: u32, height: u32, data: &[u8]) -> Result<(), ImageError> {
    write_png(path, width, height, data, image::ExtendedColorType::L8)
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    data: &[u8],
    color: image::ExtendedColorType,
) -> Result<(), ImageError> {
    use image::ImageEncoder;
    let err = encode_err(path);
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(data, width, height, color)
        .map_err(|e| err(e.to_string()))?;
    crate::pipeline::cache::write_atomic(path, &bytes).map_err(|e| err(e.to_string()))
}

/// Ground truth | render | 4× absolute difference, side by side.
pub fn compare_strip(truth: &[u8], render: &[u8], w: usize, h: usize) -> Rgb8 {
    let mut data = vec![0u8; 3 * w * h * 3];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let i = (y * w + x) * 3 + c;
                let row = y * 3 * w * 3;
                data[row + x * 3 + c] = truth[i];
                data[row + (w + x) * 3 + c] = render[i];
                data[row + (2 * w + x) * 3 + c] = (4
                    * (i32::from(truth[i]) - i32::from(render[i])).unsigned_abs())
                .min(255) as u8;
            }
        }
    }
    Rgb8 {
        width: 3 * w as u32,
        height: h as u32,
        data,
    }
}
