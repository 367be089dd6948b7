//! `/v1/assets/{id}/attribution…`: the per-Gaussian attribution of a watermarked asset — its
//! records page by page, their summary, and what the console's attribution viewer shows: a
//! view of the scene drawn as one of the attribution pictures ([`crate::embed::explain`]) and
//! the Gaussian under a pixel of it with its record (the "why" panel).

use axum::Json;
use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;

use super::AppState;
use super::assets::{load_scenes, parse_id, readable};
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::embed::attribution::AttributionRecord;
use crate::embed::explain::{ExplainError, Layer, Pictures};
use crate::embed::sbag::Role;
use crate::scene::Camera;
use crate::scene::orbit::{OrbitOptions, orbit_cameras};
use crate::store::{Asset, AssetKind};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AttributionQuery {
    role: Option<String>,
    cursor: Option<u32>,
    limit: Option<u32>,
}
/// Largest attribution page.
pub const MAX_PAGE: u32 = 10_000;

/// One page of an attribution listing, as a client asked for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AttributionPage {
    /// Only the Gaussians of this role.
    pub role: Option<Role>,
    /// Continue after this Gaussian index.
    pub cursor: Option<u32>,
    /// At most this many records, 1 to [`MAX_PAGE`].
    pub limit: u32,
}

impl AttributionQuery {
    /// The page this query asks for, checked as the handler checks it (400 for an unknown role
    /// or a limit outside 1 to [`MAX_PAGE`]).
    pub fn into_page(self) -> ApiResult<AttributionPage> {
        let role = match self.role.as_deref() {
            None => None,
            Some("carrier") => Some(Role::Carrier),
            Some("compensator") => Some(Role::Compensator),
            Some("untouched") => Some(Role::Untouched),
            Some(r) => {
                return Err(ApiError::bad_request(format!(
                    "role '{r}': expected carrier, compensator or untouched"
                )));
            }
        };
        let limit = self.limit.unwrap_or(1000);
        if !(1..=MAX_PAGE).contains(&limit) {
            return Err(ApiError::bad_request(format!(
                "limit must be 1 to {MAX_PAGE}"
            )));
        }
        Ok(AttributionPage {
            role,
            cursor: self.cursor,
            limit,
        })
    }
}

async fn watermarked(st: &AppState, caller: &Caller, id: &str) -> ApiResult<Asset> {
    let a = readable(st, caller, parse_id(id)?).await?;
    if a.kind != AssetKind::Watermarked {
        return Err(ApiError::not_found(
            "attribution (this asset is an original; its watermarked versions have one)",
        ));
    }
    Ok(a)
}

/// `GET /v1/assets/{id}/attribution?role=&cursor=&limit=` — one record per Gaussian of a
/// watermarked asset, in index order; `next_cursor` continues.
pub async fn attribution(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    Query(q): Query<AttributionQuery>,
) -> ApiResult<Response> {
    let a = watermarked(&st, &caller, &id).await?;
    let page = q.into_page()?;
    let (items, next) = st
        .store
        .attribution_page(a.id, page.role, page.cursor, page.limit)
        .await?;
    Ok(Json(json!({"items": items, "next_cursor": next})).into_response())
}

/// `GET /v1/assets/{id}/attribution/summary`.
pub async fn attribution_summary(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let a = watermarked(&st, &caller, &id).await?;
    Ok(Json(st.store.attribution_summary(a.id).await?).into_response())
}

/// Most orbit views a picture may be one of.
pub const MAX_VIEWS: usize = 64;
/// Sides of a picture, pixels.
pub const PICTURE_SIDES: std::ops::RangeInclusive<u32> = 32..=1024;

/// `?layer=view|roles|heat|diff&view=K&views=N&size=S`: view K of N orbit views around the
/// scene (the orbit the embedding uses when no cameras come with an upload), S × S pixels.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PictureQuery {
    layer: Option<String>,
    view: Option<usize>,
    views: Option<usize>,
    size: Option<u32>,
}

/// The picture query plus the pixel (`x`, `y`) to pick.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PickQuery {
    view: Option<usize>,
    views: Option<usize>,
    size: Option<u32>,
    x: u32,
    y: u32,
}

/// The view (index, count, side) a query asks for, checked.
fn view_of(
    view: Option<usize>,
    views: Option<usize>,
    size: Option<u32>,
) -> ApiResult<(usize, usize, u32)> {
    let (views, size) = (views.unwrap_or(8), size.unwrap_or(384));
    if !(1..=MAX_VIEWS).contains(&views) {
        return Err(ApiError::bad_request(format!(
            "views must be 1 to {MAX_VIEWS}"
        )));
    }
    if !PICTURE_SIDES.contains(&size) {
        return Err(ApiError::bad_request(format!(
            "size must be {} to {} pixels",
            PICTURE_SIDES.start(),
            PICTURE_SIDES.end()
        )));
    }
    let view = view.unwrap_or(0);
    if view >= views {
        return Err(ApiError::bad_request(format!(
            "view {view} of {views}: views are numbered from 0"
        )));
    }
    Ok((view, views, size))
}

