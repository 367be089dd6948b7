//! The service put together: configuration → store → worker pool → HTTP server, with graceful
//! shutdown. `splatmark serve` runs it; the integration tests start it on 127.0.0.1:0.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use burn::tensor::Device;
use tokio::sync::{Notify, watch};
use tokio::task::JoinHandle;

use crate::config::Config;
use crate::http::{AppState, Decoders, Metrics, router};
use crate::queue::{Pool, WorkerSpec, plan_workers, start};
use crate::store::{DataDirLock, LockMode, MasterKey, Scope, Store};

/// A running service.
pub struct App {
    /// The address it listens on (the real port when the config asked for port 0).
    pub addr: SocketAddr,
    pub store: Store,
    /// Where the bootstrap admin token was written, on the first start only.
    pub admin_token_file: Option<PathBuf>,
    shutdown: watch::Sender<bool>,
    server: JoinHandle<std::io::Result<()>>,
    pool: Pool,
    /// Held shared while the app runs: no master-key rotation beside it (`store::lock`).
    _lock: DataDirLock,
}

impl App {
    /// Opens the store under `cfg.data_dir`, starts the workers (as planned from `cfg`, or
    /// `workers` when given) and the HTTP server; returns once it listens.
    pub async fn start(
        cfg: Config,
        master: MasterKey,
        workers: Option<Vec<WorkerSpec>>,
    ) -> Result<App> {
        cfg.validate()?;
        std::fs::create_dir_all(&cfg.data_dir)
            .with_context(|| format!("cannot create {}", cfg.data_dir.display()))?;
        let lock = DataDirLock::acquire(&cfg.data_dir, LockMode::Shared)?;
        let database = cfg.database();
        let blobs = cfg.blobs();
        let store = Store::open_with_blobs(&cfg.data_dir, &database, &blobs, master)
            .await
            .with_context(|| {
                let at = match &blobs {
                    crate::store::BlobConfig::S3 { url, .. } => url.to_string(),
                    crate::store::BlobConfig::Local => cfg.data_dir.display().to_string(),
                };
                format!("cannot open the store ({database}, blobs in {at})")
            })?;
        let admin_token_file = if cfg.role.serves_api() {
            bootstrap_admin(&store, &cfg).await?
        } else {
            None
        };
        let listener = tokio::net::TcpListener::bind(cfg.bind)
            .await
            .with_context(|| format!("cannot listen on {}", cfg.bind))?;
        let addr = listener.local_addr()?;
        let workers = match workers {
            _ if !cfg.role.runs_workers() => Vec::new(),
            Some(w) => w,
            None => plan_workers(&cfg).await,
        };
        let cfg_header_timeout = cfg.header_timeout();
        let cfg_limits = (cfg.verify_per_minute, cfg.auth_failures_per_minute);
        let cfg = Arc::new(cfg);
        let (shutdown, rx) = watch::channel(false);
        let wake = Arc::new(Notify::new());
        let pool = start(
            store.clone(),
            cfg.clone(),
            workers,
            wake.clone(),
            rx.clone(),
        );
        let verify_slots = Arc::new(tokio::sync::Semaphore::new(cfg.verify_concurrency.max(1)));
        let upload_slots = Arc::new(tokio::sync::Semaphore::new(cfg.upload_concurrency.max(1)));
        let upload_memory = Arc::new(tokio::sync::Semaphore::new(
            usize::try_from(cfg.upload_memory_kib()).unwrap_or(usize::MAX >> 4),
        ));
        let state = AppState {
            store: store.clone(),
            cfg,
            wake,
            pool: pool.status.clone(),
            decoders: Arc::new(Decoders::new(Device::flex())),
            metrics: Arc::new(Metrics::default()),
            verify_slots,
            upload_slots,
            upload_memory,
            limits: Arc::new(crate::http::limit::Limits::new(cfg_limits.0, cfg_limits.1)),
        };
        let role = state.cfg.role;
        let app = if role.serves_api() {
            router(state)
        } else {
            crate::http::ops_router(state)
        };
        let rx_gc = rx.clone();
        let rx_server = rx;
        let header_timeout = cfg_header_timeout;
        let server = tokio::spawn(crate::http::server::serve(
            listener,
            app,
            header_timeout,
            rx_server,
        ));
        if role.serves_api() {
            tokio::spawn(collect_garbage_periodically(store.clone(), rx_gc));
        }
        tracing::info!(%addr, ?role, "splatmark listening");
        Ok(App {
            addr,
            store,
            admin_token_file,
            shutdown,
            server,
            pool,
            _lock: lock,
        })
    }

