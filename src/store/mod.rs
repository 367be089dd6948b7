//! Storage for the service (issue 5): SQLite through sqlx (WAL, 5 s busy timeout, foreign keys,
//! `synchronous = FULL`, schema in `migrations/`) and content-addressed blobs on disk.
//!
//! | file | holds |
//! |---|---|
//! | `blobs` | [`BlobStore`]: `blobs/ab/cdef…` by SHA-256, temp file + fsync + rename |
//! | `s3` | blobs in an S3-compatible object store instead ([`BlobConfig`], [`BlobUrl`]) |
//! | `crypto` | [`MasterKey`], XChaCha20-Poly1305 for messages at rest |
//! | `assets` | uploaded and watermarked assets |
//! | `keys` | each watermarked asset's message (encrypted) |
//! | `jobs` | the queue: claim with lease, heartbeat, requeue, backoff, dead letter, cancel |
//! | `publish` | a job's result, exactly once |
//! | `attribution` | per-Gaussian records, compact and paged, summary, embed report |
//! | `verifications` | dispute verifications |
//! | `audit` | append-only hash-chained log |
//! | `api_keys` | bearer tokens (hashed) and scopes |
//!
//! Every write that must not interleave with another runs in a `BEGIN IMMEDIATE` transaction,
//! so SQLite serializes writers up front and a transaction never fails half-way on a lock upgrade.

pub(crate) mod api_keys;
mod assets;
pub(crate) mod attribution;
mod audit;
pub mod backup;
mod blobs;
pub(crate) mod crypto;
pub mod database;
mod error;
pub(crate) mod jobs;
mod keys;
mod lock;
mod publish;
pub mod s3;
mod time;
mod verifications;

#[cfg(test)]
mod tests;

pub use api_keys::{ApiKey, Scope, TOKEN_PREFIX};
pub use assets::{Asset, AssetKind, GcReport, NewAsset};
pub use attribution::{AttributionSummary, MAX_ATTRIBUTION_PAGE};
pub use audit::{AuditEntry, AuditFilter, AuditRow, ChainReport, GENESIS_HASH, MAX_AUDIT_PAGE};
pub use blobs::{BlobInfo, BlobRef, BlobStore, PinnedBlob};
pub use crypto::{MASTER_KEY_ENV, MasterKey};
pub use error::{Result, StoreError};
pub use jobs::{
    BACKOFF_BASE, BACKOFF_CAP, Claimed, Job, JobCounts, JobState, MAX_ATTEMPTS, MAX_LEASE, NewJob,
    ProgressUpdate, backoff,
};
pub use keys::{MAX_MESSAGE_BITS, Readout, Registration, WatermarkKey};
pub use lock::{DataDirLock, LOCK_FILE, LockError, LockMode};
pub use time::normalize_timestamp;
pub use verifications::NewVerification;

pub use database::{Backend, Database};
pub use s3::{BlobConfig, BlobUrl, S3Options, Secret};

use serde::Serialize;
use sqlx::AnyPool;
use sqlx::any::AnyPoolOptions;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqliteSynchronous};
use sqlx::{Any, Connection, Executor, Row, Transaction};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use uuid::Uuid;

/// Database file name inside the data directory.
pub const DB_FILE: &str = "splatmark.db";
/// Blob directory name inside the data directory.
pub const BLOB_DIR: &str = "blobs";

/// The storage handle: a connection pool and the blob store. Cheap to clone.
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    inner: Arc<Inner>,
}

struct Inner {
    blobs: BlobStore,
    cipher: crypto::Cipher,
    backend: Backend,
}

/// Row counts for `/metrics`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Counts {
    /// Jobs per state.
    pub jobs: JobCounts,
    /// Assets (originals and watermarked).
    pub assets: u64,
    /// Watermarked assets.
    pub watermarked: u64,
    /// Verifications recorded.
    pub verifications: u64,
    /// Audit rows.
    pub audit_rows: u64,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store")
            .field("backend", &self.inner.backend)
            .field("blobs", &self.inner.blobs)
            .finish_non_exhaustive()
    }
}

impl Store {
    /// Opens (creating) `data_dir/splatmark.db` and `data_dir/blobs/`, applies the migrations and
    /// checks `master` against the key-check value written when the database was created
    /// (`Crypto` for a different key, so a misconfigured service fails at start, not at verify).
    pub async fn open(data_dir: &Path, master: MasterKey) -> Result<Store> {
        Self::open_with(data_dir, &Database::in_data_dir(data_dir), master).await
    }

    /// Opens `database` (SQLite or PostgreSQL, [`Database`]) with the blobs in
    /// `data_dir/blobs/`, applies that dialect's migrations (`migrations/sqlite`,
    /// `migrations/postgres`) and checks `master` as [`Store::open`] does.
    pub async fn open_with(
        data_dir: &Path,
        database: &Database,
        master: MasterKey,
    ) -> Result<Store> {
        Self::open_with_blobs(data_dir, database, &BlobConfig::Local, master).await
    }

