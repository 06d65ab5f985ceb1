//! Content-addressed cache of stage outputs (ARCHITECTURE §4).
//!
//! Key = blake3 of the canonical JSON (sorted keys, floats as shortest round-trip text) of a
//! [`KeyMaterial`]: key-format version, stage kind and code version, resolved parameters, the
//! scene fields the stage reads, upstream keys (Merkle chaining), content hashes of external
//! inputs by logical name, and the output schema versions. Nothing else: not thread count,
//! paths, hosts or times.
//!
//! An entry `.pipe/cache/<stage>-<key>/` is built in `.pipe/tmp/` and renamed into place, so it
//! exists whole or not at all; its `manifest.json` lists every output with its blake3 hash and
//! size, and an entry whose files do not match is reported and treated as missing.

use std::collections::BTreeMap;
use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

/// Bumped when the key recipe itself changes.
pub const KEY_FORMAT: u32 = 1;

/// Everything a stage's output depends on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeyMaterial {
    /// [`KEY_FORMAT`].
    pub key_format: u32,
    /// Stage kind.
    pub kind: String,
    /// Stage code version.
    pub version: u32,
    /// Resolved parameters.
    pub params: Value,
    /// Scene fields the stage reads.
    pub scene: Value,
    /// Upstream stage name → its key.
    pub upstream: BTreeMap<String, String>,
    /// Logical input name → blake3 of its content.
    pub inputs: BTreeMap<String, String>,
    /// Output table → schema version.
    pub schemas: BTreeMap<String, u32>,
}

impl KeyMaterial {
    /// The cache key: blake3 of the canonical encoding, hex.
    pub fn key(&self) -> String {
        let v = serde_json::to_value(self).expect("key material is plain data");
        debug_assert!(v.is_object());
        blake3::hash(canonical_json(&v).as_bytes())
            .to_hex()
            .to_string()
    }
}

/// Canonical JSON text: object keys sorted, no whitespace, floats in shortest round-trip form.
pub fn canonical_json(v: &Value) -> String {
    fn sorted(v: &Value) -> Value {
        match v {
            Value::Object(m) => {
                let mut keys: Vec<&String> = m.keys().collect();
                keys.sort();
                Value::Object(
                    keys.into_iter()
                        .map(|k| (k.clone(), sorted(&m[k])))
                        .collect(),
                )
            }
            Value::Array(a) => Value::Array(a.iter().map(sorted).collect()),
            other => other.clone(),
        }
    }
    // serde_json prints floats with ryu: the shortest text that round-trips.
    serde_json::to_string(&sorted(v)).expect("a Value always serialises")
}

/// One output file of an entry.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputFile {
    /// blake3, hex.
    pub blake3: String,
    /// Bytes.
    pub size: u64,
}

/// `manifest.json` of an entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// The key (directory name suffix).
    pub key: String,
    /// Stage name in the pipeline that produced it.
    pub stage: String,
    /// What the key was computed from.
    pub key_material: KeyMaterial,
    /// Relative path → hash and size.
    pub outputs: BTreeMap<String, OutputFile>,
    /// Wall-clock time of the stage, seconds (summed over the runs of a resumed stage).
    pub wall_s: f64,
    /// Peak resident memory of the process while the stage ran (Linux `VmHWM`, reset when the
    /// stage starts), bytes (0 if unknown).
    pub peak_rss_bytes: u64,
    /// `pipe` crate version that wrote it.
    pub pipe_version: String,
    /// Worker threads used (informational; results do not depend on it).
    pub threads: usize,
    /// Unix time of the commit, seconds.
    pub created_unix_s: u64,
    /// The warnings the stage gave while it ran (the last run of a resumed stage).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// Why an entry cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EntryProblem {
    /// No entry for this key.
    #[error("not cached")]
    Missing,
    /// `manifest.json` missing or unreadable.
    #[error("{0}: manifest unreadable ({1})")]
    BadManifest(PathBuf, String),
    /// An output listed in the manifest is missing.
    #[error("{0}: output file missing")]
    MissingOutput(PathBuf),
    /// An output's content does not match its recorded hash or size.
    #[error("{0}: content does not match the manifest (corrupted or modified)")]
    Corrupted(PathBuf),
}

/// Errors of the cache store itself (I/O).
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// A file-system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The path involved.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// blake3 of a file's content, hex.
pub fn hash_file(path: &Path) -> std::io::Result<(String, u64)> {
    let mut f = fs::File::open(path)?;
    let mut hasher = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut size = 0u64;
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        size += n as u64;
        hasher.update(&buf[..n]);
    }
    Ok((hasher.finalize().to_hex().to_string(), size))
}

/// Write `bytes` to `path` atomically (temp file in the same folder + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("file"),
        std::process::id()
    ));
    fs::write(&tmp, bytes)?;
    fs::rename(&tmp, path)
}

