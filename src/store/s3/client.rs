//! The S3 client behind a blob store ([`S3Blobs`]): uploads (single or multipart), verified
//! downloads into the read cache, HEAD / LIST / DELETE, on its own small tokio runtime.

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
use sha2::{Digest, Sha256};

use super::cache::prune;
use super::{BlobUrl, MIN_PART_SIZE, S3Options};
use crate::store::blobs::{is_blob_id, location};
use crate::store::error::{Result, StoreError};

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
            crate::store::assets::CACHE_MAX_AGE,
            options.cache_max_bytes,
        );
        Ok(S3Blobs {
            store: Arc::new(store),
            url: url.clone(),
            // For messages only: no user-info password.
            endpoint: endpoint.map(|e| crate::store::database::redact(&e)),
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
            self.prune_cache(crate::store::assets::CACHE_MAX_AGE);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::s3::{BlobConfig, Secret};

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
