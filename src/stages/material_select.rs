//! `material: {model: auto}`: the simplest model the frames support, measured on views the
//! field never saw.
//!
//! The global model is fitted first on every training view (exactly `model: global`'s fit).
//! Then a field, started from it, is fitted on the training views minus a held-out set, and
//! both are scored on the held-out views alone. The field is kept only when it lowers that
//! loss by more than `margin` (relative). The global model saw the held-out views and the field
//! did not, so the comparison leans towards the simpler model: a field is kept only when the
//! object really is not uniform. When the global model is kept, every figure is the global
//! model's.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Settings of `model: auto` (the `auto:` block of `material`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AutoSettings {
    /// Training views held out of the field's fit and used to decide (default: every fourth
    /// training view, from the fourth on; at least one).
    #[serde(default)]
    pub held_out_views: Option<Vec<u16>>,
    /// The field is kept when its held-out loss is below `(1 − margin)` × the global model's.
    #[serde(default = "margin")]
    pub margin: f64,
    /// The last frames held out as well (of every view): the field is fitted on the fit views'
    /// earlier frames and scored on what it did not see, later frames included, which tests
    /// that it predicts the motion rather than fits it (default: a quarter of the frames,
    /// rounded up; 0 holds out views only).
    #[serde(default)]
    pub held_out_frames: Option<u16>,
    /// A field that wins is scored again on the same object rebuilt on a grid whose cell is
    /// this many times as large (particles resampled, the field read at their rest
    /// positions), and kept only when it wins there too: a gain that depends on the
    /// discretisation (a bounce that happens to land nearer the truth) is not a property of
    /// the object. 1 skips the check.
    #[serde(default = "regrid")]
    pub regrid: f64,
    /// The share of the field's relative held-out gain on its own grid that must remain on
    /// the second grid (`regrid`): a property of the object survives a 20 % change of the
    /// discretisation, a gain that mostly vanishes with it is the discretisation's. 0 asks
    /// only that the field win there by `margin`.
    #[serde(default = "regrid_keep")]
    pub regrid_keep: f64,
}

impl AutoSettings {
    /// The setting at fault (`auto.margin`, `auto.regrid`, `auto.regrid_keep`) and why.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(self.margin.is_finite() && (0.0..1.0).contains(&self.margin)) {
            return Err((
                "auto.margin",
                format!("must be in [0, 1), found {}", self.margin),
            ));
        }
        if !(self.regrid.is_finite() && (0.5..=2.0).contains(&self.regrid)) {
            return Err((
                "auto.regrid",
                format!(
                    "must be in [0.5, 2] (1 skips the second grid), found {}",
                    self.regrid
                ),
            ));
        }
        if !(self.regrid_keep.is_finite() && (0.0..=1.0).contains(&self.regrid_keep)) {
            return Err((
                "auto.regrid_keep",
                format!("must be in [0, 1], found {}", self.regrid_keep),
            ));
        }
        Ok(())
    }

    /// The frames held out of `1..=last`.
    pub fn held_out_frames(&self, last: u16) -> u16 {
        self.held_out_frames
            .unwrap_or(if last >= 2 { last.div_ceil(4) } else { 0 })
    }
}

fn margin() -> f64 {
    0.02
}

fn regrid() -> f64 {
    1.2
}

fn regrid_keep() -> f64 {
    0.5
}

impl Default for AutoSettings {
    fn default() -> Self {
        Self {
            held_out_views: None,
            margin: margin(),
            held_out_frames: None,
            regrid: regrid(),
            regrid_keep: regrid_keep(),
        }
    }
}

