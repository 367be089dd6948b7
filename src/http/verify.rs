//! `POST /v1/verify` — a dispute: rendered images (PNG/JPEG, multipart field `image`, repeated)
//! and optionally `asset_id`. The images are decoded once per decoder (logits and pooled
//! features averaged over the images) and tested against the asset's message — or, without an
//! asset id, against every registered message — each read with the decoder its key names
//! (`decoder::registry`), through its asset's matched head and relative to its asset reference
//! when the job registered them, with p-values corrected for the number of candidates tested.
//! A registration whose decoder the server does not hold is not tested but listed
//! (`untestable`); when the dispute names an asset and none of its watermarks can be tested, the
//! answer is 409.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::extract::{Multipart, State};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use sha2::{Digest, Sha256};
use uuid::Uuid;

use super::AppState;
use super::assets::{multipart_err, next_chunk, next_field};
use super::auth::Caller;
use super::error::{ApiError, ApiResult};
use crate::decoder::artifact::short_digest;
use crate::decoder::eval::decode_images;
use crate::decoder::registry::{self, Located};
use crate::store::{AssetKind, AuditEntry, NewVerification, Registration, Scope};
use crate::verify::dispute::{Candidate, Decoded, judge};

/// Largest image file accepted for verification.
const MAX_IMAGE_BYTES: usize = 64 << 20;
/// Candidates listed in a response (the decision uses all of them).
const LIST: usize = 10;

/// A reader for a PNG or JPEG (415 for anything else).
fn reader(bytes: &[u8], i: usize) -> ApiResult<image::ImageReader<std::io::Cursor<&[u8]>>> {
    let r = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(ApiError::internal)?;
    match r.format() {
        Some(image::ImageFormat::Png | image::ImageFormat::Jpeg) => Ok(r),
        _ => Err(ApiError::unsupported(format!(
            "image {i}: only PNG and JPEG images can be verified"
        ))),
    }
}

/// Width × height from the image's header, without decoding it.
fn header_pixels(bytes: &[u8], i: usize) -> ApiResult<u64> {
    let (w, h) = reader(bytes, i)?
        .into_dimensions()
        .map_err(|e| ApiError::unprocessable(format!("image {i}: {e}")))?;
    Ok(u64::from(w) * u64::from(h))
}

/// Refuses a request whose images hold more than `max` pixels together (413), before any of
/// them is decoded.
fn check_pixels(images: &[Vec<u8>], max: u64) -> ApiResult<()> {
    let mut total = 0u64;
    for (i, b) in images.iter().enumerate() {
        total = total.saturating_add(header_pixels(b, i)?);
    }
    if total > max {
        return Err(ApiError::too_large(format!(
            "the images hold {total} pixels together; one verification decodes at most {max} \
             (send fewer or smaller renders, or split them over several requests)"
        )));
    }
    Ok(())
}

/// Waits up to `wait` for a decoding slot; 503 with `Retry-After` when none frees up.
async fn admit(
    slots: &std::sync::Arc<tokio::sync::Semaphore>,
    wait: std::time::Duration,
) -> ApiResult<tokio::sync::OwnedSemaphorePermit> {
    super::admit(
        slots,
        wait,
        "every verification slot is busy; retry shortly",
    )
    .await
}

/// Image `i` of a dispute, decoded as `/v1/verify` decodes it: PNG or JPEG by its content, each
/// side at most `max_side` (checked from the header, before the pixels are allocated), at least
/// 64 × 64, as 8-bit RGB; 422 otherwise.
pub fn decode_image(bytes: &[u8], i: usize, max_side: u32) -> ApiResult<image::RgbImage> {
    let mut r = reader(bytes, i)?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(max_side);
    limits.max_image_height = Some(max_side);
    r.limits(limits);
    // A file the JPEG decoder panics on is the client's error like any other bad image
    // (`crate::image_file`).
    let decoded = crate::image_file::guarded(|| r.decode()).map_err(|_| {
        tracing::warn!(image = i, "the image decoder panicked on a malformed file");
        ApiError::unprocessable(format!("image {i}: {}", crate::image_file::DECODER_PANIC))
    })?;
    let img = decoded
        .map_err(|e| ApiError::unprocessable(format!("image {i}: {e}")))?
        .to_rgb8();
    if img.width() < 64 || img.height() < 64 {
        return Err(ApiError::unprocessable(format!(
            "image {i} is {}×{}; the decoder needs at least 64×64 pixels",
            img.width(),
            img.height()
        )));
    }
    Ok(img)
}

