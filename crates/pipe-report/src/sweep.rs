//! `pipe sweep`'s outputs: `sweep.parquet` (one row per variant: its settings, wall time, peak
//! memory, scores and parameter errors), the Pareto plots of wall time against test PSNR and
//! against each parameter error, and `sweep.md`.

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use polars::prelude::*;
use serde_json::Value;

use crate::ReportError;
use crate::input::SweepSummary;
use crate::plot::{Figure, Series};
use crate::text::{self, md};

/// `evaluation.json` fields that become columns.
const SCORES: [&str; 9] = [
    "test_psnr_mean",
    "test_ssim_mean",
    "test_psnr_first_frame",
    "test_psnr_last_frame",
    "train_psnr_mean",
    "test_psnr_mask_mean",
    "test_mask_iou_mean",
    "chamfer_last_frame_m",
    "tracking_last_frame_m",
];

fn score(e: &Option<Value>, path: &[&str]) -> Option<f64> {
    let mut v = e.as_ref()?;
    for k in path {
        v = v.get(*k)?;
    }
    v.as_f64()
}

/// Indices of the variants on the Pareto front of `(cost, loss)`, both to minimise: sorted by
/// cost, each one strictly better in loss than every cheaper one. Variants without a finite
/// value are never on it.
pub fn pareto_front(points: &[(f64, Option<f64>)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_some_and(f64::is_finite))
        .collect();
    idx.sort_by(|&a, &b| {
        let (pa, pb) = (&points[a], &points[b]);
        pa.0.total_cmp(&pb.0).then(
            pa.1.unwrap_or(f64::NAN)
                .total_cmp(&pb.1.unwrap_or(f64::NAN)),
        )
    });
    let mut best = f64::INFINITY;
    let mut front = Vec::new();
    for i in idx {
        let loss = points[i].1.unwrap_or(f64::NAN);
        if loss < best {
            best = loss;
            front.push(i);
        }
    }
    front
}

/// The variants as a polars table.
pub fn table(sweep: &SweepSummary) -> Result<DataFrame, PolarsError> {
    let v = &sweep.variants;
    let mut cols: Vec<Column> = vec![
        Column::new(
            "variant".into(),
            v.iter().map(|r| r.variant.index as u32).collect::<Vec<_>>(),
        ),
        Column::new(
            "label".into(),
            v.iter().map(|r| r.label.clone()).collect::<Vec<_>>(),
        ),
    ];
    for a in &sweep.axes {
        cols.push(Column::new(
            format!("over.{}", a.key).into(),
            v.iter()
                .map(|r| r.variant.settings.get(&a.key).cloned())
                .collect::<Vec<_>>(),
        ));
    }
    cols.push(Column::new(
        "preset".into(),
        v.iter().map(|r| r.preset.clone()).collect::<Vec<_>>(),
    ));
    cols.push(Column::new(
        "wall_s".into(),
        v.iter().map(|r| r.wall_s).collect::<Vec<_>>(),
    ));
    cols.push(Column::new(
        "peak_rss_bytes".into(),
        v.iter().map(|r| r.peak_rss_bytes).collect::<Vec<_>>(),
    ));
    cols.push(Column::new(
        "stages_run".into(),
        v.iter().map(|r| r.ran.len() as u32).collect::<Vec<_>>(),
    ));
    let stages: BTreeSet<&String> = v.iter().flat_map(|r| r.stage_wall_s.keys()).collect();
    for s in &stages {
        cols.push(Column::new(
            format!("wall_s.{s}").into(),
            v.iter()
                .map(|r| r.stage_wall_s.get(*s).copied())
                .collect::<Vec<_>>(),
        ));
    }
    for k in SCORES {
        cols.push(Column::new(
            k.into(),
            v.iter()
                .map(|r| score(&r.evaluation, &[k]))
                .collect::<Vec<_>>(),
        ));
    }
    for group in ["errors", "learned"] {
        let names: BTreeSet<String> = v
            .iter()
            .filter_map(|r| r.evaluation.as_ref()?.get(group)?.as_object().cloned())
            .flat_map(|m| m.keys().cloned().collect::<Vec<_>>())
            .collect();
        for n in names {
            cols.push(Column::new(
                format!("{}.{n}", group.trim_end_matches('s')).into(),
                v.iter()
                    .map(|r| score(&r.evaluation, &[group, &n]))
                    .collect::<Vec<_>>(),
            ));
        }
    }
    let psnr: Vec<(f64, Option<f64>)> = v
        .iter()
        .map(|r| {
            (
                r.wall_s,
                score(&r.evaluation, &["test_psnr_mean"]).map(|p| -p),
            )
        })
        .collect();
    let front = pareto_front(&psnr);
    cols.push(Column::new(
        "pareto_psnr".into(),
        (0..v.len()).map(|i| front.contains(&i)).collect::<Vec<_>>(),
    ));
    DataFrame::new_infer_height(cols)
}

