//! The HTTP API end to end against the real server (each test boots its own, on 127.0.0.1:0 with
//! a temporary database and blob folder): uploads in every format and the ways they go wrong,
//! keys and scopes, idempotency, rate limits, audit queries, metrics and the served spec.

use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

use splatmark::scene::synthetic::object_scene;
use splatmark::store::MasterKey;

mod common;
use common::*;

#[tokio::test]
async fn bad_uploads_get_4xx_problems_and_leave_nothing_behind() {
    let mut t = TestApp::start_with(|c| c.max_upload_bytes = 200_000).await;
    let k = t.keys().await;
    let good = ply_bytes(&object_scene(300, 0, 1));
    let truncated = good[..good.len() - 100].to_vec();
    let bomb = b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\nend_header\n".to_vec();
    let mut png = vec![];
    image::RgbImage::new(8, 8)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let big = ply_bytes(&object_scene(5000, 0, 1));
    assert!(big.len() > 200_000);
    // An .spz whose gzip CRC-32 does not match its data.
    let mut bad_crc = spz_bytes(100);
    let at = bad_crc.len() - 8;
    bad_crc[at] ^= 0x40;
    // A gzip .spz of a few kilobytes whose zeros decompress to 200 000 points (issue 13: one
    // such 185 KB file declaring 3 M points took 870 MB of memory).
    let spz_bomb = {
        use std::io::Write;
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&2u32.to_le_bytes());
        raw.extend_from_slice(&200_000u32.to_le_bytes());
        raw.extend_from_slice(&[0, 12, 0, 0]);
        raw.resize(raw.len() + 200_000 * 19, 0);
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(&raw).unwrap();
        e.finish().unwrap()
    };
    for (name, bytes, status) in [
        ("bad_crc.spz", bad_crc, StatusCode::UNPROCESSABLE_ENTITY),
        ("bomb.spz", spz_bomb, StatusCode::UNPROCESSABLE_ENTITY),
        ("truncated.ply", truncated, StatusCode::UNPROCESSABLE_ENTITY),
        ("bomb.ply", bomb, StatusCode::PAYLOAD_TOO_LARGE),
        ("picture.ply", png, StatusCode::UNSUPPORTED_MEDIA_TYPE),
        ("big.ply", big, StatusCode::PAYLOAD_TOO_LARGE),
        ("empty.ply", vec![], StatusCode::UNPROCESSABLE_ENTITY),
    ] {
        let r = t.upload(&k.owner, name, bytes).await;
        let p = assert_problem(r, status).await;
        eprintln!("{name}: {}", p["detail"]);
        if name == "bad_crc.spz" {
            assert!(p["detail"].as_str().unwrap().contains("CRC-32"), "{p}");
        }
        if name == "bomb.spz" {
            assert!(
                p["detail"].as_str().unwrap().contains("compression bomb"),
                "{p}"
            );
        }
    }
    // A form without the scene field, and one with an unknown field.
    let r = t
        .client
        .post(t.url("/v1/assets"))
        .bearer_auth(&k.owner)
        .multipart(Form::new().text("colour", "red"))
        .send()
        .await
        .unwrap();
    assert_problem(r, StatusCode::BAD_REQUEST).await;
    // Nothing stored: no blob, no asset row, no upload in the audit log.
    assert!(t.stored_blobs().is_empty(), "{:?}", t.stored_blobs());
    assert_eq!(t.audited(&k.auditor, "asset.upload").await, 0);
    // …and a good upload still works.
    let r = t.upload(&k.owner, "ok.ply", good).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    t.stop().await;
}

