//! How closely the frames pin each learned parameter: the loss profile about the fit.
//!
//! Each learned parameter in turn is moved away from its fitted value, the others held, by
//! growing steps on each side (decades for the moduli, yield stress and viscosities; absolute
//! for ν; degrees for the friction angle), and each move is scored by a full forward rollout
//! on the fit's own training views and frames. The training cameras are the samples: camera
//! `c`'s rise is `d_c = mean_f (L_cf(moved) − L_cf(fit))` over its frames, and a move is
//! *resolved* when the cameras agree that it is worse, a paired t-statistic
//! `t = mean(d) / (sd(d)/√n) ≥ t_min` over the `n` cameras (with fewer than three cameras, the
//! (camera, frame) pairs are the samples). A side's bound is its first resolved step; a side
//! with none is not bounded within its largest step. A move the cameras agree is *better*
//! (`t ≤ −t_min`) says the fit stopped short of the loss's minimum on that side.
//!
//! This measures what the frames, seen through the model, hold; not the distance to the
//! truth: a mismatch of the model (the reconstructed body, baked shading) moves the minimum
//! without widening it.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::params::Param;

/// The loss of each (frame, view) of a rollout ([`super::views::ViewsLoss::view_loss`]).
pub type ViewLosses = BTreeMap<(u16, u16), f64>;

/// The stage parameters of the profile (`material.profile`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ProfileParams {
    /// Whether to profile the fit (a few forward rollouts per learned parameter).
    #[serde(default = "yes")]
    pub enabled: bool,
    /// Steps (decades) for the moduli, yield stress and viscosities, smallest first.
    #[serde(default = "decade_steps")]
    pub decades: Vec<f64>,
    /// Steps of Poisson's ratio (absolute), smallest first.
    #[serde(default = "nu_steps")]
    pub nu: Vec<f64>,
    /// Steps of the friction angle (degrees), smallest first.
    #[serde(default = "friction_steps")]
    pub friction_deg: Vec<f64>,
    /// The cameras' paired t-statistic from which a move counts as resolved.
    #[serde(default = "t_min")]
    pub t_min: f64,
    /// Moves the fit may take where the profile finds a better value of a modulus, yield stress
    /// or viscosity (the cameras agreeing at `t <= -t_min`), the profile taken again after
    /// each; 0 only reports.
    #[serde(default = "rounds")]
    pub rounds: u32,
    /// A kept material field's values are grouped into this many parts (natural breaks of
    /// its `log10 E`, [`super::field_parts`]) and each part's E is profiled alone; 0 or 1
    /// profiles no part.
    #[serde(default = "field_parts")]
    pub field_parts: usize,
}

fn yes() -> bool {
    true
}
fn decade_steps() -> Vec<f64> {
    vec![0.25, 0.5, 1.0]
}
fn nu_steps() -> Vec<f64> {
    vec![0.025, 0.05, 0.1]
}
fn friction_steps() -> Vec<f64> {
    vec![2.5, 5.0, 10.0]
}
fn t_min() -> f64 {
    2.0
}
fn rounds() -> u32 {
    3
}
fn field_parts() -> usize {
    2
}

/// The most parts `profile.field_parts` may ask for.
pub const MAX_FIELD_PARTS: usize = 8;

impl Default for ProfileParams {
    fn default() -> Self {
        Self {
            enabled: yes(),
            decades: decade_steps(),
            nu: nu_steps(),
            friction_deg: friction_steps(),
            t_min: t_min(),
            rounds: rounds(),
            field_parts: field_parts(),
        }
    }
}

