//! `/v1/assets`: streaming upload (validated by the scene reader before anything is stored),
//! listing, metadata and download (in any scene format).

use std::sync::atomic::Ordering;

use axum::Json;
use axum::body::Body;
use axum::extract::{Multipart, Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::io::AsyncWriteExt;
use uuid::Uuid;

use super::AppState;
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::scene::camera::read_cameras_bytes;
use crate::scene::format::{detect_format, read_as};
use crate::scene::{Format, Gaussians, Limits, SceneError, cost};
use crate::store::{Asset, AssetKind, AuditEntry, NewAsset, Scope};

/// A multipart field's failure as a client error.
/// A multipart body that cannot be read. Every such failure is the client's: a malformed form,
/// or a body that ended early because the client disconnected or truncated it (axum reports
/// those as 500; they are 400 here, so that they do not count as server errors).
pub(super) fn multipart_err(e: axum::extract::multipart::MultipartError) -> ApiError {
    let status = e.status();
    if status.is_server_error() {
        ApiError::bad_request(format!(
            "the request body could not be read to its end (the client disconnected or sent \
             less than it declared): {}",
            e.body_text()
        ))
    } else {
        ApiError::new(status, "Bad multipart body", e.body_text())
    }
}

/// 408 for a body that sent nothing for `idle`.
fn stalled(idle: std::time::Duration) -> ApiError {
    ApiError::new(
        axum::http::StatusCode::REQUEST_TIMEOUT,
        "Request timeout",
        format!(
            "the request body sent nothing for {} ms; send it without pausing",
            idle.as_millis()
        ),
    )
}

/// The next field of a multipart body, or 408 when the client stalls for `idle`.
pub(super) async fn next_field<'a>(
    mp: &'a mut Multipart,
    idle: std::time::Duration,
) -> ApiResult<Option<axum::extract::multipart::Field<'a>>> {
    match tokio::time::timeout(idle, mp.next_field()).await {
        Ok(r) => r.map_err(multipart_err),
        Err(_) => Err(stalled(idle)),
    }
}

/// The next chunk of a multipart field, or 408 when the client stalls for `idle`.
pub(super) async fn next_chunk(
    field: &mut axum::extract::multipart::Field<'_>,
    idle: std::time::Duration,
) -> ApiResult<Option<axum::body::Bytes>> {
    match tokio::time::timeout(idle, field.chunk()).await {
        Ok(r) => r.map_err(multipart_err),
        Err(_) => Err(stalled(idle)),
    }
}

/// The file name a client gave, reduced to a safe base name (metadata only: blobs are named by
/// their hash).
fn clean_name(name: Option<&str>) -> Option<String> {
    let base = name?.rsplit(['/', '\\']).next()?;
    let s: String = base.chars().filter(|c| !c.is_control()).take(200).collect();
    (!s.is_empty()).then_some(s)
}

/// Streams one multipart field into a temporary blob file, counting bytes against `budget`.
pub(super) async fn spool(
    st: &AppState,
    field: &mut axum::extract::multipart::Field<'_>,
    used: &mut u64,
    budget: u64,
) -> ApiResult<tempfile::NamedTempFile> {
    let tmp = st.store.blobs().temp_file().map_err(ApiError::internal)?;
    let mut out = tokio::fs::File::from_std(tmp.reopen().map_err(ApiError::internal)?);
    let idle = st.cfg.body_idle_timeout();
    while let Some(chunk) = next_chunk(field, idle).await? {
        *used += chunk.len() as u64;
        if *used > budget {
            return Err(ApiError::too_large(format!(
                "the upload is larger than this server's limit of {budget} bytes"
            )));
        }
        out.write_all(&chunk).await.map_err(ApiError::internal)?;
    }
    out.flush().await.map_err(ApiError::internal)?;
    Ok(tmp)
}

/// What the scene reader found in an upload.
struct Checked {
    format: String,
    gaussians: u64,
    sh_degree: u8,
    cameras: Option<(usize, String)>,
}

