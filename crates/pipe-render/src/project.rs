//! Per-Gaussian projection (EWA splatting, Zwicker et al. 2002; 3DGS Kerbl et al. 2023 §4)
//! and its hand-written backward.
//!
//! Forward, per Gaussian:
//! `Σ = M Mᵀ` with `M = R(q)·diag(s)`, or `M = F·R(q)·diag(s)` under a deformation `F`
//! (`Σ = F R S Sᵀ Rᵀ Fᵀ`, PhysGaussian §4.1), `t = R_v·mean + t_v`,
//! `Σ2D = J R_v Σ R_vᵀ Jᵀ + eps2d·I` with the perspective Jacobian `J` evaluated at the
//! frustum-clamped `t` (gsplat `_persp_proj`),
//! conic `Σ2D⁻¹`, `mean2d = (fx·tx/tz + cx, fy·ty/tz + cy)` (unclamped),
//! `radius = ceil(3·sqrt(λ_max))` and the 16×16 tile rectangle (3DGS `getRect`). SH colours
//! are evaluated at the view direction `d`, or at `Rᵀ·d` under a deformation's SH rotation.

use crate::camera::{Camera, TILE};
use crate::gaussians::{Colors, Gaussians, sh_coeff_count};
use crate::real::Real;
use crate::sh;

/// Projection result of one Gaussian. All fields are filled even for culled Gaussians
/// (non-finite intermediates of culled Gaussians are replaced by 0).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProjectedGaussian<T> {
    /// Centre in pixels (pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`).
    pub mean2d: [T; 2],
    /// `z_cam` (m).
    pub depth: T,
    /// Inverse 2D covariance `[A, B, C]` (`[[A, B], [B, C]]`, 1/pixel²).
    pub conic: [T; 3],
    /// 2D covariance `[a, b, c]` including `eps2d` (pixel²).
    pub cov2d: [T; 3],
    /// 3-sigma radius in pixels; 0 when culled.
    pub radius: u32,
    /// Tile rectangle `[x0, y0, x1, y1]` (half-open), computed before culling.
    pub tile_rect: [u32; 4],
    /// RGB used for blending.
    pub color: [T; 3],
    /// Activated opacity.
    pub opacity: T,
    /// Per channel: SH colour clamped at 0 (its gradient is 0).
    pub color_clamped: [bool; 3],
}

impl<T> ProjectedGaussian<T> {
    /// Not culled.
    #[inline]
    pub fn visible(&self) -> bool {
        self.radius > 0
    }
}

/// Per-render constants of the projection.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ProjectCtx<T> {
    pub limits: [T; 4],
    pub center: [T; 3],
    pub eps2d: T,
    pub tiles: (u32, u32),
}

impl<T: Real> ProjectCtx<T> {
    pub fn new(cam: &Camera<T>, eps2d: T) -> Self {
        Self {
            limits: cam.frustum_limits(),
            center: cam.center_world(),
            eps2d,
            tiles: cam.tile_grid(),
        }
    }
}

/// Unit quaternion and its norm; `None` for a zero or non-finite quaternion.
#[inline]
fn normalize_quat<T: Real>(q: [T; 4]) -> Option<([T; 4], T)> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n > T::ZERO && n.is_finite() {
        Some((q.map(|c| c / n), n))
    } else {
        None
    }
}

/// Rotation matrix of a unit quaternion `(w, x, y, z)`.
#[inline]
pub(crate) fn quat_to_rotmat<T: Real>(q: [T; 4]) -> [[T; 3]; 3] {
    let [w, x, y, z] = q;
    let one = T::ONE;
    let two = T::from_f64(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// `dL/dq` for `R = quat_to_rotmat(q)` given `G = dL/dR` (q treated as free, unnormalised).
#[inline]
fn rotmat_vjp<T: Real>(q: [T; 4], g: &[[T; 3]; 3]) -> [T; 4] {
    let [w, x, y, z] = q;
    let two = T::from_f64(2.0);
    let gw =
        two * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let gx = two
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - two * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - two * x * g[2][2]);
    let gy = two
        * (-two * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - two * y * g[2][2]);
    let gz = two
        * (-two * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - two * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    [gw, gx, gy, gz]
}

/// `F·A` for a row-major `F`.
#[inline]
fn left_multiply<T: Real>(f: &[T; 9], a: [[T; 3]; 3]) -> [[T; 3]; 3] {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            f[3 * i] * a[0][j] + f[3 * i + 1] * a[1][j] + f[3 * i + 2] * a[2][j]
        })
    })
}

