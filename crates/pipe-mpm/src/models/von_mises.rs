//! Plasticine / non-Newtonian: Hencky elasticity with a von Mises return map and optional
//! Perzyna viscosity η (PAC-NeRF "von_mises", id 12).
//!
//! `σ = max(Σ, 0.05)`, `ε = ln σ`, `s = 2μ (ε − tr ε/3)`, `‖s‖ = sqrt(s·s + 1e-8)`,
//! `y = ‖s‖ − sqrt(2/3) τ_Y`. If `y > 0`: `μ̂ = μ Σσ²/3`, `‖s_new‖ = ‖s‖ − y/(1 + η/(2 μ̂ dt))`,
//! `σ_out = exp((‖s_new‖/‖s‖) s/(2μ) + tr ε/3)`; otherwise `σ_out = σ`.

use glam::{DMat3, DVec3};

use super::hencky::{compose, compose_adjoint, f_tmp_adjoint};
use super::{Constitutive, ModelGrad, SIGMA_MIN, check_param};
use crate::error::MpmError;
use crate::state::{FamilyGrad, FamilyParams};
use crate::svd::svd3;

/// von Mises plasticity with yield stress τ_Y (Pa) and viscosity η (Pa·s; 0 = rate independent).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VonMises {
    /// Yield stress τ_Y (Pa).
    pub yield_stress: f64,
    /// Perzyna viscosity η (Pa·s).
    pub eta: f64,
}

const SQRT_2_3: f64 = 0.816_496_580_927_726;

/// Intermediate values of the return map, kept for the adjoint.
struct Map {
    sigma: DVec3,
    s: DVec3,
    ns: f64,
    plastic: Option<Plastic>,
    out: DVec3,
}

struct Plastic {
    y: f64,
    mu_hat: f64,
    den: f64,
    nsn: f64,
    r: f64,
    q: f64,
}

impl VonMises {
    fn map(&self, sig_in: DVec3, mu: f64, dt: f64) -> Map {
        let sigma = sig_in.max(DVec3::splat(SIGMA_MIN));
        let eps = sigma.ln();
        let tr = eps.element_sum();
        let eps_hat = eps - DVec3::splat(tr / 3.0);
        let s = eps_hat * (2.0 * mu);
        let ns = (s.dot(s) + 1e-8).sqrt();
        let y = ns - SQRT_2_3 * self.yield_stress;
        if y > 0.0 {
            let q = sigma.dot(sigma);
            let mu_hat = mu * q / 3.0;
            let den = 1.0 + self.eta / (2.0 * mu_hat * dt);
            let nsn = ns - y / den;
            let r = nsn / ns;
            let h = r * s / (2.0 * mu) + DVec3::splat(tr / 3.0);
            Map {
                sigma,
                s,
                ns,
                plastic: Some(Plastic {
                    y,
                    mu_hat,
                    den,
                    nsn,
                    r,
                    q,
                }),
                out: h.exp(),
            }
        } else {
            Map {
                sigma,
                s,
                ns,
                plastic: None,
                out: sigma,
            }
        }
    }

    /// Adjoint of [`Self::map`]: `(∂L/∂Σ, ∂L/∂μ, family)` from `∂L/∂σ_out`.
    fn map_adjoint(
        &self,
        m: &Map,
        sig_in: DVec3,
        g_out: DVec3,
        mu: f64,
        dt: f64,
    ) -> (DVec3, f64, FamilyGrad) {
        let mut g_mu = 0.0;
        let mut fam = FamilyGrad::default();
        let mut g_sigma = DVec3::ZERO;
        let mut g_s = DVec3::ZERO;
        let mut g_ns = 0.0;
        let mut g_tr = 0.0;
        if let Some(p) = &m.plastic {
            let g_h = g_out * m.out;
            let g_r = g_h.dot(m.s) / (2.0 * mu);
            g_s += g_h * (p.r / (2.0 * mu));
            g_mu -= p.r * g_h.dot(m.s) / (2.0 * mu * mu);
            g_tr += g_h.element_sum() / 3.0;
            let g_nsn = g_r / m.ns;
            g_ns += -g_r * p.nsn / (m.ns * m.ns);
            g_ns += g_nsn;
            let g_y = -g_nsn / p.den;
            let g_den = g_nsn * p.y / (p.den * p.den);
            fam.eta += g_den / (2.0 * p.mu_hat * dt);
            let g_mu_hat = -g_den * self.eta / (2.0 * p.mu_hat * p.mu_hat * dt);
            g_mu += g_mu_hat * p.q / 3.0;
            let g_q = g_mu_hat * mu / 3.0;
            g_sigma += m.sigma * (2.0 * g_q);
            g_ns += g_y;
            fam.yield_stress -= SQRT_2_3 * g_y;
        } else {
            g_sigma += g_out;
        }
        g_s += m.s * (g_ns / m.ns);
        let g_eps_hat = g_s * (2.0 * mu);
        let eps_hat = m.s / (2.0 * mu);
        g_mu += 2.0 * eps_hat.dot(g_s);
        g_tr -= g_eps_hat.element_sum() / 3.0;
        let g_eps = g_eps_hat + DVec3::splat(g_tr);
        g_sigma += g_eps / m.sigma;
        let mask = DVec3::select(
            sig_in.cmpgt(DVec3::splat(SIGMA_MIN)),
            DVec3::ONE,
            DVec3::ZERO,
        );
        (g_sigma * mask, g_mu, fam)
    }
}

impl Constitutive for VonMises {
    const NAME: &'static str = "von_mises";
    const HAS_FAMILY_PARAMS: bool = true;

    #[inline(always)]
    fn with_params(&self, p: &FamilyParams) -> Self {
        Self {
            yield_stress: p.yield_stress,
            eta: p.eta,
        }
    }

    fn params(&self) -> FamilyParams {
        FamilyParams {
            yield_stress: self.yield_stress,
            eta: self.eta,
            ..FamilyParams::default()
        }
    }

    fn update(&self, f_tmp: &DMat3, _c: &DMat3, mu: f64, lam: f64, dt: f64) -> (DMat3, DMat3) {
        let d = svd3(f_tmp);
        let m = self.map(d.s, mu, dt);
        compose(&d, m.out, mu, lam)
    }

    fn update_adjoint(
        &self,
        f_tmp: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        dt: f64,
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let d = svd3(f_tmp);
        let m = self.map(d.s, mu, dt);
        let cg = compose_adjoint(&d, m.out, mu, lam, g_f, g_tau);
        let (g_sig_in, g_mu, fam) = self.map_adjoint(&m, d.s, cg.g_sigma_out, mu, dt);
        let mut jac = DMat3::ZERO;
        for k in 0..3 {
            let row = self.map_adjoint(&m, d.s, DVec3::AXES[k], mu, dt).0;
            for l in 0..3 {
                jac.col_mut(l)[k] = row[l];
            }
        }
        ModelGrad {
            f_tmp: f_tmp_adjoint(&d, m.out, &jac, mu, lam, g_sig_in, g_f, g_tau),
            c: DMat3::ZERO,
            mu: cg.mu + g_mu,
            lam: cg.lam,
            family: fam,
        }
    }

    fn viscosity(&self, _mu: f64) -> f64 {
        self.eta
    }

    fn validate(&self) -> Result<(), MpmError> {
        check_param("yield_stress", self.yield_stress, 0.0, true)?;
        check_param("eta", self.eta, 0.0, true)
    }
}
