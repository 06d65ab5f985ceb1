//! Gaussians carried by a simulated deformation (PhysGaussian, Xie et al. 2024, §4.1): the
//! Gaussian of a particle that moved to `x` with deformation gradient `F` gets the mean `x`,
//! the covariance `F Σ Fᵀ`, and view-dependent colour turned with the material: its SH are
//! re-expressed so that it shows towards `d` what it showed towards `Rᵀd`, `R` the rotation of
//! the polar decomposition `F = R S`.

use std::sync::OnceLock;

use glam::{DMat3, DQuat, DVec3};
use pipe_mpm::svd::{polar_rotation, svd3};
use rayon::prelude::*;

use super::gaussians::{Gaussians, sh_coeffs};

/// Smallest scale (m) a deformed Gaussian keeps, so its log stays finite when `F` crushes it.
const MIN_SCALE_M: f64 = 1e-12;

/// `g` (one Gaussian per particle) moved to `x` (m) and deformed by `f`, per Gaussian.
pub fn deform(g: &Gaussians, x: &[DVec3], f: &[DMat3]) -> Gaussians {
    assert!(
        x.len() == g.len() && f.len() == g.len(),
        "one position and one F per Gaussian"
    );
    let k = 3 * sh_coeffs(g.sh_degree);
    let mut out = g.clone();
    out.position = x.iter().map(|p| p.as_vec3().to_array()).collect();
    out.log_scale
        .par_iter_mut()
        .zip(out.rotation.par_iter_mut())
        .zip(out.sh.par_chunks_mut(k))
        .zip(f.par_iter())
        .with_min_len(1024)
        .for_each(|(((log_scale, rotation), sh), f)| {
            (*log_scale, *rotation) = deform_shape(*log_scale, *rotation, f);
            if g.sh_degree > 0 {
                rotate_sh(g.sh_degree, sh, &polar_rotation(f));
            }
        });
    out
}

/// Log-scales and `(w, x, y, z)` quaternion of the covariance `F Σ Fᵀ`, `Σ = Q diag(s)² Qᵀ`:
/// from the SVD `F Q diag(s) = U S Vᵀ`, the new covariance is `U S² Uᵀ`.
fn deform_shape(log_scale: [f32; 3], rotation: [f32; 4], f: &DMat3) -> ([f32; 3], [f32; 4]) {
    let [w, qx, qy, qz] = rotation.map(f64::from);
    let q = DQuat::from_xyzw(qx, qy, qz, w);
    let q = if q.length_squared() > 0.0 {
        q.normalize()
    } else {
        DQuat::IDENTITY
    };
    let s = DVec3::from_array(log_scale.map(|v| f64::from(v).exp()));
    let m = *f * DMat3::from_quat(q) * DMat3::from_diagonal(s);
    let d = svd3(&m);
    let u = if d.u.determinant() < 0.0 {
        DMat3::from_cols(d.u.x_axis, d.u.y_axis, -d.u.z_axis)
    } else {
        d.u
    };
    let r = DQuat::from_mat3(&u).normalize();
    let ls =
        d.s.abs()
            .max(DVec3::splat(MIN_SCALE_M))
            .to_array()
            .map(|v| v.ln() as f32);
    (ls, [r.w, r.x, r.y, r.z].map(|v| v as f32))
}

