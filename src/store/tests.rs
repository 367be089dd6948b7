//! Storage tests: each opens its own store in a temp dir.

use super::*;
use crate::embed::attribution::AttributionRecord;
use crate::embed::sbag::Role;
use sqlx::AnyConnection;
use sqlx::Connection;
use std::collections::HashSet;
use std::time::Duration;
use tempfile::TempDir;

const LONG: Duration = Duration::from_secs(60);

/// Where the store tests keep their rows: an SQLite file in the test's folder, or — when
/// `SPLATMARK_TEST_POSTGRES` names a PostgreSQL server (`postgres://USER@HOST:PORT`, as
/// `scripts/test.sh` starts one) — a new database on that server for each test. The choice is
/// written into the folder, so that a test reopening the store, or tampering with its rows,
/// finds the same database.
const TEST_DB_FILE: &str = "test-database.url";

async fn test_database(dir: &std::path::Path) -> Database {
    let url_file = dir.join(TEST_DB_FILE);
    if let Ok(url) = std::fs::read_to_string(&url_file) {
        return Database::parse(&url).expect("stored test database URL");
    }
    let db = match std::env::var("SPLATMARK_TEST_POSTGRES") {
        Ok(server) if !server.is_empty() => {
            let name = format!("sm_{}", uuid::Uuid::new_v4().simple());
            database::create_postgres(&server, &name)
                .await
                .expect("a new database on the test PostgreSQL server")
        }
        _ => Database::in_data_dir(dir),
    };
    std::fs::write(&url_file, db.url()).expect("write the test database URL");
    db
}

/// Where the store tests keep their blobs: `dir/blobs`, or — when `SPLATMARK_TEST_S3` names an
/// S3-compatible test server (`http://KEY:SECRET@HOST:PORT/BUCKET`, as
/// `scripts/s3-test-server.sh` starts one) — a key prefix of the test's own in its bucket,
/// written into the folder like the database's URL. Multipart uploads start at
/// [`TEST_MULTIPART_THRESHOLD`] there.
const TEST_BLOBS_FILE: &str = "test-blobs.prefix";
const TEST_MULTIPART_THRESHOLD: u64 = 1 << 20;

fn test_blobs(dir: &std::path::Path) -> BlobConfig {
    let Some(server) = s3_server() else {
        return BlobConfig::Local;
    };
    let file = dir.join(TEST_BLOBS_FILE);
    let prefix = std::fs::read_to_string(&file).unwrap_or_else(|_| {
        let p = format!("t-{}", uuid::Uuid::new_v4().simple());
        std::fs::write(&file, &p).expect("write the test blob prefix");
        p
    });
    BlobConfig::test_server(&server, &prefix, TEST_MULTIPART_THRESHOLD).expect("SPLATMARK_TEST_S3")
}

fn s3_server() -> Option<String> {
    std::env::var("SPLATMARK_TEST_S3")
        .ok()
        .filter(|s| !s.is_empty())
}

fn on_s3() -> bool {
    s3_server().is_some()
}

/// Opens (or reopens) the test store of `dir`.
async fn open_in(dir: &std::path::Path, key: MasterKey) -> Result<Store> {
    let db = test_database(dir).await;
    Store::open_with_blobs(dir, &db, &test_blobs(dir), key).await
}

fn on_postgres() -> bool {
    std::env::var("SPLATMARK_TEST_POSTGRES").is_ok_and(|s| !s.is_empty())
}

async fn setup() -> (TempDir, Store) {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = open_in(dir.path(), MasterKey::generate())
        .await
        .expect("open");
    (dir, store)
}

/// A raw connection that bypasses the store (for tampering).
async fn raw(dir: &TempDir) -> AnyConnection {
    let url = test_database(dir.path()).await.url();
    AnyConnection::connect(&url).await.expect("raw connection")
}

async fn scalar(dir: &TempDir, sql: &'static str) -> i64 {
    let mut c = raw(dir).await;
    sqlx::query_scalar(sql)
        .fetch_one(&mut c)
        .await
        .expect("scalar")
}

/// Checks that the sealed pair `<part>_nonce`, `<part>_ct` of the one `keys` row (asset `id`)
/// is authenticated — a changed byte, or half of the pair missing, does not open — and that a
/// row without it (both NULL, as before its migration) opens; returns that registration.
async fn sealed_column_is_checked(
    dir: &TempDir,
    store: &Store,
    id: uuid::Uuid,
    part: &str,
) -> crate::store::Registration {
    let mut conn = raw(dir).await;
    tamper_byte(&mut conn, &format!("{part}_ct")).await;
    assert!(matches!(
        store.registration(id).await,
        Err(StoreError::Crypto)
    ));
    for (column, opens) in [("ct", false), ("nonce", true)] {
        sqlx::query(sqlx::AssertSqlSafe(format!(
            "UPDATE keys SET {part}_{column} = NULL"
        )))
        .execute(&mut conn)
        .await
        .expect("clear");
        let r = store.registrations().await;
        assert_eq!(r.is_ok(), opens, "{part} without its {column}: {r:?}");
    }
    store
        .registration(id)
        .await
        .expect("read")
        .expect("registered")
}

/// Flips the bits of byte 5 of `column` of the one row of `keys`, bypassing the store.
async fn tamper_byte(conn: &mut AnyConnection, column: &str) {
    let mut v: Vec<u8> =
        sqlx::query_scalar(sqlx::AssertSqlSafe(format!("SELECT {column} FROM keys")))
            .fetch_one(&mut *conn)
            .await
            .expect("read");
    v[5] ^= 0xff;
    sqlx::query(sqlx::AssertSqlSafe(format!(
        "UPDATE keys SET {column} = $1"
    )))
    .bind(v)
    .execute(&mut *conn)
    .await
    .expect("tamper");
}

fn entry(action: &str) -> AuditEntry {
    AuditEntry::new("tester", action)
}

fn new_original(store: &Store, content: &[u8]) -> NewAsset {
    let blob = store.blobs().put_bytes(content).expect("blob");
    NewAsset {
        owner: "alice".into(),
        kind: AssetKind::Original,
        parent_id: None,
        source_job_id: None,
        blob,
        format: "ply".into(),
        file_name: Some("scene.ply".into()),
        gaussians: 10,
        sh_degree: 3,
        cameras_blob: None,
        cameras_format: None,
    }
}

async fn original(store: &Store) -> Asset {
    store
        .insert_asset(
            new_original(store, b"original scene bytes"),
            entry("asset.upload"),
        )
        .await
        .expect("insert original")
}

/// A message with a distinctive pattern.
fn message(bits: usize, seed: u64) -> Vec<bool> {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..bits)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x & 1 == 1
        })
        .collect()
}

fn new_job(asset: Uuid, msg: Vec<bool>, key: Option<&str>, max_attempts: u32) -> NewJob {
    NewJob {
        asset_id: asset,
        owner: "alice".into(),
        bits: msg.len() as u32,
        message: msg,
        options: serde_json::json!({ "steps": 100 }),
        idempotency_key: key.map(str::to_owned),
        max_attempts,
    }
}

async fn enqueue(store: &Store, asset: Uuid, max_attempts: u32) -> Job {
    store
        .enqueue(
            new_job(asset, message(32, 7), None, max_attempts),
            entry("job.enqueue"),
        )
        .await
        .expect("enqueue")
        .0
}

/// Queues a job for `msg` and claims it (the only job in the queue); its key holds `msg`.
async fn enqueue_and_claim(store: &Store, asset: Uuid, msg: &[bool]) -> Claimed {
    store
        .enqueue(new_job(asset, msg.to_vec(), None, 3), entry("job.enqueue"))
        .await
        .expect("enqueue");
    let c = store
        .claim("w1", LONG)
        .await
        .expect("claim")
        .expect("a job");
    assert_eq!(c.key.message, msg);
    c
}

/// `n` records with every role, seed kind and a NaN, as the pipeline would make them.
fn records(n: u32) -> Vec<AttributionRecord> {
    (0..n)
        .map(|i| {
            let f = i as f32;
            let role = match i % 5 {
                0 => Role::Carrier,
                1 | 2 => Role::Compensator,
                _ => Role::Untouched,
            };
            AttributionRecord {
                index: i,
                role,
                parent: i / 3,
                child: (i % 3) as u8,
                r: [f * 0.1, 1.0 / (f + 1.0), -f],
                uncertainty: [0.1, 0.2, f32::MIN_POSITIVE],
                quality: [f.sqrt(), f32::MAX, -0.0],
                utility: if i == 7 { f32::NAN } else { (f * 0.37).sin() },
                visibility: (f * 0.11).cos(),
                feasible: i % 2 == 0,
                seed: match i % 3 {
                    0 => None,
                    1 => Some(false),
                    _ => Some(true),
                },
                mask_wm: [1.0, 0.5, 0.0, 0.25, f],
                mask_vis: [0.0, 1.0, 1.0, 0.125, -f],
                wm_grad_share: (i % 4 != 0).then_some(f * 1e-6),
            }
        })
        .collect()
}

/// Bit-exact identity of a record (NaN-safe).
fn bits_of(r: &AttributionRecord) -> Vec<u64> {
    let mut v = vec![
        u64::from(r.index),
        u64::from(r.parent),
        u64::from(r.child),
        crate::store::attribution::role_code(r.role) as u64,
        u64::from(r.feasible),
        match r.seed {
            None => 0,
            Some(false) => 1,
            Some(true) => 2,
        },
        r.wm_grad_share.map_or(u64::MAX, |x| u64::from(x.to_bits())),
    ];
    let floats = r.r.iter().chain(&r.uncertainty).chain(&r.quality);
    let floats = floats
        .chain([&r.utility, &r.visibility])
        .chain(&r.mask_wm)
        .chain(&r.mask_vis);
    v.extend(floats.map(|x| u64::from(x.to_bits())));
    v
}

fn watermarked(store: &Store, parent: Uuid, gaussians: u64, content: &[u8]) -> NewAsset {
    NewAsset {
        kind: AssetKind::Watermarked,
        parent_id: Some(parent),
        gaussians,
        ..new_original(store, content)
    }
}