/// What `model: auto` compared and kept (`material.json`'s `selection`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelSelection {
    /// The model kept (`global` or `field` for the material; `rigid`, `translation` or
    /// `field` for the velocity).
    pub kept: String,
    /// Why, in words.
    pub reason: String,
    /// The views the decision was scored on, and those the field was fitted on.
    pub held_out_views: Vec<u16>,
    pub fit_views: Vec<u16>,
    /// The loss on the held-out views of the global fit and of the field (when one was fitted).
    pub loss_global_held_out: Option<f64>,
    pub loss_field_held_out: Option<f64>,
    /// The relative margin the field had to win by.
    pub margin: f64,
    /// The field was fitted on frames `1..=fit_frames_last` (the later ones held out).
    #[serde(default)]
    pub fit_frames_last: u16,
    /// The held-out loss of one material at the field's median E and ν (material only): the
    /// field must beat the lower of it and the global fit's, and when the field loses it
    /// replaces the global fit only if it beats that by the margin too.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_global_at_field_median_held_out: Option<f64>,
    /// The cell (m) of the second grid the field was scored on (`auto.regrid`), when it won
    /// on the first, and the held-out losses there of the simpler model and of the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub regrid_dx_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_simple_regrid_held_out: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_field_regrid_held_out: Option<f64>,
    /// The parts models fitted from a winning field (`field.parts`), simplest first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parts: Vec<PartsScore>,
}

/// A parts model `auto` compared ([`crate::physics::field_parts::Parts`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PartsScore {
    /// Its number of parts.
    pub parts: usize,
    /// The field's `log10 E` between its parts, and each part's fitted `log10 E` (E in Pa).
    pub thresholds: Vec<f64>,
    pub log10_e: Vec<f64>,
    /// Its loss on the held-out data, and on the second grid's (when scored there).
    pub loss_held_out: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_regrid_held_out: Option<f64>,
}

impl ModelSelection {
    /// The simpler model `kept`, decided on `held_out_views` for a field fitted on `fit_views`
    /// and frames `1..=fit_frames_last`, with no reason or loss recorded yet.
    pub fn simpler(
        kept: &str,
        held_out_views: Vec<u16>,
        fit_views: Vec<u16>,
        margin: f64,
        fit_frames_last: u16,
    ) -> Self {
        Self {
            kept: kept.into(),
            reason: String::new(),
            held_out_views,
            fit_views,
            loss_global_held_out: None,
            loss_field_held_out: None,
            margin,
            fit_frames_last,
            loss_global_at_field_median_held_out: None,
            regrid_dx_m: None,
            loss_simple_regrid_held_out: None,
            loss_field_regrid_held_out: None,
            parts: Vec::new(),
        }
    }
}

/// A non-uniform model `auto` may keep: its name (`the 2-part model`, `the field`), its held-out loss,
/// and its held-out loss on the second grid when it was scored there.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub name: String,
    pub held_out: f64,
    pub regrid: Option<f64>,
}

/// Which of `candidates` (simplest first) `auto` keeps against the simpler model's held-out
/// loss `simple` (and `simple2` on the second grid, when `auto.regrid` scored there): those that
/// win by `margin` on the first grid, and on the second by `margin` with `keep` of their gain
/// ([`decide_again`]), pass; of them, the simplest whose held-out loss is within `margin` of
/// the lowest. `None` when none passes. The reason names every candidate's outcome.
pub fn choose(
    simple: f64,
    simple2: Option<f64>,
    candidates: &[Candidate],
    margin: f64,
    keep: f64,
    simpler: &str,
) -> (Option<usize>, String) {
    let mut clauses = Vec::new();
    let mut passing = Vec::new();
    for (i, c) in candidates.iter().enumerate() {
        let (wins, reason) = decide(simple, c.held_out, margin, simpler, &c.name);
        let (passes, reason) = match (wins, simple2, c.regrid) {
            (true, Some(s2), Some(c2)) => {
                let (again, why) = decide_again(
                    (simple, c.held_out),
                    (s2, c2),
                    margin,
                    keep,
                    simpler,
                    &c.name,
                );
                (again, format!("{reason}; on the second grid: {why}"))
            }
            // Asked for and not scored there: it cannot pass.
            (true, Some(_), None) => (false, format!("{reason}; not scored on the second grid")),
            (w, _, _) => (w, reason),
        };
        if passes {
            passing.push(i);
        }
        clauses.push(format!("{}: {reason}", c.name));
    }
    let best = passing
        .iter()
        .map(|&i| candidates[i].held_out)
        .fold(f64::INFINITY, f64::min);
    let chosen = passing
        .into_iter()
        .find(|&i| candidates[i].held_out <= (1.0 + margin) * best);
    let verdict = match chosen {
        Some(i) if candidates.len() > 1 => format!(
            "{} kept (the simplest that passes, within {:.1} % of the best that does)",
            candidates[i].name,
            100.0 * margin
        ),
        Some(i) => format!("{} kept", candidates[i].name),
        None => format!("the {simpler} kept"),
    };
    (chosen, format!("{}; {verdict}", clauses.join("; ")))
}