#[tokio::test]
async fn uploads_are_checked_within_the_memory_budget() {
    // 4 MiB for the uploads being checked: a 60 000-Gaussian .splat (1.9 MB) takes ≈ 5.5 MB
    // to read (the file, the decoded scene, the header).
    let mut t = TestApp::start_with(|c| c.upload_memory_mb = 4).await;
    let k = t.keys().await;
    let splat = |n: u32, y: f32| {
        let mut b = Vec::new();
        for i in 0..n {
            for v in [i as f32 * 1e-5, y, 0.3, 0.02, 0.03, 0.04] {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(&[200, 100, 50, 180, 255, 128, 128, 128]);
        }
        b
    };
    let r = t.upload(&k.owner, "large.splat", splat(60_000, -0.2)).await;
    let p = assert_problem(r, StatusCode::PAYLOAD_TOO_LARGE).await;
    let detail = p["detail"].as_str().unwrap();
    assert!(
        detail.contains("about 6 MiB") && detail.contains("within 4 MiB (upload_memory_mb)"),
        "{p}"
    );
    // Refused before it was read: nothing stored or audited.
    assert!(t.stored_blobs().is_empty());
    assert_eq!(t.audited(&k.auditor, "asset.upload").await, 0);
    // Scenes that fit are checked and stored, each giving its memory back: 25 000 Gaussians
    // take ≈ 2.5 MB, so the second fits only once the first has returned its reservation.
    for (name, y) in [("a.splat", 0.1), ("b.splat", 0.2), ("c.splat", 0.3)] {
        let r = t.upload(&k.owner, name, splat(25_000, y)).await;
        assert_eq!(r.status(), StatusCode::CREATED, "{name}");
    }
    t.stop().await;
}

#[tokio::test]
async fn missing_or_wrong_scopes_are_401_and_403() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let other_owner = t.key(&["owner"]).await;
    let scene = ply_bytes(&object_scene(200, 0, 2));
    // No key, a malformed header, an unknown key: 401.
    let r = t.client.get(t.url("/v1/audit")).send().await.unwrap();
    assert_problem(r, StatusCode::UNAUTHORIZED).await;
    let r = t
        .client
        .get(t.url("/v1/audit"))
        .header("authorization", "Basic abc")
        .send()
        .await
        .unwrap();
    assert_problem(r, StatusCode::UNAUTHORIZED).await;
    let r = t.get("smk_0000", "/v1/audit").await;
    assert_problem(r, StatusCode::UNAUTHORIZED).await;
    // Wrong scopes: 403.
    let r = t.upload(&k.verifier, "s.ply", scene.clone()).await;
    assert_problem(r, StatusCode::FORBIDDEN).await;
    let r = t.get(&k.owner, "/v1/audit").await;
    assert_problem(r, StatusCode::FORBIDDEN).await;
    let r = t
        .client
        .post(t.url("/v1/keys"))
        .bearer_auth(&k.owner)
        .json(&json!({"name": "x", "scopes": ["admin"]}))
        .send()
        .await
        .unwrap();
    assert_problem(r, StatusCode::FORBIDDEN).await;
    // Another owner's asset does not exist for you.
    let a: Value = t
        .upload(&k.owner, "s.ply", scene)
        .await
        .json()
        .await
        .unwrap();
    let id = a["id"].as_str().unwrap();
    let r = t.get(&other_owner, &format!("/v1/assets/{id}")).await;
    assert_problem(r, StatusCode::NOT_FOUND).await;
    let r = t
        .client
        .post(t.url(&format!("/v1/assets/{id}/watermark")))
        .bearer_auth(&other_owner)
        .json(&json!({}))
        .send()
        .await
        .unwrap();
    assert_problem(r, StatusCode::NOT_FOUND).await;
    // The auditor may read it, but not download the owner's scene; the admin may.
    assert_eq!(
        t.get(&k.auditor, &format!("/v1/assets/{id}"))
            .await
            .status(),
        StatusCode::OK
    );
    let r = t.get(&k.auditor, &format!("/v1/assets/{id}/file")).await;
    assert_problem(r, StatusCode::FORBIDDEN).await;
    let admin = t.admin.clone();
    let r = t.get(&admin, &format!("/v1/assets/{id}/file")).await;
    assert_eq!(r.status(), StatusCode::OK);
    // Verifying against an id that does not exist and against one without a watermark read
    // the same: a verifier learns nothing about which ids exist.
    let png = {
        let mut v = vec![];
        image::DynamicImage::ImageRgb8(image::RgbImage::new(64, 64))
            .write_to(&mut std::io::Cursor::new(&mut v), image::ImageFormat::Png)
            .unwrap();
        v
    };
    let mut answers = vec![];
    for asset in [id.to_string(), uuid::Uuid::new_v4().to_string()] {
        let form = Form::new()
            .part("image", Part::bytes(png.clone()).file_name("v.png"))
            .text("asset_id", asset);
        let r = t
            .client
            .post(t.url("/v1/verify"))
            .bearer_auth(&k.verifier)
            .multipart(form)
            .send()
            .await
            .unwrap();
        answers.push(assert_problem(r, StatusCode::NOT_FOUND).await);
    }
    assert_eq!(answers[0], answers[1]);
    // A revoked key stops working.
    let admin = t.admin.clone();
    let created: Value = t
        .client
        .post(t.url("/v1/keys"))
        .bearer_auth(&admin)
        .json(&json!({"name": "temp", "scopes": ["auditor"]}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let tok = created["token"].as_str().unwrap();
    assert_eq!(t.get(tok, "/v1/audit").await.status(), StatusCode::OK);
    let revoke = |id: String| {
        t.client
            .delete(t.url(&format!("/v1/keys/{id}")))
            .bearer_auth(&admin)
            .send()
    };
    let key_id = created["id"].as_str().unwrap().to_string();
    let r = revoke(key_id.clone()).await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    assert_problem(t.get(tok, "/v1/audit").await, StatusCode::UNAUTHORIZED).await;
    // Revoking it again is idempotent: 204 and no second audit row. An unknown key is 404.
    for _ in 0..3 {
        let r = revoke(key_id.clone()).await.unwrap();
        assert_eq!(r.status(), StatusCode::NO_CONTENT);
    }
    let r = revoke(uuid::Uuid::new_v4().to_string()).await.unwrap();
    assert_problem(r, StatusCode::NOT_FOUND).await;
    let audit: Value = t
        .get(&k.auditor, "/v1/audit?action=key.revoke")
        .await
        .json()
        .await
        .unwrap();
    let rows = audit["items"].as_array().unwrap();
    assert_eq!(rows.len(), 1, "{audit}");
    assert_eq!(rows[0]["details"]["key_id"], key_id);
    t.stop().await;
}

#[tokio::test]
async fn idempotency_keys_replay_and_conflict_and_bad_requests_are_named() {
    // No workers: jobs stay queued.
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let mut t = TestApp::boot(dir, cfg, MasterKey::generate().to_hex(), Some(vec![])).await;
    let k = t.keys().await;
    let a: Value = t
        .upload(&k.owner, "s.ply", ply_bytes(&object_scene(200, 0, 3)))
        .await
        .json()
        .await
        .unwrap();
    let id = a["id"].as_str().unwrap();
    let post = |body: Value, key: Option<&'static str>| {
        let mut rq = t
            .client
            .post(t.url(&format!("/v1/assets/{id}/watermark")))
            .bearer_auth(&k.owner)
            .json(&body);
        if let Some(key) = key {
            rq = rq.header("Idempotency-Key", key);
        }
        rq.send()
    };
    let r1 = post(json!({"bits": 32}), Some("k1")).await.unwrap();
    assert_eq!(r1.status(), StatusCode::ACCEPTED);
    let j1: Value = r1.json().await.unwrap();
    let r2 = post(json!({"bits": 32}), Some("k1")).await.unwrap();
    assert_eq!(r2.status(), StatusCode::ACCEPTED);
    assert_eq!(r2.headers()["idempotent-replayed"], "true");
    let j2: Value = r2.json().await.unwrap();
    assert_eq!(j1["id"], j2["id"], "same key, same job");
    let r3 = post(json!({"bits": 32, "options": {"steps": 5}}), Some("k1"))
        .await
        .unwrap();
    assert_problem(r3, StatusCode::CONFLICT).await;
    let j3: Value = post(json!({"bits": 32}), None)
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_ne!(j3["id"], j1["id"], "no key, a new job");
    // Bad requests say what is wrong.
    for (body, status, needle) in [
        (
            json!({"bits": 31}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "bits",
        ),
        (
            json!({"bits": 32, "message": "zz"}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "hex",
        ),
        (
            json!({"options": {"steps": 0}}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "steps",
        ),
        (
            json!({"colour": 1}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "colour",
        ),
    ] {
        let p = assert_problem(post(body, None).await.unwrap(), status).await;
        assert!(p["detail"].as_str().unwrap().contains(needle), "{p}");
    }
    // A message that is not hex is still a secret: the problem never repeats it.
    let p = assert_problem(
        post(json!({"bits": 32, "message": "c0ffee5g"}), None)
            .await
            .unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
    )
    .await;
    let detail = p["detail"].as_str().unwrap();
    assert!(detail.contains("character 8"), "{p}");
    assert!(!p.to_string().contains("c0ffee5"), "{p}");
    // Cancel a queued job; cancelling it again is a no-op (DELETE is idempotent).
    let jid = j3["id"].as_str().unwrap();
    let r = t
        .client
        .delete(t.url(&format!("/v1/jobs/{jid}")))
        .bearer_auth(&k.owner)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.json::<Value>().await.unwrap()["state"], "cancelled");
    let r = t
        .client
        .delete(t.url(&format!("/v1/jobs/{jid}")))
        .bearer_auth(&k.owner)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.json::<Value>().await.unwrap()["state"], "cancelled");
    t.stop().await;
}

#[tokio::test]
async fn health_metrics_and_the_served_spec_match_the_committed_one() {
    let mut t = TestApp::start().await;
    let r = t.client.get(t.url("/healthz")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let r = t.client.get(t.url("/readyz")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let m = t.metrics().await;
    assert!(
        m.contains("splatmark_http_responses_total{class=\"2xx\"}"),
        "{m}"
    );
    assert!(m.contains("splatmark_workers 1"), "{m}");
    assert!(
        m.contains("splatmark_worker_device{worker=\"cpu-0@") && m.contains("\",device=\"cpu\"} 1"),
        "{m}"
    );
    let served: Value = t
        .client
        .get(t.url("/openapi.json"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let committed: Value = serde_yaml_ng::from_str(
        &std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/api/openapi.yaml")).unwrap(),
    )
    .unwrap();
    assert_eq!(served, committed);
    let r = t.client.get(t.url("/v2/nothing")).send().await.unwrap();
    assert_problem(r, StatusCode::NOT_FOUND).await;
    t.stop().await;
}

#[tokio::test]
async fn cameras_uploaded_with_a_scene_are_validated_too() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let scene = ply_bytes(&object_scene(200, 0, 6));
    // One INRIA cameras.json entry looking at the origin from z = -4.
    let cams = json!([{
        "id": 0, "img_name": "c0", "width": 96, "height": 96,
        "position": [0.0, 0.0, -4.0],
        "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "fx": 100.0, "fy": 100.0
    }]);
    let post = |cams: Vec<u8>| {
        let form = Form::new()
            .part("scene", Part::bytes(scene.clone()).file_name("s.ply"))
            .part("cameras", Part::bytes(cams).file_name("cameras.json"));
        t.client
            .post(t.url("/v1/assets"))
            .bearer_auth(&k.owner)
            .multipart(form)
            .send()
    };
    let r = post(b"{\"frames\": 7}".to_vec()).await.unwrap();
    let p = assert_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(p["detail"].as_str().unwrap().contains("cameras"), "{p}");
    assert_eq!(t.stored_blobs(), Vec::<String>::new());
    let r = post(serde_json::to_vec(&cams).unwrap()).await.unwrap();
    assert_eq!(r.status(), StatusCode::CREATED);
    let a: Value = r.json().await.unwrap();
    assert_eq!(a["cameras_format"], "inria");
    assert_eq!(a["cameras_sha256"].as_str().unwrap().len(), 64);
    t.stop().await;
}

#[tokio::test]
async fn every_supported_scene_format_uploads_and_round_trips() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    for (name, bytes, format) in [
        ("a.ply", ply_bytes(&object_scene(100, 1, 3)), "ply"),
        (
            "b.compressed.ply",
            compressed_ply_bytes(100),
            "compressed_ply",
        ),
        ("c.splat", splat_bytes(100), "splat"),
        ("d.spz", spz_bytes(100), "spz"),
    ] {
        let r = t.upload(&k.owner, name, bytes.clone()).await;
        assert_eq!(
            r.status(),
            StatusCode::CREATED,
            "{name}: {}",
            r.text().await.unwrap()
        );
        let a: Value = r.json().await.unwrap();
        assert_eq!(a["format"], format, "{name}: {a}");
        assert_eq!(a["gaussians"], 100, "{name}: {a}");
        let id = a["id"].as_str().unwrap();
        // The metadata reads back, and the original comes back byte for byte.
        let m: Value = t
            .get(&k.owner, &format!("/v1/assets/{id}"))
            .await
            .json()
            .await
            .unwrap();
        assert_eq!(m["format"], format, "{name}: {m}");
        let f = t.get(&k.owner, &format!("/v1/assets/{id}/file")).await;
        assert_eq!(f.status(), StatusCode::OK);
        assert!(
            f.bytes().await.unwrap() == bytes,
            "{name}: the download differs"
        );
    }
    assert_eq!(t.audited(&k.auditor, "asset.upload").await, 4);
    t.stop().await;
}

#[tokio::test]
async fn an_upload_whose_insert_fails_leaves_no_blob_behind() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let kept = ply_bytes(&object_scene(100, 0, 4));
    let r = t.upload(&k.owner, "kept.ply", kept.clone()).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let kept_id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let before = t.stored_blobs();
    assert_eq!(before.len(), 1, "{before:?}");

    // The database refuses every new asset row (as a full disk or a broken file would).
    t.refuse_inserts("assets").await;

    // A new scene, with cameras: neither blob stays. The same bytes as a stored asset: that
    // asset's blob stays.
    let cams = json!([{
        "id": 0, "img_name": "c0", "width": 96, "height": 96,
        "position": [0.0, 0.0, -4.0],
        "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "fx": 100.0, "fy": 100.0
    }]);
    let form = Form::new()
        .part("scene", Part::bytes(splat_bytes(50)).file_name("new.splat"))
        .part(
            "cameras",
            Part::bytes(serde_json::to_vec(&cams).unwrap()).file_name("cameras.json"),
        );
    let r = t
        .client
        .post(t.url("/v1/assets"))
        .bearer_auth(&k.owner)
        .multipart(form)
        .send()
        .await
        .unwrap();
    let p = assert_problem(r, StatusCode::INTERNAL_SERVER_ERROR).await;
    assert!(!p["detail"].as_str().unwrap().contains("refused"), "{p}");
    let r = t.upload(&k.owner, "again.ply", kept.clone()).await;
    assert_problem(r, StatusCode::INTERNAL_SERVER_ERROR).await;
    assert_eq!(t.stored_blobs(), before);

    t.allow_inserts("assets").await;
    let f = t.get(&k.owner, &format!("/v1/assets/{kept_id}/file")).await;
    assert_eq!(f.status(), StatusCode::OK);
    assert!(f.bytes().await.unwrap() == kept);
    assert_eq!(t.audited(&k.auditor, "asset.upload").await, 1);
    let r = t.upload(&k.owner, "new.splat", splat_bytes(50)).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    t.stop().await;
}

#[tokio::test]
async fn uploaded_cameras_never_touch_the_servers_files() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let scene = ply_bytes(&object_scene(200, 0, 6));
    // A PNG that exists on the server, and a path above the upload's folder.
    let png = t.dir.path().join("server.png");
    image::RgbImage::new(64, 48).save(&png).unwrap();
    let identity = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]);
    let post = |file_path: String, size: bool| {
        let mut doc = json!({"fl_x": 100.0, "frames": [
            {"file_path": file_path, "transform_matrix": identity}
        ]});
        if size {
            doc["w"] = json!(96);
            doc["h"] = json!(72);
        }
        let form = Form::new()
            .part("scene", Part::bytes(scene.clone()).file_name("s.ply"))
            .part(
                "cameras",
                Part::bytes(serde_json::to_vec(&doc).unwrap()).file_name("transforms.json"),
            );
        t.client
            .post(t.url("/v1/assets"))
            .bearer_auth(&k.owner)
            .multipart(form)
            .send()
    };
    let mut details = vec![];
    for p in [
        "/etc/passwd".to_string(),
        "../../../../etc/hostname".to_string(),
        "../something".to_string(),
        png.to_string_lossy().into_owned(),
    ] {
        let r = post(p.clone(), false).await.unwrap();
        let v = assert_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
        let d = v["detail"].as_str().unwrap().to_string();
        assert!(d.contains("no image size"), "{p}: {d}");
        assert!(
            !d.contains("passwd") && !d.contains("something") && !d.contains(".png"),
            "{d}"
        );
        assert!(
            !d.contains(&t.dir.path().to_string_lossy().into_owned()),
            "{d}"
        );
        details.push(v);
    }
    assert!(details.windows(2).all(|w| w[0] == w[1]), "{details:?}");
    // Nothing was stored.
    assert_eq!(t.stored_blobs(), Vec::<String>::new());
    // With its size in the file, the same camera is accepted: the path is only a name, and
    // the server's PNG (64×48) is not what sized it.
    let r = post(png.to_string_lossy().into_owned(), true)
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::CREATED);
    let a: Value = r.json().await.unwrap();
    assert_eq!(a["cameras_format"], "nerf");
    t.stop().await;
}