async fn publish(
    store: &Store,
    c: &Claimed,
    recs: &[AttributionRecord],
) -> Result<Asset, StoreError> {
    let asset = watermarked(
        store,
        c.job.asset_id,
        recs.len() as u64,
        b"watermarked scene",
    );
    store
        .publish_result(
            c.job.id,
            c.lease_token,
            asset,
            &c.key,
            &Readout::default(),
            recs,
            serde_json::json!({ "psnr": 41.5 }),
            entry("watermark.publish"),
        )
        .await
}

/// Every byte the store keeps for the test in `dir`: the files of the folder (the SQLite file,
/// its WAL — freed pages and all) and, on PostgreSQL, every value of every row as stored (raw
/// bytes of BYTEA, text as UTF-8, numbers as their decimal text).
async fn stored_bytes(dir: &TempDir) -> Vec<u8> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir.path()).expect("read_dir").flatten() {
        if e.path().is_file() && e.file_name() != TEST_DB_FILE {
            out.extend(std::fs::read(e.path()).expect("read"));
        }
    }
    if on_postgres() {
        use sqlx::{Column, Row, ValueRef};
        let mut conn = raw(dir).await;
        let tables = [
            "meta",
            "assets",
            "keys",
            "jobs",
            "attribution",
            "audit",
            "verifications",
            "api_keys",
        ];
        for t in tables {
            let rows = sqlx::query(sqlx::AssertSqlSafe(format!("SELECT * FROM {t}")))
                .fetch_all(&mut conn)
                .await
                .expect("rows");
            for r in &rows {
                for c in r.columns() {
                    let i = c.ordinal();
                    if r.try_get_raw(i).expect("value").is_null() {
                        continue;
                    }
                    if let Ok(b) = r.try_get::<Vec<u8>, _>(i) {
                        out.extend(b);
                    } else if let Ok(s) = r.try_get::<String, _>(i) {
                        out.extend(s.into_bytes());
                    } else if let Ok(n) = r.try_get::<i64, _>(i) {
                        out.extend(n.to_string().into_bytes());
                    } else if let Ok(x) = r.try_get::<f64, _>(i) {
                        out.extend(x.to_string().into_bytes());
                    }
                }
            }
        }
    }
    out
}

