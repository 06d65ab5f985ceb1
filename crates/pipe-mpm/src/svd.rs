//! 3x3 singular value decomposition `F = U diag(σ) Vᵀ` (one-sided Jacobi, warm-started), the
//! polar rotation, and their adjoints.
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

/// Beyond this `|ζ|` the Jacobi rotation is `t = 1/(2ζ)`, `c = 1` to rounding (`t² < ε/2`).
const SMALL_ANGLE_ZETA: f64 = 1e8;

/// [`svd3`] starts from `V₀ = I` when the eigenvalues of `GᵀG` spread less than this
/// (relative variance `p²/q²`): `F` is then a multiple of a rotation to rounding.
const WARM_MIN_SPREAD: f64 = 1e-30;

thread_local! {
    /// Set by [`with_jacobi_svd`]: [`svd3`] runs cold-started [`svd3_jacobi`] on this thread.
    static FORCE_JACOBI: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `body` with [`svd3`] replaced by [`svd3_jacobi`] on the current thread (the reference
/// the fast path is tested against, also through the models). Not for production use.
#[doc(hidden)]
pub fn with_jacobi_svd<T>(body: impl FnOnce() -> T) -> T {
    struct Reset(bool);
    impl Drop for Reset {
        fn drop(&mut self) {
            FORCE_JACOBI.with(|c| c.set(self.0));
        }
    }
    let _reset = Reset(FORCE_JACOBI.with(|c| c.replace(true)));
    body()
}

/// SVD in the rotation-variant convention: one-sided Jacobi (as [`svd3_jacobi`]) warm-started
/// from an analytic eigenbasis of `FᵀF` (`warm_start`): typically one rotation and four
/// checks remain instead of ~9 rotations in 4 sweeps (about 2.6× faster overall).
///
/// `F` is first scaled by a power of two (exact) to a largest |entry| in `[1, 2)`, so neither
/// `FᵀF` nor the Jacobi dot products over/underflow; `σ` is scaled back at the end. Zero and
/// non-finite `F` go to [`svd3_jacobi`] unchanged. The Jacobi sweeps keep the accuracy of the
/// cold start (same stopping test); only the singular vectors of repeated singular values, which
/// are not unique, may differ from [`svd3_jacobi`]'s.
pub fn svd3(f: &DMat3) -> Svd {
    if FORCE_JACOBI.with(std::cell::Cell::get) {
        return svd3_jacobi(f);
    }
    match normalized_exp(f) {
        Some((g, k)) => {
            let mut d = jacobi_sweeps(&g, warm_start(&g));
            d.s = scale_pow2(d.s, -k);
            d
        }
        None => jacobi_sweeps(f, [DVec3::X, DVec3::Y, DVec3::Z]),
    }
}

/// Reference SVD: one-sided Jacobi rotations (Hestenes 1958) on the columns of `F` from
/// `V₀ = I` (accurate for small σ too), on `F` scaled by a power of two as in [`svd3`].
pub fn svd3_jacobi(f: &DMat3) -> Svd {
    match normalized_exp(f) {
        Some((g, k)) => {
            let mut d = jacobi_sweeps(&g, [DVec3::X, DVec3::Y, DVec3::Z]);
            d.s = scale_pow2(d.s, -k);
            d
        }
        None => jacobi_sweeps(f, [DVec3::X, DVec3::Y, DVec3::Z]),
    }
}

/// Largest root `β = 2 cos(acos(x)/3) ∈ [√3, 2]` of `f(β) = β³ − 3β − 2x` for `x ∈ [0, 1]`: a
/// quintic Chebyshev fit in `2x − 1` (error < 1.4e-6), then one Halley step
/// `β − 2ff'/(2f'² − ff'')` (cubic convergence, error ≤ 1 ulp).
#[inline]
fn isolated_root(x: f64) -> f64 {
    let t = 2.0 * x - 1.0;
    let t2 = t * t;
    let beta = (1.879_384_278_453_401_8 + 0.131_643_869_244_633_48 * t)
        + t2 * ((-0.012_845_561_350_967_037 + 0.002_208_744_742_729_177_5 * t)
            + t2 * (-0.000_512_274_646_764_806 + 0.000_121_706_350_640_534_32 * t));
    let f = beta * (beta * beta - 3.0) - 2.0 * x;
    let df = 3.0 * (beta * beta - 1.0);
    beta - 2.0 * f * df / (2.0 * df * df - 6.0 * f * beta)
}

/// Orthonormal start `V₀ = [a, b, e]` (det +1) for [`jacobi_sweeps`] on `G`: `e` is the unit
/// eigenvector of the most isolated eigenvalue `λ` of `C = GᵀG`, `a, b` complete the basis.
///
/// With `q = tr C/3`, `p² = ‖C − qI‖_F²/6`, `r = det(C − qI)/(2p³)`, the eigenvalues are
/// `q + 2p cos(acos(r)/3 + 2πk/3)` (Smith 1961, CACM 4(4):168); the isolated one,
/// `λ = q ± 2p cos(acos|r|/3)` with the sign of `r` ([`isolated_root`]), is well conditioned in
/// `r` also at a double eigenvalue (`|r| → 1`). `e` is the largest cross product of two rows of `C − λI`
/// (Kopp 2008, arXiv:physics/0610206). Then the columns `G a`, `G b` need one rotation and
/// `G e` is orthogonal to both to rounding. `I` when `C` is (nearly) a multiple of `I` or on
/// any breakdown; the sweeps converge from any orthonormal start.
#[inline]
fn warm_start(g: &DMat3) -> [DVec3; 3] {
    const IDENTITY: [DVec3; 3] = [DVec3::X, DVec3::Y, DVec3::Z];
    let (g0, g1, g2) = (g.x_axis, g.y_axis, g.z_axis);
    let (c00, c11, c22) = (g0.dot(g0), g1.dot(g1), g2.dot(g2));
    let (c01, c02, c12) = (g0.dot(g1), g0.dot(g2), g1.dot(g2));
    let q = (c00 + c11 + c22) * (1.0 / 3.0);
    let (d0, d1, d2) = (c00 - q, c11 - q, c22 - q);
    let p2 = (d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (c01 * c01 + c02 * c02 + c12 * c12)) / 6.0;
    // G is finite (normalised), so p2 is not NaN.
    if p2 <= WARM_MIN_SPREAD * q * q {
        return IDENTITY;
    }
    // r = det/(2p³) with the division and the square root side by side.
    let (p, ip2) = (p2.sqrt(), 1.0 / p2);
    let det =
        d0 * (d1 * d2 - c12 * c12) - c01 * (c01 * d2 - c12 * c02) + c02 * (c01 * c12 - d1 * c02);
    let r = (0.5 * det * p * (ip2 * ip2)).clamp(-1.0, 1.0);
    let lam = q + (p * isolated_root(r.abs())).copysign(r);
    let m0 = DVec3::new(c00 - lam, c01, c02);
    let m1 = DVec3::new(c01, c11 - lam, c12);
    let m2 = DVec3::new(c02, c12, c22 - lam);
    let (x01, x02, x12) = (m0.cross(m1), m0.cross(m2), m1.cross(m2));
    let (n01, n02, n12) = (
        x01.length_squared(),
        x02.length_squared(),
        x12.length_squared(),
    );
    let (mut x, mut n) = (x01, n01);
    if n02 > n {
        (x, n) = (x02, n02);
    }
    if n12 > n {
        (x, n) = (x12, n12);
    }
    if !(n > 0.0 && n.is_finite()) {
        return IDENTITY;
    }
    // Branchless orthonormal basis {a, b} of e⊥ with a × b = e (Duff et al. 2017, JCGT 6(1)),
    // written for e = x/L so that one division serves both 1/L and the basis.
    let l = n.sqrt();
    let sign = 1.0f64.copysign(x.z);
    let k = sign * l + x.z; // |k| ≥ L
    let dk = 1.0 / (l * k);
    let inv_l = k * dk;
    let xy = x.x * x.y * dk;
    let a = DVec3::new(1.0 - sign * x.x * x.x * dk, -sign * xy, -sign * x.x * inv_l);
    let b = DVec3::new(-xy, sign - x.y * x.y * dk, -x.y * inv_l);
    [a, b, x * inv_l]
}

/// `(c, s)` of the Jacobi rotation for `τ = (β − α)/2` and `γ ≠ 0` (see [`jacobi_sweeps`]):
/// `(1, γ/(2τ))` once `|τ| > 10⁸ |γ|` (then `t² < ε/2`), else the closed form; `ζ = τ/γ`
/// (Rutishauser's form) when `h` or `w` would leave the normal range.
#[inline]
fn jacobi_rotation(tau: f64, gamma: f64) -> (f64, f64) {
    if tau.abs() > SMALL_ANGLE_ZETA * gamma.abs() {
        return (1.0, gamma / (2.0 * tau));
    }
    let h = (tau * tau + gamma * gamma).sqrt();
    let ht = h + tau.abs();
    let w = (2.0 * h * ht).sqrt();
    if w > 1e-150 && w < 1e150 {
        let inv = 1.0 / w;
        (ht * inv, tau.signum() * gamma * inv)
    } else {
        let zeta = tau / gamma;
        let t = zeta.signum() / (zeta.abs() + (1.0 + zeta * zeta).sqrt());
        let c = 1.0 / (1.0 + t * t).sqrt();
        (c, c * t)
    }
}

/// One-sided Jacobi sweeps (Hestenes 1958) on the columns of `B = F V₀`, `V₀` orthonormal,
/// cyclic over the pairs `(0,1), (0,2), (1,2)` until three pairs in a row are orthogonal to
/// [`ORTHO_TOL`]. A pair with `α = |b_p|²`, `β = |b_q|²`, `γ = b_p·b_q` is rotated by
/// `c = (h + |τ|)/w`, `s = sign(τ) γ/w`, `τ = (β − α)/2`, `h = √(τ² + γ²)`, `w = √(2h(h + |τ|))`
/// (i.e. `t = s/c = sign ζ/(|ζ| + √(1+ζ²))`, `ζ = τ/γ`), which makes it orthogonal. Then
/// `σ_i = |b_i|`, `u_i = b_i/σ_i`, sorted and signed to the rotation-variant convention.
fn jacobi_sweeps(f: &DMat3, v0: [DVec3; 3]) -> Svd {
    let mut b = [*f * v0[0], *f * v0[1], *f * v0[2]];
    let mut v = v0;
    let mut passes = 0;
    'sweeps: for _sweep in 0..30 {
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let alpha = b[p].length_squared();
            let beta = b[q].length_squared();
            let gamma = b[p].dot(b[q]);
            // |γ| ≤ tol √α √β, squared: F is normalised in svd3 and svd3_jacobi, so nothing
            // overflows (two columns below ~1e-70 of the largest entry count as orthogonal).
            if gamma * gamma <= (ORTHO_TOL * ORTHO_TOL) * alpha * beta {
                passes += 1;
                if passes == 3 {
                    break 'sweeps;
                }
                continue;
            }
            passes = 0;
            let tau = 0.5 * (beta - alpha);
            let (c, s) = jacobi_rotation(tau, gamma);
            let (bp, bq) = (b[p], b[q]);
            b[p] = c * bp - s * bq;
            b[q] = s * bp + c * bq;
            let (vp, vq) = (v[p], v[q]);
            v[p] = c * vp - s * vq;
            v[q] = s * vp + c * vq;
        }
    }
    let n2 = [
        b[0].length_squared(),
        b[1].length_squared(),
        b[2].length_squared(),
    ];
    let n = n2.map(f64::sqrt);
    // 1/σ = σ/σ², the division beside the square root.
    let inv = n2.map(|x| 1.0 / x);
    // Stable descending order of the columns (ties keep their order), without branches:
    // code = [n₁ > n₀] + 2[n₂ > n₀] + 4[n₂ > n₁]; inconsistent codes (NaN) keep the order.
    let code = (n2[1] > n2[0]) as usize
        | ((n2[2] > n2[0]) as usize) << 1
        | ((n2[2] > n2[1]) as usize) << 2;
    let (perm, odd) = SORT_DESC[code];
    let mut sig = perm.map(|i| n[i]);
    let scale = sig[0].max(f64::MIN_POSITIVE);
    let u0 = if sig[0] > 0.0 {
        b[perm[0]] * (sig[0] * inv[perm[0]])
    } else {
        DVec3::X
    };
    let u1 = if sig[1] > TINY * scale {
        b[perm[1]] * (sig[1] * inv[perm[1]])
    } else {
        u0.any_orthonormal_vector()
    };
    let mut u2 = if sig[2] > TINY * scale {
        b[perm[2]] * (sig[2] * inv[perm[2]])
    } else {
        u0.cross(u1)
    };
    let mut vm = DMat3::from_cols(v[perm[0]], v[perm[1]], v[perm[2]]);
    // The rotations keep det V = det V₀ = +1, so the permutation's parity is det V.
    if odd {
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

/// Descending order and its parity for each comparison code of [`jacobi_sweeps`].
const SORT_DESC: [([usize; 3], bool); 8] = [
    ([0, 1, 2], false), // none
    ([1, 0, 2], true),  // n₁ > n₀ ≥ n₂
    ([0, 1, 2], false), // impossible
    ([1, 2, 0], false), // n₁ ≥ n₂ > n₀
    ([0, 2, 1], true),  // n₀ ≥ n₂ > n₁
    ([0, 1, 2], false), // impossible
    ([2, 0, 1], false), // n₂ > n₀ ≥ n₁
    ([2, 1, 0], true),  // n₂ > n₁ > n₀
];

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

/// `(F · 2^k, k)` with the largest |entry| of `F · 2^k` in [1, 2) (exact), or `None` for a zero
/// or non-finite `F`.
fn normalized_exp(f: &DMat3) -> Option<(DMat3, i32)> {
    if !f.is_finite() {
        return None;
    }
    let mut m = max_abs(f);
    if m == 0.0 {
        return None;
    }
    let mut g = *f;
    let mut k = 0;
    // Bring extreme (incl. subnormal) scales into range first, so 2^-e below stays normal.
    if m < pow2(-1000) {
        g *= pow2(600);
        m *= pow2(600);
        k = 600;
    } else if m >= pow2(1000) {
        g *= pow2(-600);
        m *= pow2(-600);
        k = -600;
    }
    let e = ((m.to_bits() >> 52) & 0x7ff) as i32 - 1023;
    Some((g * pow2(-e), k - e))
}

/// `F · 2^k` with its largest |entry| in [1, 2) (exact), or `None` for a zero or non-finite `F`.
#[inline]
fn normalized(f: &DMat3) -> Option<DMat3> {
    normalized_exp(f).map(|(g, _)| g)
}

/// `x · 2^k` for `|k| ≤ 1623` (two exact steps when `2^k` itself is out of range).
#[inline]
fn scale_pow2(x: DVec3, k: i32) -> DVec3 {
    if k == 0 {
        x
    } else if (-1000..=1000).contains(&k) {
        x * pow2(k)
    } else {
        let h = k / 2;
        x * pow2(h) * pow2(k - h)
    }
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
#[inline(always)]
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
#[inline(always)]
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

/// Adjoint of the polar rotation `R` of `F = R S` without an SVD, given `R` itself: with
/// `dR = R [ω]×`, `Rᵀ dF − dFᵀ R = [ω]× S + S [ω]× = [(tr S · I − S) ω]×`, so for `M = Rᵀ R̄`
/// and `m = (M₃₂ − M₂₃, M₁₃ − M₃₁, M₂₁ − M₁₂)`: `F̄ = R [z]×` with `(tr S · I − S) z = m`.
/// The matrix has eigenvalues `σᵢ + σⱼ`, as in [`rotation_adjoint`]. `None` when `det F ≤ 0`
/// or `(σ₁+σ₂)(σ₁+σ₃)(σ₂+σ₃) ≤ 1e-6 (σ₁+σ₂+σ₃)³` (use [`rotation_adjoint`] there).
#[inline(always)]
pub fn polar_rotation_adjoint(f: &DMat3, r: &DMat3, gr: &DMat3) -> Option<DMat3> {
    let s = r.transpose() * *f;
    let s = (s + s.transpose()) * 0.5;
    let t = s.x_axis.x + s.y_axis.y + s.z_axis.z;
    let k = DMat3::from_diagonal(DVec3::splat(t)) - s;
    let det_k = k.determinant();
    if !(f.determinant() > 0.0 && det_k > 1e-6 * t * t * t) {
        return None;
    }
    let m = r.transpose() * *gr;
    let mv = DVec3::new(
        el(&m, 2, 1) - el(&m, 1, 2),
        el(&m, 0, 2) - el(&m, 2, 0),
        el(&m, 1, 0) - el(&m, 0, 1),
    );
    // K is symmetric: K⁻¹ = cof K / det K.
    let z = crate::math::cofactor(&k) * mv / det_k;
    let skew = DMat3::from_cols(
        DVec3::new(0.0, z.z, -z.y),
        DVec3::new(-z.z, 0.0, z.x),
        DVec3::new(z.y, -z.x, 0.0),
    );
    Some(*r * skew)
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
