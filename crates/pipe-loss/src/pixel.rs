//! Per-pixel losses and metrics: L1, MSE, PSNR.

use crate::error::LossError;
use crate::image::{Image, same_size};

/// Mean absolute error over all `3·H·W` values.
pub fn l1(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    same_size(&a, &b)?;
    let s: f64 = a
        .data()
        .iter()
        .zip(b.data())
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .sum();
    Ok(s / a.data().len() as f64)
}

/// L1 and its gradient w.r.t. `a`: `sign(a - b)/N` (0 where equal).
pub fn l1_grad(a: Image<'_>, b: Image<'_>) -> Result<(f64, Vec<f32>), LossError> {
    let value = l1(a, b)?;
    let inv_n = 1.0 / a.data().len() as f64;
    let grad = a
        .data()
        .iter()
        .zip(b.data())
        .map(|(x, y)| {
            let d = *x as f64 - *y as f64;
            let s = if d > 0.0 {
                1.0
            } else if d < 0.0 {
                -1.0
            } else {
                0.0
            };
            (s * inv_n) as f32
        })
        .collect();
    Ok((value, grad))
}

/// Mean squared error over all values.
pub fn mse(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    same_size(&a, &b)?;
    let s: f64 = a
        .data()
        .iter()
        .zip(b.data())
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    Ok(s / a.data().len() as f64)
}

/// Per-channel mean squared errors.
pub fn mse_per_channel(a: Image<'_>, b: Image<'_>) -> Result<[f64; 3], LossError> {
    same_size(&a, &b)?;
    let mut s = [0.0f64; 3];
    for (i, (x, y)) in a.data().iter().zip(b.data()).enumerate() {
        s[i % 3] += (*x as f64 - *y as f64).powi(2);
    }
    let n = (a.width() * a.height()) as f64;
    Ok(s.map(|v| v / n))
}

/// `10·log10(1/mse)` for data range 1; `+inf` for identical images.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse > 0.0 {
        -10.0 * mse.log10()
    } else {
        f64::INFINITY
    }
}

/// PSNR with the MSE over all pixels and channels (scikit-image
/// `peak_signal_noise_ratio(data_range=1)`, 3DGS `metrics.py`).
pub fn psnr(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    Ok(psnr_from_mse(mse(a, b)?))
}

/// Mean of the three per-channel PSNRs (what 3DGS `train.py` reports).
pub fn psnr_mean_of_channels(a: Image<'_>, b: Image<'_>) -> Result<f64, LossError> {
    Ok(mse_per_channel(a, b)?
        .iter()
        .map(|&m| psnr_from_mse(m))
        .sum::<f64>()
        / 3.0)
}
