//! The command line: parse, call the library, print. Exit codes: 0 success, 1 failure,
//! 2 invalid pipeline file or arguments, 130 interrupted.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Parser, Subcommand};

use crate::pipeline::progress::Reporter;
use crate::pipeline::runner::{RunError, RunOptions, StageState, Workspace, short};
use crate::pipeline::spec::{self, Overrides, Preset};
use crate::pipeline::stage::Registry;
use crate::report::RunSummary;
use crate::simulate::spec::short_number;
use crate::sweep::SweepSummary;

/// pipe: multi-view videos of a deforming object → an editable, physics-driven 3D scene.
#[derive(Debug, Parser)]
#[command(name = "pipe", version, about, long_about = None)]
struct Cli {
    /// Work directory holding the cache (`.pipe/`); default: the current directory.
    #[arg(long, global = true, value_name = "DIR")]
    workdir: Option<PathBuf>,
    /// Only stage start/finish lines, no progress bars.
    #[arg(long, short, global = true)]
    quiet: bool,
    /// Worker threads for the kernels (results do not depend on it); default: all cores.
    #[arg(long, global = true, value_name = "N")]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, clap::Args)]
struct PipelineArgs {
    /// The pipeline file (YAML).
    file: PathBuf,
    /// Use this preset instead of the file's (draft | standard | paper).
    #[arg(long, value_parser = parse_preset)]
    preset: Option<Preset>,
    /// Override a parameter: `--set stage.key=value` (repeatable; the value is YAML).
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    sets: Vec<String>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run every stage that is not cached.
    Run {
        #[command(flatten)]
        pipeline: PipelineArgs,
        /// Re-run this stage and everything downstream of it, even if cached.
        #[arg(long, value_name = "STAGE")]
        from: Option<String>,
        /// Stop after this stage (run only it and what it needs).
        #[arg(long, value_name = "STAGE")]
        until: Option<String>,
        /// Re-run this stage even if cached (repeatable).
        #[arg(long, value_name = "STAGE")]
        force: Vec<String>,
        /// Do not write the report after a run that ran `evaluate`.
        #[arg(long)]
        no_report: bool,
        /// Where the report after `evaluate` goes; default: `reports/<pipeline name>`.
        #[arg(long, value_name = "DIR")]
        report_out: Option<PathBuf>,
    },
    /// Write report.html (self-contained), report.md and report.json of one or more pipeline
    /// files' cached results (several files: side by side).
    Report {
        /// The pipeline files (YAML).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Use this preset instead of the files' (draft | standard | paper).
        #[arg(long, value_parser = parse_preset)]
        preset: Option<Preset>,
        /// Override a parameter of every file: `--set stage.key=value` (repeatable).
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
        /// Output folder; default: `reports/<name>` (`reports/<name>+<name>…` for several).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// Run every combination of parameter values (sharing cached stages) and write
    /// sweep.parquet, sweep.md and Pareto plots of wall time against PSNR and parameter error.
    Sweep {
        #[command(flatten)]
        pipeline: PipelineArgs,
        /// `stage.key=v1,v2,...` or `preset=draft,standard` (repeatable: the grid is the
        /// product of all of them); replaces the file's `sweep:` axis of the same key.
        #[arg(long = "over", value_name = "KEY=V1,V2,...", value_parser = parse_axis)]
        over: Vec<crate::sweep::Axis>,
        /// Output folder; default: `sweeps/<pipeline name>`.
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// One line per stage: cached, stale (and why) or not run.
    Status {
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// Remove cache entries that no pipeline file references.
    Clean {
        /// Remove every cache entry.
        #[arg(long)]
        all: bool,
    },
    /// Export a stage's Gaussians as a 3DGS PLY, or its tables as Parquet.
    Export {
        #[command(flatten)]
        pipeline: PipelineArgs,
        /// The stage whose outputs to export (must be cached).
        #[arg(long, value_name = "STAGE")]
        stage: String,
        /// `ply`: the stage's gaussians.arrow as a standard 3DGS PLY; `parquet`: every table.
        #[arg(long, value_enum)]
        format: ExportFormat,
        /// Output file (ply) or folder (parquet); default: `exports/<pipeline>-<stage>[.ply]`.
        #[arg(long, value_name = "PATH")]
        out: Option<PathBuf>,
    },
    /// Render a 3DGS PLY (ours or another tool's) from a camera of a PAC-NeRF JSON.
    Render {
        /// The Gaussians (standard 3DGS PLY).
        ply: PathBuf,
        /// Camera file in the PAC-NeRF layout (`all_data.json`).
        #[arg(long)]
        cameras: PathBuf,
        /// Camera index.
        #[arg(long)]
        view: u16,
        /// Frame whose entry gives the camera.
        #[arg(long, default_value_t = 0)]
        frame: i32,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
        /// Also write the expected depth (metres) as an OpenEXR `Z` channel.
        #[arg(long)]
        depth: Option<PathBuf>,
        /// Output width in pixels, the intrinsics scaled from the camera's image size (read
        /// from its image file); default: that size.
        #[arg(long, requires = "height", conflicts_with = "size")]
        width: Option<u32>,
        /// Output height in pixels (with `--width`).
        #[arg(long, requires = "width", conflicts_with = "size")]
        height: Option<u32>,
        /// Output size `WxH` in pixels with the intrinsics as the camera file gives them (the
        /// size they belong to); needed when the camera's image file is absent.
        #[arg(long, value_name = "WxH", value_parser = parse_size)]
        size: Option<(u32, u32)>,
        /// Background RGB in [0, 1], e.g. `1,1,1`.
        #[arg(long, value_delimiter = ',', default_values_t = [1.0f32, 1.0, 1.0])]
        background: Vec<f32>,
    },
    /// Simulate a point cloud or 3DGS PLY as a continuum (MLS-MPM) and write the frames.
    Simulate {
        /// Particles: any point-cloud PLY or 3DGS PLY (x y z used).
        particles: PathBuf,
        /// Material, initial velocity, boundaries and forces (YAML; see README).
        #[arg(long)]
        material: PathBuf,
        /// Number of frames to write (frame 0 is the input state).
        #[arg(long, default_value_t = 14)]
        frames: u32,
        /// Output folder: frame_NNNN.ply, particles.arrow, summary.json.
        #[arg(long)]
        out: PathBuf,
        /// Also write splats_NNNN.ply: the input 3DGS splats moved, stretched and turned with
        /// the material (PhysGaussian), ready for `pipe render`.
        #[arg(long)]
        splats: bool,
        /// Floating-point precision: f64 (the reference) or f32 (about twice as fast, as the
        /// peer simulators run).
        #[arg(long, value_enum, default_value_t = PrecisionArg::F64)]
        precision: PrecisionArg,
    },
    /// Print the JSON Schema of pipeline files (for editors and validators).
    Schema,
}

/// `pipe simulate --precision`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum PrecisionArg {
    F64,
    F32,
}

/// Export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ExportFormat {
    /// Standard 3D Gaussian splatting PLY (opens in common splat viewers).
    Ply,
    /// Parquet, one file per table.
    Parquet,
}

fn parse_preset(s: &str) -> Result<Preset, String> {
    Preset::parse(s)
        .ok_or_else(|| format!("unknown preset `{s}`; expected draft, standard or paper"))
}

fn parse_axis(s: &str) -> Result<crate::sweep::Axis, String> {
    crate::sweep::Axis::parse(s)
}

/// `WxH` (or `W×H`) in pixels, both at least 1.
fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("expected WIDTHxHEIGHT in pixels like `160x120`, found `{s}`");
    let (w, h) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
    let (w, h): (u32, u32) = (
        w.trim().parse().map_err(|_| bad())?,
        h.trim().parse().map_err(|_| bad())?,
    );
    if w == 0 || h == 0 {
        return Err(format!("`{s}`: width and height must be at least 1"));
    }
    Ok((w, h))
}

static INTERRUPTED: AtomicBool = AtomicBool::new(false);

fn install_interrupt_handler() {
    // A second Ctrl-C ends the process at once; the first asks stages to stop cleanly.
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTED.swap(true, Ordering::SeqCst) {
            eprintln!("pipe: interrupted again, exiting now");
            std::process::exit(130);
        }
        eprintln!(
            "pipe: interrupt received, stopping after the current step (Ctrl-C again to quit now)"
        );
    });
}

