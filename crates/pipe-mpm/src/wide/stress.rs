//! Steps 1–4 of a substep on vectors of particles: `F_tmp = (I + dt C) F`, the model's return
//! mapping and Kirchhoff stress τ, and the APIC affine matrix `A = −dt V (4/dx²) τ + m C` that
//! P2G scatters. The elastic models run as lane kernels; the others particle by particle
//! through [`Constitutive::update_with_aux`] in `f64` (their return maps need an SVD).

use glam::DMat3;

use super::simd::{Real, Wide, WideOp};
use crate::math::{from_rows, to_rows};
use crate::models::{Constitutive, LaneKernel, particle_model};
use crate::state::{FamilyParams, Material};
use crate::svd::polar_rotation;

/// A 3×3 matrix of lanes, row-major (`m[3r + c]`).
pub(crate) type Mat<W> = [<W as Wide>::V; 9];

/// `a b`.
#[inline(always)]
pub(crate) fn mul<W: Wide>(w: W, a: &Mat<W>, b: &Mat<W>) -> Mat<W> {
    arr!(9, |k| {
        let (r, c) = (k / 3, k % 3);
        w.fma(
            a[3 * r + 2],
            b[6 + c],
            w.fma(a[3 * r + 1], b[3 + c], w.mul(a[3 * r], b[c])),
        )
    })
}

/// `a bᵀ`.
#[inline(always)]
pub(crate) fn mul_bt<W: Wide>(w: W, a: &Mat<W>, b: &Mat<W>) -> Mat<W> {
    arr!(9, |k| {
        let (r, c) = (k / 3, k % 3);
        w.fma(
            a[3 * r + 2],
            b[3 * c + 2],
            w.fma(a[3 * r + 1], b[3 * c + 1], w.mul(a[3 * r], b[3 * c])),
        )
    })
}

/// `aᵀ b`.
#[inline(always)]
pub(crate) fn mul_at<W: Wide>(w: W, a: &Mat<W>, b: &Mat<W>) -> Mat<W> {
    arr!(9, |k| {
        let (r, c) = (k / 3, k % 3);
        w.fma(
            a[6 + r],
            b[6 + c],
            w.fma(a[3 + r], b[3 + c], w.mul(a[r], b[c])),
        )
    })
}

/// Cofactor matrix `∂ det / ∂a` (`det a · a⁻ᵀ`).
#[inline(always)]
pub(crate) fn cofactor<W: Wide>(w: W, a: &Mat<W>) -> Mat<W> {
    let m = |i: usize, j: usize, k: usize, l: usize| (i, j, k, l);
    let idx = [
        m(4, 8, 5, 7),
        m(5, 6, 3, 8),
        m(3, 7, 4, 6),
        m(2, 7, 1, 8),
        m(0, 8, 2, 6),
        m(1, 6, 0, 7),
        m(1, 5, 2, 4),
        m(2, 3, 0, 5),
        m(0, 4, 1, 3),
    ];
    arr!(9, |k| {
        let (i, j, p, q) = idx[k];
        w.sub(w.mul(a[i], a[j]), w.mul(a[p], a[q]))
    })
}

/// `Σ a_ij b_ij`.
#[inline(always)]
pub(crate) fn ddot<W: Wide>(w: W, a: &Mat<W>, b: &Mat<W>) -> W::V {
    let mut s = w.mul(a[0], b[0]);
    for k in 1..9 {
        s = w.fma(a[k], b[k], s);
    }
    s
}

/// Row 0 of `a` dotted with row 0 of its cofactor: `det a`.
#[inline(always)]
pub(crate) fn det_with<W: Wide>(w: W, a: &Mat<W>, cof: &Mat<W>) -> W::V {
    w.fma(a[2], cof[2], w.fma(a[1], cof[1], w.mul(a[0], cof[0])))
}

/// `F_tmp = (I + dt C) F = F + dt (C F)`.
#[inline(always)]
pub(crate) fn predict<W: Wide>(w: W, c: &Mat<W>, f: &Mat<W>, dt: W::V) -> Mat<W> {
    let cf = mul(w, c, f);
    arr!(9, |k| w.fma(dt, cf[k], f[k]))
}

