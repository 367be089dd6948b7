//! `/healthz` (the process answers), `/readyz` (database reachable, workers running) and
//! `/metrics` (Prometheus text format).

use std::fmt::Write;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::AppState;
use super::error::{ApiError, ApiResult};
use crate::store::JobState;

/// `GET /healthz`.
pub async fn healthz() -> Response {
    Json(json!({"status": "ok"})).into_response()
}

/// `GET /readyz`: 200 when the database (and an S3 blob store) answers and every worker is
/// running, else 503.
pub async fn readyz(State(st): State<AppState>) -> ApiResult<Response> {
    if let Err(e) = st.store.ping().await {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "Not ready",
            format!("the database does not answer: {e}"),
        ));
    }
    if st.store.blobs().is_remote() {
        // An S3 blob store must answer too (a LIST under the prefix, at most 5 s).
        let blobs = st.store.blobs().clone();
        let check = tokio::task::spawn_blocking(move || blobs.check());
        let failed = match tokio::time::timeout(std::time::Duration::from_secs(5), check).await {
            Ok(Ok(Ok(()))) => None,
            Ok(Ok(Err(e))) => Some(e.to_string()),
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some("no answer within 5 s".to_string()),
        };
        if let Some(e) = failed {
            tracing::warn!(error = %e, "readiness: the blob store does not answer");
            return Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "Not ready",
                "the blob store does not answer; the error is logged",
            ));
        }
    }
    let workers = st.pool.workers.load(Ordering::Relaxed);
    let alive = st.pool.alive.load(Ordering::Relaxed);
    if alive < workers {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "Not ready",
            format!("{alive} of {workers} workers are running"),
        ));
    }
    Ok(Json(json!({"status": "ready", "workers": workers})).into_response())
}

/// `GET /metrics`.
pub async fn metrics(State(st): State<AppState>) -> ApiResult<Response> {
    let counts = st.store.counts().await?;
    let m = &st.metrics;
    let mut s = String::new();
    let mut put = |name: &str, kind: &str, help: &str, rows: &[(String, f64)]| {
        let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} {kind}");
        for (labels, v) in rows {
            let _ = writeln!(s, "{name}{labels} {v}");
        }
    };
    let classes: Vec<(String, f64)> = (0..5)
        .map(|i| {
            (
                format!("{{class=\"{}xx\"}}", i + 1),
                m.responses[i].load(Ordering::Relaxed) as f64,
            )
        })
        .collect();
    put(
        "splatmark_http_responses_total",
        "counter",
        "HTTP responses by status class.",
        &classes,
    );
    let one = |v: u64| vec![(String::new(), v as f64)];
    put(
        "splatmark_uploads_total",
        "counter",
        "Assets uploaded.",
        &one(m.uploads.load(Ordering::Relaxed)),
    );
    put(
        "splatmark_upload_bytes_total",
        "counter",
        "Bytes uploaded.",
        &one(m.upload_bytes.load(Ordering::Relaxed)),
    );
    put(
        "splatmark_verifications_total",
        "counter",
        "Verification requests answered.",
        &one(m.verifications.load(Ordering::Relaxed)),
    );
    put(
        "splatmark_detections_total",
        "counter",
        "Verifications that detected a watermark.",
        &one(m.detections.load(Ordering::Relaxed)),
    );
    let jobs: Vec<(String, f64)> = JobState::ALL
        .into_iter()
        .map(|s| {
            (
                format!("{{state=\"{}\"}}", s.as_str()),
                counts.jobs.get(s) as f64,
            )
        })
        .collect();
    put("splatmark_jobs", "gauge", "Jobs by state.", &jobs);
    put(
        "splatmark_assets",
        "gauge",
        "Stored assets.",
        &one(counts.assets),
    );
    let p = &st.pool;
    put(
        "splatmark_workers",
        "gauge",
        "Configured workers.",
        &one(p.workers.load(Ordering::Relaxed) as u64),
    );
    let devices: Vec<(String, f64)> = p
        .devices
        .iter()
        .map(|(w, d)| {
            let esc = |v: &str| v.replace('\\', "\\\\").replace('"', "\\\"");
            (
                format!("{{worker=\"{}\",device=\"{}\"}}", esc(w), esc(d)),
                1.0,
            )
        })
        .collect();
    put(
        "splatmark_worker_device",
        "gauge",
        "Each worker and the device its jobs render on (cpu, or the GPU adapter).",
        &devices,
    );
    put(
        "splatmark_workers_busy",
        "gauge",
        "Workers running a job.",
        &one(p.busy.load(Ordering::Relaxed) as u64),
    );
    put(
        "splatmark_jobs_published_total",
        "counter",
        "Results published by this process.",
        &one(p.published.load(Ordering::Relaxed)),
    );
    put(
        "splatmark_job_failures_total",
        "counter",
        "Job attempts failed in this process.",
        &one(p.failed.load(Ordering::Relaxed)),
    );
    let mut r = s.into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4"),
    );
    Ok(r)
}