    /// [`Store::open_with`] with the blobs where `blobs` says: `data_dir/blobs/`, or an
    /// S3-compatible bucket (then `data_dir/blobs/` holds only staged uploads and the verified
    /// read cache), which must answer (a LIST) before anything else is opened.
    pub async fn open_with_blobs(
        data_dir: &Path,
        database: &Database,
        blobs: &BlobConfig,
        master: MasterKey,
    ) -> Result<Store> {
        std::fs::create_dir_all(data_dir)?;
        let blobs = BlobStore::open_with(data_dir.join(BLOB_DIR), blobs)?;
        if blobs.is_remote() {
            let b = blobs.clone();
            tokio::task::spawn_blocking(move || b.check())
                .await
                .map_err(|e| StoreError::Io(std::io::Error::other(e)))??;
        }
        sqlx::any::install_default_drivers();
        let pool = match database {
            Database::Sqlite(path) => {
                if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                    std::fs::create_dir_all(dir)?;
                }
                make_private(path)?;
                // WAL is a property of the file: set once, on a connection of its own (the
                // pool's URL cannot carry it); every pooled connection then sets the rest.
                let first = sqlx::SqliteConnection::connect_with(
                    &SqliteConnectOptions::new()
                        .filename(path)
                        .create_if_missing(true)
                        .journal_mode(SqliteJournalMode::Wal)
                        .synchronous(SqliteSynchronous::Full)
                        .busy_timeout(Duration::from_secs(5))
                        .foreign_keys(true),
                )
                .await?;
                first.close().await?;
                let pool = AnyPoolOptions::new()
                    .max_connections(8)
                    .after_connect(|conn, _| {
                        Box::pin(async move {
                            conn.execute(
                                "PRAGMA synchronous = FULL; PRAGMA foreign_keys = ON; \
                                 PRAGMA busy_timeout = 5000;",
                            )
                            .await?;
                            Ok(())
                        })
                    })
                    .connect(&database.url())
                    .await?;
                sqlx::migrate!("./migrations/sqlite").run(&pool).await?;
                pool
            }
            Database::Postgres(_) => {
                let pool = AnyPoolOptions::new()
                    .max_connections(8)
                    .acquire_timeout(Duration::from_secs(30))
                    .connect(&database.url())
                    .await?;
                // sqlx takes PostgreSQL's migration advisory lock: replicas may start together.
                sqlx::migrate!("./migrations/postgres").run(&pool).await?;
                pool
            }
        };
        let store = Store {
            pool,
            inner: Arc::new(Inner {
                blobs,
                cipher: crypto::Cipher::new(&master),
                backend: database.backend(),
            }),
        };
        store.check_master_key().await?;
        Ok(store)
    }

    /// Which database engine holds the rows.
    pub fn backend(&self) -> Backend {
        self.inner.backend
    }

    /// The blob store.
    pub fn blobs(&self) -> &BlobStore {
        &self.inner.blobs
    }

    /// SQLite's `PRAGMA integrity_check`: "ok", or the problems it found, one per line. On
    /// PostgreSQL, whose pages the server checks itself, "ok" once a query runs.
    pub async fn integrity_check(&self) -> Result<String> {
        match self.backend() {
            Backend::Sqlite => {
                let rows: Vec<String> = sqlx::query_scalar("PRAGMA integrity_check")
                    .fetch_all(&self.pool)
                    .await?;
                Ok(rows.join("\n"))
            }
            Backend::Postgres => {
                self.ping().await?;
                Ok("ok".into())
            }
        }
    }

    /// A trivial query (for `/readyz`).
    pub async fn ping(&self) -> Result<()> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// Closes the pool (waits for connections in use); the last connection checkpoints the WAL.
    /// For graceful shutdown; later calls on any clone fail.
    pub async fn close(&self) {
        self.pool.close().await;
    }

    /// Jobs by state, assets, verifications and audit rows.
    pub async fn counts(&self) -> Result<Counts> {
        let mut c = Counts::default();
        let rows = sqlx::query("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state")
            .fetch_all(&self.pool)
            .await?;
        for r in rows {
            let state: String = r.try_get("state")?;
            let n = to_u64(r.try_get("n")?)?;
            c.jobs.add(state.parse()?, n);
        }
        let r = sqlx::query(
            "SELECT (SELECT COUNT(*) FROM assets) AS assets, \
                    (SELECT COUNT(*) FROM assets WHERE kind = 'watermarked') AS watermarked, \
                    (SELECT COUNT(*) FROM verifications) AS verifications, \
                    (SELECT COUNT(*) FROM audit) AS audit_rows",
        )
        .fetch_one(&self.pool)
        .await?;
        c.assets = to_u64(r.try_get("assets")?)?;
        c.watermarked = to_u64(r.try_get("watermarked")?)?;
        c.verifications = to_u64(r.try_get("verifications")?)?;
        c.audit_rows = to_u64(r.try_get("audit_rows")?)?;
        Ok(c)
    }

    /// A write transaction that no other write transaction interleaves with: SQLite's write
    /// lock taken at once (`BEGIN IMMEDIATE`); on PostgreSQL, the write lock
    /// ([`database::WRITE_LOCK`], a transaction-scoped advisory lock) taken before anything is
    /// read — every writer of several processes then reads the audit chain's head and the
    /// rows it checks as the previous writer left them.
    pub(crate) async fn begin_immediate(&self) -> Result<Transaction<'static, Any>> {
        match self.backend() {
            Backend::Sqlite => Ok(self.pool.begin_with("BEGIN IMMEDIATE").await?),
            Backend::Postgres => {
                let mut tx = self.pool.begin().await?;
                database::write_lock(&mut tx).await?;
                Ok(tx)
            }
        }
    }

    pub(crate) fn cipher(&self) -> &crypto::Cipher {
        &self.inner.cipher
    }

    /// Writes the key-check value on first open; afterwards refuses any other master key.
    async fn check_master_key(&self) -> Result<()> {
        let mut tx = self.begin_immediate().await?;
        let row = sqlx::query("SELECT value FROM meta WHERE key = 'key_check'")
            .fetch_optional(&mut *tx)
            .await?;
        match row {
            Some(r) => {
                let value: Vec<u8> = r.try_get("value")?;
                if value.len() < 24 {
                    return Err(StoreError::corrupt("meta.key_check is too short"));
                }
                let (nonce, ct) = value.split_at(24);
                let plain = self.cipher().open(nonce, ct, crypto::KEY_CHECK_AAD)?;
                if plain.as_slice() != crypto::KEY_CHECK_PLAINTEXT {
                    return Err(StoreError::Crypto);
                }
                tx.rollback().await?;
            }
            None => {
                let sealed = self
                    .cipher()
                    .seal(crypto::KEY_CHECK_PLAINTEXT, crypto::KEY_CHECK_AAD)?;
                let mut value = sealed.nonce;
                value.extend_from_slice(&sealed.ciphertext);
                sqlx::query("INSERT INTO meta (key, value) VALUES ('key_check', $1)")
                    .bind(value)
                    .execute(&mut *tx)
                    .await?;
                tx.commit().await?;
            }
        }
        Ok(())
    }
}

