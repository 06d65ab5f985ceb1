//! Particle state and per-particle material, structure of arrays, SI units.

use glam::{DMat3, DVec3};

use crate::error::MpmError;
use crate::math::mat_finite;

/// The evolving state of every particle.
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    /// Positions (m).
    pub x: Vec<DVec3>,
    /// Velocities (m/s).
    pub v: Vec<DVec3>,
    /// APIC affine velocity matrices `C` (1/s).
    pub c: Vec<DMat3>,
    /// Deformation gradients `F` (dimensionless). Newtonian fluid: `diag(J, 1, 1)`.
    pub f: Vec<DMat3>,
}

impl State {
    /// Particles at rest (`v = 0`, `C = 0`, `F = I`) at the given positions (m).
    pub fn at_rest(x: Vec<DVec3>) -> Self {
        let n = x.len();
        Self {
            x,
            v: vec![DVec3::ZERO; n],
            c: vec![DMat3::ZERO; n],
            f: vec![DMat3::IDENTITY; n],
        }
    }

    /// Number of particles.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// `true` when there are no particles.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Checks lengths and finiteness.
    pub fn validate(&self) -> Result<(), MpmError> {
        let n = self.x.len();
        if n == 0 {
            return Err(MpmError::EmptyParticles);
        }
        self.check_len(n)?;
        for i in 0..n {
            check_vec("x", i, self.x[i])?;
            check_vec("v", i, self.v[i])?;
            check_mat("C", i, &self.c[i])?;
            check_mat("F", i, &self.f[i])?;
        }
        Ok(())
    }

    /// Checks that `x`, `v`, `C` and `F` hold `n` particles each.
    pub(crate) fn check_len(&self, n: usize) -> Result<(), MpmError> {
        for (field, len) in [
            ("x", self.x.len()),
            ("v", self.v.len()),
            ("C", self.c.len()),
            ("F", self.f.len()),
        ] {
            if len != n {
                return Err(MpmError::LengthMismatch {
                    field,
                    len,
                    expected: n,
                });
            }
        }
        Ok(())
    }

    /// First non-finite quantity, as `(quantity, particle)`.
    pub fn first_non_finite(&self) -> Option<(&'static str, usize)> {
        for i in 0..self.len() {
            if !self.x[i].is_finite() {
                return Some(("x", i));
            }
            if !self.v[i].is_finite() {
                return Some(("v", i));
            }
            if !mat_finite(&self.c[i]) {
                return Some(("C", i));
            }
            if !mat_finite(&self.f[i]) {
                return Some(("F", i));
            }
        }
        None
    }
}

fn check_vec(field: &'static str, index: usize, v: DVec3) -> Result<(), MpmError> {
    for value in v.to_array() {
        if !value.is_finite() {
            return Err(MpmError::NonFiniteInput {
                field,
                index,
                value,
            });
        }
    }
    Ok(())
}

fn check_mat(field: &'static str, index: usize, m: &DMat3) -> Result<(), MpmError> {
    for value in m.to_cols_array() {
        if !value.is_finite() {
            return Err(MpmError::NonFiniteInput {
                field,
                index,
                value,
            });
        }
    }
    Ok(())
}

/// Per-particle material: mass, volume and the Lamé parameters the models receive.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// Mass (kg).
    pub mass: Vec<f64>,
    /// Initial volume `V_p` (m³).
    pub volume: Vec<f64>,
    /// Shear modulus μ (Pa); Newtonian fluid: dynamic viscosity μ (Pa·s).
    pub mu: Vec<f64>,
    /// Lamé λ (Pa); Newtonian fluid: `κ − 2μ/3` (Pa).
    pub lam: Vec<f64>,
    /// Per-particle family scalars (yield stress, viscosity, friction), so that a learned field
    /// can drive them; empty: every particle takes the model's own
    /// ([`crate::Constitutive::with_params`]).
    pub family: Vec<FamilyParams>,
}