#[tokio::test]
async fn audit_time_filters_must_be_real_instants() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    for q in [
        "since=2026-99-99T99:99:99Z",
        "since=2026-02-30T00:00:00Z",
        "until=2026-12-01T24:00:00Z",
        "until=2026-12-01T16:09:21.1234Z",
        "since=2026-12-01",
    ] {
        let r = t.get(&k.auditor, &format!("/v1/audit?{q}")).await;
        let p = assert_problem(r, StatusCode::BAD_REQUEST).await;
        assert!(
            p["detail"].as_str().unwrap().contains("RFC 3339"),
            "{q}: {p}"
        );
    }
    // Real instants work, with or without fraction digits.
    for q in [
        "since=2000-01-01T00:00:00Z",
        "since=2000-01-01T00:00:00.5Z&until=2999-12-31T23:59:59.999Z",
    ] {
        let r = t.get(&k.auditor, &format!("/v1/audit?{q}")).await;
        assert_eq!(r.status(), StatusCode::OK, "{q}");
        let v: Value = r.json().await.unwrap();
        assert!(!v["items"].as_array().unwrap().is_empty(), "{q}: {v}");
    }
    t.stop().await;
}

/// Starts a multipart upload by hand on a raw connection: the request head (declaring a body
/// of 100 000 bytes) and the first bytes of the scene field, nothing more.
async fn start_raw_upload(t: &TestApp, token: &str) -> tokio::net::TcpStream {
    use tokio::io::AsyncWriteExt;
    let addr = t.base.trim_start_matches("http://");
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /v1/assets HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\n\
         Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
         --XyZ\r\nContent-Disposition: form-data; name=\"scene\"; filename=\"s.ply\"\r\n\
         Content-Type: application/octet-stream\r\n\r\nply\nformat binary_little_endian 1.0\n"
    );
    s.write_all(head.as_bytes()).await.unwrap();
    s.flush().await.unwrap();
    s
}