impl ProfileParams {
    /// The first invalid setting, as `(field, message)`.
    pub fn invalid(&self) -> Option<(&'static str, String)> {
        let check = |name: &'static str, steps: &[f64]| {
            let ok = steps.iter().all(|s| s.is_finite() && *s > 0.0)
                && steps.windows(2).all(|w| w[0] < w[1]);
            (!ok).then(|| {
                (
                    name,
                    format!("{steps:?}: steps must be finite, positive and increasing"),
                )
            })
        };
        check("decades", &self.decades)
            .or_else(|| check("nu", &self.nu))
            .or_else(|| check("friction_deg", &self.friction_deg))
            .or_else(|| {
                (self.field_parts > MAX_FIELD_PARTS).then(|| {
                    (
                        "field_parts",
                        format!(
                            "{}: at most {MAX_FIELD_PARTS} (0 or 1 profiles no part)",
                            self.field_parts
                        ),
                    )
                })
            })
            .or_else(|| {
                (!(self.t_min.is_finite() && self.t_min > 0.0)).then(|| {
                    (
                        "t_min",
                        format!("{}: must be finite and positive", self.t_min),
                    )
                })
            })
    }

    /// The steps of a parameter, in its [`unit`].
    fn steps(&self, q: Param) -> &[f64] {
        match q {
            Param::Nu => &self.nu,
            Param::FrictionAngle => &self.friction_deg,
            _ => &self.decades,
        }
    }
}

/// The unit a parameter's steps are in.
pub fn unit(q: Param) -> &'static str {
    match q {
        Param::Nu => "absolute",
        Param::FrictionAngle => "deg",
        _ => "decades",
    }
}

/// The value `step` away from `value` (signed; in [`unit`]), when the parameter can hold it.
fn moved(q: Param, value: f64, step: f64) -> Option<f64> {
    let v = if q.log_scaled() {
        value * 10f64.powf(step)
    } else {
        value + step
    };
    q.encodable(v).then_some(v)
}

/// One move away from the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Move {
    /// Signed step, in the parameter's unit.
    pub step: f64,
    /// The parameter's value there.
    pub value: f64,
    /// Mean loss rise over the samples, relative to the fit's mean loss (%).
    pub rise_pct: f64,
    /// The cameras' paired t-statistic of the rise (clamped to ±1e6).
    pub t: f64,
}

/// How one side of the profile ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SideEnd {
    /// The cameras agree the last move is worse: its value bounds the parameter.
    Bounded,
    /// No step was resolved.
    Open,
    /// The cameras agree the last move is better: the fit stopped short on this side.
    Better,
    /// The next step leaves the parameter's range (ν in (0, 0.49), a positive modulus).
    Range,
}

/// The profile of one parameter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamProfile {
    /// [`Param::name`].
    pub param: String,
    /// The unit of the steps.
    pub unit: String,
    /// The fitted value.
    pub value: f64,
    /// The moves below the fit, nearest first.
    pub below: Vec<Move>,
    /// The moves above the fit, nearest first.
    pub above: Vec<Move>,
    /// How each side (below, above) ended.
    pub ends: [SideEnd; 2],
    /// The values of the bounds (below, above), where the side is [`SideEnd::Bounded`].
    pub bounds: [Option<f64>; 2],
}

impl ParamProfile {
    /// The move of side `k` (0 below, 1 above) that the cameras agree is better and that
    /// lowers the loss most.
    pub fn best(&self, k: usize) -> Option<&Move> {
        let moves = if k == 0 { &self.below } else { &self.above };
        moves
            .iter()
            .filter(|m| m.rise_pct < 0.0)
            .min_by(|a, b| a.rise_pct.total_cmp(&b.rise_pct))
    }

    /// One line for the log: `E 1.0182e6: from 5.7255e5 (-0.25 decades) to 1.8106e6 (+0.25)`.
    pub fn summary(&self) -> String {
        let side = |k: usize| -> String {
            let moves = if k == 0 { &self.below } else { &self.above };
            let (bound, open) = if k == 0 {
                ("from", "down to")
            } else {
                ("to", "up to")
            };
            let shown = match self.ends[k] {
                SideEnd::Better => self.best(k),
                _ => moves.last(),
            };
            match (self.ends[k], shown) {
                (SideEnd::Bounded, Some(m)) => {
                    format!("{bound} {:.4e} ({:+} {})", m.value, m.step, self.unit)
                }
                (SideEnd::Better, Some(m)) => format!(
                    "{:.4e} ({:+} {}) is better: the fit stopped short",
                    m.value, m.step, self.unit
                ),
                (SideEnd::Range, _) => format!("{open} the end of its range"),
                (_, Some(m)) => format!(
                    "not bounded {open} {:.4e} ({:+} {})",
                    m.value, m.step, self.unit
                ),
                (_, None) => "not profiled".into(),
            }
        };
        format!(
            "{} {:.4e}: {}; {}",
            self.param,
            self.value,
            side(0),
            side(1)
        )
    }
}

