//! Adam (Kingma & Ba 2015) over parameter groups, each with its own learning-rate schedule.

use serde::{Deserialize, Serialize};

use crate::error::{FieldError, Result, check_len};
use crate::field::{Field, FieldGradient};

/// Exponential decay from `lr` to `lr_final` over `steps` steps (constant after):
/// `lr(k) = lr · (lr_final/lr)^(min(k, steps−1)/(steps−1))` at 0-based step `k`, so the first
/// step uses `lr` and step `steps−1` uses `lr_final`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LrSchedule {
    /// Rate of the first step (units of the parameter per step).
    pub lr: f64,
    /// Rate from step `steps − 1` on.
    pub lr_final: f64,
    /// Length of the decay, steps (≥ 1).
    pub steps: u32,
}

impl LrSchedule {
    /// The same rate at every step.
    pub fn constant(lr: f64) -> Self {
        Self {
            lr,
            lr_final: lr,
            steps: 1,
        }
    }

    /// Exponential decay from `lr` to `lr_final` over `steps` steps.
    pub fn exponential(lr: f64, lr_final: f64, steps: u32) -> Self {
        Self {
            lr,
            lr_final,
            steps,
        }
    }

    /// An error naming `field` when a rate is not finite and > 0 or `steps` is 0.
    pub fn validate(&self, field: &'static str) -> Result<()> {
        for value in [self.lr, self.lr_final] {
            if !(value.is_finite() && value > 0.0) {
                return Err(FieldError::Config {
                    field,
                    value: value.to_string(),
                    reason: "learning rates must be finite and > 0",
                });
            }
        }
        if self.steps == 0 {
            return Err(FieldError::Config {
                field,
                value: "steps = 0".to_owned(),
                reason: "a schedule lasts at least 1 step",
            });
        }
        Ok(())
    }

    /// Rate at 0-based step `k`.
    pub fn at(&self, k: u32) -> f64 {
        if self.steps <= 1 {
            return if k == 0 { self.lr } else { self.lr_final };
        }
        let t = f64::from(k.min(self.steps - 1)) / f64::from(self.steps - 1);
        self.lr * (self.lr_final / self.lr).powf(t)
    }
}

/// Adam hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdamConfig {
    /// Decay of the first moment, in [0, 1).
    pub beta1: f64,
    /// Decay of the second moment, in [0, 1).
    pub beta2: f64,
    /// Denominator guard (> 0).
    pub eps: f64,
}

impl Default for AdamConfig {
    /// β₁ = 0.9, β₂ = 0.999, ε = 1e-15 (the 3DGS / K-planes choice).
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

impl AdamConfig {
    /// An error naming the first out-of-range value.
    pub fn validate(&self) -> Result<()> {
        for (field, value) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&value) {
                return Err(FieldError::Config {
                    field,
                    value: value.to_string(),
                    reason: "must be in [0, 1)",
                });
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(FieldError::Config {
                field: "eps",
                value: self.eps.to_string(),
                reason: "must be finite and > 0",
            });
        }
        Ok(())
    }
}

/// One group of parameters optimised with its own schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamGroup {
    /// Name used in errors (e.g. `planes`).
    pub name: &'static str,
    /// Number of parameters.
    pub len: usize,
    /// Learning-rate schedule.
    pub schedule: LrSchedule,
}

/// Adam state over several parameter groups.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    config: AdamConfig,
    groups: Vec<ParamGroup>,
    m: Vec<Vec<f64>>,
    v: Vec<Vec<f64>>,
    steps: u32,
}

impl Adam {
    /// Zero moments for `groups`; an error names a bad hyper-parameter or schedule.
    pub fn new(config: AdamConfig, groups: Vec<ParamGroup>) -> Result<Self> {
        config.validate()?;
        for g in &groups {
            g.schedule.validate(g.name)?;
        }
        Ok(Self {
            config,
            m: groups.iter().map(|g| vec![0.0; g.len]).collect(),
            v: groups.iter().map(|g| vec![0.0; g.len]).collect(),
            groups,
            steps: 0,
        })
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// The groups, in order.
    pub fn groups(&self) -> &[ParamGroup] {
        &self.groups
    }

    /// Rate the next step applies to group `g`.
    pub fn lr(&self, g: usize) -> f64 {
        self.groups[g].schedule.at(self.steps)
    }

    /// One step: per value, `m ← β₁m + (1−β₁)g`, `v ← β₂v + (1−β₂)g²`,
    /// `p ← p − lr_k · m̂ / (√v̂ + ε)` with bias-corrected `m̂ = m/(1−β₁ᵗ)`, `v̂ = v/(1−β₂ᵗ)`.
    /// `params[i]` and `grads[i]` belong to group `i`. A count or length mismatch or a
    /// non-finite gradient is an error naming the group, and nothing is changed.
    pub fn step(&mut self, params: &mut [&mut [f64]], grads: &[&[f64]]) -> Result<()> {
        check_len("parameter groups", self.groups.len(), params.len())?;
        check_len("gradient groups", self.groups.len(), grads.len())?;
        for ((g, p), d) in self.groups.iter().zip(params.iter()).zip(grads) {
            if p.len() != g.len || d.len() != g.len {
                return Err(FieldError::Length {
                    field: g.name,
                    expected: g.len,
                    got: if p.len() != g.len { p.len() } else { d.len() },
                });
            }
            if let Some(index) = d.iter().position(|v| !v.is_finite()) {
                return Err(FieldError::NotFinite {
                    field: format!("gradient of {}", g.name),
                    index,
                    value: d[index],
                });
            }
        }
        let AdamConfig { beta1, beta2, eps } = self.config;
        let t = self.steps + 1;
        let bc1 = 1.0 - beta1.powf(f64::from(t));
        let bc2 = 1.0 - beta2.powf(f64::from(t));
        for (i, (p, d)) in params.iter_mut().zip(grads).enumerate() {
            let lr = self.groups[i].schedule.at(self.steps);
            for (((p, g), m), v) in p
                .iter_mut()
                .zip(d.iter())
                .zip(&mut self.m[i])
                .zip(&mut self.v[i])
            {
                *m = beta1 * *m + (1.0 - beta1) * g;
                *v = beta2 * *v + (1.0 - beta2) * g * g;
                *p -= lr * (*m / bc1) / ((*v / bc2).sqrt() + eps);
            }
        }
        self.steps = t;
        Ok(())
    }
}

/// Adam over a [`Field`]'s two groups: `planes` (plane features) and `mlp` (weights and
/// biases), each with its own schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldAdam {
    adam: Adam,
}

impl FieldAdam {
    /// Zero moments for `field`'s weights.
    pub fn new(
        field: &Field,
        planes: LrSchedule,
        mlp: LrSchedule,
        config: AdamConfig,
    ) -> Result<Self> {
        let groups = vec![
            ParamGroup {
                name: "planes",
                len: field.triplane().values().len(),
                schedule: planes,
            },
            ParamGroup {
                name: "mlp",
                len: field.mlp().params().len(),
                schedule: mlp,
            },
        ];
        Ok(Self {
            adam: Adam::new(config, groups)?,
        })
    }

    /// One Adam step on `field` with `grad` (e.g. [`Field::backward`] plus
    /// [`Field::tv_backward`]).
    pub fn step(&mut self, field: &mut Field, grad: &FieldGradient) -> Result<()> {
        let (planes, mlp) = field.params_mut();
        self.adam
            .step(&mut [planes, mlp], &[&grad.planes, &grad.mlp])
    }

    /// The underlying optimiser (step count, current rates).
    pub fn adam(&self) -> &Adam {
        &self.adam
    }
}
