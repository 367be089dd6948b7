//! `splatmark serve` (the service), `splatmark keys create` (API keys from the shell), `keys
//! rotate-master` and `keys decoders` (which decoders the registered watermarks need).

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

use crate::config::{Config, DevicePolicy};
use crate::store::{Scope, Store};

/// Flags of `serve`: each overrides the config file and the environment.
#[derive(Args, Debug)]
pub(crate) struct ServeArgs {
    /// TOML config file (see deploy/splatmark.toml); default: $SPLATMARK_CONFIG when set.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Address to listen on (default 127.0.0.1:8080).
    #[arg(long)]
    bind: Option<SocketAddr>,
    /// Folder for the database, blobs and master key (default ./data).
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// What this process runs: all (API and workers, default), api, or worker (workers with
    /// /healthz, /readyz and /metrics).
    #[arg(long)]
    role: Option<crate::config::Role>,
    /// Number of workers (default: one per GPU adapter, or one CPU worker).
    #[arg(long)]
    workers: Option<usize>,
    /// auto, cpu or wgpu.
    #[arg(long)]
    device: Option<String>,
    /// Log as JSON lines.
    #[arg(long)]
    log_json: bool,
}

impl ServeArgs {
    /// Defaults < file < environment < flags.
    pub(crate) fn config(&self) -> Result<Config> {
        let file = self
            .config
            .clone()
            .or_else(|| std::env::var_os("SPLATMARK_CONFIG").map(PathBuf::from));
        let mut c = Config::from_file(file.as_deref())?.with_env(|k| std::env::var(k).ok())?;
        if let Some(b) = self.bind {
            c.bind = b;
        }
        if let Some(d) = &self.data_dir {
            c.data_dir = d.clone();
        }
        if let Some(r) = self.role {
            c.role = r;
        }
        if let Some(w) = self.workers {
            c.workers = Some(w);
        }
        if let Some(d) = &self.device {
            c.device = match d.as_str() {
                "auto" => DevicePolicy::Auto,
                "cpu" => DevicePolicy::Cpu,
                "wgpu" => DevicePolicy::Wgpu,
                _ => anyhow::bail!("--device must be auto, cpu or wgpu"),
            };
        }
        c.log_json |= self.log_json;
        c.validate()?;
        Ok(c)
    }
}

fn init_tracing(json: bool) {
    let filter =
        tracing_subscriber::EnvFilter::try_from_env("SPLATMARK_LOG").unwrap_or_else(|_| {
            tracing_subscriber::EnvFilter::new("info,tower_http=info,wgpu=warn,naga=warn")
        });
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = if json {
        b.json().try_init()
    } else {
        b.try_init()
    };
}

pub(crate) fn serve_cmd(a: &ServeArgs) -> Result<()> {
    let cfg = a.config()?;
    init_tracing(cfg.log_json);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(crate::app::serve(cfg))
}

#[derive(Subcommand, Debug)]
pub(crate) enum KeysCommand {
    /// Create an API key and print its token (shown once; only its hash is stored).
    Create {
        /// A name for the key (who or what uses it).
        #[arg(long)]
        name: String,
        /// Comma-separated scopes: owner, verifier, auditor, admin.
        #[arg(long, value_delimiter = ',', required = true)]
        scope: Vec<String>,
        #[command(flatten)]
        serve: ServeArgs,
    },
    /// List the decoders the registered watermarks were written for, how many keys name each
    /// and where this server finds it (JSON on stdout). Exits with an error when some decoder is
    /// not held: copy its files into the weights folder's archive/ (weights/README.md). Run it
    /// after replacing a decoder or upgrading.
    Decoders {
        #[command(flatten)]
        serve: ServeArgs,
    },
    /// Re-seal every secret under a fresh master key, atomically, with the service stopped.
    /// The new key is written next to the old one first (`<key file>.new`, 0600), then the
    /// database is re-sealed in one transaction, then the new file replaces the old one; with
    /// `SPLATMARK_MASTER_KEY` set, the new key goes to `--new-key-file` instead.
    RotateMaster {
        /// Where to write the new key when the current one comes from the environment.
        #[arg(long)]
        new_key_file: Option<PathBuf>,
        #[command(flatten)]
        serve: ServeArgs,
    },
}

