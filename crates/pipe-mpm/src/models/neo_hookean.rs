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
    const LANE_KERNEL: super::LaneKernel = super::LaneKernel::NeoHookean;

    const NAME: &'static str = "neo_hookean";

    #[inline(always)]
    fn update(&self, f: &DMat3, c: &DMat3, mu: f64, lam: f64, dt: f64) -> (DMat3, DMat3) {
        let (f, tau, _) = self.update_with_aux(f, c, mu, lam, dt);
        (f, tau)
    }

    const STRESS_AUX: bool = true;

    /// The scalar kept for the adjoint is `ln J`.
    #[inline(always)]
    fn update_with_aux(
        &self,
        f: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
    ) -> (DMat3, DMat3, f64) {
        let ln_j = f.determinant().ln();
        let tau = *f * f.transpose() * mu + DMat3::IDENTITY * (lam * ln_j - mu);
        (*f, tau, ln_j)
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
        let ln_j = f.determinant().ln();
        adjoint_given_ln_j(f, mu, lam, ln_j, g_f, g_tau)
    }

    /// With `ln J` from the forward pass, no logarithm is taken again.
    #[inline(always)]
    fn update_adjoint_given_stress(
        &self,
        f: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
        (_, ln_j): (&DMat3, f64),
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        adjoint_given_ln_j(f, mu, lam, ln_j, g_f, g_tau)
    }
}

/// The adjoint of `τ = μ F Fᵀ + (λ ln J − μ) I` given `ln J`.
#[inline(always)]
fn adjoint_given_ln_j(
    f: &DMat3,
    mu: f64,
    lam: f64,
    ln_j: f64,
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
        lam: tr_g * ln_j,
        family: FamilyGrad::default(),
    }
}
