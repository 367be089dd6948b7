//! Dispute verifications: who submitted which images and what was decided.

use super::audit::{self, AuditEntry};
use super::blobs::is_blob_id;
use super::error::{Result, StoreError};
use super::{Store, time};
use serde::{Deserialize, Serialize};
use uuid::Uuid;

/// Most images one verification may list.
pub const MAX_IMAGES: usize = 1024;

/// A verification to record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NewVerification {
    /// Who asked (API key id).
    pub actor: String,
    /// The asset checked against, or `None` when every registered message was searched.
    pub asset_id: Option<Uuid>,
    /// Number of images submitted.
    pub images: u32,
    /// SHA-256 (lowercase hex) of each image.
    pub image_sha256: Vec<String>,
    /// The decision (bits, accuracies, p-values, ...).
    pub result: serde_json::Value,
}

impl Store {
    /// Records a verification and its audit row (`asset_id` filled in when `None`) in one
    /// transaction; returns the verification id and the audit row id.
    pub async fn record_verification(
        &self,
        v: NewVerification,
        mut audit_entry: AuditEntry,
    ) -> Result<(Uuid, i64)> {
        if v.image_sha256.len() > MAX_IMAGES || v.image_sha256.iter().any(|h| !is_blob_id(h)) {
            return Err(StoreError::invalid(format!(
                "image_sha256: at most {MAX_IMAGES} lowercase hex SHA-256 digests"
            )));
        }
        if v.actor.is_empty() || v.actor.len() > 255 {
            return Err(StoreError::invalid("actor must be 1..=255 bytes"));
        }
        let hashes = serde_json::to_string(&v.image_sha256)
            .map_err(|e| StoreError::invalid(format!("image_sha256: {e}")))?;
        let result = serde_json::to_string(&v.result)
            .map_err(|e| StoreError::invalid(format!("result: {e}")))?;
        let id = Uuid::new_v4();
        let mut tx = self.begin_immediate().await?;
        if let Some(a) = v.asset_id {
            audit_entry.asset_id.get_or_insert(a);
        }
        let row = audit::append_in(&mut tx, &audit_entry).await?;
        sqlx::query(
            "INSERT INTO verifications (id, actor, asset_id, images, image_sha256, result, \
             audit_id, created_at) VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
        )
        .bind(id.to_string())
        .bind(&v.actor)
        .bind(v.asset_id.map(|u| u.to_string()))
        .bind(i64::from(v.images))
        .bind(&hashes)
        .bind(&result)
        .bind(row.id)
        .bind(time::now())
        .execute(&mut *tx)
        .await
        .map_err(|e| match StoreError::from_db(e) {
            StoreError::Invalid(_) => StoreError::NotFound,
            other => other,
        })?;
        tx.commit().await?;
        Ok((id, row.id))
    }
}
