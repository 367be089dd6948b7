//! Assets: uploaded originals and the watermarked scenes published from them.

use super::audit::{self, AuditEntry};
use super::blobs::{BlobRef, PinnedBlob, is_blob_id};
use super::error::{Result, StoreError};
use super::{Store, parse_opt_uuid, parse_uuid, time, to_i64, to_u64};
use crate::scene::Format;
use serde::{Deserialize, Serialize};
use sqlx::AnyConnection;
use sqlx::Row;
use sqlx::any::AnyRow;
use uuid::Uuid;

/// Scene formats an asset may have: the scene reader's names ([`Format::as_str`]), so that what
/// the reader detects is always what the database accepts.
pub const SCENE_FORMATS: [&str; 5] = [
    Format::ALL[0].as_str(),
    Format::ALL[1].as_str(),
    Format::ALL[2].as_str(),
    Format::ALL[3].as_str(),
    Format::ALL[4].as_str(),
];
const MAX_NAME: usize = 255;

/// Whether an asset was uploaded or made by watermarking.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AssetKind {
    /// Uploaded by its owner.
    Original,
    /// Published by a watermarking job.
    Watermarked,
}

impl AssetKind {
    /// The stored / serialized name.
    pub fn as_str(self) -> &'static str {
        match self {
            AssetKind::Original => "original",
            AssetKind::Watermarked => "watermarked",
        }
    }

    fn parse(s: &str) -> Result<Self> {
        match s {
            "original" => Ok(AssetKind::Original),
            "watermarked" => Ok(AssetKind::Watermarked),
            _ => Err(StoreError::corrupt(format!("asset kind {s:?}"))),
        }
    }
}

/// An asset to insert; its blobs must already be committed to the [`super::BlobStore`].
#[derive(Clone, Debug, PartialEq)]
pub struct NewAsset {
    pub owner: String,
    pub kind: AssetKind,
    /// The original a watermarked asset was made from.
    pub parent_id: Option<Uuid>,
    /// The job that made a watermarked asset (unique: one result per job).
    pub source_job_id: Option<Uuid>,
    /// The scene file.
    pub blob: BlobRef,
    /// "ply", "compressed_ply", "splat", "spz" or "sog" ([`Format::as_str`];
    /// [`Format::parse`]'s other spellings are accepted and stored under the canonical name).
    pub format: String,
    /// The name the owner gave the file (shown back, never used as a path).
    pub file_name: Option<String>,
    pub gaussians: u64,
    pub sh_degree: u8,
    /// A camera file uploaded with the scene.
    pub cameras_blob: Option<BlobRef>,
    pub cameras_format: Option<String>,
}

/// A stored asset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Asset {
    pub id: Uuid,
    pub owner: String,
    pub kind: AssetKind,
    pub parent_id: Option<Uuid>,
    pub source_job_id: Option<Uuid>,
    /// Blob id of the scene file.
    pub sha256: String,
    pub size: u64,
    pub format: String,
    pub file_name: Option<String>,
    pub gaussians: u64,
    pub sh_degree: u8,
    /// Blob id of the camera file, if any.
    pub cameras_sha256: Option<String>,
    pub cameras_format: Option<String>,
    /// RFC 3339 UTC.
    pub created_at: String,
}

/// What [`Store::collect_garbage`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct GcReport {
    /// Blobs on disk.
    pub scanned: u64,
    /// Unreferenced blobs old enough, removed.
    pub removed: u64,
    /// Their bytes.
    pub bytes: u64,
}

