//! The watermarking queue. A job is `queued` → `running` (claimed under a lease token that the
//! worker renews by heartbeat) → `done`; a failure makes it `failed` (waits out an exponential
//! backoff, then is claimable again) or, after `max_attempts`, `dead` with its error kept; a
//! lease that expires puts it back in the queue (or `dead`). `cancelled` is final.
//! The message is stored sealed (associated data `job:<id>`) with the secret mask drawn for it
//! when the job is queued (`job:<id>/mask`): the job's [`WatermarkKey`], which becomes the result's.

use super::audit::{self, AuditEntry};
use super::error::{Result, StoreError};
use super::keys::{WatermarkKey, validate_message};
use super::{Backend, Store, parse_opt_uuid, parse_uuid, time, to_i64, to_u64};
use serde::{Deserialize, Serialize};
use sqlx::AnyConnection;
use sqlx::Row;
use sqlx::any::AnyRow;
use std::str::FromStr;
use std::time::Duration;
use uuid::Uuid;

/// First retry delay; doubles with each attempt.
pub const BACKOFF_BASE: Duration = Duration::from_secs(5);
/// Longest retry delay.
pub const BACKOFF_CAP: Duration = Duration::from_secs(600);
/// Most attempts a job may be given.
pub const MAX_ATTEMPTS: u32 = 100;
/// Longest lease a worker may take (it renews by heartbeat).
pub const MAX_LEASE: Duration = Duration::from_secs(24 * 3600);
const MAX_ERROR: usize = 4096;
const MAX_OPTIONS: usize = 64 * 1024;

/// Where a job is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// Claimed by a worker under a lease.
    Running,
    /// Published (see `result_asset_id`).
    Done,
    /// Failed; will be retried once `not_before` has passed.
    Failed,
    /// Failed `max_attempts` times (or lost its lease on the last one); `error` says why.
    Dead,
    /// Cancelled by its owner or an admin.
    Cancelled,
}

impl JobState {
    /// Every state, in declaration order.
    pub const ALL: [JobState; 6] = [
        JobState::Queued,
        JobState::Running,
        JobState::Done,
        JobState::Failed,
        JobState::Dead,
        JobState::Cancelled,
    ];

    /// The stored / serialized name.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Dead => "dead",
            JobState::Cancelled => "cancelled",
        }
    }

    /// Whether the job will never run again.
    pub fn is_final(self) -> bool {
        matches!(self, JobState::Done | JobState::Dead | JobState::Cancelled)
    }
}

impl FromStr for JobState {
    type Err = StoreError;

    fn from_str(s: &str) -> Result<Self> {
        JobState::ALL
            .into_iter()
            .find(|st| st.as_str() == s)
            .ok_or_else(|| StoreError::invalid(format!("unknown job state {s:?}")))
    }
}

impl std::fmt::Display for JobState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Jobs per state.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct JobCounts {
    pub queued: u64,
    pub running: u64,
    pub done: u64,
    pub failed: u64,
    pub dead: u64,
    pub cancelled: u64,
}

impl JobCounts {
    /// The count of one state.
    pub fn get(&self, s: JobState) -> u64 {
        match s {
            JobState::Queued => self.queued,
            JobState::Running => self.running,
            JobState::Done => self.done,
            JobState::Failed => self.failed,
            JobState::Dead => self.dead,
            JobState::Cancelled => self.cancelled,
        }
    }

    pub(crate) fn add(&mut self, s: JobState, n: u64) {
        let slot = match s {
            JobState::Queued => &mut self.queued,
            JobState::Running => &mut self.running,
            JobState::Done => &mut self.done,
            JobState::Failed => &mut self.failed,
            JobState::Dead => &mut self.dead,
            JobState::Cancelled => &mut self.cancelled,
        };
        *slot += n;
    }
}

/// A watermarking request.
#[derive(Clone, Debug, PartialEq)]
pub struct NewJob {
    /// The original to watermark.
    pub asset_id: Uuid,
    pub owner: String,
    /// Message length; must equal `message.len()`.
    pub bits: u32,
    /// Stored sealed, never in plaintext.
    pub message: Vec<bool>,
    /// Embedding options (JSON, at most 64 KiB).
    pub options: serde_json::Value,
    /// Same owner + same key → the same job.
    pub idempotency_key: Option<String>,
    /// 1..=100.
    pub max_attempts: u32,
}