#[tokio::test]
async fn stalled_and_vanishing_uploads_are_client_errors_not_server_errors() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut t = TestApp::start_with(|c| c.body_idle_timeout_ms = 300).await;
    let k = t.keys().await;
    let before = responses_of_class(&t, "5xx").await;

    // A client that stops sending mid-body gets 408 once the body has been silent for 300 ms,
    // instead of holding the connection for the whole request timeout.
    let mut s = start_raw_upload(&t, &k.owner).await;
    let started = Instant::now();
    let mut reply = vec![0u8; 4096];
    let n = tokio::time::timeout(Duration::from_secs(20), s.read(&mut reply))
        .await
        .expect("the server answers a stalled body")
        .unwrap();
    let reply = String::from_utf8_lossy(&reply[..n]).to_string();
    assert!(reply.starts_with("HTTP/1.1 408"), "{reply}");
    assert!(reply.contains("application/problem+json"), "{reply}");
    assert!(started.elapsed() < Duration::from_secs(15));

    // A client that closes its side before sending what it declared: a client error.
    let mut s = start_raw_upload(&t, &k.owner).await;
    s.shutdown().await.unwrap();
    let mut reply = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(20), s.read_to_end(&mut reply)).await;
    let reply = String::from_utf8_lossy(&reply).to_string();
    eprintln!("vanishing client: {:?}", reply.lines().next());
    assert!(
        reply.is_empty() || reply.starts_with("HTTP/1.1 400"),
        "{reply}"
    );

    // Neither counts as a server error, and neither left a blob behind.
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(responses_of_class(&t, "5xx").await, before);
    assert!(t.stored_blobs().is_empty());
    t.stop().await;
}