/// The held-out views among `train` (sorted, distinct): `asked`, checked, or every fourth from
/// the fourth (at least one). At least one training view must remain for the fit.
///
/// # Errors
/// Fewer than two training views, an asked view that is not a training view, or a set that
/// leaves none to fit, named.
pub fn held_out_views(train: &[u16], asked: Option<&[u16]>) -> Result<Vec<u16>, String> {
    if train.len() < 2 {
        return Err(format!(
            "model: auto holds training views out to decide, and the capture has {} training view(s); use `model: global` or `model: field`",
            train.len()
        ));
    }
    let held: Vec<u16> = match asked {
        Some(a) => {
            if let Some(v) = a.iter().find(|v| !train.contains(v)) {
                return Err(format!(
                    "auto.held_out_views: view {v} is not a training view (they are {train:?})"
                ));
            }
            let mut a = a.to_vec();
            a.sort_unstable();
            a.dedup();
            a
        }
        None => {
            let every: Vec<u16> = train.iter().skip(3).step_by(4).copied().collect();
            if every.is_empty() {
                vec![train[train.len() - 1]]
            } else {
                every
            }
        }
    };
    if held.is_empty() {
        return Err("auto.held_out_views: empty; leave it out for the default".into());
    }
    if held.len() >= train.len() {
        return Err(format!(
            "auto.held_out_views: {held:?} leaves no training view to fit the field on"
        ));
    }
    Ok(held)
}

/// The training views of `targets` split into (held out, fitted on) for `auto` of stage
/// `stage` (sorted, distinct).
///
/// # Errors
/// [`held_out_views`]' errors, named with the stage.
pub fn split_views(
    targets: &[crate::scene::targets::Target],
    auto: &AutoSettings,
    stage: &str,
) -> Result<(Vec<u16>, Vec<u16>), crate::pipeline::stage::StageError> {
    let mut train: Vec<u16> = targets.iter().map(|t| t.row.view).collect();
    train.sort_unstable();
    train.dedup();
    let held = held_out_views(&train, auto.held_out_views.as_deref()).map_err(|m| {
        crate::pipeline::stage::StageError::failed(crate::physics::fit::FitError::Invalid(format!(
            "stages.{stage}.{m}"
        )))
    })?;
    let fit = train.into_iter().filter(|v| !held.contains(v)).collect();
    Ok((held, fit))
}

/// Whether the richer model `name` (`the field`, `the 2-part model`) wins (its held-out loss
/// `field` below `(1 − margin)` × the simpler model's `simple`), and the reason in words
/// (`simpler` names that model).
pub fn decide(simple: f64, field: f64, margin: f64, simpler: &str, name: &str) -> (bool, String) {
    let wins = field_wins(simple, field, margin);
    let reason = format!(
        "held-out loss {field:.5} with {name} against {simple:.5} with the {simpler} ({:+.2} %); {name} {} by more than {:.1} %",
        100.0 * (field / simple - 1.0),
        if wins { "wins" } else { "does not win" },
        100.0 * margin
    );
    (wins, reason)
}