/// Neo-Hookean `τ = μ F Fᵀ + (λ ln J − μ) I` and `ln J`.
#[inline(always)]
pub(crate) fn neo_hookean<W: Wide>(w: W, f: &Mat<W>, mu: W::V, lam: W::V) -> (Mat<W>, W::V) {
    let ln_j = w.ln(det_with(w, f, &cofactor(w, f)));
    let b = mul_bt(w, f, f);
    let diag = w.sub(w.mul(lam, ln_j), mu);
    let tau = arr!(9, |k| {
        let t = w.mul(mu, b[k]);
        if k.is_multiple_of(4) {
            w.add(t, diag)
        } else {
            t
        }
    });
    (tau, ln_j)
}

/// `XᵀX − I` and its squared norm.
#[inline(always)]
fn defect<W: Wide>(w: W, x: &Mat<W>) -> (Mat<W>, W::V) {
    let mut e = mul_at(w, x, x);
    for k in [0, 4, 8] {
        e[k] = w.sub(e[k], w.c(1.0));
    }
    let e2 = ddot(w, &e, &e);
    (e, e2)
}

/// Largest lane value.
#[inline(always)]
fn lane_max<W: Wide>(w: W, v: W::V) -> W::T {
    let a = w.lanes(v);
    a[1..W::T::N]
        .iter()
        .fold(a[0], |m, &x| if x > m { x } else { m })
}

/// Rotation of the polar decomposition of every lane, as [`polar_rotation`] computes it
/// (scaled Newton steps while `‖XᵀX − I‖² ≥ 1`, then the cubic iteration), all lanes stepping
/// together; lanes that are inverted, near-singular, extreme or not converged get
/// [`polar_rotation`] itself (in `f64`).
#[inline(always)]
pub(crate) fn polar<W: Wide>(w: W, f: &Mat<W>) -> Mat<W> {
    let n2 = ddot(w, f, f);
    let mut x: Mat<W> = {
        let s = w.sqrt(w.div(w.c(3.0), n2));
        arr!(9, |k| w.mul(f[k], s))
    };
    let cof = cofactor(w, &x);
    let det0 = det_with(w, &x, &cof);
    // Lanes the iteration may not take: det X ≤ 1e-4 (as polar_rotation), ‖F‖² out of range.
    let (lo, hi) = if W::T::N == 8 {
        (1e-30, 1e30)
    } else {
        (1e-200, 1e200)
    };
    let mut bad = (w.lanes(det0).iter().zip(w.lanes(n2).iter()))
        .take(W::T::N)
        .enumerate()
        .fold(0u32, |m, (i, (d, n))| {
            let ok = d.f64() > 1e-4 && n.f64() > lo && n.f64() < hi;
            m | (u32::from(!ok) << i)
        });
    if bad != (1 << W::T::N) - 1 {
        let (mut e, mut e2) = defect(w, &x);
        let mut steps = 0;
        while lane_max(w, e2).f64() >= 1.0 && steps < 20 {
            // X ← ½(ζX + ζ⁻¹X⁻ᵀ), ζ = (‖X⁻¹‖/‖X‖)^½ with ‖X⁻¹‖ = ‖cof X‖/det X.
            let cof = cofactor(w, &x);
            let det = det_with(w, &x, &cof);
            let q = w.sqrt(w.sqrt(w.div(ddot(w, &cof, &cof), ddot(w, &x, &x))));
            let zeta = w.sqrt(w.div(q, det));
            let a = w.mul(w.c(0.5), zeta);
            let b = w.div(w.c(0.5), w.mul(zeta, det));
            x = arr!(9, |k| w.fma(a, x[k], w.mul(b, cof[k])));
            (e, e2) = defect(w, &x);
            steps += 1;
        }
        let tol = if W::T::N == 8 { 1e-9 } else { 1e-10 };
        let mut converged = false;
        for _ in 0..12 {
            // X ← X (I − ½E + ⅜E²).
            let e_sq = mul(w, &e, &e);
            let p: Mat<W> = arr!(9, |k| {
                let t = w.fma(w.c(0.375), e_sq[k], w.mul(w.c(-0.5), e[k]));
                if k.is_multiple_of(4) {
                    w.add(t, w.c(1.0))
                } else {
                    t
                }
            });
            x = mul(w, &x, &p);
            if lane_max(w, e2).f64() <= tol {
                converged = true;
                break;
            }
            (e, e2) = defect(w, &x);
        }
        // NaN e2 (never below tol) also ends here unconverged.
        if !converged {
            bad = (1 << W::T::N) - 1;
        }
    }
    if bad != 0 {
        let mut lanes: [[W::T; 8]; 9] = std::array::from_fn(|k| w.lanes(x[k]));
        let fl: [[W::T; 8]; 9] = std::array::from_fn(|k| w.lanes(f[k]));
        for i in (0..W::T::N).filter(|i| bad & (1 << i) != 0) {
            let r = polar_rotation(&from_rows(std::array::from_fn(|r| {
                std::array::from_fn(|c| fl[3 * r + c][i].f64())
            })));
            let rows = to_rows(&r);
            for k in 0..9 {
                lanes[k][i] = W::T::of(rows[k / 3][k % 3]);
            }
        }
        x = std::array::from_fn(|k| w.vector(lanes[k]));
    }
    x
}

