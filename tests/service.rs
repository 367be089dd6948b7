//! The service end to end: each test starts the real server (`splatmark::app::App`) on
//! 127.0.0.1:0 with its own temporary database and blob folder, and talks HTTP to it.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

use splatmark::app::App;
use splatmark::config::Config;
use splatmark::embed::pipeline::split_views;
use splatmark::queue::{JobOptions, JobSpec};
use splatmark::render::RenderOptions;
use splatmark::scene::orbit::orbit_cameras;
use splatmark::scene::synthetic::object_scene;
use splatmark::scene::{Gaussians, Limits, read_scene_bytes, write_ply};
use splatmark::store::MasterKey;
use splatmark::verify::eval::render_views;
use splatmark::verify::message::parse_hex;

/// A running server with its own data folder and an HTTP client.
struct TestApp {
    app: Option<App>,
    base: String,
    client: reqwest::Client,
    dir: tempfile::TempDir,
    /// The bootstrap admin token (read from DATA_DIR/admin.token, as an operator would).
    admin: String,
}

struct Keys {
    owner: String,
    verifier: String,
    auditor: String,
}

fn config(dir: &Path) -> Config {
    Config {
        bind: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.join("data"),
        workers: Some(1),
        device: splatmark::config::DevicePolicy::Cpu,
        ..Config::default()
    }
}

impl TestApp {
    async fn start() -> Self {
        Self::start_with(|_| {}).await
    }

    async fn start_with(f: impl FnOnce(&mut Config)) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = config(dir.path());
        f(&mut cfg);
        let master = MasterKey::generate().to_hex();
        Self::boot(dir, cfg, master, None).await
    }

    async fn boot(
        dir: tempfile::TempDir,
        cfg: Config,
        master: String,
        workers: Option<Vec<splatmark::queue::WorkerSpec>>,
    ) -> Self {
        let app = App::start(cfg.clone(), MasterKey::from_hex(&master).unwrap(), workers)
            .await
            .expect("the server starts");
        let admin = std::fs::read_to_string(cfg.data_dir.join("admin.token"))
            .expect("the first start writes an admin token")
            .trim()
            .to_string();
        Self {
            base: format!("http://{}", app.addr),
            app: Some(app),
            client: reqwest::Client::new(),
            dir,
            admin,
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    async fn key(&self, scopes: &[&str]) -> String {
        let r = self
            .client
            .post(self.url("/v1/keys"))
            .bearer_auth(&self.admin)
            .json(&json!({"name": scopes.join("+"), "scopes": scopes}))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::CREATED);
        r.json::<Value>().await.unwrap()["token"]
            .as_str()
            .unwrap()
            .to_string()
    }

    async fn keys(&self) -> Keys {
        Keys {
            owner: self.key(&["owner"]).await,
            verifier: self.key(&["verifier"]).await,
            auditor: self.key(&["auditor"]).await,
        }
    }

    async fn upload(&self, token: &str, name: &str, bytes: Vec<u8>) -> reqwest::Response {
        let form = Form::new().part("scene", Part::bytes(bytes).file_name(name.to_string()));
        self.client
            .post(self.url("/v1/assets"))
            .bearer_auth(token)
            .multipart(form)
            .send()
            .await
            .unwrap()
    }

    async fn get(&self, token: &str, path: &str) -> reqwest::Response {
        self.client
            .get(self.url(path))
            .bearer_auth(token)
            .send()
            .await
            .unwrap()
    }

    async fn verify(&self, token: &str, images: &[image::RgbImage], asset: Option<&str>) -> Value {
        let mut form = Form::new();
        for img in images {
            let mut png = vec![];
            img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                .unwrap();
            form = form.part("image", Part::bytes(png).file_name("view.png"));
        }
        if let Some(a) = asset {
            form = form.text("asset_id", a.to_string());
        }
        let r = self
            .client
            .post(self.url("/v1/verify"))
            .bearer_auth(token)
            .multipart(form)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        r.json().await.unwrap()
    }

    /// The `/metrics` page.
    async fn metrics(&self) -> String {
        let r = self.client.get(self.url("/metrics")).send().await.unwrap();
        r.text().await.unwrap()
    }

    /// Polls a job until it leaves the queued/running states.
    async fn wait_job(&self, token: &str, id: &str, limit: Duration) -> Value {
        self.wait_job_until(token, id, limit, |j| {
            j["state"] != "queued" && j["state"] != "running"
        })
        .await
    }

    /// Polls a job until `done` holds for its JSON (panics after `limit`).
    async fn wait_job_until(
        &self,
        token: &str,
        id: &str,
        limit: Duration,
        done: impl Fn(&Value) -> bool,
    ) -> Value {
        let t0 = Instant::now();
        loop {
            let j: Value = self
                .get(token, &format!("/v1/jobs/{id}"))
                .await
                .json()
                .await
                .unwrap();
            if done(&j) {
                return j;
            }
            assert!(
                t0.elapsed() < limit,
                "job still {} after {limit:?}: {j}",
                j["state"]
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Uploads a small synthetic object and asks for a watermark job of `steps` steps on it;
    /// returns the asset and job ids.
    async fn small_object_job(&self, owner: &str, steps: usize) -> (String, String) {
        let a: Value = self
            .upload(owner, "s.ply", ply_bytes(&object_scene(600, 0, 5)))
            .await
            .json()
            .await
            .unwrap();
        let id = a["id"].as_str().unwrap().to_string();
        let r = self
            .client
            .post(self.url(&format!("/v1/assets/{id}/watermark")))
            .bearer_auth(owner)
            .json(&{
                // Exactly `steps` steps: these jobs are about the queue, not the watermark.
                let mut body = small_job("0badc0de", steps);
                body["options"]["embed"]["finetune"]["extra_steps"] = json!(0);
                body
            })
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::ACCEPTED);
        let job: Value = r.json().await.unwrap();
        (id, job["id"].as_str().unwrap().to_string())
    }

    fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    async fn stop(&mut self) {
        if let Some(a) = self.app.take() {
            a.stop().await.unwrap();
        }
    }
}

fn ply_bytes(g: &Gaussians) -> Vec<u8> {
    let mut v = vec![];
    write_ply(g, &mut v).unwrap();
    v
}

async fn assert_problem(r: reqwest::Response, status: StatusCode) -> Value {
    assert_eq!(r.status(), status);
    assert_eq!(
        r.headers()["content-type"].to_str().unwrap(),
        "application/problem+json"
    );
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["status"], status.as_u16());
    assert!(!v["detail"].as_str().unwrap().is_empty());
    v
}

/// Files under the blob folder other than in-flight temporaries.
fn stored_blobs(data: &Path) -> Vec<PathBuf> {
    fn walk(p: &Path, out: &mut Vec<PathBuf>) {
        if let Ok(rd) = std::fs::read_dir(p) {
            for e in rd.flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, out);
                } else {
                    out.push(p);
                }
            }
        }
    }
    let blobs = data.join("blobs");
    let mut out = vec![];
    walk(&blobs, &mut out);
    out.retain(|p| !p.starts_with(blobs.join("tmp")));
    out.sort();
    out
}

