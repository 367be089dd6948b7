//! Content-addressed blobs named by the SHA-256 of their bytes (so names are always
//! server-made): on disk, `blobs/ab/cdef…`, written as temp file in `blobs/tmp` + fsync + rename;
//! or in an S3-compatible object store (`store::s3`), staged in the same local temp folder and
//! read back through a verified local cache.

use super::error::{Result, StoreError};
use super::s3::{BlobConfig, S3Blobs};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::fs::{self, File};
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

/// A committed blob: its id (lowercase hex SHA-256) and size in bytes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct BlobRef {
    /// Lowercase hex SHA-256 of the bytes; also the blob's name.
    pub sha256: String,
    /// Size in bytes.
    pub size: u64,
}

/// A stored blob as the garbage collector sees it.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct BlobInfo {
    pub id: String,
    pub size: u64,
    /// Since the blob was last committed (file mtime, or the object's `LastModified`).
    pub age: Duration,
}

/// The blob store: the local blob folder (`DATA_DIR/blobs`: the blobs themselves, or on S3 the
/// staging `tmp` and the verified read `cache`). Every method may block on I/O — on S3 on the
/// network —, so async code calls them from `spawn_blocking`. Cheap to clone.
#[derive(Clone, Debug)]
pub struct BlobStore {
    root: PathBuf,
    /// How many [`PinnedBlob`]s of this process hold each blob id.
    pins: Arc<Mutex<HashMap<String, usize>>>,
    /// The object store holding the blobs, when they are not in `root`.
    remote: Option<Arc<S3Blobs>>,
}

/// A blob committed by [`BlobStore::commit_pinned`] for a row that is not written yet. While it
/// lives, the garbage collector leaves the blob alone, and so does
/// [`super::Store::discard_unreferenced`] when another pin holds the same blob (two uploads of
/// the same bytes). Dropping it unpins.
#[derive(Debug)]
pub struct PinnedBlob {
    blob: BlobRef,
    pins: Arc<Mutex<HashMap<String, usize>>>,
}

impl PinnedBlob {
    /// The committed blob.
    pub fn blob(&self) -> &BlobRef {
        &self.blob
    }
}

impl Drop for PinnedBlob {
    fn drop(&mut self) {
        let mut pins = self.pins.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(n) = pins.get_mut(&self.blob.sha256) {
            *n -= 1;
            if *n == 0 {
                pins.remove(&self.blob.sha256);
            }
        }
    }
}

impl BlobStore {
    /// Opens (creating) `root` and `root/tmp`, removing temp files older than a day (left by a
    /// process that died mid-upload; younger ones may belong to another running process).
    pub(crate) fn open(root: PathBuf) -> io::Result<Self> {
        let tmp = root.join("tmp");
        fs::create_dir_all(&tmp)?;
        let day = std::time::Duration::from_secs(24 * 3600);
        for e in fs::read_dir(&tmp)?.flatten() {
            if modified_longer_ago(&e, day)
                && let Err(err) = fs::remove_file(e.path())
            {
                tracing::warn!(path = %e.path().display(), %err, "could not remove a stale temp file");
            }
        }
        Ok(BlobStore {
            root,
            pins: Arc::default(),
            remote: None,
        })
    }

    /// Opens the blob store `config` names, with `root` as its local folder (the blobs
    /// themselves, or the staging and cache folders of an object store). Sends nothing: see
    /// [`Self::check`].
    pub fn open_with(root: PathBuf, config: &BlobConfig) -> Result<Self> {
        let mut store = Self::open(root)?;
        if let BlobConfig::S3 { url, options } = config {
            store.remote = Some(Arc::new(S3Blobs::new(&store.root, url, options)?));
        }
        Ok(store)
    }

    /// Where the blobs are, for messages: the folder or `s3://BUCKET/PREFIX at ENDPOINT`
    /// (never a secret).
    pub fn describe(&self) -> String {
        match &self.remote {
            Some(r) => r.describe(),
            None => self.root.display().to_string(),
        }
    }

    /// The object store side (tests tamper with objects through it).
    #[cfg(test)]
    pub(crate) fn remote(&self) -> Option<&S3Blobs> {
        self.remote.as_deref()
    }

    /// Whether the blobs are in an object store (shared by every process that names it).
    pub fn is_remote(&self) -> bool {
        self.remote.is_some()
    }

    /// Checks that the store answers (S3: a LIST under the prefix; a folder: nothing to do).
    pub fn check(&self) -> io::Result<()> {
        match &self.remote {
            Some(r) => r.check(),
            None => Ok(()),
        }
    }

    /// A new temporary file in `blobs/tmp` (same file system as the blobs, so [`Self::commit`]
    /// is a rename). Dropping it without committing deletes it.
    pub fn temp_file(&self) -> io::Result<tempfile::NamedTempFile> {
        tempfile::NamedTempFile::new_in(self.root.join("tmp"))
    }

