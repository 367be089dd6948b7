//! Bearer API keys: `Authorization: Bearer smk_…`, looked up by hash in the store. Scopes:
//! owner (upload, watermark, read own assets), verifier (submit disputes), auditor (read the
//! audit log and every asset's attribution), admin (everything, and API keys).

use axum::extract::{ConnectInfo, FromRequestParts};
use axum::http::header;
use axum::http::request::Parts;

use super::AppState;
use super::error::{ApiError, ApiResult};
use crate::store::{ApiKey, Scope};

/// The authenticated caller of a request.
#[derive(Clone, Debug)]
pub struct Caller(pub ApiKey);

impl Caller {
    /// The id recorded as owner and as audit actor.
    pub fn id(&self) -> String {
        self.0.id.to_string()
    }

    /// Whether the key has scope `s` (admin has every scope).
    pub fn has(&self, s: Scope) -> bool {
        self.0.scopes.iter().any(|&k| k == s || k == Scope::Admin)
    }

    /// 403 unless the key has one of `scopes`.
    pub fn require(&self, scopes: &[Scope]) -> ApiResult<()> {
        if scopes.iter().any(|&s| self.has(s)) {
            Ok(())
        } else {
            Err(ApiError::forbidden(format!(
                "this API key lacks the scope for this action (needs one of: {})",
                scopes
                    .iter()
                    .map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )))
        }
    }

    /// 404 (not 403, so ids do not leak) unless the caller owns `owner`'s resource or may read
    /// every resource (auditor, admin).
    pub fn may_read(&self, owner: &str) -> ApiResult<()> {
        if owner == self.id() || self.has(Scope::Auditor) {
            Ok(())
        } else {
            Err(ApiError::not_found("resource"))
        }
    }

    /// Whether the caller may download `owner`'s scene file: the owner or an admin. Auditors
    /// read every asset's metadata, report, attribution and audit trail — what a dispute
    /// needs — but not the scene itself, which is the owner's work (403, as they already see
    /// that the asset exists).
    pub fn may_download(&self, owner: &str) -> ApiResult<()> {
        if owner == self.id() || self.has(Scope::Admin) {
            Ok(())
        } else {
            Err(ApiError::forbidden(
                "only the asset's owner (or an admin) may download its scene file; auditors read \
                 its metadata, report, attribution and audit trail",
            ))
        }
    }

    /// Like [`Caller::may_read`] for changes: only the owner or an admin.
    pub fn may_write(&self, owner: &str) -> ApiResult<()> {
        if owner == self.id() || self.has(Scope::Admin) {
            Ok(())
        } else {
            Err(ApiError::not_found("resource"))
        }
    }
}

impl FromRequestParts<AppState> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        // A client address that has spent its failed-authentication budget is refused before
        // its key is even looked at.
        let client = crate::http::limit::client_key(
            parts
                .extensions
                .get::<ConnectInfo<std::net::SocketAddr>>()
                .map(|c| c.0.ip()),
        );
        let failures = &state.limits.auth_failures;
        if let Some(wait) = failures.exhausted(&client) {
            return Err(ApiError::too_many(
                "too many requests with a bad API key from this address",
                wait,
            ));
        }
        let failed = |e: ApiError| {
            let _ = failures.take(&client);
            e
        };
        let value = parts.headers.get(header::AUTHORIZATION).ok_or_else(|| {
            failed(ApiError::unauthorized(
                "missing Authorization: Bearer <API key>",
            ))
        })?;
        let token = value
            .to_str()
            .ok()
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .ok_or_else(|| {
                failed(ApiError::unauthorized(
                    "the Authorization header is not 'Bearer <API key>'",
                ))
            })?;
        match state.store.authenticate(token).await? {
            Some(k) => Ok(Caller(k)),
            None => Err(failed(ApiError::unauthorized("unknown or revoked API key"))),
        }
    }
}