/// Error names (`E`, `nu`, `v0_m_s`, …) any variant has.
fn error_names(sweep: &SweepSummary) -> Vec<String> {
    let names: BTreeSet<String> = sweep
        .variants
        .iter()
        .filter_map(|r| r.evaluation.as_ref()?.get("errors")?.as_object().cloned())
        .flat_map(|m| m.keys().cloned().collect::<Vec<_>>())
        .collect();
    names.into_iter().collect()
}

/// Axis label of a parameter error, with what `evaluate` measures.
fn error_label(name: &str) -> String {
    match name {
        "E" | "yield_stress" | "viscosity" | "bulk_modulus" => {
            format!("error of {name}: |Δlog10| (decades)")
        }
        "v0_m_s" => "error of v0: |Δv0| (m/s)".into(),
        "angular_velocity_rad_s" => "error of ω: |Δω| (rad/s)".into(),
        "friction_angle" => "error of the friction angle: |Δ| (deg)".into(),
        other => format!("error of {other}: |Δ|"),
    }
}

/// The Pareto figures: wall time against test PSNR, and against each parameter error.
pub fn figures(sweep: &SweepSummary) -> Vec<(String, Figure)> {
    let v = &sweep.variants;
    let labels: Vec<String> = v.iter().map(|r| format!("#{}", r.variant.index)).collect();
    let spread = {
        let w: Vec<f64> = v.iter().map(|r| r.wall_s).filter(|w| *w > 0.0).collect();
        let lo = w.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = w.iter().copied().fold(0.0, f64::max);
        hi / lo
    };
    let figure =
        |id: String, title: String, y_label: String, ys: Vec<Option<f64>>, maximise: bool| {
            let pts: Vec<(f64, f64)> = v
                .iter()
                .zip(&ys)
                .map(|(r, y)| (r.wall_s, y.unwrap_or(f64::NAN)))
                .collect();
            let losses: Vec<(f64, Option<f64>)> = v
                .iter()
                .zip(&ys)
                .map(|(r, y)| (r.wall_s, y.map(|y| if maximise { -y } else { y })))
                .collect();
            let front: Vec<(f64, f64)> = pareto_front(&losses).iter().map(|&i| pts[i]).collect();
            (
                id,
                Figure {
                    title,
                    x_label: "wall time of all stages (s)".into(),
                    y_label,
                    series: vec![
                        Series::markers("variants", pts, labels.clone(), 0),
                        Series::line("Pareto front", front, 3),
                    ],
                    log_y: false,
                    log_x: spread > 20.0,
                },
            )
        };
    let mut out = vec![figure(
        "pareto_psnr".into(),
        format!("{}: wall time against test PSNR", sweep.name),
        "test PSNR, mean (dB)".into(),
        v.iter()
            .map(|r| score(&r.evaluation, &["test_psnr_mean"]))
            .collect(),
        true,
    )];
    for n in error_names(sweep) {
        out.push(figure(
            format!("pareto_error_{n}"),
            format!("{}: wall time against the error of {n}", sweep.name),
            error_label(&n),
            v.iter()
                .map(|r| score(&r.evaluation, &["errors", &n]))
                .collect(),
            false,
        ));
    }
    out
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ReportError + '_ {
    move |source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Write `sweep.parquet`, the Pareto plots (`pareto_*.svg`) and `sweep.md` into `out`.
pub fn write(sweep: &SweepSummary, out: &Path) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(out).map_err(io(out))?;
    let parquet = out.join("sweep.parquet");
    let mut df = table(sweep).map_err(|e| ReportError::Table {
        path: parquet.clone(),
        message: e.to_string(),
    })?;
    let file = std::fs::File::create(&parquet).map_err(io(&parquet))?;
    ParquetWriter::new(file)
        .finish(&mut df)
        .map_err(|e| ReportError::Table {
            path: parquet.clone(),
            message: e.to_string(),
        })?;
    let mut written = vec![parquet];
    let mut plots = Vec::new();
    for (id, fig) in figures(sweep) {
        if let Some(svg) = fig.svg()? {
            let p = out.join(format!("{id}.svg"));
            std::fs::write(&p, svg).map_err(io(&p))?;
            plots.push((fig.title.clone(), format!("{id}.svg")));
            written.push(p);
        }
    }
    let md_path = out.join("sweep.md");
    std::fs::write(&md_path, markdown(sweep, &plots)).map_err(io(&md_path))?;
    written.push(md_path);
    Ok(written)
}