/// Drops an audit-log trigger behind the store's back (SQLite and PostgreSQL spell it apart).
async fn drop_trigger(conn: &mut AnyConnection, name: &str) {
    let sql = if on_postgres() {
        format!("DROP TRIGGER {name} ON audit")
    } else {
        format!("DROP TRIGGER {name}")
    };
    sqlx::query(sqlx::AssertSqlSafe(sql))
        .execute(&mut *conn)
        .await
        .expect("drop");
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

// ---- blobs -------------------------------------------------------------------------------

#[tokio::test]
async fn blob_commit_is_content_addressed_and_idempotent() {
    let (dir, store) = setup().await;
    let a = store.blobs().put_bytes(b"hello splats").expect("put");

    assert_eq!(
        a.sha256,
        hex::encode(<sha2::Sha256 as sha2::Digest>::digest(b"hello splats"))
    );
    assert_eq!(a.size, 12);
    let path = store.blobs().path(&a.sha256).expect("path");
    // On S3 the local file is the verified cached copy.
    let folder = if on_s3() { "blobs/cache" } else { "blobs" };
    assert_eq!(
        path,
        dir.path()
            .join(folder)
            .join(&a.sha256[..2])
            .join(&a.sha256[2..])
    );
    assert_eq!(std::fs::read(&path).expect("read"), b"hello splats");
    // The same bytes through a temp file: same id, one file, temp dir empty.
    let mut tmp = store.blobs().temp_file().expect("tmp");
    std::io::Write::write_all(&mut tmp, b"hello splats").expect("write");
    let b = store.blobs().commit(tmp).expect("commit");
    assert_eq!(a, b);
    assert_eq!(
        store.blobs().read(&a.sha256).expect("read"),
        b"hello splats"
    );
    let tmp_dir = dir.path().join("blobs/tmp");
    assert_eq!(std::fs::read_dir(tmp_dir).expect("tmp dir").count(), 0);
    let other = store.blobs().put_bytes(b"other").expect("put");
    assert_ne!(other.sha256, a.sha256);
}

/// The garbage collector's age threshold on S3 in these tests: an object's `LastModified`
/// cannot be set, so blobs get older than this by waiting ([`age_blobs`]).
const S3_MIN_AGE: Duration = Duration::from_secs(2);

/// The age threshold a test passes to the garbage collector: `local` on a folder,
/// [`S3_MIN_AGE`] on S3.
fn gc_min_age(local: Duration) -> Duration {
    if on_s3() { S3_MIN_AGE } else { local }
}

/// Makes blobs `ids` `age` old: their files' modification times set back, or on S3 a wait past
/// [`S3_MIN_AGE`] (every blob of the store ages then; `LastModified` has 1 s resolution).
async fn age_blobs(store: &Store, ids: &[&String], age: Duration) {
    if on_s3() {
        tokio::time::sleep(S3_MIN_AGE + Duration::from_millis(1500)).await;
        return;
    }
    for id in ids {
        std::fs::File::options()
            .write(true)
            .open(store.blobs().path(id).expect("blob"))
            .expect("open")
            .set_modified(std::time::SystemTime::now() - age)
            .expect("set mtime");
    }
}

fn pinned(store: &Store, bytes: &[u8]) -> PinnedBlob {
    let mut tmp = store.blobs().temp_file().expect("temp");
    std::io::Write::write_all(&mut tmp, bytes).expect("write");
    store.blobs().commit_pinned(tmp).expect("commit")
}

#[tokio::test]
async fn a_failed_insert_discards_its_blobs_but_not_anyone_elses() {
    let (_dir, store) = setup().await;
    let kept = original(&store).await;

    // Unreferenced and pinned by the caller alone (twice: scene and cameras alike): removed.
    let a = pinned(&store, b"a rejected upload");
    let a2 = pinned(&store, b"a rejected upload");
    let b = pinned(&store, b"its cameras");
    let (ida, idb) = (a.blob().sha256.clone(), b.blob().sha256.clone());
    assert!(store.blobs().is_pinned(&ida));
    assert_eq!(
        store
            .discard_unreferenced(vec![a, a2, b])
            .await
            .expect("discard"),
        2
    );
    for id in [&ida, &idb] {
        assert!(matches!(store.blobs().path(id), Err(StoreError::NotFound)));
        assert!(!store.blobs().is_pinned(id));
    }

    // Referenced by an asset: kept.
    let c = pinned(&store, b"original scene bytes");
    assert_eq!(c.blob().sha256, kept.sha256);
    assert_eq!(
        store.discard_unreferenced(vec![c]).await.expect("discard"),
        0
    );
    store.blobs().path(&kept.sha256).expect("kept");

    // Pinned by a concurrent upload of the same bytes too: kept for it, and the garbage
    // collector leaves it alone while it is pinned, however old.
    let d = pinned(&store, b"uploaded twice at once");
    let other = pinned(&store, b"uploaded twice at once");
    let id = d.blob().sha256.clone();
    assert_eq!(
        store.discard_unreferenced(vec![d]).await.expect("discard"),
        0
    );
    store
        .blobs()
        .path(&id)
        .expect("still there for the other upload");
    age_blobs(&store, &[&id], Duration::from_secs(7 * 24 * 3600)).await;
    let min_age = gc_min_age(LONG);
    assert_eq!(store.collect_garbage(min_age).await.expect("gc").removed, 0);
    drop(other);
    assert_eq!(store.collect_garbage(min_age).await.expect("gc").removed, 1);
}

#[tokio::test]
async fn garbage_collection_removes_old_unreferenced_blobs_only() {
    let (dir, store) = setup().await;
    let day = gc_min_age(Duration::from_secs(24 * 3600));
    let kept = original(&store).await;
    let cams = store.blobs().put_bytes(b"cameras").expect("blob");
    let mut with_cams = new_original(&store, b"scene with cameras");
    with_cams.cameras_blob = Some(cams.clone());
    with_cams.cameras_format = Some("inria".into());
    store
        .insert_asset(with_cams, entry("asset.upload"))
        .await
        .expect("insert");
    let orphan = store.blobs().put_bytes(b"a failed publish").expect("blob");
    let young = store.blobs().put_bytes(b"being published").expect("blob");
    age_blobs(
        &store,
        &[&kept.sha256, &cams.sha256, &orphan.sha256, &young.sha256],
        2 * day,
    )
    .await;
    // Committing bytes that are already there makes the blob young again.
    assert_eq!(
        store.blobs().put_bytes(b"being published").expect("blob"),
        young
    );

    let r = store.collect_garbage(day).await.expect("gc");
    assert_eq!(
        r,
        GcReport {
            scanned: 5,
            removed: 1,
            bytes: orphan.size
        }
    );
    assert!(matches!(
        store.blobs().path(&orphan.sha256),
        Err(StoreError::NotFound)
    ));
    for id in [&kept.sha256, &cams.sha256, &young.sha256] {
        store.blobs().path(id).expect("kept");
    }
    assert_eq!(
        scalar(&dir, "SELECT COUNT(*) FROM audit WHERE action = 'blob.gc'").await,
        1
    );
    // Nothing left to do: no second audit row.
    assert_eq!(store.collect_garbage(day).await.expect("gc").removed, 0);
    assert_eq!(
        scalar(&dir, "SELECT COUNT(*) FROM audit WHERE action = 'blob.gc'").await,
        1
    );
    assert!(store.verify_audit_chain().await.expect("chain").ok);
}

#[tokio::test]
async fn bad_blob_ids_are_rejected() {
    let (_dir, store) = setup().await;
    let good = store.blobs().put_bytes(b"x").expect("put");
    for bad in [
        "../../etc/passwd",
        "",
        &good.sha256[..63],
        &good.sha256.to_uppercase(),
        &format!("{}/", &good.sha256[..63]),
    ] {
        assert!(
            matches!(store.blobs().path(bad), Err(StoreError::Invalid(_))),
            "{bad:?}"
        );
        assert!(
            matches!(store.blobs().read(bad), Err(StoreError::Invalid(_))),
            "{bad:?}"
        );
    }
    let missing = "0".repeat(64);
    assert!(matches!(
        store.blobs().path(&missing),
        Err(StoreError::NotFound)
    ));
    assert!(matches!(
        store.blobs().read(&missing),
        Err(StoreError::NotFound)
    ));
}

#[tokio::test]
async fn stale_temp_files_are_removed_at_open_and_fresh_ones_kept() {
    let dir = tempfile::tempdir().expect("tempdir");
    let key = MasterKey::generate();
    let store = open_in(dir.path(), key.clone()).await.expect("open");
    let old = store
        .blobs()
        .temp_file()
        .expect("tmp")
        .keep()
        .expect("keep")
        .1;
    let young = store
        .blobs()
        .temp_file()
        .expect("tmp")
        .keep()
        .expect("keep")
        .1;
    let two_days = std::time::SystemTime::now() - Duration::from_secs(48 * 3600);
    std::fs::File::options()
        .write(true)
        .open(&old)
        .expect("open")
        .set_modified(two_days)
        .expect("set mtime");
    store.close().await;
    open_in(dir.path(), key).await.expect("reopen");
    assert!(!old.exists(), "stale temp file removed");
    assert!(young.exists(), "fresh temp file kept");
}

#[tokio::test]
async fn a_blob_larger_than_the_multipart_threshold_round_trips() {
    let (_dir, store) = setup().await;
    let mut rng = crate::scene::synthetic::Rng::new(42);
    // Two parts and a bit on S3 (8 MiB parts above the tests' 1 MiB threshold).
    let n = 2 * s3::DEFAULT_PART_SIZE as usize + 12_345;
    let big: Vec<u8> = (0..n.div_ceil(8))
        .flat_map(|_| rng.next_u64().to_le_bytes())
        .take(n)
        .collect();
    let blobs = store.blobs().clone();
    let a = blobs.put_bytes(&big).expect("put");
    assert_eq!(a.size, n as u64);
    assert_eq!(
        a.sha256,
        hex::encode(<sha2::Sha256 as sha2::Digest>::digest(&big))
    );
    assert_eq!(blobs.size_of(&a.sha256).expect("size"), a.size);
    assert!(blobs.read(&a.sha256).expect("read") == big);
    if let Some(remote) = blobs.remote() {
        // A multipart object's ETag is "MD5-OF-PART-MD5S-PARTS".
        let (_, etag) = remote.meta(&a.sha256).expect("head").expect("stored");
        let etag = etag.unwrap_or_default();
        assert!(etag.trim_matches('"').ends_with("-3"), "{etag}");
    }
    // Again: the same blob, stored once.
    assert_eq!(blobs.put_bytes(&big).expect("put again"), a);
    let listed = blobs.list().expect("list");
    assert_eq!(listed.iter().filter(|b| b.id == a.sha256).count(), 1);
    assert_eq!(
        listed.iter().find(|b| b.id == a.sha256).map(|b| b.size),
        Some(a.size)
    );
}

/// `SKIPPED:` for a test that needs the S3 test server.
fn skip_without_s3(test: &str) -> bool {
    if on_s3() {
        return false;
    }
    eprintln!("SKIPPED: {test} needs an S3 server (SPLATMARK_TEST_S3; scripts/test.sh starts one)");
    true
}

#[tokio::test]
async fn a_corrupted_object_is_a_typed_error_and_never_cached() {
    if skip_without_s3("a_corrupted_object_is_a_typed_error_and_never_cached") {
        return;
    }
    let (dir, store) = setup().await;
    let blobs = store.blobs().clone();
    let truth = b"the true bytes of a scene".to_vec();
    let a = blobs.put_bytes(&truth).expect("put");
    let remote = blobs.remote().expect("on S3");
    let cached = dir
        .path()
        .join("blobs/cache")
        .join(&a.sha256[..2])
        .join(&a.sha256[2..]);
    // Behind the store's back: other bytes of the same size, then of another size.
    for wrong in [truth.to_ascii_uppercase(), b"short".to_vec()] {
        remote.put_raw(&a.sha256, wrong).expect("overwrite");
        let e = blobs.path(&a.sha256).expect_err("corrupt");
        assert!(matches!(e, StoreError::BlobCorrupt(_)), "{e}");
        assert!(e.to_string().contains(&a.sha256), "{e}");
        assert!(matches!(
            blobs.read(&a.sha256),
            Err(StoreError::BlobCorrupt(_))
        ));
        assert!(!cached.exists(), "nothing cached");
        let staged = std::fs::read_dir(dir.path().join("blobs/tmp"))
            .expect("tmp")
            .count();
        assert_eq!(staged, 0, "the download's temp file is gone");
    }
    // The true bytes back: read, verified and cached.
    remote.put_raw(&a.sha256, truth.clone()).expect("restore");
    assert_eq!(blobs.read(&a.sha256).expect("read"), truth);
    assert_eq!(std::fs::read(&cached).expect("cached"), truth);
    // A cached copy of the wrong size (a crash mid-write) is fetched again.
    std::fs::write(&cached, b"trunc").expect("truncate");
    assert_eq!(blobs.read(&a.sha256).expect("read"), truth);
}

#[tokio::test]
async fn the_read_cache_stays_within_its_bound_and_evicted_blobs_read_again() {
    if skip_without_s3("the_read_cache_stays_within_its_bound_and_evicted_blobs_read_again") {
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let BlobConfig::S3 { url, mut options } = test_blobs(dir.path()) else {
        unreachable!("on S3")
    };
    let (a_bytes, b_bytes) = (vec![1u8; 3000], vec![2u8; 4000]);
    options.cache_max_bytes = 6000;
    let config = BlobConfig::S3 { url, options };
    tokio::task::spawn_blocking(move || {
        let blobs = BlobStore::open_with(dir.path().join("blobs"), &config).expect("open");
        let a = blobs.put_bytes(&a_bytes).expect("put a");
        let b = blobs.put_bytes(&b_bytes).expect("put b");
        let cached = |id: &str| dir.path().join("blobs/cache").join(&id[..2]).join(&id[2..]);
        assert_eq!(blobs.read(&a.sha256).expect("read a"), a_bytes);
        assert!(cached(&a.sha256).exists());
        // a was last used two hours ago; reading b takes the cache past 6 000 bytes.
        std::fs::File::options()
            .write(true)
            .open(cached(&a.sha256))
            .expect("cached a")
            .set_modified(std::time::SystemTime::now() - std::time::Duration::from_secs(7200))
            .expect("age");
        assert_eq!(blobs.read(&b.sha256).expect("read b"), b_bytes);
        assert!(
            !cached(&a.sha256).exists(),
            "the least recently used copy went"
        );
        assert!(cached(&b.sha256).exists(), "the one just read stays");
        // An evicted blob is fetched and verified again.
        assert_eq!(blobs.read(&a.sha256).expect("read a again"), a_bytes);
        assert!(cached(&a.sha256).exists());
    })
    .await
    .expect("blocking");
}

#[tokio::test]
async fn replicas_share_the_bucket_and_one_collector_serves_all() {
    if skip_without_s3("replicas_share_the_bucket_and_one_collector_serves_all") {
        return;
    }
    // Two stores on one database and one bucket prefix, each with its own data folder: two
    // replicas.
    let (dir1, dir2) = (
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
    );
    let key = MasterKey::generate();
    let one = open_in(dir1.path(), key.clone()).await.expect("open");
    let db = test_database(dir1.path()).await;
    let two = Store::open_with_blobs(dir2.path(), &db, &test_blobs(dir1.path()), key)
        .await
        .expect("open the second replica");

    // Uploaded through one, read (verified) through the other; referenced by an asset row.
    let kept = one
        .insert_asset(new_original(&one, b"shared scene"), entry("asset.upload"))
        .await
        .expect("insert");
    assert_eq!(
        two.blobs().read(&kept.sha256).expect("read"),
        b"shared scene"
    );
    let orphan = one.blobs().put_bytes(b"a failed publish").expect("put");
    let young = one.blobs().put_bytes(b"being published").expect("put");
    assert_eq!(
        two.blobs().read(&orphan.sha256).expect("read"),
        b"a failed publish"
    );
    let remote = one.blobs().remote().expect("on S3");
    let (before, _) = remote.meta(&young.sha256).expect("head").expect("stored");
    age_blobs(&one, &[], S3_MIN_AGE).await;
    // The other replica commits the same bytes again: the object is touched, young again.
    assert_eq!(
        two.blobs().put_bytes(b"being published").expect("put"),
        young
    );
    let (after, _) = remote.meta(&young.sha256).expect("head").expect("stored");
    assert!(after > before, "LastModified {before:?} → {after:?}");

    let r = one.collect_garbage(S3_MIN_AGE).await.expect("gc");
    assert_eq!((r.scanned, r.removed, r.bytes), (3, 1, orphan.size));
    // Gone for both replicas, the other's cached copy included.
    for s in [&one, &two] {
        assert!(matches!(
            s.blobs().path(&orphan.sha256),
            Err(StoreError::NotFound)
        ));
    }
    let cached2 = dir2
        .path()
        .join("blobs/cache")
        .join(&orphan.sha256[..2])
        .join(&orphan.sha256[2..]);
    assert!(!cached2.exists());
    for id in [&kept.sha256, &young.sha256] {
        two.blobs().path(id).expect("kept");
    }
    // The second replica's collector finds nothing more to do.
    assert_eq!(
        two.collect_garbage(S3_MIN_AGE).await.expect("gc").removed,
        0
    );
    assert!(one.verify_audit_chain().await.expect("chain").ok);
}

#[tokio::test]
async fn s3_credentials_never_print() {
    if skip_without_s3("s3_credentials_never_print") {
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let BlobConfig::S3 { url, mut options } = test_blobs(dir.path()) else {
        unreachable!("on S3")
    };
    let real = options.secret_access_key.clone().expect("secret");
    let store = open_in(dir.path(), MasterKey::generate())
        .await
        .expect("open");
    store.blobs().put_bytes(b"x").expect("put");
    let shown = format!("{store:?} {:?} {}", store.blobs(), store.blobs().describe());
    assert!(!shown.contains(real.expose()), "{shown}");

    // A wrong secret: refused at open, and no message repeats it.
    let wrong = "wrong-secret-hunter2-0123456789";
    options.secret_access_key = Some(Secret::new(wrong));
    let bad = BlobConfig::S3 { url, options };
    let b = BlobStore::open_with(dir.path().join("other"), &bad).expect("client");
    let e = b.check().expect_err("wrong credentials are refused");
    let db = test_database(dir.path()).await;
    let e2 = Store::open_with_blobs(dir.path(), &db, &bad, MasterKey::generate())
        .await
        .expect_err("refused at open");
    let shown = format!("{e} {e:?} {e2} {e2:?} {b:?} {bad:?}");
    assert!(
        !shown.contains(wrong) && !shown.contains(real.expose()),
        "{shown}"
    );
}

// ---- master key and keys at rest -----------------------------------------------------------

#[tokio::test]
async fn master_key_roundtrip_and_wrong_key_fails() {
    let k = MasterKey::generate();
    let hex = k.to_hex();
    assert_eq!(hex.len(), 64);
    assert_eq!(MasterKey::from_hex(&hex).expect("parse").to_hex(), hex);
    assert_eq!(format!("{k:?}"), "MasterKey(***)");
    assert!(matches!(
        MasterKey::from_hex("zz"),
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        MasterKey::from_hex(&hex[..62]),
        Err(StoreError::Invalid(_))
    ));

    let c1 = crypto::Cipher::new(&k);
    let c2 = crypto::Cipher::new(&MasterKey::generate());
    let msg = message(48, 3);
    let sealed = c1.seal_bits(&msg, b"asset-1").expect("seal");
    assert_eq!(
        c1.open_bits(&sealed.nonce, &sealed.ciphertext, b"asset-1")
            .expect("open"),
        msg
    );
    assert!(matches!(
        c2.open_bits(&sealed.nonce, &sealed.ciphertext, b"asset-1"),
        Err(StoreError::Crypto)
    ));
    assert!(matches!(
        c1.open_bits(&sealed.nonce, &sealed.ciphertext, b"asset-2"),
        Err(StoreError::Crypto)
    ));

    // A store refuses to open under another master key.
    let dir = tempfile::tempdir().expect("tempdir");
    drop(open_in(dir.path(), k.clone()).await.expect("first open"));
    assert!(matches!(
        open_in(dir.path(), MasterKey::generate()).await,
        Err(StoreError::Crypto)
    ));
    open_in(dir.path(), k)
        .await
        .expect("reopen with the right key");
}

#[tokio::test]
async fn master_key_file_is_created_0600_and_reloaded() {
    if std::env::var_os(MASTER_KEY_ENV).is_some() {
        eprintln!("SKIPPED: {MASTER_KEY_ENV} is set");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("conf/master.key");
    let k1 = MasterKey::load_or_create(&file).expect("create");
    let k2 = MasterKey::load_or_create(&file).expect("load");
    assert_eq!(k1.to_hex(), k2.to_hex());
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&file).expect("meta").permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
    }
    std::fs::write(&file, "not hex").expect("write");
    assert!(matches!(
        MasterKey::load_or_create(&file),
        Err(StoreError::Invalid(_))
    ));
}

#[tokio::test]
async fn messages_are_never_stored_in_plaintext() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let msg = message(64, 99);
    let c = enqueue_and_claim(&store, a.id, &msg).await;
    let wm = publish(&store, &c, &records(10)).await.expect("publish");
    assert_eq!(store.key_of(wm.id).await.expect("key"), Some(c.key.clone()));

    // Neither the message, nor the mask, nor the payload is in any file in any encoding.
    let bytes = stored_bytes(&dir).await;
    assert!(bytes.len() > 1024, "the stored bytes were read");
    for secret in [&msg, &c.key.mask, &c.key.payload()] {
        let ascii = crypto::bits_to_ascii(secret);
        let packed: Vec<u8> = secret
            .chunks(8)
            .map(|b| b.iter().fold(0u8, |acc, &x| acc << 1 | u8::from(x)))
            .collect();
        let hex_lower = hex::encode(&packed);
        let hex_upper = hex_lower.to_uppercase();
        for needle in [
            &ascii[..],
            &packed[..],
            hex_lower.as_bytes(),
            hex_upper.as_bytes(),
        ] {
            assert!(
                !contains(&bytes, needle),
                "a secret found in the database files"
            );
        }
    }
    // Sanity of the grep itself: the owner name is there in plaintext.
    assert!(contains(&bytes, b"alice"));
}

#[tokio::test]
async fn tampered_key_ciphertext_is_a_crypto_error() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store
        .claim("w1", LONG)
        .await
        .expect("claim")
        .expect("a job");
    let wm = publish(&store, &c, &records(10)).await.expect("publish");
    let mut conn = raw(&dir).await;
    tamper_byte(&mut conn, "ciphertext").await;
    assert!(matches!(store.key_of(wm.id).await, Err(StoreError::Crypto)));
    assert!(matches!(store.all_keys().await, Err(StoreError::Crypto)));
}

