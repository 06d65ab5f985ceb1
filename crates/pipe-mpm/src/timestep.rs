//! Time-step control: explicit stability limits and substeps per frame.
//!
//! Elastic wave (CFL): `dt ≤ c · dx / (max|v| + max_p sqrt(M_p/ρ_p))`, `ρ_p = m_p/V_p`, with
//! `M = λ + 2μ` (P-wave modulus; Newtonian fluid: `7 κ_eff`, see [`Constitutive::wave_modulus`]).
//! Viscous: `dt ≤ c_ν · min_p ρ_p dx² / η_p` with η the model's viscosity (Pa·s).

use crate::error::MpmError;
use crate::models::Constitutive;
use crate::state::{Material, State};

/// Safety factors of the two limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimits {
    /// CFL factor `c` of the wave limit (default 0.3).
    pub cfl: f64,
    /// Factor `c_ν` of the viscous limit (default 1/6, explicit diffusion in 3D).
    pub viscous: f64,
}

impl Default for StepLimits {
    fn default() -> Self {
        Self {
            cfl: 0.3,
            viscous: 1.0 / 6.0,
        }
    }
}

/// The largest stable step and which limit sets it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StableStep {
    /// Wave (CFL) limit (s).
    pub wave: f64,
    /// Viscous limit (s; `inf` without viscosity).
    pub viscous: f64,
}

impl StableStep {
    /// `min(wave, viscous)` (s).
    pub fn dt(&self) -> f64 {
        self.wave.min(self.viscous)
    }

    /// Name of the binding limit.
    pub fn limit(&self) -> &'static str {
        if self.wave <= self.viscous {
            "elastic wave (CFL)"
        } else {
            "viscous"
        }
    }

    /// Error if `dt` (s) exceeds either limit, naming it.
    pub fn check(&self, dt: f64) -> Result<(), MpmError> {
        if dt > self.wave {
            return Err(MpmError::StepTooLarge {
                limit: "elastic wave (CFL)",
                dt,
                max_dt: self.wave,
            });
        }
        if dt > self.viscous {
            return Err(MpmError::StepTooLarge {
                limit: "viscous",
                dt,
                max_dt: self.viscous,
            });
        }
        Ok(())
    }

    /// Substeps needed to cover `frame_dt` (s) without exceeding the limit.
    pub fn substeps_per_frame(&self, frame_dt: f64) -> usize {
        ((frame_dt / self.dt()).ceil() as usize).max(1)
    }
}

/// Stability limits for the current state and material with cell size `dx` (m).
pub fn stable_step<M: Constitutive>(
    model: &M,
    state: &State,
    mat: &Material,
    dx: f64,
    limits: StepLimits,
) -> StableStep {
    let vmax = state.v.iter().map(|v| v.length()).fold(0.0, f64::max);
    let mut cmax: f64 = 0.0;
    let mut visc = f64::INFINITY;
    for p in 0..mat.len() {
        let rho = mat.mass[p] / mat.volume[p];
        cmax = cmax.max((model.wave_modulus(mat.mu[p], mat.lam[p]).max(0.0) / rho).sqrt());
        let eta = model.viscosity(mat.mu[p]);
        if eta > 0.0 {
            visc = visc.min(limits.viscous * rho * dx * dx / eta);
        }
    }
    let wave = if vmax + cmax > 0.0 {
        limits.cfl * dx / (vmax + cmax)
    } else {
        f64::INFINITY
    };
    StableStep {
        wave,
        viscous: visc,
    }
}

/// Substeps per frame: from the limit, or the user's fixed count checked against it.
pub fn substeps_per_frame(
    stable: &StableStep,
    frame_dt: f64,
    user: Option<usize>,
) -> Result<usize, MpmError> {
    match user {
        None => Ok(stable.substeps_per_frame(frame_dt)),
        Some(0) => Err(MpmError::InvalidParameter {
            field: "substeps",
            value: 0.0,
            reason: "must be >= 1",
        }),
        Some(n) => {
            stable.check(frame_dt / n as f64)?;
            Ok(n)
        }
    }
}
