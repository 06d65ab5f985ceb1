//! The 3DGS photometric loss `λ·L1 + (1 - λ)·D-SSIM` (Kerbl et al. 2023 eq. 7; λ = 0.2
//! there, 0.1 in the PAC-NeRF/PhysGaussian-style pipeline of this project).

use crate::error::LossError;
use crate::image::Image;
use crate::pixel::l1_grad;
use crate::ssim::dssim_grad;

/// `λ·L1(a, b) + (1 - λ)·(1 - SSIM(a, b))` and its gradient w.r.t. `a`; `λ` in `[0, 1]`.
pub fn l1_dssim(a: Image<'_>, b: Image<'_>, lambda: f64) -> Result<(f64, Vec<f32>), LossError> {
    if !(0.0..=1.0).contains(&lambda) {
        return Err(LossError::Value {
            field: "lambda",
            value: lambda,
            reason: "must be in [0, 1]",
        });
    }
    let (l1, g1) = l1_grad(a, b)?;
    let (ds, gs) = dssim_grad(a, b)?;
    let grad = g1
        .iter()
        .zip(&gs)
        .map(|(x, y)| (lambda * *x as f64 + (1.0 - lambda) * *y as f64) as f32)
        .collect();
    Ok((lambda * l1 + (1.0 - lambda) * ds, grad))
}