    /// Asks the server and the workers to stop.
    pub fn shutdown(&self) {
        let _ = self.shutdown.send(true);
    }

    /// Stops and waits: in-flight requests finish; a running job is cancelled and released back
    /// to the queue (its attempt not counted).
    pub async fn stop(self) -> Result<()> {
        self.shutdown();
        self.server.await??;
        self.pool.join().await;
        Ok(())
    }
}

/// Blobs no asset references are removed once they are this old (a failed publish or upload
/// leaves its blob behind; the age keeps blobs whose asset row is being written).
pub const BLOB_GC_MIN_AGE: std::time::Duration = std::time::Duration::from_secs(24 * 3600);

/// How often the service collects unreferenced blobs (first run at start).
pub const BLOB_GC_EVERY: std::time::Duration = std::time::Duration::from_secs(3600);

async fn collect_garbage_periodically(store: Store, mut shutdown: watch::Receiver<bool>) {
    loop {
        match store.collect_garbage(BLOB_GC_MIN_AGE).await {
            Ok(r) if r.removed > 0 => {
                tracing::info!(
                    removed = r.removed,
                    bytes = r.bytes,
                    "removed unreferenced blobs"
                )
            }
            Ok(_) => {}
            Err(e) => tracing::warn!(error = %e, "blob garbage collection failed"),
        }
        tokio::select! {
            _ = tokio::time::sleep(BLOB_GC_EVERY) => {}
            _ = shutdown.wait_for(|&s| s) => return,
        }
    }
}

/// On a store without API keys: creates an admin key and writes its token to
/// `DATA_DIR/admin.token` (mode 0600); the token is never logged.
async fn bootstrap_admin(store: &Store, cfg: &Config) -> Result<Option<PathBuf>> {
    if store.api_key_count().await? > 0 {
        return Ok(None);
    }
    let (_, token) = store
        .create_api_key("system", "bootstrap-admin", &[Scope::Admin])
        .await?;
    let path = cfg.data_dir.join("admin.token");
    write_secret(&path, token.as_bytes())?;
    tracing::warn!(file = %path.display(), "created the first admin API key; its token is in this file");
    Ok(Some(path))
}

/// Writes a secret readable by the owner only.
pub fn write_secret(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let dir = path.parent().unwrap_or(std::path::Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir)?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o600))?;
    }
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    tmp.persist(path)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// The master key: `SPLATMARK_MASTER_KEY` (hex) when set, else the key file (created on first
/// start).
pub fn master_key(cfg: &Config) -> Result<MasterKey> {
    if let Ok(hex) = std::env::var("SPLATMARK_MASTER_KEY") {
        return MasterKey::from_hex(hex.trim())
            .context("SPLATMARK_MASTER_KEY is not a 64-digit hex key");
    }
    let path = cfg.master_key_path();
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d)?;
    }
    MasterKey::load_or_create(&path)
        .with_context(|| format!("cannot load or create the master key {}", path.display()))
}

/// `splatmark serve`: runs until Ctrl-C or SIGTERM, then shuts down gracefully.
pub async fn serve(cfg: Config) -> Result<()> {
    let master = master_key(&cfg)?;
    let app = App::start(cfg, master, None).await?;
    if let Some(f) = &app.admin_token_file {
        eprintln!(
            "admin API token written to {} (keep it secret)",
            f.display()
        );
    }
    eprintln!("splatmark listening on http://{}", app.addr);
    shutdown_signal().await;
    tracing::info!("shutting down");
    app.stop().await
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
