//! What the service tests share: [`TestApp`] boots the real server (`splatmark::app::App`) on
//! 127.0.0.1:0 with its own temporary database and blob folder and talks HTTP to it; builders for
//! scene files in each format.
#![allow(dead_code)] // each test binary uses its own subset

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

use splatmark::app::App;
use splatmark::config::Config;
use splatmark::embed::pipeline::split_views;
use splatmark::queue::JobSpec;
use splatmark::scene::orbit::orbit_cameras;
use splatmark::scene::synthetic::object_scene;
use splatmark::scene::{Gaussians, write_ply};
use splatmark::store::{BlobConfig, BlobStore, Database, MasterKey};

/// A running server with its own data folder and an HTTP client.
pub struct TestApp {
    pub app: Option<App>,
    pub base: String,
    pub client: reqwest::Client,
    pub dir: tempfile::TempDir,
    /// The bootstrap admin token (read from DATA_DIR/admin.token, as an operator would).
    pub admin: String,
    /// The database the server opened.
    pub database: Database,
    /// The blob store the server opened (a folder, or a prefix of the test S3 bucket), opened
    /// again beside it for looking behind its back.
    pub blobs: BlobStore,
}

pub struct Keys {
    pub owner: String,
    pub verifier: String,
    pub auditor: String,
}

/// A new, empty database on the PostgreSQL server that `SPLATMARK_TEST_POSTGRES` names
/// (`postgres://USER@HOST:PORT`; `scripts/test.sh` starts one and runs the service suites a
/// second time against it), or `None` — SQLite in the data folder — when it names none.
pub fn test_database() -> Option<Database> {
    let server = std::env::var("SPLATMARK_TEST_POSTGRES")
        .ok()
        .filter(|s| !s.is_empty())?;
    let name = format!("sm_{}", uuid::Uuid::new_v4().simple());
    // A thread of its own: the caller may be inside a runtime already.
    std::thread::spawn(move || {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap()
            .block_on(splatmark::store::database::create_postgres(&server, &name))
            .expect("a new database on the test PostgreSQL server")
    })
    .join()
    .map(Some)
    .unwrap()
}

/// The S3-compatible test server `SPLATMARK_TEST_S3` names
/// (`http://ACCESS_KEY:SECRET@HOST:PORT/BUCKET`; `scripts/test.sh` starts one with
/// `scripts/s3-test-server.sh` and runs the service suites against it), with a new key prefix
/// of its own, or `None` — blobs in the data folder — when it names none.
pub fn test_blobs() -> Option<BlobConfig> {
    let server = std::env::var("SPLATMARK_TEST_S3")
        .ok()
        .filter(|s| !s.is_empty())?;
    let prefix = format!("t-{}", uuid::Uuid::new_v4().simple());
    Some(
        BlobConfig::test_server(&server, &prefix, 1 << 20)
            .expect("SPLATMARK_TEST_S3 is http://ACCESS_KEY:SECRET@HOST:PORT/BUCKET"),
    )
}

pub fn config(dir: &Path) -> Config {
    let (blob_url, s3) = match test_blobs() {
        Some(BlobConfig::S3 { url, options }) => (Some(url), options),
        _ => (None, Default::default()),
    };
    Config {
        bind: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.join("data"),
        database_url: test_database(),
        blob_url,
        s3,
        workers: Some(1),
        device: splatmark::config::DevicePolicy::Cpu,
        ..Config::default()
    }
}

impl TestApp {
    pub async fn start() -> Self {
        Self::start_with(|_| {}).await
    }

