//! Checkpoints of long stages, so that an interrupted or killed run continues where it stopped
//! (the stage API is [`StageContext::resume`](super::stage::StageContext::resume) and
//! [`StageContext::checkpoint`](super::stage::StageContext::checkpoint)).
//!
//! They live beside the cache, in `.pipe/checkpoints/<stage>-<key>/`, never in `.pipe/cache/`
//! (they are not entries) nor in `.pipe/tmp/` (which every run clears). Each checkpoint is a
//! numbered generation directory `<seq>/` holding `checkpoint.json` (format version, stage,
//! key, a progress line, the stage's metrics so far, its state, and the blake3 hash and size of
//! each file the stage saved beside it). A generation is assembled in `next/`, its files
//! fsync'd, and renamed to `<seq>/` (atomic), then the older generations are removed: a kill at
//! any point leaves the last complete generation readable, and a half-written `next/` is
//! ignored and cleared by the next checkpoint. The newest generation is the one resumed; one
//! that is unreadable, of another format, stage or key, or whose files do not match their
//! hashes is reported and ignored.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::de::{DeserializeOwned, IgnoredAny};
use serde::{Deserialize, Serialize};

use super::cache::{OutputFile, hash_file, list_files};
use super::stage::MetricRow;

/// Bumped when the layout of `checkpoint.json` changes.
pub const CHECKPOINT_FORMAT: u32 = 1;

/// The state file of a generation.
pub const STATE_FILE: &str = "checkpoint.json";

/// The generation being assembled.
const PENDING: &str = "next";

/// `checkpoint.json`.
#[derive(Debug, Serialize, Deserialize)]
struct Envelope<S> {
    format: u32,
    stage: String,
    key: String,
    /// Human-readable position, e.g. `epoch 12`.
    progress: String,
    /// Wall time of the stage up to this checkpoint, over every run it took, seconds.
    wall_s: f64,
    /// Files saved beside the state (relative path → hash and size).
    files: BTreeMap<String, OutputFile>,
    /// The stage's metric rows so far.
    metrics: Vec<MetricRow>,
    /// The stage's own state.
    state: S,
}

/// Just the format version (read first, so another layout is named as such).
#[derive(Deserialize)]
struct FormatOnly {
    format: u32,
}

/// A checkpoint on disk, as `pipe status` and the resume notice describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct Saved {
    /// What the stage said when it saved it, e.g. `epoch 12`.
    pub progress: String,
    /// The generation directory.
    pub dir: PathBuf,
    /// Wall time of the stage up to the checkpoint, seconds.
    pub wall_s: f64,
    /// The files saved beside the state.
    pub files: Vec<String>,
}

/// A checkpoint read back with its state.
#[derive(Debug)]
pub struct Loaded<T> {
    /// Where and what.
    pub saved: Saved,
    /// The stage's metric rows up to the checkpoint.
    pub metrics: Vec<MetricRow>,
    /// The stage's state.
    pub state: T,
}

/// Why a checkpoint cannot be resumed (reported as a warning; the stage starts over).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckpointProblem {
    /// The directory or `checkpoint.json` cannot be read or parsed.
    #[error("{0}: unreadable ({1})")]
    Unreadable(PathBuf, String),
    /// Written by another checkpoint format.
    #[error("{path}: checkpoint format {found}, this pipe reads format {CHECKPOINT_FORMAT}")]
    Format {
        /// `checkpoint.json`.
        path: PathBuf,
        /// Its format version.
        found: u32,
    },
    /// It belongs to another stage or key (copied or renamed by hand).
    #[error("{path}: it records stage `{stage}` with key {key}, not this stage's key")]
    Mismatch {
        /// `checkpoint.json`.
        path: PathBuf,
        /// The stage it records.
        stage: String,
        /// The key it records.
        key: String,
    },
    /// A file listed in it is missing.
    #[error("{0}: file missing")]
    MissingFile(PathBuf),
    /// A file's content does not match its recorded hash or size.
    #[error("{0}: content does not match the checkpoint (corrupted or modified)")]
    Corrupted(PathBuf),
    /// The state is not what this stage's code reads (e.g. its layout changed).
    #[error("{0}: the state does not fit this stage ({1})")]
    State(PathBuf, String),
}

