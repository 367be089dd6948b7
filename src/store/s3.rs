//! Blobs in an S3-compatible object store (issue 17): the same content addresses as on disk,
//! `PREFIX/ab/cdef…` in a bucket, through the `object_store` crate.
//!
//! - **Staging stays local**: uploads and job results are written to a temp file in
//!   `DATA_DIR/blobs/tmp`, hashed, and only then uploaded — one PUT up to
//!   `multipart_threshold` bytes, a multipart upload in parts of `part_size` bytes above it
//!   (two parts in flight at most). An object of that size already under the key is not
//!   uploaded again, only *touched* (see below).
//! - **Reads are verified**: [`S3Blobs::fetch`] streams the object into a temp file, hashing it,
//!   and moves it into the local cache `DATA_DIR/blobs/cache/ab/cdef…` only when its SHA-256 is
//!   its name and its size the object's; otherwise [`StoreError::BlobCorrupt`], nothing cached.
//!   A cache hit is checked cheaply: a HEAD says the object still exists (a blob the garbage
//!   collector of another replica removed is `NotFound` here too, and its cache copy dropped)
//!   and the cached file must have its size (a copy cut short by a crash is fetched again;
//!   one altered in place at its size is not detected). Files not used for a day are removed
//!   at start and by each garbage collection, and the cache is bounded by size
//!   (`s3.cache_max_bytes`, 10 GiB by default): a download that takes it past the bound evicts
//!   the least recently used copies down to 90 % of it — except those used in the last
//!   [`CACHE_GRACE`], whose paths a reader may be about to open.
//! - **Age for the garbage collector** is the object's `LastModified`. Committing bytes that are
//!   already stored must make the blob young again (the collector's age rule protects a blob
//!   whose asset row is about to be written): S3 cannot set a modification time, so the object
//!   is copied onto itself (a server-side copy, which sets a new `LastModified`); a server that
//!   refuses that copy (AWS S3 refuses a self-copy that changes no metadata) gets the bytes
//!   uploaded again, which refreshes it as well.
//! - The client is async; [`crate::store::BlobStore`]'s API is synchronous. This module owns a
//!   small tokio runtime (two threads) and every call spawns its request there and waits for
//!   the answer on the calling thread, which must therefore be allowed to block (the service
//!   calls blob methods from `spawn_blocking`); unlike `Runtime::block_on`, a call from a
//!   runtime thread blocks that thread but cannot panic.
//! - Secrets (the secret access key, a session token) never appear in `Debug`, `Display`,
//!   a configuration dump or an error message: errors are scrubbed of them.

use std::fmt;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use futures_util::StreamExt;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path as Key;
use object_store::{ObjectStore, ObjectStoreExt, PutPayload, WriteMultipart};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::blobs::{is_blob_id, location, modified_longer_ago};
use super::error::{Result, StoreError};

/// Smallest part S3 accepts in a multipart upload (all but the last).
pub const MIN_PART_SIZE: u64 = 5 << 20;
/// Uploads above this size are multipart by default.
pub const DEFAULT_MULTIPART_THRESHOLD: u64 = 16 << 20;
/// Default part size of a multipart upload.
pub const DEFAULT_PART_SIZE: u64 = 8 << 20;
/// Default bound of the local read cache, bytes.
pub const DEFAULT_CACHE_MAX_BYTES: u64 = 10 << 30;
/// Cached copies used more recently than this are never evicted by the size bound.
pub const CACHE_GRACE: Duration = Duration::from_secs(60);

/// A bucket and an optional key prefix: `s3://BUCKET/optional/prefix`.
#[derive(Clone, PartialEq, Eq)]
pub struct BlobUrl {
    bucket: String,
    prefix: String,
}

