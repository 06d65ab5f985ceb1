//! 3x3 singular value decomposition `F = U diag(σ) Vᵀ` (one-sided Jacobi) and its adjoint.
//!
//! Convention ("rotation variant", as Taichi's `ti.svd` and PAC-NeRF): `U` and `V` are proper
//! rotations (det = +1), `σ₀ ≥ σ₁ ≥ |σ₂|` and `σ₂ < 0` exactly when `det F < 0`.

use glam::{DMat3, DVec3};

use crate::math::{cofactor, ddot, el, max_abs, outer};

/// Result of [`svd3`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Svd {
    /// Left rotation.
    pub u: DMat3,
    /// Signed singular values, descending in magnitude.
    pub s: DVec3,
    /// Right rotation.
    pub v: DMat3,
}

impl Svd {
    /// `U diag(d) Vᵀ`.
    #[inline]
    pub fn compose(&self, d: DVec3) -> DMat3 {
        self.u * DMat3::from_diagonal(d) * self.v.transpose()
    }
}

/// Below this relative size a singular vector is completed geometrically instead of by division.
const TINY: f64 = 1e-30;

/// Columns count as orthogonal once `|b_p·b_q| ≤ ORTHO_TOL |b_p| |b_q|`: 2ε, the rounding
/// floor of the dot product. A tighter bound (it was 1e-16 < ε) is never met for about 2% of
/// matrices, whose sweeps then rotate on rounding noise up to the 30-sweep cap.
const ORTHO_TOL: f64 = 2.0 * f64::EPSILON;

/// SVD by one-sided Jacobi rotations on the columns of `F` (accurate for small σ too).
pub fn svd3(f: &DMat3) -> Svd {
    let mut b = [f.x_axis, f.y_axis, f.z_axis];
    let mut v = [DVec3::X, DVec3::Y, DVec3::Z];
    for _sweep in 0..30 {
        let mut rotated = false;
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let alpha = b[p].length_squared();
            let beta = b[q].length_squared();
            let gamma = b[p].dot(b[q]);
            if gamma == 0.0 || gamma.abs() <= ORTHO_TOL * (alpha * beta).sqrt() {
                continue;
            }
            rotated = true;
            let zeta = (beta - alpha) / (2.0 * gamma);
            let t = zeta.signum() / (zeta.abs() + (1.0 + zeta * zeta).sqrt());
            let c = 1.0 / (1.0 + t * t).sqrt();
            let s = c * t;
            let (bp, bq) = (b[p], b[q]);
            b[p] = c * bp - s * bq;
            b[q] = s * bp + c * bq;
            let (vp, vq) = (v[p], v[q]);
            v[p] = c * vp - s * vq;
            v[q] = s * vp + c * vq;
        }
        if !rotated {
            break;
        }
    }
    let mut sig = [b[0].length(), b[1].length(), b[2].length()];
    // Sort descending (tiny insertion sort keeping b, v aligned).
    for i in 1..3 {
        let mut j = i;
        while j > 0 && sig[j] > sig[j - 1] {
            sig.swap(j, j - 1);
            b.swap(j, j - 1);
            v.swap(j, j - 1);
            j -= 1;
        }
    }
    let scale = sig[0].max(f64::MIN_POSITIVE);
    let u0 = if sig[0] > 0.0 {
        b[0] / sig[0]
    } else {
        DVec3::X
    };
    let u1 = if sig[1] > TINY * scale {
        b[1] / sig[1]
    } else {
        u0.any_orthonormal_vector()
    };
    let mut u2 = if sig[2] > TINY * scale {
        b[2] / sig[2]
    } else {
        u0.cross(u1)
    };
    let mut vm = DMat3::from_cols(v[0], v[1], v[2]);
    if vm.determinant() < 0.0 {
        // F(-v2) = σ2(-u2): flip both, σ unchanged.
        vm.z_axis = -vm.z_axis;
        u2 = -u2;
    }
    let mut um = DMat3::from_cols(u0, u1, u2);
    if um.determinant() < 0.0 {
        um.z_axis = -um.z_axis;
        sig[2] = -sig[2];
    }
    Svd {
        u: um,
        s: DVec3::from_array(sig),
        v: vm,
    }
}

