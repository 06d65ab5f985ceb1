//! `pipe sweep`, `pipe report` and the report after `pipe run`, end to end on the embedded demo
//! scene (`tests/fixtures/torus-elastic-small`, 5 frames, epochs cut to 1–5 so the whole file
//! takes seconds), through the `pipe` command line with this crate as its writer, as the
//! `pipe` binary wires it.
//!
//! One work directory serves every test (built once): a sweep over two `material.lr` values
//! (as if a three-value sweep had been interrupted after two variants), the full three-value
//! sweep, a `pipe run` of the first variant that re-runs `evaluate` (and so writes its report),
//! and a side-by-side report of two pipeline files.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use polars::prelude::*;
use serde_json::Value;

/// The `pipe` binary's writer (src/main.rs), here for the library's command line.
struct Documents;

impl pipe::cli::Publisher for Documents {
    fn report(
        &self,
        runs: &[pipe::report::RunSummary],
        out: &Path,
    ) -> Result<Vec<PathBuf>, String> {
        let value = serde_json::to_value(runs).map_err(|e| e.to_string())?;
        pipe_report::write_report_value(value, out).map_err(|e| e.to_string())
    }

    fn sweep(&self, sweep: &pipe::sweep::SweepSummary, out: &Path) -> Result<Vec<PathBuf>, String> {
        let value = serde_json::to_value(sweep).map_err(|e| e.to_string())?;
        pipe_report::write_sweep_value(value, out).map_err(|e| e.to_string())
    }
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A pipeline file of the demo scene with the epochs cut.
fn pipeline(dir: &Path, name: &str, lr: f64) -> PathBuf {
    let scene = repo()
        .join("tests/fixtures/torus-elastic-small")
        .canonicalize()
        .unwrap();
    let file = dir.join(format!("{name}.yaml"));
    std::fs::write(
        &file,
        format!(
            "name: {name}\nscene:\n  dataset: pacnerf\n  path: {}\n  test_views: [10]\n  material: elastic\npreset: draft\nstages:\n  ingest: {{frames: [0, 1, 2, 3, 4]}}\n  init: {{}}\n  warmup: {{epochs: 5}}\n  velocity: {{epochs: 2, frames: 3, cells: 10}}\n  material: {{model: global, epochs: 1, cells: 10, lr: {lr}}}\n  evaluate: {{}}\n",
            scene.display()
        ),
    )
    .unwrap();
    file
}

fn pipe(workdir: &Path, args: &[&str]) {
    let mut all = vec!["pipe", "--quiet", "--workdir", workdir.to_str().unwrap()];
    all.extend(args);
    let code = pipe::cli::run_with(all.clone(), pipe::stages::builtin(), Some(&Documents));
    assert_eq!(code, 0, "pipe {}", all.join(" "));
}

struct Demo {
    dir: tempfile::TempDir,
}

impl Demo {
    fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }

    fn cache(&self) -> PathBuf {
        self.path(".pipe/cache")
    }

    /// Entries of a stage kind.
    fn entries(&self, stage: &str) -> Vec<PathBuf> {
        let mut out: Vec<PathBuf> = std::fs::read_dir(self.cache())
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .filter(|p| {
                p.file_name()
                    .unwrap()
                    .to_string_lossy()
                    .starts_with(&format!("{stage}-"))
            })
            .collect();
        out.sort();
        out
    }

    fn json(&self, rel: &str) -> Value {
        read_json(&self.path(rel))
    }
}

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

const LRS: [&str; 3] = ["0.05", "0.1", "0.2"];

fn demo() -> &'static Demo {
    static DEMO: OnceLock<Demo> = OnceLock::new();
    DEMO.get_or_init(|| {
        let demo = Demo {
            dir: tempfile::tempdir().unwrap(),
        };
        let w = demo.dir.path();
        let a = pipeline(w, "demo-a", 0.05);
        let b = pipeline(w, "demo-b", 0.1);
        let (a, b) = (a.to_str().unwrap(), b.to_str().unwrap());
        let out = |rel: &str| w.join(rel).to_str().unwrap().to_string();
        let over2 = format!("material.lr={},{}", LRS[0], LRS[1]);
        let over3 = format!("material.lr={}", LRS.join(","));
        pipe(w, &["sweep", a, "--over", &over2, "--out", &out("sweep2")]);
        pipe(w, &["sweep", a, "--over", &over3, "--out", &out("sweep3")]);
        pipe(
            w,
            &[
                "run",
                a,
                "--force",
                "evaluate",
                "--report-out",
                &out("auto"),
            ],
        );
        pipe(w, &["report", a, b, "--out", &out("side")]);
        demo
    })
}

