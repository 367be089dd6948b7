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
//!
//! # The asset reference
//! A job that decodes relative to the asset (`embed.reference`) also registers the original's
//! mean logits over its training views ([`Registration::reference`]); a dispute subtracts them
//! before reading bits. They are computed from the unmarked original, so they are independent of
//! the mask and the Binomial(n, ½) argument above still holds. Sealed too (AAD
//! `<asset id>/reference`), so that they cannot be changed unnoticed.
//!
//! # The matched head
//! A job whose embedding read the bits through a matched head (`embed.projection.matched`, eq.
//! `matchedhead`) registers it ([`Registration::head`]); a dispute reads the candidate's bits
//! through it. Fitted on the unmarked original alone, so the argument above holds for it too.
//! Sealed as JSON (AAD `<asset id>/head`).

use super::crypto::Sealed;
use super::error::{Result, StoreError};
use super::{Store, parse_uuid, time};
use crate::decoder::projection::ViewProjection;
use crate::verify::message::random_message;
use sqlx::AnyConnection;
use sqlx::Row;
use sqlx::any::AnyRow;
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

/// A registered watermark: what a dispute tests images against.
#[derive(Clone, Debug)]
pub struct Registration {
    /// The watermarked asset.
    pub asset_id: Uuid,
    pub key: WatermarkKey,
    /// The asset reference (one logit per bit), when the job decoded relative to the asset.
    pub reference: Option<Vec<f32>>,
    /// The asset's matched head, when the job read the bits through one.
    pub head: Option<ViewProjection>,
    /// The digest of the decoder the bits were written for
    /// ([`crate::decoder::artifact::digest_of`]); `None` for keys registered before it was
    /// recorded (their bits are read with the server's current decoder).
    pub decoder: Option<String>,
}

/// The associated data of a decoder digest sealed for asset `id`.
fn decoder_aad(id: &str) -> String {
    format!("{id}/decoder")
}

/// A decoder digest is 64 lowercase hex digits.
pub(crate) fn validate_decoder(digest: &str) -> Result<()> {
    if digest.len() == 64
        && digest
            .bytes()
            .all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
    {
        Ok(())
    } else {
        Err(StoreError::invalid(
            "a decoder digest is 64 lowercase hex digits",
        ))
    }
}

/// How a dispute reads a watermarked asset's bits, registered with its key by the job that wrote
/// them: all three come from the unmarked original and the decoder, none from the payload.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Readout {
    /// The asset reference (one finite logit per bit), when the job decoded relative to it.
    pub reference: Option<Vec<f32>>,
    /// The asset's matched head, when the job read the bits through one.
    pub head: Option<ViewProjection>,
    /// The digest of the decoder the bits were written for
    /// ([`crate::decoder::artifact::digest_of`]).
    pub decoder: Option<String>,
}

impl Readout {
    /// Checks every part against a key of `bits` bits.
    pub(crate) fn validate(&self, bits: usize) -> Result<()> {
        if let Some(r) = &self.reference {
            validate_reference(r, bits)?;
        }
        if let Some(h) = &self.head {
            validate_head(h, bits)?;
        }
        if let Some(d) = &self.decoder {
            validate_decoder(d)?;
        }
        Ok(())
    }
}

/// The associated data of a matched head sealed for asset `id`.
fn head_aad(id: &str) -> String {
    format!("{id}/head")
}

/// A matched head must read `bits` bits from finite values.
pub(crate) fn validate_head(head: &ViewProjection, bits: usize) -> Result<()> {
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    match &head.head {
        Some(a) if head.head_bits() == bits && a.len() == bits * head.features() => {}
        _ => {
            return Err(StoreError::invalid(format!(
                "the matched head does not read {bits} bits"
            )));
        }
    }
    if !finite(&head.mean) || !head.head.as_deref().is_some_and(finite) {
        return Err(StoreError::invalid(
            "the matched head holds a non-finite value",
        ));
    }
    Ok(())
}

/// The associated data of a reference sealed for asset `id`.
fn reference_aad(id: &str) -> String {
    format!("{id}/reference")
}

