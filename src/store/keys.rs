//! Each watermarked asset's message ("key"), sealed with XChaCha20-Poly1305 under the master key
//! with the asset id as associated data. Plaintext never reaches the database or the log.

use super::error::{Result, StoreError};
use super::{Store, parse_uuid, time};
use sqlx::Row;
use sqlx::sqlite::SqliteConnection;
use uuid::Uuid;

/// Most bits a message may have.
pub const MAX_MESSAGE_BITS: usize = 4096;

impl Store {
    /// The message of a watermarked asset (`None` when it has none); `Crypto` if it does not
    /// decrypt.
    pub async fn message_of(&self, asset: Uuid) -> Result<Option<Vec<bool>>> {
        let id = asset.to_string();
        let row = sqlx::query("SELECT nonce, ciphertext FROM keys WHERE asset_id = ?")
            .bind(&id)
            .fetch_optional(&self.pool)
            .await?;
        let Some(r) = row else { return Ok(None) };
        let nonce: Vec<u8> = r.try_get("nonce")?;
        let ct: Vec<u8> = r.try_get("ciphertext")?;
        self.cipher()
            .open_bits(&nonce, &ct, id.as_bytes())
            .map(Some)
    }

    /// Every registered message with its asset, oldest first (verification without an asset id).
    pub async fn all_messages(&self) -> Result<Vec<(Uuid, Vec<bool>)>> {
        let rows = sqlx::query(
            "SELECT asset_id, nonce, ciphertext FROM keys ORDER BY created_at, asset_id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let id: String = r.try_get("asset_id")?;
                let nonce: Vec<u8> = r.try_get("nonce")?;
                let ct: Vec<u8> = r.try_get("ciphertext")?;
                let bits = self.cipher().open_bits(&nonce, &ct, id.as_bytes())?;
                Ok((parse_uuid(&id)?, bits))
            })
            .collect()
    }

    /// Seals and inserts the message of `asset` on `conn` (inside the caller's transaction).
    pub(crate) async fn insert_key_in(
        &self,
        conn: &mut SqliteConnection,
        asset: Uuid,
        message: &[bool],
    ) -> Result<()> {
        validate_message(message)?;
        let id = asset.to_string();
        let sealed = self.cipher().seal_bits(message, id.as_bytes())?;
        sqlx::query(
            "INSERT INTO keys (asset_id, bits, nonce, ciphertext, created_at) VALUES (?, ?, ?, ?, ?)",
        )
        .bind(&id)
        .bind(message.len() as i64)
        .bind(sealed.nonce)
        .bind(sealed.ciphertext)
        .bind(time::now())
        .execute(&mut *conn)
        .await
        .map_err(StoreError::from_db)?;
        Ok(())
    }
}

/// A message must have 1..=4096 bits.
pub(crate) fn validate_message(message: &[bool]) -> Result<()> {
    if message.is_empty() || message.len() > MAX_MESSAGE_BITS {
        return Err(StoreError::invalid(format!(
            "a message has 1..={MAX_MESSAGE_BITS} bits"
        )));
    }
    Ok(())
}
