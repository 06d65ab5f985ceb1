//! Forward rendering: project (parallel chunks), bin into tiles, blend front to back
//! (parallel over bands of tiles).
//!
//! Per pixel (3DGS Kerbl et al. 2023, eq. 3): `C = Σ_i c_i α_i T_i + T_N·bg`,
//! `T_{i+1} = T_i (1 - α_i)`, `T_0 = 1`, over the tile's depth-sorted list, skipping
//! `α < 1/255` and stopping before a splat that would bring `T` below `1e-4`.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::blend::{STRIDE, TileForward, TileRect, forward_tile};
use crate::camera::{Camera, TILE};
use crate::error::RenderError;
use crate::gaussians::Gaussians;
use crate::project::{ProjectCtx, ProjectedGaussian, project_one};
use crate::real::Real;
use crate::splat::Splat;
use crate::tiles::{TileBins, bin};

/// Gaussians per parallel projection task.
pub(crate) const PROJECT_CHUNK: usize = 4096;

/// Rendering options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions<T> {
    /// Background RGB, composited with the final transmittance.
    pub background: [T; 3],
    /// Added to the diagonal of every 2D covariance (pixel², 3DGS: 0.3).
    pub eps2d: T,
}

impl<T: Real> Default for RenderOptions<T> {
    fn default() -> Self {
        Self {
            background: [T::ZERO; 3],
            eps2d: T::from_f64(0.3),
        }
    }
}

impl<T: Real> RenderOptions<T> {
    fn validate(&self) -> Result<(), RenderError> {
        if !(self.eps2d.is_finite() && self.eps2d >= T::ZERO) {
            return Err(RenderError::Value {
                field: "eps2d",
                value: self.eps2d.to_f64(),
                reason: "must be finite and >= 0",
            });
        }
        if let Some(b) = self.background.iter().find(|b| !b.is_finite()) {
            return Err(RenderError::Value {
                field: "background",
                value: b.to_f64(),
                reason: "must be finite",
            });
        }
        Ok(())
    }
}

/// Wall time of each forward phase.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ForwardTimings {
    /// Projection, SH colour, radius and tile rectangles.
    pub project: Duration,
    /// Tile binning and per-tile depth sort.
    pub sort: Duration,
    /// Front-to-back blending.
    pub blend: Duration,
}

/// Forward result, and the state the backward needs.
#[derive(Debug, Clone)]
pub struct Rendered<T> {
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// RGB including the background, row-major `[H][W]`.
    pub image: Vec<[T; 3]>,
    /// Accumulated opacity `1 - T_final`, row-major.
    pub alpha: Vec<T>,
    /// Expected depth along z_cam (m) of the blended Gaussians: `Σ_i w_i z_i / Σ_i w_i` with
    /// `w_i = α_i T_i` (normalised by the pixel's alpha; 0 where nothing was blended). Not
    /// differentiated by [`crate::backward()`].
    pub depth: Vec<T>,
    /// Number of Gaussians blended into each pixel.
    pub n_contrib: Vec<u32>,
    /// Final transmittance `T_final` per pixel.
    pub final_transmittance: Vec<T>,
    /// Per pixel, 1 + the position in its tile list of the last blended Gaussian (0 if none).
    pub last_contributor: Vec<u32>,
    /// Per-Gaussian projection (same order as the input).
    pub projected: Vec<ProjectedGaussian<T>>,
    /// Depth-sorted tile lists.
    pub bins: TileBins,
    /// Phase timings.
    pub timings: ForwardTimings,
}

/// Checks every input of a render call.
pub(crate) fn validate<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
) -> Result<(), RenderError> {
    g.validate()?;
    cam.validate()?;
    opts.validate()
}

/// Projects every Gaussian (in parallel chunks of 4096), without blending.
pub fn project_all<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
) -> Result<Vec<ProjectedGaussian<T>>, RenderError> {
    validate(g, cam, opts)?;
    Ok(project_unchecked(g, cam, opts))
}