/// Fixed-corotated `τ = 2μ (F − R) Fᵀ + λ J (J − 1) I`.
#[inline(always)]
pub(crate) fn fixed_corotated<W: Wide>(w: W, f: &Mat<W>, mu: W::V, lam: W::V) -> Mat<W> {
    let r = polar(w, f);
    let j = det_with(w, f, &cofactor(w, f));
    let fr: Mat<W> = arr!(9, |k| w.sub(f[k], r[k]));
    let p = mul_bt(w, &fr, f);
    let two_mu = w.add(mu, mu);
    let diag = w.mul(w.mul(lam, j), w.sub(j, w.c(1.0)));
    arr!(9, |k| {
        let t = w.mul(two_mu, p[k]);
        if k.is_multiple_of(4) {
            w.add(t, diag)
        } else {
            t
        }
    })
}

/// Particles `i..` of a per-particle array, or its first value everywhere when `uniform`.
#[inline(always)]
pub(crate) fn lane_of<W: Wide>(w: W, v: &[W::T], i: usize, uniform: bool) -> W::V {
    if uniform {
        w.splat(v[0])
    } else {
        w.load(&v[i..])
    }
}

/// `v[r]`, or `v` itself when empty (a per-particle array that is only kept when needed).
fn part<T>(v: &[T], r: std::ops::Range<usize>) -> &[T] {
    if v.is_empty() { v } else { &v[r] }
}

/// The slots `r` of a per-particle array, or all of it when `uniform` (one value).
fn per_slot<T>(v: &[T], r: std::ops::Range<usize>, uniform: bool) -> &[T] {
    if uniform { v } else { &v[r] }
}

/// The per-particle material of some slots: mass (kg), volume (m³), μ and λ (Pa) in `T`, one
/// value each when `uniform`; and the `f64` μ, λ and family parameters the per-particle
/// models read (empty unless a per-particle model or family parameters need them).
#[derive(Clone, Copy)]
pub(crate) struct SlotMaterial<'a, T> {
    pub uniform: bool,
    pub mass: &'a [T],
    pub volume: &'a [T],
    pub mu: &'a [T],
    pub lam: &'a [T],
    pub mu64: &'a [f64],
    pub lam64: &'a [f64],
    pub family: &'a [FamilyParams],
}

impl<'a, T> SlotMaterial<'a, T> {
    /// `[mass, volume, μ, λ]` in slot order and the slot-order `f64` material `mat`.
    pub fn new(t: [&'a [T]; 4], mat: &'a Material, uniform: bool) -> Self {
        let [mass, volume, mu, lam] = t;
        Self {
            uniform,
            mass,
            volume,
            mu,
            lam,
            mu64: &mat.mu,
            lam64: &mat.lam,
            family: &mat.family,
        }
    }

    /// Slots `r` of this material, of which the first `real` hold particles (the rest
    /// padding: the `f64` arrays have no entries for it).
    pub fn slots(&self, r: std::ops::Range<usize>, real: usize) -> Self {
        let rr = r.start..r.start + real;
        let u = self.uniform;
        Self {
            uniform: u,
            mass: per_slot(self.mass, r.clone(), u),
            volume: per_slot(self.volume, r.clone(), u),
            mu: per_slot(self.mu, r.clone(), u),
            lam: per_slot(self.lam, r, u),
            mu64: part(self.mu64, rr.clone()),
            lam64: part(self.lam64, rr.clone()),
            family: part(self.family, rr),
        }
    }
}

/// Where the stress pass keeps τ (per-particle models only) and the model's scalar, if at all.
pub(crate) type Kept<'a, T> = Option<(Option<[&'a mut [T]; 9]>, &'a mut [T])>;