/// The move the cameras agree lowers the loss most, over the profiles of the parameters
/// `eligible` accepts: (index of the parameter, its value there, relative rise %, negative).
pub fn best_better(
    profiles: &[ParamProfile],
    eligible: impl Fn(usize) -> bool,
) -> Option<(usize, f64, f64)> {
    profiles
        .iter()
        .enumerate()
        .filter(|(k, _)| eligible(*k))
        .flat_map(|(k, p)| {
            (0..2).filter_map(move |s| match p.ends[s] {
                SideEnd::Better => p.best(s).map(|m| (k, m.value, m.rise_pct)),
                _ => None,
            })
        })
        .min_by(|a, b| a.2.total_cmp(&b.2))
}

/// The paired statistics of a move against the fit: (relative rise %, t over the cameras).
pub fn paired(fit: &ViewLosses, at: &ViewLosses) -> (f64, f64) {
    // Per camera: the mean over its frames of the rise.
    let mut per_view: BTreeMap<u16, (f64, usize)> = BTreeMap::new();
    let mut pairs = Vec::new();
    let (mut base, mut n) = (0.0, 0usize);
    for (key, l0) in fit {
        let Some(l1) = at.get(key) else { continue };
        let d = l1 - l0;
        pairs.push(d);
        let e = per_view.entry(key.1).or_default();
        e.0 += d;
        e.1 += 1;
        base += l0;
        n += 1;
    }
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let samples: Vec<f64> = if per_view.len() >= 3 {
        per_view.values().map(|(s, k)| s / *k as f64).collect()
    } else {
        pairs.clone()
    };
    let rise = pairs.iter().sum::<f64>() / n as f64;
    let rel = 100.0 * rise / (base / n as f64).max(f64::MIN_POSITIVE);
    (rel, t_statistic(&samples))
}

/// `mean / (sd / √n)`, clamped to ±1e6 (identical samples give ±1e6, or 0 when all are 0).
fn t_statistic(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    if x.len() < 2 {
        return 0.0;
    }
    let mean = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let se = (var / n).sqrt();
    if se == 0.0 {
        return if mean == 0.0 {
            0.0
        } else {
            1e6 * mean.signum()
        };
    }
    (mean / se).clamp(-1e6, 1e6)
}

/// Where the parabola through a parameter's fit and its first move on each side puts the
/// loss's minimum, when both moves are resolved at the first step (the profile brackets the
/// minimum there): `x* = s (r₋ − r₊) / (2 (r₋ + r₊))` with `r±` the rises at `±s`, at most
/// `s/2` from the fit (the steps quantise the fit to `s`; the vertex refines it within one).
pub fn vertex(p: &ParamProfile, q: Param) -> Option<f64> {
    let ([lo], [hi]) = (p.below.as_slice(), p.above.as_slice()) else {
        return None;
    };
    if p.ends != [SideEnd::Bounded; 2] || lo.rise_pct <= 0.0 || hi.rise_pct <= 0.0 {
        return None;
    }
    let s = hi.step;
    let x = s * (lo.rise_pct - hi.rise_pct) / (2.0 * (lo.rise_pct + hi.rise_pct));
    moved(q, p.value, x.clamp(-0.5 * s, 0.5 * s))
}