/// What the images are tested against for a registration: its payload, matched head,
/// reference, and the decoder `located` that reads its bits.
fn candidate(r: Registration, located: &Located) -> Candidate {
    Candidate {
        asset_id: r.asset_id,
        payload: r.key.payload(),
        reference: r.reference,
        head: r.head,
        decoder: located.digest.clone(),
    }
}

/// The decoder that reads a registration's bits: the one its key names, or — for a key
/// registered before keys named one — the server's current decoder for its length. `None`
/// when the server holds no decoder with the named digest (`decoder::registry`).
fn locate(r: &Registration, weights_dir: Option<&std::path::Path>) -> ApiResult<Option<Located>> {
    let bits = r.key.bits();
    match &r.decoder {
        Some(d) => registry::find(weights_dir, bits, d).map_err(ApiError::internal),
        None => registry::current(weights_dir, bits)
            .map(Some)
            .map_err(ApiError::internal),
    }
}

/// The registrations whose decoder this server does not hold, for the response.
fn untestable_json(missing: &[(Uuid, String)]) -> serde_json::Value {
    let listed: Vec<_> = missing
        .iter()
        .take(LIST)
        .map(|(id, d)| json!({"asset_id": id, "decoder": d}))
        .collect();
    json!({"count": missing.len(), "listed": listed})
}

