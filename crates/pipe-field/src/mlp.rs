//! A small fully connected network: `layers` hidden layers of width `hidden` with an
//! element-wise activation, then a linear output layer.
//!
//! Layer `l` maps `a_{l−1}` (`a_{−1}` = the input) to `z_l = a_{l−1} W_l + b_l` with `W_l` of
//! shape `[fan_in, fan_out]` (row-major, one row per input) and `a_l = σ(z_l)` on hidden layers;
//! the output is `z_L`. All parameters live in one buffer: `W_0, b_0, W_1, b_1, …`.

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, Result};

/// Element-wise activation of the hidden layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    /// `max(z, 0)` (derivative taken as 0 at `z = 0`; NaN stays NaN).
    #[default]
    Relu,
    /// `ln(1 + eᶻ)`, smooth.
    Softplus,
}

impl Activation {
    #[inline]
    fn value(self, z: f64) -> f64 {
        match self {
            // Not `z.max(0.0)`: that maps NaN to 0 and would hide an overflow upstream.
            Self::Relu => {
                if z < 0.0 {
                    0.0
                } else {
                    z
                }
            }
            // Stable for large |z|: max(z, 0) + ln(1 + e^{−|z|}).
            Self::Softplus => z.max(0.0) + (-z.abs()).exp().ln_1p(),
        }
    }

    #[inline]
    fn derivative(self, z: f64) -> f64 {
        match self {
            Self::Relu => {
                if z > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            // The logistic function, without overflow on either side.
            Self::Softplus => {
                let e = (-z.abs()).exp();
                if z >= 0.0 {
                    1.0 / (1.0 + e)
                } else {
                    e / (1.0 + e)
                }
            }
        }
    }
}

/// Where one layer's weights and biases sit in the parameter buffer.
#[derive(Debug, Clone, Copy, PartialEq)]
struct LayerSpan {
    fan_in: usize,
    fan_out: usize,
    weight: usize,
    bias: usize,
}

/// The network's parameters and shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    inputs: usize,
    hidden: usize,
    layers: usize,
    outputs: usize,
    activation: Activation,
    spans: Vec<LayerSpan>,
    params: Vec<f64>,
}

/// Per-point buffers of a forward/backward pass (one per worker; no allocation per point).
#[derive(Debug, Clone)]
pub struct MlpScratch {
    /// Pre-activations `z_l` of every layer.
    z: Vec<Vec<f64>>,
    /// Activations `a_l` of the hidden layers.
    a: Vec<Vec<f64>>,
    /// `∂L/∂z` of the current layer and `∂L/∂a` of the layer below.
    dz: Vec<f64>,
    da: Vec<f64>,
}

impl Mlp {
    /// A network with zero parameters: `inputs` → `layers` × `hidden` → `outputs`.
    pub fn zeros(
        inputs: usize,
        hidden: usize,
        layers: usize,
        outputs: usize,
        activation: Activation,
    ) -> Result<Self> {
        for (field, value) in [("inputs", inputs), ("outputs", outputs)] {
            if value < 1 {
                return Err(FieldError::Config {
                    field,
                    value: value.to_string(),
                    reason: "must be at least 1",
                });
            }
        }
        if layers > 0 && hidden < 1 {
            return Err(FieldError::Config {
                field: "hidden",
                value: hidden.to_string(),
                reason: "must be at least 1 when layers > 0",
            });
        }
        let mut widths = vec![inputs];
        widths.extend(std::iter::repeat_n(hidden, layers));
        widths.push(outputs);
        let mut spans = Vec::with_capacity(layers + 1);
        let mut at = 0;
        for w in widths.windows(2) {
            let (fan_in, fan_out) = (w[0], w[1]);
            spans.push(LayerSpan {
                fan_in,
                fan_out,
                weight: at,
                bias: at + fan_in * fan_out,
            });
            at += fan_in * fan_out + fan_out;
        }
        Ok(Self {
            inputs,
            hidden,
            layers,
            outputs,
            activation,
            spans,
            params: vec![0.0; at],
        })
    }

    /// He-uniform weights on hidden layers (`U(±√(6/fan_in))`), LeCun-uniform on the output
    /// layer (`U(±√(3/fan_in))`), zero biases.
    pub(crate) fn randomise(&mut self, rng: &mut impl Rng) {
        let last = self.spans.len() - 1;
        for (l, s) in self.spans.clone().into_iter().enumerate() {
            let gain = if l == last { 3.0 } else { 6.0 };
            let bound = (gain / s.fan_in as f64).sqrt();
            for w in &mut self.params[s.weight..s.bias] {
                *w = bound * (2.0 * rng.random::<f64>() - 1.0);
            }
            self.params[s.bias..s.bias + s.fan_out].fill(0.0);
        }
    }

    /// Zero the output layer's weights and set its bias to `value`, so the network outputs
    /// `value` exactly at every input.
    pub(crate) fn set_constant_output(&mut self, value: &[f64]) {
        let s = self.spans[self.spans.len() - 1];
        self.params[s.weight..s.bias].fill(0.0);
        self.params[s.bias..s.bias + s.fan_out].copy_from_slice(value);
    }

    /// Input width.
    pub fn inputs(&self) -> usize {
        self.inputs
    }