#[tokio::test]
async fn a_client_trickling_its_request_header_is_cut_off() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut t = TestApp::start_with(|c| c.header_timeout_ms = 500).await;
    let addr = t.base.trim_start_matches("http://").to_string();
    let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHo").await.unwrap();
    // One byte every 100 ms, never the end of the header; the server must close the connection
    // well before this client would give up on its own (10 s).
    let started = Instant::now();
    let closed = loop {
        let mut buf = [0u8; 512];
        match tokio::time::timeout(Duration::from_millis(100), s.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break true,
            Ok(Ok(n)) => {
                let reply = String::from_utf8_lossy(&buf[..n]).to_string();
                assert!(reply.starts_with("HTTP/1.1 408"), "{reply}");
                break true;
            }
            Err(_) => {}
        }
        if started.elapsed() > Duration::from_secs(10) {
            break false;
        }
        if s.write_all(b"s").await.is_err() {
            break true;
        }
    };
    assert!(closed, "a trickled header held the connection for 10 s");
    assert!(started.elapsed() < Duration::from_secs(5));
    // Everyone else is served as usual.
    let health = t.client.get(t.url("/healthz")).send().await.unwrap();
    assert_eq!(health.status(), 200);
    t.stop().await;
}

#[tokio::test]
async fn every_response_carries_the_security_headers_and_no_cors() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let r = t
        .upload(&k.owner, "a.ply", ply_bytes(&object_scene(50, 0, 1)))
        .await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let evil = "https://evil.example";
    let responses = [
        // JSON, a problem, a 404 of no route, the unauthenticated health check, a created key.
        t.client
            .get(t.url(&format!("/v1/assets/{id}")))
            .bearer_auth(&k.owner)
            .header("origin", evil)
            .send()
            .await
            .unwrap(),
        t.client
            .get(t.url("/v1/audit"))
            .header("origin", evil)
            .send()
            .await
            .unwrap(),
        t.get(&k.owner, "/no/such/route").await,
        t.client.get(t.url("/healthz")).send().await.unwrap(),
        t.client
            .post(t.url("/v1/keys"))
            .bearer_auth(&t.admin)
            .json(&serde_json::json!({"name": "v", "scopes": ["verifier"]}))
            .send()
            .await
            .unwrap(),
    ];
    let statuses: Vec<u16> = responses.iter().map(|r| r.status().as_u16()).collect();
    assert_eq!(statuses, [200, 401, 404, 200, 201]);
    for r in &responses {
        let h = r.headers();
        for &(name, value) in splatmark::http::SECURITY_HEADERS {
            assert_eq!(
                h.get(name).and_then(|v| v.to_str().ok()),
                Some(value),
                "{} {}: {name}",
                r.status(),
                r.url()
            );
        }
        assert!(
            h.get("access-control-allow-origin").is_none(),
            "{}",
            r.url()
        );
    }
    // A browser's CORS preflight is refused and allows nothing.
    let r = t
        .client
        .request(reqwest::Method::OPTIONS, t.url("/v1/verify"))
        .header("origin", evil)
        .header("access-control-request-method", "POST")
        .header("access-control-request-headers", "authorization")
        .send()
        .await
        .unwrap();
    assert!(!r.status().is_success(), "{}", r.status());
    assert!(r.headers().get("access-control-allow-origin").is_none());
    assert!(r.headers().get("access-control-allow-methods").is_none());
    // The scene file: the owner's client may keep it and revalidate by ETag, shared caches not.
    let f = t.get(&k.owner, &format!("/v1/assets/{id}/file")).await;
    assert_eq!(f.headers()["cache-control"], "private, no-cache");
    assert_eq!(f.headers()["x-content-type-options"], "nosniff");
    t.stop().await;
}

