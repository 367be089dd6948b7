//! No secret reaches a log line: a whole round trip (keys, upload, a watermarking job,
//! verification, audit) through the real service with every log line at DEBUG captured, then
//! searched for the master key, every API token, the message, the secret mask and the payload.
//! Its own test binary, because it installs the process-wide log subscriber.

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};
use splatmark::app::App;
use splatmark::config::{Config, DevicePolicy};
use splatmark::queue::JobOptions;
use splatmark::render::RenderOptions;
use splatmark::scene::orbit::orbit_cameras;
use splatmark::scene::synthetic::object_scene;
use splatmark::scene::write_ply;
use splatmark::store::{BlobConfig, MasterKey};
use splatmark::verify::eval::render_views;
use splatmark::verify::message::to_hex;

/// Every log line, as the service's text formatter writes them.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_secret_reaches_a_log_line_at_debug_level() {
    let logs = Captured::default();
    let sink = logs.clone();
    tracing_subscriber::fmt()
        .with_env_filter("debug")
        .with_ansi(false)
        .with_writer(move || sink.clone())
        .init();

    let dir = tempfile::tempdir().unwrap();
    let mut cfg = Config {
        bind: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.path().join("data"),
        workers: Some(1),
        device: DevicePolicy::Cpu,
        ..Config::default()
    };
    // With an S3 test server (SPLATMARK_TEST_S3), the blobs go there, and its secret key
    // joins the secrets searched for (the HTTP client's own debug lines included).
    let mut s3_secret = None;
    if let Some(server) = std::env::var("SPLATMARK_TEST_S3")
        .ok()
        .filter(|s| !s.is_empty())
    {
        let prefix = format!("t-{}", uuid::Uuid::new_v4().simple());
        let Ok(BlobConfig::S3 { url, options }) = BlobConfig::test_server(&server, &prefix, 4096)
        else {
            panic!("SPLATMARK_TEST_S3 is http://KEY:SECRET@HOST:PORT/BUCKET");
        };
        s3_secret = options
            .secret_access_key
            .as_ref()
            .map(|s| s.expose().to_string());
        cfg.blob_url = Some(url);
        cfg.s3 = options;
    }
    let master = MasterKey::generate();
    let master_hex = master.to_hex();
    let app = App::start(cfg.clone(), master, None).await.unwrap();
    let base = format!("http://{}", app.addr);
    let url = |p: &str| format!("{base}{p}");
    let client = reqwest::Client::new();
    let admin = std::fs::read_to_string(cfg.data_dir.join("admin.token"))
        .unwrap()
        .trim()
        .to_string();
    let mut tokens = vec![admin.clone()];
    let key = |scope: &'static str| {
        let r = client
            .post(url("/v1/keys"))
            .bearer_auth(&admin)
            .json(&json!({"name": scope, "scopes": [scope]}))
            .send();
        async move {
            let r = r.await.unwrap();
            assert_eq!(r.status(), StatusCode::CREATED);
            let v: Value = r.json().await.unwrap();
            v["token"].as_str().unwrap().to_string()
        }
    };
    let owner = key("owner").await;
    let verifier = key("verifier").await;
    let auditor = key("auditor").await;
    tokens.extend([owner.clone(), verifier.clone(), auditor.clone()]);

    // Upload and watermark a small object (a short job: the logs, not the watermark, are on
    // trial here).
    let scene = object_scene(600, 0, 5);
    let mut ply = vec![];
    write_ply(&scene, &mut ply).unwrap();
    let form = Form::new().part("scene", Part::bytes(ply).file_name("s.ply"));
    let r = client
        .post(url("/v1/assets"))
        .bearer_auth(&owner)
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::CREATED);
    let asset: Value = r.json().await.unwrap();
    let id = asset["id"].as_str().unwrap().to_string();
    let message = "5ec2e75a";
    let body = json!({
        "bits": 32,
        "message": message,
        "options": {
            "orbit": {"count": 4, "width": 64, "height": 64},
            "holdout_every": 0,
            "embed": {"finetune": {"steps": 6, "extra_steps": 0}},
        }
    });
    let r = client
        .post(url(&format!("/v1/assets/{id}/watermark")))
        .bearer_auth(&owner)
        .json(&body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let job: Value = r.json().await.unwrap();
    let job_id = job["id"].as_str().unwrap().to_string();
    let t0 = Instant::now();
    let job = loop {
        let j: Value = client
            .get(url(&format!("/v1/jobs/{job_id}")))
            .bearer_auth(&owner)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if j["state"] != "queued" && j["state"] != "running" {
            break j;
        }
        assert!(t0.elapsed() < Duration::from_secs(600), "{j}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(job["state"], "done", "{job}");
    let marked_id = job["result_asset_id"].as_str().unwrap().to_string();

    // A dispute: render the training views of the downloaded result and verify them; a bad
    // key, the audit log.
    let bytes = client
        .get(url(&format!("/v1/assets/{marked_id}/file")))
        .bearer_auth(&owner)
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let marked = splatmark::scene::read_scene_bytes(
        &bytes,
        Some("ply"),
        &splatmark::scene::Limits::default(),
    )
    .unwrap();
    let opts: JobOptions = serde_json::from_value(body["options"].clone()).unwrap();
    let spec = opts.resolve(&cfg, 32).unwrap();
    let views = orbit_cameras(&scene, &spec.orbit).unwrap();
    let imgs = render_views(&marked, &views, &RenderOptions::default()).unwrap();
    let mut form = Form::new().text("asset_id", marked_id.clone());
    for img in &imgs {
        let mut png = vec![];
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        form = form.part("image", Part::bytes(png).file_name("v.png"));
    }
    let r = client
        .post(url("/v1/verify"))
        .bearer_auth(&verifier)
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    // A guess that differs from the real token in its last character (whatever that is).
    let last = if owner.ends_with('0') { '1' } else { '0' };
    let wrong = format!("{}{last}", &owner[..owner.len() - 1]);
    let r = client
        .get(url("/v1/audit"))
        .bearer_auth(&wrong)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    let r = client
        .get(url("/v1/audit?limit=1000"))
        .bearer_auth(&auditor)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);

    let key = app
        .store
        .key_of(marked_id.parse().unwrap())
        .await
        .unwrap()
        .unwrap();
    let (mask, payload) = (to_hex(&key.mask), to_hex(&key.payload()));
    assert_eq!(to_hex(&key.message), message);
    app.stop().await.unwrap();

    let text = String::from_utf8(logs.0.lock().unwrap().clone()).unwrap();
    // The capture saw the round trip (so an empty log cannot pass) …
    for expected in ["job published", "splatmark listening"] {
        assert!(
            text.contains(expected),
            "no '{expected}' in the log:\n{text}"
        );
    }
    assert!(text.lines().count() > 20, "{text}");
    // … and none of the secrets, in either case.
    let mut secrets: Vec<(&str, String)> = vec![
        ("master key", master_hex),
        ("message", message.to_string()),
        ("mask", mask),
        ("payload", payload),
        ("wrong guess", wrong),
    ];
    secrets.extend(tokens.into_iter().map(|t| ("API token", t)));
    secrets.extend(s3_secret.map(|s| ("S3 secret access key", s)));
    // The token's secret part alone, too (a log that strips the prefix still leaks).
    let parts: Vec<(&str, String)> = secrets
        .iter()
        .filter_map(|(_, t)| {
            t.strip_prefix("smk_")
                .map(|h| ("token body", h.to_string()))
        })
        .collect();
    secrets.extend(parts);
    for (what, s) in &secrets {
        for form in [s.to_lowercase(), s.to_uppercase()] {
            if let Some(line) = text.lines().find(|l| l.contains(&form)) {
                panic!("the {what} appears in a log line: {line}");
            }
        }
    }
}