/// Smallest `det X₀` (`X₀ = F √3/‖F‖_F`, so `Σσ² = 3`) that [`polar_rotation`] iterates on;
/// flatter, inverted or degenerate `F` go through [`svd3`]. As `det X₀ ≤ √3 (σ₂ + σ₃)²/4`, it
/// keeps `σ₂ + σ₃ > 0.015`: `R`, whose sensitivity is `∝ 1/(σ₂ + σ₃)`, stays well conditioned.
const POLAR_MIN_DET: f64 = 1e-4;

/// Polynomial phase once `‖XᵀX − I‖_F² <` this: every `σ² − 1 ∈ (−1, 1)`, inside the
/// convergence interval `(−1, 4/3)` of the cubic iteration.
const POLAR_NEAR: f64 = 1.0;

/// The cubic iteration stops after the step taken with `‖XᵀX − I‖_F² ≤` this: the error left is
/// about `(5/16)‖XᵀX − I‖³ ≤ 3e-16`.
const POLAR_TOL2: f64 = 1e-10;

/// Caps on Newton steps (at most 4 seen above [`POLAR_MIN_DET`]) and cubic steps (≤ 7 from
/// [`POLAR_NEAR`]); past them [`svd3`] decides.
const POLAR_MAX_NEWTON: usize = 20;
const POLAR_MAX_CUBIC: usize = 12;

/// `‖F‖_F²` range in which [`polar_rotation`] uses `F` as is (no over/underflow in `cof F`);
/// outside it `F` is first scaled by a power of two.
const POLAR_SAFE_NORM2: (f64, f64) = (1e-200, 1e200);

/// `2^e` for `-1022 ≤ e ≤ 1023`.
#[inline]
fn pow2(e: i32) -> f64 {
    f64::from_bits(((1023 + e) as u64) << 52)
}

/// `F · 2^k` with its largest |entry| in [1, 2) (exact), or `None` for a zero or non-finite `F`.
fn normalized(f: &DMat3) -> Option<DMat3> {
    if !f.is_finite() {
        return None;
    }
    let mut m = max_abs(f);
    if m == 0.0 {
        return None;
    }
    let mut g = *f;
    // Bring extreme (incl. subnormal) scales into range first, so 2^-e below stays normal.
    if m < pow2(-1000) {
        g *= pow2(600);
        m *= pow2(600);
    } else if m >= pow2(1000) {
        g *= pow2(-600);
        m *= pow2(-600);
    }
    let e = ((m.to_bits() >> 52) & 0x7ff) as i32 - 1023;
    Some(g * pow2(-e))
}

/// `R = U Vᵀ` of [`svd3`]'s rotation-variant decomposition (the fallback, kept out of line).
#[cold]
#[inline(never)]
fn rotation_from_svd(f: &DMat3) -> DMat3 {
    let d = svd3(f);
    d.u * d.v.transpose()
}

/// One scaled Newton step `½(ζX + ζ⁻¹X⁻ᵀ)`, `X⁻ᵀ = cof X / det X`, with the Frobenius
/// scaling `ζ = (‖X⁻¹‖_F/‖X‖_F)^{1/2}` (Higham 1986, §3); `None` unless `det X > 0`.
#[inline]
fn scaled_newton_step(x: &DMat3) -> Option<DMat3> {
    let cof = cofactor(x);
    let det = x.x_axis.dot(cof.x_axis);
    if det <= 0.0 {
        return None;
    }
    let zeta = ((ddot(&cof, &cof) / ddot(x, x)).sqrt().sqrt() / det).sqrt();
    Some(*x * (0.5 * zeta) + cof * (0.5 / (zeta * det)))
}

/// `XᵀX − I` and its squared Frobenius norm.
#[inline]
fn orthogonality_defect(x: &DMat3) -> (DMat3, f64) {
    let e = x.transpose() * *x - DMat3::IDENTITY;
    (e, ddot(&e, &e))
}