#[tokio::test]
async fn malformed_requests_get_problem_json_like_every_other_error() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    // A query string that does not parse, a multipart body without a boundary, a JSON body
    // that is not the schema, a method the route does not have: each is problem+json with
    // the reason, not axum's plain text.
    let r = t
        .client
        .get(t.url("/v1/audit?limit=lots"))
        .bearer_auth(&k.auditor)
        .send()
        .await
        .unwrap();
    let p = assert_problem(r, StatusCode::BAD_REQUEST).await;
    assert!(p["detail"].as_str().unwrap().contains("limit"), "{p}");
    let r = t
        .client
        .post(t.url("/v1/assets"))
        .bearer_auth(&k.owner)
        .header("content-type", "multipart/form-data")
        .body("--x\r\n")
        .send()
        .await
        .unwrap();
    assert!(r.status().is_client_error(), "{}", r.status());
    let status = r.status();
    assert_problem(r, status).await;
    let r = t
        .client
        .get(t.url("/v1/verify"))
        .bearer_auth(&k.verifier)
        .send()
        .await
        .unwrap();
    let allow = r.headers().get("allow").cloned();
    assert_problem(r, StatusCode::METHOD_NOT_ALLOWED).await;
    assert!(allow.is_some(), "405 keeps its Allow header");
    t.stop().await;
}

