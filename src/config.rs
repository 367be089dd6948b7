//! Configuration of `splatmark serve`, in layers: embedded defaults < optional TOML file <
//! environment (`SPLATMARK_*`) < command-line flags. The defaults make one command work on a
//! fresh machine: SQLite and blobs under `./data`, bind `127.0.0.1:8080`, one CPU worker.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// Which devices the workers use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DevicePolicy {
    /// One worker per hardware GPU adapter (the GPU rasterizer on its own wgpu device); one
    /// CPU worker when there is none.
    #[default]
    Auto,
    /// CPU workers only.
    Cpu,
    /// The GPU rasterizer on the best wgpu adapter (Mesa's software Vulkan counts).
    Wgpu,
}

/// What one `serve` process runs: several API replicas and workers on other machines share one
/// PostgreSQL database (`database_url`) and blob store.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// The HTTP API and the workers (one machine).
    #[default]
    All,
    /// The HTTP API only: jobs are left to worker processes.
    Api,
    /// Workers only, with `/healthz`, `/readyz` and `/metrics` for probes and scrapers.
    Worker,
}

impl std::str::FromStr for Role {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "all" => Ok(Role::All),
            "api" => Ok(Role::Api),
            "worker" => Ok(Role::Worker),
            _ => Err(format!("unknown role {s:?}: expected all, api or worker")),
        }
    }
}

impl Role {
    /// Whether this process serves the API (and so bootstraps the admin key and collects
    /// unreferenced blobs).
    pub fn serves_api(self) -> bool {
        self != Role::Worker
    }

    /// Whether this process runs workers.
    pub fn runs_workers(self) -> bool {
        self != Role::Api
    }
}

/// Views the embedding trains on when an upload comes without cameras (orbit around the scene)
/// and the resolution renders are made at. 512² by default: at 256² donut's unseen views decode
/// 97.9 % of the bits, at 512² 99.2 % (docs/RESULTS.md), for about 2.6× the CPU time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ViewDefaults {
    /// Orbit views for 32-bit payloads: 48, as for longer ones since the planning and the
    /// calibration read at most `EmbedOptions::analysis_views` of them (24) — twice the 24
    /// views of before bring every 32-bit payload measured over 98.5 % of the bits on unseen
    /// views (two of four did not) for ~3 % more time (docs/RESULTS.md).
    pub orbit: usize,
    /// Orbit views for longer payloads (48 and 64 bits): 48 carry 4–6 points more of their bits
    /// to unseen views than 24 (donut, 512²: 48 bits 92.4 → 96.7 %, 64 bits 89.6 → 95.3 %;
    /// docs/RESULTS.md).
    pub orbit_long: usize,
    pub width: u32,
    pub height: u32,
}

impl ViewDefaults {
    /// The orbit views a `bits`-bit payload trains on by default.
    pub fn orbit_for(&self, bits: usize) -> usize {
        if bits > 32 {
            self.orbit_long
        } else {
            self.orbit
        }
    }
}

impl Default for ViewDefaults {
    fn default() -> Self {
        Self {
            orbit: 48,
            orbit_long: 48,
            width: 512,
            height: 512,
        }
    }
}

