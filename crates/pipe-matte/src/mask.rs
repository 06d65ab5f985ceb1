//! Binary masks and the intersection-over-union metric.

use crate::error::MatteError;
use crate::view::pixel_count;

/// A binary mask: row-major, one byte per pixel, `0` = background, `255` = object.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mask {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl Mask {
    /// An all-background mask.
    ///
    /// # Errors
    /// [`MatteError::DimensionOverflow`] if `width * height` overflows.
    pub fn empty(width: usize, height: usize) -> Result<Self, MatteError> {
        Ok(Self {
            width,
            height,
            data: vec![0; pixel_count(width, height)?],
        })
    }

    /// Binarises an 8-bit alpha/grey buffer: a pixel is object iff `value >= threshold`
    /// (use `128` for ground-truth alpha mattes).
    ///
    /// # Errors
    /// [`MatteError::BufferLength`] if `values.len() != width * height`.
    pub fn from_threshold(
        width: usize,
        height: usize,
        values: &[u8],
        threshold: u8,
    ) -> Result<Self, MatteError> {
        let expected = pixel_count(width, height)?;
        if values.len() != expected {
            return Err(MatteError::BufferLength {
                width,
                height,
                channels: 1,
                expected,
                actual: values.len(),
            });
        }
        let data = values
            .iter()
            .map(|&v| if v >= threshold { 255 } else { 0 })
            .collect();
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Builds a mask from per-pixel booleans (`true` = object); `bits.len()` must be
    /// `width * height` (checked by the callers inside the crate).
    pub(crate) fn from_bits(width: usize, height: usize, bits: &[bool]) -> Self {
        debug_assert_eq!(bits.len(), width * height);
        Self {
            width,
            height,
            data: bits.iter().map(|&b| if b { 255 } else { 0 }).collect(),
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major bytes, each `0` or `255`.
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// Consumes the mask and returns its bytes.
    pub fn into_data(self) -> Vec<u8> {
        self.data
    }

    /// Whether pixel `(x, y)` is object; `false` outside the image.
    pub fn get(&self, x: usize, y: usize) -> bool {
        x < self.width && y < self.height && self.data[y * self.width + x] != 0
    }

    /// Number of object pixels.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&v| v != 0).count()
    }
}

/// Intersection over union `|A ∩ B| / |A ∪ B|` of two masks' object pixels.
///
/// Two empty masks agree perfectly (`1.0`). Masks of different dimensions are not
/// comparable and score `0.0`.
pub fn iou(a: &Mask, b: &Mask) -> f64 {
    if a.width != b.width || a.height != b.height {
        return 0.0;
    }
    let (mut inter, mut union) = (0usize, 0usize);
    for (&x, &y) in a.data.iter().zip(&b.data) {
        let (x, y) = (x != 0, y != 0);
        inter += usize::from(x && y);
        union += usize::from(x || y);
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}
