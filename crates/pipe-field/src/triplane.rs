//! Three axis-aligned feature planes over the domain, sampled bilinearly (paper §3.2).
//!
//! Plane `p` ∈ {XY, XZ, YZ} spans the normalised axes `(a, b)` ∈ {(x, y), (x, z), (y, z)} and
//! holds `R × R` nodes of `C` channels; node `(i, j)` sits at `u_a = i/(R−1)`, `u_b = j/(R−1)`,
//! so the box's faces lie on the outer nodes. With `s = u_a (R−1) = i + f_s` and
//! `t = u_b (R−1) = j + f_t` (`0 ≤ f < 1`, except `f = 1` on the upper face):
//!
//! `f_p(u) = (1−f_s)(1−f_t) P[j,i] + f_s(1−f_t) P[j,i+1] + (1−f_s) f_t P[j+1,i] + f_s f_t P[j+1,i+1]`
//!
//! and the feature is `f_XY + f_XZ + f_YZ` ([`Combine::Sum`], `C` values) or
//! `[f_XY, f_XZ, f_YZ]` ([`Combine::Concat`], `3C` values). Storage is one buffer, index
//! `((p·R + j)·R + i)·C + c`.

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, Result};

/// How the three plane features are combined into the MLP input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Combine {
    /// `f_XY + f_XZ + f_YZ`: `C` inputs.
    #[default]
    Sum,
    /// `[f_XY, f_XZ, f_YZ]`: `3C` inputs.
    Concat,
}

/// The normalised axes `(a, b)` spanned by each plane, in storage order.
pub const PLANE_AXES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// Names of the planes in storage order.
pub const PLANE_NAMES: [&str; 3] = ["xy", "xz", "yz"];

/// Three `R × R × C` feature planes (dimensionless features).
#[derive(Debug, Clone, PartialEq)]
pub struct Triplane {
    resolution: usize,
    channels: usize,
    combine: Combine,
    values: Vec<f64>,
}

/// Where a point falls on one plane: the buffer index of node `(i, j)`'s first channel and the
/// fractional position `(f_s, f_t)` within the cell.
#[derive(Debug, Clone, Copy)]
struct Cell {
    base: usize,
    fs: f64,
    ft: f64,
}

/// Lower node index and fraction of normalised coordinate `u ∈ [0, 1]` on `r` nodes.
#[inline]
fn locate(u: f64, r: usize) -> (usize, f64) {
    let s = u * (r - 1) as f64;
    let i = (s as usize).min(r - 2);
    (i, s - i as f64)
}

impl Triplane {
    /// Planes of `resolution × resolution` nodes (≥ 2) with `channels` (≥ 1) zero features.
    pub fn zeros(resolution: usize, channels: usize, combine: Combine) -> Result<Self> {
        if resolution < 2 {
            return Err(FieldError::Config {
                field: "resolution",
                value: resolution.to_string(),
                reason: "a plane needs at least 2 nodes per side",
            });
        }
        if channels < 1 {
            return Err(FieldError::Config {
                field: "channels",
                value: channels.to_string(),
                reason: "must be at least 1",
            });
        }
        Ok(Self {
            resolution,
            channels,
            combine,
            values: vec![0.0; 3 * resolution * resolution * channels],
        })
    }

    /// Fill every feature with a uniform draw from `[−scale, scale]`.
    pub(crate) fn randomise(&mut self, scale: f64, rng: &mut impl Rng) {
        for v in &mut self.values {
            *v = scale * (2.0 * rng.random::<f64>() - 1.0);
        }
    }

    /// Nodes per plane side `R`.
    pub fn resolution(&self) -> usize {
        self.resolution
    }

    /// Channels per node `C`.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// How plane features are combined.
    pub fn combine(&self) -> Combine {
        self.combine
    }

    /// Length of the feature vector: `C` (sum) or `3C` (concat).
    pub fn features(&self) -> usize {
        match self.combine {
            Combine::Sum => self.channels,
            Combine::Concat => 3 * self.channels,
        }
    }

    /// All features, `3·R·R·C` values, index `((p·R + j)·R + i)·C + c`.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Mutable view of [`Triplane::values`].
    pub fn values_mut(&mut self) -> &mut [f64] {
        &mut self.values
    }

    /// Buffer index of channel `c` of node `(i, j)` (column `i` along the plane's first axis,
    /// row `j` along its second) of plane `p`.
    pub fn index(&self, p: usize, j: usize, i: usize, c: usize) -> usize {
        ((p * self.resolution + j) * self.resolution + i) * self.channels + c
    }

    #[inline]
    fn cell(&self, p: usize, u: [f64; 3]) -> Cell {
        let (a, b) = PLANE_AXES[p];
        let r = self.resolution;
        let (i, fs) = locate(u[a], r);
        let (j, ft) = locate(u[b], r);
        Cell {
            base: ((p * r + j) * r + i) * self.channels,
            fs,
            ft,
        }
    }

