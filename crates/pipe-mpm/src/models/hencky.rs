//! Shared Hencky (logarithmic strain) stress for the plastic families:
//! `F_new = U diag(σ_out) Vᵀ`, `τ = U diag(2μ ln σ_out + λ Σ ln σ_out) Uᵀ`.

use glam::{DMat3, DVec3};

use crate::math::diagonal;
use crate::svd::{Svd, divided_differences, isotropic_adjoint};

/// Principal Kirchhoff stresses `t_i = 2μ ln σ_i + λ Σ_k ln σ_k`.
#[inline]
fn principal(sigma_out: DVec3, mu: f64, lam: f64) -> DVec3 {
    let lo = sigma_out.ln();
    lo * (2.0 * mu) + DVec3::splat(lam * lo.element_sum())
}

/// `(F_new, τ)` from the SVD of `F_tmp` and the returned singular values.
#[inline]
pub(crate) fn compose(svd: &Svd, sigma_out: DVec3, mu: f64, lam: f64) -> (DMat3, DMat3) {
    let t = principal(sigma_out, mu, lam);
    (
        svd.compose(sigma_out),
        svd.u * DMat3::from_diagonal(t) * svd.u.transpose(),
    )
}

/// Gradients of [`compose`] on the principal values: `σ̄_out` (through F and τ) and the direct
/// μ, λ parts of τ.
pub(crate) struct ComposeGrad {
    pub g_sigma_out: DVec3,
    pub mu: f64,
    pub lam: f64,
}

pub(crate) fn compose_adjoint(
    svd: &Svd,
    sigma_out: DVec3,
    mu: f64,
    lam: f64,
    g_f: &DMat3,
    g_tau: &DMat3,
) -> ComposeGrad {
    let lo = sigma_out.ln();
    let (u, v) = (svd.u, svd.v);
    let g_sig = diagonal(&(u.transpose() * *g_f * v));
    let g_t = diagonal(&(u.transpose() * *g_tau * u));
    let sum_gt = g_t.element_sum();
    let g_lo = g_t * (2.0 * mu) + DVec3::splat(lam * sum_gt);
    ComposeGrad {
        g_sigma_out: g_sig + g_lo / sigma_out,
        mu: 2.0 * g_t.dot(lo),
        lam: sum_gt * lo.element_sum(),
    }
}

/// `∂L/∂F_tmp` given the full gradient on the input singular values `g_sigma_in` and the
/// Jacobian `jac` of the return map (`jac.col(l)[k] = ∂σ_out_k/∂Σ_l`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn f_tmp_adjoint(
    svd: &Svd,
    sigma_out: DVec3,
    jac: &DMat3,
    mu: f64,
    lam: f64,
    g_sigma_in: DVec3,
    g_f: &DMat3,
    g_tau: &DMat3,
) -> DMat3 {
    let t = principal(sigma_out, mu, lam);
    // ∂t/∂Σ = (2μ I + λ 11ᵀ) diag(1/σ_out) ∂σ_out/∂Σ.
    let k = DMat3::IDENTITY * (2.0 * mu)
        + DMat3::from_cols(DVec3::splat(lam), DVec3::splat(lam), DVec3::splat(lam));
    let jt = k * DMat3::from_diagonal(sigma_out.recip()) * *jac;
    let df = divided_differences(svd.s, sigma_out, jac);
    let dt = divided_differences(svd.s, t, &jt);
    isotropic_adjoint(svd, g_f, sigma_out, &df, g_tau, t, &dt, g_sigma_in)
}