pub(crate) fn keys_cmd(c: &KeysCommand) -> Result<()> {
    let (name, scope, serve) = match c {
        KeysCommand::Create { name, scope, serve } => (name, scope, serve),
        KeysCommand::RotateMaster {
            new_key_file,
            serve,
        } => return rotate_master_cmd(new_key_file.as_deref(), serve),
        KeysCommand::Decoders { serve } => return decoders_cmd(serve),
    };
    let scopes = scope
        .iter()
        .map(|s| {
            s.trim()
                .parse::<Scope>()
                .map_err(|e| anyhow::anyhow!("{e}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let cfg = serve.config()?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async {
        std::fs::create_dir_all(&cfg.data_dir)?;
        let store = open_store(&cfg).await?;
        let (key, token) = store.create_api_key("cli", name, &scopes).await?;
        eprintln!(
            "created API key {} ({}) with scopes {:?}",
            key.id, key.name, key.scopes
        );
        println!("{token}");
        Ok(())
    })
}

/// The service's store as `cfg` names it, opened with its master key.
async fn open_store(cfg: &Config) -> Result<Store> {
    Ok(Store::open_with_blobs(
        &cfg.data_dir,
        &cfg.database(),
        &cfg.blobs(),
        crate::app::master_key(cfg)?,
    )
    .await?)
}

fn decoders_cmd(serve: &ServeArgs) -> Result<()> {
    let cfg = serve.config()?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let regs = rt.block_on(async { anyhow::Ok(open_store(&cfg).await?.registrations().await?) })?;
    let rows = crate::decoder::registry::survey(
        cfg.weights_dir.as_deref(),
        regs.iter().map(|r| (r.key.bits(), r.decoder.as_deref())),
    )?;
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({ "decoders": rows }))?
    );
    let missing: usize = rows
        .iter()
        .filter(|r| r.held.is_none())
        .map(|r| r.keys)
        .sum();
    if missing > 0 {
        anyhow::bail!(
            "{missing} registered watermark(s) name a decoder this server does not hold: put its \
             files in the weights folder's archive/ (weights/README.md)"
        );
    }
    Ok(())
}

/// Flags of `backup`.
#[derive(Args, Debug)]
pub(crate) struct BackupArgs {
    /// Folder to write the backup to (must not exist or be empty).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    serve: ServeArgs,
}

/// Flags of `restore`.
#[derive(Args, Debug)]
pub(crate) struct RestoreArgs {
    /// The backup folder (`splatmark backup --out`).
    #[arg(long)]
    from: PathBuf,
    #[command(flatten)]
    serve: ServeArgs,
}

/// `backup` and `restore` copy an SQLite file and the blobs: a PostgreSQL database is backed up
/// with the server's own tools.
fn sqlite_only(cfg: &Config, command: &str) -> Result<()> {
    if let Some(url) = &cfg.blob_url {
        anyhow::bail!(
            "`{command}` copies the blob folder; the blobs are in an object store ({url}): back \
             the bucket up with its own tools (versioning, replication, a copy)"
        );
    }
    let db = cfg.database();
    match db {
        crate::store::Database::Sqlite(ref path)
            if *path == cfg.data_dir.join(crate::store::DB_FILE) =>
        {
            Ok(())
        }
        crate::store::Database::Sqlite(_) => anyhow::bail!(
            "`{command}` works on DATA_DIR/{} only; the configured database is {db}",
            crate::store::DB_FILE
        ),
        crate::store::Database::Postgres(_) => anyhow::bail!(
            "`{command}` copies an SQLite database; the configured database is PostgreSQL ({db}): back it up \
             with pg_dump / pg_basebackup (and the blob folder {} alongside)",
            cfg.data_dir.join(crate::store::BLOB_DIR).display()
        ),
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?)
}

pub(crate) fn backup_cmd(a: &BackupArgs) -> Result<()> {
    let cfg = a.serve.config()?;
    sqlite_only(&cfg, "backup")?;
    let m = runtime()?.block_on(crate::store::backup::backup(&cfg.data_dir, &a.out))?;
    eprintln!(
        "backed up {} assets, {} blobs and {} audit rows to {}",
        m.assets,
        m.blobs.len(),
        m.audit_rows,
        a.out.display()
    );
    println!("{}", serde_json::to_string_pretty(&m)?);
    Ok(())
}

