//! From an edit's interactions to the simulator's forces: which particles each one acts on
//! and how much each of them gets.
//!
//! A selection picks Gaussians of the canonical state (frame 0). The force or impulse acts on
//! the material of the region it covers: the picked Gaussians that simulate, and the filler
//! particles (the solid's interior, simulated but not rendered) inside the same region (the
//! sphere, the box, or for `nearest` the ball around `point` reaching the farthest picked
//! Gaussian). The vector is the **total** over that material, spread in proportion to mass:
//! particle `p` of a selection of mass `M` gets `F m_p / M`, so every selected particle is
//! given the same acceleration `F / M` (an impulse `J`: the same velocity change `J / M`) and
//! the selection's momentum grows by exactly `F·τ` (or `J`). The engine takes one vector per
//! particle set ([`ParticleForce`]), so the particles of a selection are grouped by mass.

use std::collections::BTreeMap;

use glam::DVec3;
use pipe_mpm::ParticleForce;
use serde::Serialize;

use super::params::{Interaction, Selection};

/// The particles of the object an edit can act on.
#[derive(Debug, Clone, Copy)]
pub struct Targets<'a> {
    /// Every simulated particle at frame 0 (m): the simulated Gaussians first, then fillers.
    pub x: &'a [DVec3],
    /// Their masses (kg).
    pub mass: &'a [f64],
    /// How many of them are Gaussians.
    pub gaussians: usize,
    /// Gaussians that render but do not simulate (held in place), at their positions (m).
    pub fixed: &'a [DVec3],
}

/// What one interaction acts on, for `edit.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Acting {
    /// `force` or `impulse`.
    pub kind: &'static str,
    /// The selection as written.
    pub select: Selection,
    /// Simulated Gaussians picked.
    pub gaussians: usize,
    /// Gaussians picked that do not simulate (nothing acts on them).
    pub fixed_gaussians: usize,
    /// Filler particles inside the region.
    pub fillers: usize,
    /// Mass acted on (kg).
    pub mass_kg: f64,
    /// The total force (N) or impulse (N·s).
    pub total: [f64; 3],
    /// What every selected particle gets from it: `F/M` (m/s²) or `J/M` (m/s).
    pub per_kg: [f64; 3],
    /// Window (s): `[start, end)` of a force, `[time, time]` of an impulse.
    pub start_s: f64,
    /// End of the window (s; `null`: to the end of the edit).
    pub end_s: Option<f64>,
    /// The region's mass-weighted centre at frame 0 (m).
    pub centre_m: [f64; 3],
}

/// The simulator's forces of all interactions and, per interaction, its particles.
#[derive(Debug, Clone)]
pub struct Resolved {
    /// Forces and impulses, grouped by particle mass.
    pub forces: Vec<ParticleForce>,
    /// Per interaction: the particle indices it acts on.
    pub particles: Vec<Vec<usize>>,
    /// Per interaction: what it acts on.
    pub acting: Vec<Acting>,
}

/// An interaction that cannot act: the field (`interactions[i].select`) and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SelectError {
    /// Path of the field inside the edit's parameters.
    pub field: String,
    /// What is wrong, with the value.
    pub message: String,
}

/// Resolves `interactions` on `targets`.
pub fn resolve(
    interactions: &[Interaction],
    targets: Targets<'_>,
) -> Result<Resolved, SelectError> {
    let mut out = Resolved {
        forces: Vec::new(),
        particles: Vec::new(),
        acting: Vec::new(),
    };
    for (i, it) in interactions.iter().enumerate() {
        let field = format!("interactions[{i}].select");
        let (particles, fixed) = pick(it.select(), targets, &field)?;
        let gaussians = particles.iter().filter(|&&p| p < targets.gaussians).count();
        let mass: f64 = particles.iter().map(|&p| targets.mass[p]).sum();
        let centre = particles
            .iter()
            .map(|&p| targets.x[p] * targets.mass[p])
            .sum::<DVec3>()
            / mass;
        // Particles of equal mass get equal shares: one engine force per mass.
        let mut by_mass: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
        for &p in &particles {
            by_mass
                .entry(targets.mass[p].to_bits())
                .or_default()
                .push(p);
        }
        let (kind, total, start, end) = match *it {
            Interaction::Force {
                force, start, end, ..
            } => ("force", DVec3::from_array(force), start, end),
            Interaction::Impulse { impulse, time, .. } => {
                ("impulse", DVec3::from_array(impulse), time, Some(time))
            }
        };
        for (bits, group) in by_mass {
            let share = total * (f64::from_bits(bits) / mass);
            out.forces.push(match *it {
                Interaction::Force { .. } => ParticleForce::Force {
                    particles: group,
                    force: share,
                    start,
                    end: end.unwrap_or(f64::MAX),
                },
                Interaction::Impulse { time, .. } => ParticleForce::Impulse {
                    particles: group,
                    impulse: share,
                    time,
                },
            });
        }
        out.acting.push(Acting {
            kind,
            select: it.select().clone(),
            gaussians,
            fixed_gaussians: fixed,
            fillers: particles.len() - gaussians,
            mass_kg: mass,
            total: total.to_array(),
            per_kg: (total / mass).to_array(),
            start_s: start,
            end_s: end,
            centre_m: centre.to_array(),
        });
        out.particles.push(particles);
    }
    Ok(out)
}

