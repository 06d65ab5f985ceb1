//! CPU 3D Gaussian splatting rasterizer (Kerbl et al. 2023) with a hand-written backward.
//!
//! Pipeline: [`project`] each Gaussian (EWA, gsplat frustum clamp, `eps2d` blur, 3-sigma
//! radius), bin into 16×16 [`tiles`] with a per-tile depth sort, blend front to back per
//! pixel ([`forward`]); [`backward()`] walks each pixel's list back to front and chains the
//! gradients through the projection, SH and activations.
//!
//! Conventions: OpenCV camera (x right, y down, z forward), `camera_from_world`
//! (`x_cam = R x_world + t`), metres, pixels with the centre of pixel `(i, j)` at
//! `(i + 0.5, j + 0.5)`, images row-major `[H][W]`. Everything is generic over [`Real`]
//! (`f32` for production, `f64` for gradient checks). Results are bit-identical for any
//! rayon thread count (no atomics; per-tile gradients reduced in a fixed order).
//!
//! Outputs per pixel: RGB (with background), alpha `1 - T_final`, the expected depth
//! `Σ w_i z_i / Σ w_i` (`w_i = α_i T_i`, z = camera-space depth in m; not differentiated)
//! and the number of blended Gaussians. The backward takes `dL/d image` and optionally
//! `dL/d alpha` and returns gradients w.r.t. means, (log-)scales, raw quaternions,
//! opacities (and logits), RGB or SH coefficients, plus `dL/d means2d` (pixels) for
//! densification. Gradients through the 0.99 alpha clamp and clamped SH channels are 0.
//!
//! Deformed Gaussians (PhysGaussian, Xie et al. 2024, §4.1): with
//! [`Gaussians::deformation`] each Gaussian carries a deformation gradient `F` and optionally
//! an SH rotation `R` (row-major 3×3, [`Deformation`]). It is rendered at its mean with
//! covariance `F Σ Fᵀ` (`Σ = R(q) S Sᵀ R(q)ᵀ`, i.e. `M = F R(q) diag(s)`, `Σ' = M Mᵀ`) and
//! SH colour evaluated at `Rᵀ·d`, `d` the unit view direction. The backward adds `dL/dF`
//! (`= dL/dM·(R(q) diag(s))ᵀ`, the rest `Fᵀ dL/dM` going on to scales and quaternions) and
//! `dL/dR` (`dL/dR[j][i] = d_j·(dL/dd')_i`, `d' = Rᵀd`, and `R·dL/dd'` on to the mean), so
//! a simulation's adjoint can take them with `dL/d means`. Without a deformation the code
//! path, image and gradients are those of the canonical Gaussians, bit for bit.
//!
//! ```
//! use pipe_render::{Camera, Colors, Gaussians, Opacities, RenderOptions, Scales, backward, render};
//!
//! let cam = Camera {
//!     camera_from_world_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
//!     camera_from_world_translation: [0.0, 0.0, 0.0],
//!     fx: 40.0, fy: 40.0, cx: 16.0, cy: 16.0, width: 32, height: 32, near: 0.01,
//! };
//! let means = [[0.0f32, 0.0, 2.0]];
//! let log_scales = [[-3.0f32; 3]];
//! let quats = [[1.0f32, 0.0, 0.0, 0.0]];
//! let logits = [2.0f32];
//! let rgb = [[1.0f32, 0.5, 0.0]];
//! let g = Gaussians {
//!     means: &means,
//!     scales: Scales::Log(&log_scales),
//!     quats: &quats,
//!     opacities: Opacities::Logit(&logits),
//!     colors: Colors::Rgb(&rgb),
//!     deformation: None,
//! };
//! let opts = RenderOptions::default();
//! let out = render(&g, &cam, &opts)?;
//! assert!(out.alpha[16 * 32 + 16] > 0.5);
//! let d_image = vec![[1.0f32; 3]; 32 * 32];
//! let grads = backward(&g, &cam, &opts, &out, &d_image, None)?;
//! assert!(grads.opacity_logits[0] > 0.0);
//! # Ok::<(), pipe_render::RenderError>(())
//! ```

pub mod backward;
mod blend;
pub mod camera;
pub mod error;
pub mod forward;
pub mod gaussians;
pub mod project;
pub mod real;
pub mod sh;
#[cfg(target_arch = "x86_64")]
mod simd;
mod splat;
pub mod tiles;

pub use backward::{BackwardTimings, Gradients, backward};
pub use camera::{Camera, TILE};
pub use error::RenderError;
pub use forward::{ForwardTimings, RenderOptions, Rendered, project_all, render};
pub use gaussians::{Colors, Deformation, Gaussians, Opacities, Scales, sh_coeff_count, sigmoid};
pub use project::{ProjectedGaussian, ProjectedGrad};
pub use real::Real;
pub use splat::{ALPHA_MAX, ALPHA_MIN, T_MIN};
pub use tiles::TileBins;
