//! Integer box filters: every output pixel is the rounded mean of an `f`×`f` block.

/// Box-filters an RGB image by `f` (the remainder rows and columns are dropped).
pub fn box_filter_rgb(img: &image::RgbImage, f: u32) -> image::RgbImage {
    let (w, h) = (img.width() / f, img.height() / f);
    image::RgbImage::from_fn(w, h, |x, y| {
        let mut acc = [0u32; 3];
        for dy in 0..f {
            for dx in 0..f {
                let p = img.get_pixel(x * f + dx, y * f + dy);
                for c in 0..3 {
                    acc[c] += u32::from(p[c]);
                }
            }
        }
        let n = f * f;
        image::Rgb(acc.map(|a| ((a + n / 2) / n) as u8))
    })
}

/// Box-filters a grey image (e.g. an alpha mask) by `f`.
pub fn box_filter_luma(img: &image::GrayImage, f: u32) -> image::GrayImage {
    let (w, h) = (img.width() / f, img.height() / f);
    image::GrayImage::from_fn(w, h, |x, y| {
        let mut acc = 0u32;
        for dy in 0..f {
            for dx in 0..f {
                acc += u32::from(img.get_pixel(x * f + dx, y * f + dy)[0]);
            }
        }
        let n = f * f;
        image::Luma([((acc + n / 2) / n) as u8])
    })
}