/// A job as clients see it (no message, no lease token).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Job {
    pub id: Uuid,
    pub asset_id: Uuid,
    pub owner: String,
    pub bits: u32,
    pub options: serde_json::Value,
    pub state: JobState,
    /// Last reported pipeline phase.
    pub phase: Option<String>,
    pub step: u64,
    pub total: u64,
    pub eta_seconds: Option<f64>,
    /// Claims so far.
    pub attempts: u32,
    pub max_attempts: u32,
    /// The last failure (kept when dead).
    pub error: Option<String>,
    /// The watermarked asset once done.
    pub result_asset_id: Option<Uuid>,
    /// While running.
    pub lease_expires_at: Option<String>,
    /// Not claimable before this time (the backoff of a failed job).
    pub not_before: String,
    /// Last heartbeat while running.
    pub heartbeat_at: Option<String>,
    pub created_at: String,
    pub updated_at: String,
}

/// A claimed job: the lease token proves ownership to heartbeat, fail and publish.
#[derive(Clone, Debug)]
pub struct Claimed {
    pub job: Job,
    pub lease_token: Uuid,
    /// The decrypted key; the worker embeds its [`payload`](WatermarkKey::payload).
    pub key: WatermarkKey,
}

/// Progress a worker reports with its heartbeat.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProgressUpdate {
    pub phase: String,
    pub step: u64,
    pub total: u64,
    pub eta_seconds: Option<f64>,
}

const JOB_COLUMNS: &str = "id, asset_id, owner, bits, options, state, phase, step, total, \
     eta_seconds, attempts, max_attempts, error, result_asset_id, lease_expires_at, not_before, \
     heartbeat_at, created_at, updated_at";

impl Store {
    /// Queues a job and its audit row (`job_id`, `asset_id` filled in when `None`). With an
    /// idempotency key already used by the same owner: the existing job and `false` when the
    /// request is the same (asset, bits, message, options, max_attempts), `Conflict` otherwise.
    /// `NotFound` when the asset does not exist, `Invalid` when it is not an original.
    pub async fn enqueue(&self, j: NewJob, mut audit_entry: AuditEntry) -> Result<(Job, bool)> {
        validate_new_job(&j)?;
        let options = serde_json::to_string(&j.options)
            .map_err(|e| StoreError::invalid(format!("options: {e}")))?;
        if options.len() > MAX_OPTIONS {
            return Err(StoreError::invalid("options exceed 64 KiB"));
        }
        let mut tx = self.begin_immediate().await?;
        if let Some(key) = &j.idempotency_key {
            let existing = sqlx::query(
                "SELECT id, asset_id, bits, options, max_attempts, message_nonce, message_ct, \
                 mask_nonce, mask_ct FROM jobs WHERE owner = $1 AND idempotency_key = $2",
            )
            .bind(&j.owner)
            .bind(key)
            .fetch_optional(&mut *tx)
            .await?;
            if let Some(r) = existing {
                let id: String = r.try_get("id")?;
                let stored_options: String = r.try_get("options")?;
                let stored_options: serde_json::Value = serde_json::from_str(&stored_options)
                    .map_err(|e| StoreError::corrupt(format!("job options: {e}")))?;
                let message = self
                    .open_key(&r, "message_nonce", "message_ct", &job_aad(&id))?
                    .message;
                let same = r.try_get::<String, _>("asset_id")? == j.asset_id.to_string()
                    && r.try_get::<i64, _>("bits")? == i64::from(j.bits)
                    && r.try_get::<i64, _>("max_attempts")? == i64::from(j.max_attempts)
                    && stored_options == j.options
                    && message == j.message;
                if !same {
                    return Err(StoreError::Conflict(
                        "idempotency key already used with a different request".into(),
                    ));
                }
                let job = fetch_job(&mut tx, &id).await?.ok_or(StoreError::NotFound)?;
                tx.rollback().await?;
                return Ok((job, false));
            }
        }
        let kind: Option<String> = sqlx::query_scalar("SELECT kind FROM assets WHERE id = $1")
            .bind(j.asset_id.to_string())
            .fetch_optional(&mut *tx)
            .await?;
        match kind.as_deref() {
            None => return Err(StoreError::NotFound),
            Some("original") => {}
            Some(_) => return Err(StoreError::invalid("only an original can be watermarked")),
        }
        let id = Uuid::new_v4().to_string();
        let key = WatermarkKey::draw(j.message.clone());
        let sealed = self.seal_key(&key, &job_aad(&id))?;
        let now = time::now();
        sqlx::query(
            "INSERT INTO jobs (id, asset_id, owner, bits, message_nonce, message_ct, mask_nonce, \
             mask_ct, options, idempotency_key, state, max_attempts, not_before, created_at, \
             updated_at) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, 'queued', $11, $12, $13, $14)",
        )
        .bind(&id)
        .bind(j.asset_id.to_string())
        .bind(&j.owner)
        .bind(i64::from(j.bits))
        .bind(sealed.message.nonce)
        .bind(sealed.message.ciphertext)
        .bind(sealed.mask.nonce)
        .bind(sealed.mask.ciphertext)
        .bind(&options)
        .bind(&j.idempotency_key)
        .bind(i64::from(j.max_attempts))
        .bind(&now)
        .bind(&now)
        .bind(&now)
        .execute(&mut *tx)
        .await
        .map_err(StoreError::from_db)?;
        let job = fetch_job(&mut tx, &id).await?.ok_or(StoreError::NotFound)?;
        audit_entry.job_id.get_or_insert(job.id);
        audit_entry.asset_id.get_or_insert(job.asset_id);
        audit::append_in(&mut tx, &audit_entry).await?;
        tx.commit().await?;
        Ok((job, true))
    }

