//! Runtime choice of the material family with monomorphised simulation inside: match once on
//! [`Family`], then run generic code for the concrete model through a [`ModelVisitor`].

use crate::error::MpmError;
use crate::models::{Constitutive, DruckerPrager, FixedCorotated, NeoHookean, Newtonian, VonMises};

/// A material family and its global parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Family {
    /// PAC-NeRF "elasticity": compressible neo-Hookean.
    NeoHookean,
    /// Fixed-corotated elasticity (PhysGaussian / PhysDreamer).
    FixedCorotated,
    /// Plasticine / non-Newtonian: yield stress τ_Y (Pa), viscosity η (Pa·s).
    VonMises {
        /// τ_Y (Pa).
        yield_stress: f64,
        /// η (Pa·s).
        eta: f64,
    },
    /// Newtonian fluid (μ, κ are per particle in [`crate::Material`]).
    Newtonian,
    /// Sand with friction angle φ (degrees).
    DruckerPrager {
        /// φ (degrees).
        friction_angle_deg: f64,
    },
}

/// Generic code to run with the concrete model of a [`Family`].
pub trait ModelVisitor {
    /// Result type.
    type Output;
    /// Called once with the concrete, monomorphised model.
    fn visit<M: Constitutive + Clone + 'static>(self, model: M) -> Self::Output;
}

impl Family {
    /// Family from a scene's material name: `elastic` / `elasticity`, `fixed_corotated`,
    /// `plasticine` / `non_newtonian` / `von_mises`, `newtonian` / `viscous_fluid`,
    /// `sand` / `drucker_prager`; parameters that the name does not carry start at 0
    /// (friction angle 30°).
    pub fn from_name(name: &str) -> Result<Self, MpmError> {
        Ok(match name {
            "elastic" | "elasticity" | "neo_hookean" => Family::NeoHookean,
            "fixed_corotated" => Family::FixedCorotated,
            "plasticine" | "non_newtonian" | "von_mises" => Family::VonMises {
                yield_stress: 0.0,
                eta: 0.0,
            },
            "newtonian" | "viscous_fluid" => Family::Newtonian,
            "sand" | "drucker_prager" => Family::DruckerPrager {
                friction_angle_deg: 30.0,
            },
            _ => {
                return Err(MpmError::InvalidParameter {
                    field: "material",
                    value: f64::NAN,
                    reason: "unknown family (elastic, fixed_corotated, plasticine, non_newtonian, newtonian, sand)",
                });
            }
        })
    }

    /// Runs `v` with the concrete model (one match; everything inside is monomorphised).
    pub fn visit<V: ModelVisitor>(self, v: V) -> V::Output {
        match self {
            Family::NeoHookean => v.visit(NeoHookean),
            Family::FixedCorotated => v.visit(FixedCorotated),
            Family::VonMises { yield_stress, eta } => v.visit(VonMises { yield_stress, eta }),
            Family::Newtonian => v.visit(Newtonian),
            Family::DruckerPrager { friction_angle_deg } => {
                v.visit(DruckerPrager::from_friction_angle_deg(friction_angle_deg))
            }
        }
    }

    /// Names of the global parameters this family learns besides the per-particle ones.
    pub fn parameter_names(&self) -> &'static [&'static str] {
        match self {
            Family::NeoHookean | Family::FixedCorotated => &[],
            Family::VonMises { .. } => &["yield_stress", "eta"],
            Family::Newtonian => &[],
            Family::DruckerPrager { .. } => &["friction_angle_deg"],
        }
    }
}