impl BlobUrl {
    /// Parses `s3://BUCKET[/PREFIX]` (`Invalid` otherwise; credentials in the URL are refused,
    /// and an error never repeats them).
    pub fn parse(url: &str) -> Result<Self> {
        let url = url.trim();
        let Some(rest) = url.strip_prefix("s3://") else {
            return Err(StoreError::invalid(format!(
                "a blob URL must start with s3:// (got {})",
                super::database::redact(url)
            )));
        };
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.contains('@') {
            return Err(StoreError::invalid(
                "a blob URL carries no credentials: give them as AWS_ACCESS_KEY_ID / \
                 AWS_SECRET_ACCESS_KEY or in the [s3] section of the configuration",
            ));
        }
        let bucket_ok = (3..=63).contains(&bucket.len())
            && bucket
                .bytes()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'.' || c == b'-');
        if !bucket_ok {
            return Err(StoreError::invalid(format!(
                "bucket name {bucket:?}: 3 to 63 of a-z, 0-9, '.', '-'"
            )));
        }
        let prefix = prefix.trim_matches('/');
        let segment_ok = |s: &str| {
            !s.is_empty()
                && s != "."
                && s != ".."
                && s.bytes().all(|c| {
                    c.is_ascii_alphanumeric() || matches!(c, b'-' | b'_' | b'.' | b'=' | b'+')
                })
        };
        if !prefix.is_empty() && !prefix.split('/').all(segment_ok) {
            return Err(StoreError::invalid(format!(
                "key prefix {prefix:?}: '/'-separated segments of A-Z, a-z, 0-9, '-', '_', '.', '=', '+'"
            )));
        }
        Ok(BlobUrl {
            bucket: bucket.to_owned(),
            prefix: prefix.to_owned(),
        })
    }

    pub fn bucket(&self) -> &str {
        &self.bucket
    }

    /// The key prefix without slashes at either end (empty: the bucket's root).
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// This URL with `child` appended to its prefix (the tests' own prefix in a shared bucket).
    pub fn join(&self, child: &str) -> Result<Self> {
        BlobUrl::parse(&format!("{self}/{child}"))
    }
}

impl fmt::Display for BlobUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.prefix.is_empty() {
            write!(f, "s3://{}", self.bucket)
        } else {
            write!(f, "s3://{}/{}", self.bucket, self.prefix)
        }
    }
}

impl fmt::Debug for BlobUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "BlobUrl({self})")
    }
}

impl std::str::FromStr for BlobUrl {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        BlobUrl::parse(s).map_err(|e| e.to_string())
    }
}

impl<'de> Deserialize<'de> for BlobUrl {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        BlobUrl::parse(&String::deserialize(d)?).map_err(serde::de::Error::custom)
    }
}

impl Serialize for BlobUrl {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

/// A secret string: read from configuration, shown as `***` by `Debug`, `Display` and
/// serialization (a configuration dump never carries it).
#[derive(Clone, PartialEq, Eq, Default)]
pub struct Secret(String);

impl Secret {
    pub fn new(s: impl Into<String>) -> Self {
        Secret(s.into())
    }

    /// The secret itself (never log it).
    pub fn expose(&self) -> &str {
        &self.0
    }
}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("***")
    }
}

impl fmt::Display for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("***")
    }
}

impl<'de> Deserialize<'de> for Secret {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        Ok(Secret(String::deserialize(d)?))
    }
}

impl Serialize for Secret {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str("***")
    }
}

/// The S3 client's settings besides the URL (the configuration's `[s3]` table). What is unset
/// comes from the standard environment variables — `AWS_ENDPOINT_URL`, `AWS_REGION`,
/// `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_ALLOW_HTTP`, and
/// the container / web-identity credentials of EKS and ECS.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct S3Options {
    /// The server, e.g. `http://127.0.0.1:8333` (default: AWS S3 of the region).
    pub endpoint: Option<String>,
    pub region: Option<String>,
    pub access_key_id: Option<String>,
    pub secret_access_key: Option<Secret>,
    /// Plain HTTP to the endpoint. Default: allowed for a loopback endpoint
    /// (`http://127.0.0.1:…`, `http://localhost:…`) only, else as `AWS_ALLOW_HTTP` says.
    pub allow_http: Option<bool>,
    /// Blobs larger than this many bytes are uploaded in parts.
    pub multipart_threshold: u64,
    /// Bytes per part of a multipart upload (at least 5 MiB, S3's minimum).
    pub part_size: u64,
    /// Bound of the local read cache in bytes (least recently used copies go first; 0: no
    /// bound, only the one-day age rule).
    pub cache_max_bytes: u64,
}

impl Default for S3Options {
    fn default() -> Self {
        S3Options {
            endpoint: None,
            region: None,
            access_key_id: None,
            secret_access_key: None,
            allow_http: None,
            multipart_threshold: DEFAULT_MULTIPART_THRESHOLD,
            part_size: DEFAULT_PART_SIZE,
            cache_max_bytes: DEFAULT_CACHE_MAX_BYTES,
        }
    }
}