/// Writes the documents of `pipe report` and `pipe sweep`. The `pipe` binary plugs in the
/// `pipe-report` crate (polars, plots, HTML); this library never links it.
pub trait Publisher: Sync {
    /// Write report.html, report.md and report.json of `runs` (side by side) into `out`;
    /// returns the files written.
    fn report(&self, runs: &[RunSummary], out: &Path) -> Result<Vec<PathBuf>, String>;
    /// Write sweep.parquet, sweep.md and the Pareto plots of `sweep` into `out`.
    fn sweep(&self, sweep: &SweepSummary, out: &Path) -> Result<Vec<PathBuf>, String>;
}

/// Run the CLI with `args` against the stages of `registry` (no `report`/`sweep` writer).
pub fn main(
    args: impl IntoIterator<Item = impl Into<OsString> + Clone>,
    registry: Registry,
) -> ExitCode {
    ExitCode::from(run(args, registry))
}

/// Like [`main`], with the writer of `pipe report` and `pipe sweep`.
pub fn main_with(
    args: impl IntoIterator<Item = impl Into<OsString> + Clone>,
    registry: Registry,
    publisher: &dyn Publisher,
) -> ExitCode {
    ExitCode::from(run_with(args, registry, Some(publisher)))
}

/// Like [`main`], returning the exit status as a number.
pub fn run(args: impl IntoIterator<Item = impl Into<OsString> + Clone>, registry: Registry) -> u8 {
    run_with(args, registry, None)
}

