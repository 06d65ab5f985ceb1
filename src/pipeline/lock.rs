//! One runner per work directory: an OS file lock on `.pipe/lock`.
//!
//! The lock is held by the open file, so the OS releases it when the process ends, however it
//! ends (no stale lock after a crash). The file's text says who holds it.

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Held for the duration of a run; dropping it releases the lock.
#[derive(Debug)]
pub struct WorkdirLock {
    _file: File,
    path: PathBuf,
}

/// Why the lock could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another process holds it.
    #[error(
        "another pipe runner is using {dir} ({holder}); wait for it to finish or stop it, then run again"
    )]
    Held {
        /// The `.pipe` directory.
        dir: PathBuf,
        /// What the holder wrote (pid, command, start time).
        holder: String,
    },
    /// The lock file could not be opened.
    #[error("{path}: cannot open the lock file: {source}")]
    Io {
        /// The lock file.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
}

impl WorkdirLock {
    /// Take the lock of the `.pipe` directory `root`, recording `command` as the holder.
    pub fn acquire(root: &Path, command: &str) -> Result<Self, LockError> {
        let path = root.join("lock");
        let io = |source| LockError::Io {
            path: path.clone(),
            source,
        };
        fs::create_dir_all(root).map_err(io)?;
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io)?;
        // A holder that is just finishing (or a forked child that has not yet exec'd and still
        // shares the descriptor) releases the lock within moments: retry briefly first.
        let mut attempt = file.try_lock();
        let deadline = std::time::Instant::now() + std::time::Duration::from_millis(500);
        while matches!(attempt, Err(fs::TryLockError::WouldBlock))
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(std::time::Duration::from_millis(20));
            attempt = file.try_lock();
        }
        match attempt {
            Ok(()) => {}
            Err(fs::TryLockError::WouldBlock) => {
                let holder = fs::read_to_string(&path)
                    .unwrap_or_default()
                    .trim()
                    .to_string();
                return Err(LockError::Held {
                    dir: root.to_path_buf(),
                    holder: if holder.is_empty() {
                        "holder unknown".into()
                    } else {
                        holder
                    },
                });
            }
            Err(fs::TryLockError::Error(e)) => return Err(io(e)),
        }
        let since = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        file.set_len(0).map_err(io)?;
        write!(
            file,
            "pid {}, `{command}`, since unix time {since}",
            std::process::id()
        )
        .map_err(io)?;
        file.flush().map_err(io)?;
        Ok(Self { _file: file, path })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}
