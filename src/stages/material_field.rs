//! The field phase of `material: {model: field}` (and `auto`): starting from the global fit
//! (every particle at the global E and ν), a triplane + MLP field ([`MaterialField`]) gives
//! each particle its own `E` (and `ν` with `field.vary`), learned by Adam with the planes'
//! total variation (eq. 8) added to the gradient: by default (`field.truncate: none`) once an
//! epoch along the whole rollout's gradient, the step's length searched on the loss
//! ([`StepSearch`]); with `field.truncate: frame` after every frame's truncated backward pass
//! (the seed method's online descent). The family's other learned parameters (ν, a yield
//! stress, ...) stay global and keep stepping with their own Adam at the field's rates.

use pipe_field::{AdamConfig as FieldAdamConfig, FieldAdam, LrSchedule};

use crate::physics::adam::{Adam, AdamConfig, decayed};
use crate::physics::fit::FitError;
use crate::physics::material_field::{MaterialField, percentiles};
use crate::physics::params::{MaterialValues, Param};
use crate::physics::rollout::{
    FrameGradient, Moduli, NextMaterial, Rollout, RolloutError, Truncate, Wants, is_fluid,
};
use crate::physics::step_search::{StepSearch, lerp, stalled};
use crate::physics::views::ViewsLoss;
use crate::pipeline::spec::MaterialFamily;
use crate::pipeline::stage::{MetricRow, StageContext, StageError};
use crate::stages::material::MaterialParams;

/// What the field phase learned.
pub(crate) struct FieldFit {
    /// The field.
    pub field: MaterialField,
    /// Its per-particle E and ν.
    pub moduli: Moduli,
    /// The family's values (the global parameters other than E and ν updated).
    pub values: MaterialValues,
}

/// The parameters a field learns (those of `vary` among `learned`, which must name E or ν), or
/// why `model: field` does not apply to the family (stage `name`).
pub(crate) fn outputs(
    family: MaterialFamily,
    learned: &[Param],
    vary: &[Param],
    name: &str,
) -> Result<Vec<Param>, StageError> {
    let invalid = |m: String| StageError::failed(FitError::Invalid(m));
    if is_fluid(family) {
        return Err(invalid(format!(
            "stages.{name}.model: field learns a solid's E and ν per particle; the family `{}` has neither (use `model: global`)",
            crate::simulate::spec::family_name(family)
        )));
    }
    if let Some(q) = vary.iter().find(|q| !matches!(q, Param::E | Param::Nu)) {
        return Err(invalid(format!(
            "stages.{name}.field.vary: `{}` cannot vary per particle (E and nu can)",
            q.name()
        )));
    }
    let outputs: Vec<Param> = learned
        .iter()
        .copied()
        .filter(|q| vary.contains(q))
        .collect();
    if outputs.is_empty() {
        return Err(invalid(format!(
            "stages.{name}.model: field varies {} per particle, and `learn` names none of them",
            vary.iter()
                .map(|q| q.name())
                .collect::<Vec<_>>()
                .join(" and ")
        )));
    }
    Ok(outputs)
}

/// A stage error naming the field phase's epoch.
fn training(epoch: u32, message: String) -> StageError {
    StageError::failed(FitError::Training { epoch, message })
}