/// The extension of the file name a client gave, the readers' hint for `.splat`.
fn extension(name: Option<&str>) -> Option<&str> {
    name.and_then(|n| n.rsplit_once('.').map(|(_, e)| e))
}

/// What checking the spooled files will hold in memory at its peak, in bytes, from the scene's
/// header and the files' sizes (`scene::cost`; nothing but the scene's first bytes is read).
/// A scene declaring more Gaussians than the limit is refused here, before anything is reserved.
fn reservation(
    scene: &std::path::Path,
    scene_name: Option<&str>,
    cameras: Option<&std::path::Path>,
    limits: &Limits,
) -> Result<u64, ApiError> {
    let len = std::fs::metadata(scene).map_err(ApiError::internal)?.len();
    if len == 0 {
        return Err(ApiError::unprocessable("the scene file is empty"));
    }
    let hint = extension(scene_name);
    let declared = cost::declared_file(scene, hint)?;
    limits.check_count(declared.count)?;
    let cams = match cameras {
        Some(p) => {
            cost::cameras_read_bytes(std::fs::metadata(p).map_err(ApiError::internal)?.len())
        }
        None => 0,
    };
    Ok(declared.read_bytes(len).saturating_add(cams))
}

/// Admits work that parses a scene holding about `need` bytes in memory (`what`: "checking this
/// upload", "converting this scene"): 413 past the whole upload memory budget, 503 while that
/// memory or every parsing slot stays taken. Both permits are held until the work ends.
async fn admit_parse(
    st: &AppState,
    need: u64,
    what: &str,
) -> ApiResult<(
    tokio::sync::OwnedSemaphorePermit,
    tokio::sync::OwnedSemaphorePermit,
)> {
    let need_kib = need.div_ceil(1024);
    let budget_kib = st.cfg.upload_memory_kib();
    if need_kib > budget_kib {
        return Err(ApiError::too_large(format!(
            "{what} takes about {} MiB of memory; this server parses scenes within {} MiB \
             (upload_memory_mb)",
            need_kib.div_ceil(1024),
            budget_kib / 1024
        )));
    }
    let wait = std::time::Duration::from_millis(st.cfg.upload_wait_ms);
    let memory = super::admit_many(
        &st.upload_memory,
        u32::try_from(need_kib).map_err(ApiError::internal)?,
        wait,
        "the memory for parsing scenes is in use by other uploads or conversions; retry shortly",
    )
    .await?;
    let permit = super::admit(
        &st.upload_slots,
        wait,
        "every scene parsing slot is busy; retry shortly",
    )
    .await?;
    Ok((permit, memory))
}

/// Validates the spooled files with the scene and camera readers (`cameras`: the spooled file and
/// the name the client gave it).
fn check(
    scene: &std::path::Path,
    scene_name: Option<&str>,
    cameras: Option<(&std::path::Path, Option<&str>)>,
    limits: &Limits,
) -> Result<Checked, ApiError> {
    let bytes = std::fs::read(scene).map_err(ApiError::internal)?;
    if bytes.is_empty() {
        return Err(ApiError::unprocessable("the scene file is empty"));
    }
    let hint = extension(scene_name);
    let format = detect_format(&bytes, hint)?;
    let g = read_as(&bytes, format, limits)?;
    if g.is_empty() {
        return Err(ApiError::unprocessable("the scene has no Gaussians"));
    }
    let cameras = match cameras {
        Some((p, name)) => {
            // From the bytes alone: nothing the file names on this server is opened.
            let bytes = std::fs::read(p).map_err(ApiError::internal)?;
            let (kind, cams) =
                read_cameras_bytes(&bytes, name.unwrap_or("cameras")).map_err(|e| match e {
                    SceneError::Io { .. } | SceneError::IoPlain(_) => ApiError::internal(e),
                    e => ApiError::unprocessable(format!("cameras: {e}")),
                })?;
            if cams.is_empty() {
                return Err(ApiError::unprocessable("cameras: the file holds no camera"));
            }
            // What a job will render through them: refused now, not retried into the dead
            // letter later.
            use crate::queue::spec::{MAX_SIDE, MAX_VIEWS};
            if cams.len() > MAX_VIEWS {
                return Err(ApiError::unprocessable(format!(
                    "cameras: the file holds {} cameras; a job renders at most {MAX_VIEWS}",
                    cams.len()
                )));
            }
            if let Some((i, c)) = cams.iter().enumerate().find(|(_, c)| {
                !(1..=MAX_SIDE).contains(&c.width) || !(1..=MAX_SIDE).contains(&c.height)
            }) {
                return Err(ApiError::unprocessable(format!(
                    "cameras: camera {i} is {}×{} px; a job renders at most {MAX_SIDE} px a side",
                    c.width, c.height
                )));
            }
            Some((cams.len(), kind.as_str().to_string()))
        }
        None => None,
    };
    Ok(Checked {
        format: format.as_str().to_string(),
        gaussians: g.len() as u64,
        sh_degree: g.sh_degree,
        cameras,
    })
}

