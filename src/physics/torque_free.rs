//! The rotation of a body on which no torque acts (Euler's equations of a free rigid body,
//! Goldstein, *Classical Mechanics*, §5.5): its angular momentum `L` (world) is constant, its
//! body-frame angular momentum `π = Rᵀ L` follows `dπ/dt = π × Ω`, and its orientation
//! `dR/dt = R [Ω]×`, with `Ω = J⁻¹ π` the body-frame angular velocity for the inertia tensor `J`
//! (about the centre of mass, at rest orientation). Only a body turning about a principal axis
//! keeps a constant angular velocity: an asymmetric tumbling body's `ω` wanders (a thrown bar
//! spinning at (1, 4, 6) rad/s about its centre turns its `ω` by ~0.4 rad in half a second).
//!
//! The MPM that simulates the object (MLS-MPM with APIC transfers and quadratic B-splines,
//! starting from `C = 0` as PAC-NeRF does) adds to every particle the inertia of its affine
//! velocity, `m_p D` with `D = Δx²/4` on each axis: about any axis the body turns with
//! `J = I + (M Δx²/2) 𝟙`, while its angular momentum is `I ω₀` from its initial velocity field
//! `v + ω₀ × (x − c)` (Jiang et al. 2015, *The affine particle-in-cell method*, §5). So the
//! closed form that stands for a simulation of the body in free flight turns it with `J` from
//! `L = I ω₀` (test `simulate::a_spinning_block_turns_about_its_centre_of_mass` measures the
//! simulator's rate `I ω₀ / (I + M Δx²/2)` about a principal axis).
//!
//! Integrated by the classical fourth-order Runge–Kutta method on the unit quaternion of `R`
//! and on `π` (the quaternion renormalised after each step), with steps of at most 0.01 rad
//! (the local error is then ~1e-10 rad); the derivative of the rotation with respect to `ω₀`
//! by central differences of the same integration (the same steps: a smooth function of `ω₀`).

use glam::{DMat3, DQuat, DVec3};

/// The largest rotation of one integration step (rad).
const STEP_ANGLE: f64 = 0.01;

/// The body's orientation at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orientation {
    /// `R(t)`, rest orientation to world.
    pub r: DMat3,
    /// The world angular velocity `R Ω` (rad/s).
    pub omega: DVec3,
    /// `∂θ/∂ω₀` (s), column `k` for `ω₀`'s component `k`, where a change of `ω₀` turns the
    /// body by `dR = R [dθ]×` (zero when not asked for).
    pub jacobian: DMat3,
}

/// The inertia tensor `Σ m (|r|² 𝟙 − r rᵀ)` (kg·m²) of point masses `mass` (kg) at `x` (m)
/// about `centre` (m).
pub fn inertia(x: &[DVec3], mass: &[f64], centre: DVec3) -> DMat3 {
    x.iter().zip(mass).fold(DMat3::ZERO, |acc, (x, m)| {
        let r = *x - centre;
        acc + (DMat3::from_diagonal(DVec3::splat(r.length_squared()))
            - DMat3::from_cols(r * r.x, r * r.y, r * r.z))
            * *m
    })
}

/// A free body's rotation: its own inertia `own` (for `L = own · ω₀`) and the inertia it turns
/// with, `turning` (kg·m², both about its centre of mass, at rest orientation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FreeRotation {
    /// The inertia of the initial velocity field's angular momentum.
    pub own: DMat3,
    /// The inertia the body turns with (`own` plus APIC's affine inertia in a simulation).
    pub turning: DMat3,
}

impl FreeRotation {
    /// A body of particles `x` (m) of masses `mass` (kg) about `centre` (m) as the MPM on a
    /// grid of cell `dx` (m) turns it: `J = I + (M dx²/2) 𝟙`.
    pub fn of_simulated(x: &[DVec3], mass: &[f64], centre: DVec3, dx: f64) -> Self {
        let own = inertia(x, mass, centre);
        let total: f64 = mass.iter().sum();
        Self {
            own,
            turning: own + DMat3::from_diagonal(DVec3::splat(0.5 * total * dx * dx)),
        }
    }

    /// A bound on the angular speed `|ω(t)|` (rad/s) at every time of a body started with `ω₀`
    /// (rad/s): `|Ω| ≤ ‖J⁻¹‖_F |π|`, and `|π| = |L| = |I ω₀|` is constant (`|ω₀|` when the body
    /// has no inertia to turn with).
    pub fn max_rate(&self, omega0: DVec3) -> f64 {
        let det = self.turning.determinant();
        if !(det > 0.0 && det.is_finite()) {
            return omega0.length();
        }
        let m = self.turning.inverse();
        let norm =
            (m.x_axis.length_squared() + m.y_axis.length_squared() + m.z_axis.length_squared())
                .sqrt();
        norm * (self.own * omega0).length()
    }

