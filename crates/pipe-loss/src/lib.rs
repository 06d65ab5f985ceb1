//! Image losses and metrics with gradients: L1, SSIM / D-SSIM (3DGS and scikit-image
//! conventions), PSNR.
//!
//! Images are `[H][W][3]` f32 row-major buffers wrapped in [`Image`]; sums are accumulated in
//! f64; gradients are returned as f32 buffers in the same layout as the first image.

pub mod error;
pub mod image;
pub mod photometric;
pub mod pixel;
pub mod ssim;
pub mod window;

pub use error::LossError;
pub use image::Image;
pub use photometric::l1_dssim;
pub use pixel::{l1, l1_grad, mse, mse_per_channel, psnr, psnr_from_mse, psnr_mean_of_channels};
pub use ssim::{dssim_grad, ssim, ssim_grad, ssim_map, ssim_skimage};