/// Why a checkpoint could not be saved (the stage fails with it).
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// A file-system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The path involved.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The state does not come back equal from its JSON text, so a resumed run would differ.
    #[error(
        "checkpoint of `{stage}`: the state does not survive JSON (NaN and infinite numbers become null): {message}"
    )]
    NotRoundTrip {
        /// The stage.
        stage: String,
        /// What differed.
        message: String,
    },
    /// A file name that is not a plain name, or is reserved.
    #[error(
        "checkpoint of `{stage}`: `{name}` is not a valid checkpoint file name (a plain name, not `{STATE_FILE}`)"
    )]
    BadName {
        /// The stage.
        stage: String,
        /// The name asked for.
        name: String,
    },
    /// The context was built without a checkpoint store.
    #[error("stage `{0}`: this context keeps no checkpoints (built without `with_checkpoints`)")]
    NoStore(String),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// fsync a file or a directory (so a rename into it survives a power loss).
fn sync_path(path: &Path) -> Result<(), CheckpointError> {
    fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io_err(path))
}

/// The checkpoints of one stage at one key: `.pipe/checkpoints/<stage>-<key>/`.
#[derive(Debug)]
pub struct Checkpoints {
    root: PathBuf,
    stage: String,
    key: String,
    /// `next/` was cleared and created by this run (leftovers of a killed run are not reused).
    pending_ready: AtomicBool,
    /// Wall time recorded by the resumed checkpoint, seconds.
    resumed_wall_s: Mutex<f64>,
    started: Instant,
}

impl Checkpoints {
    /// The checkpoints of `stage` at `key` in `root` (`Store::checkpoint_dir`). Creating the
    /// handle touches nothing on disk; it starts the stage's wall clock.
    pub fn new(root: PathBuf, stage: &str, key: &str) -> Self {
        Self {
            root,
            stage: stage.to_string(),
            key: key.to_string(),
            pending_ready: AtomicBool::new(false),
            resumed_wall_s: Mutex::new(0.0),
            started: Instant::now(),
        }
    }

    /// `.pipe/checkpoints/<stage>-<key>/`.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The stage's wall time so far: this run's plus that of the runs it resumed, seconds.
    pub fn wall_s(&self) -> f64 {
        *self.resumed_wall_s.lock().expect("not poisoned") + self.started.elapsed().as_secs_f64()
    }