/// Removes the blobs of an upload whose asset row was not written (best effort: what fails here
/// is logged, and the garbage collector removes it later).
async fn discard(st: &AppState, pins: Vec<crate::store::PinnedBlob>) {
    match st.store.discard_unreferenced(pins).await {
        Ok(n) if n > 0 => tracing::info!(blobs = n, "removed the blobs of a rejected upload"),
        Ok(_) => {}
        Err(e) => tracing::warn!(error = %e, "could not remove the blobs of a rejected upload"),
    }
}

/// `POST /v1/assets` — multipart fields `scene` (required) and `cameras` (optional).
pub async fn upload(
    State(st): State<AppState>,
    caller: Caller,
    mut mp: Multipart,
) -> ApiResult<Response> {
    caller.require(&[Scope::Owner])?;
    let budget = st.cfg.max_upload_bytes;
    let mut used = 0u64;
    let mut scene = None;
    let mut cameras = None;
    let idle = st.cfg.body_idle_timeout();
    while let Some(mut field) = next_field(&mut mp, idle).await? {
        let name = field.name().unwrap_or_default().to_string();
        let slot = match name.as_str() {
            "scene" => &mut scene,
            "cameras" => &mut cameras,
            other => {
                return Err(ApiError::bad_request(format!(
                    "unexpected multipart field '{other}' (expected 'scene' and optionally 'cameras')"
                )));
            }
        };
        if slot.is_some() {
            return Err(ApiError::bad_request(format!("field '{name}' given twice")));
        }
        let file_name = clean_name(field.file_name());
        let tmp = spool(&st, &mut field, &mut used, budget).await?;
        *slot = Some((tmp, file_name));
    }
    let (scene, scene_name) =
        scene.ok_or_else(|| ApiError::bad_request("missing multipart field 'scene'"))?;
    let limits = Limits {
        max_gaussians: st.cfg.max_gaussians,
        max_file_bytes: Some(budget),
    };
    // Reading the files holds them and the decoded scene in memory: what that costs is
    // reserved from the upload memory budget first (413 past the whole budget, 503 while it is
    // in use), and at most `upload_concurrency` parses run at once.
    let need = {
        let (scene, name) = (scene.path().to_path_buf(), scene_name.clone());
        let cams = cameras.as_ref().map(|(t, _)| t.path().to_path_buf());
        tokio::task::spawn_blocking(move || {
            reservation(&scene, name.as_deref(), cams.as_deref(), &limits)
        })
        .await
        .map_err(ApiError::internal)??
    };
    let (permit, memory) = admit_parse(&st, need, "checking this upload").await?;
    let blobs = st.store.blobs().clone();
    let name = scene_name.clone();
    let (checked, pins, committed) = tokio::task::spawn_blocking(move || {
        let _held = (permit, memory); // until the parse and the blob commit end
        let checked = check(
            scene.path(),
            name.as_deref(),
            cameras.as_ref().map(|(t, n)| (t.path(), n.as_deref())),
            &limits,
        )?;
        // Only now does anything become permanent. The blobs stay pinned until their row is
        // written, and are removed again if it is not.
        let mut pins = Vec::new();
        let committed = (|| {
            pins.push(blobs.commit_pinned(scene)?);
            if let Some((t, _)) = cameras {
                pins.push(blobs.commit_pinned(t)?);
            }
            Ok::<_, std::io::Error>(())
        })();
        Ok::<_, ApiError>((checked, pins, committed))
    })
    .await
    .map_err(ApiError::internal)??;
    if let Err(e) = committed {
        discard(&st, pins).await;
        return Err(ApiError::internal(e));
    }
    let scene_blob = pins[0].blob().clone();
    let cams_blob = pins.get(1).map(|p| p.blob().clone());
    let size = scene_blob.size;
    let (n_cams, cams_format) = match checked.cameras {
        Some((n, f)) => (Some(n), Some(f)),
        None => (None, None),
    };
    let inserted = st
        .store
        .insert_asset(
            NewAsset {
                owner: caller.id(),
                kind: AssetKind::Original,
                parent_id: None,
                source_job_id: None,
                blob: scene_blob,
                format: checked.format,
                file_name: scene_name,
                gaussians: checked.gaussians,
                sh_degree: checked.sh_degree,
                cameras_blob: cams_blob,
                cameras_format: cams_format,
            },
            AuditEntry {
                actor: caller.id(),
                action: "asset.upload".into(),
                asset_id: None,
                job_id: None,
                details: json!({"bytes": size, "gaussians": checked.gaussians, "cameras": n_cams}),
            },
        )
        .await;
    let asset = match inserted {
        Ok(a) => a,
        Err(e) => {
            discard(&st, pins).await;
            return Err(e.into());
        }
    };
    drop(pins);
    st.metrics.uploads.fetch_add(1, Ordering::Relaxed);
    st.metrics.upload_bytes.fetch_add(used, Ordering::Relaxed);
    tracing::info!(asset = %asset.id, gaussians = asset.gaussians, "asset uploaded");
    let mut r = (StatusCode::CREATED, Json(&asset)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/assets/{}", asset.id)) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    Ok(r)
}

/// The asset `id` if the caller may read it.
pub(super) async fn readable(st: &AppState, caller: &Caller, id: Uuid) -> ApiResult<Asset> {
    let a = st
        .store
        .get_asset(id)
        .await?
        .ok_or_else(|| ApiError::not_found("asset"))?;
    caller
        .may_read(&a.owner)
        .map_err(|_| ApiError::not_found("asset"))?;
    Ok(a)
}

pub(super) fn parse_id(s: &str) -> ApiResult<Uuid> {
    s.parse().map_err(|_| ApiError::not_found("asset"))
}

#[derive(Serialize)]
struct AssetView {
    #[serde(flatten)]
    asset: Asset,
    /// Watermarked versions of an original.
    watermarked: Vec<Uuid>,
    /// The embedding report of a watermarked asset.
    report: Option<serde_json::Value>,
}

/// `GET /v1/assets/{id}`.
pub async fn get_one(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let a = readable(&st, &caller, parse_id(&id)?).await?;
    let watermarked = st
        .store
        .watermarked_of(a.id)
        .await?
        .into_iter()
        .map(|w| w.id)
        .collect();
    let report = st.store.report_of(a.id).await?;
    Ok(Json(AssetView {
        asset: a,
        watermarked,
        report,
    })
    .into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileQuery {
    /// `ply`, `compressed_ply` (or `compressed-ply`), `splat` or `spz`; `sog` only for an asset
    /// stored as SOG (which is not written).
    format: Option<String>,
}

/// The format a `?format=` names (`compressed-ply` accepted for `compressed_ply`).
fn requested_format(name: &str) -> ApiResult<Format> {
    Format::parse(&name.replace('-', "_")).ok_or_else(|| {
        ApiError::bad_request(format!(
            "format {name:?}: expected ply, compressed_ply, splat or spz (or sog for an asset \
             stored as SOG)"
        ))
    })
}

/// Bytes per Gaussian of the largest file a conversion writes (a PLY at SH degree 3: 62 floats).
const MAX_WRITTEN_BYTES_PER_GAUSSIAN: u64 = 62 * 4;

/// `GET /v1/assets/{id}/file[?format=ply|compressed_ply|splat|spz]` — the scene as stored (as
/// uploaded for originals, INRIA binary PLY for watermarked assets), streamed; with `format`
/// naming another format, converted to it (`scene::write_scene`: the quantised formats round
/// as they do in every viewer — docs/RESULTS.md records what each keeps of a watermark; SOG is
/// read-only, so `format=sog` is 400 unless the asset is stored as SOG). A conversion decodes
/// the scene in memory, so it is admitted against the same memory budget and parsing slots as
/// uploads.
pub async fn file(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    Query(q): Query<FileQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let a = readable(&st, &caller, parse_id(&id)?).await?;
    caller.may_download(&a.owner)?;
    let stored = Format::parse(&a.format)
        .ok_or_else(|| ApiError::internal(format!("stored format {:?}", a.format)))?;
    let to = match q.format.as_deref() {
        Some(name) => requested_format(name)?,
        None => stored,
    };
    if to != stored && !to.is_writable() {
        return Err(ApiError::bad_request(crate::scene::sog::READ_ONLY));
    }
    let etag = if to == stored {
        format!("\"{}\"", a.sha256)
    } else {
        format!("\"{}-{}\"", a.sha256, to.as_str())
    };
    if headers
        .get(header::IF_NONE_MATCH)
        .is_some_and(|v| v.as_bytes() == etag.as_bytes())
    {
        let mut r = StatusCode::NOT_MODIFIED.into_response();
        r.headers_mut().insert(
            header::CACHE_CONTROL,
            HeaderValue::from_static("private, no-cache"),
        );
        if let Ok(v) = HeaderValue::from_str(&etag) {
            r.headers_mut().insert(header::ETAG, v);
        }
        return Ok(r);
    }
    let path = blob_path(&st, &a.sha256).await?;
    let (body, length) = if to == stored {
        let f = tokio::fs::File::open(&path)
            .await
            .map_err(ApiError::internal)?;
        (
            Body::from_stream(tokio_util::io::ReaderStream::new(f)),
            a.size,
        )
    } else {
        let bytes = convert(&st, &path, stored, to).await?;
        let n = bytes.len() as u64;
        (Body::from(bytes), n)
    };
    let mut r = body.into_response();
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(length));
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    // The owner's client may keep the file and revalidate it by its ETag; shared caches not.
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, no-cache"),
    );
    if let Ok(v) = HeaderValue::from_str(&format!(
        "attachment; filename=\"{}.{}\"",
        a.id,
        to.extension()
    )) {
        h.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok(r)
}

/// A local file holding blob `sha256` (on S3 downloaded, verified and cached first: on a
/// blocking thread, as every blob store call from async code).
pub(super) async fn blob_path(st: &AppState, sha256: &str) -> ApiResult<std::path::PathBuf> {
    let (blobs, id) = (st.store.blobs().clone(), sha256.to_owned());
    Ok(tokio::task::spawn_blocking(move || blobs.path(&id))
        .await
        .map_err(ApiError::internal)??)
}

/// Bytes of memory parsing the stored scene at `path` (in `from`) takes, plus `per_gaussian`
/// bytes for each of its Gaussians; 413 past `max_gaussians`.
async fn parse_need(
    path: &std::path::Path,
    from: Format,
    limits: Limits,
    per_gaussian: u64,
) -> ApiResult<u64> {
    let path = path.to_path_buf();
    tokio::task::spawn_blocking(move || {
        let len = std::fs::metadata(&path).map_err(ApiError::internal)?.len();
        let declared = cost::declared_file(&path, Some(from.extension()))?;
        limits.check_count(declared.count)?;
        Ok::<_, ApiError>(
            declared
                .read_bytes(len)
                .saturating_add(declared.count.saturating_mul(per_gaussian)),
        )
    })
    .await
    .map_err(ApiError::internal)?
}

fn scene_limits(st: &AppState) -> Limits {
    Limits {
        max_gaussians: st.cfg.max_gaussians,
        max_file_bytes: None,
    }
}

/// The stored scene at `path` (in `from`) written in `to`, within the upload memory budget.
async fn convert(
    st: &AppState,
    path: &std::path::Path,
    from: Format,
    to: Format,
) -> ApiResult<Vec<u8>> {
    let limits = scene_limits(st);
    let need = parse_need(path, from, limits, MAX_WRITTEN_BYTES_PER_GAUSSIAN).await?;
    let (permit, memory) = admit_parse(st, need, "converting this scene").await?;
    let path = path.to_path_buf();
    tokio::task::spawn_blocking(move || {
        let _held = (permit, memory);
        let bytes = std::fs::read(&path).map_err(ApiError::internal)?;
        let g = read_as(&bytes, from, &limits)?;
        drop(bytes);
        let mut out = Vec::new();
        crate::scene::write_scene(&g, to, &mut out).map_err(|e| match e {
            // What a format cannot hold (an spz position past its range) is the request's
            // problem, not the server's.
            SceneError::Unsupported(m) => ApiError::unprocessable(m),
            e => ApiError::internal(e),
        })?;
        Ok(out)
    })
    .await
    .map_err(ApiError::internal)?
}

/// Permits of the upload memory budget and a parsing slot, held while their work lasts.
pub(super) type Admitted = (
    tokio::sync::OwnedSemaphorePermit,
    tokio::sync::OwnedSemaphorePermit,
);

/// The scenes of `assets`, parsed within the upload memory budget and one parsing slot (`what`
/// names the work in a 413 / 503), with the permits for that memory plus `per_gaussian` bytes
/// per Gaussian of further work the caller does while it holds them.
pub(super) async fn load_scenes(
    st: &AppState,
    assets: &[&Asset],
    per_gaussian: u64,
    what: &str,
) -> ApiResult<(Vec<Gaussians>, Admitted)> {
    let limits = scene_limits(st);
    let mut files = Vec::with_capacity(assets.len());
    let mut need = 0u64;
    for a in assets {
        let from = Format::parse(&a.format)
            .ok_or_else(|| ApiError::internal(format!("stored format {:?}", a.format)))?;
        let path = blob_path(st, &a.sha256).await?;
        need = need.saturating_add(parse_need(&path, from, limits, per_gaussian).await?);
        files.push((path, from));
    }
    let held = admit_parse(st, need, what).await?;
    tokio::task::spawn_blocking(move || {
        let mut scenes = Vec::with_capacity(files.len());
        for (path, from) in files {
            let bytes = std::fs::read(&path).map_err(ApiError::internal)?;
            scenes.push(read_as(&bytes, from, &limits)?);
        }
        Ok((scenes, held))
    })
    .await
    .map_err(ApiError::internal)?
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    cursor: Option<i64>,
    limit: Option<u32>,
}

/// `GET /v1/assets?cursor=&limit=` — the caller's assets newest first (an auditor's or admin's:
/// everyone's); `next_cursor` continues.
pub async fn list(
    State(st): State<AppState>,
    caller: Caller,
    Query(q): Query<ListQuery>,
) -> ApiResult<Response> {
    let limit = q.limit.unwrap_or(50);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::bad_request("limit must be 1 to 1000"));
    }
    let me = caller.id();
    let owner = (!caller.has(Scope::Auditor)).then_some(me.as_str());
    let (items, next) = st.store.list_assets(owner, q.cursor, limit).await?;
    Ok(Json(json!({"items": items, "next_cursor": next})).into_response())
}