/// `sweep.md`: the table and the plots.
fn markdown(sweep: &SweepSummary, plots: &[(String, String)]) -> String {
    let mut s = format!(
        "# Sweep of {} ({})\n\nAxes: {}.\nWall time: the sum of the variant's stages as recorded when each ran (a stage shared with another variant counts in both); `*` marks the Pareto front of wall time against test PSNR.\n\n",
        sweep.name,
        sweep.file.display(),
        sweep
            .axes
            .iter()
            .map(|a| format!("`{}` = {}", a.key, a.values.join(", ")))
            .collect::<Vec<_>>()
            .join("; ")
    );
    let errors = error_names(sweep);
    let mut head = vec![
        "#".to_string(),
        "variant".into(),
        "wall time (s)".into(),
        "peak memory (MiB)".into(),
        "test PSNR (dB)".into(),
        "test SSIM".into(),
        "last-frame PSNR (dB)".into(),
    ];
    head.extend(errors.iter().map(|e| format!("error {e}")));
    head.push("stages run".into());
    let _ = writeln!(s, "| {} |", head.join(" | "));
    let _ = writeln!(s, "|{}", "---|".repeat(head.len()));
    let psnr: Vec<(f64, Option<f64>)> = sweep
        .variants
        .iter()
        .map(|r| {
            (
                r.wall_s,
                score(&r.evaluation, &["test_psnr_mean"]).map(|p| -p),
            )
        })
        .collect();
    let front = pareto_front(&psnr);
    for (i, r) in sweep.variants.iter().enumerate() {
        let mut cells = vec![
            format!(
                "{}{}",
                r.variant.index,
                if front.contains(&i) { "*" } else { "" }
            ),
            md(&r.label),
            format!("{:.2}", r.wall_s),
            text::mib(Some(r.peak_rss_bytes)),
            text::opt(score(&r.evaluation, &["test_psnr_mean"])),
            text::opt(score(&r.evaluation, &["test_ssim_mean"])),
            text::opt(score(&r.evaluation, &["test_psnr_last_frame"])),
        ];
        cells.extend(
            errors
                .iter()
                .map(|e| text::opt(score(&r.evaluation, &["errors", e]))),
        );
        cells.push(if r.ran.is_empty() {
            "— (cached)".into()
        } else {
            r.ran.join(", ")
        });
        let _ = writeln!(s, "| {} |", cells.join(" | "));
    }
    s.push('\n');
    for (title, file) in plots {
        let _ = writeln!(s, "![{title}]({file})\n");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_front_keeps_each_variant_better_than_every_cheaper_one() {
        let pts = [
            (10.0, Some(-30.0)),
            (5.0, Some(-28.0)),
            (20.0, Some(-29.0)), // slower and worse than #0
            (40.0, Some(-33.0)),
            (1.0, None),           // not scored
            (2.0, Some(f64::NAN)), // diverged
        ];
        assert_eq!(pareto_front(&pts), vec![1, 0, 3]);
    }
}
