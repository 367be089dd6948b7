//! The HTTP API (axum): one module per resource, one error type ([`error::ApiError`], rendered
//! as problem+json), bearer API keys with scopes ([`auth`]).

pub mod assets;
pub mod attribution;
pub mod audit;
pub mod auth;
pub mod console;
pub mod error;
pub mod health;
pub mod jobs;
pub mod keys;
pub mod limit;
pub mod openapi;
pub mod server;
pub mod verify;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::middleware::{self, Next};
use axum::response::Response;
use axum::routing::{get, post};
use burn::tensor::Device;
use tokio::sync::Notify;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

use crate::config::Config;
use crate::decoder::WatermarkModel;
use crate::decoder::registry::Located;
use crate::queue::PoolStatus;
use crate::store::Store;

/// What every handler can reach.
#[derive(Clone)]
pub struct AppState {
    pub store: Store,
    pub cfg: Arc<Config>,
    /// Wakes idle workers when a job is enqueued.
    pub wake: Arc<Notify>,
    pub pool: Arc<PoolStatus>,
    pub decoders: Arc<Decoders>,
    pub metrics: Arc<Metrics>,
    /// Decoding slots of `/v1/verify` (`verify_concurrency` permits).
    pub verify_slots: Arc<tokio::sync::Semaphore>,
    /// Parsing slots of `POST /v1/assets` (`upload_concurrency` permits).
    pub upload_slots: Arc<tokio::sync::Semaphore>,
    /// The memory of the uploads being checked, in KiB (`upload_memory_mb`): each holds what
    /// reading its files costs while it reads them.
    pub upload_memory: Arc<tokio::sync::Semaphore>,
    /// Rate limits (`verify_per_minute`, `auth_failures_per_minute`).
    pub limits: Arc<limit::Limits>,
}

/// Waits up to `wait` for one of `slots`; 503 with `Retry-After: 1` and `busy` as its detail when
/// none frees up. The permit is held until dropped.
pub(crate) async fn admit(
    slots: &Arc<tokio::sync::Semaphore>,
    wait: std::time::Duration,
    busy: &str,
) -> error::ApiResult<tokio::sync::OwnedSemaphorePermit> {
    admit_many(slots, 1, wait, busy).await
}

/// Like [`admit`], for `n` permits at once.
pub(crate) async fn admit_many(
    slots: &Arc<tokio::sync::Semaphore>,
    n: u32,
    wait: std::time::Duration,
    busy: &str,
) -> error::ApiResult<tokio::sync::OwnedSemaphorePermit> {
    match tokio::time::timeout(wait, slots.clone().acquire_many_owned(n)).await {
        Ok(Ok(permit)) => Ok(permit),
        _ => Err(error::ApiError::busy(busy, 1)),
    }
}

/// Frozen decoders for verification (CPU, loaded on first use): a small pool per decoder
/// (by digest, `decoder::registry`), so concurrent verifications decode in parallel (at most
/// `verify_concurrency` at once, see [`AppState::verify_slots`]) instead of queueing behind one
/// lock, and assets marked with an earlier decoder are read with theirs.
pub struct Decoders {
    device: Device,
    idle: Mutex<HashMap<String, Vec<WatermarkModel>>>,
}

impl Decoders {
    pub fn new(device: Device) -> Self {
        Self {
            device,
            idle: Mutex::new(HashMap::new()),
        }
    }

    /// Runs `f` with the decoder `located` names, taken from the pool (or loaded), and puts it
    /// back (blocking: call from a blocking thread). The pool's lock is held only to take and
    /// return.
    pub fn with<T>(
        &self,
        located: &Located,
        f: impl FnOnce(&WatermarkModel, &Device) -> T,
    ) -> Result<T, crate::decoder::artifact::WeightsError> {
        let taken = self
            .idle
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get_mut(&located.digest)
            .and_then(Vec::pop);
        let m = match taken {
            Some(m) => m,
            None => located.load(&self.device)?,
        };
        let out = f(&m, &self.device);
        self.idle
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(located.digest.clone())
            .or_default()
            .push(m);
        Ok(out)
    }
}

/// Request counters for `/metrics`.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Responses by status class 1xx..5xx (index 0..4).
    pub responses: [AtomicU64; 5],
    pub uploads: AtomicU64,
    pub upload_bytes: AtomicU64,
    pub verifications: AtomicU64,
    pub detections: AtomicU64,
}

async fn count(State(m): State<Arc<Metrics>>, req: Request, next: Next) -> Response {
    let r = next.run(req).await;
    let class = (r.status().as_u16() / 100).clamp(1, 5) as usize - 1;
    m.responses[class].fetch_add(1, Ordering::Relaxed);
    r
}