    /// The slice of the feature vector plane `p` writes to.
    #[inline]
    fn span(&self, p: usize) -> std::ops::Range<usize> {
        match self.combine {
            Combine::Sum => 0..self.channels,
            Combine::Concat => p * self.channels..(p + 1) * self.channels,
        }
    }

    /// Feature vector at normalised coordinates `u ∈ [0, 1]³` into `features`
    /// ([`Triplane::features`] values).
    #[inline]
    pub fn sample(&self, u: [f64; 3], features: &mut [f64]) {
        debug_assert_eq!(features.len(), self.features());
        features.fill(0.0);
        let c = self.channels;
        let row = self.resolution * c;
        for p in 0..3 {
            let Cell { base, fs, ft } = self.cell(p, u);
            let w = [
                (1.0 - fs) * (1.0 - ft),
                fs * (1.0 - ft),
                (1.0 - fs) * ft,
                fs * ft,
            ];
            let v00 = &self.values[base..base + c];
            let v10 = &self.values[base + c..base + 2 * c];
            let v01 = &self.values[base + row..base + row + c];
            let v11 = &self.values[base + row + c..base + row + 2 * c];
            let out = &mut features[self.span(p)];
            for k in 0..c {
                out[k] += w[0] * v00[k] + w[1] * v10[k] + w[2] * v01[k] + w[3] * v11[k];
            }
        }
    }

    /// Adjoint of [`Triplane::sample`]: adds `∂L/∂P` into `grad` (layout of
    /// [`Triplane::values`]) given `d_features = ∂L/∂features`, and returns `∂L/∂u`.
    #[inline]
    pub fn sample_backward(&self, u: [f64; 3], d_features: &[f64], grad: &mut [f64]) -> [f64; 3] {
        debug_assert_eq!(d_features.len(), self.features());
        debug_assert_eq!(grad.len(), self.values.len());
        let c = self.channels;
        let row = self.resolution * c;
        let scale = (self.resolution - 1) as f64;
        let mut d_u = [0.0; 3];
        for p in 0..3 {
            let Cell { base, fs, ft } = self.cell(p, u);
            let w = [
                (1.0 - fs) * (1.0 - ft),
                fs * (1.0 - ft),
                (1.0 - fs) * ft,
                fs * ft,
            ];
            let d = &d_features[self.span(p)];
            let (mut ds, mut dt) = (0.0, 0.0);
            let v00 = &self.values[base..base + c];
            let v10 = &self.values[base + c..base + 2 * c];
            let v01 = &self.values[base + row..base + row + c];
            let v11 = &self.values[base + row + c..base + row + 2 * c];
            for ((((dk, v00), v10), v01), v11) in d.iter().zip(v00).zip(v10).zip(v01).zip(v11) {
                ds += dk * ((1.0 - ft) * (v10 - v00) + ft * (v11 - v01));
                dt += dk * ((1.0 - fs) * (v01 - v00) + fs * (v11 - v10));
            }
            for (offset, wk) in [0, c, row, row + c].into_iter().zip(w) {
                let g = &mut grad[base + offset..base + offset + c];
                for (gk, dk) in g.iter_mut().zip(d) {
                    *gk += wk * dk;
                }
            }
            let (a, b) = PLANE_AXES[p];
            d_u[a] += scale * ds;
            d_u[b] += scale * dt;
        }
        d_u
    }

    /// Total variation of the planes (eq. 8), squared differences of neighbouring nodes:
    ///
    /// `TV = w Σ_p [ mean_{j, i<R−1, c} (P[j,i+1,c] − P[j,i,c])² + mean_{j<R−1, i, c} (P[j+1,i,c] − P[j,i,c])² ]`
    ///
    /// (each mean over `R(R−1)C` pairs, so `w` does not scale with the channel count).
    pub fn tv(&self, weight: f64) -> f64 {
        self.tv_impl(weight, None)
    }

    /// [`Triplane::tv`], and its gradient added into `grad` (layout of [`Triplane::values`]).
    pub fn tv_backward(&self, weight: f64, grad: &mut [f64]) -> f64 {
        debug_assert_eq!(grad.len(), self.values.len());
        self.tv_impl(weight, Some(grad))
    }

    fn tv_impl(&self, weight: f64, mut grad: Option<&mut [f64]>) -> f64 {
        let (r, c) = (self.resolution, self.channels);
        let scale = weight / (r * (r - 1) * c) as f64;
        let mut sum = 0.0;
        for p in 0..3 {
            for j in 0..r {
                for i in 0..r {
                    let here = self.index(p, j, i, 0);
                    let mut neighbours = [None, None];
                    if i + 1 < r {
                        neighbours[0] = Some(here + c);
                    }
                    if j + 1 < r {
                        neighbours[1] = Some(here + r * c);
                    }
                    for there in neighbours.into_iter().flatten() {
                        for k in 0..c {
                            let d = self.values[there + k] - self.values[here + k];
                            sum += d * d;
                            if let Some(g) = grad.as_deref_mut() {
                                g[there + k] += 2.0 * scale * d;
                                g[here + k] -= 2.0 * scale * d;
                            }
                        }
                    }
                }
            }
        }
        scale * sum
    }
}
