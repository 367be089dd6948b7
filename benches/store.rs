//! Storage benchmarks: publishing a watermarked asset with 1 M attribution records (one
//! `BEGIN IMMEDIATE` transaction, prepared 512-row INSERTs), then reading pages and the summary;
//! then the queue: how many jobs a second 1, 4 and 16 concurrent claimers take from a queue of
//! 1 000 (each claim one transaction: the job's row, its lease, its audit row).
//!
//! Run: `cargo bench --bench store` (add `-- N` for another record count, `-- 0` for the queue
//! alone). Prints one line per measurement. SQLite in a temporary folder, or the database
//! `SPLATMARK_BENCH_DATABASE_URL` names (an empty PostgreSQL database, for example).

use splatmark::embed::attribution::AttributionRecord;
use splatmark::embed::sbag::Role;
use splatmark::store::{AssetKind, AuditEntry, Database, MasterKey, NewAsset, NewJob, Store};
use std::time::{Duration, Instant};

fn records(n: u32) -> Vec<AttributionRecord> {
    (0..n)
        .map(|i| {
            let f = i as f32;
            let role = match i % 20 {
                0 => Role::Carrier,
                1 | 2 => Role::Compensator,
                _ => Role::Untouched,
            };
            AttributionRecord {
                index: i,
                role,
                parent: i - i % 3,
                child: (i % 3) as u8,
                r: [f.sin(), f.cos(), 0.5],
                uncertainty: [0.1, 0.2, 0.3],
                quality: [0.9, 0.8, f * 1e-6],
                utility: (f * 0.37).sin().abs(),
                visibility: (f * 0.11).cos().abs(),
                feasible: i % 2 == 0,
                seed: (role != Role::Untouched).then_some(i % 7 != 0),
                mask_wm: [1.0, 1.0, 0.0, 0.5, 0.5],
                mask_vis: [0.0, 1.0, 1.0, 1.0, 1.0],
                wm_grad_share: Some(f * 1e-9),
            }
        })
        .collect()
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

async fn run(n: u32) -> Result<(), Box<dyn std::error::Error>> {
    let dir = tempfile::tempdir()?;
    let database = match std::env::var("SPLATMARK_BENCH_DATABASE_URL") {
        Ok(url) if !url.is_empty() => Database::parse(&url)?,
        _ => Database::in_data_dir(dir.path()),
    };
    println!("database: {database}");
    let store = Store::open_with(dir.path(), &database, MasterKey::generate()).await?;
    let blob = store.blobs().put_bytes(b"original")?;
    let original = store
        .insert_asset(
            NewAsset {
                owner: "bench".into(),
                kind: AssetKind::Original,
                parent_id: None,
                source_job_id: None,
                blob,
                format: "ply".into(),
                file_name: None,
                gaussians: u64::from(n),
                sh_degree: 3,
                cameras_blob: None,
                cameras_format: None,
            },
            AuditEntry::new("bench", "asset.upload"),
        )
        .await?;
    let message: Vec<bool> = (0..32).map(|i| i % 3 == 0).collect();
    enqueue(&store, &original, &message).await?;
    let claimed = store
        .claim("bench", Duration::from_secs(600))
        .await?
        .ok_or("no job to claim")?;
    if n > 0 {
        publish_and_read(&store, &original, claimed, n).await?;
    }
    for claimers in [1, 4, 16] {
        claims(&store, &original, &message, 1000, claimers).await?;
    }
    store.close().await;
    let Database::Sqlite(file) = &database else {
        return Ok(());
    };
    let db = std::fs::metadata(file)?.len();
    if n > 0 {
        println!(
            "database file after close: {:.1} MiB ({:.0} bytes per record)",
            db as f64 / (1 << 20) as f64,
            db as f64 / f64::from(n)
        );
    }
    Ok(())
}

/// Enqueues one job of `message` for `original`.
async fn enqueue(
    store: &Store,
    original: &splatmark::store::Asset,
    message: &[bool],
) -> Result<(), splatmark::store::StoreError> {
    store
        .enqueue(
            NewJob {
                asset_id: original.id,
                owner: "bench".into(),
                bits: 32,
                message: message.to_vec(),
                options: serde_json::json!({}),
                idempotency_key: None,
                max_attempts: 3,
            },
            AuditEntry::new("bench", "job.enqueue"),
        )
        .await?;
    Ok(())
}

/// Enqueues `jobs` jobs, then `claimers` tasks claim until the queue is empty: claims per
/// second and the claim latency's median and 99th percentile.
async fn claims(
    store: &Store,
    original: &splatmark::store::Asset,
    message: &[bool],
    jobs: usize,
    claimers: usize,
) -> Result<(), Box<dyn std::error::Error>> {
    for _ in 0..jobs {
        enqueue(store, original, message).await?;
    }
    let t = Instant::now();
    let mut tasks = Vec::new();
    for k in 0..claimers {
        let store = store.clone();
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            loop {
                let t = Instant::now();
                let got = store
                    .claim(&format!("bench-{k}"), Duration::from_secs(600))
                    .await?;
                if got.is_none() {
                    return Ok::<_, splatmark::store::StoreError>(lat);
                }
                lat.push(t.elapsed());
            }
        }));
    }
    let mut lat = Vec::new();
    for task in tasks {
        lat.extend(task.await??);
    }
    let wall = t.elapsed();
    assert_eq!(lat.len(), jobs, "every job claimed exactly once");
    lat.sort();
    let q = |p: f64| ms(lat[((lat.len() - 1) as f64 * p).round() as usize]);
    println!(
        "claim, {claimers} concurrent claimers, {jobs} jobs: {:.0} claims/s, p50 {:.2} ms, p99 {:.2} ms",
        jobs as f64 / wall.as_secs_f64(),
        q(0.5),
        q(0.99)
    );
    Ok(())
}

