//! `/v1/audit` (filtered, paged) and `/v1/audit/verify` (checks the hash chain) for auditors.

use axum::Json;
use axum::extract::{Query, State};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;
use uuid::Uuid;

use super::AppState;
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::store::{AuditFilter, MAX_AUDIT_PAGE, Scope};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuditQuery {
    asset_id: Option<Uuid>,
    action: Option<String>,
    actor: Option<String>,
    /// RFC 3339 UTC, inclusive.
    since: Option<String>,
    /// RFC 3339 UTC, exclusive.
    until: Option<String>,
    cursor: Option<i64>,
    limit: Option<u32>,
}

/// A `since`/`until` filter must be a real RFC 3339 UTC instant (400 otherwise, before anything
/// is queried): see [`crate::store::normalize_timestamp`].
fn check_time(name: &str, t: &Option<String>) -> ApiResult<()> {
    if let Some(t) = t
        && crate::store::normalize_timestamp(t).is_none()
    {
        return Err(ApiError::bad_request(format!(
            "{name} must be an RFC 3339 UTC time such as 2026-12-01T16:00:00Z or \
             2026-12-01T16:00:00.123Z (a real date and time, at most 3 fraction digits)"
        )));
    }
    Ok(())
}

impl AuditQuery {
    /// The store's filter for this query, checked as the handler checks it (400 for a time that
    /// is not a real RFC 3339 UTC instant or a limit outside 1 to 1000), before anything is
    /// queried.
    pub fn into_filter(self) -> ApiResult<AuditFilter> {
        check_time("since", &self.since)?;
        check_time("until", &self.until)?;
        let limit = self.limit.unwrap_or(100);
        if !(1..=MAX_AUDIT_PAGE).contains(&limit) {
            return Err(ApiError::bad_request(format!(
                "limit must be 1 to {MAX_AUDIT_PAGE}"
            )));
        }
        Ok(AuditFilter {
            asset_id: self.asset_id,
            action: self.action,
            actor: self.actor,
            since: self.since,
            until: self.until,
            after_id: self.cursor,
            limit,
        })
    }
}

/// `GET /v1/audit`.
pub async fn query(
    State(st): State<AppState>,
    caller: Caller,
    Query(q): Query<AuditQuery>,
) -> ApiResult<Response> {
    caller.require(&[Scope::Auditor])?;
    let (items, next) = st.store.audit_query(&q.into_filter()?).await?;
    Ok(Json(json!({"items": items, "next_cursor": next})).into_response())
}

/// `GET /v1/audit/verify`.
pub async fn verify_chain(State(st): State<AppState>, caller: Caller) -> ApiResult<Response> {
    caller.require(&[Scope::Auditor])?;
    Ok(Json(st.store.verify_audit_chain().await?).into_response())
}