/// Rotation `R` of the polar decomposition `F = R S`, equal to `U Vᵀ` of [`svd3`] (a proper
/// rotation, also when `det F ≤ 0`) to rounding, several times faster.
///
/// For `det F` comfortably positive, with `X₀ = F √3/‖F‖_F` and `E = XᵀX − I`:
/// * while `‖E‖_F ≥ 1`, scaled Newton steps `X ← ½(ζX + ζ⁻¹X⁻ᵀ)` (Higham 1986, "Computing the
///   polar decomposition — with applications"), quadratic from any non-singular `X`;
/// * then the division-free cubic iteration `X ← X (I − ½E + ⅜E²)`, the second-order Taylor
///   polynomial of `(I + E)^{-1/2}` (Kovarik 1970; Björck & Bowie 1971), for which
///   `E' = ⅝E³ + O(E⁴)`.
///
/// Both act on the singular values only, so the limit is `U Vᵀ`. Inverted, near-singular,
/// zero or non-finite `F` (and non-convergence, never seen) use [`svd3`] (on `F` scaled by a
/// power of two when `‖F‖` is extreme), hence exactly `svd3(F)`'s rotation in the ordinary
/// floating-point range.
#[inline]
pub fn polar_rotation(f: &DMat3) -> DMat3 {
    let n2 = ddot(f, f);
    if n2 > POLAR_SAFE_NORM2.0 && n2 < POLAR_SAFE_NORM2.1 {
        polar_in_range(f, n2)
    } else {
        polar_rescaled(f)
    }
}

/// [`polar_rotation`] for `‖F‖_F²` outside [`POLAR_SAFE_NORM2`], zero or non-finite `F`.
#[cold]
#[inline(never)]
fn polar_rescaled(f: &DMat3) -> DMat3 {
    match normalized(f) {
        Some(g) => polar_in_range(&g, ddot(&g, &g)),
        None => rotation_from_svd(f),
    }
}

/// [`polar_rotation`] body for `n2 = ‖F‖_F²` in [`POLAR_SAFE_NORM2`].
#[inline]
fn polar_in_range(f: &DMat3, n2: f64) -> DMat3 {
    let mut x = *f * (3.0 / n2).sqrt();
    // F is finite here (‖F‖² < 1e200), so nothing below is NaN.
    if x.determinant() <= POLAR_MIN_DET {
        return rotation_from_svd(f);
    }
    let (mut e, mut e2) = orthogonality_defect(&x);
    let mut newton = 0;
    while e2 >= POLAR_NEAR {
        match scaled_newton_step(&x) {
            Some(next) if newton < POLAR_MAX_NEWTON => x = next,
            _ => return rotation_from_svd(f),
        }
        newton += 1;
        (e, e2) = orthogonality_defect(&x);
    }
    for _ in 0..POLAR_MAX_CUBIC {
        x *= DMat3::IDENTITY - e * 0.5 + (e * e) * 0.375;
        if e2 <= POLAR_TOL2 {
            return x;
        }
        (e, e2) = orthogonality_defect(&x);
    }
    rotation_from_svd(f)
}

/// Smallest magnitude allowed for `σ_j² − σ_i²` in [`svd3_adjoint`] (repeated singular values).
pub const SVD_GRAD_EPS: f64 = 1e-6;

#[inline]
fn guarded(d: f64) -> f64 {
    if d.abs() < SVD_GRAD_EPS {
        if d < 0.0 { -SVD_GRAD_EPS } else { SVD_GRAD_EPS }
    } else {
        d
    }
}