    /// The orientation at each of `times` (s, increasing from ≥ 0) of a body that started at
    /// rest orientation with angular velocity field `ω₀` (rad/s); with `jacobian`, also
    /// `∂θ/∂ω₀`. A body with no inertia to turn with (`det J ≤ 0`) turns as `exp([ω₀ t]×)`.
    pub fn orientations(&self, omega0: DVec3, times: &[f64], jacobian: bool) -> Vec<Orientation> {
        let det = self.turning.determinant();
        if !(det > 0.0 && det.is_finite()) {
            return times
                .iter()
                .map(|&t| Orientation {
                    r: exp_so3(omega0 * t),
                    omega: omega0,
                    jacobian: DMat3::ZERO,
                })
                .collect();
        }
        let j_inv = self.turning.inverse();
        // The steps of each interval, from the bound on the rate.
        let top = self.max_rate(omega0);
        let mut steps = Vec::with_capacity(times.len());
        let mut last = 0.0;
        for &t in times {
            let span = (t - last).max(0.0);
            steps.push((span, ((span * top / STEP_ANGLE).ceil() as usize).max(1)));
            last = t;
        }
        let path = |w: DVec3| integrate(j_inv, self.own * w, &steps);
        let centre = path(omega0);
        let mut jac = vec![DMat3::ZERO; times.len()];
        if jacobian {
            let h = 1e-6 * omega0.length().max(1.0);
            for k in 0..3 {
                let e = DVec3::AXES[k] * h;
                let (up, down) = (path(omega0 + e), path(omega0 - e));
                for ((j, (r, _)), (ru, rd)) in jac.iter_mut().zip(&centre).zip(up.iter().zip(&down))
                {
                    let a = r.transpose() * ((ru.0 - rd.0) * (0.5 / h));
                    let col = 0.5
                        * DVec3::new(
                            a.y_axis.z - a.z_axis.y,
                            a.z_axis.x - a.x_axis.z,
                            a.x_axis.y - a.y_axis.x,
                        );
                    *j.col_mut(k) = col;
                }
            }
        }
        centre
            .into_iter()
            .zip(jac)
            .map(|((r, omega), jacobian)| Orientation { r, omega, jacobian })
            .collect()
    }
}

/// `R` and the world angular velocity at the end of each `(span, steps)` interval, from rest
/// orientation with world angular momentum `l`.
fn integrate(j_inv: DMat3, l: DVec3, intervals: &[(f64, usize)]) -> Vec<(DMat3, DVec3)> {
    // State: q (body → world) and π (body frame).
    let rate = |q: DQuat, pi: DVec3| {
        let w = j_inv * pi;
        (q * DQuat::from_xyzw(w.x, w.y, w.z, 0.0) * 0.5, pi.cross(w))
    };
    let (mut q, mut pi) = (DQuat::IDENTITY, l);
    let mut out = Vec::with_capacity(intervals.len());
    for &(span, n) in intervals {
        let h = span / n as f64;
        for _ in 0..n {
            let (q1, p1) = rate(q, pi);
            let (q2, p2) = rate(q + q1 * (0.5 * h), pi + p1 * (0.5 * h));
            let (q3, p3) = rate(q + q2 * (0.5 * h), pi + p2 * (0.5 * h));
            let (q4, p4) = rate(q + q3 * h, pi + p3 * h);
            q = (q + (q1 + q2 * 2.0 + q3 * 2.0 + q4) * (h / 6.0)).normalize();
            pi += (p1 + p2 * 2.0 + p3 * 2.0 + p4) * (h / 6.0);
        }
        let r = DMat3::from_quat(q);
        out.push((r, r * (j_inv * pi)));
    }
    out
}