fn manifest(entry: &Path) -> Value {
    read_json(&entry.join("manifest.json"))
}

#[test]
fn the_sweep_runs_warmup_once_and_shares_it() {
    let d = demo();
    // From the cache manifests: one warm-up (and one velocity: `material.lr` is downstream of
    // it) served all three variants, whose `material` and `evaluate` entries all name it.
    let warmups = d.entries("warmup");
    assert_eq!(warmups.len(), 1, "{warmups:?}");
    let warmup_key = manifest(&warmups[0])["key"].as_str().unwrap().to_string();
    assert_eq!(d.entries("velocity").len(), 1);
    let materials = d.entries("material");
    let evaluates = d.entries("evaluate");
    assert_eq!((materials.len(), evaluates.len()), (3, 3));
    for e in &evaluates {
        assert_eq!(
            manifest(e)["key_material"]["upstream"]["warmup"],
            Value::String(warmup_key.clone()),
            "{}",
            e.display()
        );
    }
    let lrs: Vec<String> = materials
        .iter()
        .map(|m| manifest(m)["key_material"]["params"]["lr"].to_string())
        .collect();
    for lr in LRS {
        assert!(lrs.contains(&lr.to_string()), "{lrs:?}");
    }
}

fn read_parquet(path: &Path) -> DataFrame {
    ParquetReader::new(std::fs::File::open(path).unwrap())
        .finish()
        .unwrap()
}

fn strings(df: &DataFrame, col: &str) -> Vec<String> {
    df.column(col)
        .unwrap()
        .str()
        .unwrap()
        .iter()
        .map(|v| v.unwrap().to_string())
        .collect()
}

fn numbers(df: &DataFrame, col: &str) -> Vec<f64> {
    let c = df.column(col).unwrap().cast(&DataType::Float64).unwrap();
    c.f64()
        .unwrap()
        .iter()
        .map(|v| v.unwrap_or(f64::NAN))
        .collect()
}

#[test]
fn the_sweep_parquet_reads_back_with_one_row_per_variant() {
    let d = demo();
    let df = read_parquet(&d.path("sweep3/sweep.parquet"));
    assert_eq!(df.height(), 3);
    assert_eq!(strings(&df, "over.material.lr"), LRS);
    assert_eq!(numbers(&df, "variant"), [0.0, 1.0, 2.0]);
    for col in [
        "wall_s",
        "test_psnr_mean",
        "test_ssim_mean",
        "error.E",
        "error.v0_m_s",
    ] {
        let v = numbers(&df, col);
        assert!(v.iter().all(|x| x.is_finite() && *x >= 0.0), "{col}: {v:?}");
    }
    // Each row's scores are its variant's evaluation.json.
    let evaluates = d.entries("evaluate");
    let psnr = numbers(&df, "test_psnr_mean");
    for (i, lr) in LRS.iter().enumerate() {
        let e = evaluates
            .iter()
            .find(|e| {
                let m = manifest(e);
                let material = m["key_material"]["upstream"]["material"]
                    .as_str()
                    .unwrap()
                    .to_string();
                let mm = manifest(&d.cache().join(format!("material-{material}")));
                mm["key_material"]["params"]["lr"] == lr.parse::<f64>().unwrap()
            })
            .unwrap();
        let ev = read_json(&e.join("evaluation.json"));
        assert_eq!(
            psnr[i],
            ev["test_psnr_mean"].as_f64().unwrap(),
            "variant {i}"
        );
    }
    // Wall time is the sum of the variant's stages, peak memory their largest.
    let wall = numbers(&df, "wall_s");
    let stage_sum: f64 = [
        "ingest", "init", "warmup", "velocity", "material", "evaluate",
    ]
    .iter()
    .map(|s| numbers(&df, &format!("wall_s.{s}"))[0])
    .sum();
    assert!(
        (wall[0] - stage_sum).abs() < 1e-9,
        "{} vs {stage_sum}",
        wall[0]
    );
    assert!(numbers(&df, "peak_rss_bytes").iter().all(|b| *b > 0.0));
    // The Pareto plots exist and are SVG.
    for f in ["pareto_psnr.svg", "pareto_error_E.svg", "sweep.md"] {
        let text = std::fs::read_to_string(d.path(&format!("sweep3/{f}"))).unwrap();
        assert!(!text.is_empty(), "{f}");
    }
}

