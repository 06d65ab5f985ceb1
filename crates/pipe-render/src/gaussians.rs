//! The Gaussians to render, borrowed as structure-of-arrays slices.

use crate::error::RenderError;
use crate::real::Real;

/// Per-axis standard deviations of the Gaussians (m).
#[derive(Debug, Clone, Copy)]
pub enum Scales<'a, T> {
    /// Trainable parameterisation: `scale = exp(log_scale)`.
    Log(&'a [[T; 3]]),
    /// Already activated linear standard deviations.
    Linear(&'a [[T; 3]]),
}

/// Opacities of the Gaussians.
#[derive(Debug, Clone, Copy)]
pub enum Opacities<'a, T> {
    /// Trainable parameterisation: `opacity = sigmoid(logit)`.
    Logit(&'a [T]),
    /// Already activated opacities in `[0, 1]`.
    Linear(&'a [T]),
}

/// Where each Gaussian's RGB comes from.
#[derive(Debug, Clone, Copy)]
pub enum Colors<'a, T> {
    /// RGB per Gaussian, used directly (no clamp).
    Rgb(&'a [[T; 3]]),
    /// Real spherical harmonics (3DGS basis) of degree 0..=3, laid out
    /// `[gaussian][coeff k][channel]` with `(degree+1)²` coefficients per Gaussian;
    /// `rgb = max(0, Σ_k Y_k(dir)·sh_k + 0.5)`.
    Sh {
        /// SH degree, 0..=3.
        degree: u32,
        /// `n·(degree+1)²` RGB triples.
        coeffs: &'a [[T; 3]],
    },
}

/// A deformation carried by each Gaussian (PhysGaussian, Xie et al. 2024, §4.1): the
/// Gaussian of a material point with deformation gradient `F` has covariance
/// `Σ' = F Σ Fᵀ` (`Σ = R(q) S Sᵀ R(q)ᵀ` from its scales and quaternion), and its SH colour
/// is turned with the material: `rgb = SH(Rᵀ·d)`, `d` the unit view direction (mean − camera
/// centre). Matrices are row-major 3×3 (`m[3·row + col]`), dimensionless. The backward
/// returns `dL/dF` and `dL/dR` ([`crate::Gradients::deformation`], `sh_rotation`).
/// Non-finite entries cull the Gaussian (zero gradients), as a non-finite quaternion does.
#[derive(Debug, Clone, Copy)]
pub struct Deformation<'a, T> {
    /// Per Gaussian, the deformation gradient `F` (row-major): `Σ' = F Σ Fᵀ`. Any matrix;
    /// a singular `F` flattens the Gaussian (its 2D footprint keeps the `eps2d` blur).
    pub f: &'a [[T; 9]],
    /// Per Gaussian, the rotation `R` (row-major) the SH are evaluated in: `rgb = SH(Rᵀ·d)`
    /// (typically the polar rotation of `F`). Not re-orthonormalised: a non-rotation gives
    /// the SH polynomials at a non-unit vector. `None`: colours are not turned. Ignored (zero
    /// gradient) for [`Colors::Rgb`] and SH degree 0.
    pub sh_rotation: Option<&'a [[T; 9]]>,
}

/// Gaussians as borrowed SoA slices, all of the same length `n`.
#[derive(Debug, Clone, Copy)]
pub struct Gaussians<'a, T> {
    /// Centres in world space (m).
    pub means: &'a [[T; 3]],
    /// Standard deviations along the local axes.
    pub scales: Scales<'a, T>,
    /// Rotations as quaternions `(w, x, y, z)`, any non-zero length (normalised inside,
    /// gradients flow through the normalisation).
    pub quats: &'a [[T; 4]],
    /// Opacities.
    pub opacities: Opacities<'a, T>,
    /// Colours.
    pub colors: Colors<'a, T>,
    /// Optional per-Gaussian deformation (`None`: the canonical Gaussians).
    pub deformation: Option<Deformation<'a, T>>,
}

/// Number of SH coefficients per channel for a degree: `(degree+1)²`.
pub const fn sh_coeff_count(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

impl<T: Real> Gaussians<'_, T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Checks that every buffer has `n` entries (`n·(degree+1)²` for SH, also the
    /// deformation's `f` and `sh_rotation`) and `degree <= 3`.
    pub fn validate(&self) -> Result<(), RenderError> {
        let n = self.len();
        let check = |field: &'static str, got: usize, expected: usize| {
            if got == expected {
                Ok(())
            } else {
                Err(RenderError::Length {
                    field,
                    expected,
                    got,
                })
            }
        };
        match self.scales {
            Scales::Log(s) => check("log_scales", s.len(), n)?,
            Scales::Linear(s) => check("scales", s.len(), n)?,
        }
        check("quats", self.quats.len(), n)?;
        match self.opacities {
            Opacities::Logit(o) => check("opacity_logits", o.len(), n)?,
            Opacities::Linear(o) => check("opacities", o.len(), n)?,
        }
        match self.colors {
            Colors::Rgb(c) => check("colors", c.len(), n)?,
            Colors::Sh { degree, coeffs } => {
                if degree > 3 {
                    return Err(RenderError::ShDegree(degree));
                }
                check("sh", coeffs.len(), n * sh_coeff_count(degree))?;
            }
        }
        if let Some(d) = &self.deformation {
            check("deformation.f", d.f.len(), n)?;
            if let Some(r) = d.sh_rotation {
                check("deformation.sh_rotation", r.len(), n)?;
            }
        }
        Ok(())
    }

    /// Linear scale of Gaussian `i`.
    #[inline]
    pub fn scale(&self, i: usize) -> [T; 3] {
        match self.scales {
            Scales::Log(s) => s[i].map(T::exp),
            Scales::Linear(s) => s[i],
        }
    }

    /// Deformation gradient `F` of Gaussian `i`, if any.
    #[inline]
    pub fn deformation_f(&self, i: usize) -> Option<&[T; 9]> {
        self.deformation.as_ref().map(|d| &d.f[i])
    }

    /// SH rotation `R` of Gaussian `i`, if any.
    #[inline]
    pub fn sh_rotation(&self, i: usize) -> Option<&[T; 9]> {
        self.deformation
            .as_ref()
            .and_then(|d| d.sh_rotation)
            .map(|r| &r[i])
    }

    /// Activated opacity of Gaussian `i`.
    #[inline]
    pub fn opacity(&self, i: usize) -> T {
        match self.opacities {
            Opacities::Logit(o) => sigmoid(o[i]),
            Opacities::Linear(o) => o[i],
        }
    }
}

/// `1 / (1 + e^-x)`, finite for every finite or infinite `x`.
#[inline]
pub fn sigmoid<T: Real>(x: T) -> T {
    if x >= T::ZERO {
        T::ONE / (T::ONE + (-x).exp())
    } else {
        let e = x.exp();
        e / (T::ONE + e)
    }
}
