//! The append-only audit log. Every row carries the hash of the one before it:
//! `hash = sha256(prev_hash || canonical bytes of (id, at, actor, action, asset_id, job_id,
//! details))`, with 64 zeros as the first row's `prev_hash`. Triggers refuse UPDATE and DELETE;
//! [`Store::verify_audit_chain`] detects rows edited behind the triggers' back.

use super::error::{Result, StoreError};
use super::{Store, time};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use sqlx::AnyConnection;
use sqlx::any::AnyRow;
use sqlx::{AssertSqlSafe, Row};
use uuid::Uuid;

/// `prev_hash` of the first row.
pub const GENESIS_HASH: &str = "0000000000000000000000000000000000000000000000000000000000000000";

/// Most rows one [`Store::audit_query`] page returns.
pub const MAX_AUDIT_PAGE: u32 = 1000;

/// What happened, as the caller describes it. Methods that create the asset or job the entry is
/// about fill in `asset_id` / `job_id` when the caller left them `None`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AuditEntry {
    /// Who: an API key id, a worker name or "system".
    pub actor: String,
    /// What, e.g. "asset.upload", "job.enqueue", "job.claim", "job.requeue", "job.fail",
    /// "job.dead", "job.cancel", "watermark.publish", "verify".
    pub action: String,
    /// The asset concerned, if any.
    pub asset_id: Option<Uuid>,
    /// The job concerned, if any.
    pub job_id: Option<Uuid>,
    /// Anything else worth keeping (never keys or messages).
    pub details: serde_json::Value,
}

impl AuditEntry {
    /// An entry with no asset, job or details.
    pub fn new(actor: impl Into<String>, action: impl Into<String>) -> Self {
        AuditEntry {
            actor: actor.into(),
            action: action.into(),
            asset_id: None,
            job_id: None,
            details: serde_json::Value::Null,
        }
    }
}

/// A stored audit row.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AuditRow {
    /// Position in the chain (1, 2, ...).
    pub id: i64,
    /// When it was appended.
    pub at: String,
    pub actor: String,
    pub action: String,
    pub asset_id: Option<Uuid>,
    pub job_id: Option<Uuid>,
    pub details: serde_json::Value,
    /// Hash of the previous row (64 zeros for the first).
    pub prev_hash: String,
    /// This row's hash.
    pub hash: String,
}

/// Which rows [`Store::audit_query`] returns (all filters ANDed; times inclusive).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AuditFilter {
    pub asset_id: Option<Uuid>,
    pub action: Option<String>,
    pub actor: Option<String>,
    /// RFC 3339 UTC, `...Z` with or without milliseconds.
    pub since: Option<String>,
    /// RFC 3339 UTC, `...Z` with or without milliseconds.
    pub until: Option<String>,
    /// Cursor: only rows with a larger id.
    pub after_id: Option<i64>,
    /// Page size, 1..=1000 (0 means the maximum).
    pub limit: u32,
}

/// Outcome of [`Store::verify_audit_chain`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct ChainReport {
    /// Whether every row links to its predecessor and hashes to its stored hash.
    pub ok: bool,
    /// Rows checked.
    pub rows: u64,
    /// The first row that does not verify.
    pub first_bad_id: Option<i64>,
    /// Hash of the last row (64 zeros when empty); publish it to anchor the log externally.
    pub head_hash: String,
}

const MAX_FIELD: usize = 256;
const MAX_DETAILS: usize = 64 * 1024;

impl Store {
    /// Appends one row in its own `BEGIN IMMEDIATE` transaction.
    pub async fn append_audit(&self, e: AuditEntry) -> Result<AuditRow> {
        let mut tx = self.begin_immediate().await?;
        let row = append_in(&mut tx, &e).await?;
        tx.commit().await?;
        Ok(row)
    }

