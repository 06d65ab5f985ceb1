//! Typed errors for invalid input.

/// Why a loss or metric rejected its input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LossError {
    /// A pixel buffer does not hold `height·width·3` values.
    #[error("`{field}` has {got} values, expected {expected} ({height}x{width}x3)")]
    Length {
        /// Name of the offending buffer.
        field: &'static str,
        /// Required value count.
        expected: usize,
        /// Value count received.
        got: usize,
        /// Declared image height.
        height: usize,
        /// Declared image width.
        width: usize,
    },
    /// An image dimension is zero.
    #[error("image size {width}x{height} is invalid: both must be at least 1 pixel")]
    ImageSize {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
    },
    /// The two images of a comparison differ in size.
    #[error("image sizes differ: {a_width}x{a_height} vs {b_width}x{b_height}")]
    SizeMismatch {
        /// Width of the first image.
        a_width: usize,
        /// Height of the first image.
        a_height: usize,
        /// Width of the second image.
        b_width: usize,
        /// Height of the second image.
        b_height: usize,
    },
    /// A scalar parameter is out of range.
    #[error("`{field}` = {value} is invalid: {reason}")]
    Value {
        /// Name of the parameter.
        field: &'static str,
        /// The value received.
        value: f64,
        /// What was expected.
        reason: &'static str,
    },
}
