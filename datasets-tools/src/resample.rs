//! Integer box filters (every output pixel the rounded mean of an `f`×`f` block, remainder rows
//! and columns dropped) on `image` buffers: the pipeline's area resampling
//! (`pipe::io::resample`, which `ingest.scale` uses too) at `size / f`.

use pipe::io::resample::area;

/// Box-filters an RGB image by `f`.
pub fn box_filter_rgb(img: &image::RgbImage, f: u32) -> image::RgbImage {
    let (w, h) = (img.width(), img.height());
    let (w2, h2) = (w / f, h / f);
    // Whole blocks only: crop the remainder, then average f×f blocks.
    let cropped = image::imageops::crop_imm(img, 0, 0, w2 * f, h2 * f).to_image();
    let data = area(cropped.as_raw(), w2 * f, h2 * f, 3, w2, h2);
    image::RgbImage::from_raw(w2, h2, data).expect("w2·h2·3 bytes")
}

/// Box-filters a grey image (e.g. an alpha mask) by `f`.
pub fn box_filter_luma(img: &image::GrayImage, f: u32) -> image::GrayImage {
    let (w, h) = (img.width(), img.height());
    let (w2, h2) = (w / f, h / f);
    let cropped = image::imageops::crop_imm(img, 0, 0, w2 * f, h2 * f).to_image();
    let data = area(cropped.as_raw(), w2 * f, h2 * f, 1, w2, h2);
    image::GrayImage::from_raw(w2, h2, data).expect("w2·h2 bytes")
}
