//! Compressible neo-Hookean elasticity as PAC-NeRF writes it:
//! `τ = μ F Fᵀ + (λ ln J − μ) I`, `J = det F`; no plasticity (`F_new = F_tmp`).

use glam::DMat3;

use super::{Constitutive, ModelGrad};
use crate::math::{cofactor, ddot, trace};
use crate::state::FamilyGrad;

/// PAC-NeRF "elasticity" (material id 10).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NeoHookean;

impl Constitutive for NeoHookean {
    const NAME: &'static str = "neo_hookean";

    #[inline(always)]
    fn update(&self, f: &DMat3, _c: &DMat3, mu: f64, lam: f64, _dt: f64) -> (DMat3, DMat3) {
        let j = f.determinant();
        let tau = *f * f.transpose() * mu + DMat3::IDENTITY * (lam * j.ln() - mu);
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
        // d J / dF = cof(F), so J = F₀·cof(F)₀ and d ln J / dF = cof(F)/J.
        let cof = cofactor(f);
        let j = f.x_axis.dot(cof.x_axis);
        let tr_g = trace(g_tau);
        // h = 2 sym(τ̄) F: ∂(τ̄ : μ F Fᵀ)/∂F = μ h and τ̄ : F Fᵀ = ½ h : F.
        let h = (*g_tau + g_tau.transpose()) * *f;
        let g = *g_f + h * mu + cof * (lam * tr_g / j);
        ModelGrad {
            f_tmp: g,
            c: DMat3::ZERO,
            mu: 0.5 * ddot(&h, f) - tr_g,
            lam: tr_g * j.ln(),
            family: FamilyGrad::default(),
        }
    }
}