impl Store {
    /// Removes blobs that no asset references (scene or cameras) and that are older than
    /// `min_age` — left by a publish or an upload that failed after its blob was committed.
    /// Committing touches a blob, so the age rule protects blobs whose asset row is about to be
    /// written, whichever process committed them. The blobs are listed without a lock; the
    /// candidates are then checked again and removed under the database's write lock: each is
    /// still unreferenced (rows are only written under that lock, after their blobs were
    /// checked under it too) and still old enough (a commit of the same bytes by any replica
    /// since the listing made it young). One audit row "blob.gc" when anything was removed.
    /// Cached copies of S3 blobs older than `CACHE_MAX_AGE` (a day) are dropped too.
    pub async fn collect_garbage(&self, min_age: std::time::Duration) -> Result<GcReport> {
        let blobs = self.blobs().clone();
        let listed = tokio::task::spawn_blocking(move || {
            blobs.prune_cache(CACHE_MAX_AGE);
            blobs.list()
        })
        .await
        .map_err(join_error)??;
        let mut report = GcReport {
            scanned: listed.len() as u64,
            ..GcReport::default()
        };
        let referenced = referenced_blobs(&mut *self.pool.acquire().await?).await?;
        let candidates: Vec<String> = listed
            .into_iter()
            .filter(|b| {
                !referenced.contains(&b.id) && b.age >= min_age && !self.blobs().is_pinned(&b.id)
            })
            .map(|b| b.id)
            .collect();
        if candidates.is_empty() {
            return Ok(report);
        }
        let mut tx = self.begin_immediate().await?;
        let referenced = referenced_blobs(&mut tx).await?;
        let candidates: Vec<String> = candidates
            .into_iter()
            .filter(|id| !referenced.contains(id))
            .collect();
        let blobs = self.blobs().clone();
        let removed = tokio::task::spawn_blocking(move || {
            let mut removed = Vec::new();
            for id in candidates {
                match blobs.remove_if_old(&id, min_age) {
                    Ok(Some(size)) => removed.push((id, size)),
                    Ok(None) => {}
                    Err(e) => tracing::warn!(blob = %id, error = %e, "could not remove a blob"),
                }
            }
            removed
        })
        .await
        .map_err(join_error)?;
        if removed.is_empty() {
            tx.rollback().await?;
            return Ok(report);
        }
        report.removed = removed.len() as u64;
        report.bytes = removed.iter().map(|(_, size)| size).sum();
        let mut entry = AuditEntry::new("system", "blob.gc");
        entry.details = serde_json::json!({
            "removed": report.removed,
            "bytes": report.bytes,
            "blobs": removed.iter().map(|(id, _)| id).collect::<Vec<_>>(),
        });
        audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok(report)
    }

    /// Removes the blobs an operation committed for a row it then failed to write (a rejected
    /// upload), so that a failed request leaves nothing behind: each pinned blob that no asset
    /// references and that no other pin of this process holds (a concurrent upload of the same
    /// bytes) is deleted. Runs under the database's write lock, so no row referencing the blob
    /// can be written meanwhile (a replica that committed the same bytes at the same moment
    /// finds its blob gone when it checks it under the lock, and its request fails cleanly;
    /// no row ever references a missing blob). Returns how many blobs were removed.
    pub async fn discard_unreferenced(&self, pins: Vec<PinnedBlob>) -> Result<u64> {
        if pins.is_empty() {
            return Ok(0);
        }
        let mut tx = self.begin_immediate().await?;
        let mut unused = Vec::new();
        for (i, pin) in pins.iter().enumerate() {
            let id = &pin.blob().sha256;
            if pins[..i].iter().any(|p| &p.blob().sha256 == id) {
                continue;
            }
            let used: i64 = sqlx::query_scalar(
                "SELECT COUNT(*) FROM assets WHERE sha256 = $1 OR cameras_sha256 = $2",
            )
            .bind(id)
            .bind(id)
            .fetch_one(&mut *tx)
            .await?;
            if used == 0 {
                unused.push(i);
            }
        }
        let blobs = self.blobs().clone();
        let removed = tokio::task::spawn_blocking(move || {
            // The same bytes may be pinned twice by the caller (scene and cameras alike).
            let own = |id: &str| pins.iter().filter(|p| p.blob().sha256 == id).count();
            let mut removed = 0;
            for i in unused {
                let pin = &pins[i];
                if blobs.remove_if_only_pin(pin, own(&pin.blob().sha256))? {
                    removed += 1;
                }
            }
            Ok::<_, std::io::Error>(removed)
        })
        .await
        .map_err(join_error)??;
        tx.rollback().await?;
        Ok(removed)
    }

    /// Inserts an asset and its audit row (`asset_id` filled in when `None`) in one transaction.
    /// `Invalid` for bad fields, a missing blob or a blob of another size; nothing is written then.
    pub async fn insert_asset(&self, a: NewAsset, mut audit_entry: AuditEntry) -> Result<Asset> {
        self.validate_asset(&a)?;
        let mut tx = self.begin_immediate().await?;
        self.check_blobs(&a).await?;
        let asset = insert_in(&mut tx, &a).await?;
        audit_entry.asset_id.get_or_insert(asset.id);
        audit::append_in(&mut tx, &audit_entry).await?;
        tx.commit().await?;
        Ok(asset)
    }

    /// One asset.
    pub async fn get_asset(&self, id: Uuid) -> Result<Option<Asset>> {
        let sql = "SELECT id, owner, kind, parent_id, source_job_id, sha256, size, format, \
                   file_name, gaussians, sh_degree, cameras_sha256, cameras_format, created_at \
                   FROM assets WHERE id = $1";
        let row = sqlx::query(sql)
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(decode_asset).transpose()
    }

