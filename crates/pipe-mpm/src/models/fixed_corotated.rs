//! Fixed-corotated elasticity (Stomakhin et al. 2012, PhysGaussian / PhysDreamer):
//! `τ = 2μ (F − R) Fᵀ + λ J (J − 1) I`, `R` the rotation of the polar decomposition; no plasticity.

use glam::DMat3;

use super::{Constitutive, ModelGrad};
use crate::math::{cofactor, ddot, trace};
use crate::state::FamilyGrad;
use crate::svd::{polar_rotation, polar_rotation_adjoint, rotation_adjoint, svd3};

/// Fixed-corotated elastic solid.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FixedCorotated;

impl Constitutive for FixedCorotated {
    const LANE_KERNEL: super::LaneKernel = super::LaneKernel::FixedCorotated;

    const NAME: &'static str = "fixed_corotated";

    #[inline(always)]
    fn update(&self, f: &DMat3, _c: &DMat3, mu: f64, lam: f64, _dt: f64) -> (DMat3, DMat3) {
        // `R = U Vᵀ` of svd3 (rotation variant), without the SVD when det F > 0.
        let r = polar_rotation(f);
        let j = f.determinant();
        let tau = (*f - r) * f.transpose() * (2.0 * mu) + DMat3::IDENTITY * (lam * j * (j - 1.0));
        (*f, tau)
    }

    #[inline(always)]
    fn update_adjoint(
        &self,
        f: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let cof = cofactor(f);
        adjoint_with_rotation(f, &cof, &polar_rotation(f), mu, lam, g_f, g_tau)
    }

    /// With the forward stress at hand, `R` comes from it in closed form
    /// (`rotation_from_stress`) instead of the polar iteration.
    #[inline(always)]
    fn update_adjoint_given_stress(
        &self,
        f: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
        (tau, _): (&DMat3, f64),
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let cof = cofactor(f);
        let r = rotation_from_stress(f, &cof, tau, mu, lam).unwrap_or_else(|| polar_rotation(f));
        adjoint_with_rotation(f, &cof, &r, mu, lam, g_f, g_tau)
    }
}

/// Smallest `det X` of `X = F √3/‖F‖_F` (`Σσ² = 3`) for which [`rotation_from_stress`] solves
/// for `R`: it divides by `det F`, and its error grows like the condition number of `F`
/// (below this, ≤ 1e3 at Σσ² = 3).
const STRESS_ROTATION_MIN_DET: f64 = 1e-2;

/// `R` of the polar decomposition recovered from the stress the forward pass computed:
/// `(F − R)Fᵀ = (τ − λJ(J − 1) I)/(2μ)`, so `R Fᵀ = F Fᵀ − (τ − λJ(J − 1) I)/(2μ)` and
/// `R = R Fᵀ · cof(F)/J` (`F⁻ᵀ = cof(F)/J`, `cof` = [`cofactor`] of `f`). `None` for flat,
/// inverted or extreme `F`, or `μ ≤ 0` (the polar iteration decides there), and when the result
/// is not a rotation to 1e-10 (`‖RᵀR − I‖_F²`, so a stress that does not belong to `F` cannot
/// slip through).
#[inline(always)]
fn rotation_from_stress(f: &DMat3, cof: &DMat3, tau: &DMat3, mu: f64, lam: f64) -> Option<DMat3> {
    let n2 = ddot(f, f);
    let j = f.x_axis.dot(cof.x_axis);
    let scale = 3.0 / n2;
    if !(n2 > 1e-100
        && n2 < 1e100
        && mu > 0.0
        && j * scale * scale.sqrt() > STRESS_ROTATION_MIN_DET)
    {
        return None;
    }
    let p = (*tau - DMat3::from_diagonal(glam::DVec3::splat(lam * j * (j - 1.0)))) * (0.5 / mu);
    let r = (*f * f.transpose() - p) * *cof * (1.0 / j);
    let e = r.transpose() * r - DMat3::IDENTITY;
    (ddot(&e, &e) < 1e-20).then_some(r)
}

/// The adjoint of `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I` given `R` and `cof` = [`cofactor`] of `f`
/// (`∂J/∂F`, and `J = F₀·cof₀`).
#[inline(always)]
fn adjoint_with_rotation(
    f: &DMat3,
    cof: &DMat3,
    r: &DMat3,
    mu: f64,
    lam: f64,
    g_f: &DMat3,
    g_tau: &DMat3,
) -> ModelGrad {
    let j = f.x_axis.dot(cof.x_axis);
    let tr_g = trace(g_tau);
    let gt = g_tau.transpose();
    // τ = 2μ(F Fᵀ − R Fᵀ) + λ(J² − J) I; τ̄ F is shared by ∂/∂F, R̄ and ∂/∂μ
    // (τ̄ : (F − R)Fᵀ = τ̄ F : (F − R)).
    let gf = *g_tau * *f;
    let mut g = *g_f + (gf + gt * (*f - *r)) * (2.0 * mu);
    g += *cof * (lam * (2.0 * j - 1.0) * tr_g);
    let g_r = gf * (-2.0 * mu);
    // The rotation's adjoint from R alone where F is well inside det F > 0, else via the SVD.
    g += polar_rotation_adjoint(f, r, &g_r).unwrap_or_else(|| rotation_adjoint(&svd3(f), &g_r));
    ModelGrad {
        f_tmp: g,
        c: DMat3::ZERO,
        mu: 2.0 * ddot(&gf, &(*f - *r)),
        lam: tr_g * j * (j - 1.0),
        family: FamilyGrad::default(),
    }
}