/// Where the blobs live.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum BlobConfig {
    /// `DATA_DIR/blobs` (the default).
    #[default]
    Local,
    /// A bucket of an S3-compatible object store.
    S3 { url: BlobUrl, options: S3Options },
}

impl BlobConfig {
    /// The blob store of a test server (`scripts/s3-test-server.sh` prints its URL,
    /// `http://ACCESS_KEY:SECRET@HOST:PORT/BUCKET`, which the tests read from
    /// `SPLATMARK_TEST_S3`), under key prefix `prefix` (each test its own). Multipart uploads
    /// start at `multipart_threshold` bytes.
    pub fn test_server(server: &str, prefix: &str, multipart_threshold: u64) -> Result<Self> {
        let bad = || StoreError::invalid("expected http://ACCESS_KEY:SECRET@HOST:PORT/BUCKET");
        let rest = server.trim().strip_prefix("http://").ok_or_else(bad)?;
        let (auth, rest) = rest.split_once('@').ok_or_else(bad)?;
        let (key, secret) = auth.split_once(':').ok_or_else(bad)?;
        let (host, bucket) = rest.split_once('/').ok_or_else(bad)?;
        let url = BlobUrl::parse(&format!("s3://{}", bucket.trim_end_matches('/')))?;
        Ok(BlobConfig::S3 {
            url: if prefix.is_empty() {
                url
            } else {
                url.join(prefix)?
            },
            options: S3Options {
                endpoint: Some(format!("http://{host}")),
                region: Some("us-east-1".into()),
                access_key_id: Some(key.to_owned()),
                secret_access_key: Some(Secret::new(secret)),
                allow_http: Some(true),
                multipart_threshold,
                ..S3Options::default()
            },
        })
    }
}

/// A tokio runtime dropped without blocking (a runtime dropped inside another one's task would
/// panic otherwise).
struct OwnedRuntime(Option<tokio::runtime::Runtime>);

impl Drop for OwnedRuntime {
    fn drop(&mut self) {
        if let Some(rt) = self.0.take() {
            rt.shutdown_background();
        }
    }
}

/// The S3 side of a [`crate::store::BlobStore`].
pub(crate) struct S3Blobs {
    store: Arc<AmazonS3>,
    url: BlobUrl,
    endpoint: Option<String>,
    rt: OwnedRuntime,
    /// Strings that must not appear in an error message.
    secrets: Vec<String>,
    multipart_threshold: u64,
    part_size: usize,
    /// `blobs/tmp` (downloads) and `blobs/cache`.
    tmp: PathBuf,
    cache: PathBuf,
    cache_max_bytes: u64,
    /// Bytes in `cache` (recounted by every pruning; downloads add theirs).
    cache_bytes: AtomicU64,
}

impl fmt::Debug for S3Blobs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("S3Blobs")
            .field("url", &self.url.to_string())
            .field("endpoint", &self.endpoint)
            .field("cache", &self.cache)
            .finish_non_exhaustive()
    }
}

/// A listed object: blob id, size, age.
pub(crate) type Listed = (String, u64, Duration);