    /// Rows matching `f` in id order, and the cursor for the next page (`None` at the end).
    pub async fn audit_query(&self, f: &AuditFilter) -> Result<(Vec<AuditRow>, Option<i64>)> {
        let limit = if f.limit == 0 {
            MAX_AUDIT_PAGE
        } else {
            f.limit.min(MAX_AUDIT_PAGE)
        };
        let since = f.since.as_deref().map(normalize_time).transpose()?;
        let until = f.until.as_deref().map(normalize_time).transpose()?;
        // Filters in a fixed order, numbered $2.. (the same text on SQLite and PostgreSQL).
        let mut sql = String::from(
            "SELECT id, at, actor, action, asset_id, job_id, details, prev_hash, hash \
             FROM audit WHERE id > $1",
        );
        let mut texts: Vec<String> = Vec::new();
        let filters = [
            ("asset_id =", f.asset_id.map(|a| a.to_string())),
            ("action =", f.action.clone()),
            ("actor =", f.actor.clone()),
            ("at >=", since),
            ("at <=", until),
        ];
        for (cond, value) in filters {
            if let Some(v) = value {
                texts.push(v);
                sql.push_str(&format!(" AND {cond} ${}", texts.len() + 1));
            }
        }
        sql.push_str(&format!(" ORDER BY id LIMIT ${}", texts.len() + 2));
        let mut q = sqlx::query(AssertSqlSafe(sql)).bind(f.after_id.unwrap_or(0));
        for t in texts {
            q = q.bind(t);
        }
        let q = q.bind(i64::from(limit) + 1);
        let rows = q.fetch_all(&self.pool).await?;
        let mut out = rows.iter().map(decode_row).collect::<Result<Vec<_>>>()?;
        let next = if out.len() > limit as usize {
            out.truncate(limit as usize);
            out.last().map(|r| r.id)
        } else {
            None
        };
        Ok((out, next))
    }

    /// Walks the whole log in id order and checks every link and hash.
    pub async fn verify_audit_chain(&self) -> Result<ChainReport> {
        const BATCH: i64 = 5000;
        let mut expected_prev = GENESIS_HASH.to_owned();
        let mut rows = 0u64;
        let mut after = 0i64;
        let mut first_bad = None;
        loop {
            let batch = sqlx::query(
                "SELECT id, at, actor, action, asset_id, job_id, details, prev_hash, hash \
                 FROM audit WHERE id > $1 ORDER BY id LIMIT $2",
            )
            .bind(after)
            .bind(BATCH)
            .fetch_all(&self.pool)
            .await?;
            for r in &batch {
                let id: i64 = r.try_get("id")?;
                let prev: String = r.try_get("prev_hash")?;
                let hash: String = r.try_get("hash")?;
                let computed = chain_hash(
                    &prev,
                    id,
                    &r.try_get::<String, _>("at")?,
                    &r.try_get::<String, _>("actor")?,
                    &r.try_get::<String, _>("action")?,
                    r.try_get::<Option<String>, _>("asset_id")?.as_deref(),
                    r.try_get::<Option<String>, _>("job_id")?.as_deref(),
                    &r.try_get::<String, _>("details")?,
                );
                if first_bad.is_none() && (prev != expected_prev || computed != hash) {
                    first_bad = Some(id);
                }
                rows += 1;
                after = id;
                expected_prev = hash;
            }
            if (batch.len() as i64) < BATCH {
                break;
            }
        }
        Ok(ChainReport {
            ok: first_bad.is_none(),
            rows,
            first_bad_id: first_bad,
            head_hash: expected_prev,
        })
    }
}