#[tokio::test]
async fn cameras_no_job_could_render_are_refused_at_upload() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let scene = ply_bytes(&object_scene(200, 0, 6));
    let identity = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]);
    let post = |w: u64, h: u64, frames: usize| {
        let frame = json!({"file_path": "a", "transform_matrix": identity});
        let doc = json!({"fl_x": 100.0, "w": w, "h": h, "frames": vec![frame; frames]});
        let form = Form::new()
            .part("scene", Part::bytes(scene.clone()).file_name("s.ply"))
            .part(
                "cameras",
                Part::bytes(serde_json::to_vec(&doc).unwrap()).file_name("transforms.json"),
            );
        t.client
            .post(t.url("/v1/assets"))
            .bearer_auth(&k.owner)
            .multipart(form)
            .send()
    };
    // 4·10⁹ pixels a view (the probe's job retried three times into the dead letter), and more
    // views than a job renders: 422 at upload, nothing stored.
    for (w, h, n, says) in [
        (65_536, 65_536, 1, "px a side"),
        (64, 64, 1_001, "at most 1000"),
    ] {
        let v = assert_problem(
            post(w, h, n).await.unwrap(),
            StatusCode::UNPROCESSABLE_ENTITY,
        )
        .await;
        assert!(v["detail"].as_str().unwrap().contains(says), "{v}");
    }
    assert_eq!(t.stored_blobs(), Vec::<String>::new());
    // The same file within the limits is an asset.
    assert_eq!(post(96, 72, 3).await.unwrap().status(), StatusCode::CREATED);
    t.stop().await;
}