    /// The newest complete generation, if any.
    fn newest(&self) -> Result<Option<(u64, PathBuf)>, CheckpointProblem> {
        let rd = match fs::read_dir(&self.root) {
            Ok(rd) => rd,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => {
                return Err(CheckpointProblem::Unreadable(
                    self.root.clone(),
                    e.to_string(),
                ));
            }
        };
        Ok(rd
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let seq = e.file_name().to_str()?.parse::<u64>().ok()?;
                Some((seq, e.path()))
            })
            .max_by_key(|(seq, _)| *seq))
    }

    /// Read and check the newest generation, its state as `S`.
    fn read<S: DeserializeOwned>(&self) -> Result<Option<(Saved, Envelope<S>)>, CheckpointProblem> {
        // `pipe status` reads without the work-directory lock: if a runner replaced the
        // generation meanwhile, read the new one.
        let mut attempt = 0;
        loop {
            let Some((_, dir)) = self.newest()? else {
                return Ok(None);
            };
            match self.read_generation(&dir) {
                Err(_) if !dir.exists() && attempt < 3 => attempt += 1,
                other => return other.map(Some),
            }
        }
    }

    fn read_generation<S: DeserializeOwned>(
        &self,
        dir: &Path,
    ) -> Result<(Saved, Envelope<S>), CheckpointProblem> {
        let path = dir.join(STATE_FILE);
        let unreadable = |e: String| CheckpointProblem::Unreadable(path.clone(), e);
        let bytes = fs::read(&path).map_err(|e| unreadable(e.to_string()))?;
        let format: FormatOnly =
            serde_json::from_slice(&bytes).map_err(|e| unreadable(e.to_string()))?;
        if format.format != CHECKPOINT_FORMAT {
            return Err(CheckpointProblem::Format {
                path,
                found: format.format,
            });
        }
        let head: Envelope<IgnoredAny> =
            serde_json::from_slice(&bytes).map_err(|e| unreadable(e.to_string()))?;
        if head.stage != self.stage || head.key != self.key {
            return Err(CheckpointProblem::Mismatch {
                path,
                stage: head.stage,
                key: head.key,
            });
        }
        for (rel, expected) in &head.files {
            let p = dir.join(rel);
            match hash_file(&p) {
                Err(_) => return Err(CheckpointProblem::MissingFile(p)),
                Ok((h, size)) if h != expected.blake3 || size != expected.size => {
                    return Err(CheckpointProblem::Corrupted(p));
                }
                Ok(_) => {}
            }
        }
        let full: Envelope<S> = serde_json::from_slice(&bytes)
            .map_err(|e| CheckpointProblem::State(path.clone(), e.to_string()))?;
        let saved = Saved {
            progress: full.progress.clone(),
            dir: dir.to_path_buf(),
            wall_s: full.wall_s,
            files: full.files.keys().cloned().collect(),
        };
        Ok((saved, full))
    }

    /// The newest checkpoint, checked (format, stage, key, file hashes) but its state unread.
    pub fn latest(&self) -> Result<Option<Saved>, CheckpointProblem> {
        Ok(self.read::<IgnoredAny>()?.map(|(saved, _)| saved))
    }

    /// The newest checkpoint with its state read as `T`; remembers its wall time.
    pub fn load<T: DeserializeOwned>(&self) -> Result<Option<Loaded<T>>, CheckpointProblem> {
        let Some((saved, env)) = self.read::<T>()? else {
            return Ok(None);
        };
        *self.resumed_wall_s.lock().expect("not poisoned") = env.wall_s;
        Ok(Some(Loaded {
            saved,
            metrics: env.metrics,
            state: env.state,
        }))
    }

    /// Where the stage writes file `name` of its next checkpoint (`next/<name>`).
    pub fn file(&self, name: &str) -> Result<PathBuf, CheckpointError> {
        let plain = Path::new(name)
            .file_name()
            .is_some_and(|f| f == std::ffi::OsStr::new(name));
        if !plain || name == STATE_FILE || name.starts_with('.') {
            return Err(CheckpointError::BadName {
                stage: self.stage.clone(),
                name: name.to_string(),
            });
        }
        Ok(self.pending()?.join(name))
    }

    /// `next/`, cleared of a killed run's leftovers the first time this run asks for it.
    fn pending(&self) -> Result<PathBuf, CheckpointError> {
        let dir = self.root.join(PENDING);
        if !self.pending_ready.load(Ordering::SeqCst) {
            if dir.exists() {
                fs::remove_dir_all(&dir).map_err(io_err(&dir))?;
            }
            fs::create_dir_all(&dir).map_err(io_err(&dir))?;
            self.pending_ready.store(true, Ordering::SeqCst);
        }
        Ok(dir)
    }

    /// Save a generation: the files written through [`Self::file`] since the last save, and
    /// `checkpoint.json` with `state`. The state must come back from its JSON text unchanged
    /// (checked here), so a resumed run continues from exactly this state.
    pub fn save<T: Serialize + DeserializeOwned>(
        &self,
        progress: &str,
        metrics: &[MetricRow],
        state: &T,
    ) -> Result<Saved, CheckpointError> {
        let pending = self.pending()?;
        let mut files = BTreeMap::new();
        for rel in list_files(&pending).map_err(io_err(&pending))? {
            if rel == STATE_FILE {
                continue;
            }
            let p = pending.join(&rel);
            sync_path(&p)?;
            let (blake3, size) = hash_file(&p).map_err(io_err(&p))?;
            files.insert(rel, OutputFile { blake3, size });
        }
        let envelope = Envelope {
            format: CHECKPOINT_FORMAT,
            stage: self.stage.clone(),
            key: self.key.clone(),
            progress: progress.to_string(),
            wall_s: self.wall_s(),
            files,
            metrics: metrics.to_vec(),
            state,
        };
        let text = serde_json::to_vec_pretty(&envelope).map_err(|e| self.not_round_trip(e))?;
        let back: Envelope<T> =
            serde_json::from_slice(&text).map_err(|e| self.not_round_trip(e))?;
        // Compared as values: map order (a HashMap's) may differ, content may not.
        let again = serde_json::to_value(&back).map_err(|e| self.not_round_trip(e))?;
        if again != serde_json::to_value(&envelope).map_err(|e| self.not_round_trip(e))? {
            return Err(CheckpointError::NotRoundTrip {
                stage: self.stage.clone(),
                message: "its JSON text reads back as a different value".into(),
            });
        }
        let state_path = pending.join(STATE_FILE);
        fs::write(&state_path, &text).map_err(io_err(&state_path))?;
        sync_path(&state_path)?;
        sync_path(&pending)?;

        let seq = self.newest().ok().flatten().map_or(1, |(s, _)| s + 1);
        let dest = self.root.join(seq.to_string());
        fs::rename(&pending, &dest).map_err(io_err(&dest))?;
        self.pending_ready.store(false, Ordering::SeqCst);
        sync_path(&self.root)?;
        // Older generations are superseded; one left behind (a kill right here) is harmless,
        // the newest is the one read.
        if let Ok(rd) = fs::read_dir(&self.root) {
            for e in rd.filter_map(|e| e.ok()) {
                if e.file_name()
                    .to_str()
                    .and_then(|n| n.parse::<u64>().ok())
                    .is_some_and(|s| s < seq)
                {
                    let _ = fs::remove_dir_all(e.path());
                }
            }
        }
        Ok(Saved {
            progress: progress.to_string(),
            dir: dest,
            wall_s: envelope.wall_s,
            files: envelope.files.keys().cloned().collect(),
        })
    }

    fn not_round_trip(&self, e: serde_json::Error) -> CheckpointError {
        CheckpointError::NotRoundTrip {
            stage: self.stage.clone(),
            message: e.to_string(),
        }
    }

    /// Remove every generation (the stage committed its entry).
    pub fn remove(&self) -> Result<(), CheckpointError> {
        if self.root.exists() {
            fs::remove_dir_all(&self.root).map_err(io_err(&self.root))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    struct State {
        epoch: u32,
        x: f64,
        y: f32,
        rng: u64,
    }

    fn state() -> State {
        State {
            epoch: 3,
            x: 0.1 + 0.2,
            y: 1.0e-7f32 / 3.0,
            rng: u64::MAX - 12345,
        }
    }

    fn rows() -> Vec<MetricRow> {
        vec![
            MetricRow {
                epoch: Some(1),
                view: None,
                frame: Some(2),
                metric: "loss".into(),
                value: 1.0 / 3.0,
            },
            MetricRow {
                epoch: None,
                view: Some(4),
                frame: None,
                metric: "psnr".into(),
                value: f64::INFINITY,
            },
        ]
    }

    fn store(dir: &Path) -> Checkpoints {
        Checkpoints::new(dir.join("train-abc"), "train", "abc")
    }

    #[test]
    fn state_metrics_and_files_come_back_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let cp = store(dir.path());
        assert!(cp.latest().unwrap().is_none());
        fs::write(cp.file("moments.bin").unwrap(), [1u8, 2, 3]).unwrap();
        cp.save("epoch 3", &rows(), &state()).unwrap();
        let back = store(dir.path()).load::<State>().unwrap().unwrap();
        assert_eq!(back.state, state());
        assert_eq!(back.state.x.to_bits(), state().x.to_bits());
        assert_eq!(back.metrics, rows());
        assert_eq!(back.saved.progress, "epoch 3");
        assert_eq!(back.saved.files, ["moments.bin"]);
        assert_eq!(
            fs::read(back.saved.dir.join("moments.bin")).unwrap(),
            [1, 2, 3]
        );
    }

    #[test]
    fn a_new_generation_replaces_the_old_and_leftovers_are_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let cp = store(dir.path());
        fs::write(cp.file("a.bin").unwrap(), b"old").unwrap();
        cp.save("epoch 1", &[], &state()).unwrap();
        let mut s = state();
        s.epoch = 2;
        cp.save("epoch 2", &[], &s).unwrap();
        // a.bin belonged to generation 1 only.
        let gens: Vec<String> = fs::read_dir(cp.root())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        assert_eq!(gens, ["2"]);
        // A killed run's half-written generation is not read, and is cleared before reuse.
        let next = cp.root().join(PENDING);
        fs::create_dir_all(&next).unwrap();
        fs::write(next.join(STATE_FILE), "{\"form").unwrap();
        fs::write(next.join("junk.bin"), "x").unwrap();
        let fresh = store(dir.path());
        let back = fresh.load::<State>().unwrap().unwrap();
        assert_eq!(
            (back.state.epoch, back.saved.progress.as_str()),
            (2, "epoch 2")
        );
        fresh.file("b.bin").unwrap();
        assert!(!next.join("junk.bin").exists());
    }

    #[test]
    fn corrupt_foreign_or_mismatched_checkpoints_are_problems_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let cp = store(dir.path());
        fs::write(cp.file("m.bin").unwrap(), b"moments").unwrap();
        let saved = cp.save("epoch 3", &[], &state()).unwrap();
        let state_path = saved.dir.join(STATE_FILE);
        let good = fs::read(&state_path).unwrap();

        // Another key's checkpoint copied here.
        let other = Checkpoints::new(cp.root().to_path_buf(), "train", "def");
        match other.load::<State>() {
            Err(CheckpointProblem::Mismatch { key, .. }) => assert_eq!(key, "abc"),
            other => panic!("{other:?}"),
        }
        // State of another shape.
        #[derive(Debug, Deserialize)]
        #[allow(dead_code)]
        struct Other {
            weights: Vec<f64>,
        }
        match cp.load::<Other>() {
            Err(CheckpointProblem::State(p, m)) => {
                assert_eq!(p, state_path);
                assert!(m.contains("weights"), "{m}");
            }
            other => panic!("{other:?}"),
        }
        // A modified file.
        fs::write(saved.dir.join("m.bin"), b"moments!").unwrap();
        assert_eq!(
            cp.latest(),
            Err(CheckpointProblem::Corrupted(saved.dir.join("m.bin")))
        );
        fs::remove_file(saved.dir.join("m.bin")).unwrap();
        assert_eq!(
            cp.latest(),
            Err(CheckpointProblem::MissingFile(saved.dir.join("m.bin")))
        );
        // Truncated text, another format.
        fs::write(&state_path, &good[..good.len() / 2]).unwrap();
        assert!(matches!(
            cp.load::<State>(),
            Err(CheckpointProblem::Unreadable(..))
        ));
        let text = String::from_utf8(good).unwrap().replacen(
            &format!("\"format\": {CHECKPOINT_FORMAT}"),
            "\"format\": 99",
            1,
        );
        fs::write(&state_path, text).unwrap();
        let e = cp.load::<State>().unwrap_err();
        assert!(
            matches!(e, CheckpointProblem::Format { found: 99, .. }),
            "{e}"
        );
        assert!(e.to_string().contains("format 99"), "{e}");
    }

    #[test]
    fn a_state_that_json_cannot_hold_is_refused_when_saved() {
        let dir = tempfile::tempdir().unwrap();
        let cp = store(dir.path());
        let mut s = state();
        s.x = f64::NAN;
        let e = cp.save("epoch 3", &[], &s).unwrap_err();
        assert!(matches!(e, CheckpointError::NotRoundTrip { .. }), "{e}");
        assert!(e.to_string().contains("`train`"), "{e}");
        assert!(cp.latest().unwrap().is_none());
        for bad in ["", "a/b", "..", ".hidden", STATE_FILE] {
            assert!(
                matches!(cp.file(bad), Err(CheckpointError::BadName { .. })),
                "{bad}"
            );
        }
    }
}
