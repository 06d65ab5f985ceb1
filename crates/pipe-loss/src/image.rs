//! A borrowed RGB image: `[H][W][3]` f32 values, row-major.

use crate::error::LossError;

/// A validated view of an `height × width × 3` f32 image (row-major, channels last).
#[derive(Debug, Clone, Copy)]
pub struct Image<'a> {
    data: &'a [f32],
    width: usize,
    height: usize,
}

impl<'a> Image<'a> {
    /// Wraps `data` (`height·width·3` values). `field` names the buffer in errors.
    pub fn new(
        field: &'static str,
        data: &'a [f32],
        width: usize,
        height: usize,
    ) -> Result<Self, LossError> {
        if width == 0 || height == 0 {
            return Err(LossError::ImageSize { width, height });
        }
        let expected = width * height * 3;
        if data.len() != expected {
            return Err(LossError::Length {
                field,
                expected,
                got: data.len(),
                height,
                width,
            });
        }
        Ok(Self {
            data,
            width,
            height,
        })
    }

    /// Wraps pixels given as RGB triples (e.g. a rasterizer's output).
    pub fn from_rgb(
        field: &'static str,
        data: &'a [[f32; 3]],
        width: usize,
        height: usize,
    ) -> Result<Self, LossError> {
        Self::new(field, data.as_flattened(), width, height)
    }

    /// The values, `[H][W][3]` row-major.
    pub fn data(&self) -> &'a [f32] {
        self.data
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Channel `c` as an f64 plane `[H][W]`.
    pub(crate) fn plane(&self, c: usize) -> Vec<f64> {
        self.data
            .iter()
            .skip(c)
            .step_by(3)
            .map(|&v| v as f64)
            .collect()
    }
}

/// Checks that two images have the same size.
pub(crate) fn same_size(a: &Image<'_>, b: &Image<'_>) -> Result<(), LossError> {
    if a.width == b.width && a.height == b.height {
        Ok(())
    } else {
        Err(LossError::SizeMismatch {
            a_width: a.width,
            a_height: a.height,
            b_width: b.width,
            b_height: b.height,
        })
    }
}