    /// One job.
    pub async fn get_job(&self, id: Uuid) -> Result<Option<Job>> {
        let mut conn = self.pool.acquire().await?;
        fetch_job(&mut conn, &id.to_string()).await
    }

    /// The jobs of `asset`, newest first, at most `limit` (1–1000).
    pub async fn jobs_of(&self, asset: Uuid, limit: u32) -> Result<Vec<Job>> {
        let sql = format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE asset_id = $1 \
             ORDER BY created_at DESC, id DESC LIMIT $2"
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(asset.to_string())
            .bind(i64::from(limit.clamp(1, 1000)))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(decode_job).collect()
    }

    /// The job `owner` queued under `key`, if any (lets the HTTP layer answer a retried request
    /// before drawing a fresh random message for it).
    pub async fn job_by_idempotency_key(&self, owner: &str, key: &str) -> Result<Option<Job>> {
        let id: Option<String> =
            sqlx::query_scalar("SELECT id FROM jobs WHERE owner = $1 AND idempotency_key = $2")
                .bind(owner)
                .bind(key)
                .fetch_optional(&self.pool)
                .await?;
        match id {
            None => Ok(None),
            Some(id) => {
                let mut conn = self.pool.acquire().await?;
                fetch_job(&mut conn, &id).await
            }
        }
    }