/// Directions the SH bands are sampled at (a golden spiral of `n` points), unit vectors.
fn spiral(n: usize) -> Vec<DVec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|k| {
            let z = 1.0 - (2.0 * k as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let a = golden * k as f64;
            DVec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// The band-`l` basis values (`2l + 1` of them) at unit direction `d`.
fn band(l: usize, d: DVec3) -> Vec<f64> {
    let all = pipe_render::sh::basis(3, d.to_array());
    all[l * l..(l + 1) * (l + 1)].to_vec()
}

/// Directions each band is sampled at (more than any band has functions, so the fit is
/// well-conditioned).
const SAMPLES: usize = 16;

/// Per band `l = 1..=3`: the sample directions and the least-squares projector
/// `P = (BᵀB)⁻¹Bᵀ` (`2l + 1` × [`SAMPLES`], row-major) of the basis values `B` there
/// (row k: direction k), which recovers a band's coefficients from its values.
fn band_projectors() -> &'static [(Vec<DVec3>, Vec<f64>); 3] {
    static P: OnceLock<[(Vec<DVec3>, Vec<f64>); 3]> = OnceLock::new();
    P.get_or_init(|| {
        std::array::from_fn(|i| {
            let l = i + 1;
            let m = 2 * l + 1;
            let dirs = spiral(SAMPLES);
            let b: Vec<f64> = dirs.iter().flat_map(|&d| band(l, d)).collect();
            let mut g: Vec<f64> = (0..m * m)
                .map(|e| {
                    (0..SAMPLES)
                        .map(|k| b[k * m + e / m] * b[k * m + e % m])
                        .sum()
                })
                .collect();
            let g_inv = invert(&mut g, m).expect("the spiral samples every SH band");
            let p = (0..m * SAMPLES)
                .map(|e| {
                    let (r, k) = (e / SAMPLES, e % SAMPLES);
                    (0..m).map(|j| g_inv[r * m + j] * b[k * m + j]).sum()
                })
                .collect();
            (dirs, p)
        })
    })
}

/// Inverse of the `m × m` row-major matrix `a` (destroyed), by Gauss–Jordan elimination with
/// partial pivoting; `None` when singular.
fn invert(a: &mut [f64], m: usize) -> Option<Vec<f64>> {
    let mut inv: Vec<f64> = (0..m * m)
        .map(|k| if k / m == k % m { 1.0 } else { 0.0 })
        .collect();
    for c in 0..m {
        let p = (c..m).max_by(|&i, &j| a[i * m + c].abs().total_cmp(&a[j * m + c].abs()))?;
        if a[p * m + c].abs() < 1e-12 {
            return None;
        }
        for k in 0..m {
            a.swap(c * m + k, p * m + k);
            inv.swap(c * m + k, p * m + k);
        }
        let piv = a[c * m + c];
        for k in 0..m {
            a[c * m + k] /= piv;
            inv[c * m + k] /= piv;
        }
        for r in (0..m).filter(|&r| r != c) {
            let fct = a[r * m + c];
            for k in 0..m {
                a[r * m + k] -= fct * a[c * m + k];
                inv[r * m + k] -= fct * inv[c * m + k];
            }
        }
    }
    Some(inv)
}

/// Rotates the SH coefficients `sh` (`[coeff k][channel]`, degree `degree`) by `r`: the new
/// function at `d` equals the old one at `rᵀd`. Each band `l ≥ 1` is a rotation-invariant
/// space, so the turned band is again a band-`l` function, whose coefficients its values at
/// fixed directions `D` give: `c' = P B(rᵀD) c` (`band_projectors`).
pub fn rotate_sh(degree: u8, sh: &mut [f32], r: &DMat3) {
    let projectors = band_projectors();
    let rt = r.transpose();
    let degree = usize::from(degree).min(3);
    // Every band is sampled at the same directions: evaluate the turned basis once.
    let dirs = &projectors[0].0;
    let turned: [[f64; 16]; SAMPLES] =
        std::array::from_fn(|k| pipe_render::sh::basis(3, (rt * dirs[k]).to_array()));
    for l in 1..=degree {
        let p = &projectors[l - 1].1;
        let (m, first) = (2 * l + 1, l * l);
        // t = P B(rᵀD), m × m (at most 7 × 7).
        let mut t = [0.0; 49];
        for (e, te) in t.iter_mut().enumerate().take(m * m) {
            let (i, j) = (e / m, e % m);
            *te = (0..SAMPLES)
                .map(|k| p[i * SAMPLES + k] * turned[k][first + j])
                .sum();
        }
        for ch in 0..3 {
            let c: [f64; 7] = std::array::from_fn(|j| {
                if j < m {
                    f64::from(sh[(first + j) * 3 + ch])
                } else {
                    0.0
                }
            });
            for i in 0..m {
                sh[(first + i) * 3 + ch] = (0..m).map(|j| t[i * m + j] * c[j]).sum::<f64>() as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SH colour of coefficients `sh` (one channel) towards `d`.
    fn colour(degree: u8, sh: &[f32], ch: usize, d: DVec3) -> f64 {
        let b = pipe_render::sh::basis(u32::from(degree), d.normalize().to_array());
        (0..sh_coeffs(degree))
            .map(|k| b[k] * f64::from(sh[k * 3 + ch]))
            .sum()
    }

    fn rotation(axis: DVec3, angle: f64) -> DMat3 {
        DMat3::from_quat(DQuat::from_axis_angle(axis.normalize(), angle))
    }

    #[test]
    fn rotated_sh_show_towards_d_what_they_showed_towards_r_transpose_d() {
        let sh: Vec<f32> = (0..48)
            .map(|k| ((k * 37 % 19) as f32 - 9.0) / 10.0)
            .collect();
        let r = rotation(DVec3::new(0.3, -1.0, 0.6), 1.1);
        for degree in 1..=3u8 {
            let k = sh_coeffs(degree);
            let old = &sh[..3 * k];
            let mut new = old.to_vec();
            rotate_sh(degree, &mut new, &r);
            for d in spiral(40) {
                for ch in 0..3 {
                    let (a, b) = (
                        colour(degree, &new, ch, d),
                        colour(degree, old, ch, r.transpose() * d),
                    );
                    assert!((a - b).abs() < 1e-5, "degree {degree}: {a} vs {b}");
                }
            }
            // The DC term does not turn; the identity changes nothing.
            assert_eq!(new[..3], old[..3]);
            let mut same = old.to_vec();
            rotate_sh(degree, &mut same, &DMat3::IDENTITY);
            for (a, b) in same.iter().zip(old) {
                assert!((a - b).abs() < 1e-6);
            }
        }
    }

    /// The covariance of a Gaussian with log-scales `ls` and quaternion `q` (w, x, y, z).
    fn covariance(ls: [f32; 3], q: [f32; 4]) -> DMat3 {
        let [w, x, y, z] = q.map(f64::from);
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let s2 = DVec3::from_array(ls.map(|v| (2.0 * f64::from(v)).exp()));
        r * DMat3::from_diagonal(s2) * r.transpose()
    }

    #[test]
    fn the_covariance_becomes_f_sigma_f_transpose() {
        let ls = [-3.0f32, -4.0, -5.0];
        let q = [0.9f32, 0.1, -0.3, 0.2];
        let sigma = covariance(ls, q);
        for f in [
            DMat3::IDENTITY,
            rotation(DVec3::Z, 0.7),
            DMat3::from_cols_array(&[1.3, 0.2, 0.0, -0.1, 0.8, 0.3, 0.05, 0.0, 1.1]),
            DMat3::from_diagonal(DVec3::new(2.0, 0.5, 1.0)),
        ] {
            let (ls2, q2) = deform_shape(ls, q, &f);
            let got = covariance(ls2, q2);
            let want = f * sigma * f.transpose();
            let err = (got - want)
                .to_cols_array()
                .iter()
                .map(|e| e.abs())
                .fold(0.0, f64::max);
            let scale = want
                .to_cols_array()
                .iter()
                .map(|e| e.abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-6 * scale, "F = {f:?}: {got:?} vs {want:?}");
        }
    }

    #[test]
    fn gaussians_follow_their_particles() {
        let g = Gaussians {
            sh_degree: 1,
            id: vec![0, 1],
            position: vec![[0.0; 3]; 2],
            log_scale: vec![[-3.0; 3]; 2],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacity_logit: vec![0.5, -1.0],
            sh: (0..24).map(|k| k as f32 / 24.0).collect(),
            simulated: vec![true; 2],
        };
        let x = [DVec3::new(1.0, 2.0, 3.0), DVec3::new(-1.0, 0.5, 0.0)];
        let f = [
            DMat3::IDENTITY,
            DMat3::from_diagonal(DVec3::new(2.0, 1.0, 1.0)),
        ];
        let out = deform(&g, &x, &f);
        assert_eq!(out.position, vec![[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]]);
        assert_eq!(
            (out.opacity_logit.clone(), out.id.clone()),
            (g.opacity_logit.clone(), g.id.clone())
        );
        // A stretch along x doubles that axis' scale and turns nothing.
        let mut ls = out.log_scale[1];
        ls.sort_by(f32::total_cmp);
        assert!(
            (ls[2] - (-3.0 + 2f32.ln())).abs() < 1e-5 && (ls[0] + 3.0).abs() < 1e-5,
            "{ls:?}"
        );
        for (a, b) in out.sh.iter().zip(&g.sh) {
            assert!((a - b).abs() < 1e-6);
        }
    }
}
