//! Bearer API keys. A token is `smk_` + 64 hex digits (32 random bytes); only its SHA-256 is
//! stored, so the token is shown once, at creation.

use super::audit::{self, AuditEntry};
use super::crypto::fill_random;
use super::error::{Result, StoreError};
use super::{Store, parse_uuid, time, to_u64};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use sqlx::Row;
use sqlx::any::AnyRow;
use std::str::FromStr;
use uuid::Uuid;

/// Prefix of every token.
pub const TOKEN_PREFIX: &str = "smk_";

/// What a key may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scope {
    /// Upload assets, watermark them, read their jobs, files and attribution.
    Owner,
    /// Submit images for verification.
    Verifier,
    /// Read the audit log.
    Auditor,
    /// Everything, including key management.
    Admin,
}

impl Scope {
    /// The stored / serialized name.
    pub fn as_str(self) -> &'static str {
        match self {
            Scope::Owner => "owner",
            Scope::Verifier => "verifier",
            Scope::Auditor => "auditor",
            Scope::Admin => "admin",
        }
    }
}

impl FromStr for Scope {
    type Err = StoreError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "owner" => Ok(Scope::Owner),
            "verifier" => Ok(Scope::Verifier),
            "auditor" => Ok(Scope::Auditor),
            "admin" => Ok(Scope::Admin),
            _ => Err(StoreError::invalid(format!(
                "unknown scope {s:?} (owner, verifier, auditor, admin)"
            ))),
        }
    }
}

impl std::fmt::Display for Scope {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A stored key (never the token).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct ApiKey {
    pub id: Uuid,
    pub name: String,
    pub scopes: Vec<Scope>,
    pub created_at: String,
    pub revoked: bool,
}

impl ApiKey {
    /// Whether the key has `scope` (admin has every scope).
    pub fn allows(&self, scope: Scope) -> bool {
        self.scopes.contains(&scope) || self.scopes.contains(&Scope::Admin)
    }
}

impl Store {
    /// Creates a key for `actor` (the admin key's id, `system` at bootstrap, `cli` from the
    /// shell); returns it and its token (shown once, only its hash is stored). The key and its
    /// `key.create` audit row are written in one transaction: no key exists unaudited.
    pub async fn create_api_key(
        &self,
        actor: &str,
        name: &str,
        scopes: &[Scope],
    ) -> Result<(ApiKey, String)> {
        if name.is_empty() || name.len() > 255 || name.chars().any(char::is_control) {
            return Err(StoreError::invalid(
                "key name must be 1..=255 bytes without control characters",
            ));
        }
        if scopes.is_empty() {
            return Err(StoreError::invalid("a key needs at least one scope"));
        }
        let mut scopes = scopes.to_vec();
        scopes.sort();
        scopes.dedup();
        let mut secret = zeroize::Zeroizing::new([0u8; 32]);
        fill_random(&mut secret[..]);
        let token = format!("{TOKEN_PREFIX}{}", hex::encode(&secret[..]));
        let mut tx = self.begin_immediate().await?;
        let key = ApiKey {
            id: Uuid::new_v4(),
            name: name.to_owned(),
            scopes,
            created_at: time::now(),
            revoked: false,
        };
        sqlx::query(
            "INSERT INTO api_keys (id, name, token_sha256, scopes, created_at) VALUES ($1, $2, $3, $4, $5)",
        )
        .bind(key.id.to_string())
        .bind(&key.name)
        .bind(token_hash(&token))
        .bind(join_scopes(&key.scopes))
        .bind(&key.created_at)
        .execute(&mut *tx)
        .await
        .map_err(StoreError::from_db)?;
        let entry = super::AuditEntry {
            details: serde_json::json!({"key_id": key.id, "name": key.name, "scopes": key.scopes}),
            ..super::AuditEntry::new(actor, "key.create")
        };
        super::audit::append_in(&mut tx, &entry).await?;
        tx.commit().await?;
        Ok((key, token))
    }

    /// The key a bearer token belongs to; `None` for malformed, unknown or revoked tokens.
    pub async fn authenticate(&self, token: &str) -> Result<Option<ApiKey>> {
        let well_formed = token.strip_prefix(TOKEN_PREFIX).is_some_and(|h| {
            h.len() == 64 && h.bytes().all(|c| matches!(c, b'0'..=b'9' | b'a'..=b'f'))
        });
        if !well_formed {
            return Ok(None);
        }
        let row = sqlx::query(
            "SELECT id, name, scopes, created_at, revoked_at FROM api_keys \
             WHERE token_sha256 = $1 AND revoked_at IS NULL",
        )
        .bind(token_hash(token))
        .fetch_optional(&self.pool)
        .await?;
        row.as_ref().map(decode_key).transpose()
    }

    /// Number of keys, revoked ones included (0 → `serve` prints a bootstrap admin token).
    pub async fn api_key_count(&self) -> Result<u64> {
        let n: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM api_keys")
            .fetch_one(&self.pool)
            .await?;
        to_u64(n)
    }

    /// All keys, oldest first (never tokens).
    pub async fn list_api_keys(&self) -> Result<Vec<ApiKey>> {
        let rows = sqlx::query(
            "SELECT id, name, scopes, created_at, revoked_at FROM api_keys ORDER BY created_at, id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(decode_key).collect()
    }

    /// Revokes a key and appends `audit_entry` in the same transaction. Idempotent: revoking a
    /// key that is already revoked changes nothing and appends no audit row (`Ok(false)`; the
    /// first revocation's time and row stand). `NotFound` when unknown.
    pub async fn revoke_api_key(&self, id: Uuid, audit_entry: AuditEntry) -> Result<bool> {
        let id = id.to_string();
        let mut tx = self.begin_immediate().await?;
        let res =
            sqlx::query("UPDATE api_keys SET revoked_at = $1 WHERE id = $2 AND revoked_at IS NULL")
                .bind(time::now())
                .bind(&id)
                .execute(&mut *tx)
                .await?;
        if res.rows_affected() == 0 {
            let known: Option<i64> = sqlx::query_scalar("SELECT 1 FROM api_keys WHERE id = $1")
                .bind(&id)
                .fetch_optional(&mut *tx)
                .await?;
            tx.rollback().await?;
            return match known {
                Some(_) => Ok(false),
                None => Err(StoreError::NotFound),
            };
        }
        audit::append_in(&mut tx, &audit_entry).await?;
        tx.commit().await?;
        Ok(true)
    }
}

/// Lowercase hex SHA-256 of a token.
pub(crate) fn token_hash(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

fn join_scopes(scopes: &[Scope]) -> String {
    scopes
        .iter()
        .map(|s| s.as_str())
        .collect::<Vec<_>>()
        .join(",")
}

fn decode_key(r: &AnyRow) -> Result<ApiKey> {
    let scopes: String = r.try_get("scopes")?;
    let scopes = scopes
        .split(',')
        .map(|s| {
            s.parse()
                .map_err(|_| StoreError::corrupt(format!("scope {s:?}")))
        })
        .collect::<Result<Vec<Scope>>>()?;
    Ok(ApiKey {
        id: parse_uuid(&r.try_get::<String, _>("id")?)?,
        name: r.try_get("name")?,
        scopes,
        created_at: r.try_get("created_at")?,
        revoked: r.try_get::<Option<String>, _>("revoked_at")?.is_some(),
    })
}
