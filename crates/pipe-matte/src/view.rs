//! Borrowed RGB8 image views with validated dimensions.

use crate::error::MatteError;

/// A borrowed, row-major, tightly packed RGB8 image (`3 * width * height` bytes).
///
/// Construct it with [`RgbImageView::new`], which checks the buffer length, so every
/// view that exists is internally consistent.
#[derive(Debug, Clone, Copy)]
pub struct RgbImageView<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
}

impl<'a> RgbImageView<'a> {
    /// Wraps `data` as a `width` x `height` RGB8 image.
    ///
    /// # Errors
    /// [`MatteError::DimensionOverflow`] if `3 * width * height` overflows `usize`, and
    /// [`MatteError::BufferLength`] if `data.len()` differs from it.
    pub fn new(data: &'a [u8], width: usize, height: usize) -> Result<Self, MatteError> {
        let expected = pixel_count(width, height)?
            .checked_mul(3)
            .ok_or(MatteError::DimensionOverflow { width, height })?;
        if data.len() != expected {
            return Err(MatteError::BufferLength {
                width,
                height,
                channels: 3,
                expected,
                actual: data.len(),
            });
        }
        Ok(Self {
            data,
            width,
            height,
        })
    }

    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The raw RGB8 bytes, row-major.
    pub fn data(&self) -> &'a [u8] {
        self.data
    }
}

/// `width * height`, or [`MatteError::DimensionOverflow`].
pub(crate) fn pixel_count(width: usize, height: usize) -> Result<usize, MatteError> {
    width
        .checked_mul(height)
        .ok_or(MatteError::DimensionOverflow { width, height })
}