/// `exp([θ]×)`, the rotation by `|θ|` about `θ`.
fn exp_so3(theta: DVec3) -> DMat3 {
    let a = theta.length();
    if a > 0.0 {
        DMat3::from_axis_angle(theta / a, a)
    } else {
        DMat3::IDENTITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn box_particles(half: DVec3, n: usize) -> (Vec<DVec3>, Vec<f64>) {
        let mut x = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let u = |a: usize| (a as f64 + 0.5) / n as f64 * 2.0 - 1.0;
                    x.push(DVec3::new(u(i), u(j), u(k)) * half);
                }
            }
        }
        let m = vec![0.01; x.len()];
        (x, m)
    }

    #[test]
    fn a_spin_about_a_principal_axis_is_steady_at_the_simulators_rate() {
        let (x, m) = box_particles(DVec3::new(0.16, 0.05, 0.06), 8);
        let dx = 0.03;
        let body = FreeRotation::of_simulated(&x, &m, DVec3::ZERO, dx);
        let mass: f64 = m.iter().sum();
        // About x, the long axis: ω = ω₀ I_x / (I_x + M dx²/2).
        let w0 = DVec3::new(5.0, 0.0, 0.0);
        let ix = body.own.x_axis.x;
        let rate = 5.0 * ix / (ix + 0.5 * mass * dx * dx);
        let t = [0.1, 0.25, 0.5];
        for (o, t) in body.orientations(w0, &t, false).iter().zip(t) {
            let want = DMat3::from_axis_angle(DVec3::X, rate * t);
            assert!((o.r - want).abs_diff_eq(DMat3::ZERO, 1e-9), "{o:?} at {t}");
            assert!((o.omega - DVec3::X * rate).length() < 1e-9);
        }
    }

    #[test]
    fn a_tumbling_bar_keeps_its_angular_momentum_and_energy() {
        let (x, m) = box_particles(DVec3::new(0.16, 0.05, 0.06), 8);
        let body = FreeRotation::of_simulated(&x, &m, DVec3::ZERO, 0.02);
        let w0 = DVec3::new(1.0, 4.0, 6.0);
        let l = body.own * w0;
        let times: Vec<f64> = (1..=13).map(|k| k as f64 / 24.0).collect();
        let path = body.orientations(w0, &times, false);
        let energy = |o: &Orientation| {
            let omega_body = o.r.transpose() * o.omega;
            0.5 * omega_body.dot(body.turning * omega_body)
        };
        let e0 = energy(&path[0]);
        for o in &path {
            let lw = o.r * (body.turning * (o.r.transpose() * o.omega));
            assert!((lw - l).length() < 1e-9 * l.length(), "{lw} against {l}");
            assert!((energy(o) - e0).abs() < 1e-9 * e0);
            assert!((o.r.transpose() * o.r - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-12));
        }
        // The angular velocity wanders: not a steady spin.
        let last = path.last().unwrap().omega;
        println!(
            "ω from {} to {last}: {} rad",
            path[0].omega,
            last.angle_between(path[0].omega)
        );
        assert!(
            (last - path[0].omega).length() > 0.1,
            "{last} against {}",
            path[0].omega
        );
    }

    #[test]
    fn the_derivative_in_the_initial_spin_matches_finite_differences_of_the_rotation() {
        let (x, m) = box_particles(DVec3::new(0.16, 0.05, 0.06), 6);
        let body = FreeRotation::of_simulated(&x, &m, DVec3::ZERO, 0.02);
        let w0 = DVec3::new(1.0, -4.0, 6.0);
        let times = [0.2, 0.5];
        let path = body.orientations(w0, &times, true);
        // A larger step than the integration's own: the same rotation, seen from outside.
        let h = 1e-4;
        for k in 0..3 {
            let e = DVec3::AXES[k] * h;
            let up = body.orientations(w0 + e, &times, false);
            let down = body.orientations(w0 - e, &times, false);
            for i in 0..times.len() {
                // dR ≈ R [J e_k]× dω
                let d = (up[i].r - down[i].r) * (0.5 / h);
                let u = path[i].jacobian.col(k);
                let skew = DMat3::from_cols(
                    DVec3::new(0.0, u.z, -u.y),
                    DVec3::new(-u.z, 0.0, u.x),
                    DVec3::new(u.y, -u.x, 0.0),
                );
                let want = path[i].r * skew;
                assert!(
                    (d - want).abs_diff_eq(DMat3::ZERO, 1e-6),
                    "ω₀ component {k}, t {}: {d} against {want}",
                    times[i]
                );
            }
        }
        // A sphere-like body (J ∝ 𝟙) turns as exp([ω t]×) with ω = ω₀ I/J: its derivative is the
        // exponential map's right Jacobian times t I/J.
        let (x, m) = box_particles(DVec3::splat(0.1), 6);
        let body = FreeRotation::of_simulated(&x, &m, DVec3::ZERO, 0.0);
        let o = body.orientations(DVec3::ZERO, &[0.3], true)[0];
        assert!(
            (o.jacobian - DMat3::IDENTITY * 0.3).abs_diff_eq(DMat3::ZERO, 1e-8),
            "{o:?}"
        );
    }
}