/// [`geometry`] with `M = F·R(q)·diag(s)` when Gaussian `i` carries a deformation.
#[inline(always)]
fn geometry_of<T: Real>(
    g: &Gaussians<'_, T>,
    i: usize,
    cam: &Camera<T>,
    ctx: &ProjectCtx<T>,
) -> Option<Geometry<T>> {
    let (mean, scale, quat) = (g.means[i], g.scale(i), g.quats[i]);
    match g.deformation_f(i) {
        None => geometry(cam, ctx, mean, scale, quat, |a| a),
        Some(f) => geometry(cam, ctx, mean, scale, quat, |a| left_multiply(f, a)),
    }
}

/// Quantities shared by the forward and the backward of one Gaussian.
struct Geometry<T> {
    q: [T; 4],
    qnorm: T,
    rot: [[T; 3]; 3],
    scale: [T; 3],
    /// `M = R(q)·diag(s)`, or `M = F·R(q)·diag(s)` under a deformation.
    m: [[T; 3]; 3],
    /// `Σ = M Mᵀ`.
    sigma: [[T; 3]; 3],
    /// Camera-space mean.
    t: [T; 3],
    /// Clamped ratios `tx/tz`, `ty/tz` and whether each is strictly inside the limits.
    u: [T; 2],
    u_free: [bool; 2],
    /// `T2 = J·R_v` (2×3).
    tj: [[T; 3]; 2],
    cov: [T; 3],
}

/// [`Geometry`] of a Gaussian; `deform` maps `R(q)·diag(s)` to `M` (the identity, or `F·`
/// under a deformation: one instance each, so the canonical path is the plain 3DGS code).
/// Out of line, as the compiler chose before deformations existed: inlined into
/// [`geometry_of`] the canonical path's projection ran 6 % more instructions (cachegrind).
#[inline(never)]
fn geometry<T: Real>(
    cam: &Camera<T>,
    ctx: &ProjectCtx<T>,
    mean: [T; 3],
    scale: [T; 3],
    quat: [T; 4],
    deform: impl Fn([[T; 3]; 3]) -> [[T; 3]; 3],
) -> Option<Geometry<T>> {
    let (q, qnorm) = normalize_quat(quat)?;
    let rot = quat_to_rotmat(q);
    let m = deform(std::array::from_fn(|i| {
        std::array::from_fn(|j| rot[i][j] * scale[j])
    }));
    let sigma: [[T; 3]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|j| m[i][0] * m[j][0] + m[i][1] * m[j][1] + m[i][2] * m[j][2])
    });
    let t = cam.camera_from_world_point(mean);
    let tz = t[2];
    let [lxn, lxp, lyn, lyp] = ctx.limits;
    let rx = t[0] / tz;
    let ry = t[1] / tz;
    let u = [rx.max(-lxn).min(lxp), ry.max(-lyn).min(lyp)];
    let u_free = [rx >= -lxn && rx <= lxp, ry >= -lyn && ry <= lyp];
    // J = [[fx/tz, 0, -fx·u/tz], [0, fy/tz, -fy·v/tz]]
    let j = [
        [cam.fx / tz, T::ZERO, -cam.fx * u[0] / tz],
        [T::ZERO, cam.fy / tz, -cam.fy * u[1] / tz],
    ];
    let rv = &cam.camera_from_world_rotation;
    let tj: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| j[r][0] * rv[0][c] + j[r][1] * rv[1][c] + j[r][2] * rv[2][c])
    });
    // cov2d = T2 Σ T2ᵀ
    let ts: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            tj[r][0] * sigma[0][c] + tj[r][1] * sigma[1][c] + tj[r][2] * sigma[2][c]
        })
    });
    let dot = |a: &[T; 3], b: &[T; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cov = [
        dot(&ts[0], &tj[0]) + ctx.eps2d,
        dot(&ts[0], &tj[1]),
        dot(&ts[1], &tj[1]) + ctx.eps2d,
    ];
    Some(Geometry {
        q,
        qnorm,
        rot,
        scale,
        m,
        sigma,
        t,
        u,
        u_free,
        tj,
        cov,
    })
}

