//! The S3 settings: the bucket URL ([`BlobUrl`]), [`Secret`] strings, the client's
//! [`S3Options`] and where the blobs live ([`BlobConfig`]).

use std::fmt;

use serde::{Deserialize, Serialize};

use super::{DEFAULT_CACHE_MAX_BYTES, DEFAULT_MULTIPART_THRESHOLD, DEFAULT_PART_SIZE};
use crate::store::error::{Result, StoreError};

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
                crate::store::database::redact(url)
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
