//! Blobs in an S3-compatible object store (issue 17): the same content addresses as on disk,
//! `PREFIX/ab/cdef…` in a bucket, through the `object_store` crate.
//!
//! - **Staging stays local**: uploads and job results are written to a temp file in
//!   `DATA_DIR/blobs/tmp`, hashed, and only then uploaded — one PUT up to
//!   `multipart_threshold` bytes, a multipart upload in parts of `part_size` bytes above it
//!   (two parts in flight at most). An object of that size already under the key is not
//!   uploaded again, only *touched* (see below).
//! - **Reads are verified**: `S3Blobs::fetch` streams the object into a temp file, hashing it,
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
//!
//! [`StoreError::BlobCorrupt`]: super::StoreError::BlobCorrupt

mod cache;
mod client;
mod config;

pub(crate) use client::S3Blobs;
pub use config::{BlobConfig, BlobUrl, S3Options, Secret};

use std::time::Duration;

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