impl S3Blobs {
    /// A client for `url` (nothing is sent yet): `root` is the local blob folder whose `tmp`
    /// and `cache` it uses.
    pub(crate) fn new(root: &Path, url: &BlobUrl, options: &S3Options) -> Result<Self> {
        if options.part_size < MIN_PART_SIZE {
            return Err(StoreError::invalid(format!(
                "s3.part_size must be at least {MIN_PART_SIZE} bytes (S3's smallest part)"
            )));
        }
        if options.multipart_threshold == 0 {
            return Err(StoreError::invalid(
                "s3.multipart_threshold must be at least 1",
            ));
        }
        let part_size = usize::try_from(options.part_size)
            .map_err(|_| StoreError::invalid("s3.part_size is too large"))?;
        let mut b = AmazonS3Builder::from_env().with_bucket_name(url.bucket());
        let mut secrets = Vec::new();
        for var in ["AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN"] {
            if let Ok(v) = std::env::var(var)
                && !v.is_empty()
            {
                secrets.push(v);
            }
        }
        let endpoint = options.endpoint.clone().or_else(|| {
            ["AWS_ENDPOINT_URL", "AWS_ENDPOINT"]
                .iter()
                .find_map(|v| std::env::var(v).ok().filter(|s| !s.is_empty()))
        });
        if let Some(e) = &options.endpoint {
            b = b.with_endpoint(e);
        }
        if let Some(r) = &options.region {
            b = b.with_region(r);
        }
        if let Some(k) = &options.access_key_id {
            b = b.with_access_key_id(k);
        }
        if let Some(s) = &options.secret_access_key {
            b = b.with_secret_access_key(s.expose());
            secrets.push(s.expose().to_owned());
        }
        match options.allow_http {
            Some(allow) => b = b.with_allow_http(allow),
            None if endpoint.as_deref().is_some_and(is_loopback_http) => {
                b = b.with_allow_http(true)
            }
            None => {}
        }
        secrets.retain(|s| s.len() >= 4);
        let scrub = |msg: String| scrub(msg, &secrets);
        let store = b.build().map_err(|e| {
            StoreError::invalid(format!("the S3 client for {url}: {}", scrub(e.to_string())))
        })?;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("blob-s3")
            .enable_all()
            .build()?;
        let tmp = root.join("tmp");
        let cache = root.join("cache");
        fs::create_dir_all(&cache)?;
        let cached = prune(
            &cache,
            super::assets::CACHE_MAX_AGE,
            options.cache_max_bytes,
        );
        Ok(S3Blobs {
            store: Arc::new(store),
            url: url.clone(),
            // For messages only: no user-info password.
            endpoint: endpoint.map(|e| super::database::redact(&e)),
            rt: OwnedRuntime(Some(rt)),
            secrets,
            multipart_threshold: options.multipart_threshold,
            part_size,
            tmp,
            cache,
            cache_max_bytes: options.cache_max_bytes,
            cache_bytes: AtomicU64::new(cached),
        })
    }

    /// `s3://BUCKET/PREFIX` and the endpoint, for messages.
    pub(crate) fn describe(&self) -> String {
        match &self.endpoint {
            Some(e) => format!("{} at {e}", self.url),
            None => self.url.to_string(),
        }
    }