/// Appends `e` on `conn`, which must be inside a `BEGIN IMMEDIATE` transaction (so no other
/// writer can read the same head and fork the chain).
pub(crate) async fn append_in(conn: &mut AnyConnection, e: &AuditEntry) -> Result<AuditRow> {
    validate_field("actor", &e.actor)?;
    validate_field("action", &e.action)?;
    let details = serde_json::to_string(&e.details)
        .map_err(|err| StoreError::invalid(format!("audit details: {err}")))?;
    if details.len() > MAX_DETAILS {
        return Err(StoreError::invalid("audit details exceed 64 KiB"));
    }
    let head = sqlx::query("SELECT id, hash FROM audit ORDER BY id DESC LIMIT 1")
        .fetch_optional(&mut *conn)
        .await?;
    let (id, prev_hash) = match head {
        Some(r) => (
            r.try_get::<i64, _>("id")? + 1,
            r.try_get::<String, _>("hash")?,
        ),
        None => (1, GENESIS_HASH.to_owned()),
    };
    let at = time::now();
    let asset = e.asset_id.map(|u| u.to_string());
    let job = e.job_id.map(|u| u.to_string());
    let hash = chain_hash(
        &prev_hash,
        id,
        &at,
        &e.actor,
        &e.action,
        asset.as_deref(),
        job.as_deref(),
        &details,
    );
    sqlx::query(
        "INSERT INTO audit (id, at, actor, action, asset_id, job_id, details, prev_hash, hash) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
    )
    .bind(id)
    .bind(&at)
    .bind(&e.actor)
    .bind(&e.action)
    .bind(&asset)
    .bind(&job)
    .bind(&details)
    .bind(&prev_hash)
    .bind(&hash)
    .execute(&mut *conn)
    .await?;
    Ok(AuditRow {
        id,
        at,
        actor: e.actor.clone(),
        action: e.action.clone(),
        asset_id: e.asset_id,
        job_id: e.job_id,
        details: e.details.clone(),
        prev_hash,
        hash,
    })
}

fn validate_field(name: &str, v: &str) -> Result<()> {
    if v.is_empty() || v.len() > MAX_FIELD || v.chars().any(char::is_control) {
        return Err(StoreError::invalid(format!(
            "audit {name} must be 1..={MAX_FIELD} bytes without control characters"
        )));
    }
    Ok(())
}

/// A `since`/`until` filter in the stored form ([`time::normalize_timestamp`]).
fn normalize_time(s: &str) -> Result<String> {
    time::normalize_timestamp(s).ok_or_else(|| {
        StoreError::invalid(
            "times must be RFC 3339 UTC like 2026-12-01T16:09:21Z or 2026-12-01T16:09:21.123Z",
        )
    })
}

/// `sha256(prev_hash || canonical bytes)`; strings are length-prefixed (u64 big-endian), options
/// carry a presence byte, so no two different rows share an encoding.
#[allow(clippy::too_many_arguments)]
pub(crate) fn chain_hash(
    prev_hash: &str,
    id: i64,
    at: &str,
    actor: &str,
    action: &str,
    asset_id: Option<&str>,
    job_id: Option<&str>,
    details: &str,
) -> String {
    fn put(h: &mut Sha256, s: &str) {
        h.update((s.len() as u64).to_be_bytes());
        h.update(s.as_bytes());
    }
    fn put_opt(h: &mut Sha256, s: Option<&str>) {
        match s {
            None => h.update([0u8]),
            Some(s) => {
                h.update([1u8]);
                put(h, s);
            }
        }
    }
    let mut h = Sha256::new();
    h.update(prev_hash.as_bytes());
    h.update(b"splatmark-audit-v1");
    h.update(id.to_be_bytes());
    put(&mut h, at);
    put(&mut h, actor);
    put(&mut h, action);
    put_opt(&mut h, asset_id);
    put_opt(&mut h, job_id);
    put(&mut h, details);
    hex::encode(h.finalize())
}

fn decode_row(r: &AnyRow) -> Result<AuditRow> {
    let details: String = r.try_get("details")?;
    Ok(AuditRow {
        id: r.try_get("id")?,
        at: r.try_get("at")?,
        actor: r.try_get("actor")?,
        action: r.try_get("action")?,
        asset_id: super::parse_opt_uuid(r.try_get("asset_id")?)?,
        job_id: super::parse_opt_uuid(r.try_get("job_id")?)?,
        details: serde_json::from_str(&details)
            .map_err(|e| StoreError::corrupt(format!("stored audit details: {e}")))?,
        prev_hash: r.try_get("prev_hash")?,
        hash: r.try_get("hash")?,
    })
}
