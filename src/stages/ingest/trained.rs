//! A PhysDreamer scene's trained Gaussians (`point_cloud.ply`) written as `gaussians.arrow`,
//! `simulated` true exactly for the moving part: the object's Gaussians (near
//! `clean_object_points.ply`; all of them without it) that are near `moving_part_points.ply`
//! (every object Gaussian without it), with the tolerance of [`crate::scene::parts`]. The others
//! (the object's still part, the clutter around it) are rendered where they are.

use glam::DVec3;

use super::IngestError;
use crate::io::capture::DatasetFile;
use crate::io::physdreamer::PhysdreamerScene;
use crate::io::ply;
use crate::pipeline::stage::{MetricRow, StageContext, StageError};
use crate::scene::gaussians::Gaussians;
use crate::scene::parts::{self, Set};
use crate::scene::table;

/// The file `gaussians.arrow` is written to, relative to the entry.
pub const GAUSSIANS: &str = "gaussians.arrow";

fn points(f: &DatasetFile) -> Result<Vec<DVec3>, IngestError> {
    let pc = ply::read_points(&f.path)?;
    if pc.positions.is_empty() {
        return Err(IngestError::Invalid(format!(
            "{}: holds no points",
            f.path.display()
        )));
    }
    Ok(pc
        .positions
        .iter()
        .map(|p| DVec3::from_array(p.map(f64::from)))
        .collect())
}

/// Reads the trained Gaussians and the selections, marks the moving part and writes
/// `gaussians.arrow` into the entry, with counts in the log and `metrics.arrow`.
pub(super) fn write(t: &PhysdreamerScene, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
    let failed = |e: IngestError| StageError::failed(e);
    let mut g: Gaussians =
        ply::read_gaussians(&t.point_cloud.path).map_err(|e| failed(e.into()))?;
    if g.is_empty() {
        return Err(failed(IngestError::Invalid(format!(
            "{}: holds no Gaussians",
            t.point_cloud.path.display()
        ))));
    }
    let centres: Vec<DVec3> = g
        .position
        .iter()
        .map(|p| DVec3::from_array(p.map(f64::from)))
        .collect();
    let object = t
        .clean_object
        .as_ref()
        .map(points)
        .transpose()
        .map_err(failed)?;
    let moving = t
        .moving_part
        .as_ref()
        .map(points)
        .transpose()
        .map_err(failed)?;
    let parts = parts::select(&centres, object.as_deref(), moving.as_deref()).map_err(|e| {
        let file = match e.set() {
            Set::Object => t.clean_object.as_ref(),
            Set::Moving => t.moving_part.as_ref(),
        }
        .expect("the set with a problem was given");
        let against = match &e {
            parts::PartsError::MovingOutsideObject { .. } => t.clean_object.as_ref(),
            parts::PartsError::FarFromGaussians { .. } => Some(&t.point_cloud),
            parts::PartsError::NoSpacing { .. } => None,
        };
        failed(IngestError::Invalid(match against {
            Some(a) => format!(
                "{}: {e} (against {})",
                file.path.display(),
                a.path.display()
            ),
            None => format!("{}: {e}", file.path.display()),
        }))
    })?;
    let n_object = parts.object.iter().filter(|o| **o).count();
    let n_moving = parts.moving.iter().filter(|m| **m).count();
    if n_moving == 0 {
        return Err(failed(IngestError::Invalid(format!(
            "{}: no Gaussian of {} is in the moving part, so nothing would simulate",
            t.moving_part
                .as_ref()
                .map_or(&t.point_cloud.path, |m| &m.path)
                .display(),
            t.point_cloud.path.display()
        ))));
    }
    g.simulated = parts.moving.clone();
    table::write(&ctx.out_dir.join(GAUSSIANS), &g).map_err(StageError::failed)?;
    let describe = |f: &Option<DatasetFile>, s: &Option<parts::PointSet>, what: &str| match (f, s) {
        (Some(f), Some(s)) => format!(
            "{what} from {} ({})",
            f.logical_name,
            match s.subset {
                true => "its points are Gaussians' centres: exactly those".to_string(),
                false => format!(
                    "the Gaussians within {:.1} mm: {} × its spacing {:.1} mm",
                    s.tolerance * 1e3,
                    parts::TOLERANCE_SPACINGS,
                    s.spacing * 1e3
                ),
            }
        ),
        _ => format!("{what}: every Gaussian (no {what} points file)"),
    };
    ctx.progress.log(&format!(
        "{}: {} Gaussians, {n_object} of the object ({} clutter), {n_moving} in the moving part \
         (simulated), {} held in place; {}; {}",
        t.point_cloud.logical_name,
        g.len(),
        g.len() - n_object,
        g.len() - n_moving,
        describe(&t.clean_object, &parts.object_set, "object"),
        describe(&t.moving_part, &parts.moving_set, "moving part"),
    ));
    let mut metric = |name: &str, value: f64| {
        ctx.metric(MetricRow::of_stage(name, value));
    };
    metric("gaussians", g.len() as f64);
    metric("object_gaussians", n_object as f64);
    metric("moving_gaussians", n_moving as f64);
    if let Some(s) = &parts.object_set {
        metric("object_tolerance_m", s.tolerance);
    }
    if let Some(s) = &parts.moving_set {
        metric("moving_tolerance_m", s.tolerance);
    }
    Ok(())
}
