//! Hand-written backward of [`crate::render`].
//!
//! Blend (per pixel, back to front from the last blended splat, recovering
//! `T_i = T_{i+1}/(1 - α_i)` from the stored final transmittance):
//! `dC/dc_i = α_i T_i`, `dC/dα_i = c_i T_i - S_i/(1 - α_i)` with
//! `S_i = Σ_{j>i} c_j α_j T_j + T_N·bg`, and `d(1 - T_N)/dα_i = T_N/(1 - α_i)`.
//! Through `α = o·exp(power)` (zero where the 0.99 clamp is active, the true derivative):
//! `dα/do = exp(power)`, `dα/dpower = α`, `power = -½(A dx² + C dy²) - B dx dy`.
//! Per-tile gradients land in a buffer parallel to the tile lists and are summed per
//! Gaussian in tile order, so results do not depend on the thread count.
//! Then per Gaussian (parallel chunks) through the projection (and a deformation's `F` and
//! SH rotation), SH and the activations.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::blend::{STRIDE, SplatGrad, TileBackward, TileRect, backward_tile};
use crate::camera::{Camera, TILE};
use crate::error::RenderError;
use crate::forward::{PROJECT_CHUNK, RenderOptions, Rendered, gather, splat_table, validate};
use crate::gaussians::{Colors, Gaussians, sh_coeff_count};
use crate::project::{GradSlots, ParamGrad, ProjectCtx, ProjectedGrad, project_one_vjp};
use crate::real::Real;
use crate::tiles::split_by_offsets;

/// Wall time of each backward phase.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BackwardTimings {
    /// Per-pixel blend backward.
    pub blend: Duration,
    /// Fixed-order reduction of per-tile gradients into per-Gaussian ones.
    pub reduce: Duration,
    /// Projection, SH and activation backward.
    pub project: Duration,
}

/// Gradients of the loss w.r.t. every input, per Gaussian in input order. Culled Gaussians
/// get zeros.
#[derive(Debug, Clone, Default)]
pub struct Gradients<T> {
    /// `dL/d means` (world, per m), including the SH view-direction path.
    pub means: Vec<[T; 3]>,
    /// `dL/d scales` (linear standard deviations).
    pub scales: Vec<[T; 3]>,
    /// `dL/d log_scales` (`= dL/d scales · scales`).
    pub log_scales: Vec<[T; 3]>,
    /// `dL/d quats` for the raw input quaternion, through the normalisation.
    pub quats: Vec<[T; 4]>,
    /// `dL/d opacities` (activated).
    pub opacities: Vec<T>,
    /// `dL/d opacity_logits` (`= dL/d opacities · o(1 - o)`).
    pub opacity_logits: Vec<T>,
    /// `dL/d colours`: the input RGB ([`Colors::Rgb`]) or the SH-evaluated RGB after the clamp.
    pub colors: Vec<[T; 3]>,
    /// `dL/d sh` (`[gaussian][coeff k][channel]`, empty for [`Colors::Rgb`]).
    pub sh: Vec<[T; 3]>,
    /// `dL/dF` per Gaussian, row-major like [`crate::Deformation::f`] (empty without a
    /// deformation). Goes with `means` to the simulation's adjoint.
    pub deformation: Vec<[T; 9]>,
    /// `dL/dR` per Gaussian for the SH rotation, row-major like
    /// [`crate::Deformation::sh_rotation`] (empty without one; zeros for [`Colors::Rgb`] and
    /// SH degree 0).
    pub sh_rotation: Vec<[T; 9]>,
    /// `dL/d means2d` (per pixel), the densification statistic of 3DGS.
    pub means2d: Vec<[T; 2]>,
    /// `dL/d conics` `[A, B, C]` (B counted once).
    pub conics: Vec<[T; 3]>,
    /// Phase timings.
    pub timings: BackwardTimings,
}

