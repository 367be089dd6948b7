//! The data folder's advisory lock, `splatmark.lock`: every running `splatmark serve` holds it
//! shared, `splatmark keys rotate-master` exclusively. A server keeps the master key in memory
//! and seals each new key and job with it; a rotation beside a live server would re-seal the
//! database under the new key while the server went on sealing under the old one, and those rows
//! would no longer open after a restart. The lock is the kernel's (`flock`): a process killed
//! with `kill -9` releases it with its file descriptors, so nothing stale is ever left to clean.

use std::fs::{File, OpenOptions, TryLockError};
use std::path::{Path, PathBuf};

/// The lock file's name inside the data folder.
pub const LOCK_FILE: &str = "splatmark.lock";

/// How a process uses the data folder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LockMode {
    /// A server: several may share the folder.
    Shared,
    /// A maintenance command that must run alone (master-key rotation).
    Exclusive,
}

/// Why the lock could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    #[error(
        "the data folder {0} is in use by another splatmark process (a running `serve`, or a \
         master-key rotation): stop it first"
    )]
    Busy(PathBuf),
    #[error("cannot open or lock {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// A held lock; released when dropped (or when the process dies).
#[derive(Debug)]
pub struct DataDirLock {
    _file: File,
}

impl DataDirLock {
    /// Takes the lock of `dir` (which must exist) in `mode`, without waiting.
    pub fn acquire(dir: &Path, mode: LockMode) -> Result<Self, LockError> {
        let path = dir.join(LOCK_FILE);
        let io = |source| LockError::Io {
            path: path.clone(),
            source,
        };
        let file = OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)
            .map_err(io)?;
        let taken = match mode {
            LockMode::Shared => file.try_lock_shared(),
            LockMode::Exclusive => file.try_lock(),
        };
        match taken {
            Ok(()) => Ok(Self { _file: file }),
            Err(TryLockError::WouldBlock) => Err(LockError::Busy(dir.to_path_buf())),
            Err(TryLockError::Error(e)) => Err(io(e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn servers_share_the_folder_and_a_rotation_waits_for_all_of_them() {
        let dir = tempfile::tempdir().unwrap();
        let a = DataDirLock::acquire(dir.path(), LockMode::Shared).unwrap();
        let b = DataDirLock::acquire(dir.path(), LockMode::Shared).unwrap();
        let busy = DataDirLock::acquire(dir.path(), LockMode::Exclusive).unwrap_err();
        assert!(matches!(busy, LockError::Busy(_)), "{busy}");
        assert!(busy.to_string().contains("stop it first"));
        drop(a);
        assert!(DataDirLock::acquire(dir.path(), LockMode::Exclusive).is_err());
        drop(b);
        let rotation = DataDirLock::acquire(dir.path(), LockMode::Exclusive).unwrap();
        // While a rotation runs, no server starts.
        assert!(matches!(
            DataDirLock::acquire(dir.path(), LockMode::Shared),
            Err(LockError::Busy(_))
        ));
        drop(rotation);
        DataDirLock::acquire(dir.path(), LockMode::Shared).unwrap();
    }

    #[test]
    fn a_missing_folder_is_an_io_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let gone = dir.path().join("nope");
        let e = DataDirLock::acquire(&gone, LockMode::Shared).unwrap_err();
        assert!(matches!(e, LockError::Io { .. }));
        assert!(e.to_string().contains(LOCK_FILE));
    }
}