impl Material {
    /// Uniform material from Young's modulus `E` (Pa), Poisson ratio `ν` and density ρ (kg/m³).
    pub fn from_e_nu(
        n: usize,
        volume: f64,
        density: f64,
        e: f64,
        nu: f64,
    ) -> Result<Self, MpmError> {
        let (mu, lam) = lame(e, nu)?;
        check_positive("volume", volume)?;
        check_positive("density", density)?;
        Ok(Self {
            mass: vec![density * volume; n],
            volume: vec![volume; n],
            mu: vec![mu; n],
            lam: vec![lam; n],
            family: Vec::new(),
        })
    }

    /// Per-particle Young's modulus `e` (Pa) and Poisson ratio `nu`, with mass (kg) and
    /// volume (m³) per particle; errors name the particle.
    pub fn from_e_nu_per_particle(
        mass: Vec<f64>,
        volume: Vec<f64>,
        e: &[f64],
        nu: &[f64],
    ) -> Result<Self, MpmError> {
        let n = mass.len();
        for (field, len) in [("volume", volume.len()), ("E", e.len()), ("nu", nu.len())] {
            if len != n {
                return Err(MpmError::LengthMismatch {
                    field,
                    len,
                    expected: n,
                });
            }
        }
        let mut mu = Vec::with_capacity(n);
        let mut lam = Vec::with_capacity(n);
        for i in 0..n {
            let (m, l) = lame(e[i], nu[i]).map_err(|err| err.at_particle(i))?;
            mu.push(m);
            lam.push(l);
        }
        let out = Self {
            mass,
            volume,
            mu,
            lam,
            family: Vec::new(),
        };
        out.validate(n)?;
        Ok(out)
    }

    /// Uniform Newtonian fluid from viscosity μ (Pa·s) and bulk modulus κ (Pa): `λ = κ − 2μ/3`.
    pub fn fluid(
        n: usize,
        volume: f64,
        density: f64,
        viscosity: f64,
        bulk: f64,
    ) -> Result<Self, MpmError> {
        check_non_negative("viscosity", viscosity)?;
        check_positive("bulk modulus", bulk)?;
        check_positive("volume", volume)?;
        check_positive("density", density)?;
        Ok(Self {
            mass: vec![density * volume; n],
            volume: vec![volume; n],
            mu: vec![viscosity; n],
            lam: vec![bulk - 2.0 / 3.0 * viscosity; n],
            family: Vec::new(),
        })
    }

    /// Number of particles.
    pub fn len(&self) -> usize {
        self.mass.len()
    }

    /// `true` when there are no particles.
    pub fn is_empty(&self) -> bool {
        self.mass.is_empty()
    }

    /// Checks lengths against `n`, finiteness, positive mass and volume, `μ ≥ 0`.
    pub fn validate(&self, n: usize) -> Result<(), MpmError> {
        if n == 0 || self.mass.is_empty() {
            return Err(MpmError::EmptyParticles);
        }
        if !self.family.is_empty() && self.family.len() != n {
            return Err(MpmError::LengthMismatch {
                field: "family",
                len: self.family.len(),
                expected: n,
            });
        }
        for (field, len) in [
            ("mass", self.mass.len()),
            ("volume", self.volume.len()),
            ("mu", self.mu.len()),
            ("lam", self.lam.len()),
        ] {
            if len != n {
                return Err(MpmError::LengthMismatch {
                    field,
                    len,
                    expected: n,
                });
            }
        }
        for i in 0..n {
            for (field, value) in [
                ("mass", self.mass[i]),
                ("volume", self.volume[i]),
                ("mu", self.mu[i]),
                ("lam", self.lam[i]),
            ] {
                if !value.is_finite() {
                    return Err(MpmError::NonFiniteInput {
                        field,
                        index: i,
                        value,
                    });
                }
            }
            for (field, value, ok) in [
                ("mass", self.mass[i], self.mass[i] > 0.0),
                ("volume", self.volume[i], self.volume[i] > 0.0),
                ("mu", self.mu[i], self.mu[i] >= 0.0),
            ] {
                if !ok {
                    let reason = if field == "mu" {
                        "must be >= 0"
                    } else {
                        "must be > 0"
                    };
                    return Err(MpmError::InvalidParticleParameter {
                        field,
                        index: i,
                        value,
                        reason,
                    });
                }
            }
        }
        Ok(())
    }
}

