//! The material parameters a stage learns, in the unconstrained coordinates the optimiser
//! steps: `log10` of the moduli, yield stress and viscosities (a 10× error is one unit
//! whatever the scale), Poisson's ratio through `ν = 0.49·σ(u)` (so it stays in (0, 0.49)),
//! the friction angle through `φ = 80°·σ(u)`.
//!
//! Only the parameters of the scene's declared family exist ([`Param::of_family`]); `learn:`
//! picks among them, the others stay at their guess.

use std::collections::BTreeMap;

use pipe_mpm::{DruckerPrager, MaterialGrad};
use serde::{Deserialize, Serialize};

use crate::pipeline::spec::MaterialFamily;
use crate::simulate::spec::MaterialSpec;

/// A material parameter.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Serialize,
    Deserialize,
    schemars::JsonSchema,
)]
pub enum Param {
    /// Young's modulus E (Pa).
    #[serde(rename = "E")]
    E,
    /// Poisson's ratio ν.
    #[serde(rename = "nu")]
    Nu,
    /// Yield stress τ_Y (Pa): plasticine, non_newtonian.
    #[serde(rename = "yield_stress")]
    YieldStress,
    /// Viscosity (Pa·s): the plastic flow's η (plasticine, non_newtonian), the fluid's μ
    /// (newtonian).
    #[serde(rename = "viscosity")]
    Viscosity,
    /// Bulk modulus κ (Pa): newtonian.
    #[serde(rename = "bulk_modulus")]
    BulkModulus,
    /// Friction angle φ (degrees): sand.
    #[serde(rename = "friction_angle")]
    FrictionAngle,
}

/// Upper bound of Poisson's ratio's map.
pub const NU_MAX: f64 = 0.49;
/// Upper bound of the friction angle's map (degrees).
pub const FRICTION_MAX_DEG: f64 = 80.0;

fn sigmoid(u: f64) -> f64 {
    1.0 / (1.0 + (-u).exp())
}

fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

impl Param {
    /// Every parameter, in a fixed order.
    pub const ALL: [Param; 6] = [
        Param::E,
        Param::Nu,
        Param::YieldStress,
        Param::Viscosity,
        Param::BulkModulus,
        Param::FrictionAngle,
    ];

    /// The name used in pipeline files, tables and reports.
    pub fn name(self) -> &'static str {
        match self {
            Param::E => "E",
            Param::Nu => "nu",
            Param::YieldStress => "yield_stress",
            Param::Viscosity => "viscosity",
            Param::BulkModulus => "bulk_modulus",
            Param::FrictionAngle => "friction_angle",
        }
    }

    /// The parameter named `name` ([`Param::name`]).
    pub fn from_name(name: &str) -> Option<Param> {
        Param::ALL.into_iter().find(|p| p.name() == name)
    }

    /// Unit of the value, for reports.
    pub fn unit(self) -> &'static str {
        match self {
            Param::E | Param::YieldStress | Param::BulkModulus => "Pa",
            Param::Nu => "",
            Param::Viscosity => "Pa s",
            Param::FrictionAngle => "deg",
        }
    }

    /// The parameters a family has.
    pub fn of_family(family: MaterialFamily) -> &'static [Param] {
        use MaterialFamily as F;
        match family {
            F::Elastic | F::ElasticFcr => &[Param::E, Param::Nu],
            F::Plasticine | F::NonNewtonian => {
                &[Param::E, Param::Nu, Param::YieldStress, Param::Viscosity]
            }
            F::Newtonian => &[Param::Viscosity, Param::BulkModulus],
            F::Sand => &[Param::E, Param::Nu, Param::FrictionAngle],
        }
    }

    /// What the `material` stage learns of a family unless `learn:` says otherwise.
    pub fn learned_by_default(family: MaterialFamily) -> &'static [Param] {
        use MaterialFamily as F;
        match family {
            F::Elastic | F::ElasticFcr => &[Param::E, Param::Nu],
            // PAC-NeRF's plasticine has no viscosity (η = 0); `learn:` adds it.
            F::Plasticine => &[Param::E, Param::Nu, Param::YieldStress],
            F::NonNewtonian => &[Param::E, Param::Nu, Param::YieldStress, Param::Viscosity],
            F::Newtonian => &[Param::Viscosity, Param::BulkModulus],
            // PAC-NeRF's sand configurations hold E = 1e6 Pa, ν = 0.3.
            F::Sand => &[Param::FrictionAngle],
        }
    }

    /// The default guess of a family's parameter.
    pub fn default_guess(self, family: MaterialFamily) -> f64 {
        match (self, family) {
            (Param::E, MaterialFamily::Sand) => 1e6,
            (Param::E, _) => 1e5,
            (Param::Nu, _) => 0.3,
            (Param::YieldStress, _) => 1e3,
            (Param::Viscosity, MaterialFamily::Plasticine) => 0.0,
            (Param::Viscosity, _) => 10.0,
            (Param::BulkModulus, _) => 1e5,
            (Param::FrictionAngle, _) => 30.0,
        }
    }

    /// Whether the optimiser steps it in decades (`log10`): the moduli, yield stress and
    /// viscosities, not the bounded ratios.
    pub fn log_scaled(self) -> bool {
        !matches!(self, Param::Nu | Param::FrictionAngle)
    }

    /// The optimiser's coordinate of a value.
    pub fn encode(self, value: f64) -> f64 {
        match self {
            Param::Nu => logit(value / NU_MAX),
            Param::FrictionAngle => logit(value / FRICTION_MAX_DEG),
            _ => value.log10(),
        }
    }

    /// The value of an optimiser coordinate.
    pub fn decode(self, u: f64) -> f64 {
        match self {
            Param::Nu => NU_MAX * sigmoid(u),
            Param::FrictionAngle => FRICTION_MAX_DEG * sigmoid(u),
            _ => 10f64.powf(u),
        }
    }

    /// `d value / d u` at `u`.
    pub fn dvalue_du(self, u: f64) -> f64 {
        match self {
            Param::Nu | Param::FrictionAngle => {
                let max = if self == Param::Nu {
                    NU_MAX
                } else {
                    FRICTION_MAX_DEG
                };
                let s = sigmoid(u);
                max * s * (1.0 - s)
            }
            _ => 10f64.powf(u) * std::f64::consts::LN_10,
        }
    }

    /// Whether a value is one the encoding can hold (`learn:` of a value outside it is an
    /// error naming the value).
    pub fn encodable(self, value: f64) -> bool {
        match self {
            Param::Nu => value > 0.0 && value < NU_MAX,
            Param::FrictionAngle => value > 0.0 && value < FRICTION_MAX_DEG,
            _ => value.is_finite() && value > 0.0,
        }
    }
}

