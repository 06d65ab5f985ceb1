//! Generated scenes through the pipeline: `datasets-tools scene` (or `two-material`) into a folder, then a pipeline
//! file's stages on it, quietly, with its outputs read back as JSON.

use std::path::Path;
use std::process::Command;

use pipe::pipeline::progress::{Mode, Reporter};
use pipe::pipeline::runner::{RunOptions, Workspace};
use pipe::pipeline::spec::{self, Overrides, Pipeline};
use pipe::pipeline::stage::Registry;
use serde_json::Value;

/// `datasets-tools COMMAND DST ARGS...` (`scene`, `two-material`), which must succeed.
pub fn generate(command: &str, dst: &Path, args: &[&str]) {
    let o = Command::new(env!("CARGO_BIN_EXE_datasets-tools"))
        .arg(command)
        .arg(dst)
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}: {}",
        dst.display(),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// A pipeline run in `root` (its cache there), from the pipeline file's text.
pub struct Run {
    ws: Workspace,
    pipeline: Pipeline,
    registry: Registry,
}

impl Run {
    /// Writes `root/p.yaml` with `yaml` and runs every stage, panicking with `label` on error.
    pub fn new(root: &Path, yaml: &str, label: &str) -> Self {
        let file = root.join("p.yaml");
        std::fs::write(&file, yaml).unwrap();
        let registry = pipe::stages::builtin();
        let pipeline = spec::load(&file, &registry, &Overrides::default()).unwrap();
        let ws = Workspace::new(root);
        ws.run(
            &pipeline,
            &registry,
            &RunOptions::default(),
            &Reporter::new(Mode::Quiet),
            &std::sync::atomic::AtomicBool::new(false),
            "test",
        )
        .unwrap_or_else(|e| panic!("{label}: {e}"));
        Self {
            ws,
            pipeline,
            registry,
        }
    }

    /// The JSON file `name` of `stage`'s cache entry.
    pub fn json(&self, stage: &str, name: &str) -> Value {
        let entry = self
            .ws
            .cached_entry(&self.pipeline, &self.registry, stage)
            .unwrap();
        serde_json::from_slice(&std::fs::read(entry.join(name)).unwrap()).unwrap()
    }
}
