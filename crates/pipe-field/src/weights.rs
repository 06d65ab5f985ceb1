//! A field's weights as named tensors (name, shape, values): the serialisable form for a
//! weights table (`field.*`, ARCHITECTURE §5).
//!
//! Tensors, in order: `plane.xy`, `plane.xz`, `plane.yz` of shape `[R, R, C]` (row `j` along the
//! plane's second axis, column `i` along its first, channel); then per linear layer `l`
//! (input first) `mlp.<l>.weight` of shape `[fan_in, fan_out]` and `mlp.<l>.bias` of shape
//! `[fan_out]`.

use serde::{Deserialize, Serialize};

use crate::config::FieldConfig;
use crate::domain::Domain;
use crate::error::{FieldError, Result, check_finite};
use crate::field::Field;
use crate::mlp::Mlp;
use crate::triplane::PLANE_NAMES;

/// One weight tensor, row-major.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedTensor {
    /// e.g. `plane.xy`, `mlp.0.weight`.
    pub name: String,
    /// Dimensions, outermost first.
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values.
    pub values: Vec<f64>,
}

/// Everything needed to rebuild a [`Field`]: its shape, its box (metres) and its tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldWeights {
    /// Shape of the field.
    pub config: FieldConfig,
    /// Lower corner of the domain, metres.
    pub domain_min: [f64; 3],
    /// Upper corner of the domain, metres.
    pub domain_max: [f64; 3],
    /// The weight tensors, in the order of the module doc.
    pub tensors: Vec<NamedTensor>,
}

/// The tensor names and shapes `config` implies, with their ranges in the plane buffer
/// (`true`) or MLP buffer (`false`).
fn layout(config: &FieldConfig) -> Vec<(String, Vec<usize>, bool, std::ops::Range<usize>)> {
    let (r, c) = (config.resolution, config.channels);
    let plane = r * r * c;
    let mut out: Vec<_> = PLANE_NAMES
        .iter()
        .enumerate()
        .map(|(p, name)| {
            (
                format!("plane.{name}"),
                vec![r, r, c],
                true,
                p * plane..(p + 1) * plane,
            )
        })
        .collect();
    if let Ok(mlp) = Mlp::zeros(
        config.features(),
        config.hidden,
        config.layers,
        config.outputs,
        config.activation,
    ) {
        for (l, (fan_in, fan_out, w, b)) in mlp.layer_ranges().enumerate() {
            out.push((format!("mlp.{l}.weight"), vec![fan_in, fan_out], false, w));
            out.push((format!("mlp.{l}.bias"), vec![fan_out], false, b));
        }
    }
    out
}

impl Field {
    /// The field's weights as named tensors.
    pub fn weights(&self) -> FieldWeights {
        let tensors = layout(self.config())
            .into_iter()
            .map(|(name, shape, plane, range)| {
                let src = if plane {
                    self.triplane().values()
                } else {
                    self.mlp().params()
                };
                NamedTensor {
                    name,
                    shape,
                    values: src[range].to_vec(),
                }
            })
            .collect();
        FieldWeights {
            config: *self.config(),
            domain_min: self.domain().min(),
            domain_max: self.domain().max(),
            tensors,
        }
    }

    /// Rebuild a field from [`Field::weights`]; an error names a bad config or domain, or the
    /// tensor that is missing, misnamed, misshaped or holds a non-finite value.
    pub fn from_weights(weights: &FieldWeights) -> Result<Self> {
        let config = weights.config;
        config.validate()?;
        let domain = Domain::new(weights.domain_min, weights.domain_max)?;
        let (mut triplane, mut mlp) = crate::field::zero_parts(&config)?;
        let expected = layout(&config);
        if weights.tensors.len() != expected.len() {
            return Err(FieldError::Weights {
                tensor: "*".to_owned(),
                reason: format!(
                    "{} tensors, expected {} for this config",
                    weights.tensors.len(),
                    expected.len()
                ),
            });
        }
        for (t, (name, shape, plane, range)) in weights.tensors.iter().zip(expected) {
            if t.name != name {
                return Err(FieldError::Weights {
                    tensor: t.name.clone(),
                    reason: format!("expected tensor `{name}` at this position"),
                });
            }
            if t.shape != shape || t.values.len() != range.len() {
                return Err(FieldError::Weights {
                    tensor: name,
                    reason: format!(
                        "shape {:?} with {} values, expected shape {shape:?} ({} values)",
                        t.shape,
                        t.values.len(),
                        range.len()
                    ),
                });
            }
            check_finite(&name, &t.values)?;
            let dst = if plane {
                triplane.values_mut()
            } else {
                mlp.params_mut()
            };
            dst[range].copy_from_slice(&t.values);
        }
        Ok(Field::from_parts(config, domain, triplane, mlp))
    }
}
