//! Shading that stays in the world when the object turns: a re-lighting of deformed Gaussians.
//!
//! The warm-up bakes the capture's lighting into each Gaussian's colour: a patch that faced the
//! light at frame 0 is bright, one that faced the floor is dark. Carried by the simulation
//! ([`crate::physics::pose`]) the colours turn with the material, so when the body tips over or
//! flattens its dark side comes up dark. Under distant lighting a diffuse surface's radiance is
//! `albedo · E(n)`, `E` the irradiance of its normal `n`, a smooth function of `n` (Ramamoorthi
//! & Hanrahan 2001, "An efficient representation for irradiance environment maps"). We fit its
//! lowest orders, `ln E(n) = w₀ + w·n`: an ambient term and one dominant light direction (the
//! quadratic terms, measured on the demo torus and the blob, over-brightened what had faced
//! the floor, which is dark also from occlusion this model does not know). So:
//!
//! 1. each Gaussian gets an outward normal at rest, away from the volume-weighted centroid of
//!    the body's particles around it ([`rest_normals`]; a confidence in `[0, 1]` from how far
//!    that centroid is off-centre, 0 deep inside or on a thin sheet);
//! 2. `ln E` is fitted to the Gaussians' baked luminance, `ln Y_i = ln a_i + Σ_k w_k B_k(n_i)`,
//!    by weighted least squares over `B = (1, n_x, n_y, n_z)` (the albedo `a_i` is the
//!    residual: it does not depend on the normal, [`Shading::fit`]);
//! 3. in a deformed state the normal is `cof(F) n` (normals transform by `F⁻ᵀ`), and the colour
//!    is multiplied by the gain `E(n_t) / E(n_0)` ([`Shading::gains`], [`relit_sh`]).
//!
//! Shadows, occlusion and inter-reflections are not modelled: the gain is clamped to
//! `[1/2, 2]`.

use glam::{DMat3, DMat4, DVec3, DVec4};
use pipe_mpm::math::cofactor;
use pipe_render::gaussians::sigmoid;
use rayon::prelude::*;

use super::gaussians::{Gaussians, sh_coeffs};
use super::neighbors::PointGrid;

/// `Y_0^0` of the real SH basis: a DC coefficient `c` shows the colour `SH_C0·c + 1/2`.
const SH_C0: f64 = 0.282_094_791_773_878_14;

/// Gains are kept within `[1/MAX_GAIN, MAX_GAIN]`.
const MAX_GAIN: f64 = 2.0;

/// Darkest luminance the fit takes the log of.
const MIN_LUMINANCE: f64 = 0.02;

/// The basis of `ln E` at the unit normal `n`: the real SH of degree ≤ 1 (constants dropped:
/// they only scale the fitted weights).
fn basis(n: DVec3) -> DVec4 {
    DVec4::new(1.0, n.x, n.y, n.z)
}

/// Outward unit normal at each point `at` (the Gaussians at rest), with a confidence in
/// `[0, 1]`: away from the volume-weighted centroid of the particles `x` within `radius` (m). The
/// confidence is the centroid's offset over `radius / 4` (capped at 1): a point on a surface
/// has its neighbours on one side, one deep inside or on a thin sheet has them all round.
pub fn rest_normals(x: &[DVec3], volume: &[f64], at: &[DVec3], radius: f64) -> Vec<(DVec3, f64)> {
    assert_eq!(x.len(), volume.len(), "one volume per particle");
    if x.is_empty() || !(radius.is_finite() && radius > 0.0) {
        return vec![(DVec3::ZERO, 0.0); at.len()];
    }
    let grid = PointGrid::new(x, radius);
    at.par_iter()
        .with_min_len(256)
        .map(|&p| {
            let (mut sum, mut w) = (DVec3::ZERO, 0.0);
            grid.within(p, radius, |j| {
                sum += x[j] * volume[j];
                w += volume[j];
            });
            if w <= 0.0 {
                return (DVec3::ZERO, 0.0);
            }
            let off = p - sum / w;
            let len = off.length();
            if len == 0.0 || !len.is_finite() {
                return (DVec3::ZERO, 0.0);
            }
            (off / len, (len / (0.25 * radius)).min(1.0))
        })
        .collect()
}

