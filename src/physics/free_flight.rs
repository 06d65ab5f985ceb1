//! A rigid body in free flight, in closed form: frame `k` (time `t = k·Δt`) puts particle `p`
//! at `x_p(t) = c + v t + ½ g t² + R(t) (X_p − c)` with deformation gradient `F_p = R(t)` (a
//! fluid keeps `F = I`: its splats do not turn), `c` the centre of mass, and `R(t)` the
//! torque-free rotation from the initial spin `ω` ([`super::torque_free`]: Euler's equations,
//! with the inertia the MPM turns the body with, `I + (M Δx²/2) 𝟙`; a constant `exp([ω t]×)`
//! holds only about a principal axis, and the simulator's spin is slower than `ω` by APIC's
//! affine inertia). This is what an MPM rollout of a body that touches nothing computes with
//! many substeps (the body stays rigid; its centre follows gravity); the `velocity` stage uses
//! it for the frames the hulls show in free flight, at the cost of rendering them.
//!
//! The gradient (`∂L/∂v`, `∂L/∂ω`): `∂L/∂θ = w` for a turn `dR = R [dθ]×`, with
//! `∂(R r)/∂θ = −R [r]×` for the positions and `w` the axial vector of `RᵀG − GᵀR` for
//! `∂L/∂F = G`; then `∂L/∂ω = (∂θ/∂ω)ᵀ ∂L/∂θ` ([`super::torque_free::Orientation::jacobian`]).

use glam::{DMat3, DVec3};
use pipe_mpm::{State, StateGrad};

use super::fit::RigidVelocity;
use super::object::Object;
use super::rollout::{FrameLoss, RolloutError};
use super::torque_free::{FreeRotation, Orientation};
use crate::simulate::spec::BoundarySpec;

/// The rotation of `rigid`'s body in free flight at frames `0..=frames` (with `∂θ/∂ω` when
/// `jacobian`), as the simulation on `object`'s grid turns it.
fn orientations(
    object: &Object,
    rigid: &RigidVelocity,
    frames: u16,
    jacobian: bool,
) -> Vec<Orientation> {
    let body = FreeRotation::of_simulated(
        &object.body.state.x,
        &object.body.material.mass,
        DVec3::from_array(rigid.centre),
        object.body.setup.dx,
    );
    let times: Vec<f64> = (0..=frames)
        .map(|k| f64::from(k) * object.spec.frame_dt)
        .collect();
    body.orientations(DVec3::from_array(rigid.angular), &times, jacobian)
}

/// The centre's position `c + v t + ½ g t²` (m) at time `t` (s).
fn centre_at(object: &Object, rigid: &RigidVelocity, t: f64) -> DVec3 {
    DVec3::from_array(rigid.centre)
        + DVec3::from_array(rigid.linear) * t
        + 0.5 * DVec3::from_array(object.spec.gravity) * t * t
}

/// The particles of `object` at frame `frame` of `rigid`'s free flight (m).
pub fn positions(object: &Object, rigid: &RigidVelocity, frame: u16) -> Vec<DVec3> {
    let r = orientations(object, rigid, frame, false)[usize::from(frame)].r;
    let t = f64::from(frame) * object.spec.frame_dt;
    placed(
        object,
        DVec3::from_array(rigid.centre),
        r,
        centre_at(object, rigid, t),
    )
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
    let path = orientations(object, rigid, frames, false);
    let c = DVec3::from_array(rigid.centre);
    path.iter().enumerate().all(|(frame, o)| {
        let t = frame as f64 * object.spec.frame_dt;
        placed(object, c, o.r, centre_at(object, rigid, t))
            .iter()
            .all(|x| {
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
    let (v, c) = (
        DVec3::from_array(rigid.linear),
        DVec3::from_array(rigid.centre),
    );
    let g = DVec3::from_array(object.spec.gravity);
    let rest = &object.body.state.x;
    let n = rest.len();
    let path = orientations(object, rigid, frames, gradient);
    let (mut total, mut gv, mut gw) = (0.0, DVec3::ZERO, DVec3::ZERO);
    for frame in 1..=frames {
        let o = path[usize::from(frame)];
        let (r, t) = (o.r, f64::from(frame) * object.spec.frame_dt);
        let shift = centre_at(object, rigid, t);
        let mut state = State::at_rest(placed(object, c, r, shift));
        let speed = v + g * t;
        for (p, x) in state.v.iter_mut().zip(&state.x) {
            *p = speed + o.omega.cross(*x - shift);
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
        // ∂L/∂θ from the positions and the deformation gradients.
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
        gw += o.jacobian.transpose() * g_theta;
    }
    Ok((total, gradient.then_some((gv, gw))))
}