/// Like [`main_with`], returning the exit status as a number.
pub fn run_with(
    args: impl IntoIterator<Item = impl Into<OsString> + Clone>,
    registry: Registry,
    publisher: Option<&dyn Publisher>,
) -> u8 {
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { 2 } else { 0 };
        }
    };
    if let Some(n) = cli.threads {
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global();
    }
    let workdir = cli.workdir.clone().unwrap_or_else(|| PathBuf::from("."));
    let ws = Workspace::new(&workdir);
    // Run on a worker of the pool: parallel kernels started from a thread outside the pool
    // hand over and sleep until done, a futex round trip per kernel call.
    match rayon::scope(|_| execute(&cli, &ws, &registry, publisher)) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("error: {e}");
            let mut src = std::error::Error::source(&e);
            while let Some(s) = src {
                if !e.to_string().contains(&s.to_string()) {
                    eprintln!("  caused by: {s}");
                }
                src = s.source();
            }
            match e {
                RunError::Spec(_) | RunError::Selection(_) | RunError::Usage(_) => 2,
                RunError::Interrupted(_) => 130,
                _ => 1,
            }
        }
    }
}

fn load(args: &PipelineArgs, registry: &Registry) -> Result<spec::Pipeline, RunError> {
    let overrides = Overrides {
        preset: args.preset,
        sets: args.sets.clone(),
    };
    Ok(spec::load(&args.file, registry, &overrides)?)
}

fn no_publisher() -> RunError {
    RunError::Usage(
        "this build has no report writer: `report` and `sweep` are commands of the `pipe` binary"
            .into(),
    )
}

/// `reports/<name>` or, for several runs, `reports/<name>+<name>…`.
fn default_report_dir(names: &[String]) -> PathBuf {
    PathBuf::from("reports").join(names.join("+"))
}