/// The fitted irradiance, `ln E(n) = w₀ + (w₁, w₂, w₃)·n`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shading {
    /// Weights of the basis functions (the first, the mean log-albedo, plays no part in the
    /// gains; the others are the light's direction times its strength).
    pub weights: DVec4,
    /// Share of the weighted variance of the Gaussians' log-luminance the normals explain.
    pub explained: f64,
}

impl Shading {
    /// Fits `ln E` to the luminance of `g`'s DC colours (one `(normal, confidence)` per
    /// Gaussian), weighted by opacity × confidence. `None` when fewer than 32 Gaussians have a
    /// normal or the system is singular.
    pub fn fit(g: &Gaussians, normals: &[(DVec3, f64)]) -> Option<Self> {
        let k = 3 * sh_coeffs(g.sh_degree);
        let n = normals.len().min(g.len());
        let (mut ata, mut atb) = (DMat4::ZERO, DVec4::ZERO);
        let (mut rows, mut sw, mut swy, mut swyy) = (0usize, 0.0, 0.0, 0.0);
        for (i, &(normal, conf)) in normals.iter().enumerate().take(n) {
            let w = sigmoid(f64::from(g.opacity_logit[i])) * conf;
            if w.is_nan() || w <= 0.0 {
                continue;
            }
            let dc = &g.sh[i * k..i * k + 3];
            let rgb = dc.iter().map(|&c| SH_C0 * f64::from(c) + 0.5);
            let lum: f64 = rgb
                .zip([0.2126, 0.7152, 0.0722])
                .map(|(c, l)| c.max(0.0) * l)
                .sum();
            let y = lum.max(MIN_LUMINANCE).ln();
            let b = basis(normal);
            atb += b * (w * y);
            ata += DMat4::from_cols(b * b.x, b * b.y, b * b.z, b * b.w) * w;
            rows += 1;
            sw += w;
            swy += w * y;
            swyy += w * y * y;
        }
        if rows < 32 {
            return None;
        }
        let ridge = 1e-6 * (ata.x_axis.x + ata.y_axis.y + ata.z_axis.z + ata.w_axis.w) / 4.0;
        let ata = ata + DMat4::from_diagonal(DVec4::splat(ridge));
        let det = ata.determinant();
        if !det.is_finite() || det <= 0.0 {
            return None;
        }
        let weights = ata.inverse() * atb;
        let variance = swyy / sw - (swy / sw).powi(2);
        // Weighted residual variance: Σw(y − b·w)² = Σwy² − 2 wᵀAᵀy + wᵀAᵀA w.
        let residual = (swyy - 2.0 * weights.dot(atb) + weights.dot(ata * weights)) / sw;
        let explained = if variance > 0.0 {
            (1.0 - residual / variance).clamp(0.0, 1.0)
        } else {
            0.0
        };
        weights.is_finite().then_some(Self { weights, explained })
    }

    /// `ln E(n)`.
    fn log_irradiance(&self, n: DVec3) -> f64 {
        basis(n).dot(self.weights)
    }

    /// The colour gain of each Gaussian deformed by `f` (one per normal): `E(n_t)/E(n_0)`,
    /// `n_t = cof(F) n_0` normalised, in the log blended by the normal's confidence and
    /// clamped to `[1/2, 2]`; 1 where `det F ≤ 0` or `F` is not finite.
    pub fn gains(&self, normals: &[(DVec3, f64)], f: &[DMat3]) -> Vec<f32> {
        assert_eq!(normals.len(), f.len(), "one F per normal");
        normals
            .par_iter()
            .zip(f.par_iter())
            .with_min_len(1024)
            .map(|(&(n0, conf), f)| {
                let det = f.determinant();
                if conf <= 0.0 || !det.is_finite() || det <= 0.0 {
                    return 1.0;
                }
                let nt = (cofactor(f) * n0).normalize_or_zero();
                if nt == DVec3::ZERO {
                    return 1.0;
                }
                let log_gain = conf * (self.log_irradiance(nt) - self.log_irradiance(n0));
                log_gain.clamp(-MAX_GAIN.ln(), MAX_GAIN.ln()).exp() as f32
            })
            .collect()
    }
}