/// Everything `serve` needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Address to listen on.
    pub bind: SocketAddr,
    /// SQLite database (`splatmark.db`), blobs (`blobs/`), master key and bootstrap token.
    pub data_dir: PathBuf,
    /// The database (`sqlite://PATH` or `postgres://USER:PASSWORD@HOST:PORT/DB`); `None`:
    /// `DATA_DIR/splatmark.db`. Blobs stay in `DATA_DIR/blobs/`. Never printed with its password.
    pub database_url: Option<crate::store::Database>,
    /// Where the blobs live: `None`, `DATA_DIR/blobs/`; `s3://BUCKET/optional/prefix`, a
    /// bucket of an S3-compatible object store shared by every process (then `DATA_DIR/blobs/`
    /// holds only staged uploads and a verified read cache). The client's settings are in `s3`.
    pub blob_url: Option<crate::store::BlobUrl>,
    /// The S3 client (endpoint, region, credentials, multipart sizes) for an `s3://` blob URL;
    /// unset fields come from the standard `AWS_*` environment variables. The secret key is
    /// never printed.
    pub s3: crate::store::S3Options,
    /// What this process runs: `all` (default), `api` or `worker`.
    pub role: Role,
    /// Number of workers; `None`: one per GPU adapter, or one CPU worker.
    pub workers: Option<usize>,
    pub device: DevicePolicy,
    /// Largest upload (scene + cameras) in bytes.
    pub max_upload_bytes: u64,
    /// Largest scene accepted, in Gaussians.
    pub max_gaussians: usize,
    /// Most images in one verification request.
    pub max_verify_images: usize,
    /// Largest side of an image submitted for verification, in pixels.
    pub max_image_side: u32,
    /// Most pixels (all images together) one verification may ask to decode: bounds the work of
    /// a request (one 4096² image costs ≈ 8.6 s of CPU on the 2-core machine).
    pub max_verify_pixels: u64,
    /// Verifications decoded at once; further ones wait up to `verify_wait_ms`, then get 503
    /// with `Retry-After`.
    pub verify_concurrency: usize,
    /// How long a verification waits for a decoding slot, in milliseconds.
    pub verify_wait_ms: u64,
    /// Uploads parsed at once (a parse holds the whole decoded scene in memory: ≈ 240 bytes
    /// per Gaussian of SH degree 3, so up to ≈ 2.4 GB at `max_gaussians`); further ones wait up
    /// to `upload_wait_ms`, then get 503 with `Retry-After`. Their bytes are spooled to disk
    /// meanwhile, not held in memory.
    pub upload_concurrency: usize,
    /// How long an upload waits for a parsing slot or for its memory, in milliseconds.
    pub upload_wait_ms: u64,
    /// Memory the uploads being checked may take together, in MiB. Each reserves what reading
    /// its files costs — the file, the decoded scene and the packed arrays, known from the
    /// scene's header (`scene::cost`) — before it reads them; it waits up to `upload_wait_ms`
    /// for that much to be free (then 503 with `Retry-After`), and one that needs more than the
    /// whole budget is refused with 413.
    pub upload_memory_mb: u64,
    /// A multipart body (upload, verification) that sends nothing for this long is answered
    /// 408 and dropped, in milliseconds (slow clients cannot hold a connection for the whole
    /// request timeout).
    pub body_idle_timeout_ms: u64,
    /// A request header that has not arrived whole this long after the connection started
    /// waiting for it closes the connection, in milliseconds (a client trickling its header
    /// cannot hold a connection open).
    pub header_timeout_ms: u64,
    /// Verifications one API key may submit a minute (in bursts of as many); further ones get
    /// 429 with `Retry-After`.
    pub verify_per_minute: u32,
    /// Requests with a missing, malformed, unknown or revoked API key one client address may
    /// make a minute; past that, every request from it gets 429 with `Retry-After` until the
    /// budget refills (guessing keys is slowed down, valid keys from other addresses are not).
    pub auth_failures_per_minute: u32,
    /// Family-wise false-positive rate of verification decisions.
    pub fpr: f64,
    /// Job lease; workers heartbeat every third of it.
    pub lease_seconds: u64,
    /// Attempts before a job goes to the dead state.
    pub max_attempts: u32,
    /// File with the master key (hex); created on first start when missing. The environment
    /// variable `SPLATMARK_MASTER_KEY` (hex) takes precedence. Default `DATA_DIR/master.key`.
    pub master_key_file: Option<PathBuf>,
    /// Folder with decoder weights `decoder-{bits}.bpk` (+ sidecars) overriding the shipped ones.
    pub weights_dir: Option<PathBuf>,
    /// Views for uploads without cameras.
    pub views: ViewDefaults,
    /// Finetuning steps of an embedding unless a request says otherwise.
    pub steps: usize,
    /// Log lines as JSON (for log shippers) instead of text.
    pub log_json: bool,
}

/// Largest `upload_memory_mb`: the budget is counted in KiB, and a reservation must fit a u32.
pub const MAX_UPLOAD_MEMORY_MB: u64 = 1 << 22;

impl Config {
    /// The database the store opens: `database_url`, or `DATA_DIR/splatmark.db`.
    pub fn database(&self) -> crate::store::Database {
        self.database_url
            .clone()
            .unwrap_or_else(|| crate::store::Database::in_data_dir(&self.data_dir))
    }

    /// Where the store keeps the blobs: `blob_url` with the `s3` settings, or `DATA_DIR/blobs`.
    pub fn blobs(&self) -> crate::store::BlobConfig {
        match &self.blob_url {
            Some(url) => crate::store::BlobConfig::S3 {
                url: url.clone(),
                options: self.s3.clone(),
            },
            None => crate::store::BlobConfig::Local,
        }
    }

    /// The upload memory budget in KiB (the unit of [`crate::http::AppState::upload_memory`]).
    pub fn upload_memory_kib(&self) -> u64 {
        self.upload_memory_mb.min(MAX_UPLOAD_MEMORY_MB) * 1024
    }
}