/// The cache directory `<workdir>/.pipe`.
#[derive(Debug, Clone)]
pub struct Store {
    root: PathBuf,
}

impl Store {
    /// The store under `workdir/.pipe`.
    pub fn new(workdir: &Path) -> Self {
        Self {
            root: workdir.join(".pipe"),
        }
    }

    /// `.pipe`.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// `.pipe/cache`.
    pub fn cache_dir(&self) -> PathBuf {
        self.root.join("cache")
    }

    /// Where the entry of `stage` with `key` lives.
    pub fn entry_dir(&self, stage: &str, key: &str) -> PathBuf {
        self.cache_dir().join(format!("{stage}-{key}"))
    }

    /// `.pipe/checkpoints`: checkpoints of unfinished stages (see `checkpoint`); never entries,
    /// and not cleared with the temporary directory.
    pub fn checkpoints_dir(&self) -> PathBuf {
        self.root.join("checkpoints")
    }

    /// Where the checkpoints of `stage` with `key` live.
    pub fn checkpoint_dir(&self, stage: &str, key: &str) -> PathBuf {
        self.checkpoints_dir().join(format!("{stage}-{key}"))
    }

    /// Load and verify an entry: every output present with the recorded hash.
    pub fn verify(&self, stage: &str, key: &str) -> Result<Manifest, EntryProblem> {
        let dir = self.entry_dir(stage, key);
        if !dir.is_dir() {
            return Err(EntryProblem::Missing);
        }
        let mpath = dir.join("manifest.json");
        let manifest: Manifest = fs::read(&mpath)
            .map_err(|e| e.to_string())
            .and_then(|b| serde_json::from_slice(&b).map_err(|e| e.to_string()))
            .map_err(|e| EntryProblem::BadManifest(mpath.clone(), e))?;
        if manifest.key != key {
            return Err(EntryProblem::BadManifest(
                mpath,
                format!("it records key {}", manifest.key),
            ));
        }
        for (rel, out) in &manifest.outputs {
            let p = dir.join(rel);
            match hash_file(&p) {
                Err(_) => return Err(EntryProblem::MissingOutput(p)),
                Ok((h, size)) if h != out.blake3 || size != out.size => {
                    return Err(EntryProblem::Corrupted(p));
                }
                Ok(_) => {}
            }
        }
        Ok(manifest)
    }

    /// A fresh temporary directory to build an entry in.
    pub fn begin(&self, stage: &str, key: &str) -> Result<PathBuf, CacheError> {
        let tmp = self.root.join("tmp").join(format!(
            "{stage}-{}-{}",
            &key[..16.min(key.len())],
            std::process::id()
        ));
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(io_err(&tmp))?;
        }
        fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
        Ok(tmp)
    }

    /// Hash every file in `tmp`, write the manifest, and rename `tmp` into place.
    pub fn commit(&self, tmp: &Path, mut manifest: Manifest) -> Result<Manifest, CacheError> {
        manifest.outputs.clear();
        for rel in list_files(tmp).map_err(io_err(tmp))? {
            if rel == "manifest.json" {
                continue;
            }
            let (blake3, size) = hash_file(&tmp.join(&rel)).map_err(io_err(&tmp.join(&rel)))?;
            manifest.outputs.insert(rel, OutputFile { blake3, size });
        }
        let mpath = tmp.join("manifest.json");
        let text = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
        write_atomic(&mpath, &text).map_err(io_err(&mpath))?;
        let dest = self.entry_dir(&manifest.stage, &manifest.key);
        fs::create_dir_all(self.cache_dir()).map_err(io_err(&self.cache_dir()))?;
        if dest.exists() {
            // A forced re-run or a corrupted entry: move the old one aside first.
            let trash = self.root.join("tmp").join(format!(
                "old-{}-{}",
                manifest.stage,
                std::process::id()
            ));
            let _ = fs::remove_dir_all(&trash);
            fs::rename(&dest, &trash).map_err(io_err(&dest))?;
            let _ = fs::remove_dir_all(&trash);
        }
        fs::rename(tmp, &dest).map_err(io_err(&dest))?;
        Ok(manifest)
    }

    /// Remove an entry (e.g. a corrupted one).
    pub fn remove(&self, stage: &str, key: &str) -> Result<(), CacheError> {
        let dir = self.entry_dir(stage, key);
        if dir.exists() {
            fs::remove_dir_all(&dir).map_err(io_err(&dir))?;
        }
        Ok(())
    }

    /// Names (`<stage>-<key>`) of all entries.
    pub fn entries(&self) -> Result<Vec<String>, CacheError> {
        subdirectories(&self.cache_dir())
    }

    /// Names (`<stage>-<key>`) of all checkpoint directories.
    pub fn checkpoints(&self) -> Result<Vec<String>, CacheError> {
        subdirectories(&self.checkpoints_dir())
    }

    /// Delete leftovers of interrupted runs (caller holds the work-directory lock).
    pub fn clear_tmp(&self) -> Result<(), CacheError> {
        let tmp = self.root.join("tmp");
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(io_err(&tmp))?;
        }
        Ok(())
    }
}

