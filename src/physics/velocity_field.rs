//! The initial velocity as a field (the seed paper's §3.2: a triplane + MLP over the object,
//! 8³ planes): each particle moves at the rigid motion learned first plus the field's residual
//! (m/s) at its rest position, so parts of an object that move apart at the start (a bent
//! flap, a spinning part) are explained. The field starts at zero residual: exactly the rigid
//! motion it refines. Like the material field, it is a function of space, so any particle set
//! of the object (another stage's grid, an edit's) can ask it.

use std::path::Path;

use glam::DVec3;
use pipe_field::{Field, FieldConfig, FieldError, FieldGradient};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::fit::RigidVelocity;
use super::material_field::{FieldTable, MARGIN, read_field};
use super::object::Object;
use crate::scene::table::{self, TableError};

/// The weights' file in the `velocity` entry.
pub const WEIGHTS_FILE: &str = "field.velocity.arrow";

/// The outputs' names in the weights' table.
pub const OUTPUTS: [&str; 3] = ["vx", "vy", "vz"];

/// Settings of `velocity: {model: field}` (the `field:` block of the stage).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct VelocityFieldSettings {
    /// Nodes per plane side (the paper: 8).
    #[serde(default = "resolution")]
    pub resolution: usize,
    /// Feature channels per plane node.
    #[serde(default = "channels")]
    pub channels: usize,
    /// Width and count of the MLP's hidden layers.
    #[serde(default = "hidden")]
    pub hidden: usize,
    #[serde(default = "layers")]
    pub layers: usize,
    /// Weight of the planes' total variation (eq. 8).
    #[serde(default = "tv_weight")]
    pub tv_weight: f64,
    /// Epochs of the field after the rigid fit (default: the stage's `epochs`).
    #[serde(default)]
    pub epochs: Option<u32>,
    /// Adam's first and last step (the step's length is then searched on the loss).
    #[serde(default = "lr")]
    pub lr: f64,
    #[serde(default = "lr_final")]
    pub lr_final: f64,
    /// Seed of the initial weights.
    #[serde(default)]
    pub seed: u64,
}

fn resolution() -> usize {
    8
}
fn channels() -> usize {
    8
}
fn hidden() -> usize {
    32
}
fn layers() -> usize {
    2
}
fn tv_weight() -> f64 {
    1e-3
}
fn lr() -> f64 {
    0.005
}
fn lr_final() -> f64 {
    0.0005
}

impl Default for VelocityFieldSettings {
    fn default() -> Self {
        Self {
            resolution: resolution(),
            channels: channels(),
            hidden: hidden(),
            layers: layers(),
            tv_weight: tv_weight(),
            epochs: None,
            lr: lr(),
            lr_final: lr_final(),
            seed: 0,
        }
    }
}

impl VelocityFieldSettings {
    /// The field's configuration (3 outputs, m/s).
    pub fn config(&self) -> FieldConfig {
        FieldConfig {
            resolution: self.resolution,
            channels: self.channels,
            hidden: self.hidden,
            layers: self.layers,
            tv_weight: self.tv_weight,
            ..FieldConfig::material(3)
        }
    }
}

/// The residual field at a set of rest positions.
#[derive(Debug, Clone, PartialEq)]
pub struct VelocityField {
    /// The triplane + MLP (3 outputs, m/s).
    pub field: Field,
    /// Rest positions it is evaluated at (m).
    pub points: Vec<[f64; 3]>,
}

impl VelocityField {
    /// A zero residual over `points` (rest positions, m), its box grown by [`MARGIN`].
    ///
    /// # Errors
    /// A degenerate box or a bad setting, named.
    pub fn zero(
        settings: &VelocityFieldSettings,
        points: Vec<[f64; 3]>,
    ) -> Result<Self, FieldError> {
        let extent = super::material_field::largest_extent(&points);
        let domain = pipe_field::Domain::around(&points, MARGIN * extent)?;
        let field =
            Field::with_constant_output(&settings.config(), domain, settings.seed, &[0.0; 3])?;
        Ok(Self { field, points })
    }

    /// The residual velocity of every point (m/s).
    ///
    /// # Errors
    /// A non-finite output, named.
    pub fn residual(&self) -> Result<Vec<DVec3>, FieldError> {
        let y = self.field.forward(&self.points)?;
        Ok(y.chunks_exact(3)
            .map(|c| DVec3::new(c[0], c[1], c[2]))
            .collect())
    }

    /// The weights' gradient from `∂L/∂v0` of every point.
    ///
    /// # Errors
    /// A length mismatch or a non-finite value, named.
    pub fn backward(&self, grad_v0: &[DVec3]) -> Result<FieldGradient, FieldError> {
        let d: Vec<f64> = grad_v0.iter().flat_map(|g| g.to_array()).collect();
        self.field.backward(&self.points, &d)
    }
}

/// Writes the field's weights to `path` (atomically).
pub fn write_weights(path: &Path, field: &VelocityField) -> Result<(), TableError> {
    table::write(
        path,
        &FieldTable {
            weights: field.field.weights(),
            outputs: OUTPUTS.iter().map(|s| s.to_string()).collect(),
            log10_e_centre: None,
            parts: None,
        },
    )
}

/// The initial velocity of every particle of `object` (m/s): `rigid`, plus the residual of
/// the field written at `field` when there is one.
///
/// # Errors
/// An unreadable or inconsistent weights' table, or a non-finite residual, named.
pub fn initial_velocities(
    object: &Object,
    rigid: &RigidVelocity,
    field: Option<&Path>,
) -> Result<Vec<DVec3>, String> {
    let mut v = rigid.field(object);
    if let Some(path) = field {
        let (f, table) = read_field(path)?;
        let names = table.outputs;
        if names != OUTPUTS {
            return Err(format!(
                "{}: outputs {names:?}, expected a velocity field's {OUTPUTS:?}",
                path.display()
            ));
        }
        let residual = VelocityField {
            field: f,
            points: object.body.state.x.iter().map(|x| x.to_array()).collect(),
        }
        .residual()
        .map_err(|e| format!("{}: {e}", path.display()))?;
        for (v, r) in v.iter_mut().zip(residual) {
            *v += r;
        }
    }
    Ok(v)
}