/// The job options of the toy round trips: a small orbit so CI can afford real embeddings, the
/// default recipe without its fidelity bound (`target_psnr` 0) and at ×5 learning rate, so that
/// the 1 500-Gaussian toy scene reliably carries a random payload to its training views, and up
/// to 300 extra steps until those views decode every bit. How well the default recipe embeds at
/// the paper's fidelity is the donut test's business (views the job never saw, bound 38 dB).
fn small_job(message: &str, steps: usize) -> Value {
    json!({
        "bits": 32,
        "message": message,
        "options": {
            "orbit": {"count": 8, "width": 128, "height": 128},
            "holdout_every": 0,
            "embed": {"finetune": {"steps": steps, "extra_steps": 300, "coupled": true, "wm_lr_scale": 5.0, "views_per_step": 4, "target_psnr": 0.0}},
        }
    })
}

/// The views the job trained on, as a disputer who knows them would render them.
fn training_views(g: &Gaussians, spec: &JobSpec) -> Vec<splatmark::scene::Camera> {
    let cams = orbit_cameras(g, &spec.orbit).unwrap();
    split_views(&cams, spec.holdout_every).0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_watermark_download_render_verify_round_trip() {
    // A false-positive rate of 1e-3 (threshold 26 of 32 matching bits) instead of the default
    // 1e-6 (30 of 32): this 1 500-Gaussian toy scene does not carry every random 32-bit payload
    // (with the CNN decoder shipped before December 2026, in eight runs it stopped at 28–29
    // bits four times, even with the 300 extra steps); how well the pipeline embeds is measured
    // on real scenes (the donut test below, on views the job never saw, and docs/RESULTS.md).
    // This test is about the service around the pipeline.
    let mut t = TestApp::start_with(|c| c.fpr = 1e-3).await;
    let k = t.keys().await;
    let original = object_scene(1500, 1, 4);
    let r = t.upload(&k.owner, "object.ply", ply_bytes(&original)).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let asset: Value = r.json().await.unwrap();
    assert_eq!(asset["gaussians"], 1500);
    assert_eq!(asset["sh_degree"], 1);
    assert_eq!(asset["format"], "ply");
    let id = asset["id"].as_str().unwrap().to_string();

    // The owner registers as message what the decoder already reads in the *unmarked* scene's
    // renders — what a dishonest owner would pick to "detect" a watermark in images that carry
    // none. The secret mask makes that useless (checked at the end).
    let opts: JobOptions =
        serde_json::from_value(small_job("00000000", 300)["options"].clone()).unwrap();
    let spec = opts.resolve(&config(t.dir.path())).unwrap();
    let views = training_views(&original, &spec);
    let ro = RenderOptions {
        background: spec.embed.finetune.background,
        ..RenderOptions::default()
    };
    let plain = render_views(&original, &views, &ro).unwrap();
    let before = t.verify(&k.verifier, &plain, None).await;
    assert_eq!(before["candidates_tested"], 0, "{before}");
    let message = before["decoded"]["32"].as_str().unwrap().to_string();
    let message = message.as_str();
    let r = t
        .client
        .post(t.url(&format!("/v1/assets/{id}/watermark")))
        .bearer_auth(&k.owner)
        .header("Idempotency-Key", "round-trip-1")
        .json(&small_job(message, 300))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let job: Value = r.json().await.unwrap();
    let job_id = job["id"].as_str().unwrap().to_string();
    let job = t
        .wait_job(&k.owner, &job_id, Duration::from_secs(900))
        .await;
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["step"], job["total"]);
    let marked_id = job["result_asset_id"].as_str().unwrap().to_string();

    // Download: a PLY with the reported count.
    let r = t
        .get(&k.owner, &format!("/v1/assets/{marked_id}/file"))
        .await;
    assert_eq!(r.status(), StatusCode::OK);
    let bytes = r.bytes().await.unwrap();
    let marked = read_scene_bytes(&bytes, Some("ply"), &Limits::default()).unwrap();
    let meta: Value = t
        .get(&k.owner, &format!("/v1/assets/{marked_id}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(meta["gaussians"].as_u64().unwrap() as usize, marked.len());
    assert_eq!(meta["kind"], "watermarked");
    assert_eq!(meta["parent_id"].as_str().unwrap(), id);

    // Render what the job trained on and verify against the asset, then against everything.
    let stored: JobSpec = serde_json::from_value(job["options"].clone()).unwrap();
    assert_eq!(training_views(&original, &stored), views);
    let imgs = render_views(&marked, &views, &ro).unwrap();
    let v = t.verify(&k.verifier, &imgs, Some(&marked_id)).await;
    assert_eq!(v["detected"], true, "{v}\nreport: {}", meta["report"]);
    assert_eq!(v["fpr"], 1e-3);
    assert_eq!(v["best"]["asset_id"].as_str().unwrap(), marked_id);
    assert_eq!(v["candidates_tested"], 1);
    // What the scene carries is the payload (message ⊕ the job's secret mask), not the message:
    // the decoded bits agree with the message only as a random string would (≥ 30 of 32 with a
    // uniformly random mask: probability about 1e-7).
    let decoded = parse_hex(v["decoded"]["32"].as_str().unwrap(), 32).unwrap();
    let raw = parse_hex(message, 32).unwrap();
    let agree = decoded.iter().zip(&raw).filter(|(a, b)| a == b).count();
    assert!(agree < 30, "decoded {} vs message {message}", v["decoded"]);
    // The job checked how its training views decode before publishing, as the dispute below
    // decodes them.
    let check = &meta["report"]["views_check"];
    assert_eq!(check["bits"], 32, "{meta}");
    assert!(
        check["matches"].as_u64() >= v["best"]["threshold"].as_u64(),
        "{meta}"
    );
    // Neither the message nor the embedded bits are shown with the asset (its stored report).
    assert!(meta["report"]["carriers"].as_u64().unwrap() > 0, "{meta}");
    assert!(meta["report"].get("message_hex").is_none(), "{meta}");
    let shown = meta.to_string();
    let payload = v["decoded"]["32"].as_str().unwrap();
    assert!(
        !shown.contains(message) && !shown.contains(payload),
        "{shown}"
    );
    let by_original = t.verify(&k.verifier, &imgs, Some(&id)).await;
    assert_eq!(by_original["detected"], true, "{by_original}");
    let any = t.verify(&k.verifier, &imgs, None).await;
    assert_eq!(any["detected"], true, "{any}");
    // The unmarked scene's renders are not detected, although they decode to the message.
    let v0 = t.verify(&k.verifier, &plain, Some(&marked_id)).await;
    assert_eq!(v0["decoded"]["32"], message, "{v0}");
    assert_eq!(v0["detected"], false, "{v0}");

    // Attribution: one record per Gaussian, carriers as the summary says.
    let sum: Value = t
        .get(
            &k.owner,
            &format!("/v1/assets/{marked_id}/attribution/summary"),
        )
        .await
        .json()
        .await
        .unwrap();
    let mut seen = 0;
    let mut carriers = 0;
    let mut cursor: Option<u64> = None;
    loop {
        let q = match cursor {
            Some(c) => format!("/v1/assets/{marked_id}/attribution?limit=500&cursor={c}"),
            None => format!("/v1/assets/{marked_id}/attribution?limit=500"),
        };
        let page: Value = t.get(&k.auditor, &q).await.json().await.unwrap();
        for r in page["items"].as_array().unwrap() {
            seen += 1;
            carriers += usize::from(r["role"] == "carrier");
        }
        match page["next_cursor"].as_u64() {
            Some(c) => cursor = Some(c),
            None => break,
        }
    }
    assert_eq!(seen, marked.len());
    assert!(carriers > 0);
    assert!(sum.to_string().contains(&carriers.to_string()), "{sum}");

    // The audit log holds every step and its chain verifies.
    let audit: Value = t
        .get(&k.auditor, &format!("/v1/audit?asset_id={id}&limit=1000"))
        .await
        .json()
        .await
        .unwrap();
    let actions: Vec<&str> = audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["action"].as_str().unwrap())
        .collect();
    for a in ["asset.upload", "job.enqueue", "watermark.publish", "verify"] {
        assert!(actions.contains(&a), "{a} missing from {actions:?}");
    }
    let chain: Value = t
        .get(&k.auditor, "/v1/audit/verify")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(chain["ok"], true, "{chain}");
    t.stop().await;
}

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
    assert!(
        stored_blobs(&t.data()).is_empty(),
        "{:?}",
        stored_blobs(&t.data())
    );
    let audit: Value = t
        .get(&k.auditor, "/v1/audit?action=asset.upload")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(audit["items"].as_array().unwrap().len(), 0);
    // …and a good upload still works.
    let r = t.upload(&k.owner, "ok.ply", good).await;
    assert_eq!(r.status(), StatusCode::CREATED);
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_result_is_published_once_when_a_worker_dies_mid_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(dir.path());
    cfg.lease_seconds = 3;
    let master = MasterKey::generate().to_hex();
    // First life: no workers; a worker that will "die" claims the job directly.
    let mut t = TestApp::boot(dir, cfg.clone(), master.clone(), Some(vec![])).await;
    let k = t.keys().await;
    let (id, job_id) = t.small_object_job(&k.owner, 3).await;
    let store = t.app.as_ref().unwrap().store.clone();
    let dead = store
        .claim("doomed", Duration::from_secs(3))
        .await
        .unwrap()
        .expect("the queued job");
    assert_eq!(dead.job.id.to_string(), job_id);
    t.stop().await;
    drop(store);

    // Second life with a real worker: the expired lease is re-queued and the job completes.
    let dir = t.dir;
    let t = TestApp::boot(dir, cfg, master, None).await;
    let done = t
        .wait_job(&k.owner, &job_id, Duration::from_secs(600))
        .await;
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["attempts"], 2);
    // The dead worker wakes up and tries to publish: refused, nothing duplicated.
    let store = t.app.as_ref().unwrap().store.clone();
    let asset = store.get_asset(dead.job.asset_id).await.unwrap().unwrap();
    let late = store
        .publish_result(
            dead.job.id,
            dead.lease_token,
            splatmark::store::NewAsset {
                owner: dead.job.owner.clone(),
                kind: splatmark::store::AssetKind::Watermarked,
                parent_id: Some(asset.id),
                source_job_id: Some(dead.job.id),
                blob: store.blobs().put_bytes(b"not a scene").unwrap(),
                format: "ply".into(),
                file_name: None,
                gaussians: 1,
                sh_degree: 0,
                cameras_blob: None,
                cameras_format: None,
            },
            &dead.key,
            None,
            None,
            &[],
            json!({}),
            splatmark::store::AuditEntry {
                actor: "worker:doomed".into(),
                action: "watermark.publish".into(),
                asset_id: Some(asset.id),
                job_id: Some(dead.job.id),
                details: json!({}),
            },
        )
        .await;
    assert!(
        matches!(late, Err(splatmark::store::StoreError::LeaseLost)),
        "{late:?}"
    );
    let versions = store.watermarked_of(asset.id).await.unwrap();
    assert_eq!(versions.len(), 1, "exactly one published result");
    let audit: Value = t
        .get(
            &t.key(&["auditor"]).await,
            &format!("/v1/audit?asset_id={id}&action=watermark.publish"),
        )
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(audit["items"].as_array().unwrap().len(), 1);
}

