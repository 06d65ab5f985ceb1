//! Particle state as structure of arrays in the run's precision: one array per component, so
//! consecutive particles fill the lanes of a vector.
//!
//! Positions are stored relative to the grid's first node (metres), so that `x/dx` stays small
//! and keeps its fractional digits in `f32`. Matrices are row-major: `C[r][c]` is field
//! `C + 3r + c`. Arrays are padded past the last particle with particles at rest (`F = I`),
//! so whole vectors can be loaded at any particle and full chunks run through the stress pass.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use super::simd::Real;
use crate::state::State;

/// Field offsets in [`Soa::vcf`]: velocity (3), `C` (9), `F` (9).
pub(crate) const V: usize = 0;
pub(crate) const C: usize = 3;
pub(crate) const F: usize = 12;
/// Number of fields of [`Soa::vcf`].
pub(crate) const VCF: usize = 21;

/// Particles per task of the conversions from and to [`State`].
const CONVERT_CHUNK: usize = 4096;

/// Padding after the last particle (a vector's worth, plus rounding to a multiple of 8).
#[inline]
pub(crate) fn padded(n: usize) -> usize {
    n.div_ceil(8) * 8 + 8
}

/// Per-particle state in precision `T`: positions apart (a substep writes the new ones to a
/// second buffer while it still reads the old), the rest together.
#[derive(Debug, Clone)]
pub(crate) struct Soa<T> {
    /// Particles.
    pub n: usize,
    /// Entries per field (`padded(n)`).
    pub stride: usize,
    /// Positions: 3 fields of `stride` entries.
    pub x: Vec<T>,
    /// Velocity, `C`, `F`: `VCF` fields of `stride` entries.
    pub vcf: Vec<T>,
}

impl<T: Real> Soa<T> {
    /// `n` particles at rest at the grid's first node (`F = I`).
    pub fn new(n: usize) -> Self {
        let stride = padded(n);
        let mut vcf = vec![T::of(0.0); VCF * stride];
        for d in [0, 4, 8] {
            vcf[(F + d) * stride..(F + d + 1) * stride].fill(T::of(1.0));
        }
        Self {
            n,
            stride,
            x: vec![T::of(0.0); 3 * stride],
            vcf,
        }
    }

    /// No particles and no storage (a placeholder for a buffer taken away).
    pub fn empty() -> Self {
        Self {
            n: 0,
            stride: 0,
            x: Vec::new(),
            vcf: Vec::new(),
        }
    }

    /// `n` particles, every entry 0 (a gradient state).
    pub fn zeros(n: usize) -> Self {
        let stride = padded(n);
        Self {
            n,
            stride,
            x: vec![T::of(0.0); 3 * stride],
            vcf: vec![T::of(0.0); VCF * stride],
        }
    }

    /// A gradient state in the caller's order as slot order `ids` (slot `i` holds the
    /// caller's `ids[i]`), padding 0.
    pub fn from_grad(g: &crate::state::StateGrad, ids: &[u32]) -> Self {
        let s = State {
            x: g.x.clone(),
            v: g.v.clone(),
            c: g.c.clone(),
            f: g.f.clone(),
        };
        let caller = Self::from_state(&s, DVec3::ZERO, None);
        let mut out = Self::zeros(g.len());
        caller.permute_into(ids, &mut out);
        out
    }

    /// Position field `a` (all `stride` entries).
    #[inline(always)]
    pub fn x(&self, a: usize) -> &[T] {
        &self.x[a * self.stride..(a + 1) * self.stride]
    }

    /// The state of `s` (slot `i` = particle `i`), positions shifted by `-origin` (m), written
    /// into `out` when it has room for exactly these particles (its padding at rest).
    pub fn from_state(s: &State, origin: DVec3, out: Option<Self>) -> Self {
        let n = s.len();
        let mut out = out.filter(|o| o.n == n).unwrap_or_else(|| Self::new(n));
        let st = out.stride;
        let cuts = super::chunk_cuts(n, CONVERT_CHUNK);
        let xf: [&mut [T]; 3] = super::fields_mut(&mut out.x, st, 0);
        let fields: [&mut [T]; VCF] = super::fields_mut(&mut out.vcf, st, 0);
        super::split_fields(xf, &cuts)
            .into_par_iter()
            .zip(super::split_fields(fields, &cuts))
            .zip(cuts.par_windows(2))
            .for_each(|((xf, f), w)| {
                for (i, p) in (w[0]..w[1]).enumerate() {
                    let (x, v) = (s.x[p] - origin, s.v[p]);
                    for d in 0..3 {
                        xf[d][i] = T::of(x[d]);
                        f[V + d][i] = T::of(v[d]);
                    }
                    // Row-major fields from column-major matrices.
                    let (c, m) = (s.c[p].to_cols_array(), s.f[p].to_cols_array());
                    for col in 0..3 {
                        for r in 0..3 {
                            f[C + 3 * r + col][i] = T::of(c[3 * col + r]);
                            f[F + 3 * r + col][i] = T::of(m[3 * col + r]);
                        }
                    }
                }
            });
        out
    }

    /// Writes the particles into `s` in the caller's order: particle `p` from slot `rank[p]`,
    /// positions shifted by `+origin` (m). Only `x` and `v` when `motion_only`, else `C` and
    /// `F` too.
    pub fn to_state(&self, rank: &[u32], origin: DVec3, s: &mut State, motion_only: bool) {
        let st = self.stride;
        let (xs, d) = (&self.x, &self.vcf);
        s.x.par_chunks_mut(CONVERT_CHUNK)
            .zip(s.v.par_chunks_mut(CONVERT_CHUNK))
            .zip(rank.par_chunks(CONVERT_CHUNK))
            .for_each(|((x, v), rank)| {
                for (k, &i) in rank.iter().enumerate() {
                    let i = i as usize;
                    let at = |field: usize| d[field * st + i].f64();
                    x[k] = DVec3::new(xs[i].f64(), xs[st + i].f64(), xs[2 * st + i].f64()) + origin;
                    v[k] = DVec3::new(at(V), at(V + 1), at(V + 2));
                }
            });
        if motion_only {
            return;
        }
        s.c.par_chunks_mut(CONVERT_CHUNK)
            .zip(s.f.par_chunks_mut(CONVERT_CHUNK))
            .zip(rank.par_chunks(CONVERT_CHUNK))
            .for_each(|((c, f), rank)| {
                for (k, &i) in rank.iter().enumerate() {
                    let i = i as usize;
                    let at = |field: usize| d[field * st + i].f64();
                    // Column-major matrices from row-major fields.
                    let m = |b: usize| {
                        DMat3::from_cols_array(&[
                            at(b),
                            at(b + 3),
                            at(b + 6),
                            at(b + 1),
                            at(b + 4),
                            at(b + 7),
                            at(b + 2),
                            at(b + 5),
                            at(b + 8),
                        ])
                    };
                    c[k] = m(C);
                    f[k] = m(F);
                }
            });
    }

    /// Writes the particles reordered into `out` (same size): slot `i` of `out` gets slot
    /// `from[i]` of `self` (padding untouched).
    pub fn permute_into(&self, from: &[u32], out: &mut Self) {
        let st = self.stride;
        for (src, dst) in [(&self.x, &mut out.x), (&self.vcf, &mut out.vcf)] {
            src.par_chunks_exact(st)
                .zip(dst.par_chunks_exact_mut(st))
                .for_each(|(s, d)| {
                    for (d, &i) in d.iter_mut().zip(from) {
                        *d = s[i as usize];
                    }
                });
        }
    }
}