/// One task of the stress pass: particles `0..len` of its slices (`len` a multiple of the
/// lanes; the first `real` are particles, the rest padding at rest).
pub(crate) struct StressTask<'a, T, M> {
    pub model: &'a M,
    pub dt: f64,
    /// `4/dx²` (1/m²).
    pub d_inv: f64,
    pub real: usize,
    pub c: [&'a [T]; 9],
    pub mat: SlotMaterial<'a, T>,
    /// `F` in (when separate from the output) and new `F` out (in place otherwise).
    pub f0: Option<[&'a [T]; 9]>,
    pub f: [&'a mut [T]; 9],
    /// `A` out.
    pub a: [&'a mut [T]; 9],
    /// τ (for the per-particle models; the lane models' adjoints recompute it) and the
    /// model's scalar ([`Constitutive::update_with_aux`]) out, when kept.
    pub keep: Kept<'a, T>,
}

impl<T: Real, M: Constitutive> WideOp<T> for StressTask<'_, T, M> {
    /// Whether some new `F` is NaN/Inf.
    type Output = bool;

    #[inline(always)]
    fn with<W: Wide<T = T>>(self, w: W) -> bool {
        match M::LANE_KERNEL {
            LaneKernel::PerParticle => self.per_particle(),
            kernel => self.lanes(w, kernel),
        }
    }
}

impl<T: Real, M: Constitutive> StressTask<'_, T, M> {
    #[inline(always)]
    fn lanes<W: Wide<T = T>>(mut self, w: W, kernel: LaneKernel) -> bool {
        let n = T::N;
        let dt = w.c(self.dt);
        let k = w.c(-self.dt * self.d_inv);
        let mut bad = 0;
        for i in (0..self.f[0].len()).step_by(n) {
            let c: Mat<W> = arr!(9, |j| w.load(&self.c[j][i..]));
            let f0: Mat<W> = match &self.f0 {
                Some(f0) => arr!(9, |j| w.load(&f0[j][i..])),
                None => arr!(9, |j| w.load(&self.f[j][i..])),
            };
            let ft = predict(w, &c, &f0, dt);
            let (mat, u) = (&self.mat, self.mat.uniform);
            let (mu, lam) = (lane_of(w, mat.mu, i, u), lane_of(w, mat.lam, i, u));
            let (tau, aux) = match kernel {
                LaneKernel::NeoHookean => neo_hookean(w, &ft, mu, lam),
                _ => (fixed_corotated(w, &ft, mu, lam), w.zero()),
            };
            let kv = w.mul(k, lane_of(w, mat.volume, i, u));
            let m = lane_of(w, mat.mass, i, u);
            for j in 0..9 {
                bad |= w.non_finite_mask(ft[j]);
                w.store(ft[j], &mut self.f[j][i..]);
                w.store(w.fma(kv, tau[j], w.mul(m, c[j])), &mut self.a[j][i..]);
            }
            if let Some((t, a)) = &mut self.keep {
                if let Some(t) = t {
                    for j in 0..9 {
                        w.store(tau[j], &mut t[j][i..]);
                    }
                }
                w.store(aux, &mut a[i..]);
            }
        }
        bad != 0
    }

    #[inline(always)]
    fn per_particle(mut self) -> bool {
        let mut bad = false;
        for p in 0..self.real {
            let at = |m: [&[T]; 9]| -> DMat3 {
                from_rows(std::array::from_fn(|r| {
                    std::array::from_fn(|c| m[3 * r + c][p].f64())
                }))
            };
            let c = at(self.c);
            let f0 = match self.f0 {
                Some(f0) => at(f0),
                None => at(self.f.each_ref().map(|x| &**x)),
            };
            let mat = &self.mat;
            let model = particle_model(self.model, mat.family, p);
            let ft = model.predict(&c, &f0, self.dt);
            let (f_new, tau, aux) =
                model.update_with_aux(&ft, &c, mat.mu64[p], mat.lam64[p], self.dt);
            bad |= !f_new.is_finite();
            let q = if mat.uniform { 0 } else { p };
            let a = tau * (-self.dt * mat.volume[q].f64() * self.d_inv) + c * mat.mass[q].f64();
            let (fr, ar, tr) = (to_rows(&f_new), to_rows(&a), to_rows(&tau));
            for j in 0..9 {
                self.f[j][p] = T::of(fr[j / 3][j % 3]);
                self.a[j][p] = T::of(ar[j / 3][j % 3]);
            }
            if let Some((t, x)) = &mut self.keep {
                if let Some(t) = t {
                    for j in 0..9 {
                        t[j][p] = T::of(tr[j / 3][j % 3]);
                    }
                }
                x[p] = T::of(aux);
            }
        }
        bad
    }
}
