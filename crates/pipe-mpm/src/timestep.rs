//! Time-step control: explicit stability limits and substeps per frame.
//!
//! Elastic wave (CFL): `dt ≤ c · dx / (max|v| + max_p sqrt(M_p/ρ_p))`, `ρ_p = m_p/V_p`, with
//! `M = λ + 2μ` (P-wave modulus; Newtonian fluid: `7 κ_eff`, see [`Constitutive::wave_modulus`]).
//! A step's CFL number is `ν = dt · (max|v| + max_p sqrt(M_p/ρ_p)) / dx`, so `c` bounds it.
//! Viscous: `dt ≤ c_ν · min_p ρ_p dx² / η_p` with η the model's viscosity (Pa·s).
//!
//! Two CFL numbers: automatic substeps use [`StepLimits::cfl`] (0.3, a safety margin); a
//! user-fixed step is refused only above [`StepLimits::cfl_max`] (0.5). Measured on the PAC-NeRF
//! scenes with fixed steps (`pipe simulate`, 14 frames, `allow_unstable`): the neo-Hookean torus
//! ran at 70 substeps per frame (ν up to 1.22) and diverged at 60; the Newtonian droplet ran at
//! 80 (ν ≤ 0.75) and diverged at 70 (ν = 0.79 in its first frame). PAC-NeRF's own 200 per frame
//! are ν = 0.39–0.43 (torus) and 0.28–0.30 (droplet): they run, and reproduce its frames to
//! 1e-5 m, where the automatic 0.3 differs by a few mm (each P2G/G2P transfer damps a little,
//! so results depend on the step).

use crate::error::MpmError;
use crate::models::Constitutive;
use crate::state::{Material, State};

/// Safety factors of the two limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimits {
    /// CFL number of the automatic substeps (default 0.3).
    pub cfl: f64,
    /// Largest CFL number a user-fixed step may use (default 0.5; ≥ `cfl`).
    pub cfl_max: f64,
    /// Factor `c_ν` of the viscous limit (default 1/6, explicit diffusion in 3D).
    pub viscous: f64,
}

impl Default for StepLimits {
    fn default() -> Self {
        Self {
            cfl: 0.3,
            cfl_max: 0.5,
            viscous: 1.0 / 6.0,
        }
    }
}

/// The largest stable step and which limit sets it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StableStep {
    /// Wave (CFL) limit of the automatic substeps (s): [`StepLimits::cfl`] `/ wave_rate`.
    pub wave: f64,
    /// Wave (CFL) limit a fixed step must respect (s): [`StepLimits::cfl_max`] `/ wave_rate`.
    pub wave_max: f64,
    /// `(max|v| + max_p sqrt(M_p/ρ_p)) / dx` (1/s): a step `dt` has CFL number `dt · wave_rate`.
    pub wave_rate: f64,
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

    /// CFL number `ν = dt · wave_rate` of a step `dt` (s).
    pub fn cfl_number(&self, dt: f64) -> f64 {
        dt * self.wave_rate
    }

    /// The largest step a fixed substep count may use (s): `min(wave_max, viscous)`.
    pub fn max_fixed_dt(&self) -> f64 {
        self.wave_max.min(self.viscous)
    }

    /// Error if a fixed step `dt` (s) exceeds [`Self::wave_max`] or the viscous limit, naming
    /// the limit.
    pub fn check(&self, dt: f64) -> Result<(), MpmError> {
        if dt > self.wave_max {
            return Err(MpmError::StepTooLarge {
                limit: "elastic wave (CFL)",
                dt,
                max_dt: self.wave_max,
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

    /// Fewest fixed substeps that cover `frame_dt` (s) within [`Self::max_fixed_dt`].
    pub fn fixed_substeps_needed(&self, frame_dt: f64) -> usize {
        steps_to_cover(frame_dt, self.max_fixed_dt())
    }

    /// Substeps needed to cover `frame_dt` (s) without exceeding the limit.
    pub fn substeps_per_frame(&self, frame_dt: f64) -> usize {
        steps_to_cover(frame_dt, self.dt())
    }
}

/// Fewest steps of at most `dt` covering `frame_dt` (s), at least one (saturating).
fn steps_to_cover(frame_dt: f64, dt: f64) -> usize {
    ((frame_dt / dt).ceil() as usize).max(1)
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
    stable_step_at_speed(model, mat, vmax, dx, limits)
}

/// Stability limits for particles up to speed `vmax` (m/s), e.g. a bound that includes the
/// forces and impulses about to act ([`crate::forces::speed_bound`]).
pub fn stable_step_at_speed<M: Constitutive>(
    model: &M,
    mat: &Material,
    vmax: f64,
    dx: f64,
    limits: StepLimits,
) -> StableStep {
    let mut cmax: f64 = 0.0;
    let mut visc = f64::INFINITY;
    for p in 0..mat.len() {
        let rho = mat.mass[p] / mat.volume[p];
        cmax = cmax.max((model.wave_modulus(mat.mu[p], mat.lam[p]).max(0.0) / rho).sqrt());
        let eta = crate::models::particle_model(model, &mat.family, p).viscosity(mat.mu[p]);
        if eta > 0.0 {
            visc = visc.min(limits.viscous * rho * dx * dx / eta);
        }
    }
    let wave_rate = (vmax + cmax) / dx;
    let at = |cfl: f64| {
        if wave_rate > 0.0 {
            cfl / wave_rate
        } else {
            f64::INFINITY
        }
    };
    StableStep {
        wave: at(limits.cfl),
        wave_max: at(limits.cfl_max.max(limits.cfl)),
        wave_rate,
        viscous: visc,
    }
}

/// Substeps per frame: from the limit, or the user's fixed count checked against
/// [`StableStep::check`] (the looser [`StepLimits::cfl_max`]).
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
