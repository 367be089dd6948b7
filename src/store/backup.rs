//! Backup and restore of a data folder while the service runs.
//!
//! A backup is a folder: `splatmark.db` (a consistent snapshot taken with SQLite's
//! `VACUUM INTO`, readers and writers of the live database carry on), `blobs/` (every blob the
//! snapshot's assets reference, hashed while copied) and `manifest.json` (written last, so its
//! presence means the backup is whole: the database's and every blob's SHA-256 and size, the
//! row counts and the audit chain's head). Keys stay sealed under the master key, which is
//! not part of a backup: restoring needs the same master key (checked when the restored store
//! opens).

use std::collections::BTreeSet;
use std::fs;
use std::io::{self, Read, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use sqlx::sqlite::{SqliteConnectOptions, SqlitePoolOptions};

use super::blobs::BlobStore;
use super::error::{Result, StoreError};
use super::{BLOB_DIR, DB_FILE};

/// Name of the manifest inside a backup folder.
pub const MANIFEST: &str = "manifest.json";

/// What a backup holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// `splatmark` version that wrote it.
    pub version: String,
    /// When the snapshot was taken (RFC 3339 UTC).
    pub created_at: String,
    pub database: FileEntry,
    /// Every referenced blob, by id (its SHA-256).
    pub blobs: Vec<FileEntry>,
    pub assets: u64,
    pub audit_rows: u64,
    /// Hash of the snapshot's last audit row (64 zeros when empty).
    pub audit_head: String,
}

/// A file of the backup: its SHA-256 and size.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileEntry {
    pub sha256: String,
    pub size: u64,
}

fn invalid(msg: impl Into<String>) -> StoreError {
    StoreError::Invalid(msg.into())
}

/// Copies `from` to `to`, returning the bytes' SHA-256 (lowercase hex) and size; `to` is
/// fsynced.
fn copy_hashed(from: &Path, to: &Path) -> io::Result<FileEntry> {
    let mut src = fs::File::open(from)?;
    let mut dst = fs::File::create(to)?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut size = 0u64;
    loop {
        let n = src.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        dst.write_all(&buf[..n])?;
        size += n as u64;
    }
    dst.sync_all()?;
    Ok(FileEntry {
        sha256: hex::encode(h.finalize()),
        size,
    })
}

/// Backs up the data folder `data_dir` (the service may be running) into `out`, which must
/// not exist or be empty.
pub async fn backup(data_dir: &Path, out: &Path) -> Result<Manifest> {
    let db = data_dir.join(DB_FILE);
    if !db.is_file() {
        return Err(invalid(format!("no database in {}", data_dir.display())));
    }
    if out.exists() && fs::read_dir(out)?.next().is_some() {
        return Err(invalid(format!("{} is not empty", out.display())));
    }
    fs::create_dir_all(out.join(BLOB_DIR))?;
    let snapshot = out.join(DB_FILE);
    let live = SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(
            SqliteConnectOptions::new()
                .filename(&db)
                .busy_timeout(std::time::Duration::from_secs(30)),
        )
        .await?;
    sqlx::query("VACUUM INTO ?")
        .bind(snapshot.to_string_lossy().into_owned())
        .execute(&live)
        .await?;
    live.close().await;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        fs::set_permissions(&snapshot, fs::Permissions::from_mode(0o600))?;
    }

    // What the snapshot references, and its counts.
    let snap = SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(
            SqliteConnectOptions::new()
                .filename(&snapshot)
                .read_only(true),
        )
        .await?;
    let referenced: BTreeSet<String> = sqlx::query_scalar(
        "SELECT sha256 FROM assets UNION SELECT cameras_sha256 FROM assets \
         WHERE cameras_sha256 IS NOT NULL",
    )
    .fetch_all(&snap)
    .await?
    .into_iter()
    .collect();
    let assets: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM assets")
        .fetch_one(&snap)
        .await?;
    let audit_rows: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM audit")
        .fetch_one(&snap)
        .await?;
    let audit_head: Option<String> =
        sqlx::query_scalar("SELECT hash FROM audit ORDER BY id DESC LIMIT 1")
            .fetch_optional(&snap)
            .await?;
    snap.close().await;

    let (src_root, dst_root) = (data_dir.join(BLOB_DIR), out.join(BLOB_DIR));
    let blobs = tokio::task::spawn_blocking(move || -> Result<Vec<FileEntry>> {
        let mut entries = Vec::with_capacity(referenced.len());
        for id in &referenced {
            if id.len() != 64 || !id.bytes().all(|c| c.is_ascii_hexdigit()) {
                return Err(invalid(format!(
                    "the database references a bad blob id {id:?}"
                )));
            }
            let to = super::blobs::location(&dst_root, id);
            fs::create_dir_all(to.parent().expect("blob paths have a parent"))?;
            let e = copy_hashed(&super::blobs::location(&src_root, id), &to)
                .map_err(|e| invalid(format!("blob {id} referenced by the database: {e}")))?;
            if &e.sha256 != id {
                return Err(invalid(format!(
                    "blob {id} does not hash to its name (it hashes to {}): the live blob store \
                     is damaged",
                    e.sha256
                )));
            }
            entries.push(e);
        }
        Ok(entries)
    })
    .await
    .map_err(|e| StoreError::Io(io::Error::other(e)))??;
    let database = {
        let s = snapshot.clone();
        tokio::task::spawn_blocking(move || hash_file(&s))
            .await
            .map_err(|e| StoreError::Io(io::Error::other(e)))??
    };
    let manifest = Manifest {
        version: env!("CARGO_PKG_VERSION").to_string(),
        created_at: super::time::now(),
        database,
        blobs,
        assets: assets as u64,
        audit_rows: audit_rows as u64,
        audit_head: audit_head.unwrap_or_else(|| super::GENESIS_HASH.to_string()),
    };
    let tmp = out.join(".manifest.json.tmp");
    fs::write(
        &tmp,
        serde_json::to_vec_pretty(&manifest).expect("serialisable"),
    )?;
    fs::File::open(&tmp)?.sync_all()?;
    fs::rename(&tmp, out.join(MANIFEST))?;
    Ok(manifest)
}

