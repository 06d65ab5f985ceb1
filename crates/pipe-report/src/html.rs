//! `report.html`: one self-contained page. Images are embedded as base64 `data:` URIs and plots
//! as inline SVG; a Content-Security-Policy forbids every other source, so opening the page
//! makes no request.

use std::fmt::Write as _;
use std::path::Path;

use base64::Engine as _;
use serde_json::Value;

use crate::ReportError;
use crate::model::{Drawn, Report, SceneReport};
use crate::plot::inline;
use crate::text::{self, html as esc};

/// The summary row of `evaluation.json`'s `relight_explained` (percent; empty when not re-lit).
pub const RELIGHT_LABEL: &str =
    "re-lit: share of the colours' log-luminance the normals explain (%)";

/// The summary row of `evaluation.json`'s `colour_refit`.
pub const COLOUR_LABEL: &str = "colours refitted along the motion (held-out training views' loss)";

/// The cell of [`COLOUR_LABEL`]: whether the refit was kept and how it changed the held-out
/// views' loss; empty when there was none.
pub fn colour_refit_cell(s: &SceneReport) -> String {
    let Some(r) = s.evaluation.as_ref().and_then(|e| e.get("colour_refit")) else {
        return String::new();
    };
    let kept = r.get("kept").and_then(Value::as_bool);
    let change = match (
        r.get("held_out_loss_before").and_then(Value::as_f64),
        r.get("held_out_loss_after").and_then(Value::as_f64),
    ) {
        (Some(b), Some(a)) if b > 0.0 => format!("{:+.1} %", 100.0 * (a / b - 1.0)),
        _ => "undecided".into(),
    };
    match kept {
        Some(true) => format!(
            "kept ({change}, {} passes)",
            r.get("epochs").and_then(Value::as_u64).unwrap_or(0)
        ),
        Some(false) => format!("not kept ({change})"),
        None => String::new(),
    }
}

/// Everything a page may load: images from `data:` URIs, its own inline style; nothing else.
pub const CSP: &str = "default-src 'none'; img-src data:; style-src 'unsafe-inline'";