/// Collect `pipelines`' results and write their report into `out`.
fn write_report(
    ws: &Workspace,
    registry: &Registry,
    publisher: &dyn Publisher,
    pipelines: &[spec::Pipeline],
    out: &Path,
) -> Result<Vec<PathBuf>, RunError> {
    let images = out.join("images");
    let mut runs = Vec::new();
    for (i, p) in pipelines.iter().enumerate() {
        let prefix = if pipelines.len() > 1 {
            format!("{}_", i + 1)
        } else {
            String::new()
        };
        let run = crate::report::collect(ws, p, registry, &images, &prefix)?;
        for line in run.missing() {
            eprintln!("note: {line}");
        }
        runs.push(run);
    }
    publisher
        .report(&runs, out)
        .map_err(|e| RunError::Output(format!("writing the report into {}: {e}", out.display())))
}

fn execute(
    cli: &Cli,
    ws: &Workspace,
    registry: &Registry,
    publisher: Option<&dyn Publisher>,
) -> Result<(), RunError> {
    match &cli.command {
        Command::Run {
            pipeline,
            from,
            until,
            force,
            no_report,
            report_out,
        } => {
            let p = load(pipeline, registry)?;
            install_interrupt_handler();
            let reporter = Reporter::auto(cli.quiet);
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let options = RunOptions {
                from: from.clone(),
                until: until.clone(),
                force: force.clone(),
            };
            let report = ws.run(&p, registry, &options, &reporter, &INTERRUPTED, &command)?;
            let ran = report.executed();
            println!(
                "{}: {} stage(s) ran, {} cached; outputs in {}",
                p.name,
                ran.len(),
                report
                    .stages
                    .iter()
                    .filter(|(_, _, o)| *o == crate::pipeline::runner::Outcome::Cached)
                    .count(),
                ws.store.cache_dir().display()
            );
            // The report follows a run that evaluated (ran `evaluate`, not only found it cached).
            let evaluated = report.stages.iter().any(|(name, _, o)| {
                matches!(o, crate::pipeline::runner::Outcome::Ran { .. })
                    && p.stage(name).is_some_and(|s| s.kind == "evaluate")
            });
            if let (true, false, Some(publisher)) = (evaluated, *no_report, publisher) {
                let out = report_out
                    .clone()
                    .unwrap_or_else(|| default_report_dir(std::slice::from_ref(&p.name)));
                let written =
                    write_report(ws, registry, publisher, std::slice::from_ref(&p), &out)?;
                println!("report: {}", files_line(&written));
            }
            Ok(())
        }
        Command::Report {
            files,
            preset,
            sets,
            out,
        } => {
            let publisher = publisher.ok_or_else(no_publisher)?;
            let overrides = Overrides {
                preset: *preset,
                sets: sets.clone(),
            };
            let pipelines = files
                .iter()
                .map(|f| spec::load(f, registry, &overrides))
                .collect::<Result<Vec<_>, _>>()?;
            let names: Vec<String> = pipelines.iter().map(|p| p.name.clone()).collect();
            let out = out.clone().unwrap_or_else(|| default_report_dir(&names));
            let written = write_report(ws, registry, publisher, &pipelines, &out)?;
            println!("report: {}", files_line(&written));
            Ok(())
        }
        Command::Sweep {
            pipeline,
            over,
            out,
        } => {
            let publisher = publisher.ok_or_else(no_publisher)?;
            let request = crate::sweep::SweepRequest {
                file: pipeline.file.clone(),
                base: Overrides {
                    preset: pipeline.preset,
                    sets: pipeline.sets.clone(),
                },
                axes: over.clone(),
            };
            install_interrupt_handler();
            let reporter = Reporter::auto(cli.quiet);
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let summary =
                crate::sweep::run(ws, registry, &request, &reporter, &INTERRUPTED, &command)?;
            let out = out
                .clone()
                .unwrap_or_else(|| PathBuf::from("sweeps").join(&summary.name));
            let written = publisher.sweep(&summary, &out).map_err(|e| {
                RunError::Output(format!("writing the sweep into {}: {e}", out.display()))
            })?;
            println!(
                "{}: {} variant(s), {} stage run(s); {}",
                summary.name,
                summary.variants.len(),
                summary.variants.iter().map(|v| v.ran.len()).sum::<usize>(),
                files_line(&written)
            );
            Ok(())
        }
        Command::Status { pipeline } => {
            let p = load(pipeline, registry)?;
            let (_, planned) = ws.plan(&p, registry)?;
            println!(
                "{} ({}), preset {}, cache {}",
                p.name,
                p.file.display(),
                p.preset.name(),
                ws.store.cache_dir().display()
            );
            let width = planned.iter().map(|s| s.name.len()).max().unwrap_or(0);
            for s in &planned {
                let line = match &s.state {
                    StageState::Cached(m) => {
                        let dir = ws.store.entry_dir(&s.name, &s.key);
                        format!(
                            "cached   {}  ran in {:.2} s{}, {}",
                            short(&s.key),
                            m.wall_s,
                            headline_metrics(&dir),
                            display_dir(&dir)
                        )
                    }
                    StageState::Stale(reasons) => format!(
                        "stale    {}{}",
                        reasons.join("; "),
                        checkpoint_note(ws, &s.name, &s.key, "; ")
                    ),
                    StageState::NotRun => {
                        format!("not run{}", checkpoint_note(ws, &s.name, &s.key, " ("))
                    }
                };
                println!("  {:width$}  {line}", s.name);
            }
            Ok(())
        }
        Command::Clean { all } => {
            let removed = ws.clean(registry, *all)?;
            let (e, c) = (removed.entries.len(), removed.checkpoints.len());
            println!(
                "removed {e} cache {} and {c} {}",
                if e == 1 { "entry" } else { "entries" },
                if c == 1 { "checkpoint" } else { "checkpoints" }
            );
            for r in removed.entries {
                println!("  {r}");
            }
            for r in removed.checkpoints {
                println!("  checkpoint {r}");
            }
            Ok(())
        }
        Command::Export {
            pipeline,
            stage,
            format,
            out,
        } => {
            let p = load(pipeline, registry)?;
            let entry = ws.cached_entry(&p, registry, stage)?;
            let (fmt, default) = match format {
                ExportFormat::Ply => (
                    crate::export::Format::Ply,
                    format!("exports/{}-{stage}.ply", p.name),
                ),
                ExportFormat::Parquet => (
                    crate::export::Format::Parquet,
                    format!("exports/{}-{stage}", p.name),
                ),
            };
            let out = out.clone().unwrap_or_else(|| PathBuf::from(default));
            for (file, what) in crate::export::export(&entry, stage, fmt, &out)
                .map_err(|e| RunError::Output(e.to_string()))?
            {
                println!("wrote {what} to {}", file.display());
            }
            Ok(())
        }
        Command::Render {
            ply,
            cameras,
            view,
            frame,
            out,
            depth,
            width,
            height,
            size,
            background,
        } => {
            use crate::preview::OutputSize;
            let size = match (size, width.zip(*height)) {
                (Some((w, h)), _) => OutputSize::Exact(*w, *h),
                (None, Some((w, h))) => OutputSize::Rescaled(w, h),
                (None, None) => OutputSize::Native,
            };
            let req = crate::preview::PreviewRequest {
                ply: ply.clone(),
                cameras: cameras.clone(),
                view: *view,
                frame: *frame,
                size,
                background: <[f32; 3]>::try_from(background.as_slice()).map_err(|_| {
                    RunError::Usage(format!(
                        "--background: expected three comma-separated values in [0, 1] like `1,1,1`, found {} value(s)",
                        background.len()
                    ))
                })?,
            };
            let p = crate::preview::render(&req).map_err(|e| RunError::Output(e.to_string()))?;
            crate::io::image::write_rgb8(out, &p.image)
                .map_err(|e| RunError::Output(e.to_string()))?;
            if let Some(d) = depth {
                crate::io::exr::write_depth(d, p.image.width, p.image.height, &p.depth)
                    .map_err(|e| RunError::Output(e.to_string()))?;
            }
            println!(
                "rendered {} Gaussians from camera {view} at {}×{} to {}{}",
                p.gaussians,
                p.image.width,
                p.image.height,
                out.display(),
                depth
                    .as_ref()
                    .map(|d| format!(" (depth: {})", d.display()))
                    .unwrap_or_default()
            );
            Ok(())
        }
        Command::Simulate {
            particles,
            material,
            frames,
            out,
            splats,
            precision,
        } => {
            install_interrupt_handler();
            let reporter = Reporter::auto(cli.quiet);
            let options = crate::simulate::Options {
                splats: *splats,
                precision: match precision {
                    PrecisionArg::F64 => pipe_mpm::Precision::F64,
                    PrecisionArg::F32 => pipe_mpm::Precision::F32,
                },
            };
            let summary =
                crate::simulate::run_with(particles, material, *frames, out, &reporter, options)
                    .map_err(|e| RunError::Output(e.to_string()))?;
            println!("{}", summary.report(out));
            Ok(())
        }
        Command::Schema => {
            let s = spec::json_schema(registry);
            println!(
                "{}",
                serde_json::to_string_pretty(&s).expect("schema serialises")
            );
            Ok(())
        }
    }
}

