//! Shape and initialisation of a field.

use serde::{Deserialize, Serialize};

use crate::error::{FieldError, Result};
use crate::mlp::Activation;
use crate::triplane::Combine;

/// Shape of a [`crate::Field`]: triplane, MLP, regulariser weight and initialisation scale.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldConfig {
    /// Nodes per plane side `R` (≥ 2).
    pub resolution: usize,
    /// Feature channels per node `C` (≥ 1).
    pub channels: usize,
    /// How the three plane features are combined.
    pub combine: Combine,
    /// Width of the hidden layers.
    pub hidden: usize,
    /// Number of hidden layers (0: the output is linear in the features).
    pub layers: usize,
    /// Hidden activation.
    pub activation: Activation,
    /// Numbers per point the field outputs (e.g. 2: log10 E and encoded ν).
    pub outputs: usize,
    /// Weight `w` of the plane total variation (eq. 8, see [`crate::Triplane::tv`]).
    pub tv_weight: f64,
    /// Plane features start uniform in `[−plane_init, plane_init]`.
    pub plane_init: f64,
}

impl FieldConfig {
    /// The seed paper's material field: 24 × 24 planes. Our choices where the paper gives no
    /// value here: 16 channels summed, 2 hidden layers of 64 ReLU, TV weight 1e-3, plane
    /// features initialised in ±0.1.
    pub fn material(outputs: usize) -> Self {
        Self {
            resolution: 24,
            channels: 16,
            combine: Combine::Sum,
            hidden: 64,
            layers: 2,
            activation: Activation::Relu,
            outputs,
            tv_weight: 1e-3,
            plane_init: 0.1,
        }
    }

    /// The seed paper's velocity field: 8 × 8 planes, otherwise as [`FieldConfig::material`].
    pub fn velocity(outputs: usize) -> Self {
        Self {
            resolution: 8,
            ..Self::material(outputs)
        }
    }

    /// An error naming the first out-of-range value.
    pub fn validate(&self) -> Result<()> {
        let bad = |field, value: String, reason| {
            Err(FieldError::Config {
                field,
                value,
                reason,
            })
        };
        if self.resolution < 2 {
            return bad(
                "resolution",
                self.resolution.to_string(),
                "a plane needs at least 2 nodes per side",
            );
        }
        if self.channels < 1 {
            return bad("channels", self.channels.to_string(), "must be at least 1");
        }
        if self.layers > 0 && self.hidden < 1 {
            return bad(
                "hidden",
                self.hidden.to_string(),
                "must be at least 1 when layers > 0",
            );
        }
        if self.outputs < 1 {
            return bad("outputs", self.outputs.to_string(), "must be at least 1");
        }
        if !(self.tv_weight.is_finite() && self.tv_weight >= 0.0) {
            return bad(
                "tv_weight",
                self.tv_weight.to_string(),
                "must be finite and >= 0",
            );
        }
        if !(self.plane_init.is_finite() && self.plane_init >= 0.0) {
            return bad(
                "plane_init",
                self.plane_init.to_string(),
                "must be finite and >= 0",
            );
        }
        Ok(())
    }

    /// Length of the MLP input: `C` (sum) or `3C` (concat).
    pub fn features(&self) -> usize {
        match self.combine {
            Combine::Sum => self.channels,
            Combine::Concat => 3 * self.channels,
        }
    }
}