#[tokio::test]
async fn an_asset_reference_is_registered_sealed_and_checked() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let bits = c.key.bits();
    let publish_with = |reference: Vec<f32>| {
        let store = &store;
        let c = &c;
        async move {
            store
                .publish_result(
                    c.job.id,
                    c.lease_token,
                    watermarked(store, a.id, 10, b"w"),
                    &c.key,
                    &Readout {
                        reference: Some(reference.clone()),
                        ..Readout::default()
                    },
                    &records(10),
                    serde_json::Value::Null,
                    entry("watermark.publish"),
                )
                .await
        }
    };
    // One logit per bit, all finite, or nothing is written and the job keeps running.
    for bad in [vec![0.5; bits - 1], {
        let mut r = vec![0.5; bits];
        r[1] = f32::NAN;
        r
    }] {
        let r = publish_with(bad).await;
        assert!(matches!(r, Err(StoreError::Invalid(_))), "{r:?}");
    }
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 0);
    let reference: Vec<f32> = (0..bits).map(|i| i as f32 * 0.25 - 1.0).collect();
    let wm = publish_with(reference.clone()).await.expect("publish");
    let reg = store
        .registration(wm.id)
        .await
        .expect("read")
        .expect("registered");
    assert_eq!((reg.asset_id, &reg.key), (wm.id, &c.key));
    assert_eq!(reg.reference.as_deref(), Some(&reference[..]));
    let all = store.registrations().await.expect("all");
    assert_eq!(all.len(), 1);
    assert_eq!(all[0].reference, Some(reference));
    // Sealed; a key without a reference (every row before migration 0003) reads as none.
    let reg = sealed_column_is_checked(&dir, &store, wm.id, "reference").await;
    assert_eq!(reg.reference, None);
}

/// A matched head over 4 pooled features for `bits` bits.
fn test_head(bits: usize) -> crate::decoder::projection::ViewProjection {
    crate::decoder::projection::ViewProjection {
        mean: vec![0.1, 0.2, 0.3, 0.4],
        basis: Vec::new(),
        explained: 0.0,
        head: Some((0..4 * bits).map(|i| (i % 7) as f32 - 3.0).collect()),
    }
}

#[tokio::test]
async fn a_matched_head_is_registered_sealed_and_checked() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let bits = c.key.bits();
    let publish_with = |head: crate::decoder::projection::ViewProjection| {
        let store = &store;
        let c = &c;
        async move {
            store
                .publish_result(
                    c.job.id,
                    c.lease_token,
                    watermarked(store, a.id, 10, b"w"),
                    &c.key,
                    &Readout {
                        head: Some(head.clone()),
                        ..Readout::default()
                    },
                    &records(10),
                    serde_json::Value::Null,
                    entry("watermark.publish"),
                )
                .await
        }
    };
    // A head for another length, a projection without a head, a non-finite value: nothing is
    // written and the job keeps running.
    let mut nan = test_head(bits);
    nan.mean[2] = f32::NAN;
    for bad in [
        test_head(bits + 1),
        crate::decoder::projection::ViewProjection {
            head: None,
            ..test_head(bits)
        },
        nan,
    ] {
        let r = publish_with(bad).await;
        assert!(matches!(r, Err(StoreError::Invalid(_))), "{r:?}");
    }
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 0);
    let head = test_head(bits);
    let wm = publish_with(head.clone()).await.expect("publish");
    let reg = store
        .registration(wm.id)
        .await
        .expect("read")
        .expect("registered");
    assert_eq!((reg.reference, reg.head.as_ref()), (None, Some(&head)));
    // Sealed; a key without a head (every row before migration 0004) reads as none.
    let reg = sealed_column_is_checked(&dir, &store, wm.id, "head").await;
    assert_eq!(reg.head, None);
}

/// A decoder digest (any 64 lowercase hex digits).
const TEST_DECODER: &str = "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef";

#[tokio::test]
async fn the_decoder_digest_is_registered_sealed_and_checked() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let publish_with = |decoder: &str| {
        let store = &store;
        let c = &c;
        let readout = Readout {
            decoder: Some(decoder.to_string()),
            ..Readout::default()
        };
        async move {
            store
                .publish_result(
                    c.job.id,
                    c.lease_token,
                    watermarked(store, a.id, 10, b"w"),
                    &c.key,
                    &readout,
                    &records(10),
                    serde_json::Value::Null,
                    entry("watermark.publish"),
                )
                .await
        }
    };
    // Not a digest: nothing is written and the job keeps running.
    for bad in [
        "",
        "0123",
        &TEST_DECODER.to_uppercase(),
        &format!("{TEST_DECODER}0"),
    ] {
        let r = publish_with(bad).await;
        assert!(matches!(r, Err(StoreError::Invalid(_))), "{bad:?}: {r:?}");
    }
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 0);
    let wm = publish_with(TEST_DECODER).await.expect("publish");
    let reg = store
        .registration(wm.id)
        .await
        .expect("read")
        .expect("registered");
    assert_eq!(reg.decoder.as_deref(), Some(TEST_DECODER));
    // Sealed; a key registered before migration 0006 reads as none.
    let reg = sealed_column_is_checked(&dir, &store, wm.id, "decoder").await;
    assert_eq!(reg.decoder, None);
}