/// Backward of [`crate::render`]: given `dL/d image` (and optionally `dL/d alpha`), returns
/// the gradients w.r.t. every Gaussian parameter. `g`, `cam` and `opts` must be those of the
/// forward call that produced `fwd`.
pub fn backward<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
    fwd: &Rendered<T>,
    d_image: &[[T; 3]],
    d_alpha: Option<&[T]>,
) -> Result<Gradients<T>, RenderError> {
    validate(g, cam, opts)?;
    let n_pix = cam.n_pixels();
    let len = |field, got, expected| {
        if got == expected {
            Ok(())
        } else {
            Err(RenderError::Length {
                field,
                expected,
                got,
            })
        }
    };
    len("d_image", d_image.len(), n_pix)?;
    if let Some(a) = d_alpha {
        len("d_alpha", a.len(), n_pix)?;
    }
    len("rendered.image", fwd.image.len(), n_pix)?;
    len("rendered.projected", fwd.projected.len(), g.len())?;
    let (tiles_x, tiles_y) = cam.tile_grid();
    len(
        "rendered.bins.offsets",
        fwd.bins.offsets.len(),
        tiles_x as usize * tiles_y as usize + 1,
    )?;

    let t0 = Instant::now();
    let isect_grads = blend_backward(cam, opts, fwd, d_image, d_alpha);
    let t1 = Instant::now();
    let mut up = vec![ProjectedGrad::<T>::default(); g.len()];
    for (&id, gr) in fwd.bins.ids.iter().zip(&isect_grads) {
        let u = &mut up[id as usize];
        for c in 0..2 {
            u.mean2d[c] += gr.mean2d[c];
        }
        for c in 0..3 {
            u.conic[c] += gr.conic[c];
            u.color[c] += gr.color[c];
        }
        u.opacity += gr.opacity;
    }
    drop(isect_grads);
    let t2 = Instant::now();
    let mut out = params_backward(g, cam, opts, fwd, &up);
    out.timings = BackwardTimings {
        blend: t1 - t0,
        reduce: t2 - t1,
        project: t2.elapsed(),
    };
    Ok(out)
}

/// Per-(tile, Gaussian) gradients of the projected quantities, parallel to `fwd.bins.ids`.
fn blend_backward<T: Real>(
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
    fwd: &Rendered<T>,
    d_image: &[[T; 3]],
    d_alpha: Option<&[T]>,
) -> Vec<SplatGrad<T>> {
    let (tiles_x, _) = cam.tile_grid();
    let tx_n = tiles_x as usize;
    let w = cam.width as usize;
    let offsets = &fwd.bins.offsets;
    let band_offsets: Vec<usize> = offsets.iter().step_by(tx_n).copied().collect();
    debug_assert_eq!(band_offsets.last().copied(), offsets.last().copied());
    let mut grads = vec![SplatGrad::<T>::default(); fwd.bins.n_intersections()];
    let bands = split_by_offsets(&mut grads, &band_offsets);
    let table = splat_table(&fwd.projected);
    let bg = opts.background;
    bands.into_par_iter().enumerate().for_each(|(ty, gband)| {
        let mut splats = Vec::new();
        let mut st = TileBackward::default();
        let y0 = ty * TILE as usize;
        let y1 = ((cam.height as usize) - y0).min(TILE as usize) + y0;
        let band_base = band_offsets[ty];
        for tx in 0..tx_n {
            let t_idx = ty * tx_n + tx;
            let lo = offsets[t_idx] - band_base;
            let hi = offsets[t_idx + 1] - band_base;
            if lo == hi {
                continue;
            }
            gather(fwd.bins.tile(t_idx), &table, &mut splats);
            let x0 = tx * TILE as usize;
            let rect = TileRect {
                x0,
                x1: (x0 + TILE as usize).min(w),
                y0,
                y1,
            };
            st.reset();
            for ly in 0..y1 - y0 {
                for lx in 0..rect.width() {
                    let (k, q) = ((y0 + ly) * w + x0 + lx, ly * STRIDE + lx);
                    let tn = fwd.final_transmittance[k];
                    for c in 0..3 {
                        st.dc[c][q] = d_image[k][c];
                        st.acc[c][q] = tn * bg[c];
                    }
                    st.da_tn[q] = d_alpha.map_or(T::ZERO, |a| a[k]) * tn;
                    st.t[q] = tn;
                    st.last[q] = fwd.last_contributor[k] as i32;
                }
            }
            backward_tile(&splats, rect, &mut st, &mut gband[lo..hi]);
        }
    });
    grads
}