    /// Hashes the temp file's bytes, fsyncs it and renames it to its content address. Committing
    /// bytes that are already stored keeps the existing file (idempotent).
    pub fn commit(&self, mut tmp: tempfile::NamedTempFile) -> io::Result<BlobRef> {
        tmp.as_file_mut().flush()?;
        let (sha256, size) = hash_file(tmp.as_file_mut())?;
        self.place(tmp, sha256, size)
    }

    /// Moves a hashed temp file to its content address (see [`Self::commit`]).
    fn place(
        &self,
        tmp: tempfile::NamedTempFile,
        sha256: String,
        size: u64,
    ) -> io::Result<BlobRef> {
        if let Some(r) = &self.remote {
            // Uploaded (or touched) before this returns; the temp file goes when dropped.
            r.commit(tmp.as_file(), &sha256, size)?;
            return Ok(BlobRef { sha256, size });
        }
        let dest = self.location(&sha256);
        // An existing file of another size is a truncated leftover: replaced below. An existing
        // complete one is touched, so the garbage collector's age rule sees it as new until the
        // row that references it is written.
        if fs::metadata(&dest).is_ok_and(|m| m.len() == size) {
            File::options()
                .write(true)
                .open(&dest)?
                .set_modified(std::time::SystemTime::now())?;
            return Ok(BlobRef { sha256, size });
        }
        tmp.as_file().sync_all()?;
        let dir = dest.parent().unwrap_or(&self.root).to_path_buf();
        fs::create_dir_all(&dir)?;
        tmp.persist(&dest).map_err(|e| e.error)?;
        sync_dir(&dir)?;
        Ok(BlobRef { sha256, size })
    }

    /// [`Self::commit`], pinning the blob (see [`PinnedBlob`]) before it is renamed into place, so
    /// that a concurrent `remove_if_only_pin` of the same bytes cannot remove it under us.
    pub fn commit_pinned(&self, mut tmp: tempfile::NamedTempFile) -> io::Result<PinnedBlob> {
        tmp.as_file_mut().flush()?;
        let (sha256, size) = hash_file(tmp.as_file_mut())?;
        *self
            .pins
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(sha256.clone())
            .or_default() += 1;
        // Unpinned again by the drop if placing fails.
        let pin = PinnedBlob {
            blob: BlobRef {
                sha256: sha256.clone(),
                size,
            },
            pins: self.pins.clone(),
        };
        self.place(tmp, sha256, size)?;
        Ok(pin)
    }

    /// Whether a [`PinnedBlob`] of this process holds blob `sha256`.
    pub(crate) fn is_pinned(&self, sha256: &str) -> bool {
        self.pins
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .contains_key(sha256)
    }

    /// Removes `pin`'s blob file unless pins other than the caller's `own` ones hold it too;
    /// `Ok(true)` when removed. The caller has checked that no row references the blob (and holds
    /// the database's write lock, so that none can be written meanwhile).
    pub(crate) fn remove_if_only_pin(&self, pin: &PinnedBlob, own: usize) -> io::Result<bool> {
        let pins = self.pins.lock().unwrap_or_else(PoisonError::into_inner);
        if pins.get(&pin.blob.sha256).copied().unwrap_or(0) > own {
            return Ok(false);
        }
        self.remove(&pin.blob.sha256)
    }