/// Names of the directories in `dir`, sorted (none if it does not exist).
fn subdirectories(dir: &Path) -> Result<Vec<String>, CacheError> {
    if !dir.exists() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for e in fs::read_dir(dir).map_err(io_err(dir))? {
        let e = e.map_err(io_err(dir))?;
        if e.path().is_dir() {
            out.push(e.file_name().to_string_lossy().to_string());
        }
    }
    out.sort();
    Ok(out)
}

/// Relative paths (with `/`) of all files under `dir`, sorted.
pub fn list_files(dir: &Path) -> std::io::Result<Vec<String>> {
    fn walk(base: &Path, dir: &Path, out: &mut Vec<String>) -> std::io::Result<()> {
        for e in fs::read_dir(dir)? {
            let e = e?;
            let p = e.path();
            if e.file_type()?.is_dir() {
                walk(base, &p, out)?;
            } else {
                let rel = p.strip_prefix(base).expect("under base");
                out.push(
                    rel.components()
                        .map(|c| c.as_os_str().to_string_lossy())
                        .collect::<Vec<_>>()
                        .join("/"),
                );
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out)?;
    out.sort();
    Ok(out)
}

/// Remembers content hashes of input files by (size, mtime, inode) so unchanged inputs are not
/// re-hashed on every `pipe status` / `pipe run`.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct StatCache {
    entries: BTreeMap<String, (u64, i128, u64, String)>,
    #[serde(skip)]
    dirty: bool,
}

impl StatCache {
    /// Load from `path` (empty if missing or unreadable).
    pub fn load(path: &Path) -> Self {
        fs::read(path)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default()
    }

    /// Save if anything changed (best effort: a lost stat cache only costs re-hashing).
    pub fn save(&self, path: &Path) {
        if self.dirty {
            let _ = write_atomic(path, &serde_json::to_vec(self).expect("serialises"));
        }
    }

    /// Content hash of `path`, from the cache when size, mtime and inode are unchanged.
    pub fn hash(&mut self, path: &Path) -> std::io::Result<String> {
        use std::os::unix::fs::MetadataExt;
        let md = fs::metadata(path)?;
        let abs = fs::canonicalize(path)?.to_string_lossy().to_string();
        let mtime = i128::from(md.mtime()) * 1_000_000_000 + i128::from(md.mtime_nsec());
        if let Some((size, t, ino, h)) = self.entries.get(&abs)
            && *size == md.size()
            && *t == mtime
            && *ino == md.ino()
        {
            return Ok(h.clone());
        }
        let (h, _) = hash_file(path)?;
        self.entries
            .insert(abs, (md.size(), mtime, md.ino(), h.clone()));
        self.dirty = true;
        Ok(h)
    }
}

/// Reset the process's peak resident set size to its current size (Linux: `5` written to
/// `/proc/self/clear_refs`), so [`peak_rss_bytes`] then gives the peak since this call.
/// Best effort: where the file cannot be written, the peak stays the process's since start.
pub fn reset_peak_rss() {
    let _ = fs::write("/proc/self/clear_refs", "5");
}

/// Peak resident set size of this process, bytes, since it started or since the last
/// [`reset_peak_rss`] (Linux `VmHWM`; 0 elsewhere).
pub fn peak_rss_bytes() -> u64 {
    fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map(|kb| kb * 1024)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn material() -> KeyMaterial {
        KeyMaterial {
            key_format: KEY_FORMAT,
            kind: "material".into(),
            version: 1,
            params: serde_json::json!({"grid": 32, "lr": 0.1, "b": [1, 2]}),
            scene: Value::Null,
            upstream: BTreeMap::new(),
            inputs: BTreeMap::new(),
            schemas: BTreeMap::new(),
        }
    }

    #[test]
    fn key_ignores_key_order_but_not_values() {
        let a = material();
        let mut b = material();
        b.params = serde_json::from_str(r#"{"b": [1, 2], "lr": 0.1, "grid": 32}"#).unwrap();
        assert_eq!(a.key(), b.key());
        b.params["grid"] = 64.into();
        assert_ne!(a.key(), b.key());
        let mut c = material();
        c.version = 2;
        assert_ne!(a.key(), c.key());
    }

    #[test]
    fn canonical_floats_round_trip() {
        let v = serde_json::json!({"x": 0.1f64, "y": 1e-7f64});
        assert_eq!(canonical_json(&v), r#"{"x":0.1,"y":1e-7}"#);
    }
}