/// One material: a family and a value for each of its parameters, with the density.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaterialValues {
    /// The family.
    pub family: MaterialFamily,
    /// Density ρ (kg/m³).
    pub density: f64,
    /// Every parameter of the family.
    pub values: BTreeMap<Param, f64>,
}

impl MaterialValues {
    /// The family's default guesses, overridden by `guess`.
    pub fn guess(family: MaterialFamily, density: f64, guess: &BTreeMap<Param, f64>) -> Self {
        let values = Param::of_family(family)
            .iter()
            .map(|&p| (p, guess.get(&p).copied().unwrap_or(p.default_guess(family))))
            .collect();
        Self {
            family,
            density,
            values,
        }
    }

    /// The value of `p` (`None` when the family has no such parameter).
    pub fn get(&self, p: Param) -> Option<f64> {
        self.values.get(&p).copied()
    }

    /// As the simulation file's `material:` section.
    pub fn spec(&self) -> MaterialSpec {
        let fam = self.family;
        let solid = !matches!(fam, MaterialFamily::Newtonian);
        MaterialSpec {
            family: fam,
            density: self.density,
            youngs_modulus: solid.then(|| self.get(Param::E)).flatten(),
            poisson_ratio: solid.then(|| self.get(Param::Nu)).flatten(),
            yield_stress: self.get(Param::YieldStress),
            viscosity: self.get(Param::Viscosity),
            bulk_modulus: self.get(Param::BulkModulus),
            friction_angle_deg: self.get(Param::FrictionAngle),
        }
    }

    /// `∂L/∂value` of every parameter of the family from a backward pass's material
    /// gradients (a uniform material: per-particle gradients summed).
    pub fn gradient(&self, g: &MaterialGrad) -> BTreeMap<Param, f64> {
        let mut out = BTreeMap::new();
        match self.family {
            MaterialFamily::Newtonian => {
                let (gm, gk) = g.fluid_mu_kappa();
                out.insert(Param::Viscosity, gm);
                out.insert(Param::BulkModulus, gk);
            }
            _ => {
                let (e, nu) = (
                    self.get(Param::E).unwrap_or(0.0),
                    self.get(Param::Nu).unwrap_or(0.0),
                );
                let (ge, gnu) = g.e_nu(e, nu);
                out.insert(Param::E, ge);
                out.insert(Param::Nu, gnu);
            }
        }
        match self.family {
            MaterialFamily::Plasticine | MaterialFamily::NonNewtonian => {
                out.insert(Param::YieldStress, g.family.yield_stress);
                out.insert(Param::Viscosity, g.family.eta);
            }
            MaterialFamily::Sand => {
                let phi = self.get(Param::FrictionAngle).unwrap_or(30.0);
                out.insert(
                    Param::FrictionAngle,
                    g.family.friction_alpha * DruckerPrager::dalpha_dphi_deg(phi),
                );
            }
            _ => {}
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodings_round_trip_and_their_derivatives_match_differences() {
        for (p, v) in [
            (Param::E, 3.7e5),
            (Param::Nu, 0.31),
            (Param::FrictionAngle, 33.0),
            (Param::Viscosity, 0.2),
        ] {
            let u = p.encode(v);
            assert!((p.decode(u) - v).abs() <= 1e-12 * v, "{p:?}");
            let h = 1e-6;
            let fd = (p.decode(u + h) - p.decode(u - h)) / (2.0 * h);
            assert!((fd - p.dvalue_du(u)).abs() <= 1e-6 * fd.abs(), "{p:?}");
        }
        assert!(Param::Nu.decode(50.0) <= NU_MAX && Param::Nu.decode(-50.0) > 0.0);
        assert!(Param::Nu.decode(20.0) < NU_MAX);
        assert!(!Param::Nu.encodable(0.5) && !Param::E.encodable(0.0));
    }

    #[test]
    fn each_family_has_its_own_parameters() {
        let fluid = MaterialValues::guess(MaterialFamily::Newtonian, 1000.0, &BTreeMap::new());
        assert_eq!(
            fluid.values.keys().copied().collect::<Vec<_>>(),
            vec![Param::Viscosity, Param::BulkModulus]
        );
        let spec = fluid.spec();
        assert!(spec.youngs_modulus.is_none() && spec.viscosity == Some(10.0));
        let guess = BTreeMap::from([(Param::E, 2e6)]);
        let solid = MaterialValues::guess(MaterialFamily::Elastic, 1000.0, &guess);
        assert_eq!(solid.get(Param::E), Some(2e6));
        assert_eq!(solid.get(Param::YieldStress), None);
    }
}