/// Adjoint of `F ↦ (U, σ, V)`: given `∂L/∂U`, `∂L/∂σ`, `∂L/∂V` returns `∂L/∂F`.
///
/// `F̄ = U P̄ Vᵀ`, `P̄_ii = σ̄_i`, `P̄_ij = (σ_j (A_ij − A_ji) + σ_i (B_ij − B_ji)) / (σ_j² − σ_i²)`
/// with `A = UᵀŪ`, `B = VᵀV̄`; the denominator is kept at least [`SVD_GRAD_EPS`] in magnitude.
pub fn svd3_adjoint(svd: &Svd, gu: &DMat3, gs: DVec3, gv: &DMat3) -> DMat3 {
    let a = svd.u.transpose() * *gu;
    let b = svd.v.transpose() * *gv;
    let s = svd.s;
    let mut cols = [DVec3::ZERO; 3];
    for (j, col) in cols.iter_mut().enumerate() {
        for i in 0..3 {
            col[i] = if i == j {
                gs[i]
            } else {
                let num =
                    s[j] * (el(&a, i, j) - el(&a, j, i)) + s[i] * (el(&b, i, j) - el(&b, j, i));
                num / guarded(s[j] * s[j] - s[i] * s[i])
            };
        }
    }
    svd.u * DMat3::from_cols(cols[0], cols[1], cols[2]) * svd.v.transpose()
}

/// Adjoint of the rotation `R = U Vᵀ` of the polar decomposition: `F̄ = U P̄ Vᵀ`,
/// `P̄_ij = (A_ij − A_ji)/(σ_i + σ_j)`, `A = Uᵀ R̄ V` (denominator guarded away from 0).
pub fn rotation_adjoint(svd: &Svd, gr: &DMat3) -> DMat3 {
    let a = svd.u.transpose() * *gr * svd.v;
    let s = svd.s;
    let mut p = DMat3::ZERO;
    for i in 0..3 {
        for j in 0..3 {
            if i != j {
                let d = guarded(s[i] + s[j]);
                p += outer(unit(i), unit(j)) * ((el(&a, i, j) - el(&a, j, i)) / d);
            }
        }
    }
    svd.u * p * svd.v.transpose()
}

#[inline]
fn unit(i: usize) -> DVec3 {
    match i {
        0 => DVec3::X,
        1 => DVec3::Y,
        _ => DVec3::Z,
    }
}

/// `|σ_j − σ_i|` below which [`divided_differences`] uses the Jacobian instead of the quotient.
pub const REPEATED_EPS: f64 = 1e-6;

/// Divided differences `D_ij = (f_j − f_i)/(σ_j − σ_i)` of a symmetric function `f(σ)` for
/// `i ≠ j`; at (nearly) repeated singular values the limit `∂f_j/∂σ_j − ∂f_j/∂σ_i` is used.
/// `jac.col(l)[k] = ∂f_k/∂σ_l`.
pub fn divided_differences(s: DVec3, f: DVec3, jac: &DMat3) -> DMat3 {
    let mut d = DMat3::ZERO;
    for i in 0..3 {
        for j in 0..3 {
            if i != j {
                let ds = s[j] - s[i];
                d.col_mut(j)[i] = if ds.abs() > REPEATED_EPS {
                    (f[j] - f[i]) / ds
                } else {
                    el(jac, j, j) - el(jac, j, i)
                };
            }
        }
    }
    d
}