#[test]
fn an_interrupted_sweep_continues_with_the_variants_it_has_not_finished() {
    let d = demo();
    // The two-value sweep ran everything for its first variant and `material`, `evaluate`
    // for the second; the three-value sweep found both cached and ran only the third.
    let first = read_parquet(&d.path("sweep2/sweep.parquet"));
    assert_eq!(numbers(&first, "stages_run"), [6.0, 2.0]);
    let full = read_parquet(&d.path("sweep3/sweep.parquet"));
    assert_eq!(numbers(&full, "stages_run"), [0.0, 0.0, 2.0]);
    // The cached variants' rows equal the rows the first sweep wrote.
    for col in ["test_psnr_mean", "wall_s", "error.E"] {
        assert_eq!(numbers(&first, col)[..], numbers(&full, col)[..2], "{col}");
    }
}

#[test]
fn report_json_agrees_with_evaluation_json() {
    let d = demo();
    let report = d.json("auto/report.json");
    let scene = &report["scenes"][0];
    assert_eq!(scene["name"], "demo-a");
    let stages = scene["stages"].as_array().unwrap();
    let evaluate = stages.iter().find(|s| s["kind"] == "evaluate").unwrap();
    let entry = d
        .cache()
        .join(format!("evaluate-{}", evaluate["key"].as_str().unwrap()));
    let evaluation = read_json(&entry.join("evaluation.json"));
    assert_eq!(scene["evaluation"], evaluation);
    // The per-frame means aggregated from metrics.arrow (polars) equal evaluate's own.
    let ours: Vec<f64> = scene["test_psnr_per_frame"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p[1].as_f64().unwrap())
        .collect();
    let theirs: Vec<f64> = evaluation["test_psnr_per_frame"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(ours.len(), 5);
    assert_eq!(ours.len(), theirs.len());
    for (a, b) in ours.iter().zip(&theirs) {
        assert!((a - b).abs() <= 1e-12 * b.abs(), "{ours:?} vs {theirs:?}");
    }
    // The parameter table's errors are evaluate's.
    for p in scene["parameters"].as_array().unwrap() {
        let key = if p["name"] == "v0" {
            "v0_m_s".to_string()
        } else {
            p["name"].as_str().unwrap().to_string()
        };
        assert_eq!(p["error"], evaluation["errors"][&key], "{p}");
    }
    // Every stage's wall time is its manifest's.
    for s in stages {
        let m = manifest(&d.cache().join(format!(
            "{}-{}",
            s["name"].as_str().unwrap(),
            s["key"].as_str().unwrap()
        )));
        assert_eq!(s["wall_s"], m["wall_s"], "{}", s["name"]);
        assert_eq!(s["state"], "done");
    }
    // Learned parameters' paths and loss curves are there, with the truth where known.
    let paths = scene["parameter_paths"].as_array().unwrap();
    let e = paths.iter().find(|p| p["parameter"] == "E").unwrap();
    assert_eq!(e["truth"], evaluation["ground_truth"]["E"]);
    assert_eq!(e["points"].as_array().unwrap().len(), 1);
    let vx = paths.iter().find(|p| p["parameter"] == "vx").unwrap();
    assert_eq!(vx["truth"], evaluation["ground_truth_v0"][0]);
    let curves = scene["curves"].as_array().unwrap();
    let warmup_loss = curves
        .iter()
        .find(|c| c["stage"] == "warmup" && c["metric"] == "loss")
        .unwrap();
    assert_eq!(warmup_loss["points"].as_array().unwrap().len(), 5);
    // First, middle and last frame of the test view.
    let strips: Vec<(u64, u64)> = scene["strips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["view"].as_u64().unwrap(), s["frame"].as_u64().unwrap()))
        .collect();
    assert_eq!(strips, [(10, 0), (10, 2), (10, 4)]);
}

/// `(attribute, value)` of every `src`, `href`, `srcset`, `poster`, `action`, `data` and
/// `xlink:href` attribute in `html`.
fn url_attributes(html: &str) -> Vec<(String, String)> {
    let re = regex::Regex::new(
        r#"(?i)\s(src|href|srcset|poster|action|data|xlink:href|formaction)\s*=\s*("([^"]*)"|'([^']*)'|([^\s>]+))"#,
    )
    .unwrap();
    re.captures_iter(html)
        .map(|c| {
            let v = c
                .get(3)
                .or(c.get(4))
                .or(c.get(5))
                .map(|m| m.as_str())
                .unwrap_or("");
            (c[1].to_lowercase(), v.to_string())
        })
        .collect()
}

#[test]
fn report_html_embeds_every_image_and_plot_and_names_no_url() {
    let d = demo();
    let links = regex::Regex::new(r"!\[[^\]]*\]\(([^)]+)\)").unwrap();
    for dir in ["auto", "side"] {
        let html = std::fs::read_to_string(d.path(&format!("{dir}/report.html"))).unwrap();
        let report = d.json(&format!("{dir}/report.json"));
        let scenes = report["scenes"].as_array().unwrap();
        let count = |key: &str| -> usize {
            scenes
                .iter()
                .map(|s| s[key].as_array().unwrap().len())
                .sum()
        };
        let (strips, gifs, figures) = (count("strips"), count("gifs"), count("figures"));
        assert!(
            strips >= 3 && gifs >= 1 && figures >= 6,
            "{dir}: {strips} {gifs} {figures}"
        );
        // Every URL-bearing attribute is an embedded image; nothing else exists.
        let attrs = url_attributes(&html);
        assert_eq!(attrs.len(), strips + gifs, "{dir}: {attrs:?}");
        for (name, value) in &attrs {
            assert_eq!(name, "src");
            assert!(
                value.starts_with("data:image/png;base64,")
                    || value.starts_with("data:image/gif;base64,"),
                "{dir}: {}",
                &value[..value.len().min(60)]
            );
        }
        assert_eq!(html.matches("<img ").count(), strips + gifs);
        assert_eq!(html.matches("<svg ").count(), figures, "{dir}");
        let lower = html.to_lowercase();
        for banned in [
            "http:", "https:", "//www", "url(", "@import", "<script", "<link", "<iframe",
            "<object", "<embed",
        ] {
            assert!(!lower.contains(banned), "{dir}: `{banned}` in report.html");
        }
        assert!(html.contains("Content-Security-Policy"));
        // The published reference figures, labelled as such.
        for v in [
            "32.93", "35.87", "32.86", "32.60", "21.84", "24.88", "19.90", "28.91",
        ] {
            assert!(html.contains(v), "{v}");
        }
        assert!(html.contains("Published numbers on other data"));
        // report.md links files that exist beside it.
        let md = std::fs::read_to_string(d.path(&format!("{dir}/report.md"))).unwrap();
        // Both pages hold the same settings rows; the demo sets no `prefer_substeps`.
        for page in [&html, &md] {
            assert!(
                page.contains("MPM substeps") && page.contains("automatic (the stability limit)"),
                "{dir}"
            );
        }
        let files: Vec<String> = links.captures_iter(&md).map(|c| c[1].to_string()).collect();
        assert_eq!(files.len(), strips + gifs + figures, "{dir}");
        for f in files {
            assert!(d.path(&format!("{dir}/{f}")).is_file(), "{dir}/{f}");
        }
    }
}

#[test]
fn several_files_are_reported_side_by_side() {
    let d = demo();
    let report = d.json("side/report.json");
    let names: Vec<&str> = report["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["demo-a", "demo-b"]);
    // demo-b is the sweep's second variant: all of it came from the cache.
    let b = &report["scenes"][1];
    assert_eq!(b["parameters"][0]["name"], "E");
    assert!(
        b["stages"]
            .as_array()
            .unwrap()
            .iter()
            .all(|s| s["state"] == "done")
    );
    let html = std::fs::read_to_string(d.path("side/report.html")).unwrap();
    assert!(html.contains("grid-template-columns: repeat(2, minmax(0, 1fr))"));
    assert!(html.contains("<th>demo-a</th><th>demo-b</th>"));
}

/// `data-<name>="<value>"` on the dumped `<body>`.
fn body_attribute(dom: &str, name: &str) -> Option<usize> {
    let key = format!("data-{name}=\"");
    let start = dom.find("<body")?;
    let body = &dom[start..start + dom[start..].find('>')?];
    let at = body.find(&key)? + key.len();
    body[at..].split('"').next()?.parse().ok()
}

/// Loads `html` in headless Chromium with a probe: how many images decoded, how many `<svg>`
/// elements exist, how many loads the page's policy refused.
fn probe(chromium: &Path, html: &str, dir: &Path, name: &str) -> (usize, usize, usize, usize) {
    let probe = r#"<script>
var refused = 0;
document.addEventListener('securitypolicyviolation', function () { refused++; });
window.addEventListener('load', function () {
  var images = Array.from(document.images);
  document.body.setAttribute('data-images', images.length);
  document.body.setAttribute('data-decoded', images.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length);
  document.body.setAttribute('data-svgs', document.querySelectorAll('svg').length);
  document.body.setAttribute('data-refused', refused);
});
</script>"#;
    // The page's own policy, plus the probe's inline script.
    let page = html
        .replacen(
            pipe_report::html::CSP,
            &format!("{}; script-src 'unsafe-inline'", pipe_report::html::CSP),
            1,
        )
        .replacen("<title>", &format!("{probe}<title>"), 1);
    let file = dir.join(name);
    std::fs::write(&file, page).unwrap();
    let out = std::process::Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--virtual-time-budget=5000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", dir.join("profile").display()))
        .arg(format!("file://{}", file.display()))
        .output()
        .unwrap();
    let dom = String::from_utf8_lossy(&out.stdout);
    let get = |k: &str| {
        body_attribute(&dom, k).unwrap_or_else(|| {
            panic!(
                "no data-{k} on <body>: chromium said {}",
                String::from_utf8_lossy(&out.stderr)
            )
        })
    };
    (get("images"), get("decoded"), get("svgs"), get("refused"))
}

fn chromium() -> Option<PathBuf> {
    for name in ["chromium", "chromium-browser"] {
        let found = std::process::Command::new("sh")
            .args(["-c", &format!("command -v {name}")])
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| PathBuf::from(String::from_utf8_lossy(&o.stdout).trim()));
        if found.is_some() {
            return found;
        }
    }
    None
}

#[test]
fn the_report_opens_in_headless_chromium_with_everything_and_no_request() {
    let Some(chromium) = chromium() else {
        // CI installs Debian's `chromium` (.ci/run); there the check must run.
        assert!(
            std::env::var_os("CI").is_none(),
            "chromium is not installed on CI (.ci/run installs it)"
        );
        println!("notice: chromium not found; skipping the headless-browser check of report.html");
        return;
    };
    let d = demo();
    let html = std::fs::read_to_string(d.path("auto/report.html")).unwrap();
    let report = d.json("auto/report.json");
    let s = &report["scenes"][0];
    let images = s["strips"].as_array().unwrap().len() + s["gifs"].as_array().unwrap().len();
    let figures = s["figures"].as_array().unwrap().len();
    let tmp = tempfile::tempdir().unwrap();
    let (n, decoded, svgs, refused) = probe(&chromium, &html, tmp.path(), "probe.html");
    assert_eq!((n, decoded, svgs, refused), (images, images, figures, 0));
    // The probe sees a request when there is one: the policy refuses it.
    let leaky = html.replacen(
        "</body>",
        "<img src=\"http://example.invalid/x.png\"></body>",
        1,
    );
    let (n, decoded, _, refused) = probe(&chromium, &leaky, tmp.path(), "leaky.html");
    assert_eq!((n, decoded), (images + 1, images));
    assert!(refused >= 1, "the probe missed a refused request");
    // A screenshot of the page as it is.
    let shot = tmp.path().join("report.png");
    let status = std::process::Command::new(&chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--window-size=1200,2400",
        ])
        .arg(format!(
            "--user-data-dir={}",
            tmp.path().join("profile").display()
        ))
        .arg(format!("--screenshot={}", shot.display()))
        .arg(format!("file://{}", d.path("auto/report.html").display()))
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");
    let img = image::open(&shot).unwrap().into_rgb8();
    assert_eq!(img.dimensions(), (1200, 2400));
    let distinct: std::collections::BTreeSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(
        distinct.len() > 50,
        "a near-blank screenshot ({} colours)",
        distinct.len()
    );
    if let Some(keep) = std::env::var_os("PIPE_REPORT_SCREENSHOT") {
        std::fs::copy(&shot, keep).unwrap();
    }
}

/// A report asked with settings the cached stages were not run with names the stages it has
/// no result from (a user who ran with `--set` and reports without it).
#[test]
fn a_report_under_other_settings_names_the_stages_it_lacks() {
    let d = demo();
    let file = pipeline(d.dir.path(), "demo-other-lr", 0.77);
    let reg = pipe::stages::builtin();
    let p = pipe::pipeline::spec::load(&file, &reg, &Default::default()).unwrap();
    let ws = pipe::pipeline::runner::Workspace::new(d.dir.path());
    let images = tempfile::tempdir().unwrap();
    let run = pipe::report::collect(&ws, &p, &reg, images.path(), "").unwrap();
    let missing = run.missing();
    assert_eq!(missing.len(), 2, "{missing:?}");
    assert!(missing[0].contains("stage `material`") && missing[0].contains("--set"));
    assert!(missing[1].contains("stage `evaluate`"));
    assert!(missing.iter().all(|m| m.contains("demo-other-lr.yaml")));
}

#[test]
fn a_report_of_a_pipeline_that_never_ran_says_to_run_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline(dir.path(), "never-ran", 0.1);
    let reg = pipe::stages::builtin();
    let p = pipe::pipeline::spec::load(&file, &reg, &Default::default()).unwrap();
    let ws = pipe::pipeline::runner::Workspace::new(dir.path());
    let e = pipe::report::collect(&ws, &p, &reg, &dir.path().join("images"), "")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("never-ran.yaml") && e.contains("pipe run"),
        "{e}"
    );
    let code = pipe::cli::run_with(
        [
            "pipe",
            "--quiet",
            "--workdir",
            dir.path().to_str().unwrap(),
            "report",
            file.to_str().unwrap(),
            "--out",
            dir.path().join("r").to_str().unwrap(),
        ],
        pipe::stages::builtin(),
        Some(&Documents),
    );
    assert_eq!(code, 1);
    assert!(!dir.path().join("r/report.html").exists());
}