/// Headers every response carries: the API serves JSON and files, never a page, so a browser
/// must not sniff a type, frame it, send a referrer from it or load it cross-origin; and nothing
/// is cached unless a handler says otherwise (a created API key's token, a message, an audit
/// page are not for shared caches). No CORS header is ever set: browsers keep cross-origin pages
/// out (a preflight `OPTIONS` gets 405). TLS and HSTS belong to the proxy in front.
pub const SECURITY_HEADERS: &[(&str, &str)] = &[
    ("x-content-type-options", "nosniff"),
    ("x-frame-options", "DENY"),
    (
        "content-security-policy",
        "default-src 'none'; frame-ancestors 'none'",
    ),
    ("referrer-policy", "no-referrer"),
    ("cross-origin-resource-policy", "same-origin"),
    ("cache-control", "no-store"),
];

async fn security_headers(req: Request, next: Next) -> Response {
    let mut r = next.run(req).await;
    let h = r.headers_mut();
    for &(name, value) in SECURITY_HEADERS {
        if !h.contains_key(name) {
            h.insert(
                axum::http::HeaderName::from_static(name),
                axum::http::HeaderValue::from_static(value),
            );
        }
    }
    r
}

/// Every route (method, path) — the OpenAPI spec must list exactly these (tested).
pub const ROUTES: &[(&str, &str)] = &[
    ("post", "/v1/assets"),
    ("get", "/v1/assets"),
    ("get", "/v1/assets/{id}"),
    ("get", "/v1/assets/{id}/file"),
    ("post", "/v1/assets/{id}/watermark"),
    ("get", "/v1/assets/{id}/jobs"),
    ("get", "/v1/assets/{id}/attribution"),
    ("get", "/v1/assets/{id}/attribution/summary"),
    ("get", "/v1/assets/{id}/attribution/picture"),
    ("get", "/v1/assets/{id}/attribution/pick"),
    ("get", "/v1/jobs/{id}"),
    ("delete", "/v1/jobs/{id}"),
    ("post", "/v1/verify"),
    ("get", "/v1/audit"),
    ("get", "/v1/audit/verify"),
    ("post", "/v1/keys"),
    ("delete", "/v1/keys/{id}"),
    ("get", "/healthz"),
    ("get", "/readyz"),
    ("get", "/metrics"),
    ("get", "/openapi.json"),
];

/// The web console's pages ([`console`]): not part of the API, so not in its spec.
pub const CONSOLE_ROUTES: &[(&str, &str)] = &[
    ("get", "/"),
    ("get", "/console/app.js"),
    ("get", "/console/app.css"),
];

/// The probes every process serves: liveness, readiness, metrics.
fn probes() -> Router<AppState> {
    Router::new()
        .route("/healthz", get(health::healthz))
        .route("/readyz", get(health::readyz))
        .route("/metrics", get(health::metrics))
}

/// `routes` with the fallback, the state and the middleware every router has.
fn with_middleware(routes: Router<AppState>, state: AppState) -> Router {
    let metrics = state.metrics.clone();
    routes
        .fallback(|| async { error::ApiError::not_found("route") })
        .with_state(state)
        .layer(middleware::from_fn_with_state(metrics, count))
        .layer(TimeoutLayer::with_status_code(
            axum::http::StatusCode::REQUEST_TIMEOUT,
            Duration::from_secs(600),
        ))
        .layer(middleware::from_fn(error::as_problem))
        .layer(middleware::from_fn(security_headers))
        .layer(TraceLayer::new_for_http())
}

/// The router of a worker process (`serve --role worker`): probes and metrics, no API.
pub fn ops_router(state: AppState) -> Router {
    with_middleware(probes(), state)
}

/// The API router with its middleware.
pub fn router(state: AppState) -> Router {
    let routes = Router::new()
        .route(
            "/v1/assets",
            // Uploads are counted against `max_upload_bytes` while they stream.
            post(assets::upload)
                .layer(DefaultBodyLimit::disable())
                .get(assets::list),
        )
        .route("/v1/assets/{id}", get(assets::get_one))
        .route("/v1/assets/{id}/file", get(assets::file))
        .route("/v1/assets/{id}/watermark", post(jobs::watermark))
        .route("/v1/assets/{id}/jobs", get(jobs::of_asset))
        .route("/v1/assets/{id}/attribution", get(attribution::attribution))
        .route(
            "/v1/assets/{id}/attribution/summary",
            get(attribution::attribution_summary),
        )
        .route(
            "/v1/assets/{id}/attribution/picture",
            get(attribution::picture),
        )
        .route("/v1/assets/{id}/attribution/pick", get(attribution::pick))
        .route("/v1/jobs/{id}", get(jobs::get_one).delete(jobs::cancel))
        .route(
            "/v1/verify",
            post(verify::verify).layer(DefaultBodyLimit::disable()),
        )
        .route("/v1/audit", get(audit::query))
        .route("/v1/audit/verify", get(audit::verify_chain))
        .route("/v1/keys", post(keys::create))
        .route("/v1/keys/{id}", axum::routing::delete(keys::revoke))
        .route("/openapi.json", get(openapi::json))
        .route("/", get(console::index))
        .route("/console/app.js", get(console::script))
        .route("/console/app.css", get(console::style))
        .merge(probes());
    with_middleware(routes, state)
}