    /// Assets newest first — `owner`'s, or everyone's when `None` — after the cursor `before`
    /// (a value this function returned), at most `limit` (1 to 1 000). The second value is the
    /// cursor of the next page (`None` at the end).
    pub async fn list_assets(
        &self,
        owner: Option<&str>,
        before: Option<i64>,
        limit: u32,
    ) -> Result<(Vec<Asset>, Option<i64>)> {
        let limit = i64::from(limit.clamp(1, 1000));
        let sql = "SELECT id, owner, kind, parent_id, source_job_id, sha256, size, format, \
                   file_name, gaussians, sh_degree, cameras_sha256, cameras_format, created_at, \
                   seq FROM assets WHERE ($1 IS NULL OR owner = $2) AND seq < $3 \
                   ORDER BY seq DESC LIMIT $4";
        let rows = sqlx::query(sql)
            .bind(owner)
            .bind(owner)
            .bind(before.unwrap_or(i64::MAX))
            .bind(limit + 1)
            .fetch_all(&self.pool)
            .await?;
        let more = rows.len() as i64 > limit;
        let rows = &rows[..rows.len().min(limit as usize)];
        let next = if more {
            rows.last()
                .map(|r| r.try_get::<i64, _>("seq"))
                .transpose()?
        } else {
            None
        };
        Ok((rows.iter().map(decode_asset).collect::<Result<_>>()?, next))
    }

    /// The watermarked assets made from `original`, oldest first.
    pub async fn watermarked_of(&self, original: Uuid) -> Result<Vec<Asset>> {
        let sql = "SELECT id, owner, kind, parent_id, source_job_id, sha256, size, format, \
                   file_name, gaussians, sh_degree, cameras_sha256, cameras_format, created_at \
                   FROM assets WHERE parent_id = $1 AND kind = 'watermarked' \
                   ORDER BY created_at, seq";
        let rows = sqlx::query(sql)
            .bind(original.to_string())
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(decode_asset).collect()
    }

    /// Field checks (the blobs are checked by [`Self::check_blobs`]).
    pub(crate) fn validate_asset(&self, a: &NewAsset) -> Result<()> {
        if a.owner.is_empty() || a.owner.len() > MAX_NAME || a.owner.chars().any(char::is_control) {
            return Err(StoreError::invalid(
                "owner must be 1..=255 bytes, no control characters",
            ));
        }
        if Format::parse(&a.format).is_none() {
            return Err(StoreError::invalid(format!(
                "unknown scene format {:?} (expected one of {})",
                a.format,
                SCENE_FORMATS.join(", ")
            )));
        }
        if let Some(n) = &a.file_name
            && (n.len() > MAX_NAME || n.chars().any(char::is_control))
        {
            return Err(StoreError::invalid(
                "file name must be <= 255 bytes, no control characters",
            ));
        }
        if a.sh_degree > 3 {
            return Err(StoreError::invalid("sh_degree must be 0..=3"));
        }
        to_i64(a.gaussians)?;
        match a.kind {
            AssetKind::Original if a.parent_id.is_some() || a.source_job_id.is_some() => {
                return Err(StoreError::invalid(
                    "an original has no parent or source job",
                ));
            }
            AssetKind::Watermarked if a.parent_id.is_none() => {
                return Err(StoreError::invalid("a watermarked asset needs its parent"));
            }
            _ => {}
        }
        check_blob_id(&a.blob)?;
        match (&a.cameras_blob, &a.cameras_format) {
            (None, None) => {}
            (Some(b), Some(f)) => {
                let token = |c: char| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_';
                if f.is_empty() || f.len() > 32 || !f.chars().all(token) {
                    return Err(StoreError::invalid(
                        "camera format must be 1..=32 of [a-z0-9_] (e.g. \"inria\", \"nerf\", \"llff\")",
                    ));
                }
                check_blob_id(b)?;
            }
            _ => {
                return Err(StoreError::invalid(
                    "cameras_blob and cameras_format go together",
                ));
            }
        }
        Ok(())
    }