/// SH coefficients (`[gaussian][coeff][channel]`, degree `degree`) whose colour in every
/// direction is `gain` times the original's: the DC term `c ↦ k·c + (k − 1)/(2·SH_C0)` (the
/// rasterizer adds ½ to the DC colour), the others `c ↦ k·c`.
pub fn relit_sh(sh: &[f32], degree: u8, gains: &[f32]) -> Vec<f32> {
    let k = 3 * sh_coeffs(degree);
    assert_eq!(sh.len(), k * gains.len(), "one gain per Gaussian");
    let mut out = sh.to_vec();
    out.par_chunks_mut(k)
        .zip(gains.par_iter())
        .with_min_len(1024)
        .for_each(|(c, &gain)| {
            let offset = (gain - 1.0) * (0.5 / SH_C0) as f32;
            for (j, v) in c.iter_mut().enumerate() {
                *v = if j < 3 { gain * *v + offset } else { gain * *v };
            }
        });
    out
}

/// The re-lighting of one body's Gaussians: their rest normals and the fitted irradiance.
#[derive(Debug, Clone)]
pub struct Relight {
    /// Each Gaussian's outward normal at rest and its confidence.
    pub normals: Vec<(DVec3, f64)>,
    pub shading: Shading,
}

impl Relight {
    /// For the Gaussians `g` (at rest) of a body whose particles at rest are `x` (m) with
    /// volumes `volume` (m³), simulated on a grid of cell `dx` (m): normals from the particles within
    /// 1.5 cells, the irradiance fitted to the canonical colours; `None` when too few
    /// Gaussians have a normal.
    pub fn of(x: &[DVec3], volume: &[f64], g: &Gaussians, dx: f64) -> Option<Self> {
        let at: Vec<DVec3> = g
            .position
            .iter()
            .map(|p| DVec3::from_array(p.map(f64::from)))
            .collect();
        let normals = rest_normals(x, volume, &at, 1.5 * dx);
        let shading = Shading::fit(g, &normals)?;
        Some(Self { normals, shading })
    }

    /// The colour gain of each Gaussian deformed by `f` (one per Gaussian; [`Shading::gains`]).
    pub fn gains(&self, f: &[DMat3]) -> Vec<f32> {
        self.shading.gains(&self.normals, f)
    }

