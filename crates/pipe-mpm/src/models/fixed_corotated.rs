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
        let r = polar_rotation(f);
        let j = f.determinant();
        let tr_g = trace(g_tau);
        let gt = g_tau.transpose();
        // τ = 2μ(F Fᵀ − R Fᵀ) + λ(J² − J) I; τ̄ F is shared by ∂/∂F, R̄ and ∂/∂μ
        // (τ̄ : (F − R)Fᵀ = τ̄ F : (F − R)).
        let gf = *g_tau * *f;
        let mut g = *g_f + (gf + gt * (*f - r)) * (2.0 * mu);
        g += cofactor(f) * (lam * (2.0 * j - 1.0) * tr_g);
        let g_r = gf * (-2.0 * mu);
        // The rotation's adjoint from R alone where F is well inside det F > 0, else via the SVD.
        g +=
            polar_rotation_adjoint(f, &r, &g_r).unwrap_or_else(|| rotation_adjoint(&svd3(f), &g_r));
        ModelGrad {
            f_tmp: g,
            c: DMat3::ZERO,
            mu: 2.0 * ddot(&gf, &(*f - r)),
            lam: tr_g * j * (j - 1.0),
            family: FamilyGrad::default(),
        }
    }
}