/// Publishes `n` attribution records for `claimed`'s job, then reads pages and the summary.
async fn publish_and_read(
    store: &Store,
    original: &splatmark::store::Asset,
    claimed: splatmark::store::Claimed,
    n: u32,
) -> Result<(), Box<dyn std::error::Error>> {
    let recs = records(n);
    let blob = store.blobs().put_bytes(b"watermarked")?;
    let asset = NewAsset {
        kind: AssetKind::Watermarked,
        parent_id: Some(original.id),
        blob,
        ..NewAsset {
            owner: "bench".into(),
            kind: AssetKind::Original,
            parent_id: None,
            source_job_id: None,
            blob: store.blobs().put_bytes(b"x")?,
            format: "ply".into(),
            file_name: None,
            gaussians: u64::from(n),
            sh_degree: 3,
            cameras_blob: None,
            cameras_format: None,
        }
    };
    let t = Instant::now();
    let wm = store
        .publish_result(
            claimed.job.id,
            claimed.lease_token,
            asset,
            &claimed.key,
            &splatmark::store::Readout::default(),
            &recs,
            serde_json::json!({ "bench": true }),
            AuditEntry::new("bench", "watermark.publish"),
        )
        .await?;
    let publish = t.elapsed();
    println!(
        "publish_result with {n} attribution records: {:.0} ms ({:.0} k records/s)",
        ms(publish),
        f64::from(n) / publish.as_secs_f64() / 1e3
    );

    for (label, role, after) in [
        ("first page, 1000 records", None, None),
        ("page at index 500000, 1000 records", None, Some(500_000)),
        (
            "carriers page at index 500000, 1000 records",
            Some(Role::Carrier),
            Some(500_000),
        ),
    ] {
        let mut best = Duration::MAX;
        for _ in 0..5 {
            let t = Instant::now();
            let (page, _) = store.attribution_page(wm.id, role, after, 1000).await?;
            best = best.min(t.elapsed());
            assert_eq!(page.len(), 1000.min(n as usize));
        }
        println!("attribution_page, {label}: {:.2} ms (best of 5)", ms(best));
    }
    let t = Instant::now();
    let s = store.attribution_summary(wm.id).await?;
    println!(
        "attribution_summary over {} records: {:.0} ms",
        s.gaussians,
        ms(t.elapsed())
    );
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let n = std::env::args()
        .skip(1)
        .find_map(|a| a.parse::<u32>().ok())
        .unwrap_or(1_000_000);
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run(n))
}
