//! Sand: Hencky elasticity with a Drucker–Prager return map (Klár et al. 2016; PAC-NeRF
//! "drucker_prager", id 13), cohesion 0.
//!
//! `σ = max(Σ, 0.05)`, `ε = ln σ`, `tr = Σ ε`. If `tr ≥ 0`: `ε_out = 0` (separation). Else
//! `ε̂ = ε − tr/3`, `‖ε̂‖ = sqrt(ε̂·ε̂ + 1e-8)`, `Δγ = ‖ε̂‖ + (3λ + 2μ)/(2μ) tr α`,
//! `ε_out = ε − max(Δγ, 0) ε̂/‖ε̂‖`; `σ_out = exp(ε_out)`.

use glam::{DMat3, DVec3};

use super::hencky::{compose, compose_adjoint, f_tmp_adjoint};
use super::{Constitutive, ModelGrad, SIGMA_MIN, check_param};
use crate::error::MpmError;
use crate::state::{FamilyGrad, FamilyParams};
use crate::svd::svd3;

/// Drucker–Prager plasticity with friction coefficient α.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DruckerPrager {
    /// Friction coefficient `α = sqrt(2/3) · 2 sin φ / (3 − sin φ)`.
    pub alpha: f64,
}

impl DruckerPrager {
    /// From the friction angle φ in degrees.
    pub fn from_friction_angle_deg(phi_deg: f64) -> Self {
        let s = phi_deg.to_radians().sin();
        Self {
            alpha: (2.0f64 / 3.0).sqrt() * 2.0 * s / (3.0 - s),
        }
    }

    /// `dα/dφ` per degree, to turn `∂L/∂α` into `∂L/∂φ`.
    pub fn dalpha_dphi_deg(phi_deg: f64) -> f64 {
        let phi = phi_deg.to_radians();
        let s = phi.sin();
        // α = k·2s/(3−s) → dα/ds = k·6/(3−s)².
        (2.0f64 / 3.0).sqrt() * 6.0 / ((3.0 - s) * (3.0 - s)) * phi.cos() * std::f64::consts::PI
            / 180.0
    }
}

enum Branch {
    Separate,
    Elastic,
    Project {
        eps_hat: DVec3,
        n: f64,
        dgamma: f64,
        beta: f64,
    },
}

struct Map {
    sigma: DVec3,
    tr: f64,
    branch: Branch,
    eps_out: DVec3,
}

impl DruckerPrager {
    fn map(&self, sig_in: DVec3, mu: f64, lam: f64) -> Map {
        let sigma = sig_in.max(DVec3::splat(SIGMA_MIN));
        let eps = sigma.ln();
        let tr = eps.element_sum();
        if tr >= 0.0 {
            return Map {
                sigma,
                tr,
                branch: Branch::Separate,
                eps_out: DVec3::ZERO,
            };
        }
        let eps_hat = eps - DVec3::splat(tr / 3.0);
        let n = (eps_hat.dot(eps_hat) + 1e-8).sqrt();
        let beta = (3.0 * lam + 2.0 * mu) / (2.0 * mu);
        let dgamma = n + beta * tr * self.alpha;
        if dgamma > 0.0 {
            let eps_out = eps - dgamma / n * eps_hat;
            Map {
                sigma,
                tr,
                branch: Branch::Project {
                    eps_hat,
                    n,
                    dgamma,
                    beta,
                },
                eps_out,
            }
        } else {
            Map {
                sigma,
                tr,
                branch: Branch::Elastic,
                eps_out: eps,
            }
        }
    }

    /// Adjoint of [`Self::map`]: `(∂L/∂Σ, ∂L/∂μ, ∂L/∂λ, family)` from `∂L/∂σ_out`.
    fn map_adjoint(
        &self,
        m: &Map,
        sig_in: DVec3,
        sigma_out: DVec3,
        g_out: DVec3,
        mu: f64,
        lam: f64,
    ) -> (DVec3, f64, f64, FamilyGrad) {
        let g_eps_out = g_out * sigma_out;
        let mut g_mu = 0.0;
        let mut g_lam = 0.0;
        let mut fam = FamilyGrad::default();
        let g_eps = match m.branch {
            Branch::Separate => DVec3::ZERO,
            Branch::Elastic => g_eps_out,
            Branch::Project {
                eps_hat,
                n,
                dgamma,
                beta,
            } => {
                let k = dgamma / n;
                let g_k = -g_eps_out.dot(eps_hat);
                let mut g_eps_hat = -k * g_eps_out;
                let g_dgamma = g_k / n;
                let mut g_n = -g_k * dgamma / (n * n);
                g_n += g_dgamma;
                let mut g_tr = g_dgamma * beta * self.alpha;
                fam.friction_alpha += g_dgamma * beta * m.tr;
                let g_beta = g_dgamma * m.tr * self.alpha;
                g_lam += g_beta * 3.0 / (2.0 * mu);
                g_mu -= g_beta * 3.0 * lam / (2.0 * mu * mu);
                g_eps_hat += eps_hat * (g_n / n);
                g_tr -= g_eps_hat.element_sum() / 3.0;
                g_eps_out + g_eps_hat + DVec3::splat(g_tr)
            }
        };
        let g_sigma = g_eps / m.sigma;
        let mask = DVec3::select(
            sig_in.cmpgt(DVec3::splat(SIGMA_MIN)),
            DVec3::ONE,
            DVec3::ZERO,
        );
        (g_sigma * mask, g_mu, g_lam, fam)
    }
}

impl Constitutive for DruckerPrager {
    const NAME: &'static str = "drucker_prager";
    const HAS_FAMILY_PARAMS: bool = true;

    #[inline(always)]
    fn with_params(&self, p: &FamilyParams) -> Self {
        Self {
            alpha: p.friction_alpha,
        }
    }

    fn params(&self) -> FamilyParams {
        FamilyParams {
            friction_alpha: self.alpha,
            ..FamilyParams::default()
        }
    }

    fn update(&self, f_tmp: &DMat3, _c: &DMat3, mu: f64, lam: f64, _dt: f64) -> (DMat3, DMat3) {
        let d = svd3(f_tmp);
        let m = self.map(d.s, mu, lam);
        compose(&d, m.eps_out.exp(), mu, lam)
    }

    fn update_adjoint(
        &self,
        f_tmp: &DMat3,
        _c: &DMat3,
        mu: f64,
        lam: f64,
        _dt: f64,
        g_f: &DMat3,
        g_tau: &DMat3,
    ) -> ModelGrad {
        let d = svd3(f_tmp);
        let m = self.map(d.s, mu, lam);
        let sigma_out = m.eps_out.exp();
        let cg = compose_adjoint(&d, sigma_out, mu, lam, g_f, g_tau);
        let (g_sig_in, g_mu, g_lam, fam) =
            self.map_adjoint(&m, d.s, sigma_out, cg.g_sigma_out, mu, lam);
        let mut jac = DMat3::ZERO;
        for k in 0..3 {
            let row = self
                .map_adjoint(&m, d.s, sigma_out, DVec3::AXES[k], mu, lam)
                .0;
            for l in 0..3 {
                jac.col_mut(l)[k] = row[l];
            }
        }
        ModelGrad {
            f_tmp: f_tmp_adjoint(&d, sigma_out, &jac, mu, lam, g_sig_in, g_f, g_tau),
            c: DMat3::ZERO,
            mu: cg.mu + g_mu,
            lam: cg.lam + g_lam,
            family: fam,
        }
    }

    fn validate(&self) -> Result<(), MpmError> {
        check_param("friction_alpha", self.alpha, 0.0, true)
    }
}