#[tokio::test]
async fn a_job_running_at_shutdown_goes_back_to_the_queue_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(dir.path());
    cfg.lease_seconds = 600; // far beyond the test: only the release can re-queue it
    let master = MasterKey::generate().to_hex();
    let mut t = TestApp::boot(dir, cfg.clone(), master.clone(), None).await;
    let k = t.keys().await;
    let (_, job_id) = t.small_object_job(&k.owner, 100_000).await;
    // Wait until the worker is inside the finetuning loop.
    let j = t
        .wait_job_until(&k.owner, &job_id, Duration::from_secs(300), |j| {
            j["state"] == "running" && j["phase"] == "finetune" && j["step"].as_u64() > Some(0)
        })
        .await;
    assert_eq!(j["attempts"], 1, "{j}");
    let store = t.app.as_ref().unwrap().store.clone();
    let stopped = Instant::now();
    t.stop().await;
    assert!(
        stopped.elapsed() < Duration::from_secs(60),
        "shutdown waited"
    );
    let j = store
        .get_job(job_id.parse().unwrap())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(j.state, splatmark::store::JobState::Queued, "{j:?}");
    assert_eq!(j.attempts, 0, "a shutdown is not a failed attempt");
    let (released, _) = store
        .audit_query(&splatmark::store::AuditFilter {
            asset_id: Some(j.asset_id),
            action: Some("job.release".into()),
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(released.len(), 1);
    assert_eq!(released[0].job_id, Some(j.id));
    drop(store);

    // The next start picks it up at once (attempt 1 again).
    let mut t = TestApp::boot(t.dir, cfg, master, None).await;
    let j = t
        .wait_job_until(&k.owner, &job_id, Duration::from_secs(60), |j| {
            j["state"] == "running"
        })
        .await;
    assert_eq!(j["attempts"], 1, "{j}");
    let r = t
        .client
        .delete(t.url(&format!("/v1/jobs/{job_id}")))
        .bearer_auth(&k.owner)
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    // Stopping cancels the running embedding (a test runtime that just ended would wait for it).
    let store = t.app.as_ref().unwrap().store.clone();
    t.stop().await;
    let j = store
        .get_job(job_id.parse().unwrap())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(j.state, splatmark::store::JobState::Cancelled);
}

/// The shared data folder, when present (CI has it).
fn shared_scene(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/scenes")
        .join(rel);
    if p.is_file() {
        Some(p)
    } else {
        eprintln!(
            "SKIPPED: {} is missing (../shared/data is not beside the checkout)",
            p.display()
        );
        None
    }
}

/// PSNR (dB) of two 8-bit images of one size.
fn psnr(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let se: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum();
    let mse = se / a.as_raw().len() as f64 / 255.0 / 255.0;
    -10.0 * mse.max(1e-12).log10()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_scene_is_detected_on_views_the_job_never_saw() {
    let Some(path) = shared_scene("donut/fused.ply") else {
        return;
    };
    // The service's default false-positive rate, 1e-6 (30 of 32 bits): every run embeds a
    // fresh random payload (the key's mask); read through the asset's matched head the held-out
    // views of such a job decode 87.5 % of the bits one by one at 128² (`bench quality
    // --quick`, docs/RESULTS.md), 8 of them averaged leave a few bits of slack.
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    let bytes = std::fs::read(&path).unwrap();
    let original = read_scene_bytes(&bytes, Some("ply"), &Limits::default()).unwrap();
    let r = t.upload(&k.owner, "fused.ply", bytes).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    // The default embedding (no "embed" options) on 16 orbit views at 128², every second one
    // held out of training: the dispute renders only those held-out views
    // (docs/RESULTS.md, "service round trip").
    let body = json!({
        "bits": 32,
        "message": "c0ffee42",
        "options": {"orbit": {"count": 16, "width": 128, "height": 128}, "holdout_every": 2},
    });
    let job: Value = t
        .client
        .post(t.url(&format!("/v1/assets/{id}/watermark")))
        .bearer_auth(&k.owner)
        .json(&body)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let job = t
        .wait_job(
            &k.owner,
            job["id"].as_str().unwrap(),
            Duration::from_secs(1800),
        )
        .await;
    assert_eq!(job["state"], "done", "{job}");
    let marked_id = job["result_asset_id"].as_str().unwrap().to_string();
    let bytes = t
        .get(&k.owner, &format!("/v1/assets/{marked_id}/file"))
        .await
        .bytes()
        .await
        .unwrap();
    let marked = read_scene_bytes(&bytes, Some("ply"), &Limits::default()).unwrap();
    let spec: JobSpec = serde_json::from_value(job["options"].clone()).unwrap();
    assert!(
        spec.embed.reference && spec.embed.finetune.coupled && spec.embed.projection.matched,
        "{spec:?}"
    );
    let cams = orbit_cameras(&original, &spec.orbit).unwrap();
    let (train, unseen) = split_views(&cams, spec.holdout_every);
    assert_eq!((train.len(), unseen.len()), (8, 8));
    let ro = RenderOptions {
        background: spec.embed.finetune.background,
        ..RenderOptions::default()
    };
    let marked_views = render_views(&marked, &unseen, &ro).unwrap();
    let original_views = render_views(&original, &unseen, &ro).unwrap();
    let psnrs: Vec<f64> = marked_views
        .iter()
        .zip(&original_views)
        .map(|(a, b)| psnr(a, b))
        .collect();
    let mean = psnrs.iter().sum::<f64>() / psnrs.len() as f64;
    let worst = psnrs.iter().copied().fold(f64::INFINITY, f64::min);
    // The bound holds the training views at 38 dB; unseen views measured 36.4 dB at worst.
    assert!(mean >= 37.0, "unseen views at {mean:.1} dB on average");
    let v = t.verify(&k.verifier, &marked_views, None).await;
    eprintln!(
        "donut, unseen views ({mean:.1} dB on average, {worst:.1} at worst): {}",
        v["best"]
    );
    assert_eq!(v["detected"], true, "{v}");
    assert_eq!(v["best"]["asset_id"].as_str().unwrap(), marked_id);
    assert_eq!(v["best"]["reference"], true);
    assert_eq!(v["best"]["matched_head"], true);
    let v0 = t.verify(&k.verifier, &original_views, None).await;
    assert_eq!(v0["detected"], false, "{v0}");
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
    assert_eq!(stored_blobs(&t.data()), Vec::<PathBuf>::new());
    let r = post(serde_json::to_vec(&cams).unwrap()).await.unwrap();
    assert_eq!(r.status(), StatusCode::CREATED);
    let a: Value = r.json().await.unwrap();
    assert_eq!(a["cameras_format"], "inria");
    assert_eq!(a["cameras_sha256"].as_str().unwrap().len(), 64);
    t.stop().await;
}

/// `n` Gaussians as a SuperSplat compressed PLY (one chunk of bounds, packed words from a fixed
/// generator: every 32-bit pattern decodes to a valid Gaussian).
fn compressed_ply_bytes(n: usize) -> Vec<u8> {
    assert!((1..=256).contains(&n));
    let mut h = String::from("ply\nformat binary_little_endian 1.0\nelement chunk 1\n");
    for p in [
        "min_x",
        "min_y",
        "min_z",
        "max_x",
        "max_y",
        "max_z",
        "min_scale_x",
        "min_scale_y",
        "min_scale_z",
        "max_scale_x",
        "max_scale_y",
        "max_scale_z",
    ] {
        h += &format!("property float {p}\n");
    }
    h += &format!("element vertex {n}\n");
    for p in [
        "packed_position",
        "packed_rotation",
        "packed_scale",
        "packed_color",
    ] {
        h += &format!("property uint {p}\n");
    }
    h += "end_header\n";
    let mut out = h.into_bytes();
    for v in [
        -1.0f32, -1.0, -1.0, 1.0, 1.0, 1.0, -5.0, -5.0, -5.0, -3.0, -3.0, -3.0,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let mut rng = splatmark::scene::synthetic::Rng::new(7);
    for _ in 0..n * 4 {
        out.extend_from_slice(&(rng.next_u64() as u32).to_le_bytes());
    }
    out
}

/// `n` Gaussians as an antimatter15 `.splat`.
fn splat_bytes(n: usize) -> Vec<u8> {
    let mut rng = splatmark::scene::synthetic::Rng::new(8);
    let mut out = vec![];
    for _ in 0..n {
        for _ in 0..3 {
            out.extend_from_slice(&rng.range(-1.0, 1.0).to_le_bytes());
        }
        for _ in 0..3 {
            out.extend_from_slice(&rng.range(0.01, 0.05).to_le_bytes());
        }
        out.extend_from_slice(&[200, 100, 50, 180, 255, 128, 128, 128]);
    }
    out
}

/// `n` Gaussians as a Niantic `.spz` (version 2, gzip).
fn spz_bytes(n: usize) -> Vec<u8> {
    use std::io::Write;
    let mut rng = splatmark::scene::synthetic::Rng::new(9);
    let mut raw = b"NGSP".to_vec();
    raw.extend_from_slice(&2u32.to_le_bytes());
    raw.extend_from_slice(&(n as u32).to_le_bytes());
    raw.extend_from_slice(&[0, 12, 0, 0]);
    // positions (9), alphas (1), colours (3), scales (3), rotations (3) bytes per point.
    for per_point in [9, 1, 3, 3, 3] {
        raw.extend((0..n * per_point).map(|_| rng.next_u64() as u8));
    }
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(&raw).unwrap();
    e.finish().unwrap()
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
    let audit: Value = t
        .get(&k.auditor, "/v1/audit?action=asset.upload")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(audit["items"].as_array().unwrap().len(), 4);
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
    let before = stored_blobs(&t.data());
    assert_eq!(before.len(), 1, "{before:?}");

    // The database refuses every new asset row (as a full disk or a broken file would).
    let db = sqlx::sqlite::SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(
            sqlx::sqlite::SqliteConnectOptions::new()
                .filename(t.data().join("splatmark.db"))
                .busy_timeout(Duration::from_secs(5)),
        )
        .await
        .unwrap();
    sqlx::query(
        "CREATE TRIGGER refuse_assets BEFORE INSERT ON assets \
         BEGIN SELECT RAISE(ABORT, 'refused by the test'); END",
    )
    .execute(&db)
    .await
    .unwrap();

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
    assert_eq!(stored_blobs(&t.data()), before);

    sqlx::query("DROP TRIGGER refuse_assets")
        .execute(&db)
        .await
        .unwrap();
    db.close().await;
    let f = t.get(&k.owner, &format!("/v1/assets/{kept_id}/file")).await;
    assert_eq!(f.status(), StatusCode::OK);
    assert!(f.bytes().await.unwrap() == kept);
    let audit: Value = t
        .get(&k.auditor, "/v1/audit?action=asset.upload")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(audit["items"].as_array().unwrap().len(), 1);
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
    assert_eq!(stored_blobs(&t.data()), Vec::<PathBuf>::new());
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

/// The count of one status class in `/metrics`.
async fn responses_of_class(t: &TestApp, class: &str) -> u64 {
    let m = t.metrics().await;
    let key = format!("splatmark_http_responses_total{{class=\"{class}\"}} ");
    m.lines()
        .find_map(|l| l.strip_prefix(&key))
        .map_or(0, |v| v.trim().parse::<f64>().unwrap() as u64)
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
    assert!(stored_blobs(&t.data()).is_empty());
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
    assert_eq!(stored_blobs(&t.data()), Vec::<PathBuf>::new());
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_of_a_live_server_mid_job_restores_whole() {
    use splatmark::store::backup::{backup, restore};
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let master = MasterKey::generate().to_hex();
    let mut t = TestApp::boot(dir, cfg.clone(), master.clone(), None).await;
    let k = t.keys().await;
    // A finished watermark (so a key is registered) and a job that is running at backup time.
    let (asset_id, done_job) = t.small_object_job(&k.owner, 3).await;
    let done = t
        .wait_job(&k.owner, &done_job, Duration::from_secs(300))
        .await;
    assert_eq!(done["state"], "done", "{done}");
    let marked_id: uuid::Uuid = done["result_asset_id"].as_str().unwrap().parse().unwrap();
    let (_, running) = t.small_object_job(&k.owner, 100_000).await;
    t.wait_job_until(&k.owner, &running, Duration::from_secs(300), |j| {
        j["state"] == "running" && j["step"].as_u64() > Some(0)
    })
    .await;
    let out = t.dir.path().join("backup");
    let step = |j: &Value| j["step"].as_u64().unwrap_or(0);
    let before: Value = t
        .get(&k.owner, &format!("/v1/jobs/{running}"))
        .await
        .json()
        .await
        .unwrap();
    let m = backup(&t.data(), &out).await.unwrap();
    // The service kept working meanwhile: the running job advances past where it was.
    t.wait_job_until(&k.owner, &running, Duration::from_secs(120), |j| {
        step(j) > step(&before)
    })
    .await;
    t.stop().await;
    // Two uploads of the same bytes and the watermarked result: 3 assets, 2 blobs.
    assert!(m.assets >= 3 && m.blobs.len() >= 2, "{m:?}");
    // A second backup into the same folder is refused.
    assert!(backup(&t.data(), &out).await.is_err());

    // Restore into a fresh folder: every asset and its blob, the keys (same master key), the
    // audit chain up to the snapshot.
    let fresh = tempfile::tempdir().unwrap();
    let restored_dir = fresh.path().join("data");
    restore(&out, &restored_dir).await.unwrap();
    let s = splatmark::store::Store::open(&restored_dir, MasterKey::from_hex(&master).unwrap())
        .await
        .unwrap();
    assert_eq!(s.integrity_check().await.unwrap(), "ok");
    let chain = s.verify_audit_chain().await.unwrap();
    assert!(chain.ok);
    assert_eq!(chain.rows, m.audit_rows);
    assert_eq!(chain.head_hash, m.audit_head);
    let original = s
        .get_asset(asset_id.parse().unwrap())
        .await
        .unwrap()
        .unwrap();
    let bytes = s.blobs().read(&original.sha256).unwrap();
    let digest = <sha2::Sha256 as sha2::Digest>::digest(&bytes);
    assert_eq!(hex::encode(digest), original.sha256);
    let key = s
        .key_of(marked_id)
        .await
        .unwrap()
        .expect("the key came back");
    assert_eq!(splatmark::verify::message::to_hex(&key.message), "0badc0de");
    s.close().await;
    // Restoring over a database is refused; so is a damaged backup, which leaves nothing.
    assert!(restore(&out, &restored_dir).await.is_err());
    let blob = &m.blobs[0].sha256;
    let f = out.join("blobs").join(&blob[..2]).join(&blob[2..]);
    std::fs::write(&f, flip_first_bit(&f)).unwrap();
    let other = fresh.path().join("other");
    let e = restore(&out, &other).await.unwrap_err();
    assert!(e.to_string().contains("damaged"), "{e}");
    assert!(!other.join("splatmark.db").exists());
    // Under another master key the restored keys do not open: the store refuses to start.
    let third = fresh.path().join("third");
    std::fs::write(&f, flip_first_bit(&f)).unwrap();
    restore(&out, &third).await.unwrap();
    assert!(
        splatmark::store::Store::open(&third, MasterKey::generate())
            .await
            .is_err()
    );
}

/// The bytes of the file at `f` with bit 0 of its first byte flipped.
fn flip_first_bit(f: &Path) -> Vec<u8> {
    let mut b = std::fs::read(f).unwrap();
    b[0] ^= 1;
    b
}

/// Resident memory of this process (the server runs in it), in bytes.
fn rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: u64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(raw).unwrap();
    e.finish().unwrap()
}

/// Crafted scene files, each wrong in its own way (named for what is wrong).
fn hostile_scenes() -> Vec<(&'static str, Vec<u8>)> {
    let good = ply_bytes(&object_scene(50, 0, 1));
    let props = "property float x\nproperty float y\nproperty float z\nproperty float f_dc_0\n\
                 property float f_dc_1\nproperty float f_dc_2\nproperty float opacity\n\
                 property float scale_0\nproperty float scale_1\nproperty float scale_2\n\
                 property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n";
    let ascii = |rows: &[&str]| -> Vec<u8> {
        format!(
            "ply\nformat ascii 1.0\nelement vertex {}\n{props}end_header\n{}\n",
            rows.len(),
            rows.join("\n")
        )
        .into_bytes()
    };
    let row = "0 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0";
    let header = |h: &str| h.as_bytes().to_vec();
    let mut truncated = good.clone();
    truncated.truncate(good.len() - 7);
    let mut polyglot = good.clone();
    polyglot.extend_from_slice(b"PK\x03\x04\x14\x00\x00\x00 a zip archive riding along");
    let mut png = vec![];
    image::RgbImage::new(8, 8)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let mut png_tail = good.clone();
    png_tail.extend_from_slice(&png);
    let spz_header = |magic: &[u8], version: u32, n: u32| {
        let mut raw = magic.to_vec();
        raw.extend_from_slice(&version.to_le_bytes());
        raw.extend_from_slice(&n.to_le_bytes());
        raw.extend_from_slice(&[0, 12, 0, 0]);
        raw
    };
    let mut bad_crc = spz_bytes(100);
    let at = bad_crc.len() - 8;
    bad_crc[at] ^= 0x40;
    let mut spz_bomb = spz_header(b"NGSP", 2, 200_000);
    spz_bomb.resize(spz_bomb.len() + 200_000 * 19, 0);
    let mut short_spz = spz_header(b"NGSP", 2, 1000);
    short_spz.extend_from_slice(&[7; 100]);
    let mut nan_splat = vec![];
    for _ in 0..3 {
        nan_splat.extend_from_slice(&f32::NAN.to_le_bytes());
    }
    nan_splat.extend_from_slice(&[0u8; 20]);
    vec![
        ("empty.ply", vec![]),
        ("magic_only.ply", header("ply\n")),
        (
            "wrong_magic.ply",
            header("plx\nformat ascii 1.0\nend_header\n"),
        ),
        (
            "no_end_header.ply",
            header("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"),
        ),
        (
            "lying_count.ply",
            header(
                "ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\nend_header\n",
            ),
        ),
        (
            "negative_count.ply",
            header("ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nend_header\n"),
        ),
        ("truncated.ply", truncated),
        (
            "duplicate_property.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 2\n",
            ),
        ),
        (
            "list_property.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n1 2\n",
            ),
        ),
        (
            "duplicate_element.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement vertex 1\nproperty float x\nend_header\n1\n2\n",
            ),
        ),
        (
            "nan_position.ply",
            ascii(&["nan 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0"]),
        ),
        (
            "inf_opacity.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 inf -3 -3 -3 1 0 0 0"]),
        ),
        (
            "overflowing_scale.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 0.5 100 -3 -3 1 0 0 0"]),
        ),
        (
            "zero_quaternion.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 0 0 0 0"]),
        ),
        ("too_few_values.ply", ascii(&["0 0 0 0.1"])),
        (
            "trailing_values.ply",
            [ascii(&[row]), b"9 9 9\n".to_vec()].concat(),
        ),
        (
            "banana.ply",
            ascii(&["0 0 banana 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0"]),
        ),
        (
            "version_2.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("ascii 1.0", "ascii 2.0", 1)
                .into_bytes(),
        ),
        (
            "unknown_format.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("ascii 1.0", "binary_middle_endian 1.0", 1)
                .into_bytes(),
        ),
        (
            "unknown_type.ply",
            header("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n1\n"),
        ),
        (
            "missing_opacity.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("property float opacity\n", "", 1)
                .into_bytes(),
        ),
        (
            "no_format.ply",
            header("ply\nelement vertex 1\nproperty float x\nend_header\n1\n"),
        ),
        (
            "binary_header.ply",
            b"ply\n\xff\xfe\xfd\x00\x01format\nend_header\n".to_vec(),
        ),
        ("polyglot_zip.ply", polyglot),
        ("png_tail.ply", png_tail),
        ("picture.ply", png),
        (
            "zip.ply",
            b"PK\x03\x04\x14\x00\x00\x00\x08\x00 not a scene at all".to_vec(),
        ),
        ("bad_length.splat", vec![1; 33]),
        ("nan.splat", nan_splat),
        (
            "garbage.spz",
            [&[0x1f, 0x8b, 8, 0][..], &[0xAB; 64][..]].concat(),
        ),
        ("bad_crc.spz", bad_crc),
        ("bomb.spz", gzip(&spz_bomb)),
        ("wrong_magic.spz", gzip(&spz_header(b"XXXX", 2, 1))),
        ("version_99.spz", gzip(&spz_header(b"NGSP", 99, 1))),
        ("short.spz", gzip(&short_spz)),
        (
            "zstd_garbage.spz",
            [&[0x28, 0xb5, 0x2f, 0xfd][..], &[0x55; 64][..]].concat(),
        ),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hostile_corpus_gets_4xx_problems_stores_nothing_and_keeps_memory_flat() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    // Warm up (decoders, allocator arenas) with one good upload and one verification.
    let r = t
        .upload(&k.owner, "ok.ply", ply_bytes(&object_scene(300, 0, 1)))
        .await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let kept = stored_blobs(&t.data());
    let good_view = image::RgbImage::from_pixel(64, 64, image::Rgb([90, 120, 200]));
    t.verify(&k.verifier, &[good_view], None).await;
    let before_rss = rss_bytes();
    let before_5xx = responses_of_class(&t, "5xx").await;

    let scenes = hostile_scenes();
    assert!(scenes.len() >= 30, "{}", scenes.len());
    for (name, bytes) in scenes {
        let r = t.upload(&k.owner, name, bytes).await;
        let status = r.status();
        assert!(status.is_client_error(), "{name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("{name}: {status} {}", p["detail"]);
    }
    // Cameras that lie, next to a good scene.
    let scene = ply_bytes(&object_scene(50, 0, 1));
    let identity = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]);
    let nan_matrix = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]])
        .to_string()
        .replacen("4", "1e999", 1);
    let cameras: Vec<(&str, Vec<u8>)> = vec![
        ("transforms.json", b"{not json".to_vec()),
        ("transforms.json", br#"{"fl_x": 100, "w": 64, "h": 64, "frames": []}"#.to_vec()),
        (
            "transforms.json",
            format!(r#"{{"fl_x": 100, "w": 64, "h": 64, "frames": [{{"file_path": "a", "transform_matrix": {nan_matrix}}}]}}"#)
                .into_bytes(),
        ),
        (
            "transforms.json",
            json!({"fl_x": -5, "w": 64, "h": 64, "frames": [{"file_path": "a", "transform_matrix": identity}]})
                .to_string()
                .into_bytes(),
        ),
        ("cameras.json", br#"[{"id": 0, "width": 64}]"#.to_vec()),
        ("poses_bounds.npy", b"\x93NUMPY\x01\x00garbage".to_vec()),
    ];
    for (name, bytes) in cameras {
        let form = Form::new()
            .part("scene", Part::bytes(scene.clone()).file_name("s.ply"))
            .part("cameras", Part::bytes(bytes).file_name(name));
        let r = t
            .client
            .post(t.url("/v1/assets"))
            .bearer_auth(&k.owner)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = r.status();
        assert!(status.is_client_error(), "cameras {name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("cameras {name}: {status} {}", p["detail"]);
    }
    // Images for a dispute that are not what they claim.
    let mut png = vec![];
    image::RgbImage::from_pixel(64, 64, image::Rgb([1, 2, 3]))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let mut huge = png.clone();
    // The IHDR says 100 000 × 100 000 (its CRC no longer matches either).
    huge[16..20].copy_from_slice(&100_000u32.to_be_bytes());
    huge[20..24].copy_from_slice(&100_000u32.to_be_bytes());
    let mut jpeg = vec![];
    image::RgbImage::from_pixel(64, 64, image::Rgb([9, 9, 9]))
        .write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let mut tiny = vec![];
    image::RgbImage::new(8, 8)
        .write_to(
            &mut std::io::Cursor::new(&mut tiny),
            image::ImageFormat::Png,
        )
        .unwrap();
    let images: Vec<(&str, Vec<u8>)> = vec![
        ("truncated.png", png[..png.len() / 2].to_vec()),
        ("huge.png", huge),
        ("truncated.jpg", jpeg[..jpeg.len() / 2].to_vec()),
        ("garbage.png", vec![0x42; 500]),
        ("tiny.png", tiny),
        ("scene.png", scene.clone()),
    ];
    for (name, bytes) in images {
        let form = Form::new().part("image", Part::bytes(bytes).file_name(name));
        let r = t
            .client
            .post(t.url("/v1/verify"))
            .bearer_auth(&k.verifier)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = r.status();
        assert!(status.is_client_error(), "image {name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("image {name}: {status} {}", p["detail"]);
    }

    // No 5xx, nothing stored beyond the warm-up's upload, no upload audited but that one.
    assert_eq!(responses_of_class(&t, "5xx").await, before_5xx);
    assert_eq!(stored_blobs(&t.data()), kept);
    let audit: Value = t
        .get(&k.auditor, "/v1/audit?action=asset.upload")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(audit["items"].as_array().unwrap().len(), 1);
    // Memory: the whole corpus leaves the process within 64 MB of where it started.
    if let (Some(a), Some(b)) = (before_rss, rss_bytes()) {
        let grown = b.saturating_sub(a);
        eprintln!("RSS {} MB → {} MB", a >> 20, b >> 20);
        assert!(grown < 64 << 20, "RSS grew by {} MB", grown >> 20);
    } else {
        eprintln!("SKIPPED the RSS check: no /proc/self/status");
    }
    t.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_master_key_is_not_rotated_beside_a_running_server() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let master = MasterKey::generate().to_hex();
    let mut t = TestApp::boot(dir, cfg.clone(), master.clone(), Some(vec![])).await;
    let new_key = t.dir.path().join("new.key");
    let rotate = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_splatmark"))
            .args(["keys", "rotate-master", "--data-dir"])
            .arg(&cfg.data_dir)
            .arg("--new-key-file")
            .arg(&new_key)
            .env("SPLATMARK_MASTER_KEY", &master)
            .output()
            .unwrap()
    };
    let refused = rotate();
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "rotated beside a live server");
    assert!(err.contains("in use by another splatmark process"), "{err}");
    assert!(!new_key.exists(), "a refused rotation writes no key");
    // The server keeps working under its key.
    let k = t.keys().await;
    assert!(!k.owner.is_empty());
    t.stop().await;
    // Stopped: the rotation runs.
    let done = rotate();
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    // A new key, written where asked, even though the current one comes from the environment.
    let written = std::fs::read_to_string(&new_key).unwrap();
    assert_eq!(written.trim().len(), 64);
    assert_ne!(written.trim(), master);
    let store =
        splatmark::store::Store::open(&cfg.data_dir, MasterKey::from_hex(written.trim()).unwrap())
            .await
            .unwrap();
    assert!(store.verify_audit_chain().await.unwrap().ok);
    store.close().await;
}
