//! The object's Gaussians at a simulated state, and the way back (PhysGaussian §4.1): Gaussian
//! `g` sits at its carrier particle `c` ([`crate::simulate::skin`]), at `x_c + F_c d_g`, with
//! covariance `F_c Σ_g F_cᵀ`, and its SH show
//! towards a direction `d` what they showed towards `R_cᵀ d`, `R_c` the rotation of the polar
//! decomposition `F_c = R_c S_c`. A Newtonian fluid's `F` holds only its volume ratio
//! (`diag(J, 1, 1)`): its Gaussians swell or shrink evenly, `J^{1/3} I`, and do not turn.
//!
//! [`Pose::seed`] turns the rasterizer's gradients into `∂L/∂x` and `∂L/∂F` of the particles,
//! through the polar decomposition's adjoint, for the MPM adjoint to take. Generic over the
//! rasterizer's scalar: `f32` in the stages, `f64` in the gradient checks.

use glam::{DMat3, DVec3};
use pipe_mpm::svd::{polar_rotation, polar_rotation_adjoint, rotation_adjoint, svd3};
use pipe_mpm::{State, StateGrad};
use pipe_render::Real;
use rayon::prelude::*;

use crate::simulate::skin::Skin;

/// Row-major entries of a matrix, as the rasterizer takes them.
fn rows<T: Real>(m: &DMat3) -> [T; 9] {
    std::array::from_fn(|k| T::from_f64(m.col(k % 3)[k / 3]))
}

/// A matrix of row-major entries.
fn from_rows<T: Real>(r: &[T; 9]) -> DMat3 {
    DMat3::from_cols_array(&std::array::from_fn(|k| r[3 * (k % 3) + k / 3].to_f64()))
}

/// The Gaussians' centres: each carrier's position plus its neighbourhood's map `a(c, d_g)`
/// of the Gaussian's rest offset (the carriers' positions as they are for the identity skin).
fn means_of<T: Real>(state: &State, skin: &Skin, a: impl Fn(usize, DVec3) -> DVec3) -> Vec<[T; 3]> {
    if skin.is_identity() {
        return state.x[..skin.len()]
            .iter()
            .map(|x| x.to_array().map(T::from_f64))
            .collect();
    }
    skin.carrier()
        .iter()
        .zip(skin.offset())
        .map(|(&c, d)| {
            let c = c as usize;
            (state.x[c] + a(c, *d)).to_array().map(T::from_f64)
        })
        .collect()
}

/// The Gaussians of a state, ready to render: each at its carrier particle
/// ([`crate::simulate::skin`]).
#[derive(Debug, Clone)]
pub struct Pose<T> {
    /// Centres (m), one per Gaussian.
    pub means: Vec<[T; 3]>,
    /// The deformation each Gaussian's covariance takes (row-major).
    pub f: Vec<[T; 9]>,
    /// The rotation its SH turn with (row-major); empty for a fluid.
    pub r: Vec<[T; 9]>,
    /// The carrier particles' `F` (solids) and its polar rotation, for the adjoint.
    f_r: Vec<(DMat3, DMat3)>,
    /// Fluids: the volume ratio `J` of each carrier particle.
    j: Vec<f64>,
}

impl<T: Real> Pose<T> {
    /// The Gaussians of `skin` on the particles of `state`; `fluid` for a Newtonian fluid.
    pub fn of(state: &State, skin: &Skin, fluid: bool) -> Self {
        let n = skin.particles();
        if fluid {
            let j: Vec<f64> = state.f[..n].iter().map(|f| f.x_axis.x).collect();
            let scale: Vec<f64> = j.iter().map(|&j| j.max(0.0).cbrt()).collect();
            let means = means_of(state, skin, |c, d| d * scale[c]);
            let f = skin
                .carrier()
                .iter()
                .map(|&c| rows(&DMat3::from_diagonal(DVec3::splat(scale[c as usize]))))
                .collect();
            return Self {
                means,
                f,
                r: Vec::new(),
                f_r: Vec::new(),
                j,
            };
        }
        let f_r: Vec<(DMat3, DMat3)> = state.f[..n]
            .par_iter()
            .with_min_len(1024)
            .map(|f| (*f, polar_rotation(f)))
            .collect();
        let means = means_of(state, skin, |c, d| f_r[c].0 * d);
        let per: Vec<([T; 9], [T; 9])> = f_r.iter().map(|(f, r)| (rows(f), rows(r))).collect();
        let (f, r): (Vec<_>, Vec<_>) = skin.gather(&per).iter().copied().unzip();
        Self {
            means,
            f,
            r,
            f_r,
            j: Vec::new(),
        }
    }