/// Whether the richer model `name` still wins on the second grid (`auto.regrid`): by more than `margin`
/// over the simpler model's held-out loss there (`simple2`, `field2`), and with at least
/// `keep` of its relative gain on the first grid (`simple`, `field`); the reason in words.
pub fn decide_again(
    (simple, field): (f64, f64),
    (simple2, field2): (f64, f64),
    margin: f64,
    keep: f64,
    simpler: &str,
    name: &str,
) -> (bool, String) {
    let (wins, reason) = decide(simple2, field2, margin, simpler, name);
    let gain = 1.0 - field / simple;
    let gain2 = 1.0 - field2 / simple2;
    if !wins || keep == 0.0 {
        return (wins, reason);
    }
    let kept = gain2 >= keep * gain;
    let reason = format!(
        "{reason}, {} {:.0} % of its gain on the first grid ({:.0} % of it remains)",
        if kept {
            "and keeps at least"
        } else {
            "but keeps less than"
        },
        100.0 * keep,
        100.0 * gain2 / gain
    );
    (kept, reason)
}

/// Whether the one material at the field's median (held-out loss `median`) replaces the
/// global fit (`global`) once the field has lost: only when it wins by `margin` as well, since
/// the global fit saw the held-out views and a smaller difference is their noise.
pub fn median_replaces_global(global: f64, median: f64, margin: f64) -> bool {
    field_wins(global, median, margin)
}

