//! A rigid body in free flight, in closed form: frame `k` (time `t = k·Δt`) puts particle `p`
//! at `x_p(t) = c + v t + ½ g t² + R(t) (X_p − c)` with deformation gradient `F_p = R(t)` (a
//! fluid keeps `F = I`: its splats do not turn), `c` the centre of mass, and `R(t)` the
//! torque-free rotation from the initial spin `ω` ([`super::torque_free`]: Euler's equations,
//! with the inertia the MPM turns the body with, `I + (M Δx²/2) 𝟙`; a constant `exp([ω t]×)`
//! holds only about a principal axis, and the simulator's spin is slower than `ω` by APIC's
//! affine inertia). This is what an MPM rollout of a body that touches nothing computes with
//! many substeps (the body stays rigid; its centre follows gravity); the `velocity` stage uses
//! it for the frames the hulls show in free flight, at the cost of rendering them, and the
//! `material` stage's rollouts start where the free flight ends ([`FreeFrames`]).
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

/// The free body of `object` as the simulation on its grid turns it.
fn rotation(object: &Object, rigid: &RigidVelocity) -> FreeRotation {
    FreeRotation::of_simulated(
        &object.body.state.x,
        &object.body.material.mass,
        DVec3::from_array(rigid.centre),
        object.body.setup.dx,
    )
}

/// The rotation of `rigid`'s body in free flight at frames `0..=frames` (with `∂θ/∂ω` when
/// `jacobian`), as the simulation on `object`'s grid turns it.
fn orientations(
    object: &Object,
    rigid: &RigidVelocity,
    frames: u16,
    jacobian: bool,
) -> Vec<Orientation> {
    let times: Vec<f64> = (0..=frames)
        .map(|k| f64::from(k) * object.spec.frame_dt)
        .collect();
    rotation(object, rigid).orientations(DVec3::from_array(rigid.angular), &times, jacobian)
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

/// The largest distance (m) of `object`'s particles from `centre` (m).
fn reach(object: &Object, centre: DVec3) -> f64 {
    object
        .body
        .state
        .x
        .iter()
        .map(|x| (*x - centre).length())
        .fold(0.0, f64::max)
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

/// The last frame `k ≤ frames` up to which `rigid`'s free flight keeps every particle more
/// than two grid cells from every declared ground, half-space, box and domain wall, so that
/// nothing but gravity acts on the body over `[0, k Δt]` (the transfer stencil reaches 1.5
/// cells; a body with an anchor or a force is never in free flight). Checked at times close
/// enough that no particle moves more than a quarter cell between two of them (from a bound
/// on the speed over the whole flight), so a tip that swings down and up between two frames is
/// seen.
pub fn frames_in_flight(object: &Object, rigid: &RigidVelocity, frames: u16) -> u16 {
    let dx = object.body.setup.dx;
    let margin = 2.0 * dx;
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
            BoundarySpec::Anchor { .. } => return 0,
        }
    }
    if !object.body.setup.forces.is_empty() {
        return 0;
    }
    let domain = object
        .spec
        .domain
        .as_ref()
        .map(|d| (DVec3::from_array(d.min), DVec3::from_array(d.max)));
    let clear = |x: &DVec3| {
        planes.iter().all(|(p, n)| (*x - *p).dot(*n) > margin)
            && boxes.iter().all(|(lo, hi)| {
                let outside = (*lo - *x).max(*x - *hi).max(DVec3::ZERO);
                outside.length() > margin
            })
            && domain.is_none_or(|(lo, hi)| {
                (*x - lo).min_element() > margin && (hi - *x).min_element() > margin
            })
    };
    let c = DVec3::from_array(rigid.centre);
    let body = rotation(object, rigid);
    let omega0 = DVec3::from_array(rigid.angular);
    let frame_dt = object.spec.frame_dt;
    let reach = reach(object, c);
    let t_end = f64::from(frames) * frame_dt;
    let speed = DVec3::from_array(rigid.linear).length()
        + DVec3::from_array(object.spec.gravity).length() * t_end
        + body.max_rate(omega0) * reach;
    let per_frame = ((speed * frame_dt / (0.25 * dx)).ceil() as usize).clamp(1, 10_000);
    let times: Vec<f64> = (0..=usize::from(frames) * per_frame)
        .map(|i| i as f64 * frame_dt / per_frame as f64)
        .collect();
    let path = body.orientations(omega0, &times, false);
    let first_touch = times.iter().zip(&path).position(|(&t, o)| {
        !placed(object, c, o.r, centre_at(object, rigid, t))
            .iter()
            .all(clear)
    });
    match first_touch {
        // Frames whose whole past is clear: the frame before the first sample that touches.
        Some(i) => (i.saturating_sub(1) / per_frame) as u16,
        None => frames,
    }
}