impl Default for Config {
    fn default() -> Self {
        Self {
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: PathBuf::from("data"),
            database_url: None,
            blob_url: None,
            s3: crate::store::S3Options::default(),
            role: Role::All,
            workers: None,
            device: DevicePolicy::Auto,
            max_upload_bytes: 1 << 30,
            max_gaussians: 10_000_000,
            max_verify_images: 64,
            max_image_side: 4096,
            max_verify_pixels: 1 << 24,
            verify_concurrency: 2,
            verify_wait_ms: 2000,
            upload_concurrency: 2,
            upload_wait_ms: 10_000,
            upload_memory_mb: 4096,
            body_idle_timeout_ms: 30_000,
            header_timeout_ms: 10_000,
            verify_per_minute: 120,
            auth_failures_per_minute: 30,
            fpr: 1e-6,
            lease_seconds: 60,
            max_attempts: 3,
            master_key_file: None,
            weights_dir: None,
            views: ViewDefaults::default(),
            steps: 350,
            log_json: false,
        }
    }
}

/// Why the configuration was rejected.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("environment variable {name}={value:?}: {message}")]
    Env {
        name: &'static str,
        value: String,
        message: String,
    },
    #[error("invalid configuration: {0}")]
    Invalid(String),
}

impl Config {
    /// [`Config::body_idle_timeout_ms`] as a duration.
    pub fn body_idle_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_millis(self.body_idle_timeout_ms)
    }

    /// [`Config::header_timeout_ms`] as a duration.
    pub fn header_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_millis(self.header_timeout_ms)
    }

    /// Defaults overlaid with the TOML file `path` (when given).
    pub fn from_file(path: Option<&Path>) -> Result<Self, ConfigError> {
        let Some(path) = path else {
            return Ok(Self::default());
        };
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        toml::from_str(&text).map_err(|e| ConfigError::Parse {
            path: path.to_owned(),
            message: e.to_string(),
        })
    }

    /// Overlays `SPLATMARK_*` variables read through `get` (the process environment in `serve`;
    /// a map in tests).
    pub fn with_env(mut self, get: impl Fn(&str) -> Option<String>) -> Result<Self, ConfigError> {
        fn parse<T: std::str::FromStr>(name: &'static str, value: String) -> Result<T, ConfigError>
        where
            T::Err: std::fmt::Display,
        {
            value.trim().parse().map_err(|e: T::Err| ConfigError::Env {
                name,
                message: e.to_string(),
                value,
            })
        }
        macro_rules! env {
            ($name:literal, $field:expr) => {
                if let Some(v) = get($name) {
                    $field = parse($name, v)?;
                }
            };
            ($name:literal, some $field:expr) => {
                if let Some(v) = get($name) {
                    $field = Some(parse($name, v)?);
                }
            };
        }
        env!("SPLATMARK_BIND", self.bind);
        env!("SPLATMARK_DATA_DIR", self.data_dir);
        if let Some(v) = get("SPLATMARK_DATABASE_URL") {
            // Parsed here, not by `env!`: its error would repeat the value, password and all.
            let db = crate::store::Database::parse(&v).map_err(|e| ConfigError::Env {
                name: "SPLATMARK_DATABASE_URL",
                value: crate::store::database::redact(&v),
                message: e.to_string(),
            })?;
            self.database_url = Some(db);
        }
        if let Some(v) = get("SPLATMARK_BLOB_URL") {
            let v = v.trim().to_owned();
            self.blob_url = if v.is_empty() {
                None
            } else {
                // Parsed here, not by `env!`: its error would repeat the value.
                Some(
                    crate::store::BlobUrl::parse(&v).map_err(|e| ConfigError::Env {
                        name: "SPLATMARK_BLOB_URL",
                        value: crate::store::database::redact(&v),
                        message: e.to_string(),
                    })?,
                )
            };
        }
        env!(
            "SPLATMARK_S3_MULTIPART_THRESHOLD",
            self.s3.multipart_threshold
        );
        env!("SPLATMARK_S3_PART_SIZE", self.s3.part_size);
        env!("SPLATMARK_S3_CACHE_MAX_BYTES", self.s3.cache_max_bytes);
        env!("SPLATMARK_ROLE", self.role);
        env!("SPLATMARK_WORKERS", some self.workers);
        if let Some(v) = get("SPLATMARK_DEVICE") {
            self.device = match v.trim() {
                "auto" => DevicePolicy::Auto,
                "cpu" => DevicePolicy::Cpu,
                "wgpu" => DevicePolicy::Wgpu,
                _ => {
                    return Err(ConfigError::Env {
                        name: "SPLATMARK_DEVICE",
                        value: v,
                        message: "expected auto, cpu or wgpu".into(),
                    });
                }
            };
        }
        env!("SPLATMARK_MAX_UPLOAD_BYTES", self.max_upload_bytes);
        env!("SPLATMARK_MAX_GAUSSIANS", self.max_gaussians);
        env!("SPLATMARK_FPR", self.fpr);
        env!("SPLATMARK_MAX_VERIFY_PIXELS", self.max_verify_pixels);
        env!("SPLATMARK_VERIFY_CONCURRENCY", self.verify_concurrency);
        env!("SPLATMARK_UPLOAD_CONCURRENCY", self.upload_concurrency);
        env!("SPLATMARK_UPLOAD_MEMORY_MB", self.upload_memory_mb);
        env!("SPLATMARK_LEASE_SECONDS", self.lease_seconds);
        env!("SPLATMARK_MAX_ATTEMPTS", self.max_attempts);
        env!("SPLATMARK_MASTER_KEY_FILE", some self.master_key_file);
        env!("SPLATMARK_WEIGHTS_DIR", some self.weights_dir);
        env!("SPLATMARK_STEPS", self.steps);
        env!("SPLATMARK_LOG_JSON", self.log_json);
        Ok(self)
    }

    /// Checks the values that have a valid range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: &str| Err(ConfigError::Invalid(m.into()));
        if !(self.fpr > 0.0 && self.fpr < 1.0) {
            return bad("fpr must be in (0, 1)");
        }
        if self.lease_seconds < 3 {
            return bad("lease_seconds must be at least 3");
        }
        if self.max_attempts == 0 {
            return bad("max_attempts must be at least 1");
        }
        if self.workers == Some(0) {
            return bad("workers must be at least 1");
        }
        if self.max_verify_images == 0 {
            return bad("max_verify_images must be at least 1");
        }
        if self.views.orbit < 2
            || self.views.orbit_long < 2
            || self.views.width < 16
            || self.views.height < 16
        {
            return bad("views need at least 2 orbit views of at least 16×16 pixels");
        }
        if self.verify_concurrency == 0 {
            return bad("verify_concurrency must be at least 1");
        }
        if self.body_idle_timeout_ms == 0 {
            return bad("body_idle_timeout_ms must be at least 1");
        }
        if self.verify_per_minute == 0 || self.auth_failures_per_minute == 0 {
            return bad("verify_per_minute and auth_failures_per_minute must be at least 1");
        }
        if self.header_timeout_ms == 0 {
            return bad("header_timeout_ms must be at least 1");
        }
        if self.upload_concurrency == 0 {
            return bad("upload_concurrency must be at least 1");
        }
        if !(1..=MAX_UPLOAD_MEMORY_MB).contains(&self.upload_memory_mb) {
            return bad("upload_memory_mb must be between 1 and 4194304 (4 TiB)");
        }
        if self.max_verify_pixels < 64 * 64 {
            return bad("max_verify_pixels must allow one 64×64 image");
        }
        if self.s3.part_size < crate::store::s3::MIN_PART_SIZE {
            return bad("s3.part_size must be at least 5242880 (5 MiB, S3's smallest part)");
        }
        if self.s3.multipart_threshold == 0 {
            return bad("s3.multipart_threshold must be at least 1");
        }
        if self.max_image_side < 64 {
            return bad("max_image_side must be at least 64 (the decoder reads ≥ 64 px)");
        }
        Ok(())
    }

    /// The master key file in effect.
    pub fn master_key_path(&self) -> PathBuf {
        self.master_key_file
            .clone()
            .unwrap_or_else(|| self.data_dir.join("master.key"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn env(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let m: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| m.get(k).cloned()
    }

    #[test]
    fn defaults_work_on_a_fresh_machine() {
        let c = Config::default();
        c.validate().unwrap();
        assert_eq!(c.bind.to_string(), "127.0.0.1:8080");
        assert_eq!(c.data_dir, PathBuf::from("data"));
        assert_eq!(c.master_key_path(), PathBuf::from("data/master.key"));
    }

    #[test]
    fn file_then_env_override_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("s.toml");
        std::fs::write(
            &f,
            "bind = \"0.0.0.0:9000\"\nworkers = 2\nfpr = 1e-4\n[views]\norbit = 12\n",
        )
        .unwrap();
        let c = Config::from_file(Some(&f)).unwrap();
        assert_eq!(c.bind.port(), 9000);
        assert_eq!(c.workers, Some(2));
        assert_eq!(c.views.orbit, 12);
        assert_eq!(c.views.width, 512, "unnamed fields keep their defaults");
        let c = c
            .with_env(env(&[
                ("SPLATMARK_WORKERS", "3"),
                ("SPLATMARK_DEVICE", "cpu"),
            ]))
            .unwrap();
        assert_eq!(c.workers, Some(3));
        assert_eq!(c.device, DevicePolicy::Cpu);
        assert_eq!(
            c.bind.port(),
            9000,
            "the file's value stays when env is silent"
        );
    }

    #[test]
    fn typos_and_bad_values_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("s.toml");
        std::fs::write(&f, "bnd = \"0.0.0.0:9000\"\n").unwrap();
        let e = Config::from_file(Some(&f)).unwrap_err().to_string();
        assert!(e.contains("bnd"), "{e}");
        let e = Config::default()
            .with_env(env(&[("SPLATMARK_WORKERS", "many")]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("SPLATMARK_WORKERS"), "{e}");
        let c = Config {
            fpr: 0.0,
            ..Config::default()
        };
        assert!(c.validate().is_err());
    }

    #[test]
    fn the_blob_url_is_read_and_the_s3_secret_never_shown() {
        use crate::store::BlobConfig;
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(Config::default().blobs(), BlobConfig::Local);
        let f = dir.path().join("s.toml");
        std::fs::write(
            &f,
            "blob_url = \"s3://splats/prod\"\n[s3]\nendpoint = \"http://127.0.0.1:8333\"\n\
             access_key_id = \"AKIDEXAMPLE\"\nsecret_access_key = \"wJalrXUtnFEMI-hunter2\"\n",
        )
        .unwrap();
        let c = Config::from_file(Some(&f)).unwrap();
        c.validate().unwrap();
        match c.blobs() {
            BlobConfig::S3 { url, options } => {
                assert_eq!(url.to_string(), "s3://splats/prod");
                assert_eq!(
                    options.secret_access_key.as_ref().map(|s| s.expose()),
                    Some("wJalrXUtnFEMI-hunter2")
                );
            }
            other => panic!("{other:?}"),
        }
        for shown in [
            format!("{c:?}"),
            format!("{:?}", c.blobs()),
            toml::to_string(&c).unwrap(),
        ] {
            assert!(!shown.contains("hunter2"), "{shown}");
        }
        let c = Config::default()
            .with_env(env(&[
                ("SPLATMARK_BLOB_URL", "s3://other-bucket"),
                ("SPLATMARK_S3_PART_SIZE", "6291456"),
                ("SPLATMARK_S3_CACHE_MAX_BYTES", "1073741824"),
            ]))
            .unwrap();
        assert_eq!(c.blob_url.as_ref().unwrap().bucket(), "other-bucket");
        assert_eq!(c.s3.part_size, 6 << 20);
        assert_eq!(c.s3.cache_max_bytes, 1 << 30);
        let e = Config::default()
            .with_env(env(&[(
                "SPLATMARK_BLOB_URL",
                "s3://AKID:wJalrXUtnFEMI-hunter2@splats/x",
            )]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("SPLATMARK_BLOB_URL") && !e.contains("hunter2"),
            "{e}"
        );
        let small = Config {
            s3: crate::store::S3Options {
                part_size: 1 << 20,
                ..Default::default()
            },
            ..Config::default()
        };
        assert!(small.validate().is_err());
    }

    #[test]
    fn the_database_url_is_read_and_its_password_never_shown() {
        use crate::store::{Backend, Database};
        let dir = tempfile::tempdir().unwrap();
        let c = Config {
            data_dir: dir.path().into(),
            ..Config::default()
        };
        assert_eq!(c.database(), Database::in_data_dir(dir.path()));
        let url = "postgres://app:hunter2@db.internal:5432/sm";
        let c = c.with_env(env(&[("SPLATMARK_DATABASE_URL", url)])).unwrap();
        assert_eq!(c.database().backend(), Backend::Postgres);
        for shown in [format!("{c:?}"), toml::to_string(&c).unwrap()] {
            assert!(!shown.contains("hunter2"), "{shown}");
        }
        let f = dir.path().join("s.toml");
        std::fs::write(&f, format!("database_url = \"{url}\"\n")).unwrap();
        assert_eq!(
            Config::from_file(Some(&f)).unwrap().database().backend(),
            Backend::Postgres
        );
        let e = Config::default()
            .with_env(env(&[(
                "SPLATMARK_DATABASE_URL",
                "mysql://app:hunter2@h/db",
            )]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("SPLATMARK_DATABASE_URL") && !e.contains("hunter2"),
            "{e}"
        );
    }
}