    pub async fn start_with(f: impl FnOnce(&mut Config)) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = config(dir.path());
        f(&mut cfg);
        let master = MasterKey::generate().to_hex();
        Self::boot(dir, cfg, master, None).await
    }

    pub async fn boot(
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
        let blobs = BlobStore::open_with(cfg.data_dir.join("blobs"), &cfg.blobs())
            .expect("the server's blob store");
        Self {
            base: format!("http://{}", app.addr),
            app: Some(app),
            client: reqwest::Client::new(),
            dir,
            admin,
            database: cfg.database(),
            blobs,
        }
    }

    /// Every blob the server keeps: the files under its blob folder other than in-flight
    /// temporaries, or on S3 the objects under its prefix (the local cache is not the store).
    pub fn stored_blobs(&self) -> Vec<String> {
        if self.blobs.is_remote() {
            self.blobs
                .list()
                .expect("list the bucket")
                .into_iter()
                .map(|b| b.id)
                .collect()
        } else {
            stored_blobs(&self.data())
                .into_iter()
                .map(|p| p.display().to_string())
                .collect()
        }
    }

    /// A connection to the server's database behind its back (for tampering).
    pub async fn raw_db(&self) -> sqlx::AnyConnection {
        use sqlx::Connection;
        sqlx::any::install_default_drivers();
        sqlx::AnyConnection::connect(&self.database.url())
            .await
            .unwrap()
    }

    /// Makes the database refuse every INSERT into `table` with "refused by the test" (as a
    /// full disk or a broken database would), behind the server's back.
    pub async fn refuse_inserts(&self, table: &str) {
        let mut db = self.raw_db().await;
        let statements = match &self.database {
            Database::Sqlite(_) => vec![format!(
                "CREATE TRIGGER refuse_{table} BEFORE INSERT ON {table} \
                 BEGIN SELECT RAISE(ABORT, 'refused by the test'); END"
            )],
            Database::Postgres(_) => vec![
                "CREATE OR REPLACE FUNCTION refuse_insert() RETURNS trigger LANGUAGE plpgsql \
                 AS $$ BEGIN RAISE EXCEPTION 'refused by the test'; END $$"
                    .to_string(),
                format!(
                    "CREATE TRIGGER refuse_{table} BEFORE INSERT ON {table} \
                     FOR EACH ROW EXECUTE FUNCTION refuse_insert()"
                ),
            ],
        };
        for sql in statements {
            sqlx::query(sqlx::AssertSqlSafe(sql))
                .execute(&mut db)
                .await
                .unwrap();
        }
    }

    /// Undoes [`TestApp::refuse_inserts`].
    pub async fn allow_inserts(&self, table: &str) {
        let mut db = self.raw_db().await;
        let sql = match &self.database {
            Database::Sqlite(_) => format!("DROP TRIGGER refuse_{table}"),
            Database::Postgres(_) => format!("DROP TRIGGER refuse_{table} ON {table}"),
        };
        sqlx::query(sqlx::AssertSqlSafe(sql))
            .execute(&mut db)
            .await
            .unwrap();
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn key(&self, scopes: &[&str]) -> String {
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

    pub async fn keys(&self) -> Keys {
        Keys {
            owner: self.key(&["owner"]).await,
            verifier: self.key(&["verifier"]).await,
            auditor: self.key(&["auditor"]).await,
        }
    }

    pub async fn upload(&self, token: &str, name: &str, bytes: Vec<u8>) -> reqwest::Response {
        let form = Form::new().part("scene", Part::bytes(bytes).file_name(name.to_string()));
        self.client
            .post(self.url("/v1/assets"))
            .bearer_auth(token)
            .multipart(form)
            .send()
            .await
            .unwrap()
    }

    /// How many audit rows of `action` the first page of `/v1/audit` lists (read with `token`).
    pub async fn audited(&self, token: &str, action: &str) -> usize {
        let page: Value = self
            .get(token, &format!("/v1/audit?action={action}"))
            .await
            .json()
            .await
            .unwrap();
        page["items"].as_array().unwrap().len()
    }

    pub async fn get(&self, token: &str, path: &str) -> reqwest::Response {
        self.client
            .get(self.url(path))
            .bearer_auth(token)
            .send()
            .await
            .unwrap()
    }

    pub async fn verify(
        &self,
        token: &str,
        images: &[image::RgbImage],
        asset: Option<&str>,
    ) -> Value {
        let r = self.verify_response(token, images, asset).await;
        assert_eq!(r.status(), StatusCode::OK);
        r.json().await.unwrap()
    }

    /// `POST /v1/verify` of `images` (as PNGs), against `asset` when given: the response as it
    /// comes.
    pub async fn verify_response(
        &self,
        token: &str,
        images: &[image::RgbImage],
        asset: Option<&str>,
    ) -> reqwest::Response {
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
        self.client
            .post(self.url("/v1/verify"))
            .bearer_auth(token)
            .multipart(form)
            .send()
            .await
            .unwrap()
    }

    /// The `/metrics` page.
    pub async fn metrics(&self) -> String {
        let r = self.client.get(self.url("/metrics")).send().await.unwrap();
        r.text().await.unwrap()
    }

    /// Queues a watermark job of `asset` with `body` as `token`, waits for it (at most
    /// `limit`), checks that it is done, and returns the job's JSON.
    pub async fn watermark_done(
        &self,
        token: &str,
        asset: &str,
        body: &Value,
        limit: Duration,
    ) -> Value {
        let job: Value = self
            .client
            .post(self.url(&format!("/v1/assets/{asset}/watermark")))
            .bearer_auth(token)
            .json(body)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let job = self
            .wait_job(token, job["id"].as_str().expect("a job id"), limit)
            .await;
        assert_eq!(job["state"], "done", "{job}");
        job
    }

    /// An asset's metadata and its scene as downloaded (INRIA PLY).
    pub async fn downloaded(&self, token: &str, asset: &str) -> (Value, Gaussians) {
        let meta: Value = self
            .get(token, &format!("/v1/assets/{asset}"))
            .await
            .json()
            .await
            .unwrap();
        let bytes = self
            .get(token, &format!("/v1/assets/{asset}/file"))
            .await
            .bytes()
            .await
            .unwrap();
        let g = splatmark::scene::read_scene_bytes(
            &bytes,
            Some("ply"),
            &splatmark::scene::Limits::default(),
        )
        .unwrap();
        (meta, g)
    }

    /// Polls a job until it leaves the queued/running states.
    pub async fn wait_job(&self, token: &str, id: &str, limit: Duration) -> Value {
        self.wait_job_until(token, id, limit, |j| {
            j["state"] != "queued" && j["state"] != "running"
        })
        .await
    }

    /// Polls a job until `done` holds for its JSON (panics after `limit`).
    pub async fn wait_job_until(
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
    pub async fn small_object_job(&self, owner: &str, steps: usize) -> (String, String) {
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

    pub fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    pub async fn stop(&mut self) {
        if let Some(a) = self.app.take() {
            a.stop().await.unwrap();
        }
    }
}

pub fn ply_bytes(g: &Gaussians) -> Vec<u8> {
    let mut v = vec![];
    write_ply(g, &mut v).unwrap();
    v
}

pub async fn assert_problem(r: reqwest::Response, status: StatusCode) -> Value {
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
pub fn stored_blobs(data: &Path) -> Vec<PathBuf> {
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
pub fn small_job(message: &str, steps: usize) -> Value {
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
pub fn training_views(g: &Gaussians, spec: &JobSpec) -> Vec<splatmark::scene::Camera> {
    let cams = orbit_cameras(g, &spec.orbit).unwrap();
    split_views(&cams, spec.holdout_every).0
}

/// The shared data folder, when present (CI has it).
pub fn shared_scene(rel: &str) -> Option<PathBuf> {
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
pub fn psnr(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let se: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum();
    let mse = se / a.as_raw().len() as f64 / 255.0 / 255.0;
    -10.0 * mse.max(1e-12).log10()
}

/// `n` Gaussians as a SuperSplat compressed PLY (one chunk of bounds, packed words from a fixed
/// generator: every 32-bit pattern decodes to a valid Gaussian).
pub fn compressed_ply_bytes(n: usize) -> Vec<u8> {
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
pub fn splat_bytes(n: usize) -> Vec<u8> {
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
pub fn spz_bytes(n: usize) -> Vec<u8> {
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

/// The count of one status class in `/metrics`.
pub async fn responses_of_class(t: &TestApp, class: &str) -> u64 {
    let m = t.metrics().await;
    let key = format!("splatmark_http_responses_total{{class=\"{class}\"}} ");
    m.lines()
        .find_map(|l| l.strip_prefix(&key))
        .map_or(0, |v| v.trim().parse::<f64>().unwrap() as u64)
}