#[tokio::test]
async fn rotating_the_master_key_reseals_everything_and_the_old_key_opens_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let old = MasterKey::generate();
    let store = open_in(dir.path(), old.clone()).await.expect("open");
    // A registered key with its mask and reference, and a job still queued.
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let reference: Vec<f32> = (0..c.key.bits()).map(|i| i as f32 * 0.5 - 3.0).collect();
    let head = test_head(c.key.bits());
    let wm = store
        .publish_result(
            c.job.id,
            c.lease_token,
            watermarked(&store, a.id, 10, b"w"),
            &c.key,
            &Readout {
                reference: Some(reference.clone()),
                head: Some(head.clone()),
                decoder: Some(TEST_DECODER.into()),
            },
            &records(10),
            serde_json::Value::Null,
            entry("watermark.publish"),
        )
        .await
        .expect("publish");
    let queued = enqueue(&store, a.id, 3).await;
    let before_bytes = stored_bytes(&dir).await;
    let new = MasterKey::generate();
    // keys: message, mask, reference, head, decoder; jobs: two × (message, mask).
    assert_eq!(
        store.rotate_master_key(&new, "cli").await.expect("rotate"),
        9
    );
    store.close().await;
    assert!(matches!(
        open_in(dir.path(), old).await,
        Err(StoreError::Crypto)
    ));
    let store = open_in(dir.path(), new)
        .await
        .expect("the new key opens it");
    let reg = store
        .registration(wm.id)
        .await
        .expect("read")
        .expect("registered");
    assert_eq!(reg.key, c.key);
    assert_eq!(reg.reference.as_deref(), Some(&reference[..]));
    assert_eq!(reg.head, Some(head));
    assert_eq!(reg.decoder.as_deref(), Some(TEST_DECODER));
    let next = store
        .claim("w2", LONG)
        .await
        .expect("claim")
        .expect("the queued job");
    assert_eq!(next.job.id, queued.id);
    assert_eq!(next.key.bits(), c.key.bits());
    // Every ciphertext changed (fresh nonces), and the rotation is in the audit chain.
    assert_ne!(stored_bytes(&dir).await, before_bytes);
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'master_key.rotate'"
        )
        .await,
        1
    );
    assert!(store.verify_audit_chain().await.expect("chain").ok);
}

#[tokio::test]
async fn every_job_gets_a_secret_random_mask_and_its_result_keeps_it() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    // Two jobs with one message: two independent masks, so two different payloads.
    let msg = message(64, 7);
    let mut keys = Vec::new();
    for _ in 0..2 {
        let c = enqueue_and_claim(&store, a.id, &msg).await;
        assert_eq!(c.key.mask.len(), 64);
        let ones = c.key.mask.iter().filter(|&&b| b).count();
        // 64 fair coins: outside 8..=56 ones with probability < 1e-9.
        assert!((8..=56).contains(&ones), "{ones} ones in the mask");
        keys.push(c);
    }
    assert_ne!(keys[0].key.mask, keys[1].key.mask);
    assert_ne!(keys[0].key.payload(), keys[1].key.payload());
    assert!(
        !format!("{:?}", keys[0].key).contains("true"),
        "Debug hides the key"
    );

    // A worker cannot register another key than its job's.
    let c = &keys[0];
    let other = crate::store::WatermarkKey::unmasked(msg.clone());
    let r = store
        .publish_result(
            c.job.id,
            c.lease_token,
            watermarked(&store, a.id, 10, b"w0"),
            &other,
            &Readout::default(),
            &records(10),
            serde_json::Value::Null,
            entry("watermark.publish"),
        )
        .await;
    assert!(matches!(r, Err(StoreError::Invalid(_))), "{r:?}");
    let wm = publish(&store, c, &records(10)).await.expect("publish");
    assert_eq!(store.key_of(wm.id).await.expect("key"), Some(c.key.clone()));

    // A key stored before masks existed (NULL mask) reads as unmasked: payload = message.
    let mut conn = raw(&dir).await;
    sqlx::query("UPDATE keys SET mask_nonce = NULL, mask_ct = NULL")
        .execute(&mut conn)
        .await
        .expect("legacy row");
    let legacy = store.key_of(wm.id).await.expect("key").expect("a key");
    assert_eq!(legacy.payload(), msg);
    // Half a mask (nonce without ciphertext) or a mask sealed for another row does not open.
    let other_job = keys[1].job.id.to_string();
    sqlx::query(
        "UPDATE keys SET mask_nonce = (SELECT mask_nonce FROM jobs WHERE id = $1), \
         mask_ct = (SELECT mask_ct FROM jobs WHERE id = $2)",
    )
    .bind(&other_job)
    .bind(&other_job)
    .execute(&mut conn)
    .await
    .expect("swap");
    assert!(matches!(store.key_of(wm.id).await, Err(StoreError::Crypto)));
    sqlx::query("UPDATE keys SET mask_ct = NULL")
        .execute(&mut conn)
        .await
        .expect("half");
    assert!(matches!(store.key_of(wm.id).await, Err(StoreError::Crypto)));
}

// ---- assets --------------------------------------------------------------------------------

#[tokio::test]
async fn bad_asset_input_changes_nothing() {
    let (dir, store) = setup().await;
    let good = new_original(&store, b"scene");
    let mut missing = good.clone();
    missing.blob.sha256 = "ab".repeat(32);
    let mut wrong_size = good.clone();
    wrong_size.blob.size += 1;
    let cases = vec![
        NewAsset {
            format: "obj".into(),
            ..good.clone()
        },
        NewAsset {
            owner: String::new(),
            ..good.clone()
        },
        NewAsset {
            sh_degree: 4,
            ..good.clone()
        },
        NewAsset {
            parent_id: Some(Uuid::new_v4()),
            ..good.clone()
        },
        NewAsset {
            cameras_format: Some("inria".into()),
            ..good.clone()
        },
        NewAsset {
            file_name: Some("a\nb".into()),
            ..good.clone()
        },
        missing,
        wrong_size,
    ];
    for (i, bad) in cases.into_iter().enumerate() {
        let r = store.insert_asset(bad, entry("asset.upload")).await;
        assert!(matches!(r, Err(StoreError::Invalid(_))), "case {i}: {r:?}");
    }
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM assets").await, 0);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM audit").await, 0);

    let a = store
        .insert_asset(good, entry("asset.upload"))
        .await
        .expect("insert");
    assert_eq!(store.get_asset(a.id).await.expect("get"), Some(a.clone()));
    assert_eq!(store.get_asset(Uuid::new_v4()).await.expect("get"), None);
    let (rows, _) = store
        .audit_query(&AuditFilter {
            asset_id: Some(a.id),
            ..Default::default()
        })
        .await
        .expect("audit");
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0].action, "asset.upload");
    assert!(time::is_timestamp(&a.created_at));
}

// ---- jobs ----------------------------------------------------------------------------------

#[tokio::test]
async fn enqueue_is_idempotent_and_conflicts_on_another_body() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let j = new_job(a.id, message(32, 1), Some("key-1"), 3);
    let (first, created) = store
        .enqueue(j.clone(), entry("job.enqueue"))
        .await
        .expect("enqueue");
    assert!(created);
    assert_eq!(first.state, JobState::Queued);
    let (again, created) = store
        .enqueue(j.clone(), entry("job.enqueue"))
        .await
        .expect("again");
    assert!(!created);
    assert_eq!(again.id, first.id);
    let found = store
        .job_by_idempotency_key("alice", "key-1")
        .await
        .expect("lookup");
    assert_eq!(found.map(|j| j.id), Some(first.id));

    let other_message = NewJob {
        message: message(32, 2),
        ..j.clone()
    };
    let other_options = NewJob {
        options: serde_json::json!({ "steps": 5 }),
        ..j.clone()
    };
    for bad in [other_message, other_options] {
        let r = store.enqueue(bad, entry("job.enqueue")).await;
        assert!(matches!(r, Err(StoreError::Conflict(_))), "{r:?}");
    }
    // Another owner may use the same key.
    let bob = NewJob {
        owner: "bob".into(),
        ..j.clone()
    };
    let (b, created) = store.enqueue(bob, entry("job.enqueue")).await.expect("bob");
    assert!(created);
    assert_ne!(b.id, first.id);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM jobs").await, 2);
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'job.enqueue'"
        )
        .await,
        2
    );

    // Bad input writes nothing.
    let bad_bits = NewJob {
        bits: 31,
        ..j.clone()
    };
    let unknown_asset = NewJob {
        asset_id: Uuid::new_v4(),
        idempotency_key: None,
        ..j.clone()
    };
    let no_attempts = NewJob {
        max_attempts: 0,
        ..j
    };
    assert!(matches!(
        store.enqueue(bad_bits, entry("x")).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.enqueue(unknown_asset, entry("x")).await,
        Err(StoreError::NotFound)
    ));
    assert!(matches!(
        store.enqueue(no_attempts, entry("x")).await,
        Err(StoreError::Invalid(_))
    ));
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM jobs").await, 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_job_is_claimed_by_one_worker_only() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    const N: usize = 24;
    let mut ids = HashSet::new();
    for _ in 0..N {
        ids.insert(enqueue(&store, a.id, 3).await.id);
    }
    let claimer = |name: &'static str| {
        let store = store.clone();
        tokio::spawn(async move {
            let mut got = Vec::new();
            while let Some(c) = store.claim(name, LONG).await.expect("claim") {
                got.push(c.job.id);
                tokio::task::yield_now().await;
            }
            got
        })
    };
    let (w1, w2) = (claimer("w1"), claimer("w2"));
    let (g1, g2) = (w1.await.expect("w1"), w2.await.expect("w2"));
    let all: Vec<Uuid> = g1.iter().chain(&g2).copied().collect();
    let unique: HashSet<Uuid> = all.iter().copied().collect();
    assert_eq!(
        all.len(),
        N,
        "every job claimed exactly once ({} + {})",
        g1.len(),
        g2.len()
    );
    assert_eq!(unique, ids);
    let counts = store.counts().await.expect("counts");
    assert_eq!(counts.jobs.running, N as u64);
    assert_eq!(counts.jobs.queued, 0);
}

