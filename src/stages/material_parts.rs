//! The parts phase of `material: {model: auto}`: a fitted field's values grouped into `k`
//! materials ([`Parts`], natural breaks weighted by volume), each part's E then fitted by the
//! quasi-Newton descent of the global model ([`LineSearch`]) together with the family's other
//! learned parameters (ν, ...), on the same views and frames as the field.

use crate::physics::descent::LineSearch;
use crate::physics::field_parts::{Parts, natural_breaks};
use crate::physics::fit::FitError;
use crate::physics::params::{MaterialValues, Param};
use crate::physics::rollout::{Moduli, Rollout, RolloutError, Truncate, Wants};
use crate::physics::views::ViewsLoss;
use crate::pipeline::stage::{MetricRow, StageContext, StageError};
use crate::stages::material::MaterialParams;
use crate::stages::material_field::FieldFit;

/// The optimiser's first steepest step (decades of a part's E): the parts start at the field's
/// values, a refinement rather than a search from a guess.
const FIRST_STEP: f64 = 0.1;

/// `from`'s field grouped into `k` parts, fitted for `epochs` iterations on `loss` (the
/// rollouts `base`'s with the parts' moduli). `None` when the field does not split into `k`
/// parts, or varies more than E (a ν field keeps its own values).
///
/// # Errors
/// A failed or interrupted rollout, or a non-finite gradient, named with the phase.
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit(
    p: &MaterialParams,
    ctx: &mut StageContext<'_>,
    base: Rollout<'_>,
    loss: &mut ViewsLoss<'_>,
    learned: &[Param],
    from: &FieldFit,
    k: usize,
    epochs: u32,
) -> Result<Option<FieldFit>, StageError> {
    if from.field.outputs != [Param::E] {
        return Ok(None);
    }
    let training = |epoch: u32, message: String| {
        StageError::failed(FitError::Training {
            epoch,
            message: format!("material parts ({k}): {message}"),
        })
    };
    let field_e = from
        .field
        .field_moduli_at(&from.field.points, &from.values)
        .map_err(|e| training(0, e.to_string()))?
        .e;
    let log_e: Vec<f64> = field_e.iter().map(|e| e.log10()).collect();
    let volume = &base.object.body.material.volume;
    let Some(start) = natural_breaks(&log_e, volume, k) else {
        return Ok(None);
    };
    let part = start.assign(&field_e);
    let others: Vec<Param> = learned.iter().copied().filter(|q| *q != Param::E).collect();
    let mut u: Vec<f64> = start.log10_e.clone();
    u.extend(
        others
            .iter()
            .map(|q| q.encode(from.values.get(*q).unwrap_or(1.0))),
    );
    let at = |u: &[f64]| -> (Parts, MaterialValues, Moduli) {
        let parts = Parts {
            thresholds: start.thresholds.clone(),
            log10_e: u[..k].to_vec(),
        };
        let mut values = from.values.clone();
        for (q, v) in others.iter().zip(&u[k..]) {
            values.values.insert(*q, q.decode(*v));
        }
        let mut moduli = Moduli {
            e: field_e.clone(),
            nu: vec![values.get(Param::Nu).unwrap_or(f64::NAN); field_e.len()],
        };
        parts.apply(&part, &mut moduli);
        (parts, values, moduli)
    };
    let shares = start.shares(&part, volume);
    ctx.progress.log(&format!(
        "material parts: the field's log10 E cut at {} into {k} parts ({}), each fitted as one material",
        start.cuts_text(),
        start
            .log10_e
            .iter()
            .zip(&shares)
            .map(|(l, (w, _))| format!(
                "{:.0} % of the volume at E {:.4e}",
                100.0 * w,
                10f64.powf(*l)
            ))
            .collect::<Vec<_>>()
            .join("; ")
    ));
    let fail = |epoch: u32| {
        move |e: RolloutError| match e {
            RolloutError::Interrupted => StageError::Interrupted,
            e => training(epoch, e.to_string()),
        }
    };
    let mut search = LineSearch::new(FIRST_STEP, p.lr_final, 1.0);
    let mut l = f64::NAN;
    for epoch in 0..epochs {
        if crate::stages::material::epoch_loop_stops(ctx, p, base.work, "the parts", epoch)? {
            break;
        }
        let (parts, values, moduli) = at(&u);
        let out = Rollout {
            material: &values,
            moduli: Some(&moduli),
            ..base
        }
        .run(loss, Wants::Material(Truncate::None))
        .map_err(fail(epoch))?;
        l = out.loss();
        let per = out
            .moduli
            .as_ref()
            .ok_or_else(|| training(epoch, "no per-particle gradient".into()))?;
        let mut g = parts.gradient(&part, &per.e);
        let global = out.material.clone().unwrap_or_default();
        g.extend(
            others
                .iter()
                .zip(&u[k..])
                .map(|(q, u)| global.get(q).copied().unwrap_or(0.0) * q.dvalue_du(*u)),
        );
        if let Some(v) = g.iter().find(|v| !v.is_finite()) {
            return Err(training(epoch, format!("non-finite gradient ({v})")));
        }
        let it = search
            .iterate(&u, l, &g, |trial, up_to| {
                let (_, values, moduli) = at(trial);
                Rollout {
                    material: &values,
                    moduli: Some(&moduli),
                    ..base
                }
                .run(loss, Wants::LossUpTo(up_to))
                .map(|o| o.loss())
            })
            .map_err(fail(epoch))?;
        u = it.u;
        l = it.loss;
        ctx.metric(MetricRow {
            epoch: Some(epoch),
            view: None,
            frame: None,
            metric: format!("parts{k}_loss"),
            value: l,
        });
        ctx.progress.log(&format!(
            "    parts ({k}) epoch {}/{epochs}: loss {l:.5}  E {}{}",
            epoch + 1,
            u[..k]
                .iter()
                .map(|v| format!("{:.4e}", 10f64.powf(*v)))
                .collect::<Vec<_>>()
                .join(" / "),
            others
                .iter()
                .zip(&u[k..])
                .map(|(q, v)| format!("  {} {:.4e}", q.name(), q.decode(*v)))
                .collect::<String>()
        ));
        if search.converged() {
            break;
        }
    }
    let (parts, values, moduli) = at(&u);
    if !l.is_finite() {
        return Err(training(epochs, format!("non-finite loss ({l})")));
    }
    let mut field = from.field.clone();
    field.parts = Some(parts);
    Ok(Some(FieldFit {
        field,
        moduli,
        values,
    }))
}