/// `POST /v1/verify`.
pub async fn verify(
    State(st): State<AppState>,
    caller: Caller,
    mut mp: Multipart,
) -> ApiResult<Response> {
    caller.require(&[Scope::Verifier, Scope::Owner, Scope::Auditor])?;
    // Before the body is read: a key over its budget costs the server nothing more.
    st.limits.verify.take(&caller.id()).map_err(|wait| {
        ApiError::too_many(
            format!(
                "this API key may submit {} verifications a minute",
                st.cfg.verify_per_minute
            ),
            wait,
        )
    })?;
    let mut images = vec![];
    let mut hashes = vec![];
    let mut asset_id: Option<Uuid> = None;
    let idle = st.cfg.body_idle_timeout();
    while let Some(mut field) = next_field(&mut mp, idle).await? {
        match field.name().unwrap_or_default() {
            "image" => {
                if images.len() == st.cfg.max_verify_images {
                    return Err(ApiError::too_large(format!(
                        "at most {} images per verification",
                        st.cfg.max_verify_images
                    )));
                }
                let mut bytes = Vec::new();
                while let Some(chunk) = next_chunk(&mut field, idle).await? {
                    if bytes.len() + chunk.len() > MAX_IMAGE_BYTES {
                        return Err(ApiError::too_large(format!(
                            "image {} is larger than {MAX_IMAGE_BYTES} bytes",
                            images.len()
                        )));
                    }
                    bytes.extend_from_slice(&chunk);
                }
                hashes.push(hex::encode(Sha256::digest(&bytes)));
                images.push(bytes);
            }
            "asset_id" => {
                let t = field.text().await.map_err(multipart_err)?;
                asset_id = Some(t.trim().parse().map_err(|_| {
                    ApiError::bad_request(format!("asset_id '{}' is not a UUID", t.trim()))
                })?);
            }
            other => {
                return Err(ApiError::bad_request(format!(
                    "unexpected multipart field '{other}' (expected 'image' and optionally 'asset_id')"
                )));
            }
        }
    }
    if images.is_empty() {
        return Err(ApiError::bad_request(
            "no 'image' field: submit at least one rendered image",
        ));
    }
    check_pixels(&images, st.cfg.max_verify_pixels)?;
    // Candidates: the asset's payload (or its watermarked versions'), or every registered one.
    // An unknown id and an asset without a finished watermark get the same 404: a verifier
    // learns no more than that this id carries no registered watermark.
    let unregistered = || {
        ApiError::new(
            axum::http::StatusCode::NOT_FOUND,
            "Not found",
            "no registered watermark for this asset id (unknown, or no finished watermarking job)",
        )
    };
    let registrations: Vec<Registration> = match asset_id {
        Some(id) => {
            let a = st.store.get_asset(id).await?.ok_or_else(unregistered)?;
            let ids = match a.kind {
                AssetKind::Watermarked => vec![a.id],
                AssetKind::Original => st
                    .store
                    .watermarked_of(a.id)
                    .await?
                    .into_iter()
                    .map(|w| w.id)
                    .collect(),
            };
            let mut r = vec![];
            for id in ids {
                if let Some(reg) = st.store.registration(id).await? {
                    r.push(reg);
                }
            }
            if r.is_empty() {
                return Err(unregistered());
            }
            r
        }
        None => st.store.registrations().await?,
    };
    let max_side = st.cfg.max_image_side;
    let decoders = st.decoders.clone();
    let cfg = st.cfg.clone();
    let n_images = images.len();
    let permit = admit(
        &st.verify_slots,
        std::time::Duration::from_millis(st.cfg.verify_wait_ms),
    )
    .await?;
    let decoded = tokio::task::spawn_blocking(move || {
        let _permit = permit; // held until the decoding ends
        let weights_dir = cfg.weights_dir.as_deref();
        // Each registration's decoder; those this server does not hold are set aside.
        let mut candidates = vec![];
        let mut missing = vec![];
        let mut used: BTreeMap<String, Located> = BTreeMap::new();
        // Looked up once per (length, digest): a dispute without an asset id reads every key.
        let mut found: BTreeMap<(usize, Option<String>), Option<Located>> = BTreeMap::new();
        for r in registrations {
            let k = (r.key.bits(), r.decoder.clone());
            let l = match found.get(&k) {
                Some(l) => l.clone(),
                None => {
                    let l = locate(&r, weights_dir)?;
                    found.insert(k, l.clone());
                    l
                }
            };
            match l {
                Some(l) => {
                    candidates.push(candidate(r, &l));
                    used.entry(l.digest.clone()).or_insert(l);
                }
                None => missing.push((r.asset_id, r.decoder.unwrap_or_default())),
            }
        }
        // Asked about one asset whose every watermark this server cannot read: say so.
        if asset_id.is_some() && candidates.is_empty() && !missing.is_empty() {
            let d = &missing[0].1;
            return Err(ApiError::conflict(format!(
                "the watermark was written with decoder {}…, which this server does not hold; \
                 the operator can restore it by putting that decoder's files in the weights \
                 folder's archive/ (weights/README.md)",
                short_digest(d)
            )));
        }
        // Without candidates the images are still decoded (32 bits), for the response.
        if used.is_empty() {
            let l = registry::current(weights_dir, 32).map_err(ApiError::internal)?;
            used.insert(l.digest.clone(), l);
        }
        let imgs = images
            .iter()
            .enumerate()
            .map(|(i, b)| decode_image(b, i, max_side))
            .collect::<ApiResult<Vec<_>>>()?;
        let mut out = BTreeMap::new();
        let mut detail = serde_json::Map::new();
        let mut plain = serde_json::Map::new();
        for (digest, l) in &used {
            let r = decoders
                .with(l, |m, d| decode_images(m, &imgs, d))
                .map_err(ApiError::internal)?;
            let d = Decoded {
                logits: r.logits,
                features: r.features,
            };
            let hex = d.plain_hex();
            // Keyed by length for the server's current main decoder (what a new job writes
            // for first), by `length@digest` for the others (the coarse one, older ones).
            let current = registry::current(weights_dir, l.bits).is_ok_and(|c| c.digest == *digest);
            let key = if current {
                l.bits.to_string()
            } else {
                format!("{}@{}", l.bits, short_digest(digest))
            };
            detail.insert(
                key.clone(),
                json!({"decoder": digest, "confidence": r.confidence, "per_image": r.per_image}),
            );
            plain.insert(key, hex.into());
            out.insert(digest.clone(), d);
        }
        Ok::<_, ApiError>((out, detail, plain, candidates, missing))
    })
    .await
    .map_err(ApiError::internal)??;
    let (decoded, detail, plain, candidates, missing) = decoded;
    let verdict = judge(&decoded, &candidates, st.cfg.fpr, LIST).map_err(ApiError::internal)?;
    let result = json!({
        "images": n_images,
        "asset_id": asset_id,
        "decoded": plain,
        "decoding": detail,
        "untestable": untestable_json(&missing),
        "candidates_tested": verdict.candidates_tested,
        "detected": verdict.detected,
        "fpr": verdict.fpr,
        "best": verdict.best,
        "results": verdict.results,
    });
    let (vid, audit_id) = st
        .store
        .record_verification(
            NewVerification {
                actor: caller.id(),
                asset_id,
                images: n_images as u32,
                image_sha256: hashes,
                result: result.clone(),
            },
            AuditEntry {
                actor: caller.id(),
                action: "verify".into(),
                asset_id,
                job_id: None,
                details: json!({
                    "images": n_images,
                    "detected": verdict.detected,
                    "candidates_tested": verdict.candidates_tested,
                    "best_asset": verdict.best.as_ref().map(|b| b.asset_id),
                    "best_p_value_corrected": verdict.best.as_ref().map(|b| b.detection.p_value_corrected),
                }),
            },
        )
        .await?;
    st.metrics.verifications.fetch_add(1, Ordering::Relaxed);
    if verdict.detected {
        st.metrics.detections.fetch_add(1, Ordering::Relaxed);
    }
    let mut body = result;
    body["verification_id"] = json!(vid);
    body["audit_id"] = json!(audit_id);
    Ok(Json(body).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::StatusCode;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let mut out = vec![];
        image::RgbImage::new(w, h)
            .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
            .unwrap();
        out
    }

    #[test]
    fn the_pixels_of_a_request_are_bounded_before_decoding() {
        let imgs = vec![png(100, 100), png(100, 50)];
        assert!(check_pixels(&imgs, 15_000).is_ok());
        let e = check_pixels(&imgs, 14_999).unwrap_err();
        assert_eq!(e.status, StatusCode::PAYLOAD_TOO_LARGE);
        assert!(e.detail.contains("15000 pixels"), "{}", e.detail);
        let e = check_pixels(&[b"GIF89a....".to_vec()], 1 << 20).unwrap_err();
        assert_eq!(e.status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    }

    #[test]
    fn a_file_the_jpeg_decoder_panics_on_is_a_422_like_any_bad_image() {
        let bytes =
            include_bytes!("../../fuzz/regressions/image/zune_jpeg_progressive_upsample_panic.jpg");
        let e = decode_image(bytes, 3, 4096).unwrap_err();
        assert_eq!(e.status, StatusCode::UNPROCESSABLE_ENTITY);
        assert!(e.detail.starts_with("image 3: "), "{}", e.detail);
        // A good image still decodes after it (nothing poisoned).
        assert_eq!(decode_image(&png(64, 64), 0, 4096).unwrap().width(), 64);
    }

    #[tokio::test]
    async fn a_saturated_verifier_answers_503_with_retry_after() {
        let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(1));
        let held = admit(&slots, std::time::Duration::from_millis(10))
            .await
            .unwrap();
        let e = admit(&slots, std::time::Duration::from_millis(10))
            .await
            .unwrap_err();
        assert_eq!(e.status, StatusCode::SERVICE_UNAVAILABLE);
        let r = e.into_response();
        assert_eq!(r.headers()[axum::http::header::RETRY_AFTER], "1");
        assert_eq!(
            r.headers()[axum::http::header::CONTENT_TYPE],
            "application/problem+json"
        );
        drop(held);
        assert!(
            admit(&slots, std::time::Duration::from_millis(10))
                .await
                .is_ok()
        );
    }
}
