//! The object's Gaussians at a simulated state, and the way back (PhysGaussian §4.1): Gaussian
//! `i` sits at its particle's position `x_i` with covariance `F_i Σ_i F_iᵀ`, and its SH show
//! towards a direction `d` what they showed towards `R_iᵀ d`, `R_i` the rotation of the polar
//! decomposition `F_i = R_i S_i`. A Newtonian fluid's `F` holds only its volume ratio
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

/// Row-major entries of a matrix, as the rasterizer takes them.
fn rows<T: Real>(m: &DMat3) -> [T; 9] {
    std::array::from_fn(|k| T::from_f64(m.col(k % 3)[k / 3]))
}

/// A matrix of row-major entries.
fn from_rows<T: Real>(r: &[T; 9]) -> DMat3 {
    DMat3::from_cols_array(&std::array::from_fn(|k| r[3 * (k % 3) + k / 3].to_f64()))
}

/// The Gaussians of the first particles of a state, ready to render.
#[derive(Debug, Clone)]
pub struct Pose<T> {
    /// Centres (m).
    pub means: Vec<[T; 3]>,
    /// The deformation each Gaussian's covariance takes (row-major).
    pub f: Vec<[T; 9]>,
    /// The rotation its SH turn with (row-major); empty for a fluid.
    pub r: Vec<[T; 9]>,
    /// The particles' `F` (solids) and its polar rotation, for the adjoint.
    f_r: Vec<(DMat3, DMat3)>,
    /// Fluids: the volume ratio `J` of each particle.
    j: Vec<f64>,
}

impl<T: Real> Pose<T> {
    /// The first `n` particles of `state`; `fluid` for a Newtonian fluid.
    pub fn of(state: &State, n: usize, fluid: bool) -> Self {
        let means = state.x[..n]
            .iter()
            .map(|x| x.to_array().map(T::from_f64))
            .collect();
        if fluid {
            let j: Vec<f64> = state.f[..n].iter().map(|f| f.x_axis.x).collect();
            let f = j
                .iter()
                .map(|&j| rows(&DMat3::from_diagonal(DVec3::splat(j.max(0.0).cbrt()))))
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
        Self {
            means,
            f: f_r.iter().map(|(f, _)| rows(f)).collect(),
            r: f_r.iter().map(|(_, r)| rows(r)).collect(),
            f_r,
            j: Vec::new(),
        }
    }

    /// Particles posed.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether none are.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// The canonical Gaussians `base` (one per posed particle) in this pose: moved, deformed
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

    /// Adds the gradients of one render in this pose (`∂L/∂means`, `∂L/∂F`, `∂L/∂R`) into the
    /// particles' `∂L/∂x` and `∂L/∂F` (`out` holds every particle; the posed ones first).
    pub fn seed(&self, grads: &pipe_render::Gradients<T>, out: &mut StateGrad) {
        let n = self.len();
        for (o, g) in out.x[..n].iter_mut().zip(&grads.means) {
            *o += DVec3::from_array(g.map(T::to_f64));
        }
        if !self.j.is_empty() {
            // F_render = J^{1/3} I: ∂L/∂J = tr(∂L/∂F_render) · J^{-2/3} / 3.
            for ((o, g), &j) in out.f[..n].iter_mut().zip(&grads.deformation).zip(&self.j) {
                let tr = (g[0] + g[4] + g[8]).to_f64();
                let c = j.max(1e-12).cbrt();
                o.x_axis.x += tr / (3.0 * c * c);
            }
            return;
        }
        let gf: Vec<DMat3> = (0..n)
            .into_par_iter()
            .with_min_len(1024)
            .map(|i| {
                let mut g = from_rows(&grads.deformation[i]);
                if let Some(gr) = grads.sh_rotation.get(i) {
                    let gr = from_rows(gr);
                    let (f, r) = &self.f_r[i];
                    g += polar_rotation_adjoint(f, r, &gr)
                        .unwrap_or_else(|| rotation_adjoint(&svd3(f), &gr));
                }
                g
            })
            .collect();
        for (o, g) in out.f[..n].iter_mut().zip(gf) {
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