pub(crate) fn restore_cmd(a: &RestoreArgs) -> Result<()> {
    let cfg = a.serve.config()?;
    sqlite_only(&cfg, "restore")?;
    // The master key the backup was taken under must be there already: a fresh one would
    // open none of the restored keys.
    let master = if std::env::var_os(crate::store::MASTER_KEY_ENV).is_some()
        || cfg.master_key_path().is_file()
    {
        crate::app::master_key(&cfg)?
    } else {
        anyhow::bail!(
            "no master key: put the key the backup was taken under in {} (or {})",
            cfg.master_key_path().display(),
            crate::store::MASTER_KEY_ENV
        );
    };
    runtime()?.block_on(async {
        let m = crate::store::backup::restore(&a.from, &cfg.data_dir).await?;
        let store = match Store::open(&cfg.data_dir, master).await {
            Ok(s) => s,
            Err(e) => {
                // Leave the folder as it was found.
                for suffix in ["", "-wal", "-shm"] {
                    let db = format!("{}{suffix}", crate::store::DB_FILE);
                    let _ = std::fs::remove_file(cfg.data_dir.join(db));
                }
                let _ = std::fs::remove_dir_all(cfg.data_dir.join(crate::store::BLOB_DIR));
                return Err(anyhow::anyhow!(e)).context("the restored database does not open");
            }
        };
        let integrity = store.integrity_check().await?;
        let chain = store.verify_audit_chain().await?;
        store.close().await;
        let ok = integrity == "ok" && chain.ok && chain.head_hash == m.audit_head;
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "ok": ok,
                "assets": m.assets,
                "blobs": m.blobs.len(),
                "audit_rows": chain.rows,
                "audit_chain_ok": chain.ok,
                "audit_head": chain.head_hash,
                "integrity_check": integrity,
            }))?
        );
        anyhow::ensure!(ok, "the restored data does not verify");
        Ok(())
    })
}

fn rotate_master_cmd(new_key_file: Option<&std::path::Path>, serve: &ServeArgs) -> Result<()> {
    let cfg = serve.config()?;
    // The folder's lock below is what keeps every server away from a rotation; processes on
    // other machines sharing a PostgreSQL database do not take it.
    if let db @ crate::store::Database::Postgres(_) = cfg.database() {
        anyhow::bail!(
            "rotating the master key of a PostgreSQL database ({db}) is not supported yet: no \
             lock keeps the processes of other machines from sealing under the old key meanwhile"
        );
    }
    anyhow::ensure!(
        cfg.data_dir.join(crate::store::DB_FILE).is_file(),
        "no database in {}",
        cfg.data_dir.display()
    );
    // No server may run beside a rotation: it would go on sealing under the old key.
    let _lock =
        crate::store::DataDirLock::acquire(&cfg.data_dir, crate::store::LockMode::Exclusive)?;
    let from_env = std::env::var_os(crate::store::MASTER_KEY_ENV).is_some();
    let current_file = cfg.master_key_path();
    anyhow::ensure!(
        from_env || current_file.is_file(),
        "no master key at {} (nor {})",
        current_file.display(),
        crate::store::MASTER_KEY_ENV
    );
    let (staged, final_path) = match (from_env, new_key_file) {
        (true, Some(f)) => (f.to_path_buf(), None),
        (true, None) => anyhow::bail!(
            "the master key comes from {}: say where the new one goes with --new-key-file",
            crate::store::MASTER_KEY_ENV
        ),
        (false, _) => {
            let mut s = current_file.clone().into_os_string();
            s.push(".new");
            (PathBuf::from(s), Some(current_file.clone()))
        }
    };
    anyhow::ensure!(
        !staged.exists(),
        "{} exists (left by an interrupted rotation?): if the database opens with it, move it \
         over the key file; otherwise remove it",
        staged.display()
    );
    let old = crate::app::master_key(&cfg)?;
    let new = crate::store::MasterKey::load_or_create_file(&staged)
        .with_context(|| format!("cannot write the new key {}", staged.display()))?;
    runtime()?.block_on(async {
        let store = Store::open_with(&cfg.data_dir, &cfg.database(), old).await?;
        let n = store.rotate_master_key(&new, "cli").await?;
        store.close().await;
        if let Some(f) = &final_path {
            std::fs::rename(&staged, f).with_context(|| {
                format!(
                    "the database is re-sealed under {}: move it over {} by hand",
                    staged.display(),
                    f.display()
                )
            })?;
        }
        eprintln!(
            "re-sealed {n} secrets under the new master key in {}",
            final_path.as_ref().unwrap_or(&staged).display()
        );
        Ok(())
    })
}
