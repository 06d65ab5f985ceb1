//! Typed errors for invalid input. Kernels themselves assume validated input.

/// Why a render or backward call rejected its input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// A per-Gaussian or per-pixel buffer has the wrong number of entries.
    #[error("`{field}` has {got} entries, expected {expected}")]
    Length {
        /// Name of the offending field.
        field: &'static str,
        /// Required entry count.
        expected: usize,
        /// Entry count received.
        got: usize,
    },
    /// Spherical-harmonics degree outside 0..=3.
    #[error("`sh_degree` = {0} is not supported (0..=3)")]
    ShDegree(u32),
    /// An image dimension is zero.
    #[error("image size {width}x{height} is invalid: both must be at least 1 pixel")]
    ImageSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// A camera or option scalar is out of range or not finite.
    #[error("`{field}` = {value} is invalid: {reason}")]
    Value {
        /// Name of the offending field.
        field: &'static str,
        /// The value received (widened to f64).
        value: f64,
        /// What was expected.
        reason: &'static str,
    },
}
