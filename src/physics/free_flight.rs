//! A rigid body in free flight, in closed form: frame `k` (time `t = k·Δt`) puts particle `p`
//! at `x_p(t) = c + v t + ½ g t² + R(t) (X_p − c)` with `R(t) = exp([ω t]×)` and deformation
//! gradient `F_p = R(t)` (a fluid keeps `F = I`: its splats do not turn), `c` the centre of
//! mass. This is what an MPM rollout of a body that touches nothing computes with many
//! substeps (the body stays rigid; its centre follows gravity); the `velocity` stage uses it
//! for the frames the hulls show in free flight, at the cost of rendering them.
//!
//! The gradient (`∂L/∂v`, `∂L/∂ω`) goes through the exponential map's right Jacobian
//! `J_r(θ) = I − (1 − cos|θ|)/|θ|² [θ]× + (|θ| − sin|θ|)/|θ|³ [θ]×²` (`dR = R [J_r dθ]×`):
//! `∂(R r)/∂θ = −R [r]× J_r`, and `∂L/∂θ = J_rᵀ w` for `∂L/∂F = G`, `w` the axial vector of
//! `RᵀG − GᵀR`.

use glam::{DMat3, DVec3};
use pipe_mpm::{State, StateGrad};

use super::fit::RigidVelocity;
use super::object::Object;
use super::rollout::{FrameLoss, RolloutError};
use crate::simulate::spec::BoundarySpec;

/// `[u]×`, the cross-product matrix (`[u]× r = u × r`).
fn skew(u: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, u.z, -u.y),
        DVec3::new(-u.z, 0.0, u.x),
        DVec3::new(u.y, -u.x, 0.0),
    )
}

/// `exp([θ]×)` (Rodrigues) and its right Jacobian `J_r(θ)`.
fn exp_and_jacobian(theta: DVec3) -> (DMat3, DMat3) {
    let a = theta.length();
    let k = skew(theta);
    let k2 = k * k;
    // Series below 1e-4 rad (relative error of the truncated terms < 1e-16).
    let (s, c, j1, j2) = if a < 1e-4 {
        let a2 = a * a;
        (
            1.0 - a2 / 6.0,
            0.5 - a2 / 24.0,
            0.5 - a2 / 24.0,
            1.0 / 6.0 - a2 / 120.0,
        )
    } else {
        let a2 = a * a;
        (
            a.sin() / a,
            (1.0 - a.cos()) / a2,
            (1.0 - a.cos()) / a2,
            (a - a.sin()) / (a2 * a),
        )
    };
    let r = DMat3::IDENTITY + k * s + k2 * c;
    let jr = DMat3::IDENTITY - k * j1 + k2 * j2;
    (r, jr)
}

/// Frame `frame` of `rigid`'s free flight: its time `t` (s), `R(t)`, `J_r(ω t)` and the
/// centre's position `c + v t + ½ g t²` (m).
fn pose_at(object: &Object, rigid: &RigidVelocity, frame: u16) -> (f64, DMat3, DMat3, DVec3) {
    let (v, w, c) = (
        DVec3::from_array(rigid.linear),
        DVec3::from_array(rigid.angular),
        DVec3::from_array(rigid.centre),
    );
    let t = f64::from(frame) * object.spec.frame_dt;
    let (r, jr) = exp_and_jacobian(w * t);
    let shift = c + v * t + 0.5 * DVec3::from_array(object.spec.gravity) * t * t;
    (t, r, jr, shift)
}

/// The particles of `object` at frame `frame` of `rigid`'s free flight (m).
pub fn positions(object: &Object, rigid: &RigidVelocity, frame: u16) -> Vec<DVec3> {
    let (_, r, _, shift) = pose_at(object, rigid, frame);
    placed(object, DVec3::from_array(rigid.centre), r, shift)
}

/// The rest particles turned by `r` about `centre` and moved to `shift` (m).
fn placed(object: &Object, centre: DVec3, r: DMat3, shift: DVec3) -> Vec<DVec3> {
    object
        .body
        .state
        .x
        .iter()
        .map(|x| shift + r * (*x - centre))
        .collect()
}