/// Whether the field's held-out loss beats the global model's by more than `margin`.
pub fn field_wins(global: f64, field: f64, margin: f64) -> bool {
    field.is_finite() && global.is_finite() && field < (1.0 - margin) * global
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn held_out_views_are_spread_checked_and_leave_views_to_fit() {
        let train: Vec<u16> = (0..10).collect();
        assert_eq!(held_out_views(&train, None).unwrap(), vec![3, 7]);
        assert_eq!(held_out_views(&[0, 4], None).unwrap(), vec![4]);
        assert_eq!(
            held_out_views(&train, Some(&[5, 2, 5])).unwrap(),
            vec![2, 5]
        );
        let err = held_out_views(&train, Some(&[12])).unwrap_err();
        assert!(err.contains("view 12 is not a training view"), "{err}");
        let err = held_out_views(&[1, 2], Some(&[1, 2])).unwrap_err();
        assert!(err.contains("leaves no training view"), "{err}");
        let err = held_out_views(&[3], None).unwrap_err();
        assert!(err.contains("1 training view"), "{err}");
    }

    #[test]
    fn a_field_must_keep_most_of_its_gain_on_the_second_grid() {
        // The two-material bar: -51.7 % and -41.3 %; the homogeneous torus: -26 % and -6 %.
        let (bar, why) = decide_again(
            (1.0, 0.483),
            (1.0, 0.587),
            0.02,
            0.5,
            "global model",
            "the field",
        );
        assert!(bar && why.contains("keeps at least 50 %"), "{why}");
        let (torus, why) = decide_again(
            (0.508, 0.377),
            (0.490, 0.457),
            0.02,
            0.5,
            "global model",
            "the field",
        );
        assert!(!torus && why.contains("keeps less than 50 %"), "{why}");
        assert!(why.contains("(26 % of it remains)"), "{why}");
        let (only_margin, _) = decide_again(
            (0.508, 0.377),
            (0.490, 0.457),
            0.02,
            0.0,
            "global model",
            "the field",
        );
        assert!(only_margin);
        let (lost, why) = decide_again(
            (1.0, 0.5),
            (1.0, 0.99),
            0.02,
            0.5,
            "rigid motion",
            "the field",
        );
        assert!(!lost && why.contains("does not win"), "{why}");
        let bad = AutoSettings {
            regrid_keep: 1.5,
            ..AutoSettings::default()
        };
        assert_eq!(bad.check().unwrap_err().0, "auto.regrid_keep");
    }

    #[test]
    fn the_median_material_replaces_the_global_fit_only_by_the_margin() {
        // The sample torus: the median 1.9 % below the global fit (E 1e6 exactly): kept global.
        assert!(!median_replaces_global(0.51756, 0.50793, 0.02));
        assert!(median_replaces_global(0.51756, 0.49, 0.02));
        assert!(!median_replaces_global(0.5, f64::NAN, 0.02));
    }

    #[test]
    fn a_quarter_of_the_frames_is_held_out_by_default() {
        let a = AutoSettings::default();
        assert_eq!(a.held_out_frames(9), 3);
        assert_eq!(a.held_out_frames(13), 4);
        assert_eq!(a.held_out_frames(1), 0);
        let none = AutoSettings {
            held_out_frames: Some(0),
            ..AutoSettings::default()
        };
        assert_eq!(none.held_out_frames(13), 0);
    }

    #[test]
    fn bad_auto_settings_are_named() {
        assert!(AutoSettings::default().check().is_ok());
        for (auto, field) in [
            (
                AutoSettings {
                    margin: 1.0,
                    ..AutoSettings::default()
                },
                "auto.margin",
            ),
            (
                AutoSettings {
                    regrid: 3.0,
                    ..AutoSettings::default()
                },
                "auto.regrid",
            ),
            (
                AutoSettings {
                    regrid: f64::NAN,
                    ..AutoSettings::default()
                },
                "auto.regrid",
            ),
        ] {
            let (name, why) = auto.check().unwrap_err();
            assert_eq!(name, field, "{why}");
            assert!(why.contains("found"), "{why}");
        }
        let skip = AutoSettings {
            regrid: 1.0,
            ..AutoSettings::default()
        };
        assert!(skip.check().is_ok(), "1 skips the second grid");
    }

    fn candidate(name: &str, held_out: f64, regrid: Option<f64>) -> Candidate {
        Candidate {
            name: name.into(),
            held_out,
            regrid,
        }
    }

    #[test]
    fn the_simplest_candidate_that_passes_both_grids_is_kept() {
        // A generated two-material bar at 160²: the field wins by 86 % but keeps 39 % of it on
        // the coarser grid; two parts win by 65 % and keep 58 %: the parts are kept.
        let bar = [
            candidate("the 2-part model", 0.21147, Some(0.38131)),
            candidate("the 3-part model", 0.17212, Some(0.37231)),
            candidate("the field", 0.08541, Some(0.40577)),
        ];
        let (k, why) = choose(0.60753, Some(0.61182), &bar, 0.02, 0.5, "global model");
        assert_eq!(k, Some(1), "{why}");
        assert!(
            why.contains("the 3-part model kept")
                && why.contains("the field: held-out loss 0.08541 with the field"),
            "{why}"
        );
        // The homogeneous sample torus: neither its parts nor its field keep half their gain.
        let torus = [
            candidate("the 2-part model", 0.38756, Some(0.44451)),
            candidate("the 3-part model", 0.36512, Some(0.43608)),
            candidate("the field", 0.35135, Some(0.43014)),
        ];
        let (k, why) = choose(0.53834, Some(0.50535), &torus, 0.02, 0.5, "global model");
        assert_eq!(k, None, "{why}");
        assert!(why.ends_with("the global model kept"), "{why}");
        // Without a second grid the simplest within the margin of the best wins.
        let (k, _) = choose(
            1.0,
            None,
            &[
                candidate("the 2-part model", 0.101, None),
                candidate("the field", 0.1, None),
            ],
            0.02,
            0.5,
            "global model",
        );
        assert_eq!(k, Some(0));
        let (k, _) = choose(
            1.0,
            None,
            &[
                candidate("the 2-part model", 0.2, None),
                candidate("the field", 0.1, None),
            ],
            0.02,
            0.5,
            "global model",
        );
        assert_eq!(k, Some(1));
        // A candidate that was not scored on the asked second grid cannot pass; NaN never wins.
        let (k, _) = choose(
            1.0,
            Some(1.0),
            &[
                candidate("the 2-part model", 0.1, None),
                candidate("the field", f64::NAN, Some(0.1)),
            ],
            0.02,
            0.5,
            "global model",
        );
        assert_eq!(k, None);
        assert_eq!(choose(1.0, None, &[], 0.02, 0.5, "global model").0, None);
    }

    #[test]
    fn the_field_must_win_by_the_margin() {
        assert!(field_wins(1.0, 0.97, 0.02));
        assert!(!field_wins(1.0, 0.99, 0.02));
        assert!(!field_wins(1.0, f64::NAN, 0.02));
        assert!(!field_wins(f64::NAN, 0.5, 0.02));
    }
}