/// A reference must have one finite logit per bit.
pub(crate) fn validate_reference(reference: &[f32], bits: usize) -> Result<()> {
    if reference.len() != bits {
        return Err(StoreError::invalid(format!(
            "the reference has {} logits for {bits} bits",
            reference.len()
        )));
    }
    if reference.iter().any(|z| !z.is_finite()) {
        return Err(StoreError::invalid(
            "the reference holds a non-finite logit",
        ));
    }
    Ok(())
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
        r: &AnyRow,
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
    /// Opens a `keys` row (asset id, key, mask and reference columns); `Crypto` when any part does not
    /// open or does not fit the key.
    fn open_registration(&self, r: &AnyRow) -> Result<Registration> {
        let id: String = r.try_get("asset_id")?;
        let key = self.open_key(r, "nonce", "ciphertext", &id)?;
        let nonce: Option<Vec<u8>> = r.try_get("reference_nonce")?;
        let ct: Option<Vec<u8>> = r.try_get("reference_ct")?;
        let reference = match (nonce, ct) {
            (None, None) => None,
            (Some(n), Some(c)) => {
                let bytes = self.cipher().open(&n, &c, reference_aad(&id).as_bytes())?;
                if bytes.len() != 4 * key.bits() {
                    return Err(StoreError::Crypto);
                }
                Some(
                    bytes
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                        .collect(),
                )
            }
            _ => return Err(StoreError::Crypto),
        };
        let nonce: Option<Vec<u8>> = r.try_get("head_nonce")?;
        let ct: Option<Vec<u8>> = r.try_get("head_ct")?;
        let head = match (nonce, ct) {
            (None, None) => None,
            (Some(n), Some(c)) => {
                let bytes = self.cipher().open(&n, &c, head_aad(&id).as_bytes())?;
                let head: ViewProjection =
                    serde_json::from_slice(&bytes).map_err(|_| StoreError::Crypto)?;
                validate_head(&head, key.bits()).map_err(|_| StoreError::Crypto)?;
                Some(head)
            }
            _ => return Err(StoreError::Crypto),
        };
        let nonce: Option<Vec<u8>> = r.try_get("decoder_nonce")?;
        let ct: Option<Vec<u8>> = r.try_get("decoder_ct")?;
        let decoder = match (nonce, ct) {
            (None, None) => None,
            (Some(n), Some(c)) => {
                let bytes = self.cipher().open(&n, &c, decoder_aad(&id).as_bytes())?;
                let digest = String::from_utf8(bytes.to_vec()).map_err(|_| StoreError::Crypto)?;
                validate_decoder(&digest).map_err(|_| StoreError::Crypto)?;
                Some(digest)
            }
            _ => return Err(StoreError::Crypto),
        };
        Ok(Registration {
            asset_id: parse_uuid(&id)?,
            key,
            reference,
            head,
            decoder,
        })
    }

    /// The registration of a watermarked asset (`None` when it has none); `Crypto` if it does
    /// not decrypt.
    pub async fn registration(&self, asset: Uuid) -> Result<Option<Registration>> {
        let row = sqlx::query(
            "SELECT asset_id, nonce, ciphertext, mask_nonce, mask_ct, reference_nonce, \
             reference_ct, head_nonce, head_ct, decoder_nonce, decoder_ct FROM keys WHERE asset_id = $1",
        )
        .bind(asset.to_string())
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| self.open_registration(&r)).transpose()
    }

    /// Every registration, oldest first (verification without an asset id).
    pub async fn registrations(&self) -> Result<Vec<Registration>> {
        let rows = sqlx::query(
            "SELECT asset_id, nonce, ciphertext, mask_nonce, mask_ct, reference_nonce, \
             reference_ct, head_nonce, head_ct, decoder_nonce, decoder_ct FROM keys ORDER BY created_at, asset_id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(|r| self.open_registration(r)).collect()
    }

    /// The key of a watermarked asset (`None` when it has none); `Crypto` if it does not
    /// decrypt.
    pub async fn key_of(&self, asset: Uuid) -> Result<Option<WatermarkKey>> {
        Ok(self.registration(asset).await?.map(|r| r.key))
    }

    /// Every registered key with its asset, oldest first.
    pub async fn all_keys(&self) -> Result<Vec<(Uuid, WatermarkKey)>> {
        Ok(self
            .registrations()
            .await?
            .into_iter()
            .map(|r| (r.asset_id, r.key))
            .collect())
    }

    /// Seals and inserts the key of `asset`, its reference, its matched head and its decoder's
    /// digest, if any, on `conn` (inside the caller's transaction).
    pub(crate) async fn insert_key_in(
        &self,
        conn: &mut AnyConnection,
        asset: Uuid,
        key: &WatermarkKey,
        readout: &Readout,
    ) -> Result<()> {
        let id = asset.to_string();
        let sealed = self.seal_key(key, &id)?;
        readout.validate(key.bits())?;
        let reference = match &readout.reference {
            None => None,
            Some(r) => {
                let bytes: Vec<u8> = r.iter().flat_map(|z| z.to_le_bytes()).collect();
                Some(self.cipher().seal(&bytes, reference_aad(&id).as_bytes())?)
            }
        };
        let (reference_nonce, reference_ct) = match reference {
            Some(s) => (Some(s.nonce), Some(s.ciphertext)),
            None => (None, None),
        };
        let (head_nonce, head_ct) = match &readout.head {
            None => (None, None),
            Some(h) => {
                let json = serde_json::to_vec(h).expect("a projection serialises");
                let s = self.cipher().seal(&json, head_aad(&id).as_bytes())?;
                (Some(s.nonce), Some(s.ciphertext))
            }
        };
        let (decoder_nonce, decoder_ct) = match &readout.decoder {
            None => (None, None),
            Some(d) => {
                let s = self
                    .cipher()
                    .seal(d.as_bytes(), decoder_aad(&id).as_bytes())?;
                (Some(s.nonce), Some(s.ciphertext))
            }
        };
        sqlx::query(
            "INSERT INTO keys (asset_id, bits, nonce, ciphertext, mask_nonce, mask_ct, \
             reference_nonce, reference_ct, head_nonce, head_ct, decoder_nonce, decoder_ct, \
             created_at) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13)",
        )
        .bind(&id)
        .bind(key.bits() as i64)
        .bind(sealed.message.nonce)
        .bind(sealed.message.ciphertext)
        .bind(sealed.mask.nonce)
        .bind(sealed.mask.ciphertext)
        .bind(reference_nonce)
        .bind(reference_ct)
        .bind(head_nonce)
        .bind(head_ct)
        .bind(decoder_nonce)
        .bind(decoder_ct)
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

impl Store {
    /// Re-seals every secret of the database — each key's message, mask, reference, matched head
    /// and decoder digest, each job's message and mask, the master-key check value — under `new`, in one transaction
    /// with one `master_key.rotate` audit row by `actor`: either all of them or none move. The
    /// store (this handle and every other process's) must then be reopened with `new`; run it
    /// with the service stopped, or rows the service seals meanwhile stay under the old key.
    /// Returns how many sealed values were re-sealed.
    pub async fn rotate_master_key(&self, new: &super::MasterKey, actor: &str) -> Result<u64> {
        let next = super::crypto::Cipher::new(new);
        let mut tx = self.begin_immediate().await?;
        let mut resealed = 0u64;
        // (table, id column, [(nonce column, ciphertext column, AAD of the row's id)])
        type Aad = fn(&str) -> String;
        type Sealed = (&'static str, &'static str, Aad);
        let tables: [(&str, &str, Vec<Sealed>); 2] = [
            (
                "keys",
                "asset_id",
                vec![
                    ("nonce", "ciphertext", |id| id.to_string()),
                    ("mask_nonce", "mask_ct", |id| mask_aad(id)),
                    ("reference_nonce", "reference_ct", |id| reference_aad(id)),
                    ("head_nonce", "head_ct", |id| head_aad(id)),
                    ("decoder_nonce", "decoder_ct", |id| decoder_aad(id)),
                ],
            ),
            (
                "jobs",
                "id",
                vec![
                    ("message_nonce", "message_ct", |id| super::jobs::job_aad(id)),
                    ("mask_nonce", "mask_ct", |id| {
                        mask_aad(&super::jobs::job_aad(id))
                    }),
                ],
            ),
        ];
        for (table, id_col, columns) in &tables {
            for (nonce_col, ct_col, aad) in columns {
                // Table and column names are the constants above, never input.
                let rows = sqlx::query(sqlx::AssertSqlSafe(format!(
                    "SELECT {id_col} AS id, {nonce_col} AS n, {ct_col} AS c FROM {table} \
                     WHERE {nonce_col} IS NOT NULL AND {ct_col} IS NOT NULL"
                )))
                .fetch_all(&mut *tx)
                .await?;
                for r in rows {
                    let id: String = r.try_get("id")?;
                    let aad = aad(&id);
                    let plain = self.cipher().open(
                        &r.try_get::<Vec<u8>, _>("n")?,
                        &r.try_get::<Vec<u8>, _>("c")?,
                        aad.as_bytes(),
                    )?;
                    let s = next.seal(&plain, aad.as_bytes())?;
                    sqlx::query(sqlx::AssertSqlSafe(format!(
                        "UPDATE {table} SET {nonce_col} = $1, {ct_col} = $2 WHERE {id_col} = $3"
                    )))
                    .bind(s.nonce)
                    .bind(s.ciphertext)
                    .bind(&id)
                    .execute(&mut *tx)
                    .await?;
                    resealed += 1;
                }
            }
        }
        let check = next.seal(
            super::crypto::KEY_CHECK_PLAINTEXT,
            super::crypto::KEY_CHECK_AAD,
        )?;
        let mut value = check.nonce;
        value.extend_from_slice(&check.ciphertext);
        sqlx::query("UPDATE meta SET value = $1 WHERE key = 'key_check'")
            .bind(value)
            .execute(&mut *tx)
            .await?;
        let entry = super::AuditEntry {
            details: serde_json::json!({"resealed": resealed}),
            ..super::AuditEntry::new(actor, "master_key.rotate")
        };
        super::audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok(resealed)
    }
}