/// Whether `rigid`'s free flight keeps clear of everything over frames `0..=frames`
/// ([`frames_in_flight`]).
pub fn touches_nothing(object: &Object, rigid: &RigidVelocity, frames: u16) -> bool {
    frames_in_flight(object, rigid, frames) == frames
}

/// The simulation's state of `object` at time `t` (s) of `rigid`'s free flight, turned as `o`:
/// positions, velocities `v + g t + ω(t) × r`, APIC's affine velocity `C = [ω(t)]×` (the
/// gradient of that rigid velocity field) and `F = R(t)` (a fluid keeps `F = I`).
fn state_at(object: &Object, rigid: &RigidVelocity, o: &Orientation, t: f64, fluid: bool) -> State {
    let shift = centre_at(object, rigid, t);
    let mut state = State::at_rest(placed(object, DVec3::from_array(rigid.centre), o.r, shift));
    let speed = DVec3::from_array(rigid.linear) + DVec3::from_array(object.spec.gravity) * t;
    for (p, x) in state.v.iter_mut().zip(&state.x) {
        *p = speed + o.omega.cross(*x - shift);
    }
    let w = o.omega;
    let spin = DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    );
    state.c.iter_mut().for_each(|c| *c = spin);
    if !fluid {
        state.f.iter_mut().for_each(|f| *f = o.r);
    }
    state
}

/// The largest drift a spin may cause over [`FreeFrames`], as a fraction of the grid cell.
pub const SPIN_DRIFT: f64 = 0.01;

/// A rollout's first frames in closed form: while the body is in free flight
/// ([`frames_in_flight`]) nothing but gravity acts on it, so its material plays no part in
/// them, and a rollout (the `material` stage's, which holds the velocity) may start at the last
/// of them instead of simulating them every time. A spin is the exception: it stresses the body
/// (a soft one stretches, sand flies apart), so the frames are limited to those over which the
/// spin could not move a particle by [`SPIN_DRIFT`] of a cell even if nothing held the body
/// together (`½ ω² R t²`, `R` the body's reach from its centre).
#[derive(Debug, Clone)]
pub struct FreeFrames {
    /// The states at the end of frames `1..=k`.
    states: Vec<State>,
}

impl FreeFrames {
    /// The free flight of `rigid` over frames `1..=k`, `k ≤ frames` from [`frames_in_flight`];
    /// `None` when the body touches something by frame 1.
    pub fn of(object: &Object, rigid: &RigidVelocity, frames: u16, fluid: bool) -> Option<Self> {
        let reach = reach(object, DVec3::from_array(rigid.centre));
        let rate = rotation(object, rigid).max_rate(DVec3::from_array(rigid.angular));
        let drift = |k: u16| {
            let t = f64::from(k) * object.spec.frame_dt;
            0.5 * rate * rate * reach * t * t
        };
        let limit = SPIN_DRIFT * object.body.setup.dx;
        let k = (0..=frames_in_flight(object, rigid, frames))
            .take_while(|&k| drift(k) <= limit)
            .last()
            .unwrap_or(0);
        (k > 0).then(|| {
            let path = orientations(object, rigid, k, false);
            let states = (1..=k)
                .map(|frame| {
                    let t = f64::from(frame) * object.spec.frame_dt;
                    state_at(object, rigid, &path[usize::from(frame)], t, fluid)
                })
                .collect();
            Self { states }
        })
    }

    /// The last frame in closed form.
    pub fn frames(&self) -> u16 {
        self.states.len() as u16
    }

    /// The state at the end of `frame` (`1..=frames()`).
    pub fn state(&self, frame: u16) -> &State {
        &self.states[usize::from(frame) - 1]
    }
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
    let c = DVec3::from_array(rigid.centre);
    let rest = &object.body.state.x;
    let n = rest.len();
    let path = orientations(object, rigid, frames, gradient);
    let (mut total, mut gv, mut gw) = (0.0, DVec3::ZERO, DVec3::ZERO);
    for frame in 1..=frames {
        let o = path[usize::from(frame)];
        let (r, t) = (o.r, f64::from(frame) * object.spec.frame_dt);
        let state = state_at(object, rigid, &o, t, fluid);
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
