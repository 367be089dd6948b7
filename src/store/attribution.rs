//! Per-Gaussian attribution of a watermarked asset, stored compactly: integer columns for what
//! is filtered and sorted (index, role, parent) and a 88-byte little-endian f32 blob for the
//! rest, so every record round-trips bit-exactly (NaN included). Inserted with prepared
//! multi-row INSERTs inside the publishing transaction.

use super::Backend;
use super::error::{Result, StoreError};
use super::{Store, to_u64};
use crate::embed::attribution::AttributionRecord;
use crate::embed::sbag::Role;
use serde::Serialize;
use sqlx::AnyConnection;
use sqlx::any::AnyRow;
use sqlx::{AssertSqlSafe, Row};
use std::sync::OnceLock;
use uuid::Uuid;

/// Most records one [`Store::attribution_page`] returns.
pub const MAX_ATTRIBUTION_PAGE: u32 = 10_000;

/// Rows per multi-row INSERT (10 parameters each, well under SQLite's 32 766).
const BATCH: usize = 512;
/// f32 values in the `data` blob.
const FLOATS: usize = 22;
const COLUMNS: &str =
    "asset_seq, idx, role, parent, child, flags, utility, visibility, wm_grad_share, data";

const FEASIBLE: i64 = 1;
const SEED_SHIFT: i64 = 1;
const HAS_SHARE: i64 = 8;

/// Aggregates over one asset's attribution.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct AttributionSummary {
    /// Records (= Gaussians of the watermarked scene).
    pub gaussians: u64,
    pub carriers: u64,
    pub compensators: u64,
    pub untouched: u64,
    /// Distinct parents in the uploaded scene.
    pub distinct_parents: u64,
    /// Distinct parents that carry the message.
    pub carrier_parents: u64,
    /// Records whose parent was in the feasible set.
    pub feasible: u64,
    /// Σ wm_grad_share over carriers (`None` when no carrier has one).
    pub carrier_wm_grad_share_sum: Option<f64>,
    /// Mean utility u of carriers.
    pub carrier_mean_utility: Option<f64>,
    /// Mean utility u of compensators and untouched Gaussians.
    pub other_mean_utility: Option<f64>,
    /// Mean visibility v of carriers.
    pub carrier_mean_visibility: Option<f64>,
    /// Mean visibility v of the others.
    pub other_mean_visibility: Option<f64>,
}

impl Store {
    /// Records of `asset` in index order, optionally of one role, after the cursor `after_index`;
    /// at most `limit` (0 or more than 10 000 means 10 000). The second value is the cursor of
    /// the next page (`None` at the end). `NotFound` for an unknown asset.
    pub async fn attribution_page(
        &self,
        asset: Uuid,
        role: Option<Role>,
        after_index: Option<u32>,
        limit: u32,
    ) -> Result<(Vec<AttributionRecord>, Option<u32>)> {
        let limit = if limit == 0 {
            MAX_ATTRIBUTION_PAGE
        } else {
            limit.min(MAX_ATTRIBUTION_PAGE)
        };
        let seq = self.asset_seq(asset).await?;
        let after = after_index.map_or(-1, i64::from);
        let fetch = i64::from(limit) + 1;
        let rows = match role {
            None => {
                sqlx::query(
                    "SELECT idx, role, parent, child, flags, data FROM attribution \
                 WHERE asset_seq = $1 AND idx > $2 ORDER BY idx LIMIT $3",
                )
                .bind(seq)
                .bind(after)
                .bind(fetch)
                .fetch_all(&self.pool)
                .await?
            }
            Some(role) => {
                sqlx::query(
                    "SELECT idx, role, parent, child, flags, data FROM attribution \
                 WHERE asset_seq = $1 AND role = $2 AND idx > $3 ORDER BY idx LIMIT $4",
                )
                .bind(seq)
                .bind(role_code(role))
                .bind(after)
                .bind(fetch)
                .fetch_all(&self.pool)
                .await?
            }
        };
        let mut out = rows.iter().map(decode).collect::<Result<Vec<_>>>()?;
        let next = if out.len() > limit as usize {
            out.truncate(limit as usize);
            out.last().map(|r| r.index)
        } else {
            None
        };
        Ok((out, next))
    }