/// The particles a selection acts on (sorted) and how many fixed Gaussians it picked.
fn pick(
    select: &Selection,
    t: Targets<'_>,
    field: &str,
) -> Result<(Vec<usize>, usize), SelectError> {
    let n = t.x.len();
    let inside: Box<dyn Fn(DVec3) -> bool> = match *select {
        Selection::Sphere { center, radius } => {
            let c = DVec3::from_array(center);
            Box::new(move |x: DVec3| x.distance_squared(c) <= radius * radius)
        }
        Selection::Box { min, max } => {
            let (lo, hi) = (DVec3::from_array(min), DVec3::from_array(max));
            Box::new(move |x: DVec3| x.cmpge(lo).all() && x.cmple(hi).all())
        }
        Selection::Nearest { point, count } => {
            let c = DVec3::from_array(point);
            let count = count as usize;
            if count > t.gaussians {
                return Err(SelectError {
                    field: format!("{field}.nearest.count"),
                    message: format!(
                        "{count} is more than the object's {} simulated Gaussians",
                        t.gaussians
                    ),
                });
            }
            // The `count` nearest simulated Gaussians (ties by index): the ball reaching them.
            let mut d: Vec<(f64, usize)> = (0..t.gaussians)
                .map(|p| (t.x[p].distance_squared(c), p))
                .collect();
            d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let reach = d[count - 1].0;
            let mut picked: Vec<usize> = d[..count].iter().map(|&(_, p)| p).collect();
            picked.extend((t.gaussians..n).filter(|&p| t.x[p].distance_squared(c) <= reach));
            picked.sort_unstable();
            let fixed = t
                .fixed
                .iter()
                .filter(|x| x.distance_squared(c) <= reach)
                .count();
            return Ok((picked, fixed));
        }
    };
    let picked: Vec<usize> = (0..n).filter(|&p| inside(t.x[p])).collect();
    let fixed = t.fixed.iter().filter(|&&x| inside(x)).count();
    let gaussians = picked.iter().filter(|&&p| p < t.gaussians).count();
    if gaussians == 0 {
        let (lo, hi) = bounds(&t.x[..t.gaussians]);
        let what = match *select {
            Selection::Sphere { center, radius } => {
                format!("the sphere {{center: {center:?}, radius: {radius}}}")
            }
            Selection::Box { min, max } => format!("the box {{min: {min:?}, max: {max:?}}}"),
            Selection::Nearest { .. } => unreachable!("returned above"),
        };
        let message = if fixed > 0 {
            format!(
                "{what} picks only Gaussians that do not simulate ({fixed}): nothing can move \
                 them"
            )
        } else {
            format!(
                "{what} picks no Gaussian; the object's simulated Gaussians span {:?} to {:?} m",
                lo.to_array().map(round_mm),
                hi.to_array().map(round_mm)
            )
        };
        return Err(SelectError {
            field: field.to_string(),
            message,
        });
    }
    Ok((picked, fixed))
}