    /// Hidden width.
    pub fn hidden(&self) -> usize {
        self.hidden
    }

    /// Number of hidden layers.
    pub fn layers(&self) -> usize {
        self.layers
    }

    /// Output width.
    pub fn outputs(&self) -> usize {
        self.outputs
    }

    /// Hidden activation.
    pub fn activation(&self) -> Activation {
        self.activation
    }

    /// All parameters: `W_0, b_0, W_1, b_1, …` (`W_l` row-major `[fan_in, fan_out]`).
    pub fn params(&self) -> &[f64] {
        &self.params
    }

    /// Mutable view of [`Mlp::params`].
    pub fn params_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }

    /// `(fan_in, fan_out, weight range, bias range)` of each linear layer, input first.
    pub fn layer_ranges(
        &self,
    ) -> impl Iterator<Item = (usize, usize, std::ops::Range<usize>, std::ops::Range<usize>)> + '_
    {
        self.spans.iter().map(|s| {
            (
                s.fan_in,
                s.fan_out,
                s.weight..s.bias,
                s.bias..s.bias + s.fan_out,
            )
        })
    }

    /// Buffers for [`Mlp::forward`] / [`Mlp::backward`].
    pub fn scratch(&self) -> MlpScratch {
        let widest = self.spans.iter().map(|s| s.fan_in.max(s.fan_out)).max();
        let widest = widest.unwrap_or(self.inputs);
        MlpScratch {
            z: self.spans.iter().map(|s| vec![0.0; s.fan_out]).collect(),
            a: self.spans[..self.layers]
                .iter()
                .map(|s| vec![0.0; s.fan_out])
                .collect(),
            dz: vec![0.0; widest],
            da: vec![0.0; widest],
        }
    }

    /// Output for one input vector into `out`; keeps the activations in `scratch` for
    /// [`Mlp::backward`].
    #[inline]
    pub fn forward(&self, input: &[f64], scratch: &mut MlpScratch, out: &mut [f64]) {
        debug_assert_eq!(input.len(), self.inputs);
        debug_assert_eq!(out.len(), self.outputs);
        let MlpScratch { z, a, .. } = scratch;
        for (l, s) in self.spans.iter().enumerate() {
            let prev: &[f64] = if l == 0 { input } else { &a[l - 1] };
            let zl = &mut z[l];
            zl.copy_from_slice(&self.params[s.bias..s.bias + s.fan_out]);
            let w = &self.params[s.weight..s.bias];
            for (x, row) in prev.iter().zip(w.chunks_exact(s.fan_out)) {
                // Inactive ReLU units add nothing (skipping them is exact).
                if *x == 0.0 {
                    continue;
                }
                for (zo, wo) in zl.iter_mut().zip(row) {
                    *zo += x * wo;
                }
            }
            if l < self.layers {
                for (ao, zo) in a[l].iter_mut().zip(zl.iter()) {
                    *ao = self.activation.value(*zo);
                }
            }
        }
        out.copy_from_slice(&z[self.spans.len() - 1]);
    }

    /// Adjoint of the [`Mlp::forward`] call that filled `scratch` (same `input`): adds
    /// `∂L/∂params` into `grad` (layout of [`Mlp::params`]) and writes `∂L/∂input` into
    /// `d_input`, given `d_out = ∂L/∂output`.
    #[inline]
    pub fn backward(
        &self,
        input: &[f64],
        scratch: &mut MlpScratch,
        d_out: &[f64],
        grad: &mut [f64],
        d_input: &mut [f64],
    ) {
        debug_assert_eq!(d_out.len(), self.outputs);
        debug_assert_eq!(grad.len(), self.params.len());
        debug_assert_eq!(d_input.len(), self.inputs);
        let MlpScratch { z, a, dz, da } = scratch;
        dz[..self.outputs].copy_from_slice(d_out);
        for (l, s) in self.spans.iter().enumerate().rev() {
            let prev: &[f64] = if l == 0 { input } else { &a[l - 1] };
            let dzl = &dz[..s.fan_out];
            for (gb, d) in grad[s.bias..s.bias + s.fan_out].iter_mut().zip(dzl) {
                *gb += d;
            }
            let w = &self.params[s.weight..s.bias];
            let gw = &mut grad[s.weight..s.bias];
            let d_prev = if l == 0 {
                &mut d_input[..]
            } else {
                &mut da[..s.fan_in]
            };
            for (((x, row), grow), dp) in prev
                .iter()
                .zip(w.chunks_exact(s.fan_out))
                .zip(gw.chunks_exact_mut(s.fan_out))
                .zip(d_prev.iter_mut())
            {
                if *x != 0.0 {
                    for (g, d) in grow.iter_mut().zip(dzl) {
                        *g += x * d;
                    }
                }
                *dp = dot(row, dzl);
            }
            if l > 0 {
                for ((dzo, dao), zo) in dz.iter_mut().zip(da.iter()).zip(&z[l - 1]) {
                    *dzo = dao * self.activation.derivative(*zo);
                }
            }
        }
    }
}

/// `Σ a_k b_k` with four interleaved partial sums (fixed order: deterministic, and free of the
/// serial dependency that keeps a single-accumulator loop from pipelining).
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    let mut acc = [0.0f64; 4];
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}