    /// Gaussians posed.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether none are.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// The canonical Gaussians `base` (one per posed Gaussian) in this pose: moved, deformed
    /// and turned.
    pub fn apply<'a>(
        &'a self,
        base: pipe_render::Gaussians<'a, T>,
    ) -> pipe_render::Gaussians<'a, T> {
        debug_assert_eq!(base.len(), self.len());
        pipe_render::Gaussians {
            means: &self.means,
            deformation: Some(pipe_render::Deformation {
                f: &self.f,
                sh_rotation: (!self.r.is_empty()).then_some(self.r.as_slice()),
            }),
            ..base
        }
    }

    /// Adds the gradients of one render in this pose (`∂L/∂means`, `∂L/∂F`, `∂L/∂R` of each
    /// Gaussian) into the carrier particles' `∂L/∂x` and `∂L/∂F` (`out` holds every particle;
    /// the carriers first), through `x_g = x_c + A_c d_g` of `skin`, the one it was posed with.
    pub fn seed(&self, skin: &Skin, grads: &pipe_render::Gradients<T>, out: &mut StateGrad) {
        debug_assert_eq!(skin.len(), self.len());
        let n = skin.particles();
        let gm = |g: usize| DVec3::from_array(grads.means[g].map(T::to_f64));
        for (g, &c) in skin.carrier().iter().enumerate() {
            out.x[c as usize] += gm(g);
        }
        if !self.j.is_empty() {
            // A = J^{1/3} I: ∂L/∂J = (tr(∂L/∂A) + ∂L/∂x_g · d_g) · J^{-2/3} / 3.
            let mut gj = vec![0.0; n];
            for (g, (&c, d)) in skin.carrier().iter().zip(skin.offset()).enumerate() {
                let a = &grads.deformation[g];
                gj[c as usize] += (a[0] + a[4] + a[8]).to_f64() + gm(g).dot(*d);
            }
            for ((o, gj), &j) in out.f[..n].iter_mut().zip(gj).zip(&self.j) {
                let c = j.max(1e-12).cbrt();
                o.x_axis.x += gj / (3.0 * c * c);
            }
            return;
        }
        // Per carrier: ∂L/∂F from the covariances and the offsets (∂L/∂x_g d_gᵀ), ∂L/∂R.
        let mut gf = vec![DMat3::ZERO; n];
        let mut gr: Vec<Option<DMat3>> = vec![None; n];
        for (g, (&c, d)) in skin.carrier().iter().zip(skin.offset()).enumerate() {
            let c = c as usize;
            gf[c] += from_rows(&grads.deformation[g]);
            if *d != DVec3::ZERO {
                let m = gm(g);
                gf[c] += DMat3::from_cols(m * d.x, m * d.y, m * d.z);
            }
            if let Some(r) = grads.sh_rotation.get(g) {
                let r = from_rows(r);
                gr[c] = Some(gr[c].map_or(r, |s| s + r));
            }
        }
        let adj: Vec<DMat3> = (0..n)
            .into_par_iter()
            .with_min_len(1024)
            .map(|c| {
                let mut g = gf[c];
                if let Some(gr) = &gr[c] {
                    let (f, r) = &self.f_r[c];
                    g += polar_rotation_adjoint(f, r, gr)
                        .unwrap_or_else(|| rotation_adjoint(&svd3(f), gr));
                }
                g
            })
            .collect();
        for (o, g) in out.f[..n].iter_mut().zip(adj) {
            *o += g;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_major_round_trip() {
        let m = DMat3::from_cols_array(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
        let r: [f64; 9] = rows(&m);
        // Row 0 is (m00, m01, m02) = (1, 4, 7) for glam's columns (1,2,3), (4,5,6), (7,8,9).
        assert_eq!(&r[..3], &[1.0, 4.0, 7.0]);
        assert_eq!(from_rows(&r), m);
    }
}