/// The stage's summary metrics (rows for no particular epoch, view or frame), e.g.
/// `; test_psnr_mean 29.6`.
fn headline_metrics(entry: &Path) -> String {
    let Ok(m) =
        crate::scene::table::read::<crate::scene::metrics::Metrics>(&entry.join("metrics.arrow"))
    else {
        return String::new();
    };
    let rows: Vec<String> = m
        .rows
        .iter()
        .filter(|r| r.epoch.is_none() && r.view.is_none() && r.frame.is_none())
        .take(4)
        .map(|r| format!("{} {}", r.metric, short_number(r.value)))
        .collect();
    if rows.is_empty() {
        String::new()
    } else {
        format!("; {}", rows.join(", "))
    }
}

/// What `status` says about the checkpoint a run of a stage would resume (empty if none):
/// `<sep>checkpoint from epoch 12 will be resumed`, closed by `)` when `sep` opens one.
fn checkpoint_note(ws: &Workspace, name: &str, key: &str, sep: &str) -> String {
    let close = if sep.ends_with('(') { ")" } else { "" };
    match ws.checkpoint(name, key) {
        Ok(None) => String::new(),
        Ok(Some(saved)) => format!(
            "{sep}checkpoint from {} will be resumed{close}",
            saved.progress
        ),
        Err(problem) => {
            format!(
                "{sep}its checkpoint will be ignored and the stage start over: {problem}{close}"
            )
        }
    }
}

/// The files' paths, comma-separated.
fn files_line(files: &[PathBuf]) -> String {
    files
        .iter()
        .map(|f| f.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

fn display_dir(p: &Path) -> String {
    p.display().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::stage::MetricRow;

    #[test]
    fn status_headlines_skip_per_frame_rows() {
        let dir = tempfile::tempdir().unwrap();
        let row = |frame: Option<u16>, metric: &str, value: f64| MetricRow {
            epoch: None,
            view: None,
            frame,
            metric: metric.into(),
            value,
        };
        let rows = [
            row(Some(0), "chamfer_m", 0.006),
            row(Some(1), "chamfer_m", f64::NAN),
            row(None, "test_psnr_mean", 29.24),
        ];
        crate::scene::metrics::write(&dir.path().join("metrics.arrow"), "evaluate", &rows).unwrap();
        assert_eq!(headline_metrics(dir.path()), "; test_psnr_mean 29.24");
    }
}