#[tokio::test]
async fn heartbeat_records_progress_and_refuses_a_stale_token() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 3).await;
    assert!(
        store
            .claim("w1", LONG)
            .await
            .expect("claim")
            .is_some_and(|c| c.job.id == job.id)
    );
    let c = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(c.state, JobState::Running);
    assert_eq!(c.attempts, 1);
    let r = store.heartbeat(job.id, Uuid::new_v4(), LONG, None).await;
    assert!(matches!(r, Err(StoreError::LeaseLost)));
}

#[tokio::test]
async fn heartbeat_updates_lease_and_progress() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store
        .claim("w1", Duration::from_secs(1))
        .await
        .expect("claim")
        .expect("job");
    let before = c.job.lease_expires_at.clone().expect("lease");
    let p = ProgressUpdate {
        phase: "finetune".into(),
        step: 40,
        total: 100,
        eta_seconds: Some(12.5),
    };
    store
        .heartbeat(c.job.id, c.lease_token, LONG, Some(&p))
        .await
        .expect("heartbeat");
    let j = store.get_job(c.job.id).await.expect("get").expect("job");
    assert_eq!(j.phase.as_deref(), Some("finetune"));
    assert_eq!((j.step, j.total, j.eta_seconds), (40, 100, Some(12.5)));
    assert!(j.lease_expires_at.expect("lease") > before);
}

#[tokio::test]
async fn expired_lease_is_requeued_then_claimable_and_the_old_token_is_dead() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 3).await;
    // A lease long enough that a loaded CI machine reaches the first check inside it (30 ms
    // was not: the check once ran after the lease had expired).
    let first = store
        .claim("w1", Duration::from_millis(1000))
        .await
        .expect("claim")
        .expect("job");
    assert_eq!(
        store.requeue_expired().await.expect("requeue"),
        0,
        "lease still valid"
    );
    tokio::time::sleep(Duration::from_millis(1300)).await;
    assert_eq!(store.requeue_expired().await.expect("requeue"), 1);
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Queued);
    assert!(
        j.error
            .as_deref()
            .is_some_and(|e| e.contains("lease expired"))
    );
    let second = store
        .claim("w2", LONG)
        .await
        .expect("claim")
        .expect("job again");
    assert_eq!(second.job.id, job.id);
    assert_eq!(second.job.attempts, 2);
    assert_ne!(second.lease_token, first.lease_token);
    let r = store.heartbeat(job.id, first.lease_token, LONG, None).await;
    assert!(matches!(r, Err(StoreError::LeaseLost)));
    assert!(matches!(
        store.fail(job.id, first.lease_token, "late").await,
        Err(StoreError::LeaseLost)
    ));
    store
        .heartbeat(job.id, second.lease_token, LONG, None)
        .await
        .expect("new holder");
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'job.requeue'"
        )
        .await,
        1
    );
}

#[tokio::test]
async fn a_released_job_is_queued_at_once_without_spending_an_attempt() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 1).await;
    let first = store.claim("w1", LONG).await.expect("claim").expect("job");
    assert_eq!(first.job.attempts, 1);
    // Another token cannot release it.
    assert!(matches!(
        store.release(job.id, Uuid::new_v4(), "shutdown").await,
        Err(StoreError::LeaseLost)
    ));
    store
        .release(job.id, first.lease_token, "worker shutdown")
        .await
        .expect("release");
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Queued);
    assert_eq!(j.attempts, 0);
    // The old holder is out; releasing twice is refused.
    assert!(matches!(
        store.heartbeat(job.id, first.lease_token, LONG, None).await,
        Err(StoreError::LeaseLost)
    ));
    assert!(matches!(
        store.release(job.id, first.lease_token, "again").await,
        Err(StoreError::LeaseLost)
    ));
    // Claimable right away, and with max_attempts = 1 it still has its one attempt.
    let second = store.claim("w2", LONG).await.expect("claim").expect("job");
    assert_eq!(second.job.id, job.id);
    assert_eq!(second.job.attempts, 1);
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'job.release'"
        )
        .await,
        1
    );
    // A finished job cannot be released.
    store
        .cancel(job.id, entry("job.cancel"))
        .await
        .expect("cancel");
    assert!(matches!(
        store.release(job.id, second.lease_token, "late").await,
        Err(StoreError::LeaseLost)
    ));
}

#[tokio::test]
async fn expired_lease_on_the_last_attempt_is_dead() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 1).await;
    store
        .claim("w1", Duration::from_millis(20))
        .await
        .expect("claim")
        .expect("job");
    tokio::time::sleep(Duration::from_millis(60)).await;
    assert_eq!(store.requeue_expired().await.expect("requeue"), 1);
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Dead);
    assert!(j.error.is_some());
    assert!(store.claim("w2", LONG).await.expect("claim").is_none());
}

#[tokio::test]
async fn failures_back_off_then_die_keeping_the_error() {
    let (dir, store) = setup().await;
    assert_eq!(jobs::backoff(1), Duration::from_secs(5));
    assert_eq!(jobs::backoff(2), Duration::from_secs(10));
    assert_eq!(jobs::backoff(4), Duration::from_secs(40));
    assert_eq!(jobs::backoff(8), Duration::from_secs(600));
    assert_eq!(jobs::backoff(1000), Duration::from_secs(600));

    let a = original(&store).await;
    let job = enqueue(&store, a.id, 2).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let state = store
        .fail(job.id, c.lease_token, "out of memory")
        .await
        .expect("fail");
    assert_eq!(state, JobState::Failed);
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Failed);
    assert_eq!(j.error.as_deref(), Some("out of memory"));
    assert!(j.not_before > j.updated_at, "backoff in the future");
    assert!(
        store.claim("w1", LONG).await.expect("claim").is_none(),
        "still backing off"
    );
    // The same token cannot fail it twice.
    assert!(matches!(
        store.fail(job.id, c.lease_token, "x").await,
        Err(StoreError::LeaseLost)
    ));

    // Let the backoff pass.
    let mut conn = raw(&dir).await;
    sqlx::query("UPDATE jobs SET not_before = '2000-01-01T00:00:00.000Z'")
        .execute(&mut conn)
        .await
        .expect("rewind");
    let c2 = store
        .claim("w2", LONG)
        .await
        .expect("claim")
        .expect("retry");
    assert_eq!(c2.job.attempts, 2);
    let state = store
        .fail(job.id, c2.lease_token, "out of memory again")
        .await
        .expect("fail");
    assert_eq!(state, JobState::Dead);
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Dead);
    assert_eq!(j.error.as_deref(), Some("out of memory again"));
    sqlx::query("UPDATE jobs SET not_before = '2000-01-01T00:00:00.000Z'")
        .execute(&mut conn)
        .await
        .expect("rewind");
    assert!(
        store.claim("w1", LONG).await.expect("claim").is_none(),
        "dead jobs stay dead"
    );
    assert_eq!(
        scalar(&dir, "SELECT COUNT(*) FROM audit WHERE action = 'job.fail'").await,
        1
    );
    assert_eq!(
        scalar(&dir, "SELECT COUNT(*) FROM audit WHERE action = 'job.dead'").await,
        1
    );
    assert_eq!(store.counts().await.expect("counts").jobs.dead, 1);
}

#[tokio::test]
async fn cancel_queued_and_running_jobs() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    let queued = enqueue(&store, a.id, 3).await;
    let cancelled = store
        .cancel(queued.id, entry("job.cancel"))
        .await
        .expect("cancel");
    assert_eq!(cancelled.state, JobState::Cancelled);
    assert!(store.claim("w1", LONG).await.expect("claim").is_none());
    // Idempotent.
    assert_eq!(
        store
            .cancel(queued.id, entry("job.cancel"))
            .await
            .expect("again")
            .state,
        JobState::Cancelled
    );

    let running = enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    assert_eq!(c.job.id, running.id);
    store
        .cancel(running.id, entry("job.cancel"))
        .await
        .expect("cancel running");
    let r = store.heartbeat(running.id, c.lease_token, LONG, None).await;
    assert!(matches!(r, Err(StoreError::LeaseLost)));
    assert!(matches!(
        publish(&store, &c, &records(10)).await,
        Err(StoreError::LeaseLost)
    ));

    let done = enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    publish(&store, &c, &records(10)).await.expect("publish");
    let r = store.cancel(done.id, entry("job.cancel")).await;
    assert!(matches!(r, Err(StoreError::Conflict(_))), "{r:?}");
    let r = store.cancel(Uuid::new_v4(), entry("job.cancel")).await;
    assert!(matches!(r, Err(StoreError::NotFound)));
}

// ---- publish -------------------------------------------------------------------------------

#[tokio::test]
async fn publish_result_is_exactly_once() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let recs = records(30);
    let wm = publish(&store, &c, &recs).await.expect("publish");
    assert_eq!(wm.kind, AssetKind::Watermarked);
    assert_eq!(wm.parent_id, Some(a.id));
    assert_eq!(wm.source_job_id, Some(job.id));
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Done);
    assert_eq!(j.result_asset_id, Some(wm.id));
    assert_eq!(j.lease_expires_at, None);

    // Again with the same token: nothing duplicated.
    assert!(matches!(
        publish(&store, &c, &recs).await,
        Err(StoreError::LeaseLost)
    ));
    assert!(matches!(
        store.heartbeat(job.id, c.lease_token, LONG, None).await,
        Err(StoreError::LeaseLost)
    ));
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM assets").await, 2);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 1);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM attribution").await, 30);
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'watermark.publish'"
        )
        .await,
        1
    );
    assert_eq!(store.watermarked_of(a.id).await.expect("wm").len(), 1);
    assert_eq!(store.key_of(wm.id).await.expect("key"), Some(c.key.clone()));
    assert_eq!(store.key_of(a.id).await.expect("key"), None);
    let all = store.all_keys().await.expect("all");
    assert_eq!(all, vec![(wm.id, c.key.clone())]);
    assert_eq!(
        store.report_of(wm.id).await.expect("report"),
        Some(serde_json::json!({ "psnr": 41.5 }))
    );
    assert_eq!(store.report_of(a.id).await.expect("report"), None);
    let counts = store.counts().await.expect("counts");
    assert_eq!(
        (counts.assets, counts.watermarked, counts.jobs.done),
        (2, 1, 1)
    );
}

