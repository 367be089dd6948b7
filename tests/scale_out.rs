//! Many processes on one PostgreSQL database (issue 17): two API replicas (`serve --role api`)
//! and three worker processes (`serve --role worker`), the real binary, sharing the database and
//! the blobs — with `SPLATMARK_TEST_S3`, an S3 bucket, each process with a data folder of its
//! own (staging and read cache only); without it, one shared blob folder. Thirty jobs go in
//! through both replicas; workers are killed (SIGKILL) mid-job and replaced until two jobs were
//! interrupted, and each of those is claimed again. Every job must
//! finish exactly once: one watermarked asset, one key and one full set of attribution rows per
//! job, every asset's blob in the store, and the audit chain verifies.
//!
//! Runs in the PostgreSQL pass of `scripts/test.sh` (`SPLATMARK_TEST_POSTGRES`, and
//! `SPLATMARK_TEST_S3` when an S3 server started); without PostgreSQL it prints SKIPPED.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{ply_bytes, small_job, test_blobs, test_database};
use reqwest::StatusCode;
use serde_json::{Value, json};
use splatmark::scene::synthetic::object_scene;
use splatmark::store::{BlobConfig, BlobStore, Database, MasterKey};
use sqlx::Connection;

struct Process {
    child: Child,
    base: String,
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Starts `serve --role ROLE` on `db`, data folder `data` and the blobs in `blobs` (the
/// S3 settings as an operator gives them: `SPLATMARK_BLOB_URL` and the standard `AWS_*`
/// variables); returns once `/healthz` answers.
async fn serve(
    role: &str,
    data: &Path,
    db: &Database,
    blobs: &BlobConfig,
    master: &str,
    log: &Path,
) -> Process {
    let port = free_port();
    let log = std::fs::File::create(log).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_splatmark"));
    cmd.args(["serve", "--role", role, "--workers", "1", "--device", "cpu"])
        .arg("--data-dir")
        .arg(data)
        .arg("--bind")
        .arg(format!("127.0.0.1:{port}"))
        .env("SPLATMARK_DATABASE_URL", db.url())
        .env("SPLATMARK_MASTER_KEY", master)
        // Leases of killed workers expire fast.
        .env("SPLATMARK_LEASE_SECONDS", "3")
        .stdout(Stdio::null())
        .stderr(log);
    if let BlobConfig::S3 { url, options } = blobs {
        cmd.env("SPLATMARK_BLOB_URL", url.to_string())
            .env("AWS_ENDPOINT_URL", options.endpoint.as_deref().unwrap())
            .env("AWS_REGION", options.region.as_deref().unwrap())
            .env(
                "AWS_ACCESS_KEY_ID",
                options.access_key_id.as_deref().unwrap(),
            )
            .env(
                "AWS_SECRET_ACCESS_KEY",
                options.secret_access_key.as_ref().unwrap().expose(),
            )
            // Scenes of a few hundred kB go up in parts.
            .env("SPLATMARK_S3_MULTIPART_THRESHOLD", "65536");
    }
    let child = cmd.spawn().unwrap();
    let p = Process {
        child,
        base: format!("http://127.0.0.1:{port}"),
    };
    let client = reqwest::Client::new();
    let start = Instant::now();
    loop {
        if let Ok(r) = client.get(format!("{}/healthz", p.base)).send().await
            && r.status() == StatusCode::OK
        {
            return p;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "serve --role {role} did not start"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_replicas_and_killed_workers_finish_every_job_exactly_once() {
    let Some(db) = test_database() else {
        eprintln!(
            "SKIPPED: no PostgreSQL server (SPLATMARK_TEST_POSTGRES); scripts/test.sh starts one"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let blobs = test_blobs().unwrap_or_default();
    let on_s3 = blobs != BlobConfig::Local;
    if !on_s3 {
        eprintln!(
            "NOTE: no S3 server (SPLATMARK_TEST_S3): the processes share one blob folder; \
             scripts/test.sh starts one"
        );
    }
    // On S3 every process has a data folder of its own, as on separate machines.
    let data_of = |name: &str| {
        if on_s3 {
            dir.path().join(format!("data-{name}"))
        } else {
            dir.path().join("data")
        }
    };
    let data = data_of("api1");
    let master = MasterKey::generate().to_hex();
    let logs = dir.path();
    // The first replica bootstraps the admin key; the second starts once it exists.
    let api1 = serve("api", &data, &db, &blobs, &master, &logs.join("api1.log")).await;
    let api2 = serve(
        "api",
        &data_of("api2"),
        &db,
        &blobs,
        &master,
        &logs.join("api2.log"),
    )
    .await;
    let mut workers = Vec::new();
    for i in 0..3 {
        workers.push(
            serve(
                "worker",
                &data_of(&format!("w{i}")),
                &db,
                &blobs,
                &master,
                &logs.join(format!("w{i}.log")),
            )
            .await,
        );
    }
    // A worker process serves probes and metrics, not the API.
    let client = reqwest::Client::new();
    let r = client
        .get(format!("{}/v1/assets", workers[0].base))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::NOT_FOUND);

    let admin = std::fs::read_to_string(data.join("admin.token"))
        .unwrap()
        .trim()
        .to_string();
    let key = |scopes: &'static [&'static str]| {
        let (client, base, admin) = (client.clone(), api1.base.clone(), admin.clone());
        async move {
            let r = client
                .post(format!("{base}/v1/keys"))
                .bearer_auth(&admin)
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
    };
    let (owner, auditor) = (key(&["owner"]).await, key(&["auditor"]).await);

    // One scene, uploaded through the second replica; thirty jobs through both.
    let form = reqwest::multipart::Form::new().part(
        "scene",
        reqwest::multipart::Part::bytes(ply_bytes(&object_scene(300, 0, 5))).file_name("s.ply"),
    );
    let r = client
        .post(format!("{}/v1/assets", api2.base))
        .bearer_auth(&owner)
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::CREATED);
    let asset = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let jobs = 30;
    let mut ids = Vec::new();
    for i in 0..jobs {
        let api = if i % 2 == 0 { &api1 } else { &api2 };
        let mut body = small_job(&format!("{:08x}", 0x5ca1_0000u32 + i), 12);
        body["options"]["embed"]["finetune"]["extra_steps"] = json!(0);
        body["options"]["orbit"] = json!({"count": 4, "width": 64, "height": 64});
        let r = client
            .post(format!("{}/v1/assets/{asset}/watermark", api.base))
            .bearer_auth(&owner)
            .json(&body)
            .send()
            .await
            .unwrap();
        assert_eq!(
            r.status(),
            StatusCode::ACCEPTED,
            "{}",
            r.text().await.unwrap()
        );
        ids.push(
            r.json::<Value>().await.unwrap()["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    let job = |id: String, base: String| {
        let (client, owner) = (client.clone(), owner.clone());
        async move {
            client
                .get(format!("{base}/v1/jobs/{id}"))
                .bearer_auth(&owner)
                .send()
                .await
                .unwrap()
                .json::<Value>()
                .await
                .unwrap()
        }
    };

    sqlx::any::install_default_drivers();
    let mut conn = sqlx::AnyConnection::connect(&db.url()).await.unwrap();
    // Kill a worker while it runs a job, until two jobs were interrupted; a new worker
    // process takes each one's place. A job can publish between the query and the kill: then
    // its worker died idle and the job does not count as interrupted.
    let start = Instant::now();
    let mut interrupted: Vec<String> = Vec::new();
    let mut killed = 0;
    while interrupted.len() < 2 {
        assert!(
            start.elapsed() < Duration::from_secs(300),
            "{} of two jobs interrupted in 300 s",
            interrupted.len()
        );
        // Which worker runs a job is not part of the API: read it from the database.
        let running: Vec<(String, String)> = sqlx::query_as(
            "SELECT id, worker FROM jobs WHERE state = 'running' AND step > 0 AND worker IS NOT NULL",
        )
        .fetch_all(&mut conn)
        .await
        .unwrap();
        let victim = workers.iter().enumerate().find_map(|(v, w)| {
            let pid = format!(":{}", w.child.id());
            running
                .iter()
                .find(|(_, r)| r.ends_with(&pid))
                .map(|(job, _)| (v, job.clone()))
        });
        match victim {
            Some((v, job)) => {
                let dead = workers.remove(v);
                drop(dead); // SIGKILL and wait: no release, no cleanup
                killed += 1;
                let state: String = sqlx::query_scalar("SELECT state FROM jobs WHERE id = $1")
                    .bind(&job)
                    .fetch_one(&mut conn)
                    .await
                    .unwrap();
                if state != "done" {
                    interrupted.push(job);
                }
                let log = logs.join(format!("w-new{killed}.log"));
                let own = data_of(&format!("w-new{killed}"));
                workers.push(serve("worker", &own, &db, &blobs, &master, &log).await);
            }
            None => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    }

    // Every job finishes.
    let mut results = std::collections::HashSet::new();
    for (k, id) in ids.iter().enumerate() {
        let base = if k % 2 == 0 { &api2 } else { &api1 };
        loop {
            let j = job(id.clone(), base.base.clone()).await;
            if j["state"] == "done" {
                results.insert(j["result_asset_id"].as_str().unwrap().to_string());
                break;
            }
            assert!(
                !matches!(j["state"].as_str(), Some("dead" | "cancelled")),
                "{j}"
            );
            assert!(
                start.elapsed() < Duration::from_secs(900),
                "job {id} not done: {j}"
            );
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
    }
    assert_eq!(results.len(), jobs as usize, "one result per job");

    // Exactly once, in the database: one watermarked asset and one key per job, each asset's
    // attribution rows all there.
    assert_eq!(
        count(
            &mut conn,
            "SELECT COUNT(*) FROM assets WHERE kind = 'watermarked'"
        )
        .await,
        i64::from(jobs)
    );
    assert_eq!(
        count(
            &mut conn,
            "SELECT COUNT(DISTINCT source_job_id) FROM assets WHERE kind = 'watermarked'"
        )
        .await,
        i64::from(jobs)
    );
    assert_eq!(
        count(&mut conn, "SELECT COUNT(*) FROM keys").await,
        i64::from(jobs)
    );
    assert_eq!(
        count(
            &mut conn,
            "SELECT COUNT(*) FROM assets s WHERE kind = 'watermarked' AND gaussians <> \
             (SELECT COUNT(*) FROM attribution a WHERE a.asset_seq = s.seq)"
        )
        .await,
        0,
        "an asset whose attribution rows are missing or repeated"
    );
    assert_eq!(
        count(
            &mut conn,
            "SELECT COUNT(*) FROM audit WHERE action = 'watermark.publish'"
        )
        .await,
        i64::from(jobs)
    );
    // The interrupted jobs were claimed again.
    for job in &interrupted {
        let claims: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM audit WHERE action = 'job.claim' AND job_id = $1",
        )
        .bind(job)
        .fetch_one(&mut conn)
        .await
        .unwrap();
        assert!(
            claims >= 2,
            "job {job} interrupted but claimed {claims} time(s)"
        );
    }
    // Every asset's blob is in the store, whole; on S3 no process kept a blob in its own
    // folder (staging and the read cache only).
    let root = if on_s3 {
        dir.path().join("check-blobs")
    } else {
        data.join("blobs")
    };
    let store = BlobStore::open_with(root, &blobs).unwrap();
    let ids: Vec<String> = sqlx::query_scalar("SELECT sha256 FROM assets")
        .fetch_all(&mut conn)
        .await
        .unwrap();
    assert_eq!(ids.len(), jobs as usize + 1);
    let stored = tokio::task::spawn_blocking(move || {
        for id in &ids {
            store.read(id).unwrap();
        }
        store.list().unwrap()
    })
    .await
    .unwrap();
    assert!(stored.len() > jobs as usize, "{} blobs", stored.len());
    if on_s3 {
        for e in std::fs::read_dir(dir.path()).unwrap().flatten() {
            let blob_dir = e.path().join("blobs");
            if !blob_dir.is_dir() {
                continue;
            }
            for sub in std::fs::read_dir(&blob_dir).unwrap().flatten() {
                let name = sub.file_name();
                assert!(
                    name == "tmp" || name == "cache",
                    "{} in a process's own folder",
                    sub.path().display()
                );
            }
        }
    }
    let chain: Value = client
        .get(format!("{}/v1/audit/verify", api2.base))
        .bearer_auth(&auditor)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(chain["ok"], true, "{chain}");
}

async fn count(conn: &mut sqlx::AnyConnection, sql: &'static str) -> i64 {
    sqlx::query_scalar::<_, i64>(sql)
        .fetch_one(conn)
        .await
        .unwrap()
}
