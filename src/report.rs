//! What `pipe report` reads from a work directory for one pipeline file: every stage's state
//! and cache entry (the plan `pipe status` and `pipe export` use), its manifest's wall time and
//! peak memory, and an image strip per test view (captured | ours | 4× error, as `evaluate`'s
//! GIFs) for the first, middle and last evaluated frames. The documents themselves (tables with
//! polars, plots, HTML, Markdown, JSON) are written by the `pipe-report` crate, which the `pipe`
//! binary plugs in through [`crate::cli::Publisher`]: polars never enters this library.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::io::image::{self, Rgb8};
use crate::pipeline::runner::{RunError, StageState, Workspace};
use crate::pipeline::spec::Pipeline;
use crate::pipeline::stage::Registry;
use crate::scene::frames::{FrameRow, Frames};
use crate::scene::{table, targets};

/// One pipeline file's run, as the report needs it (serialised for `pipe-report`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// `name:` of the pipeline file.
    pub name: String,
    /// The pipeline file.
    pub file: PathBuf,
    /// Effective preset.
    pub preset: String,
    /// The resolved `scene:` section (absolute `path`).
    pub scene: Value,
    /// Every stage in execution order.
    pub stages: Vec<StageRun>,
    /// Image strips of the evaluated test views.
    pub strips: Vec<Strip>,
    /// The animated GIF per rendered view that `evaluate` wrote (captured | ours | error).
    pub gifs: Vec<ViewFile>,
}

/// One stage of a [`RunSummary`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageRun {
    /// Name in the pipeline file.
    pub name: String,
    /// Stage kind (`warmup`, `material`, `evaluate`, …).
    pub kind: String,
    /// Cache key for the current parameters.
    pub key: String,
    /// `done` (its result is in the cache for the current parameters), `stale` or `not run`.
    pub state: String,
    /// Why it is stale.
    pub reasons: Vec<String>,
    /// Its cache entry, when cached.
    pub dir: Option<PathBuf>,
    /// Resolved parameters.
    pub params: Value,
    /// Wall time (s) from the manifest (summed over the runs of a resumed stage).
    pub wall_s: Option<f64>,
    /// Peak resident memory of the process while the stage ran, bytes (0: unknown).
    pub peak_rss_bytes: Option<u64>,
    /// Worker threads it ran with.
    pub threads: Option<usize>,
    /// The warnings it gave when it ran (from the manifest).
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// A PNG strip of one test view at one frame: captured | ours | 4× |captured − ours|.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Strip {
    /// Camera.
    pub view: u16,
    /// Frame.
    pub frame: u16,
    /// `first`, `middle` or `last`.
    pub position: String,
    /// The PNG file.
    pub path: PathBuf,
}

/// A file that belongs to one view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewFile {
    /// Camera.
    pub view: u16,
    /// The file.
    pub path: PathBuf,
}

/// Why a report's inputs could not be gathered.
#[derive(Debug, thiserror::Error)]
pub enum CollectError {
    /// Nothing of the pipeline has run.
    #[error(
        "{file}: no stage of `{name}` is cached for the current parameters; run `pipe run {file}` first"
    )]
    NothingRun {
        /// The pipeline file.
        file: String,
        /// Its name.
        name: String,
    },
    /// A table of an entry could not be read.
    #[error(transparent)]
    Table(#[from] table::TableError),
    /// A capture or render could not be read or the strip written.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// A capture could not be composited.
    #[error(transparent)]
    Target(#[from] targets::TargetError),
    /// The evaluated frames do not match the renders.
    #[error("{0}")]
    Inconsistent(String),
}

impl From<CollectError> for RunError {
    fn from(e: CollectError) -> Self {
        RunError::Output(e.to_string())
    }
}

/// Gather what the report of `pipeline` needs; strips are written into `images_dir` as
/// `<prefix>v<view>_f<frame>.png`.
pub fn collect(
    ws: &Workspace,
    pipeline: &Pipeline,
    registry: &Registry,
    images_dir: &Path,
    prefix: &str,
) -> Result<RunSummary, RunError> {
    let (_, planned) = ws.plan(pipeline, registry)?;
    let mut stages = Vec::new();
    for p in &planned {
        let kind = p.key_material.kind.clone();
        let params = pipeline
            .stage(&p.name)
            .map(|s| s.params.clone())
            .unwrap_or(Value::Null);
        let mut run = StageRun {
            name: p.name.clone(),
            kind,
            key: p.key.clone(),
            state: "not run".into(),
            reasons: Vec::new(),
            dir: None,
            params,
            wall_s: None,
            peak_rss_bytes: None,
            threads: None,
            warnings: Vec::new(),
        };
        match &p.state {
            StageState::Cached(m) => {
                run.state = "done".into();
                run.dir = Some(ws.store.entry_dir(&p.name, &p.key));
                run.wall_s = Some(m.wall_s);
                run.peak_rss_bytes = Some(m.peak_rss_bytes);
                run.threads = Some(m.threads);
                run.warnings = m.warnings.clone();
            }
            StageState::Stale(why) => {
                run.state = "stale".into();
                run.reasons = why.clone();
            }
            StageState::NotRun => {}
        }
        stages.push(run);
    }
    if stages.iter().all(|s| s.dir.is_none()) {
        return Err(CollectError::NothingRun {
            file: pipeline.file.display().to_string(),
            name: pipeline.name.clone(),
        }
        .into());
    }
    let entry = |kind: &str| {
        stages
            .iter()
            .find(|s| s.kind == kind)
            .and_then(|s| s.dir.clone())
    };
    let (mut strips, mut gifs) = (Vec::new(), Vec::new());
    if let (Some(ingest), Some(evaluate)) = (entry("ingest"), entry("evaluate")) {
        strips = write_strips(
            &ingest,
            &evaluate,
            &pipeline.scene.test_views,
            images_dir,
            prefix,
        )?;
        for &view in &pipeline.scene.test_views {
            let gif = evaluate.join(format!("renders/v{view}.gif"));
            if gif.is_file() {
                gifs.push(ViewFile { view, path: gif });
            }
        }
    }
    Ok(RunSummary {
        name: pipeline.name.clone(),
        file: pipeline.file.clone(),
        preset: pipeline.preset.name().to_string(),
        scene: serde_json::to_value(&pipeline.scene).expect("the scene section serialises"),
        stages,
        strips,
        gifs,
    })
}

impl RunSummary {
    /// What a report of this run lacks: one line per stage without a cached result under the
    /// file's settings (the preset and `--set` given), saying why and what to do.
    pub fn missing(&self) -> Vec<String> {
        self.stages
            .iter()
            .filter(|s| s.dir.is_none())
            .map(|s| {
                let why = if s.reasons.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", s.reasons.join("; "))
                };
                format!(
                    "{}: stage `{}` is {} with these settings{why}: the report has no results \
                     from it; run `pipe run` with the same --preset and --set first",
                    self.file.display(),
                    s.name,
                    s.state
                )
            })
            .collect()
    }
}

