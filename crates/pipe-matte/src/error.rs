//! Error type of the crate.

/// Everything that can go wrong when matting; all variants name the offending sizes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MatteError {
    /// A buffer does not hold `channels * width * height` bytes.
    #[error(
        "buffer for a {width}x{height} image with {channels} channel(s) must hold {expected} bytes, got {actual}"
    )]
    BufferLength {
        /// Declared width in pixels.
        width: usize,
        /// Declared height in pixels.
        height: usize,
        /// Bytes per pixel (3 for RGB, 1 for masks).
        channels: usize,
        /// `channels * width * height`.
        expected: usize,
        /// Length of the buffer actually passed.
        actual: usize,
    },
    /// The image and the background plate have different dimensions.
    #[error("image is {image_width}x{image_height} but plate is {plate_width}x{plate_height}")]
    SizeMismatch {
        /// Width of the camera image.
        image_width: usize,
        /// Height of the camera image.
        image_height: usize,
        /// Width of the background plate.
        plate_width: usize,
        /// Height of the background plate.
        plate_height: usize,
    },
    /// `width * height * channels` does not fit in `usize`.
    #[error("image dimensions {width}x{height} overflow usize")]
    DimensionOverflow {
        /// Declared width in pixels.
        width: usize,
        /// Declared height in pixels.
        height: usize,
    },
    /// A camera's image size differs from its image's.
    #[error(
        "view {view}: the camera is {camera_width}x{camera_height} but its image is {image_width}x{image_height}"
    )]
    CameraSize {
        /// Index of the view.
        view: usize,
        /// Camera width in pixels.
        camera_width: usize,
        /// Camera height in pixels.
        camera_height: usize,
        /// Image width in pixels.
        image_width: usize,
        /// Image height in pixels.
        image_height: usize,
    },
}
