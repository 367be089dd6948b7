//! `POST /v1/assets/{id}/watermark` (enqueue, honouring `Idempotency-Key`), `GET
//! /v1/assets/{id}/jobs` (an asset's jobs, newest first) and `/v1/jobs/{id}` (state, phase,
//! progress, ETA; `DELETE` cancels).

use axum::Json;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;
use uuid::Uuid;

use super::AppState;
use super::assets::{parse_id, readable};
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::queue::{JobOptions, available_bits};
use crate::store::{AssetKind, AuditEntry, Job, NewJob, Scope};
use crate::verify::message::{parse_hex, random_message};

/// The body of a watermark request.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WatermarkRequest {
    /// 32, 48 or 64 (default 32).
    pub bits: Option<usize>,
    /// The message as hex (bits/4 digits); default a fresh random one.
    pub message: Option<String>,
    pub options: JobOptions,
}

fn job_response(status: StatusCode, job: &Job, replayed: bool) -> Response {
    let mut r = (status, Json(job)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/jobs/{}", job.id)) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    if replayed {
        r.headers_mut()
            .insert("idempotent-replayed", HeaderValue::from_static("true"));
    }
    r
}

/// `POST /v1/assets/{id}/watermark`.
pub async fn watermark(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Result<Json<WatermarkRequest>, JsonRejection>,
) -> ApiResult<Response> {
    caller.require(&[Scope::Owner])?;
    let asset_id: Uuid = id.parse().map_err(|_| ApiError::not_found("asset"))?;
    let asset = readable(&st, &caller, asset_id).await?;
    caller.may_write(&asset.owner)?;
    let Json(req) =
        body.map_err(|e| ApiError::new(e.status(), "Invalid JSON body", e.body_text()))?;
    if asset.kind != AssetKind::Original {
        return Err(ApiError::conflict(
            "this asset is already watermarked; watermark its original instead",
        ));
    }
    let bits = req.bits.unwrap_or(32);
    if ![32, 48, 64].contains(&bits) {
        return Err(ApiError::unprocessable(format!(
            "bits must be 32, 48 or 64, got {bits}"
        )));
    }
    let available = available_bits(&st.cfg);
    if !available.contains(&bits) {
        return Err(ApiError::unprocessable(format!(
            "this server has no decoder for {bits} bits (available: {available:?})"
        )));
    }
    let message = match &req.message {
        Some(h) => parse_hex(h, bits).map_err(|e| ApiError::unprocessable(e.to_string()))?,
        None => random_message(bits),
    };
    let spec = req
        .options
        .resolve(&st.cfg, bits)
        .map_err(ApiError::unprocessable)?;
    let idempotency_key = match headers.get("idempotency-key") {
        Some(v) => {
            let k = v
                .to_str()
                .ok()
                .filter(|k| !k.is_empty() && k.len() <= 255)
                .ok_or_else(|| {
                    ApiError::bad_request(
                        "Idempotency-Key must be 1 to 255 visible ASCII characters",
                    )
                })?;
            Some(k.to_string())
        }
        None => None,
    };
    let options = serde_json::to_value(&spec).map_err(ApiError::internal)?;
    // With a key and no message, a replay must not be compared with a freshly drawn random
    // message: the stored job answers when the rest of the request is the same.
    if let (Some(k), None) = (&idempotency_key, &req.message)
        && let Some(job) = st.store.job_by_idempotency_key(&caller.id(), k).await?
    {
        if job.asset_id == asset_id && job.bits as usize == bits && job.options == options {
            return Ok(job_response(StatusCode::ACCEPTED, &job, true));
        }
        return Err(ApiError::conflict(
            "idempotency key already used with a different request",
        ));
    }
    let (job, created) = st
        .store
        .enqueue(
            NewJob {
                asset_id,
                owner: caller.id(),
                bits: bits as u32,
                message,
                options,
                idempotency_key,
                max_attempts: st.cfg.max_attempts,
            },
            AuditEntry {
                actor: caller.id(),
                action: "job.enqueue".into(),
                asset_id: Some(asset_id),
                job_id: None,
                details: json!({"bits": bits, "message_given": req.message.is_some()}),
            },
        )
        .await?;
    if created {
        st.wake.notify_waiters();
        tracing::info!(job = %job.id, asset = %asset_id, bits, "job enqueued");
    }
    Ok(job_response(StatusCode::ACCEPTED, &job, !created))
}

async fn own_job(st: &AppState, caller: &Caller, id: &str) -> ApiResult<Job> {
    let id: Uuid = id.parse().map_err(|_| ApiError::not_found("job"))?;
    let job = st
        .store
        .get_job(id)
        .await?
        .ok_or_else(|| ApiError::not_found("job"))?;
    caller
        .may_read(&job.owner)
        .map_err(|_| ApiError::not_found("job"))?;
    Ok(job)
}

#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobsQuery {
    /// At most this many (1–200, default 50).
    pub limit: Option<u32>,
}

/// `GET /v1/assets/{id}/jobs` — the jobs started on an asset the caller may read, newest first
/// (those of other owners left out).
pub async fn of_asset(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    Query(q): Query<JobsQuery>,
) -> ApiResult<Response> {
    let limit = q.limit.unwrap_or(50);
    if !(1..=200).contains(&limit) {
        return Err(ApiError::bad_request(format!(
            "limit {limit}: expected 1 to 200"
        )));
    }
    let a = readable(&st, &caller, parse_id(&id)?).await?;
    let jobs: Vec<Job> = st
        .store
        .jobs_of(a.id, limit)
        .await?
        .into_iter()
        .filter(|j| caller.may_read(&j.owner).is_ok())
        .collect();
    Ok(Json(json!({ "jobs": jobs })).into_response())
}

/// `GET /v1/jobs/{id}`.
pub async fn get_one(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let job = own_job(&st, &caller, &id).await?;
    Ok(Json(job).into_response())
}

/// `DELETE /v1/jobs/{id}` — cancels a queued or running job (a running worker stops at its
/// next heartbeat and publishes nothing).
pub async fn cancel(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let job = own_job(&st, &caller, &id).await?;
    caller
        .may_write(&job.owner)
        .map_err(|_| ApiError::not_found("job"))?;
    let job = st
        .store
        .cancel(
            job.id,
            AuditEntry {
                actor: caller.id(),
                action: "job.cancel".into(),
                asset_id: Some(job.asset_id),
                job_id: Some(job.id),
                details: json!({}),
            },
        )
        .await?;
    Ok(Json(job).into_response())
}