fn project_unchecked<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
) -> Vec<ProjectedGaussian<T>> {
    let ctx = ProjectCtx::new(cam, opts.eps2d);
    let mut out = vec![ProjectedGaussian::default(); g.len()];
    out.par_chunks_mut(PROJECT_CHUNK)
        .enumerate()
        .for_each(|(c, chunk)| {
            for (k, p) in chunk.iter_mut().enumerate() {
                *p = project_one(g, c * PROJECT_CHUNK + k, cam, &ctx);
            }
        });
    out
}

/// The blend's view of every Gaussian (computed once, copied per tile by [`gather`]).
pub(crate) fn splat_table<T: Real>(projected: &[ProjectedGaussian<T>]) -> Vec<Splat<T>> {
    let mut out = vec![Splat::default(); projected.len()];
    out.par_chunks_mut(PROJECT_CHUNK)
        .zip(projected.par_chunks(PROJECT_CHUNK))
        .for_each(|(o, p)| {
            for (o, p) in o.iter_mut().zip(p) {
                if p.visible() {
                    *o = Splat::new(p.mean2d, p.conic, p.cov2d, p.opacity, p.color, p.depth);
                }
            }
        });
    out
}

/// Gathers the splats of one tile in list order.
pub(crate) fn gather<T: Real>(ids: &[u32], table: &[Splat<T>], out: &mut Vec<Splat<T>>) {
    out.clear();
    out.extend(ids.iter().map(|&i| table[i as usize]));
}

/// Renders the Gaussians. See the crate docs for the rules.
pub fn render<T: Real>(
    g: &Gaussians<'_, T>,
    cam: &Camera<T>,
    opts: &RenderOptions<T>,
) -> Result<Rendered<T>, RenderError> {
    validate(g, cam, opts)?;
    let t0 = Instant::now();
    let projected = project_unchecked(g, cam, opts);
    let t1 = Instant::now();
    let (tiles_x, tiles_y) = cam.tile_grid();
    let bins = bin(&projected, tiles_x, tiles_y);
    let table = splat_table(&projected);
    let t2 = Instant::now();

    let (w, h) = (cam.width as usize, cam.height as usize);
    let n = w * h;
    let mut image = vec![[T::ZERO; 3]; n];
    let mut alpha = vec![T::ZERO; n];
    let mut depth = vec![T::ZERO; n];
    let mut n_contrib = vec![0u32; n];
    let mut final_t = vec![T::ONE; n];
    let mut last = vec![0u32; n];
    let band = TILE as usize * w;
    let bg = opts.background;
    (
        image.par_chunks_mut(band),
        alpha.par_chunks_mut(band),
        depth.par_chunks_mut(band),
        n_contrib.par_chunks_mut(band),
        final_t.par_chunks_mut(band),
        last.par_chunks_mut(band),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(ty, (img, al, de, nc, ft, la))| {
            let mut splats = Vec::new();
            let mut st = TileForward::default();
            let y0 = ty * TILE as usize;
            let y1 = y0 + img.len() / w;
            for tx in 0..tiles_x as usize {
                gather(bins.tile(ty * tiles_x as usize + tx), &table, &mut splats);
                let x0 = tx * TILE as usize;
                let rect = TileRect {
                    x0,
                    x1: (x0 + TILE as usize).min(w),
                    y0,
                    y1,
                };
                forward_tile(&splats, rect, &mut st);
                for ly in 0..y1 - y0 {
                    for lx in 0..rect.width() {
                        let (k, q) = (ly * w + x0 + lx, ly * STRIDE + lx);
                        let t = st.t[q];
                        let acc = T::ONE - t;
                        img[k] = std::array::from_fn(|ch| st.rgb[ch][q] + t * bg[ch]);
                        al[k] = acc;
                        de[k] = if acc > T::ZERO {
                            st.z[q] / acc
                        } else {
                            T::ZERO
                        };
                        nc[k] = st.count[q] as u32;
                        ft[k] = t;
                        la[k] = st.last[q] as u32;
                    }
                }
            }
        });
    let t3 = Instant::now();
    Ok(Rendered {
        width: cam.width,
        height: cam.height,
        image,
        alpha,
        depth,
        n_contrib,
        final_transmittance: final_t,
        last_contributor: last,
        projected,
        bins,
        timings: ForwardTimings {
            project: t1 - t0,
            sort: t2 - t1,
            blend: t3 - t2,
        },
    })
}
