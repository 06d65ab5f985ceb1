//! Constitutive models: one file per PAC-NeRF family, all behind [`Constitutive`].
//!
//! Each substep a model turns the predicted deformation `F_tmp = (I + dt C) F` into the new
//! (possibly plastically projected) `F` and the Kirchhoff stress `τ` (Pa) that P2G uses.
//! The simulator is generic over the model, so there is no per-particle branch on the family.

use glam::DMat3;

use crate::error::MpmError;
use crate::state::{FamilyGrad, FamilyParams};

mod drucker_prager;
mod fixed_corotated;
mod hencky;
mod neo_hookean;
mod newtonian;
mod von_mises;

pub use drucker_prager::DruckerPrager;
pub use fixed_corotated::FixedCorotated;
pub use neo_hookean::NeoHookean;
pub use newtonian::Newtonian;
pub use von_mises::VonMises;

/// Smallest singular value (or fluid `J`) kept by the plastic / fluid models (PAC-NeRF: 0.05).
pub const SIGMA_MIN: f64 = 0.05;

/// Gradients returned by [`Constitutive::update_adjoint`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelGrad {
    /// `∂L/∂F_tmp`.
    pub f_tmp: DMat3,
    /// `∂L/∂C` (models whose stress reads `C` directly: Newtonian).
    pub c: DMat3,
    /// `∂L/∂μ_p`.
    pub mu: f64,
    /// `∂L/∂λ_p`.
    pub lam: f64,
    /// Family scalars.
    pub family: FamilyGrad,
}

/// The model of particle `p`: `model` with the particle's family scalars when `family` holds
/// them (and the model has any), else `model` itself.
#[inline(always)]
pub(crate) fn particle_model<M: Constitutive>(model: &M, family: &[FamilyParams], p: usize) -> M {
    if M::HAS_FAMILY_PARAMS && !family.is_empty() {
        model.with_params(&family[p])
    } else {
        model.clone()
    }
}

/// Which lane kernel runs a model's stress in the vectorised engine (`crate::wide`): the
/// elastic models have one; the others run particle by particle there, through
/// [`Constitutive::update_with_aux`] in `f64`.
#[doc(hidden)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LaneKernel {
    /// Particle by particle.
    PerParticle,
    /// [`NeoHookean`].
    NeoHookean,
    /// [`FixedCorotated`].
    FixedCorotated,
}

/// A constitutive law: strain prediction, return mapping and Kirchhoff stress, with adjoints.
pub trait Constitutive: Send + Sync + std::fmt::Debug + Clone {
    /// Short name (`"neo_hookean"`, ...).
    const NAME: &'static str;

    /// The lane kernel of the vectorised engine (must compute exactly this model's
    /// [`Self::update_with_aux`], in the engine's precision).
    #[doc(hidden)]
    const LANE_KERNEL: LaneKernel = LaneKernel::PerParticle;

    /// Whether [`ModelGrad::family`] can be non-zero (the model has family scalars such as a
    /// yield stress); when false the backward pass neither stores nor sums it.
    const HAS_FAMILY_PARAMS: bool = false;

    /// This model with a particle's family scalars `p` in place of its own
    /// ([`crate::Material::family`]); models without family scalars return themselves.
    #[inline(always)]
    fn with_params(&self, p: &FamilyParams) -> Self {
        let _ = p;
        self.clone()
    }

    /// The model's own family scalars (0 for those it lacks).
    fn params(&self) -> FamilyParams {
        FamilyParams::default()
    }

    /// Predicted deformation `F_tmp = (I + dt C) F` (dt in s, C in 1/s).
    #[inline(always)]
    fn predict(&self, c: &DMat3, f: &DMat3, dt: f64) -> DMat3 {
        (DMat3::IDENTITY + *c * dt) * *f
    }

    /// Adjoint of [`Self::predict`]: returns `(∂L/∂C, ∂L/∂F)` from `∂L/∂F_tmp`.
    #[inline(always)]
    fn predict_adjoint(&self, c: &DMat3, f: &DMat3, dt: f64, g: &DMat3) -> (DMat3, DMat3) {
        (
            *g * f.transpose() * dt,
            (DMat3::IDENTITY + *c * dt).transpose() * *g,
        )
    }

    /// Return mapping and stress: `(F_new, τ)` from `F_tmp`, the previous `C`, μ, λ (Pa), dt (s).
    fn update(&self, f_tmp: &DMat3, c: &DMat3, mu: f64, lam: f64, dt: f64) -> (DMat3, DMat3);

    /// Whether [`Self::update_with_aux`] returns a scalar the adjoint reuses; the stress pass
    /// then keeps it per particle for the backward pass.
    const STRESS_AUX: bool = false;

    /// [`Self::update`] plus a scalar of its work that [`Self::update_adjoint_given_stress`]
    /// needs again (neo-Hookean: `ln J`), so the backward pass need not recompute it; 0 for
    /// models without one ([`Self::STRESS_AUX`] false).
    #[inline(always)]
    fn update_with_aux(
        &self,
        f_tmp: &DMat3,
        c: &DMat3,
        mu: f64,
        lam: f64,
        dt: f64,
    ) -> (DMat3, DMat3, f64) {
        let (f, tau) = self.update(f_tmp, c, mu, lam, dt);
        (f, tau, 0.0)
    }

    /// Adjoint of [`Self::update`] given `∂L/∂F_new` and `∂L/∂τ`.
    #[allow(clippy::too_many_arguments)]
    fn update_adjoint(
        &self,
        f_tmp: &DMat3,
        c: &DMat3,
        mu: f64,
        lam: f64,
        dt: f64,
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad;

    /// [`Self::update_adjoint`] given also the stress `tau` (Pa) and the scalar `aux` that
    /// [`Self::update_with_aux`] returned for this `f_tmp`, as the backward pass has them: a
    /// model may recover intermediates from them instead of recomputing them. The default
    /// ignores both.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn update_adjoint_given_stress(
        &self,
        f_tmp: &DMat3,
        c: &DMat3,
        mu: f64,
        lam: f64,
        dt: f64,
        (tau, aux): (&DMat3, f64),
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let _ = (tau, aux);
        self.update_adjoint(f_tmp, c, mu, lam, dt, g_f, g_tau)
    }

    /// Modulus (Pa) of the fastest wave for the CFL limit: `λ + 2μ` (P-wave) by default.
    fn wave_modulus(&self, mu: f64, lam: f64) -> f64 {
        lam + 2.0 * mu
    }

    /// Dynamic viscosity (Pa·s) limiting the explicit step (0 for none).
    fn viscosity(&self, _mu: f64) -> f64 {
        0.0
    }

    /// Checks the family parameters.
    fn validate(&self) -> Result<(), MpmError> {
        Ok(())
    }
}

pub(crate) fn check_param(
    field: &'static str,
    value: f64,
    min: f64,
    inclusive: bool,
) -> Result<(), MpmError> {
    if !value.is_finite() {
        return Err(MpmError::NonFiniteInput {
            field,
            index: 0,
            value,
        });
    }
    let ok = if inclusive { value >= min } else { value > min };
    if !ok {
        return Err(MpmError::InvalidParameter {
            field,
            value,
            reason: if inclusive {
                "must be >= 0"
            } else {
                "must be > 0"
            },
        });
    }
    Ok(())
}
