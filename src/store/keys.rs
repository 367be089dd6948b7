//! Each watermarked asset's key — the owner's message and a secret random mask — sealed with
//! XChaCha20-Poly1305 under the master key with the asset id as associated data (the mask with
//! `<asset id>/mask`). Plaintext never reaches the database or the log.
//!
//! # Why a mask
//! The service embeds the payload `message ⊕ mask`, the mask drawn from the operating system's
//! random source when the job is queued and never shown to anyone. A dispute tests decoded bits
//! against the payload. For an image that does not carry this asset's watermark, its decoded
//! bits are independent of the mask, so each matches the payload with probability exactly ½ and
//! the number of matches is exactly Binomial(n, ½) — whatever message the owner chose and
//! however biased the decoder's bits are on natural images (they are: `docs/DECODER.md`).
//! Without the mask an owner could register the decoder's favourite bit pattern as message and
//! "detect" it in images that carry no watermark at all.

use super::crypto::Sealed;
use super::error::{Result, StoreError};
use super::{Store, parse_uuid, time};
use crate::verify::message::random_message;
use sqlx::Row;
use sqlx::sqlite::{SqliteConnection, SqliteRow};
use uuid::Uuid;

/// Most bits a message may have.
pub const MAX_MESSAGE_BITS: usize = 4096;

/// A watermark's key: the owner's message and the secret mask; the embedded bits are
/// [`payload`](Self::payload). `Debug` prints neither (they are secrets).
#[derive(Clone, PartialEq, Eq)]
pub struct WatermarkKey {
    /// The owner's message.
    pub message: Vec<bool>,
    /// The secret mask, as long as the message (all zeros for keys stored before masks).
    pub mask: Vec<bool>,
}

impl WatermarkKey {
    /// A key for `message` with a fresh mask from the operating system's random source.
    pub fn draw(message: Vec<bool>) -> Self {
        let mask = random_message(message.len());
        Self { message, mask }
    }

    /// A key with the all-zero mask (payload = message): what rows stored before masks mean.
    pub fn unmasked(message: Vec<bool>) -> Self {
        let mask = vec![false; message.len()];
        Self { message, mask }
    }

    /// Message length.
    pub fn bits(&self) -> usize {
        self.message.len()
    }

    /// The bits the service embeds and a dispute tests: `message ⊕ mask`.
    pub fn payload(&self) -> Vec<bool> {
        self.message
            .iter()
            .zip(&self.mask)
            .map(|(m, k)| m ^ k)
            .collect()
    }
}

impl std::fmt::Debug for WatermarkKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WatermarkKey")
            .field("bits", &self.bits())
            .finish_non_exhaustive()
    }
}

/// The associated data of a mask sealed next to a message sealed under `aad`.
fn mask_aad(aad: &str) -> String {
    format!("{aad}/mask")
}

/// A key sealed for storage: message and mask.
pub(crate) struct SealedKey {
    pub message: Sealed,
    pub mask: Sealed,
}

impl Store {
    /// Seals `key` under `aad` (the message) and `aad/mask` (the mask).
    pub(crate) fn seal_key(&self, key: &WatermarkKey, aad: &str) -> Result<SealedKey> {
        validate_message(&key.message)?;
        if key.mask.len() != key.message.len() {
            return Err(StoreError::invalid(
                "the mask must be as long as the message",
            ));
        }
        Ok(SealedKey {
            message: self.cipher().seal_bits(&key.message, aad.as_bytes())?,
            mask: self
                .cipher()
                .seal_bits(&key.mask, mask_aad(aad).as_bytes())?,
        })
    }

    /// Opens the key of a row with columns `<prefix>nonce`, `<prefix>ciphertext` (or `…ct`)
    /// given as names, and `mask_nonce`, `mask_ct` (NULL = all-zero mask). `Crypto` when either
    /// does not open or their lengths differ.
    pub(crate) fn open_key(
        &self,
        r: &SqliteRow,
        nonce_col: &str,
        ct_col: &str,
        aad: &str,
    ) -> Result<WatermarkKey> {
        let message = self.cipher().open_bits(
            &r.try_get::<Vec<u8>, _>(nonce_col)?,
            &r.try_get::<Vec<u8>, _>(ct_col)?,
            aad.as_bytes(),
        )?;
        let mask_nonce: Option<Vec<u8>> = r.try_get("mask_nonce")?;
        let mask_ct: Option<Vec<u8>> = r.try_get("mask_ct")?;
        let key = match (mask_nonce, mask_ct) {
            (None, None) => WatermarkKey::unmasked(message),
            (Some(n), Some(c)) => WatermarkKey {
                mask: self.cipher().open_bits(&n, &c, mask_aad(aad).as_bytes())?,
                message,
            },
            _ => return Err(StoreError::Crypto),
        };
        if key.mask.len() != key.message.len() {
            return Err(StoreError::Crypto);
        }
        Ok(key)
    }
}

impl Store {
    /// The key of a watermarked asset (`None` when it has none); `Crypto` if it does not
    /// decrypt.
    pub async fn key_of(&self, asset: Uuid) -> Result<Option<WatermarkKey>> {
        let id = asset.to_string();
        let row = sqlx::query(
            "SELECT nonce, ciphertext, mask_nonce, mask_ct FROM keys WHERE asset_id = ?",
        )
        .bind(&id)
        .fetch_optional(&self.pool)
        .await?;
        match row {
            None => Ok(None),
            Some(r) => self.open_key(&r, "nonce", "ciphertext", &id).map(Some),
        }
    }

    /// Every registered key with its asset, oldest first (verification without an asset id).
    pub async fn all_keys(&self) -> Result<Vec<(Uuid, WatermarkKey)>> {
        let rows = sqlx::query(
            "SELECT asset_id, nonce, ciphertext, mask_nonce, mask_ct FROM keys \
             ORDER BY created_at, asset_id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let id: String = r.try_get("asset_id")?;
                let key = self.open_key(r, "nonce", "ciphertext", &id)?;
                Ok((parse_uuid(&id)?, key))
            })
            .collect()
    }

    /// Seals and inserts the key of `asset` on `conn` (inside the caller's transaction).
    pub(crate) async fn insert_key_in(
        &self,
        conn: &mut SqliteConnection,
        asset: Uuid,
        key: &WatermarkKey,
    ) -> Result<()> {
        let id = asset.to_string();
        let sealed = self.seal_key(key, &id)?;
        sqlx::query(
            "INSERT INTO keys (asset_id, bits, nonce, ciphertext, mask_nonce, mask_ct, created_at) \
             VALUES (?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(&id)
        .bind(key.bits() as i64)
        .bind(sealed.message.nonce)
        .bind(sealed.message.ciphertext)
        .bind(sealed.mask.nonce)
        .bind(sealed.mask.ciphertext)
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