/// Projects Gaussian `i` (forward steps 1–9 of the fixture README).
pub(crate) fn project_one<T: Real>(
    g: &Gaussians<'_, T>,
    i: usize,
    cam: &Camera<T>,
    ctx: &ProjectCtx<T>,
) -> ProjectedGaussian<T> {
    let mean = g.means[i];
    let opacity = g.opacity(i);
    // A non-finite SH rotation would give NaN colours that the clamp at 0 hides: cull.
    let mut turned_finite = true;
    let (color, color_clamped) = match g.colors {
        Colors::Rgb(c) => (c[i], [false; 3]),
        Colors::Sh { degree, coeffs } => {
            let k = sh_coeff_count(degree);
            let (dir, _) = sh::view_dir(mean, ctx.center);
            let dir = match g.sh_rotation(i) {
                None => dir,
                Some(r) => {
                    let turned = sh::rotate_dir(r, dir);
                    turned_finite = turned.iter().all(|v| v.is_finite());
                    turned
                }
            };
            sh::eval(degree, &coeffs[i * k..(i + 1) * k], dir)
        }
    };
    let mut out = ProjectedGaussian {
        color,
        color_clamped,
        opacity,
        ..Default::default()
    };
    let Some(geo) = geometry_of(g, i, cam, ctx) else {
        return sanitize(out);
    };
    let [a, b, c] = geo.cov;
    let det = a * c - b * b;
    let t = geo.t;
    out.depth = t[2];
    out.cov2d = geo.cov;
    out.conic = [c / det, -b / det, a / det];
    out.mean2d = [cam.fx * t[0] / t[2] + cam.cx, cam.fy * t[1] / t[2] + cam.cy];
    let half = T::from_f64(0.5);
    let mid = half * (a + c);
    let disc = (mid * mid - det).max(T::from_f64(0.1)).sqrt();
    let lambda = (mid + disc).max(mid - disc);
    let r = (T::from_f64(3.0) * lambda.sqrt()).ceil();
    // 3DGS getRect in its pixel frame (pixel centres at integers): p = mean2d - 0.5.
    let tile = T::from_f64(TILE as f64);
    let (tx, ty) = ctx.tiles;
    let cl = |v: T, hi: u32| v.floor().max(T::ZERO).min(T::from_f64(hi as f64)).to_f64() as u32;
    let px = out.mean2d[0] - half;
    let py = out.mean2d[1] - half;
    let fifteen = T::from_f64((TILE - 1) as f64);
    out.tile_rect = [
        cl((px - r) / tile, tx),
        cl((py - r) / tile, ty),
        cl((px + r + fifteen) / tile, tx),
        cl((py + r + fifteen) / tile, ty),
    ];
    let rect_empty = out.tile_rect[2] <= out.tile_rect[0] || out.tile_rect[3] <= out.tile_rect[1];
    let finite = det.is_finite()
        && r.is_finite()
        && out.conic.iter().chain(&out.mean2d).all(|v| v.is_finite())
        && opacity.is_finite()
        && color.iter().all(|v| v.is_finite())
        && turned_finite;
    let in_front = t[2] > cam.near;
    let positive_det = det > T::ZERO;
    let cull = !in_front || !positive_det || !finite || rect_empty;
    out.radius = if cull { 0 } else { (r.to_f64() as u32).max(1) };
    debug_assert!(cull || (det > T::ZERO && out.conic[0] > T::ZERO && out.conic[2] > T::ZERO));
    sanitize(out)
}

fn sanitize<T: Real>(mut p: ProjectedGaussian<T>) -> ProjectedGaussian<T> {
    if p.radius == 0 {
        let fix = |v: &mut T| {
            if !v.is_finite() {
                *v = T::ZERO;
            }
        };
        p.mean2d
            .iter_mut()
            .chain(p.conic.iter_mut())
            .chain(p.cov2d.iter_mut())
            .chain(p.color.iter_mut())
            .for_each(fix);
        fix(&mut p.depth);
        fix(&mut p.opacity);
    }
    p
}