fn explain_err(e: ExplainError) -> ApiError {
    match e {
        ExplainError::OutOfView { .. } => ApiError::bad_request(e.to_string()),
        e => ApiError::internal(e),
    }
}

/// Every attribution record of `a`, page by page.
async fn all_records(st: &AppState, a: &Asset) -> ApiResult<Vec<AttributionRecord>> {
    let mut out = Vec::with_capacity(a.gaussians as usize);
    let mut cursor = None;
    loop {
        let (items, next) = st
            .store
            .attribution_page(a.id, None, cursor, MAX_PAGE)
            .await?;
        out.extend(items);
        match next {
            Some(c) => cursor = Some(c),
            None => return Ok(out),
        }
    }
}

/// Bytes per Gaussian drawing pictures holds besides the parsed scenes: the role and heatmap
/// copies of the scene (59 floats each at SH degree 3) and its attribution record.
const PICTURE_BYTES_PER_GAUSSIAN: u64 = 2 * 59 * 4 + 160;

/// Loads what the pictures of `a` need (its original too when `with_original`) and runs `draw`
/// on them with orbit camera `view` of `views` at `size`², off the async runtime, within the
/// upload memory budget and parsing slots.
async fn with_pictures<T: Send + 'static>(
    st: &AppState,
    a: &Asset,
    with_original: bool,
    (view, views, size): (usize, usize, u32),
    draw: impl FnOnce(&Pictures, &Camera) -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    let records = all_records(st, a).await?;
    let original = match (with_original, a.parent_id) {
        (false, _) => None,
        (true, Some(p)) => Some(
            st.store
                .get_asset(p)
                .await?
                .ok_or_else(|| ApiError::internal("a watermarked asset without its original"))?,
        ),
        (true, None) => {
            return Err(ApiError::internal(
                "a watermarked asset without its original",
            ));
        }
    };
    let mut wanted = vec![a];
    wanted.extend(original.as_ref());
    let (mut scenes, held) = load_scenes(
        st,
        &wanted,
        PICTURE_BYTES_PER_GAUSSIAN,
        "drawing this asset",
    )
    .await?;
    tokio::task::spawn_blocking(move || {
        let _held = held;
        let original = (scenes.len() > 1).then(|| scenes.pop()).flatten();
        let marked = scenes.pop().ok_or_else(|| ApiError::internal("no scene"))?;
        let cams = orbit_cameras(
            &marked,
            &OrbitOptions {
                count: views,
                width: size,
                height: size,
                ..OrbitOptions::default()
            },
        )
        .map_err(ApiError::internal)?;
        let pictures = Pictures::new(marked, records, original).map_err(explain_err)?;
        draw(&pictures, &cams[view])
    })
    .await
    .map_err(ApiError::internal)?
}

/// `GET /v1/assets/{id}/attribution/picture` — one attribution picture of a watermarked asset
/// as PNG: the render (`view`), roles (carriers red, compensators blue, untouched grey), the
/// watermark-gradient heatmap (`heat`) or |watermarked − original| × 10 (`diff`).
pub async fn picture(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    Query(q): Query<PictureQuery>,
) -> ApiResult<Response> {
    let a = watermarked(&st, &caller, &id).await?;
    let layer = match q.layer.as_deref() {
        None => Layer::View,
        Some(s) => Layer::parse(s).ok_or_else(|| {
            ApiError::bad_request(format!("layer '{s}': expected view, roles, heat or diff"))
        })?,
    };
    let at = view_of(q.view, q.views, q.size)?;
    let png = with_pictures(&st, &a, layer == Layer::Diff, at, move |p, cam| {
        let img = p.draw_rgb8(layer, cam).map_err(explain_err)?;
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)
            .map_err(ApiError::internal)?;
        Ok(out.into_inner())
    })
    .await?;
    let mut r = Body::from(png).into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    // An asset never changes: its pictures may be kept by the reader's browser.
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, max-age=3600"),
    );
    Ok(r)
}

/// `GET /v1/assets/{id}/attribution/pick?x=&y=` — the Gaussian that pixel (`x`, `y`) of the
/// picture shows most (largest α·T) and its attribution record; `{"index": null}` on the
/// background.
pub async fn pick(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    Query(q): Query<PickQuery>,
) -> ApiResult<Response> {
    let a = watermarked(&st, &caller, &id).await?;
    let at = view_of(q.view, q.views, q.size)?;
    let (x, y) = (q.x, q.y);
    let picked = with_pictures(&st, &a, false, at, move |p, cam| {
        p.pick(cam, x, y).map_err(explain_err)
    })
    .await?;
    Ok(Json(match picked {
        Some(p) => json!({"index": p.index, "weight": p.weight, "record": p.record}),
        None => json!({"index": null}),
    })
    .into_response())
}