#[tokio::test]
async fn verifications_and_bad_keys_are_rate_limited_with_retry_after() {
    let mut t = TestApp::start_with(|c| {
        c.verify_per_minute = 2;
        c.auth_failures_per_minute = 3;
    })
    .await;
    let k = t.keys().await;
    let png = {
        let mut v = vec![];
        image::DynamicImage::ImageRgb8(image::RgbImage::new(64, 64))
            .write_to(&mut std::io::Cursor::new(&mut v), image::ImageFormat::Png)
            .unwrap();
        v
    };
    let verify = |token: String| {
        let form = Form::new().part("image", Part::bytes(png.clone()).file_name("v.png"));
        t.client
            .post(t.url("/v1/verify"))
            .bearer_auth(token)
            .multipart(form)
            .send()
    };
    // Two verifications a minute per key: the third is 429 with Retry-After; another key is
    // not affected.
    for _ in 0..2 {
        let r = verify(k.verifier.clone()).await.unwrap();
        assert_ne!(r.status(), StatusCode::TOO_MANY_REQUESTS);
    }
    let r = verify(k.verifier.clone()).await.unwrap();
    let wait: u64 = r.headers()["retry-after"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!((1..=60).contains(&wait), "{wait}");
    assert_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    let r = verify(k.owner.clone()).await.unwrap();
    assert_ne!(r.status(), StatusCode::TOO_MANY_REQUESTS);

    // Three bad keys a minute per address: each a 401; then every request from the address
    // that needs a key is 429 — a right guess included, so guessing learns nothing — while
    // the unauthenticated health check still answers.
    for bad in ["smk_nope", "smk_nope2", "smk_nope3"] {
        let r = t.get(bad, "/v1/audit").await;
        assert_problem(r, StatusCode::UNAUTHORIZED).await;
    }
    let r = t.get("smk_nope4", "/v1/audit").await;
    assert!(r.headers().contains_key("retry-after"));
    assert_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    let r = t.get(&k.auditor, "/v1/audit").await;
    assert_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    let r = t.client.get(t.url("/healthz")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    t.stop().await;
}

/// A TCP relay the test can cut: every connection to `addr` is piped to `upstream` while it is
/// open; cutting it drops the live connections and refuses new ones.
struct Relay {
    addr: std::net::SocketAddr,
    open: std::sync::Arc<std::sync::atomic::AtomicBool>,
    pipes: std::sync::Arc<std::sync::Mutex<Vec<tokio::task::JoinHandle<()>>>>,
    accept: tokio::task::JoinHandle<()>,
}

impl Relay {
    async fn start(upstream: String) -> Self {
        use std::sync::atomic::Ordering;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let open = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let pipes = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let (o, p) = (open.clone(), pipes.clone());
        let accept = tokio::spawn(async move {
            while let Ok((mut down, _)) = listener.accept().await {
                if !o.load(Ordering::SeqCst) {
                    continue; // dropped: the connection is reset
                }
                let upstream = upstream.clone();
                p.lock().unwrap().push(tokio::spawn(async move {
                    if let Ok(mut up) = tokio::net::TcpStream::connect(&upstream).await {
                        let _ = tokio::io::copy_bidirectional(&mut down, &mut up).await;
                    }
                }));
            }
        });
        Relay {
            addr,
            open,
            pipes,
            accept,
        }
    }

    fn set_open(&self, open: bool) {
        self.open.store(open, std::sync::atomic::Ordering::SeqCst);
        if !open {
            for p in self.pipes.lock().unwrap().drain(..) {
                p.abort();
            }
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.set_open(false);
        self.accept.abort();
    }
}

#[tokio::test]
async fn readiness_fails_while_the_blob_store_does_not_answer_and_names_no_secret() {
    let Some(splatmark::store::BlobConfig::S3 { options, .. }) = common::test_blobs() else {
        eprintln!(
            "SKIPPED: readiness with an unreachable blob store needs an S3 server \
             (SPLATMARK_TEST_S3; scripts/test.sh starts one)"
        );
        return;
    };
    let endpoint = options
        .endpoint
        .clone()
        .expect("the test server's endpoint");
    let secret = options
        .secret_access_key
        .as_ref()
        .expect("the test server's secret")
        .expose()
        .to_owned();
    let upstream = endpoint.trim_start_matches("http://").to_owned();
    let relay = Relay::start(upstream).await;
    let mut t = TestApp::start_with(|c| {
        c.s3.endpoint = Some(format!("http://{}", relay.addr));
    })
    .await;
    let ready = |t: &TestApp| {
        let (client, url) = (t.client.clone(), t.url("/readyz"));
        async move {
            let r = client.get(url).send().await.unwrap();
            (r.status(), r.text().await.unwrap())
        }
    };
    assert_eq!(ready(&t).await.0, StatusCode::OK);

    relay.set_open(false);
    // The probe answers (its own limit is 5 s; a hang would be a failure, not a wait).
    let (status, body) = tokio::time::timeout(Duration::from_secs(120), ready(&t))
        .await
        .expect("/readyz answers while the blob store does not");
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert!(body.contains("blob store"), "{body}");
    assert!(!body.contains(&secret), "the secret in {body}");

    // Back: ready again (the client's retries reach the store once it answers).
    relay.set_open(true);
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (status, body) = ready(&t).await;
        if status == StatusCode::OK {
            break;
        }
        assert!(Instant::now() < deadline, "still not ready: {body}");
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    t.stop().await;
}