fn check_positive(field: &'static str, value: f64) -> Result<(), MpmError> {
    if !value.is_finite() {
        return Err(MpmError::NonFiniteInput {
            field,
            index: 0,
            value,
        });
    }
    if value <= 0.0 {
        return Err(MpmError::InvalidParameter {
            field,
            value,
            reason: "must be > 0",
        });
    }
    Ok(())
}

fn check_non_negative(field: &'static str, value: f64) -> Result<(), MpmError> {
    if !value.is_finite() {
        return Err(MpmError::NonFiniteInput {
            field,
            index: 0,
            value,
        });
    }
    if value < 0.0 {
        return Err(MpmError::InvalidParameter {
            field,
            value,
            reason: "must be >= 0",
        });
    }
    Ok(())
}

/// Lamé parameters from `E` (Pa) and `ν`: `μ = E/(2(1+ν))`, `λ = Eν/((1+ν)(1−2ν))`.
pub fn lame(e: f64, nu: f64) -> Result<(f64, f64), MpmError> {
    check_positive("E", e)?;
    if !nu.is_finite() {
        return Err(MpmError::NonFiniteInput {
            field: "nu",
            index: 0,
            value: nu,
        });
    }
    if nu >= 0.5 || nu <= -1.0 {
        return Err(MpmError::InvalidParameter {
            field: "nu",
            value: nu,
            reason: "Poisson ratio must lie in (-1, 0.5)",
        });
    }
    Ok((
        e / (2.0 * (1.0 + nu)),
        e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
    ))
}

/// Chain rule from `(∂L/∂μ, ∂L/∂λ)` to `(∂L/∂E, ∂L/∂ν)`.
pub fn lame_grad_to_e_nu(e: f64, nu: f64, g_mu: f64, g_lam: f64) -> (f64, f64) {
    let dmu_de = 1.0 / (2.0 * (1.0 + nu));
    let dlam_de = nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    let dmu_dnu = -e / (2.0 * (1.0 + nu) * (1.0 + nu));
    // λ = E ν / ((1+ν)(1−2ν)) = E ν / (1 − ν − 2ν²); dλ/dν = E (1 + 2ν²) / (1 − ν − 2ν²)².
    let den = (1.0 + nu) * (1.0 - 2.0 * nu);
    let dlam_dnu = e * (1.0 + 2.0 * nu * nu) / (den * den);
    (
        g_mu * dmu_de + g_lam * dlam_de,
        g_mu * dmu_dnu + g_lam * dlam_dnu,
    )
}

/// Gradients of a state (same layout as [`State`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StateGrad {
    /// `∂L/∂x` (1/m · units of L).
    pub x: Vec<DVec3>,
    /// `∂L/∂v`.
    pub v: Vec<DVec3>,
    /// `∂L/∂C`.
    pub c: Vec<DMat3>,
    /// `∂L/∂F` (fluid: only the `(0,0)` entry, `∂L/∂J`).
    pub f: Vec<DMat3>,
}

impl StateGrad {
    /// All-zero gradient for `n` particles.
    pub fn zeros(n: usize) -> Self {
        Self {
            x: vec![DVec3::ZERO; n],
            v: vec![DVec3::ZERO; n],
            c: vec![DMat3::ZERO; n],
            f: vec![DMat3::ZERO; n],
        }
    }

    /// Number of particles.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// `true` when empty.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// `true` when every array holds `n` entries.
    pub(crate) fn has_len(&self, n: usize) -> bool {
        self.x.len() == n && self.v.len() == n && self.c.len() == n && self.f.len() == n
    }

    /// First non-finite entry, as `(quantity, particle)` with quantity `"dL/dx"`, `"dL/dv"`,
    /// `"dL/dC"` or `"dL/dF"`.
    pub fn first_non_finite(&self) -> Option<(&'static str, usize)> {
        (0..self.len()).find_map(|i| {
            if !self.x[i].is_finite() {
                Some(("dL/dx", i))
            } else if !self.v[i].is_finite() {
                Some(("dL/dv", i))
            } else if !self.c[i].is_finite() {
                Some(("dL/dC", i))
            } else if !self.f[i].is_finite() {
                Some(("dL/dF", i))
            } else {
                None
            }
        })
    }