    /// Counts per role, distinct parents, the carriers' watermark-gradient share and mean
    /// utility / visibility of carriers against the rest. `NotFound` for an unknown asset.
    pub async fn attribution_summary(&self, asset: Uuid) -> Result<AttributionSummary> {
        let seq = self.asset_seq(asset).await?;
        let r = sqlx::query(
            "SELECT COUNT(*) AS n, \
               COUNT(CASE WHEN role = 0 THEN 1 END) AS carriers, \
               COUNT(CASE WHEN role = 1 THEN 1 END) AS compensators, \
               COUNT(CASE WHEN role = 2 THEN 1 END) AS untouched, \
               COUNT(DISTINCT parent) AS parents, \
               COUNT(DISTINCT CASE WHEN role = 0 THEN parent END) AS carrier_parents, \
               COUNT(CASE WHEN (flags & 1) = 1 THEN 1 END) AS feasible, \
               SUM(CASE WHEN role = 0 THEN wm_grad_share END) AS share, \
               AVG(CASE WHEN role = 0 THEN utility END) AS cu, \
               AVG(CASE WHEN role <> 0 THEN utility END) AS ou, \
               AVG(CASE WHEN role = 0 THEN visibility END) AS cv, \
               AVG(CASE WHEN role <> 0 THEN visibility END) AS ov \
             FROM attribution WHERE asset_seq = $1",
        )
        .bind(seq)
        .fetch_one(&self.pool)
        .await?;
        Ok(AttributionSummary {
            gaussians: to_u64(r.try_get("n")?)?,
            carriers: to_u64(r.try_get("carriers")?)?,
            compensators: to_u64(r.try_get("compensators")?)?,
            untouched: to_u64(r.try_get("untouched")?)?,
            distinct_parents: to_u64(r.try_get("parents")?)?,
            carrier_parents: to_u64(r.try_get("carrier_parents")?)?,
            feasible: to_u64(r.try_get("feasible")?)?,
            carrier_wm_grad_share_sum: r.try_get("share")?,
            carrier_mean_utility: r.try_get("cu")?,
            other_mean_utility: r.try_get("ou")?,
            carrier_mean_visibility: r.try_get("cv")?,
            other_mean_visibility: r.try_get("ov")?,
        })
    }

    /// The embed report stored when `asset` was published (`None` for an unknown asset or one
    /// without a report).
    pub async fn report_of(&self, asset: Uuid) -> Result<Option<serde_json::Value>> {
        let report: Option<Option<String>> =
            sqlx::query_scalar("SELECT report FROM assets WHERE id = $1")
                .bind(asset.to_string())
                .fetch_optional(&self.pool)
                .await?;
        match report.flatten() {
            None => Ok(None),
            Some(text) => serde_json::from_str(&text)
                .map(Some)
                .map_err(|e| StoreError::corrupt(format!("stored report: {e}"))),
        }
    }

    /// The compact handle of an asset (`NotFound` when unknown).
    pub(crate) async fn asset_seq(&self, asset: Uuid) -> Result<i64> {
        sqlx::query_scalar("SELECT seq FROM assets WHERE id = $1")
            .bind(asset.to_string())
            .fetch_optional(&self.pool)
            .await?
            .ok_or(StoreError::NotFound)
    }
}

/// Inserts `records` for the asset with handle `seq` on `conn` (inside the caller's
/// transaction). Duplicate indices are a `Conflict`.
pub(crate) async fn insert_in(
    conn: &mut AnyConnection,
    backend: Backend,
    seq: i64,
    records: &[AttributionRecord],
) -> Result<()> {
    static FULL: [OnceLock<String>; 2] = [OnceLock::new(), OnceLock::new()];
    let full: &'static str = FULL[backend as usize].get_or_init(|| insert_sql(BATCH, backend));
    for chunk in records.chunks(BATCH) {
        let mut q = if chunk.len() == BATCH {
            sqlx::query(full)
        } else {
            // One-off statement for the tail: keep it out of the statement cache.
            sqlx::query(AssertSqlSafe(insert_sql(chunk.len(), backend))).persistent(false)
        };
        for rec in chunk {
            let (flags, data) = encode(rec);
            let finite = |x: f32| (!x.is_nan()).then_some(f64::from(x));
            let [(u, has_u), (v, has_v), (w, has_w)] = [
                finite(rec.utility),
                finite(rec.visibility),
                rec.wm_grad_share.and_then(finite),
            ]
            .map(super::nullable_f64);
            q = q
                .bind(seq)
                .bind(i64::from(rec.index))
                .bind(role_code(rec.role))
                .bind(i64::from(rec.parent))
                .bind(i64::from(rec.child))
                .bind(flags)
                .bind(has_u)
                .bind(u)
                .bind(has_v)
                .bind(v)
                .bind(has_w)
                .bind(w)
                .bind(data);
        }
        q.execute(&mut *conn).await.map_err(StoreError::from_db)?;
    }
    Ok(())
}