/// First, middle and last of the evaluated frames `0..=last`, without repeats.
pub fn strip_frames(last: u16) -> Vec<(u16, &'static str)> {
    let mut out = vec![(0, "first")];
    if last >= 2 {
        out.push((last / 2, "middle"));
    }
    if last >= 1 {
        out.push((last, "last"));
    }
    out
}

/// The strips of every test view that `evaluate` rendered, from the capture as `evaluate`
/// scores it (the object inside its mask, the camera's plate outside) and the saved render.
fn write_strips(
    ingest: &Path,
    evaluate: &Path,
    test_views: &[u16],
    images_dir: &Path,
    prefix: &str,
) -> Result<Vec<Strip>, CollectError> {
    let frames: Frames = table::read(&ingest.join("frames.arrow"))?;
    // The colour the ingested images were composited on, as the physics stages read it.
    let background: [f32; 3] =
        crate::io::read_json::<crate::pipeline::cache::Manifest>(&ingest.join("manifest.json"))
            .ok()
            .and_then(|m| serde_json::from_value(m.key_material.params["background"].clone()).ok())
            .unwrap_or([1.0, 1.0, 1.0]);
    let mut out = Vec::new();
    for &view in test_views {
        let rows: Vec<&FrameRow> = frames.rows.iter().filter(|r| r.view == view).collect();
        let Some(last) = rows.iter().map(|r| r.frame).max() else {
            continue;
        };
        if !evaluate.join(format!("renders/v{view}_f0.png")).is_file() {
            continue;
        }
        for (frame, position) in strip_frames(last) {
            let Some(row) = rows.iter().find(|r| r.frame == frame) else {
                continue;
            };
            let render_path = evaluate.join(format!("renders/v{view}_f{frame}.png"));
            let ours = image::read_rgb8(&render_path)?;
            let target = targets::load(ingest, &[*row])?
                .pop()
                .expect("one row gives one target");
            let (w, h) = target.size();
            if (ours.width as usize, ours.height as usize) != (w, h) {
                return Err(CollectError::Inconsistent(format!(
                    "{}: the render is {}×{}, the capture of view {view} frame {frame} {w}×{h}",
                    render_path.display(),
                    ours.width,
                    ours.height
                )));
            }
            let truth = target.over(&target.backdrop(background));
            let truth8: Vec<u8> = truth
                .iter()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            let strip: Rgb8 = image::compare_strip(&truth8, &ours.data, w, h);
            std::fs::create_dir_all(images_dir).map_err(|e| image::ImageError::Encode {
                path: images_dir.to_path_buf(),
                message: e.to_string(),
            })?;
            let path = images_dir.join(format!("{prefix}v{view}_f{frame}.png"));
            image::write_rgb8(&path, &strip)?;
            out.push(Strip {
                view,
                frame,
                position: position.into(),
                path,
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strip_frames_are_first_middle_last_without_repeats() {
        assert_eq!(strip_frames(0), vec![(0, "first")]);
        assert_eq!(strip_frames(1), vec![(0, "first"), (1, "last")]);
        assert_eq!(
            strip_frames(13),
            vec![(0, "first"), (6, "middle"), (13, "last")]
        );
    }
}