#[tokio::test]
async fn publish_after_the_lease_was_lost_writes_nothing() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let slow = store
        .claim("slow", Duration::from_millis(20))
        .await
        .expect("claim")
        .expect("job");
    tokio::time::sleep(Duration::from_millis(60)).await;
    assert_eq!(store.requeue_expired().await.expect("requeue"), 1);
    // Lost before anyone re-claimed it...
    assert!(matches!(
        publish(&store, &slow, &records(10)).await,
        Err(StoreError::LeaseLost)
    ));
    let fast = store
        .claim("fast", LONG)
        .await
        .expect("claim")
        .expect("job");
    // ...and after.
    assert!(matches!(
        publish(&store, &slow, &records(10)).await,
        Err(StoreError::LeaseLost)
    ));
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM assets").await, 1);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 0);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM attribution").await, 0);
    let wm = publish(&store, &fast, &records(10))
        .await
        .expect("the holder publishes");
    assert_eq!(store.watermarked_of(a.id).await.expect("wm"), vec![wm]);
}

#[tokio::test]
async fn a_publish_failing_half_way_rolls_back_everything() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let job = enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let mut recs = records(600);
    recs[599].index = 3; // duplicate index: fails in the second INSERT batch
    let r = publish(&store, &c, &recs).await;
    assert!(matches!(r, Err(StoreError::Conflict(_))), "{r:?}");
    let short = NewAsset {
        gaussians: 11,
        ..watermarked(&store, a.id, 11, b"w")
    };
    let r = store
        .publish_result(
            job.id,
            c.lease_token,
            short,
            &c.key,
            &Readout::default(),
            &records(10),
            serde_json::Value::Null,
            entry("watermark.publish"),
        )
        .await;
    assert!(matches!(r, Err(StoreError::Invalid(_))), "{r:?}");
    let r = store
        .publish_result(
            job.id,
            c.lease_token,
            watermarked(&store, a.id, 10, b"w"),
            &crate::store::WatermarkKey {
                message: c.key.message[..31].to_vec(),
                mask: c.key.mask[..31].to_vec(),
            },
            &Readout::default(),
            &records(10),
            serde_json::Value::Null,
            entry("watermark.publish"),
        )
        .await;
    assert!(matches!(r, Err(StoreError::Invalid(_))), "{r:?}");
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM assets").await, 1);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM keys").await, 0);
    assert_eq!(scalar(&dir, "SELECT COUNT(*) FROM attribution").await, 0);
    let j = store.get_job(job.id).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Running);
    publish(&store, &c, &records(600))
        .await
        .expect("a correct publish still works");
}

// ---- attribution ---------------------------------------------------------------------------

#[tokio::test]
async fn attribution_roundtrips_exactly_pages_and_summarises() {
    let (_dir, store) = setup().await;
    let a = original(&store).await;
    enqueue(&store, a.id, 3).await;
    let c = store.claim("w1", LONG).await.expect("claim").expect("job");
    let recs = records(2500);
    let wm = publish(&store, &c, &recs).await.expect("publish");

    let mut got = Vec::new();
    let mut cursor = None;
    let mut pages = 0;
    loop {
        let (page, next) = store
            .attribution_page(wm.id, None, cursor, 1000)
            .await
            .expect("page");
        pages += 1;
        got.extend(page);
        match next {
            Some(n) => cursor = Some(n),
            None => break,
        }
    }
    assert_eq!(pages, 3);
    assert_eq!(got.len(), recs.len());
    for (g, r) in got.iter().zip(&recs) {
        assert_eq!(bits_of(g), bits_of(r), "record {}", r.index);
    }
    assert!(got[7].utility.is_nan());

    let carriers: Vec<&AttributionRecord> =
        recs.iter().filter(|r| r.role == Role::Carrier).collect();
    let (p1, next) = store
        .attribution_page(wm.id, Some(Role::Carrier), None, 300)
        .await
        .expect("carriers");
    assert_eq!(p1.len(), 300);
    assert!(p1.iter().all(|r| r.role == Role::Carrier));
    let (p2, end) = store
        .attribution_page(wm.id, Some(Role::Carrier), next, 300)
        .await
        .expect("carriers 2");
    assert_eq!(p1.len() + p2.len(), carriers.len());
    assert_eq!(end, None);
    assert_eq!(p2.last().map(|r| r.index), carriers.last().map(|r| r.index));
    assert!(matches!(
        store.attribution_page(Uuid::new_v4(), None, None, 10).await,
        Err(StoreError::NotFound)
    ));

    let s = store.attribution_summary(wm.id).await.expect("summary");
    let count = |role| recs.iter().filter(|r| r.role == role).count() as u64;
    assert_eq!(s.gaussians, 2500);
    assert_eq!(s.carriers, count(Role::Carrier));
    assert_eq!(s.compensators, count(Role::Compensator));
    assert_eq!(s.untouched, count(Role::Untouched));
    assert_eq!(
        s.distinct_parents,
        recs.iter().map(|r| r.parent).collect::<HashSet<_>>().len() as u64
    );
    assert_eq!(
        s.feasible,
        recs.iter().filter(|r| r.feasible).count() as u64
    );
    let share: f64 = carriers
        .iter()
        .filter_map(|r| r.wm_grad_share)
        .map(f64::from)
        .sum();
    let got_share = s.carrier_wm_grad_share_sum.expect("share");
    assert!(
        (got_share - share).abs() <= 1e-9 * share.abs().max(1.0),
        "{got_share} vs {share}"
    );
    let mean = |it: Vec<f32>| it.iter().map(|&x| f64::from(x)).sum::<f64>() / it.len() as f64;
    let cu = mean(
        carriers
            .iter()
            .map(|r| r.utility)
            .filter(|x| !x.is_nan())
            .collect(),
    );
    let ov = mean(
        recs.iter()
            .filter(|r| r.role != Role::Carrier)
            .map(|r| r.visibility)
            .collect(),
    );
    assert!((s.carrier_mean_utility.expect("cu") - cu).abs() < 1e-9);
    assert!((s.other_mean_visibility.expect("ov") - ov).abs() < 1e-9);
}

// ---- audit ---------------------------------------------------------------------------------

#[tokio::test]
async fn audit_chain_verifies_and_tampering_is_found() {
    let (dir, store) = setup().await;
    let asset = Uuid::new_v4();
    for i in 0..6 {
        let mut e = entry(if i % 2 == 0 { "verify" } else { "asset.upload" });
        e.asset_id = (i < 3).then_some(asset);
        e.details = serde_json::json!({ "i": i, "nested": { "b": 1, "a": [1, 2] } });
        let row = store.append_audit(e).await.expect("append");
        assert_eq!(row.id, i + 1);
    }
    let rep = store.verify_audit_chain().await.expect("verify");
    assert!(rep.ok);
    assert_eq!((rep.rows, rep.first_bad_id), (6, None));
    let (rows, _) = store
        .audit_query(&AuditFilter::default())
        .await
        .expect("query");
    assert_eq!(rows[0].prev_hash, GENESIS_HASH);
    assert_eq!(rows[5].hash, rep.head_hash);
    assert!(rows.windows(2).all(|w| w[1].prev_hash == w[0].hash));

    // Filters and paging.
    let f = AuditFilter {
        action: Some("verify".into()),
        limit: 2,
        ..Default::default()
    };
    let (p1, next) = store.audit_query(&f).await.expect("page 1");
    assert_eq!(p1.iter().map(|r| r.id).collect::<Vec<_>>(), vec![1, 3]);
    let (p2, end) = store
        .audit_query(&AuditFilter {
            after_id: next,
            ..f.clone()
        })
        .await
        .expect("page 2");
    assert_eq!(
        (p2.iter().map(|r| r.id).collect::<Vec<_>>(), end),
        (vec![5], None)
    );
    let by_asset = AuditFilter {
        asset_id: Some(asset),
        ..Default::default()
    };
    assert_eq!(
        store.audit_query(&by_asset).await.expect("asset").0.len(),
        3
    );
    let future = AuditFilter {
        since: Some("2999-01-01T00:00:00Z".into()),
        ..Default::default()
    };
    assert!(
        store
            .audit_query(&future)
            .await
            .expect("since")
            .0
            .is_empty()
    );
    let past = AuditFilter {
        until: Some("2000-01-01T00:00:00.000Z".into()),
        ..Default::default()
    };
    assert!(store.audit_query(&past).await.expect("until").0.is_empty());
    let mut huge = entry("verify");
    huge.details = serde_json::json!({ "x": "a".repeat(70_000) });
    assert!(matches!(
        store.append_audit(huge).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.append_audit(entry("")).await,
        Err(StoreError::Invalid(_))
    ));
    let bad = AuditFilter {
        since: Some("yesterday".into()),
        ..Default::default()
    };
    assert!(matches!(
        store.audit_query(&bad).await,
        Err(StoreError::Invalid(_))
    ));

    // The triggers refuse edits and deletions.
    let mut conn = raw(&dir).await;
    for sql in [
        "UPDATE audit SET actor = 'mallory' WHERE id = 3",
        "DELETE FROM audit WHERE id = 6",
    ] {
        let e = sqlx::query(sql).execute(&mut conn).await.expect_err(sql);
        assert!(e.to_string().contains("append-only"), "{e}");
    }
    // Behind the triggers' back: detected, first bad row named.
    drop_trigger(&mut conn, "audit_no_update").await;
    sqlx::query("UPDATE audit SET details = '{\"i\":99}' WHERE id = 3")
        .execute(&mut conn)
        .await
        .expect("tamper");
    let rep = store.verify_audit_chain().await.expect("verify");
    assert!(!rep.ok);
    assert_eq!(rep.first_bad_id, Some(3));
    assert_eq!(rep.rows, 6);
}

