//! The `pipe` command. The library holds the command line; this binary plugs in `pipe-report`
//! (polars, plots, HTML) as the writer of `pipe report` and `pipe sweep`, so polars enters the
//! binary only, never the library or its tests.

use std::path::{Path, PathBuf};

use pipe::report::RunSummary;
use pipe::sweep::SweepSummary;

/// `pipe-report` behind the library's [`pipe::cli::Publisher`].
struct Documents;

impl pipe::cli::Publisher for Documents {
    fn report(&self, runs: &[RunSummary], out: &Path) -> Result<Vec<PathBuf>, String> {
        let value = serde_json::to_value(runs).map_err(|e| e.to_string())?;
        pipe_report::write_report_value(value, out).map_err(|e| e.to_string())
    }

    fn sweep(&self, sweep: &SweepSummary, out: &Path) -> Result<Vec<PathBuf>, String> {
        let value = serde_json::to_value(sweep).map_err(|e| e.to_string())?;
        pipe_report::write_sweep_value(value, out).map_err(|e| e.to_string())
    }
}

fn main() -> std::process::ExitCode {
    pipe::cli::main_with(std::env::args_os(), pipe::stages::builtin(), &Documents)
}