/// Learns the field from `base`'s material (the global fit) over its frames, its rollouts
/// `base`'s with the field's moduli.
pub(crate) fn fit(
    p: &MaterialParams,
    ctx: &mut StageContext<'_>,
    base: Rollout<'_>,
    loss: &mut ViewsLoss<'_>,
    learned: &[Param],
) -> Result<FieldFit, StageError> {
    let (object, start, last) = (base.object, base.material, base.frames);
    let invalid = |m: String| StageError::failed(FitError::Invalid(m));
    let outputs = outputs(start.family, learned, &p.field.vary, ctx.name)?;
    let others: Vec<Param> = learned
        .iter()
        .copied()
        .filter(|q| !outputs.contains(q))
        .collect();
    let points: Vec<[f64; 3]> = object.body.state.x.iter().map(|x| x.to_array()).collect();
    let mut field = MaterialField::starting_at(&p.field, points, outputs.clone(), start)
        .map_err(|e| invalid(format!("stages.{}.field: {e}", ctx.name)))?;
    let epochs = p.field.epochs.unwrap_or(p.epochs);
    let steps = match p.field.truncate {
        Truncate::Frame => epochs * u32::from(last),
        Truncate::None => epochs,
    }
    .max(2);
    let schedule = LrSchedule::exponential(p.field.lr, p.field.lr_final, steps);
    let mut field_adam =
        FieldAdam::new(&field.field, schedule, schedule, FieldAdamConfig::default())
            .map_err(|e| invalid(format!("stages.{}.field: {e}", ctx.name)))?;
    let mut u: Vec<f64> = others
        .iter()
        .map(|q| q.encode(start.get(*q).unwrap_or(1.0)))
        .collect();
    let mut adam = Adam::new(others.len());
    let cfg = AdamConfig {
        clip: p.grad_clip,
        ..Default::default()
    };
    let values_of = |u: &[f64]| {
        let mut m = start.clone();
        for (q, u) in others.iter().zip(u) {
            m.values.insert(*q, q.decode(*u));
        }
        m
    };
    let mut values = start.clone();
    let mut moduli = field
        .moduli(&values)
        .map_err(|e| training(0, e.to_string()))?;
    ctx.progress.log(&format!(
        "material field: {} outputs ({}), {}² planes × {} channels, MLP {}×{}, {} weights, {epochs} epochs from the global fit",
        outputs.len(),
        outputs.iter().map(|q| q.name()).collect::<Vec<_>>().join(", "),
        p.field.resolution,
        p.field.channels,
        p.field.layers,
        p.field.hidden,
        field.field.param_count()
    ));
    let mut search = StepSearch::default();
    ctx.progress.start("field epoch", u64::from(epochs));
    let mut losses = Vec::new();
    for epoch in 0..epochs {
        if crate::stages::material::epoch_loop_stops(ctx, p, base.work, "the field", epoch)? {
            break;
        }
        let (mut cur_values, mut cur_moduli) = (values.clone(), moduli.clone());
        let (before_w, before_u) = (field.field.to_flat(), u.clone());
        let out = {
            let mut on_frame = |frame: u16, g: FrameGradient<'_>| {
                let fail = |message: String| RolloutError::Loss { frame, message };
                let gm = g
                    .moduli
                    .ok_or_else(|| fail("no per-particle gradient".into()))?;
                let d = field.output_gradient(&cur_moduli, gm);
                let mut grad = field
                    .field
                    .backward(&field.points, &d)
                    .map_err(|e| fail(format!("field backward: {e}")))?;
                field
                    .field
                    .tv_backward(&mut grad)
                    .map_err(|e| fail(format!("field TV: {e}")))?;
                field_adam
                    .step(&mut field.field, &grad)
                    .map_err(|e| fail(format!("field step: {e}")))?;
                if !others.is_empty() {
                    let gu: Vec<f64> = others
                        .iter()
                        .zip(&u)
                        .map(|(q, u)| g.values.get(q).copied().unwrap_or(0.0) * q.dvalue_du(*u))
                        .collect();
                    if let Some((q, v)) = others.iter().zip(&gu).find(|(_, v)| !v.is_finite()) {
                        return Err(fail(format!("non-finite gradient of `{}` ({v})", q.name())));
                    }
                    let progress = f64::from(adam.t) / f64::from(steps - 1);
                    // The field's rates: the stage's `lr` is the line search's first trial.
                    let lr = decayed(p.field.lr, p.field.lr_final, progress);
                    adam.step(&cfg, &mut u, &gu, &vec![lr; gu.len()]);
                    cur_values = values_of(&u);
                }
                cur_moduli = field
                    .moduli(&cur_values)
                    .map_err(|e| fail(format!("field forward: {e}")))?;
                Ok(Some(NextMaterial {
                    values: cur_values.clone(),
                    moduli: Some(cur_moduli.clone()),
                }))
            };
            let rollout = Rollout {
                material: &values,
                moduli: Some(&moduli),
                ..base
            };
            match p.field.truncate {
                Truncate::Frame => rollout.run_online(loss, &mut on_frame),
                // One step an epoch along the whole rollout's gradient.
                Truncate::None => {
                    rollout
                        .run(loss, Wants::Material(Truncate::None))
                        .and_then(|out| {
                            let values = out.material.clone().unwrap_or_default();
                            on_frame(
                                last,
                                FrameGradient {
                                    values: &values,
                                    moduli: out.moduli.as_ref(),
                                },
                            )?;
                            Ok(out)
                        })
                }
            }
        };
        let out = out.map_err(|e| match e {
            RolloutError::Interrupted => StageError::Interrupted,
            e => training(
                epoch,
                format!("{e}; try a smaller `field.lr` or a larger `field.tv_weight`"),
            ),
        })?;
        let mut loss_after = None;
        if p.field.truncate == Truncate::None {
            // Adam's direction, its length searched on the loss ([`StepSearch`]).
            let (step_w, step_u) = (field.field.to_flat(), u.clone());
            let mut at =
                |t: f64| -> Result<Option<(Vec<f64>, MaterialValues, Moduli)>, StageError> {
                    field
                        .field
                        .set_flat(&lerp(&before_w, &step_w, t))
                        .map_err(|e| training(epoch, e.to_string()))?;
                    let trial_u = lerp(&before_u, &step_u, t);
                    let trial_values = values_of(&trial_u);
                    Ok(field
                        .moduli(&trial_values)
                        .ok()
                        .map(|m| (trial_u, trial_values, m)))
                };
            // A trial above the loss so far is rejected whatever it is (`StepSearch::run`).
            let loss0 = out.loss();
            let found = search.run(loss0, |t| {
                let Some((_, trial_values, trial_moduli)) = at(t)? else {
                    return Ok(None);
                };
                match (Rollout {
                    material: &trial_values,
                    moduli: Some(&trial_moduli),
                    ..base
                })
                .run(loss, Wants::LossUpTo(loss0))
                {
                    Ok(o) => Ok(Some(o.loss())),
                    Err(RolloutError::Interrupted) => Err(StageError::Interrupted),
                    // A step that breaks the simulation is a step too long.
                    Err(_) => Ok(None),
                }
            })?;
            let t = found.map_or(0.0, |(t, _)| t);
            if let Some((trial_u, trial_values, trial_moduli)) = at(t)? {
                (u, cur_values, cur_moduli) = (trial_u, trial_values, trial_moduli);
            }
            loss_after = found.map(|(_, l)| l);
        }
        values = cur_values;
        moduli = cur_moduli;
        let log_e: Vec<f64> = moduli.e.iter().map(|e| e.log10()).collect();
        let [e5, e50, e95] = percentiles(&log_e);
        let [_, nu50, _] = percentiles(&moduli.nu);
        let mut metric = |name: &str, value: f64| {
            ctx.metric(MetricRow {
                epoch: Some(epoch),
                view: None,
                frame: None,
                metric: name.into(),
                value,
            })
        };
        metric("field_loss", out.loss());
        metric("field_log10_E_p05", e5);
        metric("field_log10_E_p50", e50);
        metric("field_log10_E_p95", e95);
        metric("field_nu_p50", nu50);
        metric("field_tv", field.field.tv());
        if p.field.truncate == Truncate::None {
            metric("field_step_scale", search.scale);
            if let Some(l) = loss_after {
                metric("field_loss_after_step", l);
            }
        }
        for q in &others {
            metric(q.name(), values.get(*q).unwrap_or(f64::NAN));
        }
        ctx.progress.message(&format!(
            "loss {:.5}  log10 E p5/p50/p95 {e5:.3}/{e50:.3}/{e95:.3}  nu p50 {nu50:.4}",
            out.loss()
        ));
        ctx.progress.inc(1);
        // With the searched step (the loss never rises), a fit that gains nothing stops.
        if p.field.truncate == Truncate::None {
            losses.push(loss_after.unwrap_or(out.loss()));
            if stalled(&losses) {
                ctx.progress.log(&crate::physics::step_search::stall_note(
                    "material field",
                    epoch + 1,
                    epochs,
                ));
                break;
            }
        }
    }
    Ok(FieldFit {
        field,
        moduli,
        values,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_field_needs_a_solid_and_e_or_nu_among_the_learned() {
        let both = [Param::E, Param::Nu];
        let err = outputs(
            MaterialFamily::Newtonian,
            &[Param::Viscosity],
            &both,
            "material",
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("model: field") && err.contains("newtonian"),
            "{err}"
        );
        let err = outputs(
            MaterialFamily::Plasticine,
            &[Param::YieldStress],
            &both,
            "m",
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("stages.m.model") && err.contains("names none"),
            "{err}"
        );
        assert_eq!(
            outputs(
                MaterialFamily::Plasticine,
                &[Param::E, Param::Nu, Param::YieldStress],
                &both,
                "m"
            )
            .unwrap(),
            vec![Param::E, Param::Nu]
        );
        // E varies, ν stays global (and is still learned).
        assert_eq!(
            outputs(MaterialFamily::Elastic, &both, &[Param::E], "m").unwrap(),
            vec![Param::E]
        );
        let err = outputs(MaterialFamily::Elastic, &both, &[Param::YieldStress], "m")
            .unwrap_err()
            .to_string();
        assert!(err.contains("field.vary: `yield_stress`"), "{err}");
    }
}