#[test]
fn a_bad_variant_stops_the_sweep_before_anything_runs() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline(dir.path(), "bad-variant", 0.1);
    let run = |over: &str| {
        pipe::cli::run_with(
            [
                "pipe",
                "--quiet",
                "--workdir",
                dir.path().to_str().unwrap(),
                "sweep",
                file.to_str().unwrap(),
                "--over",
                over,
            ],
            pipe::stages::builtin(),
            Some(&Documents),
        )
    };
    // The second variant's `material.epochs: 0` is refused while planning.
    assert_eq!(run("material.epochs=1,0"), 2);
    // A malformed axis is a usage error.
    assert_eq!(run("material.epochs"), 2);
    assert!(!dir.path().join(".pipe/cache").exists());
}

/// One frame's PSNR and SSIM in `evaluate`'s `metrics.arrow` equal a direct computation with
/// `pipe-loss` on the saved render and the target built from `ingest`'s capture, mask and plate
/// (capture inside the mask, plate outside). The saved PNG is 8-bit, so the recomputation sees
/// the render rounded to 1/255: at ~30 dB that moves PSNR by ~0.01 dB, SSIM by ~1e-4.
#[test]
fn one_frames_scores_equal_pipe_loss_on_the_saved_render_and_target() {
    use pipe::scene::{frames::Frames, metrics::Metrics, table, targets};
    let d = demo();
    let report = d.json("auto/report.json");
    let stages = report["scenes"][0]["stages"].as_array().unwrap().clone();
    let entry = |kind: &str| {
        let s = stages.iter().find(|s| s["kind"] == kind).unwrap();
        d.cache()
            .join(format!("{kind}-{}", s["key"].as_str().unwrap()))
    };
    let (ingest, evaluate) = (entry("ingest"), entry("evaluate"));
    let frames: Frames = table::read(&ingest.join("frames.arrow")).unwrap();
    let metrics: Metrics = table::read(&evaluate.join("metrics.arrow")).unwrap();
    let (view, frame) = (10u16, 2u16);
    let row = frames
        .rows
        .iter()
        .find(|r| r.view == view && r.frame == frame)
        .unwrap();
    let target = &targets::load(&ingest, &[row]).unwrap()[0];
    let plate = target.plate.as_ref().expect("the demo scene has plates");
    let truth = target.over(plate);
    let saved = pipe::io::image::read_rgb8(&evaluate.join(format!("renders/v{view}_f{frame}.png")))
        .unwrap();
    let (w, h) = target.size();
    assert_eq!((saved.width as usize, saved.height as usize), (w, h));
    let ours: Vec<f32> = saved.data.iter().map(|v| f32::from(*v) / 255.0).collect();
    let a = pipe_loss::Image::new("render", &ours, w, h).unwrap();
    let b = pipe_loss::Image::new("target", &truth, w, h).unwrap();
    let (psnr, ssim) = (
        pipe_loss::psnr(a, b).unwrap(),
        pipe_loss::ssim(a, b).unwrap(),
    );
    let recorded = |metric: &str| {
        let found: Vec<f64> = metrics
            .rows
            .iter()
            .filter(|m| m.metric == metric && m.view == Some(view) && m.frame == Some(frame))
            .map(|m| m.value)
            .collect();
        assert_eq!(found.len(), 1, "{metric}: {found:?}");
        found[0]
    };
    let (psnr_rec, ssim_rec) = (recorded("test_psnr"), recorded("test_ssim"));
    assert!(psnr.is_finite() && ssim.is_finite(), "{psnr} {ssim}");
    assert!(
        (psnr - psnr_rec).abs() < 0.05,
        "PSNR {psnr} vs recorded {psnr_rec}"
    );
    assert!(
        (ssim - ssim_rec).abs() < 1e-3,
        "SSIM {ssim} vs recorded {ssim_rec}"
    );
    // And the test view's mean over frames is evaluation.json's.
    let evaluation = read_json(&evaluate.join("evaluation.json"));
    let test: Vec<f64> = metrics
        .rows
        .iter()
        .filter(|m| m.metric == "test_psnr")
        .map(|m| m.value)
        .collect();
    assert_eq!(test.len(), 5);
    let mean = test.iter().sum::<f64>() / test.len() as f64;
    let stated = evaluation["test_psnr_mean"].as_f64().unwrap();
    assert!(
        (mean - stated).abs() <= 1e-12 * stated,
        "{mean} vs {stated}"
    );
}