fn hash_file(p: &Path) -> io::Result<FileEntry> {
    let (sha256, size) = super::blobs::hash_file(&mut fs::File::open(p)?)?;
    Ok(FileEntry { sha256, size })
}

/// Restores the backup folder `from` into `data_dir`, which must hold no database yet: the
/// database and every blob are checked against the manifest (SHA-256 and size) as they are
/// copied; nothing is left in `data_dir` when a check fails. Open the result with
/// [`super::Store::open`] and the master key the backup was taken under.
pub async fn restore(from: &Path, data_dir: &Path) -> Result<Manifest> {
    let text = fs::read(from.join(MANIFEST)).map_err(|e| {
        invalid(format!(
            "{} has no {MANIFEST} ({e}): not a backup, or an unfinished one",
            from.display()
        ))
    })?;
    let manifest: Manifest = serde_json::from_slice(&text)
        .map_err(|e| invalid(format!("{MANIFEST} cannot be read: {e}")))?;
    if data_dir.join(DB_FILE).exists() {
        return Err(invalid(format!(
            "{} already holds a database: restore into a fresh data folder",
            data_dir.display()
        )));
    }
    let (from, data_dir) = (from.to_path_buf(), data_dir.to_path_buf());
    let m = manifest.clone();
    tokio::task::spawn_blocking(move || -> Result<()> {
        fs::create_dir_all(&data_dir)?;
        let blobs = BlobStore::open(data_dir.join(BLOB_DIR))?;
        let staged = data_dir.join(".restore.db.tmp");
        let check = |what: &str, got: &FileEntry, want: &FileEntry| {
            if got == want {
                Ok(())
            } else {
                Err(invalid(format!(
                    "{what} does not match the manifest (sha256 {}, {} bytes; expected {}, {} \
                     bytes): the backup is damaged",
                    got.sha256, got.size, want.sha256, want.size
                )))
            }
        };
        let result = (|| -> Result<()> {
            let got = copy_hashed(&from.join(DB_FILE), &staged)?;
            check("the database", &got, &m.database)?;
            for want in &m.blobs {
                let mut tmp = blobs.temp_file()?;
                let mut src =
                    fs::File::open(super::blobs::location(&from.join(BLOB_DIR), &want.sha256))
                        .map_err(|e| invalid(format!("blob {}: {e}", want.sha256)))?;
                io::copy(&mut src, tmp.as_file_mut())?;
                let got = blobs.commit(tmp)?;
                let got = FileEntry {
                    sha256: got.sha256,
                    size: got.size,
                };
                check(&format!("blob {}", want.sha256), &got, want)?;
            }
            Ok(())
        })();
        match result {
            Ok(()) => {
                #[cfg(unix)]
                {
                    use std::os::unix::fs::PermissionsExt;
                    fs::set_permissions(&staged, fs::Permissions::from_mode(0o600))?;
                }
                fs::rename(&staged, data_dir.join(DB_FILE))?;
                Ok(())
            }
            Err(e) => {
                let _ = fs::remove_file(&staged);
                let _ = fs::remove_dir_all(data_dir.join(BLOB_DIR));
                Err(e)
            }
        }
    })
    .await
    .map_err(|e| StoreError::Io(io::Error::other(e)))??;
    Ok(manifest)
}