    /// Runs `fut` on the S3 runtime and waits for it on this thread.
    fn run<T: Send + 'static>(
        &self,
        fut: impl Future<Output = T> + Send + 'static,
    ) -> io::Result<T> {
        let rt = self
            .rt
            .0
            .as_ref()
            .expect("the runtime lives as long as the store");
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        rt.spawn(async move {
            let _ = tx.send(fut.await);
        });
        rx.recv()
            .map_err(|_| io::Error::other("the S3 request's task ended without an answer"))
    }

    /// An object store error as an I/O error (`NotFound` kept), secrets scrubbed.
    fn io_err(&self, e: object_store::Error) -> io::Error {
        let kind = match e {
            object_store::Error::NotFound { .. } => io::ErrorKind::NotFound,
            _ => io::ErrorKind::Other,
        };
        io::Error::new(
            kind,
            format!(
                "blob store {}: {}",
                self.url,
                scrub(e.to_string(), &self.secrets)
            ),
        )
    }

    fn key(&self, sha256: &str) -> Key {
        let (head, tail) = sha256.split_at(2);
        if self.url.prefix().is_empty() {
            Key::from(format!("{head}/{tail}"))
        } else {
            Key::from(format!("{}/{head}/{tail}", self.url.prefix()))
        }
    }

    /// Checks that the bucket answers (a LIST of at most one page under the prefix).
    pub(crate) fn check(&self) -> io::Result<()> {
        let store = self.store.clone();
        let prefix = (!self.url.prefix().is_empty()).then(|| Key::from(self.url.prefix()));
        self.run(async move { store.list_with_delimiter(prefix.as_ref()).await.map(|_| ()) })?
            .map_err(|e| self.io_err(e))
    }

    /// HEAD: the object's metadata, `None` when there is none.
    fn head(&self, sha256: &str) -> io::Result<Option<object_store::ObjectMeta>> {
        let (store, key) = (self.store.clone(), self.key(sha256));
        match self.run(async move { store.head(&key).await })? {
            Ok(m) => Ok(Some(m)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.io_err(e)),
        }
    }

    /// Stores the hashed bytes of `file` (`size` bytes, named `sha256`): uploaded unless an
    /// object of that size is there already, which is touched instead.
    pub(crate) fn commit(&self, file: &File, sha256: &str, size: u64) -> io::Result<()> {
        // An object of another size does not hold these bytes: replaced.
        let same = self.head(sha256)?.is_some_and(|m| m.size == size);
        if same && self.touch(sha256)? {
            return Ok(());
        }
        self.upload(file, sha256, size)
    }

    /// Copies the object onto itself, which gives it a new `LastModified`; `false` when the
    /// server refuses (the caller uploads the bytes again).
    fn touch(&self, sha256: &str) -> io::Result<bool> {
        let (store, key) = (self.store.clone(), self.key(sha256));
        match self.run(async move { store.copy(&key, &key).await })? {
            Ok(()) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => {
                tracing::debug!(error = %self.io_err(e), "self-copy refused: uploading again");
                Ok(false)
            }
        }
    }

    /// Uploads `size` bytes of `file` to the blob's key: one PUT up to the multipart
    /// threshold, parts of `part_size` above it (two in flight), aborted on failure.
    fn upload(&self, file: &File, sha256: &str, size: u64) -> io::Result<()> {
        let (store, key) = (self.store.clone(), self.key(sha256));
        let mut file = file.try_clone()?;
        std::io::Seek::seek(&mut file, io::SeekFrom::Start(0))?;
        if size <= self.multipart_threshold {
            let mut bytes = Vec::with_capacity(usize::try_from(size).unwrap_or(0));
            file.read_to_end(&mut bytes)?;
            if bytes.len() as u64 != size {
                return Err(io::Error::other(
                    "the staged file changed size while uploading",
                ));
            }
            return self
                .run(async move { store.put(&key, PutPayload::from(bytes)).await })?
                .map(|_| ())
                .map_err(|e| self.io_err(e));
        }
        let part_size = self.part_size;
        let r = self.run(async move {
            let upload = store.put_multipart(&key).await.map_err(Upload::Store)?;
            let mut w = WriteMultipart::new_with_chunk_size(upload, part_size);
            let mut buf = vec![0u8; part_size];
            let mut sent = 0u64;
            let read = loop {
                // Local disk reads on a thread of the S3 runtime: short, and this runtime
                // serves nothing else that would wait for them.
                match file.read(&mut buf) {
                    Ok(0) => break Ok(()),
                    Ok(n) => {
                        sent += n as u64;
                        if let Err(e) = w.wait_for_capacity(2).await {
                            break Err(Upload::Store(e));
                        }
                        w.write(&buf[..n]);
                    }
                    Err(e) => break Err(Upload::Io(e)),
                }
            };
            let read = read.and_then(|()| {
                if sent == size {
                    Ok(())
                } else {
                    Err(Upload::Io(io::Error::other(
                        "the staged file changed size while uploading",
                    )))
                }
            });
            match read {
                Ok(()) => w.finish().await.map(|_| ()).map_err(Upload::Store),
                Err(e) => {
                    let _ = w.abort().await;
                    Err(e)
                }
            }
        })?;
        r.map_err(|e| match e {
            Upload::Io(e) => e,
            Upload::Store(e) => self.io_err(e),
        })
    }

    /// A local file holding blob `sha256`: the cached copy when the object still exists and
    /// the copy has its size, else the object downloaded, verified (SHA-256 and size) and
    /// cached. `NotFound` when no object holds the blob; `BlobCorrupt` when the object's bytes
    /// are not the blob's (nothing cached then).
    pub(crate) fn fetch(&self, sha256: &str) -> Result<PathBuf> {
        let cached = location(&self.cache, sha256);
        let Some(meta) = self.head(sha256)? else {
            let _ = fs::remove_file(&cached);
            return Err(StoreError::NotFound);
        };
        if fs::metadata(&cached).is_ok_and(|m| m.is_file() && m.len() == meta.size) {
            // Used now: the cache's pruning keeps it another day.
            if let Ok(f) = File::options().write(true).open(&cached) {
                let _ = f.set_modified(std::time::SystemTime::now());
            }
            return Ok(cached);
        }
        fs::create_dir_all(&self.tmp)?;
        let tmp = tempfile::NamedTempFile::new_in(&self.tmp)?;
        let mut out = tmp.reopen()?;
        let (store, key) = (self.store.clone(), self.key(sha256));
        let got = self.run(async move {
            let r = store.get(&key).await.map_err(Upload::Store)?;
            let mut stream = r.into_stream();
            let mut hasher = Sha256::new();
            let mut size = 0u64;
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(Upload::Store)?;
                hasher.update(&chunk);
                size += chunk.len() as u64;
                out.write_all(&chunk).map_err(Upload::Io)?;
            }
            out.flush().map_err(Upload::Io)?;
            Ok::<_, Upload>((hex::encode(hasher.finalize()), size))
        })?;
        let (hash, size) = got.map_err(|e| match e {
            Upload::Io(e) => StoreError::Io(e),
            Upload::Store(object_store::Error::NotFound { .. }) => StoreError::NotFound,
            Upload::Store(e) => StoreError::Io(self.io_err(e)),
        })?;
        if hash != sha256 || size != meta.size {
            return Err(StoreError::BlobCorrupt(format!(
                "the object of blob {sha256} in {} holds {size} bytes hashing to {hash} \
                 (expected {} bytes hashing to its name)",
                self.url, meta.size
            )));
        }
        let dir = cached.parent().unwrap_or(&self.cache);
        fs::create_dir_all(dir)?;
        tmp.persist(&cached).map_err(|e| e.error)?;
        let total = self.cache_bytes.fetch_add(size, Ordering::Relaxed) + size;
        if self.cache_max_bytes > 0 && total > self.cache_max_bytes {
            self.prune_cache(super::assets::CACHE_MAX_AGE);
        }
        Ok(cached)
    }

    /// The object's size (`NotFound` when missing).
    pub(crate) fn size_of(&self, sha256: &str) -> Result<u64> {
        self.head(sha256)?
            .map(|m| m.size)
            .ok_or(StoreError::NotFound)
    }

    /// Every blob under the prefix, with its size and its age (since its `LastModified`;
    /// a time in the future counts as age 0). Keys that are not blobs are skipped.
    pub(crate) fn list(&self) -> io::Result<Vec<Listed>> {
        let store = self.store.clone();
        let prefix = self.url.prefix().to_owned();
        let listed = self.run(async move {
            let p = (!prefix.is_empty()).then(|| Key::from(prefix.as_str()));
            let mut stream = store.list(p.as_ref());
            let mut out = Vec::new();
            while let Some(m) = stream.next().await {
                out.push(m?);
            }
            Ok::<_, object_store::Error>(out)
        })?;
        let mut out = Vec::new();
        for m in listed.map_err(|e| self.io_err(e))? {
            let key = m.location.as_ref();
            let rel = if self.url.prefix().is_empty() {
                key
            } else {
                match key
                    .strip_prefix(self.url.prefix())
                    .and_then(|r| r.strip_prefix('/'))
                {
                    Some(r) => r,
                    None => continue,
                }
            };
            let Some((head, tail)) = rel.split_once('/') else {
                continue;
            };
            let id = format!("{head}{tail}");
            if head.len() != 2 || !is_blob_id(&id) {
                continue;
            }
            out.push((id, m.size, age_of(&m)));
        }
        out.sort();
        Ok(out)
    }

    /// The size and age of blob `sha256` (`None`: not stored).
    pub(crate) fn stat(&self, sha256: &str) -> io::Result<Option<(u64, Duration)>> {
        Ok(self.head(sha256)?.map(|m| (m.size, age_of(&m))))
    }

    /// Deletes the object and the cached copy; `false` when there was no object.
    pub(crate) fn remove(&self, sha256: &str) -> io::Result<bool> {
        let _ = fs::remove_file(location(&self.cache, sha256));
        if self.head(sha256)?.is_none() {
            return Ok(false);
        }
        let (store, key) = (self.store.clone(), self.key(sha256));
        match self.run(async move { store.delete(&key).await })? {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(true),
            Err(e) => Err(self.io_err(e)),
        }
    }

    /// Removes cached copies not used for `max_age`, then the least recently used ones past the
    /// size bound (a reader holding one open keeps reading it).
    pub(crate) fn prune_cache(&self, max_age: Duration) {
        let left = prune(&self.cache, max_age, self.cache_max_bytes);
        self.cache_bytes.store(left, Ordering::Relaxed);
    }

    /// Writes `bytes` under blob `sha256`'s key as they are (for tests that corrupt objects).
    #[cfg(test)]
    pub(crate) fn put_raw(&self, sha256: &str, bytes: Vec<u8>) -> io::Result<()> {
        let (store, key) = (self.store.clone(), self.key(sha256));
        self.run(async move { store.put(&key, PutPayload::from(bytes)).await })?
            .map(|_| ())
            .map_err(|e| self.io_err(e))
    }

    /// The object's `LastModified` and `ETag` (tests).
    #[cfg(test)]
    pub(crate) fn meta(
        &self,
        sha256: &str,
    ) -> io::Result<Option<(std::time::SystemTime, Option<String>)>> {
        Ok(self.head(sha256)?.map(|m| {
            let ms = u64::try_from(m.last_modified.timestamp_millis()).unwrap_or(0);
            (std::time::UNIX_EPOCH + Duration::from_millis(ms), m.e_tag)
        }))
    }
}