/// Adjoint of `F ↦ (U diag(f(σ)) Vᵀ, U diag(t(σ)) Uᵀ)` for symmetric functions `f`, `t` of the
/// singular values (isotropic response), exact at repeated singular values:
/// `F̄ = U P̄ Vᵀ`, `P̄_ii = σ̄_i`, and for `i ≠ j` with `M = UᵀḠ_F V`, `S = Uᵀ(Ḡ_τ + Ḡ_τᵀ)U`:
/// `P̄_ij = ½(M_ij + M_ji) D^f_ij + ½(M_ij − M_ji)(f_i + f_j)/(σ_i + σ_j)
///        + ½ S_ij D^t_ij + ½ S_ij (t_j − t_i)/(σ_i + σ_j)`.
/// `g_s` is the full gradient on σ (through every scalar path), `df`, `dtau` the divided
/// differences of `f` and `t` ([`divided_differences`]).
#[allow(clippy::too_many_arguments)]
pub fn isotropic_adjoint(
    svd: &Svd,
    g_f: &DMat3,
    f: DVec3,
    df: &DMat3,
    g_tau: &DMat3,
    t: DVec3,
    dtau: &DMat3,
    g_s: DVec3,
) -> DMat3 {
    let m = svd.u.transpose() * *g_f * svd.v;
    let sm = svd.u.transpose() * (*g_tau + g_tau.transpose()) * svd.u;
    let s = svd.s;
    let mut p = DMat3::from_diagonal(g_s);
    for i in 0..3 {
        for j in 0..3 {
            if i != j {
                let (mij, mji, sij) = (el(&m, i, j), el(&m, j, i), el(&sm, i, j));
                let sum = guarded(s[i] + s[j]);
                let v = 0.5 * (mij + mji) * el(df, i, j)
                    + 0.5 * (mij - mji) * (f[i] + f[j]) / sum
                    + 0.5 * sij * el(dtau, i, j)
                    + 0.5 * sij * (t[j] - t[i]) / sum;
                p.col_mut(j)[i] = v;
            }
        }
    }
    svd.u * p * svd.v.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(f: DMat3) {
        let d = svd3(&f);
        let r = d.compose(d.s);
        assert!(
            crate::math::max_abs(&(r - f)) < 1e-13 * crate::math::max_abs(&f).max(1.0),
            "{f:?} {d:?}"
        );
        assert!((d.u.determinant() - 1.0).abs() < 1e-13);
        assert!((d.v.determinant() - 1.0).abs() < 1e-13);
        assert!(d.s[0] >= d.s[1] && d.s[1] >= d.s[2].abs());
    }

    #[test]
    fn reconstructs() {
        check(DMat3::IDENTITY);
        check(DMat3::ZERO);
        check(DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0)));
        check(DMat3::from_diagonal(DVec3::new(0.0, 2.0, 0.0)));
        check(crate::math::from_rows([
            [1.0, 0.2, 0.3],
            [0.1, 0.9, -0.2],
            [0.05, 0.3, 1.1],
        ]));
        check(crate::math::from_rows([
            [0.0, 1.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
        ]));
        check(crate::math::from_rows([
            [1.0, 2.0, 3.0],
            [2.0, 4.0, 6.0],
            [1.0, 1.0, 1.0],
        ]));
    }

    #[test]
    fn adjoint_matches_finite_differences() {
        let f = crate::math::from_rows([[1.1, 0.2, 0.3], [0.1, 0.9, -0.2], [0.05, 0.3, 0.7]]);
        let wu = crate::math::from_rows([[0.3, -0.2, 0.5], [0.1, 0.4, -0.6], [0.7, 0.2, 0.1]]);
        let wv = crate::math::from_rows([[-0.3, 0.8, 0.2], [0.5, -0.1, 0.3], [0.2, 0.6, -0.4]]);
        let ws = DVec3::new(0.3, -0.7, 1.1);
        let loss = |f: &DMat3| {
            let d = svd3(f);
            crate::math::ddot(&d.u, &wu) + d.s.dot(ws) + crate::math::ddot(&d.v, &wv)
        };
        let d = svd3(&f);
        let g = svd3_adjoint(&d, &wu, ws, &wv);
        let gr = rotation_adjoint(&d, &wu);
        let rloss = |f: &DMat3| {
            let d = svd3(f);
            crate::math::ddot(&(d.u * d.v.transpose()), &wu)
        };
        let h = 1e-6;
        for r in 0..3 {
            for c in 0..3 {
                let mut fp = f;
                let mut fm = f;
                fp.col_mut(c)[r] += h;
                fm.col_mut(c)[r] -= h;
                let fd = (loss(&fp) - loss(&fm)) / (2.0 * h);
                assert!(
                    (fd - el(&g, r, c)).abs() < 1e-7,
                    "svd ({r},{c}) {fd} {}",
                    el(&g, r, c)
                );
                let fdr = (rloss(&fp) - rloss(&fm)) / (2.0 * h);
                assert!(
                    (fdr - el(&gr, r, c)).abs() < 1e-7,
                    "rot ({r},{c}) {fdr} {}",
                    el(&gr, r, c)
                );
            }
        }
    }
}