    /// Removes blob `sha256` (the file, or the object and its cached copy); `Ok(false)` when
    /// it was not there.
    fn remove(&self, sha256: &str) -> io::Result<bool> {
        if let Some(r) = &self.remote {
            return r.remove(sha256);
        }
        let path = self.location(sha256);
        match fs::remove_file(&path) {
            Ok(()) => {
                if let Some(dir) = path.parent() {
                    sync_dir(dir)?;
                }
                Ok(true)
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// Stores `bytes` (temp file + fsync + rename).
    pub fn put_bytes(&self, bytes: &[u8]) -> io::Result<BlobRef> {
        let mut tmp = self.temp_file()?;
        tmp.write_all(bytes)?;
        self.commit(tmp)
    }

    /// The path of a local file holding an existing blob: the blob's own file, or on S3 its
    /// verified cached copy (downloaded when missing; `BlobCorrupt` when the object's bytes do
    /// not hash to its name). `Invalid` for anything but 64 lowercase hex digits, `NotFound`
    /// when no such blob is stored.
    pub fn path(&self, sha256: &str) -> Result<PathBuf> {
        validate_id(sha256)?;
        if let Some(r) = &self.remote {
            return r.fetch(sha256);
        }
        let p = self.location(sha256);
        match fs::metadata(&p) {
            Ok(m) if m.is_file() => Ok(p),
            Ok(_) => Err(StoreError::NotFound),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Err(StoreError::NotFound),
            Err(e) => Err(e.into()),
        }
    }

    /// The bytes of a blob (on S3 verified as [`Self::path`] does).
    pub fn read(&self, sha256: &str) -> Result<Vec<u8>> {
        validate_id(sha256)?;
        if self.remote.is_some() {
            return Ok(fs::read(self.path(sha256)?)?);
        }
        match fs::read(self.location(sha256)) {
            Ok(b) => Ok(b),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Err(StoreError::NotFound),
            Err(e) => Err(e.into()),
        }
    }

    /// Size of a stored blob (`NotFound` when missing).
    pub fn size_of(&self, sha256: &str) -> Result<u64> {
        validate_id(sha256)?;
        if let Some(r) = &self.remote {
            return r.size_of(sha256);
        }
        Ok(fs::metadata(self.path(sha256)?)?.len())
    }

    /// Removes blob `sha256` if it is at least `min_age` old now and no [`PinnedBlob`] of this
    /// process holds it; its size when removed. The garbage collector's last check, made under
    /// the database's write lock: a commit of the same bytes by any process since the blob was
    /// listed made it young again.
    pub(crate) fn remove_if_old(&self, sha256: &str, min_age: Duration) -> io::Result<Option<u64>> {
        let pins = self.pins.lock().unwrap_or_else(PoisonError::into_inner);
        if pins.contains_key(sha256) {
            return Ok(None);
        }
        let (size, age) = match &self.remote {
            Some(r) => match r.stat(sha256)? {
                Some(x) => x,
                None => return Ok(None),
            },
            None => match fs::metadata(self.location(sha256)) {
                Ok(m) => (m.len(), file_age(&m)),
                Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
                Err(e) => return Err(e),
            },
        };
        if age < min_age {
            return Ok(None);
        }
        Ok(self.remove(sha256)?.then_some(size))
    }

    /// Removes cached copies of S3 blobs older than `max_age` (nothing for a local folder).
    pub(crate) fn prune_cache(&self, max_age: Duration) {
        if let Some(r) = &self.remote {
            r.prune_cache(max_age);
        }
    }

    /// Every committed blob with its size and age (files that are not blobs are skipped).
    pub fn list(&self) -> io::Result<Vec<BlobInfo>> {
        if let Some(r) = &self.remote {
            return Ok(r
                .list()?
                .into_iter()
                .map(|(id, size, age)| BlobInfo { id, size, age })
                .collect());
        }
        let mut out = Vec::new();
        for dir in fs::read_dir(&self.root)?.flatten() {
            let head = dir.file_name().to_string_lossy().into_owned();
            // `tmp` and `cache` have longer names.
            if head.len() != 2 || !dir.file_type().is_ok_and(|t| t.is_dir()) {
                continue;
            }
            for f in fs::read_dir(dir.path())?.flatten() {
                let id = format!("{head}{}", f.file_name().to_string_lossy());
                let Ok(meta) = f.metadata() else { continue };
                if !is_blob_id(&id) || !meta.is_file() {
                    continue;
                }
                out.push(BlobInfo {
                    id,
                    size: meta.len(),
                    age: file_age(&meta),
                });
            }
        }
        out.sort();
        Ok(out)
    }

    /// Where a (validated) id lives: `root/ab/cdef…`.
    fn location(&self, sha256: &str) -> PathBuf {
        location(&self.root, sha256)
    }
}

/// Since a file was last modified (0 for a time in the future).
fn file_age(meta: &fs::Metadata) -> Duration {
    meta.modified()
        .ok()
        .and_then(|t| t.elapsed().ok())
        .unwrap_or_default()
}

/// Whether directory entry `e` was last modified longer than `age` ago (`false` when its time
/// cannot be read).
pub(super) fn modified_longer_ago(e: &fs::DirEntry, age: std::time::Duration) -> bool {
    e.metadata()
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.elapsed().ok())
        .is_some_and(|elapsed| elapsed > age)
}

/// Whether `id` is 64 lowercase hex digits.
pub(crate) fn is_blob_id(id: &str) -> bool {
    id.len() == 64 && id.bytes().all(|c| matches!(c, b'0'..=b'9' | b'a'..=b'f'))
}

fn validate_id(id: &str) -> Result<()> {
    if is_blob_id(id) {
        Ok(())
    } else {
        Err(StoreError::invalid(
            "blob id must be 64 lowercase hex digits",
        ))
    }
}

/// Where blob `sha256` (64 hex digits) lives under a blob folder `root`: `root/ab/cdef…`.
pub(super) fn location(root: &Path, sha256: &str) -> PathBuf {
    let (head, tail) = sha256.split_at(2);
    root.join(head).join(tail)
}

/// SHA-256 (lowercase hex) and size of a file's bytes, read from its start.
pub(super) fn hash_file(f: &mut File) -> io::Result<(String, u64)> {
    f.seek(SeekFrom::Start(0))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut size = 0u64;
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    Ok((hex::encode(hasher.finalize()), size))
}

/// Fsyncs a directory so that a rename into it survives a crash (no-op where unsupported).
pub(crate) fn sync_dir(dir: &Path) -> io::Result<()> {
    #[cfg(unix)]
    {
        File::open(dir)?.sync_all()?;
    }
    #[cfg(not(unix))]
    let _ = dir;
    Ok(())
}