/// Why an upload or a download failed.
enum Upload {
    Io(io::Error),
    Store(object_store::Error),
}

fn age_of(m: &object_store::ObjectMeta) -> Duration {
    let ms = u64::try_from(m.last_modified.timestamp_millis()).unwrap_or(0);
    (std::time::UNIX_EPOCH + Duration::from_millis(ms))
        .elapsed()
        .unwrap_or_default()
}

/// `msg` with each of `secrets` replaced by `***`.
fn scrub(mut msg: String, secrets: &[String]) -> String {
    for s in secrets {
        if !s.is_empty() {
            msg = msg.replace(s.as_str(), "***");
        }
    }
    msg
}

/// `http://` to 127.0.0.0/8, ::1 or localhost.
fn is_loopback_http(endpoint: &str) -> bool {
    let Some(rest) = endpoint.strip_prefix("http://") else {
        return false;
    };
    let authority = rest.split('/').next().unwrap_or_default();
    let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    let host = if let Some(v6) = host.strip_prefix('[') {
        v6.split(']').next().unwrap_or_default()
    } else {
        host.split(':').next().unwrap_or_default()
    };
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// Removes the files under `dir` (two levels: `ab/cdef…`) modified longer than `max_age` ago.
/// Prunes the cache folder `dir` (`ab/cdef…` files): removes the files not modified for
/// `max_age`, then — when `max_bytes` > 0 and the rest exceeds it — the least recently
/// modified ones down to 90 % of `max_bytes`, sparing those modified within [`CACHE_GRACE`].
/// Returns the bytes left.
fn prune(dir: &Path, max_age: Duration, max_bytes: u64) -> u64 {
    let mut kept: Vec<(std::time::SystemTime, u64, PathBuf)> = Vec::new();
    let Ok(heads) = fs::read_dir(dir) else {
        return 0;
    };
    for head in heads.flatten() {
        let Ok(files) = fs::read_dir(head.path()) else {
            continue;
        };
        for f in files.flatten() {
            if modified_longer_ago(&f, max_age) {
                let _ = fs::remove_file(f.path());
                continue;
            }
            if let Ok(m) = f.metadata()
                && m.is_file()
            {
                let when = m.modified().unwrap_or(std::time::SystemTime::UNIX_EPOCH);
                kept.push((when, m.len(), f.path()));
            }
        }
    }
    let mut total: u64 = kept.iter().map(|k| k.1).sum();
    if max_bytes == 0 || total <= max_bytes {
        return total;
    }
    let target = max_bytes / 10 * 9;
    kept.sort();
    for (when, size, path) in kept {
        if total <= target {
            break;
        }
        let recent = when.elapsed().map_or(true, |age| age < CACHE_GRACE);
        if !recent && fs::remove_file(&path).is_ok() {
            total -= size;
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cache_keeps_the_recently_used_copies_within_its_bound() {
        let dir = tempfile::tempdir().expect("tmp");
        let now = std::time::SystemTime::now();
        let hours = |h: u64| now - Duration::from_secs(h * 3600);
        // name, bytes, last used
        let files = [
            ("aa/old", 100, hours(30)),
            ("ab/lru", 400, hours(5)),
            ("ac/mid", 300, hours(3)),
            ("ad/new", 200, hours(1)),
            ("ae/now", 500, now),
        ];
        for (name, size, when) in files {
            let p = dir.path().join(name);
            fs::create_dir_all(p.parent().unwrap()).unwrap();
            fs::write(&p, vec![7u8; size]).unwrap();
            File::options()
                .write(true)
                .open(&p)
                .unwrap()
                .set_modified(when)
                .unwrap();
        }
        let day = Duration::from_secs(24 * 3600);
        let exists = |n: &str| dir.path().join(n).exists();
        // Unbounded: only the age rule.
        assert_eq!(prune(dir.path(), day, 0), 1400);
        assert!(!exists("aa/old"));
        // Within the bound: nothing goes.
        assert_eq!(prune(dir.path(), day, 1400), 1400);
        // Past it: the least recently used go until ≤ 90 % of the bound (1 000 → 900).
        assert_eq!(prune(dir.path(), day, 1000), 700);
        assert!(!exists("ab/lru") && !exists("ac/mid"));
        assert!(exists("ad/new") && exists("ae/now"));
        // A copy used within the grace period stays even past the bound.
        assert_eq!(prune(dir.path(), day, 100), 500);
        assert!(exists("ae/now") && !exists("ad/new"));
    }

    #[test]
    fn blob_urls_parse_and_refuse_credentials() {
        let u = BlobUrl::parse("s3://my-bucket/splat/blobs/").unwrap();
        assert_eq!((u.bucket(), u.prefix()), ("my-bucket", "splat/blobs"));
        assert_eq!(u.to_string(), "s3://my-bucket/splat/blobs");
        assert_eq!(BlobUrl::parse("s3://b12").unwrap().prefix(), "");
        assert_eq!(
            u.join("t-1").unwrap().to_string(),
            "s3://my-bucket/splat/blobs/t-1"
        );
        for bad in [
            "file:///x",
            "s3://",
            "s3://UPPER",
            "s3://b/../x",
            "s3://b/a//c x",
        ] {
            assert!(BlobUrl::parse(bad).is_err(), "{bad}");
        }
        let e = BlobUrl::parse("s3://AKIA:hunter22@bucket/p")
            .unwrap_err()
            .to_string();
        assert!(!e.contains("hunter22"), "{e}");
        let e = BlobUrl::parse("http://AKIA:hunter22@host/p")
            .unwrap_err()
            .to_string();
        assert!(!e.contains("hunter22"), "{e}");
    }

    #[test]
    fn secrets_never_print() {
        let o = S3Options {
            secret_access_key: Some(Secret::new("hunter22-very-secret")),
            access_key_id: Some("AKIDEXAMPLE".into()),
            ..S3Options::default()
        };
        let c = BlobConfig::S3 {
            url: BlobUrl::parse("s3://bucket/p").unwrap(),
            options: o.clone(),
        };
        for shown in [
            format!("{o:?}"),
            format!("{c:?}"),
            toml::to_string(&o).unwrap(),
        ] {
            assert!(!shown.contains("hunter22"), "{shown}");
        }
        // The client itself (nothing is sent), an endpoint with a password included.
        let dir = tempfile::tempdir().unwrap();
        let with_endpoint = BlobConfig::S3 {
            url: BlobUrl::parse("s3://bucket/p").unwrap(),
            options: S3Options {
                endpoint: Some("http://user:endpoint-pw-1@127.0.0.1:1".into()),
                ..o.clone()
            },
        };
        let b =
            crate::store::BlobStore::open_with(dir.path().join("blobs"), &with_endpoint).unwrap();
        let shown = format!("{b:?} {}", b.describe());
        assert!(
            !shown.contains("hunter22") && !shown.contains("endpoint-pw-1"),
            "{shown}"
        );
        assert!(shown.contains("s3://bucket/p"), "{shown}");
        assert_eq!(
            scrub(
                "x hunter22-very-secret y".into(),
                &["hunter22-very-secret".into()]
            ),
            "x *** y"
        );
    }

    #[test]
    fn only_loopback_endpoints_get_plain_http_by_default() {
        for yes in [
            "http://127.0.0.1:8333",
            "http://localhost:9000/",
            "http://[::1]:1",
        ] {
            assert!(is_loopback_http(yes), "{yes}");
        }
        for no in [
            "https://127.0.0.1",
            "http://s3.internal:8333",
            "http://10.0.0.1",
        ] {
            assert!(!is_loopback_http(no), "{no}");
        }
    }
}