/// Bound values per row: six integers, three nullable doubles as (present, value), the blob.
const PARAMS_PER_ROW: usize = 13;

/// The INSERT of `rows` records, parameters in the order they are bound: `$N` on PostgreSQL,
/// anonymous `?` on SQLite — SQLite keeps the names of numbered parameters (`$N`, `?N`) in a
/// list that binding each of them searches, which made publishing 1 M records 45× slower
/// (160 s against 3.8 s; docs/BENCHMARKS.md).
fn insert_sql(rows: usize, backend: Backend) -> String {
    let p = |k: usize| match backend {
        Backend::Sqlite => "?".to_string(),
        Backend::Postgres => format!("${k}"),
    };
    let mut s = format!("INSERT INTO attribution ({COLUMNS}) VALUES ");
    for i in 0..rows {
        let p = |k: usize| p(i * PARAMS_PER_ROW + k);
        let nullable =
            |present: usize| format!("CASE WHEN {} = 1 THEN {} END", p(present), p(present + 1));
        if i > 0 {
            s.push(',');
        }
        s.push_str(&format!(
            "({},{},{},{},{},{},{},{},{},{})",
            p(1),
            p(2),
            p(3),
            p(4),
            p(5),
            p(6),
            nullable(7),
            nullable(9),
            nullable(11),
            p(13)
        ));
    }
    s
}

/// The stored code of a role.
pub(crate) fn role_code(r: Role) -> i64 {
    match r {
        Role::Carrier => 0,
        Role::Compensator => 1,
        Role::Untouched => 2,
    }
}

fn role_of(code: i64) -> Result<Role> {
    match code {
        0 => Ok(Role::Carrier),
        1 => Ok(Role::Compensator),
        2 => Ok(Role::Untouched),
        _ => Err(StoreError::corrupt(format!("attribution role {code}"))),
    }
}

/// Flags and the float blob of a record.
fn encode(r: &AttributionRecord) -> (i64, Vec<u8>) {
    let seed = match r.seed {
        None => 0,
        Some(false) => 1,
        Some(true) => 2,
    };
    let mut flags = (i64::from(r.feasible) * FEASIBLE) | (seed << SEED_SHIFT);
    if r.wm_grad_share.is_some() {
        flags |= HAS_SHARE;
    }
    let share = r.wm_grad_share.unwrap_or(0.0);
    let mut data = Vec::with_capacity(FLOATS * 4);
    let floats =
        r.r.iter()
            .chain(&r.uncertainty)
            .chain(&r.quality)
            .chain([&r.utility, &r.visibility])
            .chain(&r.mask_wm)
            .chain(&r.mask_vis)
            .chain([&share]);
    for x in floats {
        data.extend_from_slice(&x.to_le_bytes());
    }
    (flags, data)
}

fn decode(row: &AnyRow) -> Result<AttributionRecord> {
    let data: Vec<u8> = row.try_get("data")?;
    if data.len() != FLOATS * 4 {
        return Err(StoreError::corrupt(format!(
            "attribution data of {} bytes",
            data.len()
        )));
    }
    let mut f = [0f32; FLOATS];
    for (x, b) in f.iter_mut().zip(data.chunks_exact(4)) {
        *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
    let flags: i64 = row.try_get("flags")?;
    let int = |col: &str| -> Result<u32> {
        let v: i64 = row.try_get(col)?;
        u32::try_from(v).map_err(|_| StoreError::corrupt(format!("attribution {col} = {v}")))
    };
    let child =
        u8::try_from(int("child")?).map_err(|_| StoreError::corrupt("attribution child"))?;
    let seed = match (flags >> SEED_SHIFT) & 3 {
        0 => None,
        1 => Some(false),
        2 => Some(true),
        _ => return Err(StoreError::corrupt("attribution seed flag")),
    };
    let take = |i: usize| [f[i], f[i + 1], f[i + 2]];
    let take5 = |i: usize| [f[i], f[i + 1], f[i + 2], f[i + 3], f[i + 4]];
    Ok(AttributionRecord {
        index: int("idx")?,
        role: role_of(row.try_get("role")?)?,
        parent: int("parent")?,
        child,
        r: take(0),
        uncertainty: take(3),
        quality: take(6),
        utility: f[9],
        visibility: f[10],
        feasible: flags & FEASIBLE != 0,
        seed,
        mask_wm: take5(11),
        mask_vis: take5(16),
        wm_grad_share: (flags & HAS_SHARE != 0).then_some(f[21]),
    })
}
