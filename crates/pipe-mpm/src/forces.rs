//! External forces and impulses on particle index sets, added to the particle momentum in P2G.

use glam::DVec3;

use crate::error::MpmError;

/// A force or impulse on a set of particles.
#[derive(Debug, Clone, PartialEq)]
pub enum ParticleForce {
    /// Constant force (N, per particle) while `start ≤ t < end` (s).
    Force {
        /// Particle indices.
        particles: Vec<usize>,
        /// Force per particle (N).
        force: DVec3,
        /// Window start (s).
        start: f64,
        /// Window end (s).
        end: f64,
    },
    /// Impulse (N·s, per particle) applied once, in the substep whose interval `[t, t + dt)`
    /// contains `time` (s).
    Impulse {
        /// Particle indices.
        particles: Vec<usize>,
        /// Impulse per particle (N·s).
        impulse: DVec3,
        /// Time (s).
        time: f64,
    },
}

impl ParticleForce {
    /// Checks indices against `n` particles and finiteness.
    pub fn validate(&self, n: usize) -> Result<(), MpmError> {
        let (parts, v) = match self {
            ParticleForce::Force {
                particles,
                force,
                start,
                end,
            } => {
                if !(start.is_finite() && end.is_finite()) {
                    return Err(MpmError::NonFiniteInput {
                        field: "force.window",
                        index: 0,
                        value: f64::NAN,
                    });
                }
                (particles, *force)
            }
            ParticleForce::Impulse {
                particles,
                impulse,
                time,
            } => {
                if !time.is_finite() {
                    return Err(MpmError::NonFiniteInput {
                        field: "impulse.time",
                        index: 0,
                        value: *time,
                    });
                }
                (particles, *impulse)
            }
        };
        if !v.is_finite() {
            return Err(MpmError::NonFiniteInput {
                field: "force",
                index: 0,
                value: v.max_element(),
            });
        }
        if let Some(&bad) = parts.iter().find(|&&p| p >= n) {
            return Err(MpmError::InvalidParameter {
                field: "force.particles",
                value: bad as f64,
                reason: "particle index out of range",
            });
        }
        Ok(())
    }

    /// Momentum (N·s) added to each listed particle in the substep `[t, t + dt)`.
    fn momentum(&self, t: f64, dt: f64) -> Option<(&[usize], DVec3)> {
        match self {
            ParticleForce::Force {
                particles,
                force,
                start,
                end,
            } => (t >= *start && t < *end).then_some((particles.as_slice(), *force * dt)),
            ParticleForce::Impulse {
                particles,
                impulse,
                time,
            } => (*time >= t && *time < t + dt).then_some((particles.as_slice(), *impulse)),
        }
    }
}

/// Per-particle extra momentum for the substep starting at `t` (None when nothing acts).
pub fn extra_momentum(forces: &[ParticleForce], n: usize, t: f64, dt: f64) -> Option<Vec<DVec3>> {
    let mut out: Option<Vec<DVec3>> = None;
    for f in forces {
        if let Some((parts, dp)) = f.momentum(t, dt) {
            let buf = out.get_or_insert_with(|| vec![DVec3::ZERO; n]);
            for &p in parts {
                buf[p] += dp;
            }
        }
    }
    out
}

/// Upper bound of the speed (m/s) a particle can reach during `[t0, t1)` (s) from its velocity
/// `v` at `t0` and the forces and impulses acting then: `max_p (|v_p| + Σ |F| τ / m_p +
/// Σ |J| / m_p)` with `τ` the overlap of a force's window with `[t0, t1)` (to within the
/// substep that straddles its end). Gravity and the material's own forces are not included.
/// `mass` (kg) per particle; `v.len() == mass.len()`.
pub fn speed_bound(v: &[DVec3], mass: &[f64], forces: &[ParticleForce], t0: f64, t1: f64) -> f64 {
    let mut gain: Option<Vec<f64>> = None;
    for f in forces {
        let (parts, dp) = match f {
            ParticleForce::Force {
                particles,
                force,
                start,
                end,
            } => {
                let overlap = end.min(t1) - start.max(t0);
                if overlap <= 0.0 {
                    continue;
                }
                (particles, force.length() * overlap)
            }
            ParticleForce::Impulse {
                particles,
                impulse,
                time,
            } => {
                if !(*time >= t0 && *time < t1) {
                    continue;
                }
                (particles, impulse.length())
            }
        };
        let g = gain.get_or_insert_with(|| vec![0.0; v.len()]);
        for &p in parts {
            g[p] += dp / mass[p];
        }
    }
    let speed = |p: usize| v[p].length();
    match gain {
        None => (0..v.len()).map(speed).fold(0.0, f64::max),
        Some(g) => (0..v.len()).map(|p| speed(p) + g[p]).fold(0.0, f64::max),
    }
}