    /// `sh` (the Gaussians', canonical or already turned by the deformation) re-lit for the
    /// deformation gradients `f` (one per Gaussian).
    pub fn sh(&self, sh: &[f32], degree: u8, f: &[DMat3]) -> Vec<f32> {
        relit_sh(sh, degree, &self.gains(f))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points filling a ball of radius `r` on a lattice of spacing `h`.
    fn ball(r: f64, h: f64) -> Vec<DVec3> {
        let n = (r / h).ceil() as i32;
        let mut out = Vec::new();
        for i in -n..=n {
            for j in -n..=n {
                for k in -n..=n {
                    let p = DVec3::new(i as f64, j as f64, k as f64) * h;
                    if p.length() <= r {
                        out.push(p);
                    }
                }
            }
        }
        out
    }

    /// Gaussians at `x` with DC colours `rgb`.
    fn splats(x: &[DVec3], rgb: impl Fn(usize) -> [f64; 3]) -> Gaussians {
        let n = x.len();
        Gaussians {
            sh_degree: 0,
            id: (0..n as u32).collect(),
            position: x.iter().map(|p| p.as_vec3().to_array()).collect(),
            log_scale: vec![[-4.0; 3]; n],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacity_logit: vec![4.0; n],
            sh: (0..n)
                .flat_map(|i| rgb(i).map(|c| ((c - 0.5) / SH_C0) as f32))
                .collect(),
            simulated: vec![true; n],
        }
    }

    #[test]
    fn a_balls_surface_points_outward_and_its_centre_has_no_normal() {
        let x = ball(0.1, 0.01);
        let normals = rest_normals(&x, &vec![1e-6; x.len()], &x, 0.03);
        assert_eq!(normals.len(), x.len());
        let (mut surface, mut worst) = (0, 1.0f64);
        for (p, (n, conf)) in x.iter().zip(&normals) {
            assert!(n.is_finite() && conf.is_finite());
            if p.length() > 0.095 {
                surface += 1;
                worst = worst.min(n.dot(p.normalize()));
                assert!(*conf > 0.9, "surface point {p} has confidence {conf}");
            }
            if p.length() < 1e-9 {
                assert!(*conf < 1e-6, "the centre has neighbours all round: {conf}");
            }
        }
        assert!(surface > 100);
        assert!(
            worst > 0.9,
            "a surface normal is {worst} off the radius (cosine)"
        );
    }

    #[test]
    fn a_lighting_baked_into_textured_colours_is_recovered_and_turns_with_the_body() {
        // A ball lit from above (irradiance e^{0.3 y}) with a random albedo per point.
        let x = ball(0.1, 0.01);
        let normals = rest_normals(&x, &vec![1e-6; x.len()], &x, 0.03);
        let albedo = |i: usize| 0.3 + 0.4 * ((i * 7919 % 101) as f64 / 100.0);
        let g = splats(&x, |i| {
            let e = (0.3 * normals[i].0.y).exp() * 0.5;
            [albedo(i) * e; 3]
        });
        let s = Shading::fit(&g, &normals).expect("a fit");
        assert!(
            (s.weights[2] - 0.3).abs() < 0.05 && s.weights[1].abs() < 0.05,
            "the light's weights {:?} (truth: 0.3 along y)",
            s.weights
        );
        assert!(s.explained > 0.3, "explained {}", s.explained);
        // Turned upside down (a rotation by π about z): a point that faced up now faces down
        // and must darken by about e^{-0.6}; identity leaves every colour as it was.
        let flip = DMat3::from_rotation_z(std::f64::consts::PI);
        let gains = s.gains(&normals, &vec![flip; x.len()]);
        let ident = s.gains(&normals, &vec![DMat3::IDENTITY; x.len()]);
        assert!(ident.iter().all(|&k| (k - 1.0).abs() < 1e-6));
        let top = (0..x.len())
            .filter(|&i| normals[i].1 > 0.9 && normals[i].0.y > 0.95)
            .collect::<Vec<_>>();
        assert!(!top.is_empty());
        for i in top {
            let want = (-0.6f64 * normals[i].0.y).exp();
            assert!(
                (f64::from(gains[i]) / want - 1.0).abs() < 0.25,
                "gain {} against {want}",
                gains[i]
            );
        }
        // A squash (F = diag(2, 1/2, 2)) turns side normals up: cof(F) n, not R n.
        let squash = DMat3::from_diagonal(DVec3::new(2.0, 0.5, 2.0));
        let side = (0..x.len())
            .find(|&i| normals[i].1 > 0.9 && normals[i].0.y.abs() < 0.2 && normals[i].0.y > 0.05)
            .expect("a side point");
        let k = s.gains(&[normals[side]], &[squash])[0];
        assert!(
            k > 1.05,
            "a side normal turned upwards must brighten, gain {k}"
        );
    }

    #[test]
    fn relit_sh_scales_the_colour_in_every_direction() {
        let sh: Vec<f32> = (0..12).map(|j| 0.1 * j as f32 - 0.4).collect(); // degree 1
        let out = relit_sh(&sh, 1, &[1.7]);
        for c in 0..3 {
            let before = SH_C0 as f32 * sh[c] + 0.5;
            let after = SH_C0 as f32 * out[c] + 0.5;
            assert!((after - 1.7 * before).abs() < 1e-5);
        }
        for j in 3..12 {
            assert!((out[j] - 1.7 * sh[j]).abs() < 1e-6);
        }
        assert_eq!(relit_sh(&sh, 1, &[1.0]), sh);
    }

    #[test]
    fn too_few_normals_fit_nothing() {
        let x = ball(0.02, 0.01);
        let normals = vec![(DVec3::Y, 0.0); x.len()];
        assert!(Shading::fit(&splats(&x, |_| [0.5; 3]), &normals).is_none());
    }
}