/// Per-Gaussian chain rule from the projected quantities to the parameters.
fn params_backward<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
    fwd: &Rendered<T>,
    up: &[ProjectedGrad<T>],
) -> Gradients<T> {
    let n = g.len();
    let ctx = ProjectCtx::new(cam, opts.eps2d);
    let k = match g.colors {
        Colors::Rgb(_) => 0,
        Colors::Sh { degree, .. } => sh_coeff_count(degree),
    };
    let deformed = g.deformation.as_ref();
    let n_f = if deformed.is_some() { n } else { 0 };
    let n_r = if deformed.and_then(|d| d.sh_rotation).is_some() {
        n
    } else {
        0
    };
    let mut pg = vec![ParamGrad::<T>::default(); n];
    let mut sh = vec![[T::ZERO; 3]; n * k];
    let mut g_f = vec![[T::ZERO; 9]; n_f];
    let mut g_r = vec![[T::ZERO; 9]; n_r];
    pg.par_chunks_mut(PROJECT_CHUNK)
        .zip(task_chunks(&mut sh, k, n))
        .zip(task_chunks(&mut g_f, n_f.min(1), n))
        .zip(task_chunks(&mut g_r, n_r.min(1), n))
        .enumerate()
        .for_each(|(c, (((pgc, shc), fc), rc))| {
            for (j, out) in pgc.iter_mut().enumerate() {
                let i = c * PROJECT_CHUNK + j;
                let p = &fwd.projected[i];
                if !p.visible() {
                    continue;
                }
                let slots = GradSlots {
                    sh: if k > 0 {
                        &mut shc[j * k..(j + 1) * k]
                    } else {
                        &mut [][..]
                    },
                    f: fc.get_mut(j),
                    r: rc.get_mut(j),
                };
                *out = project_one_vjp(g, i, cam, &ctx, p, &up[i], slots);
            }
        });
    let mut out = Gradients {
        means: pg.iter().map(|p| p.mean).collect(),
        scales: pg.iter().map(|p| p.scale).collect(),
        quats: pg.iter().map(|p| p.quat).collect(),
        opacities: up.iter().map(|u| u.opacity).collect(),
        colors: up.iter().map(|u| u.color).collect(),
        sh,
        deformation: g_f,
        sh_rotation: g_r,
        means2d: up.iter().map(|u| u.mean2d).collect(),
        conics: up.iter().map(|u| u.conic).collect(),
        ..Default::default()
    };
    out.log_scales = (0..n)
        .map(|i| std::array::from_fn(|c| out.scales[i][c] * g.scale(i)[c]))
        .collect();
    out.opacity_logits = (0..n)
        .map(|i| {
            let o = g.opacity(i);
            out.opacities[i] * o * (T::ONE - o)
        })
        .collect();
    out
}

/// `v` split into the chunks of the per-Gaussian tasks ([`PROJECT_CHUNK`] Gaussians with
/// `per` entries each): `n.div_ceil(PROJECT_CHUNK)` chunks, all empty when `per` is 0.
fn task_chunks<X>(v: &mut [X], per: usize, n: usize) -> Vec<&mut [X]> {
    let mut chunks: Vec<&mut [X]> = v.chunks_mut((PROJECT_CHUNK * per).max(1)).collect();
    chunks.resize_with(n.div_ceil(PROJECT_CHUNK), Default::default);
    chunks
}