/// Upstream gradient of one Gaussian's projected quantities, accumulated by the blend backward.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProjectedGrad<T> {
    /// `dL/d mean2d` (pixels).
    pub mean2d: [T; 2],
    /// `dL/d [A, B, C]` (B counted once).
    pub conic: [T; 3],
    /// `dL/d opacity` (activated).
    pub opacity: T,
    /// `dL/d colour`.
    pub color: [T; 3],
}

/// Gradients of one Gaussian w.r.t. its parameters.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct ParamGrad<T> {
    pub mean: [T; 3],
    pub scale: [T; 3],
    pub quat: [T; 4],
}

/// Where the backward of one Gaussian writes its gradients besides [`ParamGrad`].
#[derive(Debug)]
pub(crate) struct GradSlots<'a, T> {
    /// `dL/d sh` of the Gaussian (empty for [`Colors::Rgb`]).
    pub sh: &'a mut [[T; 3]],
    /// `dL/dF` (row-major), when the Gaussians carry a deformation.
    pub f: Option<&'a mut [T; 9]>,
    /// `dL/dR` (row-major), when they carry an SH rotation.
    pub r: Option<&'a mut [T; 9]>,
}

/// Backward of [`project_one`] for a visible Gaussian: chains `dL/d(mean2d, conic)` to the
/// mean, scale and quaternion (returned, the mean gradient through the view direction added
/// in); SH, `F` and SH-rotation gradients go to `slots`.
pub(crate) fn project_one_vjp<T: Real>(
    g: &Gaussians<'_, T>,
    i: usize,
    cam: &Camera<T>,
    ctx: &ProjectCtx<T>,
    p: &ProjectedGaussian<T>,
    up: &ProjectedGrad<T>,
    slots: GradSlots<'_, T>,
) -> ParamGrad<T> {
    let mean = g.means[i];
    let mut out = ParamGrad::default();
    if let Colors::Sh { degree, coeffs } = g.colors {
        let k = sh_coeff_count(degree);
        let coeffs = &coeffs[i * k..(i + 1) * k];
        let (dir, dist) = sh::view_dir(mean, ctx.center);
        match g.sh_rotation(i) {
            None => {
                out.mean = sh::eval_vjp(
                    degree,
                    coeffs,
                    dir,
                    dist,
                    p.color_clamped,
                    up.color,
                    slots.sh,
                );
            }
            Some(r) => {
                let (g_mean, g_r) = sh::eval_rotated_vjp(
                    degree,
                    coeffs,
                    (dir, dist),
                    r,
                    p.color_clamped,
                    up.color,
                    slots.sh,
                );
                out.mean = g_mean;
                if let Some(slot) = slots.r {
                    *slot = g_r;
                }
            }
        }
    }
    let Some(geo) = geometry_of(g, i, cam, ctx) else {
        debug_assert!(false, "visible Gaussian {i} without geometry");
        return out;
    };
    let [ca, cb, cc] = p.conic;
    // conic = Σ2D⁻¹: dL/dΣ2D = -Q Gq Q with Gq = [[gA, gB/2], [gB/2, gC]].
    let half = T::from_f64(0.5);
    let two = T::from_f64(2.0);
    let gq = [
        [up.conic[0], half * up.conic[1]],
        [half * up.conic[1], up.conic[2]],
    ];
    let q = [[ca, cb], [cb, cc]];
    let qg: [[T; 2]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|c| q[r][0] * gq[0][c] + q[r][1] * gq[1][c]));
    let gcov: [[T; 2]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| -(qg[r][0] * q[0][c] + qg[r][1] * q[1][c]))
    });
    // gcov is the symmetric-matrix gradient (b appears twice as a matrix entry).
    // cov2d = T2 Σ T2ᵀ: dL/dΣ = T2ᵀ G T2, dL/dT2 = 2 G T2 Σ.
    let tj = &geo.tj;
    let gt: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| gcov[r][0] * tj[0][c] + gcov[r][1] * tj[1][c])
    });
    let g_sigma: [[T; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| tj[0][r] * gt[0][c] + tj[1][r] * gt[1][c]));
    let s = &geo.sigma;
    let g_tj: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            two * (gt[r][0] * s[0][c] + gt[r][1] * s[1][c] + gt[r][2] * s[2][c])
        })
    });
    // T2 = J R_v: dL/dJ = dL/dT2 · R_vᵀ.
    let rv = &cam.camera_from_world_rotation;
    let g_j: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            g_tj[r][0] * rv[c][0] + g_tj[r][1] * rv[c][1] + g_tj[r][2] * rv[c][2]
        })
    });
    let [tx, ty, tz] = geo.t;
    let (fx, fy) = (cam.fx, cam.fy);
    let tz2 = tz * tz;
    let mut g_t = [T::ZERO; 3];
    // J00 = fx/tz, J11 = fy/tz, J02 = -fx·u/tz, J12 = -fy·v/tz.
    g_t[2] += -fx / tz2 * g_j[0][0] - fy / tz2 * g_j[1][1]
        + fx * geo.u[0] / tz2 * g_j[0][2]
        + fy * geo.u[1] / tz2 * g_j[1][2];
    let g_u = [-fx / tz * g_j[0][2], -fy / tz * g_j[1][2]];
    for (axis, (&gu, &free)) in g_u.iter().zip(&geo.u_free).enumerate() {
        if free {
            // u = t_axis / tz
            g_t[axis] += gu / tz;
            g_t[2] += -gu * geo.t[axis] / tz2;
        }
    }
    // mean2d = (fx·tx/tz + cx, fy·ty/tz + cy)
    g_t[0] += fx / tz * up.mean2d[0];
    g_t[1] += fy / tz * up.mean2d[1];
    g_t[2] += -fx * tx / tz2 * up.mean2d[0] - fy * ty / tz2 * up.mean2d[1];
    for (c, gm) in out.mean.iter_mut().enumerate() {
        *gm += rv[0][c] * g_t[0] + rv[1][c] * g_t[1] + rv[2][c] * g_t[2];
    }
    // Σ = M Mᵀ: dL/dM = 2 G_Σ M (G_Σ symmetric).
    let m = &geo.m;
    let g_m: [[T; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            two * (g_sigma[r][0] * m[0][c] + g_sigma[r][1] * m[1][c] + g_sigma[r][2] * m[2][c])
        })
    });
    // M = F·A, A = R diag(s): dL/dF = dL/dM·Aᵀ, dL/dA = Fᵀ·dL/dM (M = A without a
    // deformation).
    let rot = &geo.rot;
    let g_a = match g.deformation_f(i) {
        None => g_m,
        Some(f) => {
            if let Some(slot) = slots.f {
                let a: [[T; 3]; 3] =
                    std::array::from_fn(|k| std::array::from_fn(|c| rot[k][c] * geo.scale[c]));
                *slot = std::array::from_fn(|e| {
                    let (r, k) = (e / 3, e % 3);
                    g_m[r][0] * a[k][0] + g_m[r][1] * a[k][1] + g_m[r][2] * a[k][2]
                });
            }
            std::array::from_fn(|k| {
                std::array::from_fn(|c| {
                    f[k] * g_m[0][c] + f[3 + k] * g_m[1][c] + f[6 + k] * g_m[2][c]
                })
            })
        }
    };
    out.scale = std::array::from_fn(|c| {
        g_a[0][c] * rot[0][c] + g_a[1][c] * rot[1][c] + g_a[2][c] * rot[2][c]
    });
    let g_rot: [[T; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| g_a[r][c] * geo.scale[c]));
    let g_qn = rotmat_vjp(geo.q, &g_rot);
    // q_n = q/|q|: dL/dq = (g - q_n (q_n·g)) / |q|.
    let qn = geo.q;
    let dot = g_qn[0] * qn[0] + g_qn[1] * qn[1] + g_qn[2] * qn[2] + g_qn[3] * qn[3];
    out.quat = std::array::from_fn(|k| (g_qn[k] - qn[k] * dot) / geo.qnorm);
    out
}
