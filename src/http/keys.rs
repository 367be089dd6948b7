//! `/v1/keys` — API keys, for admins. The token is shown once, in the creation response; only
//! its hash is stored.

use axum::Json;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;
use uuid::Uuid;

use super::AppState;
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::store::{AuditEntry, Scope};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewKey {
    name: String,
    scopes: Vec<Scope>,
}

/// `POST /v1/keys` {name, scopes} → 201 {id, name, scopes, token}.
pub async fn create(
    State(st): State<AppState>,
    caller: Caller,
    body: Result<Json<NewKey>, JsonRejection>,
) -> ApiResult<Response> {
    caller.require(&[Scope::Admin])?;
    let Json(k) =
        body.map_err(|e| ApiError::new(e.status(), "Invalid JSON body", e.body_text()))?;
    let name = k.name.trim();
    if name.is_empty() || name.len() > 100 || k.scopes.is_empty() {
        return Err(ApiError::unprocessable(
            "a key needs a name (1 to 100 characters) and at least one scope",
        ));
    }
    let (key, token) = st
        .store
        .create_api_key(&caller.id(), name, &k.scopes)
        .await?;
    Ok((
        StatusCode::CREATED,
        Json(json!({"id": key.id, "name": key.name, "scopes": key.scopes, "token": token})),
    )
        .into_response())
}

/// `DELETE /v1/keys/{id}` — revokes a key: 204, with one `key.revoke` audit row. Idempotent: a
/// key that is already revoked also gets 204, and no second audit row (the first revocation is
/// the one on record). 404 for an unknown key.
pub async fn revoke(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    caller.require(&[Scope::Admin])?;
    let id: Uuid = id.parse().map_err(|_| ApiError::not_found("key"))?;
    let entry = AuditEntry {
        actor: caller.id(),
        action: "key.revoke".into(),
        asset_id: None,
        job_id: None,
        details: json!({"key_id": id}),
    };
    match st.store.revoke_api_key(id, entry).await {
        Ok(_) => Ok(StatusCode::NO_CONTENT.into_response()),
        Err(crate::store::StoreError::NotFound) => Err(ApiError::not_found("key")),
        Err(e) => Err(e.into()),
    }
}