/// Profiles each of `learned` (values `at`, in the same order) with `eval`, which scores a set
/// of values and returns the loss of every (frame, view) of the fit. The fit itself is scored
/// first (its losses are returned with the profiles); `log` hears each parameter's
/// [`ParamProfile::summary`].
pub fn profile<E>(
    params: &ProfileParams,
    learned: &[Param],
    at: &[f64],
    mut eval: impl FnMut(&[f64]) -> Result<ViewLosses, E>,
    mut log: impl FnMut(&str),
) -> Result<(Vec<ParamProfile>, ViewLosses), E> {
    let fit = eval(at)?;
    let mut out = Vec::with_capacity(learned.len());
    for (k, &q) in learned.iter().enumerate() {
        let mut sides: [Vec<Move>; 2] = [Vec::new(), Vec::new()];
        let mut ends = [SideEnd::Open; 2];
        let mut bounds = [None, None];
        for (s, sign) in [-1.0, 1.0].into_iter().enumerate() {
            for &step in params.steps(q) {
                let Some(v) = moved(q, at[k], sign * step) else {
                    if ends[s] != SideEnd::Better {
                        ends[s] = SideEnd::Range;
                    }
                    break;
                };
                let mut values = at.to_vec();
                values[k] = v;
                let (rise_pct, t) = paired(&fit, &eval(&values)?);
                let lowest = sides[s]
                    .iter()
                    .map(|m| m.rise_pct)
                    .fold(f64::INFINITY, f64::min);
                sides[s].push(Move {
                    step: sign * step,
                    value: v,
                    rise_pct,
                    t,
                });
                if ends[s] == SideEnd::Better {
                    // A better side is followed while each step lowers the loss further.
                    if rise_pct < lowest {
                        continue;
                    }
                    break;
                }
                if t >= params.t_min {
                    ends[s] = SideEnd::Bounded;
                    bounds[s] = Some(v);
                    break;
                }
                if t <= -params.t_min {
                    ends[s] = SideEnd::Better;
                }
            }
        }
        let [below, above] = sides;
        let p = ParamProfile {
            param: q.name().into(),
            unit: unit(q).into(),
            value: at[k],
            below,
            above,
            ends,
            bounds,
        };
        log(&p.summary());
        out.push(p);
    }
    Ok((out, fit))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Losses of `views` cameras over `frames` frames from a per-(frame, view) function.
    fn losses(frames: u16, views: u16, f: impl Fn(u16, u16) -> f64) -> ViewLosses {
        (1..=frames)
            .flat_map(|fr| (0..views).map(move |v| (fr, v)))
            .map(|k| (k, f(k.0, k.1)))
            .collect()
    }

    #[test]
    fn a_rise_every_camera_sees_is_resolved_and_a_mixed_one_is_not() {
        let fit = losses(4, 8, |f, v| 0.1 + 0.001 * f64::from(f + v));
        let worse = losses(4, 8, |f, v| {
            0.11 + 0.001 * f64::from(f + v) + 1e-4 * f64::from(v)
        });
        let (rise, t) = paired(&fit, &worse);
        assert!(rise > 5.0 && t > 10.0, "{rise} {t}");
        // Half the cameras see it better, half worse, by the same amount: t = 0.
        let mixed = losses(4, 8, |f, v| {
            0.1 + 0.001 * f64::from(f + v) + if v % 2 == 0 { 0.01 } else { -0.01 }
        });
        let (rise, t) = paired(&fit, &mixed);
        assert!(rise.abs() < 1e-9 && t.abs() < 1e-6, "{rise} {t}");
        // A move that changes nothing.
        assert_eq!(paired(&fit, &fit).1, 0.0);
        // No common sample: NaN, never a verdict.
        assert!(paired(&fit, &BTreeMap::new()).1.is_nan());
    }

    /// A quadratic loss about `centre` (log10 of the value) of curvature `c`, each camera with
    /// its own noise of the same scale: the profile bounds it where the rise beats the noise.
    fn quadratic(centre: f64, c: f64, noise: f64) -> impl FnMut(&[f64]) -> Result<ViewLosses, ()> {
        move |u: &[f64]| {
            let x = u[0].log10() - centre;
            Ok(losses(6, 10, |f, v| {
                // A fixed pseudo-random pattern per (frame, view), scaled by the distance.
                let h = ((u32::from(f) * 7919 + u32::from(v) * 104_729) % 1000) as f64 / 1000.0;
                0.2 + c * x * x + noise * x * (h - 0.5)
            }))
        }
    }

    #[test]
    fn a_sharp_minimum_is_bounded_at_the_first_step_and_a_flat_one_is_not() {
        let p = ProfileParams::default();
        let sharp = profile(&p, &[Param::E], &[1e6], quadratic(6.0, 0.1, 0.01), |_| {})
            .unwrap()
            .0;
        assert_eq!(sharp[0].ends, [SideEnd::Bounded; 2]);
        assert_eq!(sharp[0].below.len(), 1);
        let b = sharp[0].bounds;
        assert!((b[0].unwrap() - 10f64.powf(5.75)).abs() < 1.0, "{b:?}");
        assert!((b[1].unwrap() - 10f64.powf(6.25)).abs() < 10.0, "{b:?}");
        // The rise is tiny against the cameras' disagreement: no step is resolved.
        let flat = profile(&p, &[Param::E], &[1e6], quadratic(6.0, 1e-6, 0.5), |_| {})
            .unwrap()
            .0;
        assert_eq!(flat[0].ends, [SideEnd::Open; 2]);
        assert_eq!(flat[0].below.len(), 3);
        assert_eq!(flat[0].bounds, [None, None]);
        assert!(
            flat[0]
                .summary()
                .contains("not bounded down to 1.0000e5 (-1 decades)"),
            "{}",
            flat[0].summary()
        );
    }

    #[test]
    fn a_fit_short_of_the_minimum_is_told_and_the_range_is_respected() {
        let p = ProfileParams::default();
        // The minimum lies half a decade above the fit.
        let short = profile(&p, &[Param::E], &[1e6], quadratic(6.5, 0.1, 0.0), |_| {})
            .unwrap()
            .0;
        assert_eq!(short[0].ends, [SideEnd::Bounded, SideEnd::Better]);
        // The better side is followed while the loss falls: +0.25, +0.5 (the minimum), +1.
        let steps: Vec<f64> = short[0].above.iter().map(|m| m.step).collect();
        assert_eq!(steps, [0.25, 0.5, 1.0]);
        let (k, v, rise) = best_better(&short, |_| true).unwrap();
        assert_eq!(best_better(&short, |_| false), None);
        assert_eq!(k, 0);
        assert!(
            (v - 10f64.powf(6.5)).abs() < 10.0 && rise < 0.0,
            "{v} {rise}"
        );
        assert!(
            short[0]
                .summary()
                .contains("3.1623e6 (+0.5 decades) is better"),
            "{}",
            short[0].summary()
        );
        // At the minimum nothing is better.
        let at = profile(
            &p,
            &[Param::E],
            &[10f64.powf(6.5)],
            quadratic(6.5, 0.1, 0.0),
            |_| {},
        )
        .unwrap()
        .0;
        assert_eq!(best_better(&at, |_| true), None);
        // ν 0.47: a step of 0.025 up leaves (0, 0.49).
        let nu = profile(
            &p,
            &[Param::Nu],
            &[0.47],
            |u: &[f64]| {
                Ok::<_, ()>(losses(2, 4, |_, v| {
                    (u[0] - 0.47).powi(2) * (1.0 + 0.1 * f64::from(v))
                }))
            },
            |_| {},
        )
        .unwrap()
        .0;
        assert_eq!(nu[0].ends[1], SideEnd::Range);
        assert!(nu[0].above.is_empty());
        assert_eq!(nu[0].ends[0], SideEnd::Bounded);
    }

    #[test]
    fn the_vertex_refines_a_bracketed_minimum_within_half_a_step() {
        let p = ProfileParams::default();
        // The minimum a tenth of a decade above the fit: the parabola finds it exactly.
        let pr = profile(&p, &[Param::E], &[1e6], quadratic(6.1, 0.1, 0.0), |_| {})
            .unwrap()
            .0;
        let v = vertex(&pr[0], Param::E).unwrap();
        assert!((v.log10() - 6.1).abs() < 1e-9, "{v}");
        // Both first moves worse means the parabola's vertex lies within half a step.
        let pr = profile(&p, &[Param::E], &[1e6], quadratic(6.12, 0.1, 0.0), |_| {})
            .unwrap()
            .0;
        assert_eq!(pr[0].ends, [SideEnd::Bounded; 2]);
        let v = vertex(&pr[0], Param::E).unwrap();
        assert!((v.log10() - 6.12).abs() < 1e-9, "{v}");
        // Not bracketed at the first step: no vertex.
        let flat = profile(&p, &[Param::E], &[1e6], quadratic(6.0, 1e-6, 0.5), |_| {})
            .unwrap()
            .0;
        assert_eq!(vertex(&flat[0], Param::E), None);
    }

    #[test]
    fn invalid_steps_are_named() {
        let mut p = ProfileParams::default();
        assert!(p.invalid().is_none());
        p.decades = vec![0.5, 0.25];
        assert_eq!(p.invalid().unwrap().0, "decades");
        p.decades = vec![0.25];
        p.t_min = f64::NAN;
        assert_eq!(p.invalid().unwrap().0, "t_min");
    }
}