/// A stage's warnings reach its manifest and the report: two velocity epochs on the demo do
/// not converge, which the stage says (`velocity.json` `converged: false`), and the report lists
/// it under *Warnings* (HTML and Markdown) and in the stage's row of `report.json`.
#[test]
fn a_stages_warnings_are_kept_in_its_manifest_and_shown_by_the_report() {
    let d = demo();
    let report = d.json("auto/report.json");
    let stages = report["scenes"][0]["stages"].as_array().unwrap();
    let velocity = stages.iter().find(|s| s["kind"] == "velocity").unwrap();
    let entry = d
        .cache()
        .join(format!("velocity-{}", velocity["key"].as_str().unwrap()));
    assert_eq!(read_json(&entry.join("velocity.json"))["converged"], false);
    let kept = manifest(&entry)["warnings"].clone();
    let kept: Vec<String> = serde_json::from_value(kept).unwrap();
    assert_eq!(kept.len(), 1, "{kept:?}");
    assert!(kept[0].starts_with("velocity: the descent had not converged after 2 epochs"));
    let shown: Vec<String> = serde_json::from_value(velocity["warnings"].clone()).unwrap();
    assert_eq!(
        shown,
        [kept[0].trim_start_matches("velocity: ").to_string()]
    );
    let html = std::fs::read_to_string(d.path("auto/report.html")).unwrap();
    assert!(html.contains("<h3>Warnings</h3>"));
    assert!(html.contains("<li><b>velocity</b>: the descent had not converged after 2 epochs"));
    let md = std::fs::read_to_string(d.path("auto/report.md")).unwrap();
    assert!(md.contains("### Warnings\n\n- **velocity**: the descent had not converged"));
    // The summary at the top counts them.
    assert!(html.contains("warnings from the stages"));
    let summary = md
        .lines()
        .find(|l| l.starts_with("| warnings from the stages |"))
        .unwrap();
    assert!(
        summary.contains("velocity") && summary.contains("see Warnings"),
        "{summary}"
    );
    // Stages without warnings show none.
    let evaluate = stages.iter().find(|s| s["kind"] == "evaluate").unwrap();
    assert_eq!(evaluate["warnings"], serde_json::json!([]));
}