const STYLE: &str = "
body { font-family: sans-serif; margin: 24px; color: #222; max-width: 1800px; }
h1 { font-size: 1.6em; } h2 { border-bottom: 2px solid #ccc; padding-bottom: 4px; }
h3 { margin-top: 1.6em; }
table { border-collapse: collapse; margin: 8px 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f2f2f2; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.params { font-size: 0.8em; color: #555; max-width: 420px; }
.scenes { display: grid; gap: 28px; }
.scene { min-width: 0; }
.figs { display: flex; flex-wrap: wrap; gap: 8px 24px; }
figure { margin: 8px 0 16px 0; } figcaption { font-size: 0.85em; color: #555; }
.figs figure { width: 620px; max-width: 100%; }
svg { width: 100%; height: auto; }
img.strip { width: 100%; max-width: 900px; image-rendering: pixelated; border: 1px solid #ddd; }
img.anim { width: 100%; max-width: 900px; image-rendering: pixelated; }
.note { font-size: 0.85em; color: #666; }
";

fn data_uri(path: &Path, mime: &str) -> Result<String, ReportError> {
    let bytes = std::fs::read(path).map_err(|source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bytes)
    ))
}

fn eval_number(s: &SceneReport, key: &str) -> Option<f64> {
    s.evaluation.as_ref()?.get(key)?.as_f64()
}

/// The rows of the side-by-side summary: label, one cell per scene.
fn summary_rows(report: &Report) -> Vec<(String, Vec<String>)> {
    let scenes = &report.scenes;
    let row = |label: &str, f: &dyn Fn(&SceneReport) -> String| {
        (label.to_string(), scenes.iter().map(f).collect::<Vec<_>>())
    };
    let mut rows = vec![
        row("preset", &|s| s.preset.clone()),
        row("material family", &|s| {
            text::value(s.scene.get("material").unwrap_or(&Value::Null))
        }),
        row("test views", &|s| {
            text::value(s.scene.get("test_views").unwrap_or(&Value::Null))
        }),
        row("test PSNR, mean over views and frames (dB)", &|s| {
            text::opt(eval_number(s, "test_psnr_mean"))
        }),
        row("test SSIM, mean", &|s| {
            text::opt(eval_number(s, "test_ssim_mean"))
        }),
        row("test PSNR, first frame (dB)", &|s| {
            text::opt(eval_number(s, "test_psnr_first_frame"))
        }),
        row("test PSNR, last frame (dB)", &|s| {
            text::opt(eval_number(s, "test_psnr_last_frame"))
        }),
        row("training-view PSNR, mean (dB)", &|s| {
            text::opt(eval_number(s, "train_psnr_mean"))
        }),
        row("test PSNR inside the mask (dB)", &|s| {
            text::opt(eval_number(s, "test_psnr_mask_mean"))
        }),
        row("test mask IoU", &|s| {
            text::opt(eval_number(s, "test_mask_iou_mean"))
        }),
        row("Chamfer distance, last frame (mm)", &|s| {
            text::opt(eval_number(s, "chamfer_last_frame_m").map(|m| m * 1e3))
        }),
        row("material points off, last frame (mm)", &|s| {
            text::opt(eval_number(s, "tracking_last_frame_m").map(|m| m * 1e3))
        }),
        row(RELIGHT_LABEL, &|s| {
            text::opt(eval_number(s, "relight_explained").map(|m| m * 1e2))
        }),
        row(COLOUR_LABEL, &colour_refit_cell),
    ];
    let mut names: Vec<String> = Vec::new();
    for s in scenes {
        for p in &s.parameters {
            if !names.contains(&p.name) {
                names.push(p.name.clone());
            }
        }
    }
    for name in names {
        rows.push(row(&format!("{name}: learned (true) · error"), &|s| {
            s.parameters
                .iter()
                .find(|p| p.name == name)
                .map(|p| {
                    format!(
                        "{} ({}) · {}",
                        text::value(&p.learned),
                        text::value(&p.truth),
                        text::opt(p.error)
                    )
                })
                .unwrap_or_else(|| "—".into())
        }));
    }
    rows.push(row("wall time of all stages (s)", &|s| {
        text::seconds(Some(s.total_wall_s))
    }));
    rows.push(row("peak memory of a stage (MiB)", &|s| {
        text::mib(Some(s.peak_rss_bytes))
    }));
    rows.push(row(WARNINGS_LABEL, &warnings_cell));
    rows
}

/// The summary's row of stage warnings.
pub(crate) const WARNINGS_LABEL: &str = "warnings from the stages";

/// How many warnings the stages gave and which stages (listed under the scene's *Warnings*).
pub(crate) fn warnings_cell(s: &SceneReport) -> String {
    let warnings = s.warnings();
    let mut stages: Vec<&str> = warnings.iter().map(|(stage, _)| *stage).collect();
    stages.dedup();
    if warnings.is_empty() {
        "none".into()
    } else {
        format!("{} ({}; see Warnings)", warnings.len(), stages.join(", "))
    }
}

fn table(out: &mut String, head: &[&str], rows: &[Vec<(String, bool)>]) {
    out.push_str("<table><thead><tr>");
    for h in head {
        let _ = write!(out, "<th>{}</th>", esc(h));
    }
    out.push_str("</tr></thead><tbody>\n");
    for r in rows {
        out.push_str("<tr>");
        for (cell, numeric) in r {
            let class = if *numeric { " class=\"num\"" } else { "" };
            let _ = write!(out, "<td{class}>{}</td>", esc(cell));
        }
        out.push_str("</tr>\n");
    }
    out.push_str("</tbody></table>\n");
}

fn scene_section(
    out: &mut String,
    s: &SceneReport,
    drawn: &[Drawn],
    root: &Path,
) -> Result<(), ReportError> {
    let _ = writeln!(out, "<div class=\"scene\"><h2>{}</h2>", esc(&s.name));
    out.push_str("<h3>Scene and settings</h3>\n");
    let rows: Vec<Vec<(String, bool)>> = s
        .settings_rows()
        .into_iter()
        .map(|(k, v)| vec![(k.to_string(), false), (v, false)])
        .collect();
    table(out, &["setting", "value"], &rows);
    out.push_str("<h3>Stages</h3>\n");
    out.push_str("<table><thead><tr><th>stage</th><th>state</th><th>wall time (s)</th><th>peak memory (MiB)</th><th>threads</th><th>key</th><th>parameters</th></tr></thead><tbody>\n");
    for st in &s.stages {
        let state = if st.reasons.is_empty() {
            st.state.clone()
        } else {
            format!("{}: {}", st.state, st.reasons.join("; "))
        };
        let _ = writeln!(
            out,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td><code>{}</code></td><td class=\"params\">{}</td></tr>",
            esc(&st.name),
            esc(&state),
            text::seconds(st.wall_s),
            text::mib(st.peak_rss_bytes),
            st.threads
                .map(|t| t.to_string())
                .unwrap_or_else(|| "—".into()),
            esc(&st.key[..12.min(st.key.len())]),
            esc(&text::compact(&st.params)),
        );
    }
    out.push_str("</tbody></table>\n<p class=\"note\">Wall time from each entry's manifest (summed over the runs of a resumed stage); peak memory is the process's resident-set peak while the stage ran.</p>\n");
    let warnings = s.warnings();
    if !warnings.is_empty() {
        out.push_str("<h3>Warnings</h3>\n<ul class=\"warnings\">\n");
        for (stage, w) in warnings {
            let _ = writeln!(out, "<li><b>{}</b>: {}</li>", esc(stage), esc(w));
        }
        out.push_str("</ul>\n");
    }

    out.push_str("<h3>Learned parameters against the ground truth</h3>\n");
    if s.parameters.is_empty() {
        out.push_str("<p class=\"note\">No learned parameters (the `velocity` and `material` stages have not run).</p>\n");
    } else {
        let rows: Vec<Vec<(String, bool)>> = s
            .parameters
            .iter()
            .map(|p| {
                vec![
                    (p.name.clone(), false),
                    (p.unit.clone(), false),
                    (text::value(&p.learned), true),
                    (text::value(&p.truth), true),
                    (text::opt(p.error), true),
                    (p.error_kind.clone(), false),
                    (text::or_dash(&p.bounded), false),
                ]
            })
            .collect();
        table(
            out,
            &[
                "parameter",
                "unit",
                "learned",
                "ground truth",
                "error",
                "error is",
                "bounded by the frames (material profile)",
            ],
            &rows,
        );
    }

    let section = |out: &mut String, title: &str, pred: &dyn Fn(&str) -> bool| {
        let figs: Vec<&Drawn> = drawn.iter().filter(|d| pred(&d.reference.id)).collect();
        if figs.is_empty() {
            return;
        }
        let _ = writeln!(out, "<h3>{}</h3>\n<div class=\"figs\">", esc(title));
        for d in figs {
            let _ = writeln!(
                out,
                "<figure id=\"{}\">{}<figcaption>{}</figcaption></figure>",
                esc(&d.reference.id),
                inline(&d.svg),
                esc(&d.reference.title)
            );
        }
        out.push_str("</div>\n");
    };
    section(out, "Loss curves", &|i| {
        i.contains("loss_") || i.contains("train_psnr_")
    });
    section(
        out,
        "Learned parameters over the epochs (dashed: ground truth)",
        &|i| i.contains("param_"),
    );
    section(out, "PSNR and SSIM per frame", &|i| {
        i.ends_with("_per_frame")
    });

    if !s.view_scores.is_empty() {
        out.push_str("<table><thead><tr><th>view</th><th>frame</th><th>PSNR (dB)</th><th>SSIM</th></tr></thead><tbody>\n");
        for v in &s.view_scores {
            for (i, (f, p)) in v.psnr.iter().enumerate() {
                let ssim = v.ssim.get(i).map(|x| x.1);
                let _ = writeln!(
                    out,
                    "<tr><td class=\"num\">{}</td><td class=\"num\">{f}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
                    v.view,
                    text::num(*p),
                    text::opt(ssim)
                );
            }
        }
        out.push_str("</tbody></table>\n");
    }

    if !s.strips.is_empty() {
        out.push_str("<h3>Test views: captured | ours | 4× error</h3>\n");
        for st in &s.strips {
            let _ = writeln!(
                out,
                "<figure><img class=\"strip\" alt=\"view {v}, frame {f}: captured, ours, error\" src=\"{}\"><figcaption>view {v}, frame {f} ({}): captured | ours | 4× |captured − ours|</figcaption></figure>",
                data_uri(&root.join(&st.file), "image/png")?,
                esc(&st.position),
                v = st.view,
                f = st.frame,
            );
        }
    }
    if !s.gifs.is_empty() {
        out.push_str("<h3>Every frame (animated: captured | ours | 4× error)</h3>\n");
        for g in &s.gifs {
            let _ = writeln!(
                out,
                "<figure><img class=\"anim\" alt=\"view {v}, all frames\" src=\"{}\"><figcaption>view {v}</figcaption></figure>",
                data_uri(&root.join(&g.file), "image/gif")?,
                v = g.view
            );
        }
    }
    out.push_str("</div>\n");
    Ok(())
}

/// The page of `report`; `root` is the report folder (strips and GIFs are read from it).
pub fn page(report: &Report, drawn: &[Vec<Drawn>], root: &Path) -> Result<String, ReportError> {
    let names: Vec<&str> = report.scenes.iter().map(|s| s.name.as_str()).collect();
    let mut out = String::new();
    let _ = write!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n<meta http-equiv=\"Content-Security-Policy\" content=\"{CSP}\">\n<title>pipe report: {}</title>\n<style>{STYLE}</style></head>\n<body>\n<h1>pipe report: {}</h1>\n",
        esc(&names.join(", ")),
        esc(&names.join(" · "))
    );
    out.push_str("<h2>Summary</h2>\n<table><thead><tr><th></th>");
    for n in &names {
        let _ = write!(out, "<th>{}</th>", esc(n));
    }
    out.push_str("</tr></thead><tbody>\n");
    for (label, cells) in summary_rows(report) {
        let _ = write!(out, "<tr><th>{}</th>", esc(&label));
        for c in cells {
            let _ = write!(out, "<td class=\"num\">{}</td>", esc(&c));
        }
        out.push_str("</tr>\n");
    }
    out.push_str("</tbody></table>\n<p class=\"note\">Test views are held out of training; every score compares the render composited over the camera's background plate with the capture (object inside its mask, plate outside), as `evaluate` scores it.</p>\n");

    let p = &report.published;
    let _ = writeln!(
        out,
        "<h2>Published reference figures ({})</h2>\n<p class=\"note\">{}</p>",
        esc(p.source),
        esc(p.note)
    );
    let rows: Vec<Vec<(String, bool)>> = p
        .rows
        .iter()
        .map(|r| {
            vec![
                (r.scene.to_string(), false),
                (format!("{:.2}", r.pac_nerf_db), true),
                (format!("{:.2}", r.seed_method_db), true),
            ]
        })
        .collect();
    table(
        &mut out,
        &[
            "PAC-NeRF scene",
            "PAC-NeRF, published PSNR (dB)",
            "seed method, published PSNR (dB)",
        ],
        &rows,
    );

    let _ = writeln!(
        out,
        "<div class=\"scenes\" style=\"grid-template-columns: repeat({}, minmax(0, 1fr));\">",
        report.scenes.len().max(1)
    );
    for (s, d) in report.scenes.iter().zip(drawn) {
        scene_section(&mut out, s, d, root)?;
    }
    let _ = writeln!(
        out,
        "</div>\n<p class=\"note\">Written by {}. Data: report.json; plots: plots/*.svg.</p>\n</body></html>",
        esc(&report.tool)
    );
    Ok(out)
}
