//! The fuzz targets as plain functions: each takes the fuzzer's bytes, runs one parser the
//! service exposes to strangers and checks what a caller relies on. A panic (a failed check
//! included), a hang or an allocation over AFL's memory limit is a finding.
//!
//! `src/bin/<target>.rs` wraps each in `afl::fuzz!`; `src/bin/seeds.rs` writes the seed corpora
//! (`fuzz/corpus/<target>/`); `scripts/fuzz.sh` builds and runs them.

use splatmark::scene::{self, Limits};

/// The targets, as `scripts/fuzz.sh` and the `replay` binary name them.
pub const TARGETS: [&str; 6] = ["scene", "cameras", "image", "job_options", "query", "text"];

/// Runs target `name` on `data`; false for an unknown name.
pub fn run(name: &str, data: &[u8]) -> bool {
    match name {
        "scene" => scene_target(data),
        "cameras" => cameras_target(data),
        "image" => image_target(data),
        "job_options" => job_options_target(data),
        "query" => query_target(data),
        "text" => text_target(data),
        _ => return false,
    }
    true
}

/// The limits uploads are read under, scaled down so that a declared count the reader accepts
/// still fits AFL's memory limit.
fn limits() -> Limits {
    Limits {
        max_gaussians: 200_000,
        max_file_bytes: Some(64 << 20),
    }
}

/// Scene upload: the first byte picks the file name's extension (`.splat` has no magic, so the
/// name decides); the rest is the file. A scene that reads back is valid, and writing it as an
/// INRIA PLY and reading that gives it back bit for bit.
pub fn scene_target(data: &[u8]) {
    let Some((&pick, bytes)) = data.split_first() else {
        return;
    };
    let hint = [None, Some("ply"), Some("splat"), Some("spz")][usize::from(pick % 4)];
    let Ok((_, g)) = scene::format::read_scene_bytes_detect(bytes, hint, &limits()) else {
        return;
    };
    assert!(g.validate().is_ok(), "a scene that was read is valid");
    let mut ply = Vec::new();
    scene::format::write_ply(&g, &mut ply).expect("a valid scene writes");
    let back = scene::format::read_scene_bytes(&ply, Some("ply"), &limits())
        .expect("what we wrote reads back");
    assert!(back == g, "PLY round trip changed the scene");
}

/// Camera upload (`cameras.json`, `transforms.json`, `poses_bounds.npy`): every camera read has
/// a size and finite intrinsics and pose, so a job can render through it.
pub fn cameras_target(data: &[u8]) {
    let Ok((_, cams)) = scene::camera::read_cameras_bytes(data, "cameras") else {
        return;
    };
    for c in &cams {
        assert!(
            c.width > 0 && c.height > 0,
            "camera {} has no pixels",
            c.name
        );
        assert!(
            [c.fx, c.fy, c.cx, c.cy].iter().all(|v| v.is_finite()),
            "camera {} has non-finite intrinsics",
            c.name
        );
        assert!(
            c.rotation_mat()
                .to_cols_array()
                .iter()
                .all(|v| v.is_finite())
                && c.center().is_finite(),
            "camera {} has a non-finite pose",
            c.name
        );
    }
}

/// An image of a dispute (`/v1/verify`): decoded within the side limit, at least 64² pixels.
pub fn image_target(data: &[u8]) {
    const MAX_SIDE: u32 = 1024;
    if let Ok(img) = splatmark::http::verify::decode_image(data, 0, MAX_SIDE) {
        assert!((64..=MAX_SIDE).contains(&img.width()));
        assert!((64..=MAX_SIDE).contains(&img.height()));
    }
}

/// A job's options (`POST /v1/assets/{id}/watermark`): resolved against the default
/// configuration, and the resolved job — stored as JSON in the job row — reads back equal.
pub fn job_options_target(data: &[u8]) {
    use splatmark::queue::spec::{JobOptions, JobSpec};
    let Ok(opts) = serde_json::from_slice::<JobOptions>(data) else {
        return;
    };
    let Ok(spec) = opts.resolve(&splatmark::config::Config::default(), 32) else {
        return;
    };
    let json = serde_json::to_string(&spec).expect("a resolved job serialises");
    let back: JobSpec = serde_json::from_str(&json).expect("a stored job reads back");
    assert!(back == spec, "the stored job is not the job that runs");
}

/// The query strings of the paged listings (`/v1/audit`, `/v1/assets/{id}/attribution`):
/// parsed as axum does, then checked as the handlers do; what passes is a usable filter.
pub fn query_target(data: &[u8]) {
    use axum::extract::Query;
    use splatmark::http::{attribution::AttributionQuery, audit::AuditQuery};
    let Ok(s) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(uri) = format!("/v1/audit?{s}").parse::<axum::http::Uri>() else {
        return;
    };
    if let Ok(Query(q)) = Query::<AuditQuery>::try_from_uri(&uri)
        && let Ok(filter) = q.into_filter()
    {
        assert!((1..=splatmark::store::MAX_AUDIT_PAGE).contains(&filter.limit));
        for t in [&filter.since, &filter.until].into_iter().flatten() {
            let n = splatmark::store::normalize_timestamp(t);
            assert!(n.is_some(), "an accepted time normalises");
        }
    }
    if let Ok(Query(q)) = Query::<AttributionQuery>::try_from_uri(&uri)
        && let Ok(page) = q.into_page()
    {
        assert!((1..=splatmark::http::attribution::MAX_PAGE).contains(&page.limit));
    }
}

/// Free text a client sends that has a grammar: times (`since`, `until`) and hex messages. A
/// normalised time is a fixed point; a parsed message prints back as its own hex.
pub fn text_target(data: &[u8]) {
    use splatmark::verify::message::{parse_hex, to_hex};
    let Ok(s) = std::str::from_utf8(data) else {
        return;
    };
    if let Some(n) = splatmark::store::normalize_timestamp(s) {
        assert_eq!(
            splatmark::store::normalize_timestamp(&n).as_deref(),
            Some(n.as_str()),
            "normalising twice changes {s:?}"
        );
    }
    for bits in [32, 48, 64] {
        if let Ok(m) = parse_hex(s, bits) {
            assert_eq!(m.len(), bits);
            assert_eq!(
                parse_hex(&to_hex(&m), bits).unwrap(),
                m,
                "hex round trip of {s:?}"
            );
        }
    }
}