/// Whether `rigid`'s free flight keeps every particle more than two grid cells (the transfer
/// stencil's reach) from every declared ground, half-space, box and domain wall over frames
/// `0..=frames`, so that nothing but gravity acts on it (an object resting on the ground,
/// or an anchor, is not in free flight whatever its hulls show).
pub fn touches_nothing(object: &Object, rigid: &RigidVelocity, frames: u16) -> bool {
    let margin = 2.0 * object.body.setup.dx;
    let mut planes: Vec<(DVec3, DVec3)> = Vec::new();
    let mut boxes: Vec<(DVec3, DVec3)> = Vec::new();
    for b in &object.spec.boundaries {
        match b {
            BoundarySpec::Ground { y, .. } => planes.push((DVec3::new(0.0, *y, 0.0), DVec3::Y)),
            BoundarySpec::HalfSpace { point, normal, .. } => {
                planes.push((DVec3::from_array(*point), DVec3::from_array(*normal)));
            }
            BoundarySpec::Box { aabb, .. } => {
                boxes.push((DVec3::from_array(aabb.min), DVec3::from_array(aabb.max)));
            }
            BoundarySpec::Anchor { .. } => return false,
        }
    }
    let domain = object
        .spec
        .domain
        .as_ref()
        .map(|d| (DVec3::from_array(d.min), DVec3::from_array(d.max)));
    (0..=frames).all(|frame| {
        positions(object, rigid, frame).iter().all(|x| {
            planes.iter().all(|(p, n)| (*x - *p).dot(*n) > margin)
                && boxes.iter().all(|(lo, hi)| {
                    let outside = (*lo - *x).max(*x - *hi).max(DVec3::ZERO);
                    outside.length() > margin
                })
                && domain.is_none_or(|(lo, hi)| {
                    (*x - lo).min_element() > margin && (hi - *x).min_element() > margin
                })
        })
    })
}

/// The loss of `rigid` over frames `1..=frames` (summed as a rollout's), and with `gradient`
/// its `(∂L/∂v, ∂L/∂ω)`.
///
/// # Errors
/// The first error of `loss`.
pub fn run(
    object: &Object,
    rigid: &RigidVelocity,
    frames: u16,
    fluid: bool,
    loss: &mut dyn FrameLoss,
    gradient: bool,
) -> Result<(f64, Option<(DVec3, DVec3)>), RolloutError> {
    let (v, w, c) = (
        DVec3::from_array(rigid.linear),
        DVec3::from_array(rigid.angular),
        DVec3::from_array(rigid.centre),
    );
    let g = DVec3::from_array(object.spec.gravity);
    let rest = &object.body.state.x;
    let n = rest.len();
    let (mut total, mut gv, mut gw) = (0.0, DVec3::ZERO, DVec3::ZERO);
    for frame in 1..=frames {
        let (t, r, jr, shift) = pose_at(object, rigid, frame);
        let mut state = State::at_rest(placed(object, c, r, shift));
        // The world angular velocity of exp([ω t]×) is ω itself.
        let speed = v + g * t;
        for (p, x) in state.v.iter_mut().zip(&state.x) {
            *p = speed + w.cross(*x - shift);
        }
        if !fluid {
            state.f.iter_mut().for_each(|f| *f = r);
        }
        if !gradient {
            total += loss.frame(frame, &state, None)?;
            continue;
        }
        let mut sg = StateGrad::zeros(n);
        total += loss.frame(frame, &state, Some(&mut sg))?;
        // ∂L/∂θ from the positions and the deformation gradients, θ = ω t.
        let mut g_theta = DVec3::ZERO;
        for (x, gx) in rest.iter().zip(&sg.x) {
            gv += *gx * t;
            let rl = *x - c;
            g_theta += rl.cross(r.transpose() * *gx);
        }
        if !fluid {
            let gf: DMat3 = sg.f.iter().copied().fold(DMat3::ZERO, |a, b| a + b);
            let m = r.transpose() * gf;
            g_theta += DVec3::new(
                m.y_axis.z - m.z_axis.y,
                m.z_axis.x - m.x_axis.z,
                m.x_axis.y - m.y_axis.x,
            );
        }
        gw += jr.transpose() * g_theta * t;
    }
    Ok((total, gradient.then_some((gv, gw))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exponential_map_and_its_jacobian_match_finite_differences() {
        for theta in [
            DVec3::new(0.3, -1.2, 0.7),
            DVec3::new(2e-5, 1e-5, -3e-5),
            DVec3::ZERO,
        ] {
            let (r, jr) = exp_and_jacobian(theta);
            assert!((r.transpose() * r - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-14));
            assert!((r.determinant() - 1.0).abs() < 1e-14);
            // dR = R [J_r dθ]×, column k of J_r by central differences.
            let h = 1e-6;
            for k in 0..3 {
                let e = DVec3::AXES[k] * h;
                let d = (exp_and_jacobian(theta + e).0 - exp_and_jacobian(theta - e).0) * (0.5 / h);
                let want = r * skew(jr.col(k));
                assert!(
                    (d - want).abs_diff_eq(DMat3::ZERO, 1e-8),
                    "θ {theta}, column {k}: {d} against {want}"
                );
            }
        }
    }
}