    /// Claims the oldest claimable job (`queued`, or `failed` past its backoff) in a
    /// `BEGIN IMMEDIATE` transaction: `running`, one more attempt, a new lease token, lease expiry
    /// now + `lease`, audit row "job.claim". `None` when nothing is claimable. Expired leases are
    /// not reclaimed here; call [`Store::requeue_expired`] periodically.
    pub async fn claim(&self, worker: &str, lease: Duration) -> Result<Option<Claimed>> {
        validate_worker(worker)?;
        validate_lease(lease)?;
        let mut tx = self.begin_immediate().await?;
        let now = time::now();
        // Oldest first; jobs created in the same millisecond in insertion order (SQLite's
        // rowid, PostgreSQL's `seq`). On PostgreSQL the row is locked, skipping rows another
        // transaction holds: two claims never take one job even without the write lock, which
        // every writer takes first (before any row lock, so that a claim and, say, a cancel of
        // the same job cannot deadlock) because each appends to the one audit chain.
        let row = sqlx::query(match self.backend() {
            Backend::Sqlite => {
                "SELECT id, message_nonce, message_ct, mask_nonce, mask_ct FROM jobs \
                 WHERE state IN ('queued', 'failed') AND not_before <= $1 \
                 ORDER BY created_at, rowid LIMIT 1"
            }
            Backend::Postgres => {
                "SELECT id, message_nonce, message_ct, mask_nonce, mask_ct FROM jobs \
                 WHERE state IN ('queued', 'failed') AND not_before <= $1 \
                 ORDER BY created_at, seq LIMIT 1 FOR UPDATE SKIP LOCKED"
            }
        })
        .bind(&now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(r) = row else {
            tx.rollback().await?;
            return Ok(None);
        };
        let id: String = r.try_get("id")?;
        let key = match self.open_key(&r, "message_nonce", "message_ct", &job_aad(&id)) {
            Ok(m) => m,
            Err(e) => {
                // Never hand out a job whose message cannot be read; do not block the queue.
                let error = "the job's message does not decrypt under the master key";
                set_dead(&mut tx, &id, error, &now).await?;
                let mut entry = AuditEntry::new("system", "job.dead");
                entry.job_id = Some(parse_uuid(&id)?);
                entry.details = serde_json::json!({ "error": error });
                audit::append_in(&mut tx, &entry).await?;
                tx.commit().await?;
                return Err(e);
            }
        };
        let token = Uuid::new_v4();
        sqlx::query(
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, lease_token = $1, \
             lease_expires_at = $2, worker = $3, heartbeat_at = $4, updated_at = $5 WHERE id = $6",
        )
        .bind(token.to_string())
        .bind(time::after(lease))
        .bind(worker)
        .bind(&now)
        .bind(&now)
        .bind(&id)
        .execute(&mut *tx)
        .await?;
        let job = fetch_job(&mut tx, &id).await?.ok_or(StoreError::NotFound)?;
        let mut entry = AuditEntry::new(worker, "job.claim");
        entry.job_id = Some(job.id);
        entry.asset_id = Some(job.asset_id);
        entry.details = serde_json::json!({ "attempt": job.attempts });
        audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok(Some(Claimed {
            job,
            lease_token: token,
            key,
        }))
    }

    /// Extends the lease to now + `lease` and records `p`. `LeaseLost` when `token` no longer
    /// holds the job (requeued and re-claimed, cancelled, finished). A lease that has expired but
    /// was not yet requeued is still held.
    pub async fn heartbeat(
        &self,
        job: Uuid,
        token: Uuid,
        lease: Duration,
        p: Option<&ProgressUpdate>,
    ) -> Result<()> {
        validate_lease(lease)?;
        let now = time::now();
        let expires = time::after(lease);
        let done = match p {
            None => sqlx::query(
                "UPDATE jobs SET lease_expires_at = $1, heartbeat_at = $2, updated_at = $3 \
                 WHERE id = $4 AND state = 'running' AND lease_token = $5",
            )
            .bind(&expires)
            .bind(&now)
            .bind(&now)
            .bind(job.to_string())
            .bind(token.to_string())
            .execute(&self.pool)
            .await?
            .rows_affected(),
            Some(p) => {
                if p.phase.len() > 64 || p.phase.chars().any(char::is_control) {
                    return Err(StoreError::invalid("phase must be <= 64 bytes"));
                }
                // A nullable double, bound as value and presence: `super::nullable_f64`.
                let eta = p.eta_seconds.filter(|e| e.is_finite() && *e >= 0.0);
                sqlx::query(
                    "UPDATE jobs SET lease_expires_at = $1, heartbeat_at = $2, updated_at = $3, \
                     phase = $4, step = $5, total = $6, \
                     eta_seconds = CASE WHEN $10 = 1 THEN $7 END \
                     WHERE id = $8 AND state = 'running' AND lease_token = $9",
                )
                .bind(&expires)
                .bind(&now)
                .bind(&now)
                .bind(&p.phase)
                .bind(to_i64(p.step)?)
                .bind(to_i64(p.total)?)
                .bind(eta.unwrap_or(0.0))
                .bind(job.to_string())
                .bind(token.to_string())
                .bind(i64::from(eta.is_some()))
                .execute(&self.pool)
                .await?
                .rows_affected()
            }
        };
        if done == 1 {
            Ok(())
        } else {
            Err(StoreError::LeaseLost)
        }
    }

    /// Running jobs whose lease has expired go back to `queued` (or to `dead` when they have
    /// used all their attempts), with an audit row each ("job.requeue" / "job.dead").
    pub async fn requeue_expired(&self) -> Result<u64> {
        let mut tx = self.begin_immediate().await?;
        let now = time::now();
        let rows = sqlx::query(
            "SELECT id, asset_id, attempts, max_attempts, worker FROM jobs \
             WHERE state = 'running' AND lease_expires_at < $1 ORDER BY lease_expires_at",
        )
        .bind(&now)
        .fetch_all(&mut *tx)
        .await?;
        for r in &rows {
            let id: String = r.try_get("id")?;
            let attempts: i64 = r.try_get("attempts")?;
            let max: i64 = r.try_get("max_attempts")?;
            let worker: Option<String> = r.try_get("worker")?;
            let worker = worker.unwrap_or_default();
            let mut entry = AuditEntry::new("system", "job.requeue");
            entry.job_id = Some(parse_uuid(&id)?);
            entry.asset_id = Some(parse_uuid(&r.try_get::<String, _>("asset_id")?)?);
            if attempts >= max {
                let error =
                    format!("lease expired (worker {worker:?}) on attempt {attempts} of {max}");
                set_dead(&mut tx, &id, &error, &now).await?;
                entry.action = "job.dead".into();
                entry.details = serde_json::json!({ "attempts": attempts, "error": error });
            } else {
                let error = format!("lease expired (worker {worker:?}) on attempt {attempts}");
                sqlx::query(
                    "UPDATE jobs SET state = 'queued', lease_token = NULL, lease_expires_at = NULL, \
                     not_before = $1, error = $2, updated_at = $3 WHERE id = $4",
                )
                .bind(&now)
                .bind(&error)
                .bind(&now)
                .bind(&id)
                .execute(&mut *tx)
                .await?;
                entry.details = serde_json::json!({ "attempts": attempts, "error": error });
            }
            audit::append_in(&mut tx, &entry).await?;
        }
        tx.commit().await?;
        Ok(rows.len() as u64)
    }

    /// Hands a running job back because its worker is shutting down (not because the job
    /// failed): `queued` again at once, the attempt not counted (the next claim is the same attempt
    /// number), lease cleared, audit "job.release" with `reason`. `LeaseLost` when `token` no
    /// longer holds the job (nothing written).
    pub async fn release(&self, job: Uuid, token: Uuid, reason: &str) -> Result<()> {
        let reason = truncate(reason, MAX_ERROR);
        let mut tx = self.begin_immediate().await?;
        let id = job.to_string();
        let held = held_job(&mut tx, &id, token).await?;
        let now = time::now();
        sqlx::query(
            "UPDATE jobs SET state = 'queued', attempts = CASE WHEN attempts > 0 THEN attempts - 1 ELSE 0 END, \
             lease_token = NULL, lease_expires_at = NULL, not_before = $1, updated_at = $2 \
             WHERE id = $3",
        )
        .bind(&now)
        .bind(&now)
        .bind(&id)
        .execute(&mut *tx)
        .await?;
        let mut entry = AuditEntry::new(held.worker, "job.release");
        entry.job_id = Some(job);
        entry.asset_id = Some(held.asset_id);
        entry.details = serde_json::json!({ "attempt": held.attempts, "reason": reason });
        audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Records a failed attempt. With attempts left: `failed`, claimable again after
    /// `5 s · 2^(attempts−1)` (at most 10 min), audit "job.fail"; otherwise `dead`, audit
    /// "job.dead". The error text (at most 4 KiB kept) stays on the job. `LeaseLost` when `token`
    /// no longer holds it (nothing written).
    pub async fn fail(&self, job: Uuid, token: Uuid, error: &str) -> Result<JobState> {
        let error = truncate(error, MAX_ERROR);
        let mut tx = self.begin_immediate().await?;
        let id = job.to_string();
        let HeldJob {
            asset_id,
            attempts,
            max_attempts: max,
            worker,
        } = held_job(&mut tx, &id, token).await?;
        let now = time::now();
        let mut entry = AuditEntry::new(worker, "job.fail");
        entry.job_id = Some(job);
        entry.asset_id = Some(asset_id);
        let state = if attempts < max {
            let retry_at = time::after(backoff(attempts));
            sqlx::query(
                "UPDATE jobs SET state = 'failed', lease_token = NULL, lease_expires_at = NULL, \
                 not_before = $1, error = $2, updated_at = $3 WHERE id = $4",
            )
            .bind(&retry_at)
            .bind(error)
            .bind(&now)
            .bind(&id)
            .execute(&mut *tx)
            .await?;
            entry.details =
                serde_json::json!({ "attempt": attempts, "error": error, "retry_at": retry_at });
            JobState::Failed
        } else {
            set_dead(&mut tx, &id, error, &now).await?;
            entry.action = "job.dead".into();
            entry.details = serde_json::json!({ "attempt": attempts, "error": error });
            JobState::Dead
        };
        audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok(state)
    }

    /// Cancels a queued, failed or running job (its worker gets `LeaseLost` at its next
    /// heartbeat or publish) with the audit row (`job_id`, `asset_id` filled in when `None`).
    /// Cancelling a cancelled job returns it unchanged; `Conflict` when done or dead,
    /// `NotFound` when unknown.
    pub async fn cancel(&self, job: Uuid, mut audit_entry: AuditEntry) -> Result<Job> {
        let mut tx = self.begin_immediate().await?;
        let id = job.to_string();
        let current = fetch_job(&mut tx, &id).await?.ok_or(StoreError::NotFound)?;
        match current.state {
            JobState::Cancelled => {
                tx.rollback().await?;
                return Ok(current);
            }
            JobState::Done | JobState::Dead => {
                return Err(StoreError::Conflict(format!(
                    "job is already {}",
                    current.state
                )));
            }
            _ => {}
        }
        sqlx::query(
            "UPDATE jobs SET state = 'cancelled', lease_token = NULL, lease_expires_at = NULL, \
             updated_at = $1 WHERE id = $2",
        )
        .bind(time::now())
        .bind(&id)
        .execute(&mut *tx)
        .await?;
        audit_entry.job_id.get_or_insert(job);
        audit_entry.asset_id.get_or_insert(current.asset_id);
        audit::append_in(&mut tx, &audit_entry).await?;
        let out = fetch_job(&mut tx, &id).await?.ok_or(StoreError::NotFound)?;
        tx.commit().await?;
        Ok(out)
    }
}

/// A running job as its lease holder sees it.
struct HeldJob {
    asset_id: Uuid,
    attempts: i64,
    max_attempts: i64,
    /// The worker holding it ("system" when unknown).
    worker: String,
}

/// The running job `id` if `token` holds its lease, else `LeaseLost`.
async fn held_job(tx: &mut AnyConnection, id: &str, token: Uuid) -> Result<HeldJob> {
    let r = sqlx::query(
        "SELECT asset_id, attempts, max_attempts, worker FROM jobs \
         WHERE id = $1 AND state = 'running' AND lease_token = $2",
    )
    .bind(id)
    .bind(token.to_string())
    .fetch_optional(&mut *tx)
    .await?
    .ok_or(StoreError::LeaseLost)?;
    let worker: Option<String> = r.try_get("worker")?;
    Ok(HeldJob {
        asset_id: parse_uuid(&r.try_get::<String, _>("asset_id")?)?,
        attempts: r.try_get("attempts")?,
        max_attempts: r.try_get("max_attempts")?,
        worker: worker.unwrap_or_else(|| "system".into()),
    })
}

/// Associated data sealing a job's message.
pub(crate) fn job_aad(id: &str) -> String {
    format!("job:{id}")
}

/// The delay before retrying after failed attempt number `attempts` (1-based).
pub fn backoff(attempts: i64) -> Duration {
    let exp = u32::try_from(attempts.saturating_sub(1).clamp(0, 16)).unwrap_or(16);
    BACKOFF_BASE.saturating_mul(1 << exp).min(BACKOFF_CAP)
}

pub(crate) async fn fetch_job(conn: &mut AnyConnection, id: &str) -> Result<Option<Job>> {
    let sql = format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1");
    let row = sqlx::query(sqlx::AssertSqlSafe(sql))
        .bind(id)
        .fetch_optional(&mut *conn)
        .await?;
    row.as_ref().map(decode_job).transpose()
}

async fn set_dead(conn: &mut AnyConnection, id: &str, error: &str, now: &str) -> Result<()> {
    sqlx::query(
        "UPDATE jobs SET state = 'dead', lease_token = NULL, lease_expires_at = NULL, error = $1, \
         updated_at = $2 WHERE id = $3",
    )
    .bind(error)
    .bind(now)
    .bind(id)
    .execute(&mut *conn)
    .await?;
    Ok(())
}

fn decode_job(r: &AnyRow) -> Result<Job> {
    let options: String = r.try_get("options")?;
    let state: String = r.try_get("state")?;
    let u32_of = |col: &str| -> Result<u32> {
        let v: i64 = r.try_get(col)?;
        u32::try_from(v).map_err(|_| StoreError::corrupt(format!("jobs.{col} = {v}")))
    };
    Ok(Job {
        id: parse_uuid(&r.try_get::<String, _>("id")?)?,
        asset_id: parse_uuid(&r.try_get::<String, _>("asset_id")?)?,
        owner: r.try_get("owner")?,
        bits: u32_of("bits")?,
        options: serde_json::from_str(&options)
            .map_err(|e| StoreError::corrupt(format!("job options: {e}")))?,
        state: state
            .parse()
            .map_err(|_| StoreError::corrupt(format!("job state {state:?}")))?,
        phase: r.try_get("phase")?,
        step: to_u64(r.try_get("step")?)?,
        total: to_u64(r.try_get("total")?)?,
        eta_seconds: r.try_get("eta_seconds")?,
        attempts: u32_of("attempts")?,
        max_attempts: u32_of("max_attempts")?,
        error: r.try_get("error")?,
        result_asset_id: parse_opt_uuid(r.try_get("result_asset_id")?)?,
        lease_expires_at: r.try_get("lease_expires_at")?,
        not_before: r.try_get("not_before")?,
        heartbeat_at: r.try_get("heartbeat_at")?,
        created_at: r.try_get("created_at")?,
        updated_at: r.try_get("updated_at")?,
    })
}

fn validate_new_job(j: &NewJob) -> Result<()> {
    validate_message(&j.message)?;
    if j.bits as usize != j.message.len() {
        return Err(StoreError::invalid(format!(
            "bits is {} but the message has {} bits",
            j.bits,
            j.message.len()
        )));
    }
    if j.max_attempts == 0 || j.max_attempts > MAX_ATTEMPTS {
        return Err(StoreError::invalid(format!(
            "max_attempts must be 1..={MAX_ATTEMPTS}"
        )));
    }
    validate_worker(&j.owner).map_err(|_| StoreError::invalid("owner must be 1..=255 bytes"))?;
    if let Some(k) = &j.idempotency_key
        && (k.is_empty() || k.len() > 255 || k.chars().any(char::is_control))
    {
        return Err(StoreError::invalid(
            "idempotency key must be 1..=255 bytes without control characters",
        ));
    }
    Ok(())
}

fn validate_worker(w: &str) -> Result<()> {
    if w.is_empty() || w.len() > 255 || w.chars().any(char::is_control) {
        return Err(StoreError::invalid(
            "worker name must be 1..=255 bytes without control characters",
        ));
    }
    Ok(())
}

fn validate_lease(lease: Duration) -> Result<()> {
    if lease.is_zero() || lease > MAX_LEASE {
        return Err(StoreError::invalid("lease must be > 0 and <= 24 h"));
    }
    Ok(())
}

/// At most `max` bytes of `s`, cut at a character boundary.
fn truncate(s: &str, max: usize) -> &str {
    if s.len() <= max {
        return s;
    }
    let mut end = max;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    &s[..end]
}