    /// The asset's blobs are stored with their sizes (`Invalid` otherwise). Called under the
    /// write lock, just before the row is written: the garbage collector of any replica
    /// removes blobs under that lock only, so a blob checked here stays until the row exists.
    pub(crate) async fn check_blobs(&self, a: &NewAsset) -> Result<()> {
        let blobs = self.blobs().clone();
        let wanted: Vec<BlobRef> = std::iter::once(a.blob.clone())
            .chain(a.cameras_blob.clone())
            .collect();
        tokio::task::spawn_blocking(move || {
            for b in &wanted {
                match blobs.size_of(&b.sha256) {
                    Ok(size) if size == b.size => {}
                    Ok(size) => {
                        return Err(StoreError::invalid(format!(
                            "blob {} has {size} bytes, not {}",
                            b.sha256, b.size
                        )));
                    }
                    Err(StoreError::NotFound) => {
                        return Err(StoreError::invalid(format!(
                            "blob {} is not stored",
                            b.sha256
                        )));
                    }
                    Err(e) => return Err(e),
                }
            }
            Ok(())
        })
        .await
        .map_err(join_error)?
    }
}

/// How long a cached copy of an S3 blob stays in the local cache.
pub const CACHE_MAX_AGE: std::time::Duration = std::time::Duration::from_secs(24 * 3600);

fn check_blob_id(b: &BlobRef) -> Result<()> {
    if is_blob_id(&b.sha256) {
        Ok(())
    } else {
        Err(StoreError::invalid(
            "blob id must be 64 lowercase hex digits",
        ))
    }
}

/// A blocking task that panicked or was cancelled.
fn join_error(e: tokio::task::JoinError) -> StoreError {
    StoreError::Io(std::io::Error::other(e))
}

/// Every blob an asset references (scene or cameras).
async fn referenced_blobs(conn: &mut AnyConnection) -> Result<std::collections::HashSet<String>> {
    Ok(sqlx::query_scalar(
        "SELECT sha256 FROM assets UNION SELECT cameras_sha256 FROM assets \
         WHERE cameras_sha256 IS NOT NULL",
    )
    .fetch_all(conn)
    .await?
    .into_iter()
    .collect())
}

/// Inserts a validated asset on `conn` (inside the caller's transaction).
pub(crate) async fn insert_in(conn: &mut AnyConnection, a: &NewAsset) -> Result<Asset> {
    let asset = Asset {
        id: Uuid::new_v4(),
        owner: a.owner.clone(),
        kind: a.kind,
        parent_id: a.parent_id,
        source_job_id: a.source_job_id,
        sha256: a.blob.sha256.clone(),
        size: a.blob.size,
        format: Format::parse(&a.format)
            .map_or_else(|| a.format.clone(), |f| f.as_str().to_string()),
        file_name: a.file_name.clone(),
        gaussians: a.gaussians,
        sh_degree: a.sh_degree,
        cameras_sha256: a.cameras_blob.as_ref().map(|b| b.sha256.clone()),
        cameras_format: a.cameras_format.clone(),
        created_at: time::now(),
    };
    sqlx::query(
        "INSERT INTO assets (id, owner, kind, parent_id, source_job_id, sha256, size, format, \
         file_name, gaussians, sh_degree, cameras_sha256, cameras_format, created_at) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14)",
    )
    .bind(asset.id.to_string())
    .bind(&asset.owner)
    .bind(asset.kind.as_str())
    .bind(asset.parent_id.map(|u| u.to_string()))
    .bind(asset.source_job_id.map(|u| u.to_string()))
    .bind(&asset.sha256)
    .bind(to_i64(asset.size)?)
    .bind(&asset.format)
    .bind(&asset.file_name)
    .bind(to_i64(asset.gaussians)?)
    .bind(i64::from(asset.sh_degree))
    .bind(&asset.cameras_sha256)
    .bind(&asset.cameras_format)
    .bind(&asset.created_at)
    .execute(&mut *conn)
    .await
    .map_err(StoreError::from_db)?;
    Ok(asset)
}

pub(crate) fn decode_asset(r: &AnyRow) -> Result<Asset> {
    let id: String = r.try_get("id")?;
    let kind: String = r.try_get("kind")?;
    let sh: i64 = r.try_get("sh_degree")?;
    Ok(Asset {
        id: parse_uuid(&id)?,
        owner: r.try_get("owner")?,
        kind: AssetKind::parse(&kind)?,
        parent_id: parse_opt_uuid(r.try_get("parent_id")?)?,
        source_job_id: parse_opt_uuid(r.try_get("source_job_id")?)?,
        sha256: r.try_get("sha256")?,
        size: to_u64(r.try_get("size")?)?,
        format: r.try_get("format")?,
        file_name: r.try_get("file_name")?,
        gaussians: to_u64(r.try_get("gaussians")?)?,
        sh_degree: u8::try_from(sh).map_err(|_| StoreError::corrupt("sh_degree"))?,
        cameras_sha256: r.try_get("cameras_sha256")?,
        cameras_format: r.try_get("cameras_format")?,
        created_at: r.try_get("created_at")?,
    })
}