fn round_mm(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

fn bounds(x: &[DVec3]) -> (DVec3, DVec3) {
    x.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line of 10 Gaussians along x (1 kg, then 2 kg alternately) and 5 fillers.
    fn line() -> (Vec<DVec3>, Vec<f64>) {
        let mut x: Vec<DVec3> = (0..10).map(|i| DVec3::new(i as f64, 0.0, 0.0)).collect();
        x.extend((0..5).map(|i| DVec3::new(i as f64 + 0.5, 0.0, 0.0)));
        let m = (0..15)
            .map(|i| if i % 2 == 0 { 1.0 } else { 2.0 })
            .collect();
        (x, m)
    }

    #[test]
    fn a_total_force_is_spread_by_mass_and_sums_to_the_total() {
        let (x, m) = line();
        let t = Targets {
            x: &x,
            mass: &m,
            gaussians: 10,
            fixed: &[],
        };
        let it = Interaction::Force {
            select: Selection::Box {
                min: [-0.1, -1.0, -1.0],
                max: [3.1, 1.0, 1.0],
            },
            force: [0.0, -12.0, 0.0],
            start: 0.0,
            end: Some(1.0),
        };
        let r = resolve(&[it], t).unwrap();
        // Gaussians 0..=3 and the fillers at 0.5, 1.5, 2.5 (particles 10, 11, 12).
        assert_eq!(r.particles[0], vec![0, 1, 2, 3, 10, 11, 12]);
        let a = &r.acting[0];
        assert_eq!((a.gaussians, a.fillers), (4, 3));
        assert_eq!(a.mass_kg, 1.0 + 2.0 + 1.0 + 2.0 + 1.0 + 2.0 + 1.0);
        let mut total = DVec3::ZERO;
        for f in &r.forces {
            let ParticleForce::Force {
                particles, force, ..
            } = f
            else {
                panic!()
            };
            for &p in particles {
                total += *force;
                // The same acceleration for all.
                assert!((force.y / m[p] - (-12.0 / 10.0)).abs() < 1e-12);
            }
        }
        assert!((total - DVec3::new(0.0, -12.0, 0.0)).length() < 1e-12);
    }

    #[test]
    fn nearest_takes_the_count_nearest_and_the_fillers_within_their_reach() {
        let (x, m) = line();
        let t = Targets {
            x: &x,
            mass: &m,
            gaussians: 10,
            fixed: &[DVec3::new(9.0, 0.2, 0.0)],
        };
        let it = Interaction::Impulse {
            select: Selection::Nearest {
                point: [9.4, 0.0, 0.0],
                count: 2,
            },
            impulse: [1.0, 0.0, 0.0],
            time: 0.0,
        };
        let r = resolve(std::slice::from_ref(&it), t).unwrap();
        assert_eq!(r.particles[0], vec![8, 9]);
        assert_eq!(r.acting[0].fixed_gaussians, 1);
        let too_many = Interaction::Impulse {
            select: Selection::Nearest {
                point: [0.0; 3],
                count: 11,
            },
            impulse: [1.0, 0.0, 0.0],
            time: 0.0,
        };
        let e = resolve(&[it, too_many], t).unwrap_err();
        assert_eq!(e.field, "interactions[1].select.nearest.count");
        assert!(
            e.message.contains("11 is more than the object's 10"),
            "{e:?}"
        );
    }

    #[test]
    fn an_empty_selection_names_the_field_and_the_objects_extent() {
        let (x, m) = line();
        let fixed = [DVec3::new(20.0, 0.0, 0.0)];
        let t = Targets {
            x: &x,
            mass: &m,
            gaussians: 10,
            fixed: &fixed,
        };
        let sphere = |c: [f64; 3]| Interaction::Force {
            select: Selection::Sphere {
                center: c,
                radius: 0.2,
            },
            force: [0.0, 1.0, 0.0],
            start: 0.0,
            end: None,
        };
        let e = resolve(&[sphere([5.0, 3.0, 0.0])], t).unwrap_err();
        assert_eq!(e.field, "interactions[0].select");
        assert!(
            e.message.starts_with(
                "the sphere {center: [5.0, 3.0, 0.0], radius: 0.2} picks no Gaussian; the \
                 object's simulated Gaussians span [0.0, 0.0, 0.0] to [9.0, 0.0, 0.0] m"
            ),
            "{}",
            e.message
        );
        // A filler alone is not a pick, a fixed Gaussian alone is named.
        assert!(resolve(&[sphere([0.5, 0.0, 0.0])], t).is_err());
        let e = resolve(&[sphere([20.0, 0.0, 0.0])], t).unwrap_err();
        assert!(
            e.message
                .contains("only Gaussians that do not simulate (1)"),
            "{e:?}"
        );
    }
}