    /// `self += other`.
    pub fn add_assign(&mut self, other: &StateGrad) {
        for i in 0..self.len() {
            self.x[i] += other.x[i];
            self.v[i] += other.v[i];
            self.c[i] += other.c[i];
            self.f[i] += other.f[i];
        }
    }
}

/// A particle's family scalars ([`Material::family`]); each model reads its own and ignores the
/// rest.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FamilyParams {
    /// Yield stress τ_Y (Pa), von Mises.
    pub yield_stress: f64,
    /// Perzyna viscosity η (Pa·s), von Mises.
    pub eta: f64,
    /// Friction coefficient α, Drucker–Prager.
    pub friction_alpha: f64,
}

/// Gradients of the family's scalar parameters (zero for parameters a family lacks).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FamilyGrad {
    /// `∂L/∂τ_Y` (per Pa), von Mises.
    pub yield_stress: f64,
    /// `∂L/∂η` (per Pa·s), von Mises.
    pub eta: f64,
    /// `∂L/∂α` (friction coefficient), Drucker–Prager.
    pub friction_alpha: f64,
}

impl std::ops::Add for FamilyGrad {
    type Output = FamilyGrad;

    /// Component-wise sum.
    fn add(self, o: FamilyGrad) -> FamilyGrad {
        FamilyGrad {
            yield_stress: self.yield_stress + o.yield_stress,
            eta: self.eta + o.eta,
            friction_alpha: self.friction_alpha + o.friction_alpha,
        }
    }
}

/// Gradients of the per-particle material and the family parameters.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MaterialGrad {
    /// `∂L/∂m_p` (per kg).
    pub mass: Vec<f64>,
    /// `∂L/∂V_p` (per m³).
    pub volume: Vec<f64>,
    /// `∂L/∂μ_p` (per Pa).
    pub mu: Vec<f64>,
    /// `∂L/∂λ_p` (per Pa).
    pub lam: Vec<f64>,
    /// Family parameters, summed over the particles (the gradient of the model's own scalars).
    pub family: FamilyGrad,
    /// Family parameters per particle (the gradient of [`Material::family`]); empty for models
    /// without family scalars.
    pub family_per_particle: Vec<FamilyGrad>,
}

impl MaterialGrad {
    /// All zero for `n` particles, in place (arrays of the same length keep their memory).
    pub(crate) fn reset(&mut self, n: usize) {
        for v in [
            &mut self.mass,
            &mut self.volume,
            &mut self.mu,
            &mut self.lam,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
        self.family = FamilyGrad::default();
        self.family_per_particle.clear();
    }

    /// All-zero gradient for `n` particles.
    pub fn zeros(n: usize) -> Self {
        let mut g = Self::default();
        g.reset(n);
        g
    }

    /// `(∂L/∂E, ∂L/∂ν)` for a uniform material with the given `E` (Pa), `ν`.
    pub fn e_nu(&self, e: f64, nu: f64) -> (f64, f64) {
        let gm: f64 = self.mu.iter().sum();
        let gl: f64 = self.lam.iter().sum();
        lame_grad_to_e_nu(e, nu, gm, gl)
    }

    /// Per-particle `(∂L/∂E_p, ∂L/∂ν_p)` for per-particle `E` (Pa) and `ν`.
    pub fn e_nu_per_particle(&self, e: &[f64], nu: &[f64]) -> (Vec<f64>, Vec<f64>) {
        (0..self.mu.len())
            .map(|p| lame_grad_to_e_nu(e[p], nu[p], self.mu[p], self.lam[p]))
            .unzip()
    }

    /// Newtonian fluid `(∂L/∂μ, ∂L/∂κ)` with `λ = κ − 2μ/3`: `(Σ(ḡ_μ − 2/3 ḡ_λ), Σ ḡ_λ)`.
    pub fn fluid_mu_kappa(&self) -> (f64, f64) {
        let gm: f64 = self.mu.iter().sum();
        let gl: f64 = self.lam.iter().sum();
        (gm - 2.0 / 3.0 * gl, gl)
    }
}