/// Creates the database file readable and writable by its owner only (0600: it holds the sealed
/// messages and the audit evidence), empty — SQLite initialises an empty file as a new database —
/// so that it never exists with wider permissions. SQLite creates the `-wal` and `-shm` files
/// with the database file's mode. An existing database (or `-wal`/`-shm`) that group or others
/// may access, as earlier versions created it, is restricted to its owner, with a log line.
fn make_private(db: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(db)
        {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
        let mut wal = db.as_os_str().to_owned();
        wal.push("-wal");
        let mut shm = db.as_os_str().to_owned();
        shm.push("-shm");
        for file in [db.to_path_buf(), wal.into(), shm.into()] {
            let mode = match std::fs::metadata(&file) {
                Ok(m) => m.permissions().mode(),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(e),
            };
            if mode & 0o077 != 0 {
                std::fs::set_permissions(&file, std::fs::Permissions::from_mode(mode & 0o700))?;
                tracing::warn!(
                    path = %file.display(),
                    "the database was readable by group or others; restricted it to its owner"
                );
            }
        }
    }
    #[cfg(not(unix))]
    let _ = db;
    Ok(())
}

/// A non-negative SQLite integer as `u64`.
pub(crate) fn to_u64(v: i64) -> Result<u64> {
    u64::try_from(v).map_err(|_| StoreError::corrupt(format!("negative count {v}")))
}

/// A `u64` as a SQLite integer (`Invalid` past `i64::MAX`).
pub(crate) fn to_i64(v: u64) -> Result<i64> {
    i64::try_from(v).map_err(|_| StoreError::invalid(format!("{v} is too large")))
}

/// A nullable double as two bound values, (value, 1) or (0, 0), which the SQL reads back as
/// `CASE WHEN present = 1 THEN value END`. sqlx 0.9.0's `Any` driver sends a NULL `f64` to
/// PostgreSQL as a NULL *float4* (`AnyArguments::convert_into` swaps `Null(Real)` and
/// `Null(Double)`), and a statement prepared with that parameter type then refuses the next
/// row's float8 value ("incorrect binary data format"): binding the value always keeps the
/// parameter float8.
pub(crate) fn nullable_f64(v: Option<f64>) -> (f64, i64) {
    v.map_or((0.0, 0), |x| (x, 1))
}

/// A stored UUID.
pub(crate) fn parse_uuid(s: &str) -> Result<Uuid> {
    Uuid::parse_str(s).map_err(|_| StoreError::corrupt(format!("stored id {s:?} is not a UUID")))
}

/// A stored optional UUID.
pub(crate) fn parse_opt_uuid(s: Option<String>) -> Result<Option<Uuid>> {
    s.as_deref().map(parse_uuid).transpose()
}
