//! Newtonian fluid (PAC-NeRF "viscous_fluid", id 11). Only the volume ratio `J` is tracked
//! (stored as `F = diag(J, 1, 1)`): `J_tmp = (1 + dt tr C) J`, `J_new = max(J_tmp, 0.05)`,
//! `τ = κ_eff (J − J⁻⁶) I + μ J (C + Cᵀ)/2`, `κ_eff = 0.6666666666 μ + λ` (the truncated constant
//! is PAC-NeRF's), with μ the dynamic viscosity (Pa·s) and `λ = κ − 2μ/3` (Pa).

use glam::{DMat3, DVec3};

use super::{Constitutive, ModelGrad, SIGMA_MIN};
use crate::math::{ddot, trace};
use crate::state::FamilyGrad;

/// PAC-NeRF's truncated 2/3.
const TWO_THIRDS_PACNERF: f64 = 0.6666666666;

/// Weakly compressible Newtonian fluid.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Newtonian;

#[inline]
fn j_matrix(j: f64) -> DMat3 {
    DMat3::from_diagonal(DVec3::new(j, 1.0, 1.0))
}

impl Constitutive for Newtonian {
    const NAME: &'static str = "newtonian";

    fn predict(&self, c: &DMat3, f: &DMat3, dt: f64) -> DMat3 {
        j_matrix((1.0 + dt * trace(c)) * f.x_axis.x)
    }

    fn predict_adjoint(&self, c: &DMat3, f: &DMat3, dt: f64, g: &DMat3) -> (DMat3, DMat3) {
        let gj = g.x_axis.x;
        let j = f.x_axis.x;
        let mut gf = DMat3::ZERO;
        gf.x_axis.x = (1.0 + dt * trace(c)) * gj;
        (DMat3::IDENTITY * (dt * j * gj), gf)
    }

    fn update(&self, f_tmp: &DMat3, c: &DMat3, mu: f64, lam: f64, _dt: f64) -> (DMat3, DMat3) {
        let j = f_tmp.x_axis.x.max(SIGMA_MIN);
        let kappa = TWO_THIRDS_PACNERF * mu + lam;
        let sym = (*c + c.transpose()) * 0.5;
        let tau = DMat3::IDENTITY * (kappa * (j - j.powi(-6))) + sym * (mu * j);
        (j_matrix(j), tau)
    }

    fn update_adjoint(
        &self,
        f_tmp: &DMat3,
        c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let j_tmp = f_tmp.x_axis.x;
        let j = j_tmp.max(SIGMA_MIN);
        let kappa = TWO_THIRDS_PACNERF * mu + lam;
        let sym = (*c + c.transpose()) * 0.5;
        let tr_g = trace(g_tau);
        let g_j = g_f.x_axis.x + kappa * (1.0 + 6.0 * j.powi(-7)) * tr_g + mu * ddot(g_tau, &sym);
        let g_kappa = tr_g * (j - j.powi(-6));
        let mut gf = DMat3::ZERO;
        gf.x_axis.x = if j_tmp > SIGMA_MIN { g_j } else { 0.0 };
        ModelGrad {
            f_tmp: gf,
            c: (*g_tau + g_tau.transpose()) * (0.5 * mu * j),
            mu: TWO_THIRDS_PACNERF * g_kappa + j * ddot(g_tau, &sym),
            lam: g_kappa,
            family: FamilyGrad::default(),
        }
    }

    /// `d/dJ [κ_eff (J − J⁻⁶)]` at `J = 1`: `7 κ_eff` (μ here is a viscosity, not a modulus).
    fn wave_modulus(&self, mu: f64, lam: f64) -> f64 {
        7.0 * (TWO_THIRDS_PACNERF * mu + lam)
    }

    fn viscosity(&self, mu: f64) -> f64 {
        mu
    }
}
