//! Publishing a job's result exactly once.

use super::assets::{self, Asset, AssetKind, NewAsset};
use super::attribution;
use super::audit::{self, AuditEntry};
use super::error::{Result, StoreError};
use super::keys::{Readout, WatermarkKey, validate_message};
use super::{Store, time};
use crate::embed::attribution::AttributionRecord;
use sqlx::Row;
use uuid::Uuid;

impl Store {
    /// Publishes the result of `job` in one `BEGIN IMMEDIATE` transaction, all or nothing: checks
    /// that the job is running under `token` (else `LeaseLost`, nothing written), inserts the
    /// watermarked asset (`source_job_id` = the job, unique; `parent_id` = the job's asset when
    /// `None`), its sealed key (which must be the job's) and `readout` (asset reference, matched
    /// head, decoder digest: how a dispute reads the bits), every attribution record and the
    /// embed `report`, marks the job done with `result_asset_id`, and appends the audit row
    /// (`asset_id`, `job_id` filled in when `None`). A second publish, a stale token or a lease taken over by another worker
    /// writes nothing. `Invalid` when the asset or message does not match the job (the job keeps
    /// running; the worker should `fail` it).
    #[allow(clippy::too_many_arguments)]
    pub async fn publish_result(
        &self,
        job: Uuid,
        token: Uuid,
        mut asset: NewAsset,
        key: &WatermarkKey,
        readout: &Readout,
        attribution: &[AttributionRecord],
        report: serde_json::Value,
        mut audit_entry: AuditEntry,
    ) -> Result<Asset> {
        validate_message(&key.message)?;
        readout.validate(key.bits())?;
        if asset.kind != AssetKind::Watermarked {
            return Err(StoreError::invalid("a job publishes a watermarked asset"));
        }
        if *asset.source_job_id.get_or_insert(job) != job {
            return Err(StoreError::invalid("source_job_id is not this job"));
        }
        if !attribution.is_empty() && attribution.len() as u64 != asset.gaussians {
            return Err(StoreError::invalid(format!(
                "{} attribution records for {} Gaussians",
                attribution.len(),
                asset.gaussians
            )));
        }
        let report = serde_json::to_string(&report)
            .map_err(|e| StoreError::invalid(format!("report: {e}")))?;

        let mut tx = self.begin_immediate().await?;
        let id = job.to_string();
        let row = sqlx::query(
            "SELECT asset_id, bits, message_nonce, message_ct, mask_nonce, mask_ct FROM jobs \
             WHERE id = $1 AND state = 'running' AND lease_token = $2",
        )
        .bind(&id)
        .bind(token.to_string())
        .fetch_optional(&mut *tx)
        .await?
        .ok_or(StoreError::LeaseLost)?;
        let original: String = row.try_get("asset_id")?;
        let bits: i64 = row.try_get("bits")?;
        if bits != key.bits() as i64 {
            return Err(StoreError::invalid(format!(
                "the job embeds {bits} bits, the message has {}",
                key.bits()
            )));
        }
        if self.open_key(
            &row,
            "message_nonce",
            "message_ct",
            &super::jobs::job_aad(&id),
        )? != *key
        {
            return Err(StoreError::invalid("the key is not the job's"));
        }
        let original = super::parse_uuid(&original)?;
        if *asset.parent_id.get_or_insert(original) != original {
            return Err(StoreError::invalid("parent_id is not the job's asset"));
        }
        self.validate_asset(&asset)?;
        self.check_blobs(&asset).await?;

        let stored = assets::insert_in(&mut tx, &asset).await?;
        let seq: i64 = sqlx::query_scalar("SELECT seq FROM assets WHERE id = $1")
            .bind(stored.id.to_string())
            .fetch_one(&mut *tx)
            .await?;
        sqlx::query("UPDATE assets SET report = $1 WHERE seq = $2")
            .bind(&report)
            .bind(seq)
            .execute(&mut *tx)
            .await?;
        self.insert_key_in(&mut tx, stored.id, key, readout).await?;
        attribution::insert_in(&mut tx, self.backend(), seq, attribution).await?;
        let now = time::now();
        sqlx::query(
            "UPDATE jobs SET state = 'done', result_asset_id = $1, lease_token = NULL, \
             lease_expires_at = NULL, error = NULL, updated_at = $2 WHERE id = $3",
        )
        .bind(stored.id.to_string())
        .bind(&now)
        .bind(&id)
        .execute(&mut *tx)
        .await?;
        audit_entry.asset_id.get_or_insert(stored.id);
        audit_entry.job_id.get_or_insert(job);
        audit::append_in(&mut tx, &audit_entry).await?;
        tx.commit().await?;
        Ok(stored)
    }
}
