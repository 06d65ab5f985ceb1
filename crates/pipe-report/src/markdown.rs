//! `report.md`: the same content as the HTML page, with images and plots as files beside it
//! (`images/`, `plots/`).

use std::fmt::Write as _;

use crate::model::{Report, SceneReport};
use crate::text::{self, md};

fn eval_number(s: &SceneReport, key: &str) -> Option<f64> {
    s.evaluation.as_ref()?.get(key)?.as_f64()
}

fn row(out: &mut String, cells: &[String]) {
    let _ = writeln!(
        out,
        "| {} |",
        cells.iter().map(|c| md(c)).collect::<Vec<_>>().join(" | ")
    );
}

fn head(out: &mut String, cells: &[&str]) {
    row(
        out,
        &cells.iter().map(|c| c.to_string()).collect::<Vec<_>>(),
    );
    let _ = writeln!(out, "|{}", "---|".repeat(cells.len()));
}

fn scene(out: &mut String, s: &SceneReport) {
    let _ = writeln!(out, "\n## {}\n", s.name);
    head(out, &["setting", "value"]);
    for (k, v) in s.settings_rows() {
        row(out, &[k.to_string(), v]);
    }
    out.push_str("\n### Stages\n\n");
    head(
        out,
        &[
            "stage",
            "state",
            "wall time (s)",
            "peak memory (MiB)",
            "threads",
            "key",
            "parameters",
        ],
    );
    for st in &s.stages {
        let state = if st.reasons.is_empty() {
            st.state.clone()
        } else {
            format!("{}: {}", st.state, st.reasons.join("; "))
        };
        row(
            out,
            &[
                st.name.clone(),
                state,
                text::seconds(st.wall_s),
                text::mib(st.peak_rss_bytes),
                st.threads
                    .map(|t| t.to_string())
                    .unwrap_or_else(|| "—".into()),
                format!("`{}`", &st.key[..12.min(st.key.len())]),
                text::compact(&st.params),
            ],
        );
    }
    let warnings = s.warnings();
    if !warnings.is_empty() {
        out.push_str("\n### Warnings\n\n");
        for (stage, w) in warnings {
            let _ = writeln!(out, "- **{stage}**: {w}");
        }
    }
    if !s.parameters.is_empty() {
        out.push_str("\n### Learned parameters against the ground truth\n\n");
        head(
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
        );
        for p in &s.parameters {
            row(
                out,
                &[
                    p.name.clone(),
                    p.unit.clone(),
                    text::value(&p.learned),
                    text::value(&p.truth),
                    text::opt(p.error),
                    p.error_kind.clone(),
                    text::or_dash(&p.bounded),
                ],
            );
        }
    }
    if !s.figures.is_empty() {
        out.push_str("\n### Plots\n\n");
        for f in &s.figures {
            let _ = writeln!(out, "![{}]({})\n", f.title, f.file.display());
        }
    }
    if !s.view_scores.is_empty() {
        out.push_str("\n### PSNR and SSIM per frame\n\n");
        head(out, &["view", "frame", "PSNR (dB)", "SSIM"]);
        for v in &s.view_scores {
            for (i, (f, p)) in v.psnr.iter().enumerate() {
                row(
                    out,
                    &[
                        v.view.to_string(),
                        f.to_string(),
                        text::num(*p),
                        text::opt(v.ssim.get(i).map(|x| x.1)),
                    ],
                );
            }
        }
    }
    if !s.strips.is_empty() {
        out.push_str("\n### Test views: captured | ours | 4× error\n\n");
        for st in &s.strips {
            let _ = writeln!(
                out,
                "view {}, frame {} ({}):\n\n![view {} frame {}]({})\n",
                st.view,
                st.frame,
                st.position,
                st.view,
                st.frame,
                st.file.display()
            );
        }
    }
    for g in &s.gifs {
        let _ = writeln!(
            out,
            "Every frame of view {} (captured | ours | 4× error):\n\n![view {} animation]({})\n",
            g.view,
            g.view,
            g.file.display()
        );
    }
}

/// The Markdown text of `report`.
pub fn document(report: &Report) -> String {
    let names: Vec<&str> = report.scenes.iter().map(|s| s.name.as_str()).collect();
    let mut out = format!("# pipe report: {}\n\n## Summary\n\n", names.join(" · "));
    let mut cols = vec![""];
    cols.extend(names.iter().copied());
    head(&mut out, &cols);
    let line = |label: &str, f: &dyn Fn(&SceneReport) -> String| {
        let mut cells = vec![label.to_string()];
        cells.extend(report.scenes.iter().map(f));
        cells
    };
    for (label, key) in [
        ("test PSNR, mean (dB)", "test_psnr_mean"),
        ("test SSIM, mean", "test_ssim_mean"),
        ("test PSNR, first frame (dB)", "test_psnr_first_frame"),
        ("test PSNR, last frame (dB)", "test_psnr_last_frame"),
        ("training-view PSNR, mean (dB)", "train_psnr_mean"),
        ("test mask IoU", "test_mask_iou_mean"),
    ] {
        let cells = line(label, &|s| text::opt(eval_number(s, key)));
        row(&mut out, &cells);
    }
    let cells = line("Chamfer distance, last frame (mm)", &|s| {
        text::opt(eval_number(s, "chamfer_last_frame_m").map(|m| m * 1e3))
    });
    row(&mut out, &cells);
    let cells = line("material points off, last frame (mm)", &|s| {
        text::opt(eval_number(s, "tracking_last_frame_m").map(|m| m * 1e3))
    });
    row(&mut out, &cells);
    let cells = line(crate::html::RELIGHT_LABEL, &|s| {
        text::opt(eval_number(s, "relight_explained").map(|m| m * 1e2))
    });
    row(&mut out, &cells);
    let cells = line(crate::html::COLOUR_LABEL, &crate::html::colour_refit_cell);
    row(&mut out, &cells);
    let cells = line("wall time of all stages (s)", &|s| {
        text::seconds(Some(s.total_wall_s))
    });
    row(&mut out, &cells);
    let cells = line("peak memory of a stage (MiB)", &|s| {
        text::mib(Some(s.peak_rss_bytes))
    });
    row(&mut out, &cells);
    let cells = line(crate::html::WARNINGS_LABEL, &crate::html::warnings_cell);
    row(&mut out, &cells);

    let p = &report.published;
    let _ = writeln!(
        out,
        "\n## Published reference figures ({})\n\n{}\n",
        p.source, p.note
    );
    head(
        &mut out,
        &[
            "PAC-NeRF scene",
            "PAC-NeRF, published PSNR (dB)",
            "seed method, published PSNR (dB)",
        ],
    );
    for r in &p.rows {
        row(
            &mut out,
            &[
                r.scene.to_string(),
                format!("{:.2}", r.pac_nerf_db),
                format!("{:.2}", r.seed_method_db),
            ],
        );
    }
    for s in &report.scenes {
        scene(&mut out, s);
    }
    let _ = writeln!(
        out,
        "\n---\nWritten by {}; data in report.json.",
        report.tool
    );
    out
}