#[tokio::test]
async fn audit_chain_detects_a_deleted_row() {
    let (dir, store) = setup().await;
    for _ in 0..4 {
        store.append_audit(entry("verify")).await.expect("append");
    }
    let mut conn = raw(&dir).await;
    drop_trigger(&mut conn, "audit_no_delete").await;
    sqlx::query("DELETE FROM audit WHERE id = 2")
        .execute(&mut conn)
        .await
        .expect("delete");
    let rep = store.verify_audit_chain().await.expect("verify");
    assert_eq!((rep.ok, rep.first_bad_id, rep.rows), (false, Some(3), 3));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_appends_never_fork_the_chain() {
    let (_dir, store) = setup().await;
    let tasks: Vec<_> = (0..4)
        .map(|t| {
            let store = store.clone();
            tokio::spawn(async move {
                for _ in 0..15 {
                    store
                        .append_audit(AuditEntry::new(format!("t{t}"), "verify"))
                        .await
                        .expect("append");
                }
            })
        })
        .collect();
    for t in tasks {
        t.await.expect("task");
    }
    let rep = store.verify_audit_chain().await.expect("verify");
    assert!(rep.ok);
    assert_eq!(rep.rows, 60);
}

/// Writers with pools of their own — as separate processes have, on one SQLite file or one
/// PostgreSQL database — appending to the audit log and claiming jobs at once: the chain
/// stays one line (ids 1..=n, each row linked to the previous) and every job is claimed once.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn writers_with_their_own_pools_keep_one_chain_and_claim_each_job_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let key = MasterKey::generate();
    let first = open_in(dir.path(), key.clone()).await.expect("open");
    let a = original(&first).await;
    let jobs = 12;
    for _ in 0..jobs {
        enqueue(&first, a.id, 3).await;
    }
    let mut handles = vec![first];
    for _ in 0..3 {
        handles.push(open_in(dir.path(), key.clone()).await.expect("open"));
    }
    let tasks: Vec<_> = handles
        .iter()
        .enumerate()
        .map(|(t, store)| {
            let store = store.clone();
            tokio::spawn(async move {
                let mut claimed = Vec::new();
                for i in 0..10 {
                    store
                        .append_audit(AuditEntry::new(format!("w{t}"), "verify"))
                        .await
                        .expect("append");
                    if i % 2 == 0
                        && let Some(c) = store.claim(&format!("w{t}"), LONG).await.expect("claim")
                    {
                        claimed.push(c.job.id);
                    }
                }
                claimed
            })
        })
        .collect();
    let mut claimed = Vec::new();
    for t in tasks {
        claimed.extend(t.await.expect("task"));
    }
    let distinct: HashSet<_> = claimed.iter().collect();
    assert_eq!(claimed.len(), jobs, "every job claimed, and only once");
    assert_eq!(distinct.len(), jobs);
    let rep = handles[2].verify_audit_chain().await.expect("verify");
    assert!(rep.ok, "{rep:?}");
    // Upload, 12 enqueues, 40 appends and 12 claims.
    assert_eq!(rep.rows, 1 + 12 + 40 + 12);
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'job.claim'"
        )
        .await,
        12
    );
}

// ---- verifications -------------------------------------------------------------------------

#[tokio::test]
async fn verifications_are_recorded_with_their_audit_row() {
    let (dir, store) = setup().await;
    let a = original(&store).await;
    let v = NewVerification {
        actor: "key-1".into(),
        asset_id: Some(a.id),
        images: 2,
        image_sha256: vec!["a".repeat(64), "b".repeat(64)],
        result: serde_json::json!({ "decision": "watermarked", "p_value": 1e-9 }),
    };
    let (vid, audit_id) = store
        .record_verification(v.clone(), entry("verify"))
        .await
        .expect("record");
    let (rows, _) = store
        .audit_query(&AuditFilter {
            action: Some("verify".into()),
            ..Default::default()
        })
        .await
        .expect("audit");
    assert_eq!(
        rows.iter().map(|r| (r.id, r.asset_id)).collect::<Vec<_>>(),
        vec![(audit_id, Some(a.id))]
    );
    let mut conn = raw(&dir).await;
    let stored: String = sqlx::query_scalar("SELECT id FROM verifications")
        .fetch_one(&mut conn)
        .await
        .expect("row");
    assert_eq!(stored, vid.to_string());
    assert_eq!(store.counts().await.expect("counts").verifications, 1);

    let bad = NewVerification {
        image_sha256: vec!["../x".into()],
        ..v.clone()
    };
    assert!(matches!(
        store.record_verification(bad, entry("verify")).await,
        Err(StoreError::Invalid(_))
    ));
    let unknown = NewVerification {
        asset_id: Some(Uuid::new_v4()),
        ..v
    };
    assert!(matches!(
        store.record_verification(unknown, entry("verify")).await,
        Err(StoreError::NotFound)
    ));
    assert_eq!(store.counts().await.expect("counts").verifications, 1);
    assert_eq!(store.verify_audit_chain().await.expect("chain").rows, 2);
}

// ---- API keys ------------------------------------------------------------------------------

#[tokio::test]
async fn api_keys_authenticate_revoke_and_store_only_the_hash() {
    let (dir, store) = setup().await;
    assert_eq!(store.api_key_count().await.expect("count"), 0);
    let (key, token) = store
        .create_api_key("cli", "ci", &[Scope::Verifier, Scope::Owner, Scope::Owner])
        .await
        .expect("create");
    assert!(token.starts_with(TOKEN_PREFIX) && token.len() == 68);
    assert_eq!(key.scopes, vec![Scope::Owner, Scope::Verifier]);
    assert!(key.allows(Scope::Owner) && !key.allows(Scope::Auditor));
    assert_eq!(
        store.authenticate(&token).await.expect("auth"),
        Some(key.clone())
    );
    let mut wrong = token.clone();
    wrong.replace_range(10..11, if &token[10..11] == "0" { "1" } else { "0" });
    for bad in [
        wrong.as_str(),
        "",
        "smk_",
        "Bearer x",
        &token.to_uppercase(),
    ] {
        assert_eq!(
            store.authenticate(bad).await.expect("auth"),
            None,
            "{bad:?}"
        );
    }
    let bytes = stored_bytes(&dir).await;
    assert!(
        !contains(&bytes, token.as_bytes()),
        "token stored in plaintext"
    );
    assert!(
        !contains(&bytes, &token.as_bytes()[4..]),
        "token hex stored in plaintext"
    );
    assert!(
        contains(&bytes, api_keys::token_hash(&token).as_bytes()),
        "its hash is"
    );

    assert_eq!("auditor".parse::<Scope>().expect("scope"), Scope::Auditor);
    assert!("root".parse::<Scope>().is_err());
    assert!(store.create_api_key("cli", "x", &[]).await.is_err());
    // Every key that exists was audited once, by whoever created it; a refused one was not.
    assert_eq!(
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'key.create' AND actor = 'cli'",
        )
        .await,
        1
    );
    let audited = || async {
        scalar(
            &dir,
            "SELECT COUNT(*) FROM audit WHERE action = 'key.revoke'",
        )
        .await
    };
    assert!(
        store
            .revoke_api_key(key.id, entry("key.revoke"))
            .await
            .expect("revoke")
    );
    assert_eq!(audited().await, 1);
    let revoked_at = || async {
        let mut c = raw(&dir).await;
        sqlx::query_scalar::<_, String>("SELECT revoked_at FROM api_keys")
            .fetch_one(&mut c)
            .await
            .expect("revoked_at")
    };
    let first = revoked_at().await;
    // Again: nothing changes, no second audit row.
    for _ in 0..3 {
        assert!(
            !store
                .revoke_api_key(key.id, entry("key.revoke"))
                .await
                .expect("revoke again")
        );
    }
    assert_eq!(audited().await, 1);
    assert_eq!(revoked_at().await, first);
    assert_eq!(store.authenticate(&token).await.expect("auth"), None);
    assert!(matches!(
        store
            .revoke_api_key(Uuid::new_v4(), entry("key.revoke"))
            .await,
        Err(StoreError::NotFound)
    ));
    assert_eq!(audited().await, 1);
    assert!(store.verify_audit_chain().await.expect("chain").ok);
    assert_eq!(store.api_key_count().await.expect("count"), 1);
    assert!(store.list_api_keys().await.expect("list")[0].revoked);
}

// ---- database settings ---------------------------------------------------------------------

#[tokio::test]
async fn database_uses_wal_and_foreign_keys() {
    // SQLite's settings, whatever the suite's database.
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path(), MasterKey::generate())
        .await
        .expect("open");
    let mode: String = sqlx::query_scalar("PRAGMA journal_mode")
        .fetch_one(&store.pool)
        .await
        .expect("mode");
    assert_eq!(mode, "wal");
    let fk: i64 = sqlx::query_scalar("PRAGMA foreign_keys")
        .fetch_one(&store.pool)
        .await
        .expect("fk");
    assert_eq!(fk, 1);
    let busy: i64 = sqlx::query_scalar("PRAGMA busy_timeout")
        .fetch_one(&store.pool)
        .await
        .expect("busy");
    assert_eq!(busy, 5000);
    store.ping().await.expect("ping");
}

#[cfg(unix)]
#[tokio::test]
async fn the_database_is_readable_by_its_owner_only() {
    use std::os::unix::fs::PermissionsExt;
    let mode =
        |p: &std::path::Path| std::fs::metadata(p).expect("meta").permissions().mode() & 0o777;
    let dir = tempfile::tempdir().expect("tempdir");
    let master = MasterKey::generate().to_hex();
    async fn open(dir: &std::path::Path, master: &str) -> Store {
        Store::open(dir, MasterKey::from_hex(master).expect("key"))
            .await
            .expect("open")
    }
    let store = open(dir.path(), &master).await;
    // A write, so that the -wal and -shm files exist.
    store.append_audit(entry("test")).await.expect("audit");
    let db = dir.path().join(DB_FILE);
    let wal = dir.path().join(format!("{DB_FILE}-wal"));
    let shm = dir.path().join(format!("{DB_FILE}-shm"));
    for p in [&db, &wal, &shm] {
        assert_eq!(mode(p), 0o600, "{}", p.display());
    }
    store.close().await;

    // A database created world-readable by an earlier version is restricted when opened.
    for p in [&db, &wal, &shm] {
        if p.exists() {
            std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        }
    }
    let store = open(dir.path(), &master).await;
    store.ping().await.expect("ping");
    assert_eq!(mode(&db), 0o600);
    for p in [&wal, &shm] {
        if p.exists() {
            assert_eq!(mode(p), 0o600, "{}", p.display());
        }
    }
}
