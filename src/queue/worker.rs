//! The worker pool: each worker claims a job under a lease, runs the embedding on a blocking
//! thread while a heartbeat extends the lease and records phase and progress, and publishes the
//! result in one transaction that only succeeds while it still holds the lease — so a result
//! is published exactly once even when a worker dies mid-job and the job is retried.

use std::ops::ControlFlow;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use burn::tensor::Device;
use serde_json::json;
use tokio::sync::{Notify, watch};
use tokio::task::JoinHandle;
use tracing::Instrument;

use super::run::{JobError, execute};
use super::spec::JobSpec;
use crate::config::Config;
use crate::decoder::registry::Pair;
use crate::embed::pipeline::{EmbedError, Phase, Progress};
use crate::render::gpu::Rasterizer;
use crate::scene::Limits;
use crate::store::{
    AssetKind, AuditEntry, BlobRef, Claimed, NewAsset, ProgressUpdate, Store, StoreError,
};

/// One worker: a name (in logs, the job row and the audit log), the device of its networks and
/// the rasterizer that renders and back-propagates its jobs' views.
#[derive(Clone, Debug)]
pub struct WorkerSpec {
    pub name: String,
    pub device: Device,
    pub rasterizer: Rasterizer,
}

/// Counters for `/metrics` and `/readyz`.
#[derive(Debug, Default)]
pub struct PoolStatus {
    /// Each worker's name and the rasterizer it runs jobs on (`cpu`, or the adapter).
    pub devices: Vec<(String, String)>,
    pub workers: AtomicUsize,
    pub alive: AtomicUsize,
    pub busy: AtomicUsize,
    pub published: AtomicU64,
    pub failed: AtomicU64,
}

/// Running workers.
pub struct Pool {
    pub status: Arc<PoolStatus>,
    handles: Vec<JoinHandle<()>>,
}

impl Pool {
    /// Waits for every worker to stop (after the shutdown signal; a running job is cancelled
    /// and left to be re-queued when its lease expires).
    pub async fn join(self) {
        for h in self.handles {
            if let Err(e) = h.await {
                tracing::error!(error = %e, "worker task failed");
            }
        }
    }
}

/// Shared by the workers.
struct Ctx {
    store: Store,
    cfg: Arc<Config>,
    wake: Arc<Notify>,
    status: Arc<PoolStatus>,
    shutdown: watch::Receiver<bool>,
}

/// Starts `workers`.
pub fn start(
    store: Store,
    cfg: Arc<Config>,
    workers: Vec<WorkerSpec>,
    wake: Arc<Notify>,
    shutdown: watch::Receiver<bool>,
) -> Pool {
    let status = Arc::new(PoolStatus {
        devices: workers
            .iter()
            .map(|w| (w.name.clone(), w.rasterizer.describe()))
            .collect(),
        ..PoolStatus::default()
    });
    status.workers.store(workers.len(), Ordering::Relaxed);
    let ctx = Arc::new(Ctx {
        store,
        cfg,
        wake,
        status: status.clone(),
        shutdown,
    });
    let handles = workers
        .into_iter()
        .map(|w| tokio::spawn(worker_loop(ctx.clone(), w)))
        .collect();
    Pool { status, handles }
}

/// The decoder weights for `bits`: `weights_dir/decoder-{bits}.bpk` when present, else shipped.
pub fn weights_path(cfg: &Config, bits: usize) -> Option<PathBuf> {
    crate::decoder::registry::folder_artifact(cfg.weights_dir.as_deref(), bits)
}

/// Message lengths this server can embed and verify.
pub fn available_bits(cfg: &Config) -> Vec<usize> {
    [32, 48, 64]
        .into_iter()
        .filter(|&b| weights_path(cfg, b).is_some() || crate::decoder::artifact::is_shipped(b))
        .collect()
}

async fn worker_loop(ctx: Arc<Ctx>, w: WorkerSpec) {
    ctx.status.alive.fetch_add(1, Ordering::Relaxed);
    let lease = Duration::from_secs(ctx.cfg.lease_seconds);
    let mut shutdown = ctx.shutdown.clone();
    let mut last_sweep: Option<Instant> = None;
    tracing::info!(worker = %w.name, device = ?w.device, rasterizer = %w.rasterizer.describe(), "worker started");
    while !*shutdown.borrow() {
        if last_sweep.is_none_or(|t| t.elapsed() >= lease / 2) {
            match ctx.store.requeue_expired().await {
                Ok(0) => {}
                Ok(n) => {
                    tracing::warn!(worker = %w.name, jobs = n, "re-queued jobs whose lease expired")
                }
                Err(e) => tracing::error!(error = %e, "lease sweep failed"),
            }
            last_sweep = Some(Instant::now());
        }
        match ctx.store.claim(&w.name, lease).await {
            Ok(Some(c)) => {
                ctx.status.busy.fetch_add(1, Ordering::Relaxed);
                let span = tracing::info_span!("job", id = %c.job.id, worker = %w.name, attempt = c.job.attempts);
                run_job(&ctx, &w, c).instrument(span).await;
                ctx.status.busy.fetch_sub(1, Ordering::Relaxed);
            }
            Ok(None) => {
                tokio::select! {
                    _ = ctx.wake.notified() => {}
                    _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                    _ = shutdown.changed() => {}
                }
            }
            Err(e) => {
                tracing::error!(worker = %w.name, error = %e, "claim failed");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
    ctx.status.alive.fetch_sub(1, Ordering::Relaxed);
    tracing::info!(worker = %w.name, "worker stopped");
}

/// Progress of the running job as the heartbeat reports it. `clock`: when the steps being
/// timed started, and the step count then.
fn update(p: &Progress, clock: &mut Option<(Instant, usize)>) -> ProgressUpdate {
    update_at(p, clock, Instant::now())
}

/// [`update`] at `now`.
fn update_at(p: &Progress, clock: &mut Option<(Instant, usize)>, now: Instant) -> ProgressUpdate {
    let phase = match p.phase {
        Phase::Targets => "targets",
        Phase::Plan => "plan",
        Phase::Calibrate => "calibrate",
        Phase::Finetune => "finetune",
        Phase::Done => "publish",
    };
    let eta_seconds = match (p.phase, *clock) {
        (Phase::Finetune, Some((t0, base))) if p.log.is_some() && p.step > base => {
            let per_step = now.duration_since(t0).as_secs_f64() / (p.step - base) as f64;
            Some(per_step * p.total.saturating_sub(p.step) as f64)
        }
        _ => None,
    };
    // The steps' clock starts at each phase's report (step reports carry their step's log),
    // so the ETA counts the steps since finetuning started — or restarted after a decoder
    // switch, counting on from the discarded steps.
    if p.log.is_none() || clock.is_none() {
        *clock = Some((now, p.step));
    }
    ProgressUpdate {
        phase: phase.into(),
        step: p.step as u64,
        total: p.total as u64,
        eta_seconds,
    }
}

async fn run_job(ctx: &Ctx, w: &WorkerSpec, c: Claimed) {
    let job = c.job;
    let token = c.lease_token;
    tracing::info!(asset = %job.asset_id, bits = job.bits, "job claimed");
    let lease = Duration::from_secs(ctx.cfg.lease_seconds);

    let prepared = (|| -> Result<_, String> {
        let spec: JobSpec = serde_json::from_value(job.options.clone())
            .map_err(|e| format!("the job's options cannot be read: {e}"))?;
        Ok(spec)
    })();
    let asset = match ctx.store.get_asset(job.asset_id).await {
        Ok(Some(a)) => a,
        Ok(None) => return fail(ctx, job.id, token, "the asset no longer exists").await,
        Err(e) => return fail(ctx, job.id, token, &e.to_string()).await,
    };
    let mut spec = match prepared {
        Ok(s) => s,
        Err(e) => return fail(ctx, job.id, token, &e).await,
    };
    spec.embed.finetune.rasterizer = w.rasterizer.clone();
    // On S3 the blobs are downloaded (verified) into the local cache: a blocking thread.
    let blobs = ctx.store.blobs().clone();
    let (scene_id, cams_id) = (asset.sha256.clone(), asset.cameras_sha256.clone());
    let fetched = tokio::task::spawn_blocking(move || {
        let s = blobs.path(&scene_id)?;
        let c = match &cams_id {
            Some(h) => Some(blobs.path(h)?),
            None => None,
        };
        let t = blobs.temp_file()?;
        Ok::<_, StoreError>((s, c, t))
    })
    .await
    .map_err(|e| StoreError::Io(std::io::Error::other(e)))
    .and_then(|r| r);
    let (scene_path, cams_path, tmp) = match fetched {
        Ok(x) => x,
        Err(e) => return fail(ctx, job.id, token, &e.to_string()).await,
    };

    let cancel = Arc::new(AtomicBool::new(false));
    let (ptx, prx) = watch::channel::<Option<ProgressUpdate>>(None);
    let weights = weights_path(&ctx.cfg, job.bits as usize);
    let device = w.device.clone();
    let limits = Limits {
        max_gaussians: ctx.cfg.max_gaussians,
        max_file_bytes: None,
    };
    let format = asset.format.clone();
    // The embedded bits are the payload (message ⊕ the job's secret mask): `store::keys`.
    let message = c.key.payload();
    let bits = job.bits as usize;
    let cancel_b = cancel.clone();
    let mut blocking = tokio::task::spawn_blocking(move || {
        let mut tmp = tmp;
        let r = (|| {
            let bytes = std::fs::read(&scene_path)
                .map_err(|e| JobError::Scene(crate::scene::SceneError::IoPlain(e)))?;
            let decoders = Pair::resolve(weights.as_deref(), bits, &device.autodiff())
                .map_err(|e| JobError::Decoder(e.to_string()))?;
            let mut out = std::io::BufWriter::new(tmp.as_file_mut());
            let mut clock = None;
            execute(
                &bytes,
                &format,
                cams_path.as_deref(),
                &spec,
                &message,
                &decoders,
                &limits,
                &mut out,
                |p| {
                    let _ = ptx.send(Some(update(&p, &mut clock)));
                    if cancel_b.load(Ordering::Relaxed) {
                        ControlFlow::Break(())
                    } else {
                        ControlFlow::Continue(())
                    }
                },
            )
        })();
        (r, tmp)
    });

    // Progress is written every 2 s (cheap in SQLite); the lease is extended at least thrice per lease.
    let mut beat = tokio::time::interval((lease / 3).min(Duration::from_secs(2)));
    beat.tick().await;
    let mut shutdown = ctx.shutdown.clone();
    let mut lost = false;
    let mut stopping = false;
    let (result, tmp) = loop {
        tokio::select! {
            r = &mut blocking => match r {
                Ok(x) => break x,
                Err(e) => {
                    let msg = format!("the embedding thread failed: {e}");
                    return fail(ctx, job.id, token, &msg).await;
                }
            },
            _ = beat.tick() => {
                let p = prx.borrow().clone();
                match ctx.store.heartbeat(job.id, token, lease, p.as_ref()).await {
                    Ok(()) => {}
                    Err(StoreError::LeaseLost) => {
                        tracing::warn!("lease lost (cancelled, or expired and taken over): stopping");
                        lost = true;
                        cancel.store(true, Ordering::Relaxed);
                    }
                    Err(e) => tracing::error!(error = %e, "heartbeat failed"),
                }
            },
            _ = shutdown.changed(), if !stopping => {
                tracing::warn!("shutting down: the job stops and goes back to the queue");
                stopping = true;
                cancel.store(true, Ordering::Relaxed);
            }
        }
    };
    let out = match result {
        Ok(out) if !lost => out,
        Ok(_) | Err(JobError::Embed(EmbedError::Cancelled)) => {
            if stopping && !lost {
                // Back to the queue now (not at lease expiry), the attempt not counted.
                match ctx.store.release(job.id, token, "worker shutdown").await {
                    Ok(()) => tracing::info!("job released to the queue"),
                    Err(e) => {
                        tracing::warn!(error = %e, "releasing the job failed; it is re-queued when its lease expires")
                    }
                }
            } else {
                tracing::info!("job stopped before publishing");
            }
            return;
        }
        Err(e) => return fail(ctx, job.id, token, &e.to_string()).await,
    };
    // Record the final progress (phase "publish", step = total) and check the lease is still ours.
    let last = prx.borrow().clone();
    match ctx
        .store
        .heartbeat(job.id, token, lease, last.as_ref())
        .await
    {
        Ok(()) => {}
        Err(StoreError::LeaseLost) => {
            tracing::warn!("lease lost before publishing: the result is discarded");
            return;
        }
        Err(e) => tracing::error!(error = %e, "heartbeat failed"),
    }
    let blobs = ctx.store.blobs().clone();
    let committed = tokio::task::spawn_blocking(move || blobs.commit(tmp)).await;
    let blob = match committed {
        Ok(Ok(b)) => b,
        Ok(Err(e)) => {
            return fail(
                ctx,
                job.id,
                token,
                &format!("storing the scene failed: {e}"),
            )
            .await;
        }
        Err(e) => {
            return fail(
                ctx,
                job.id,
                token,
                &format!("storing the scene failed: {e}"),
            )
            .await;
        }
    };
    let cameras_blob = match &asset.cameras_sha256 {
        Some(h) => {
            let (blobs, id) = (ctx.store.blobs().clone(), h.clone());
            let size = tokio::task::spawn_blocking(move || blobs.size_of(&id))
                .await
                .map_err(|e| StoreError::Io(std::io::Error::other(e)))
                .and_then(|r| r);
            match size {
                Ok(size) => Some(BlobRef {
                    sha256: h.clone(),
                    size,
                }),
                Err(e) => {
                    return fail(ctx, job.id, token, &format!("the cameras blob: {e}")).await;
                }
            }
        }
        None => None,
    };
    let stem = asset
        .file_name
        .as_deref()
        .and_then(|n| {
            n.rsplit_once('.')
                .map(|(s, _)| s.to_string())
                .or(Some(n.to_string()))
        })
        .unwrap_or_else(|| asset.id.to_string());
    let new = NewAsset {
        owner: job.owner.clone(),
        kind: AssetKind::Watermarked,
        parent_id: Some(asset.id),
        source_job_id: Some(job.id),
        blob,
        format: "ply".into(),
        file_name: Some(format!("{stem}-watermarked.ply")),
        gaussians: out.gaussians,
        sh_degree: out.sh_degree,
        cameras_blob,
        cameras_format: asset.cameras_format.clone(),
    };
    let carriers = out.report.get("carriers").cloned().unwrap_or_default();
    let audit = AuditEntry {
        actor: format!("worker:{}", w.name),
        action: "watermark.publish".into(),
        asset_id: Some(asset.id),
        job_id: Some(job.id),
        details: json!({
            "bits": job.bits,
            "gaussians": out.gaussians,
            "carriers": carriers,
            "train_views": out.train_views,
            "held_out_views": out.held_out_views,
        }),
    };
    match ctx
        .store
        .publish_result(
            job.id,
            token,
            new,
            &c.key,
            &out.readout,
            &out.records,
            out.report,
            audit,
        )
        .await
    {
        Ok(a) => {
            ctx.status.published.fetch_add(1, Ordering::Relaxed);
            tracing::info!(result = %a.id, "job published");
        }
        Err(StoreError::LeaseLost) => {
            tracing::warn!("lease lost before publishing: the result is discarded")
        }
        Err(e) => fail(ctx, job.id, token, &format!("publishing failed: {e}")).await,
    }
}

async fn fail(ctx: &Ctx, job: uuid::Uuid, token: uuid::Uuid, error: &str) {
    ctx.status.failed.fetch_add(1, Ordering::Relaxed);
    // The owner reads the recorded text (`GET /v1/jobs/{id}`): the server's own folders are
    // named there only as placeholders; the log keeps the whole text.
    let shown = redact_paths(error, &ctx.cfg.data_dir);
    match ctx.store.fail(job, token, &shown).await {
        Ok(state) => tracing::warn!(%error, ?state, "job failed"),
        Err(StoreError::LeaseLost) => tracing::warn!(%error, "job failed after its lease was lost"),
        Err(e) => tracing::error!(%error, store_error = %e, "recording a job failure failed"),
    }
}

/// `text` with every mention of the data folder (as configured and canonical) and of the
/// system's temporary folder replaced by `<data>` / `<tmp>`: what a client may read of an
/// error that happened on the server.
pub(crate) fn redact_paths(text: &str, data_dir: &std::path::Path) -> String {
    let mut roots: Vec<(String, &str)> = Vec::new();
    let mut add = |p: &std::path::Path, name: &'static str| {
        let s = p.to_string_lossy().trim_end_matches('/').to_string();
        if s.len() > 1 {
            roots.push((s, name));
        }
    };
    if let Ok(c) = data_dir.canonicalize() {
        add(&c, "<data>");
    }
    if data_dir.is_absolute() {
        add(data_dir, "<data>");
    } else if let Ok(cwd) = std::env::current_dir() {
        add(&cwd.join(data_dir), "<data>");
    }
    let tmp = std::env::temp_dir();
    if let Ok(c) = tmp.canonicalize() {
        add(&c, "<tmp>");
    }
    add(&tmp, "<tmp>");
    // One pass, longest root first (a data folder inside the temp folder reads <data>); a
    // root counts only where a path starts and where one of its components ends (`/tmpfoo`
    // and `…/blobs/tmp` are not the temp folder).
    roots.sort_by_key(|r| std::cmp::Reverse(r.0.len()));
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    'scan: while i < text.len() {
        let path_char = |c: char| c.is_alphanumeric() || matches!(c, '_' | '-' | '.' | '/');
        let starts = text[..i].chars().next_back().is_none_or(|c| !path_char(c));
        for (root, name) in roots.iter().filter(|_| starts) {
            if text[i..].starts_with(root.as_str()) {
                let end = i + root.len();
                let boundary = text[end..]
                    .chars()
                    .next()
                    .is_none_or(|c| !(c.is_alphanumeric() || matches!(c, '_' | '-' | '.')));
                if boundary {
                    out.push_str(name);
                    i = end;
                    continue 'scan;
                }
            }
        }
        let c = text[i..].chars().next().expect("in bounds");
        out.push(c);
        i += c.len_utf8();
    }
    out
}

#[cfg(test)]
mod progress_tests {
    use super::*;
    use crate::embed::finetune::StepLog;

    #[test]
    fn the_eta_counts_the_steps_since_finetuning_restarted_after_a_switch() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let phase = |step, total| Progress {
            phase: Phase::Finetune,
            step,
            total,
            log: None,
        };
        let step = |step, total| Progress {
            phase: Phase::Finetune,
            step,
            total,
            log: Some(StepLog::default()),
        };
        let mut clock = None;
        // 10 steps in 20 s of 350: 680 s to go.
        assert_eq!(
            update_at(&phase(0, 350), &mut clock, at(0)).eta_seconds,
            None
        );
        let u = update_at(&step(10, 350), &mut clock, at(20));
        assert_eq!((u.step, u.total, u.eta_seconds), (10, 350, Some(680.0)));
        // A switch at step 70: calibration again, then the coarse run counts on from 70.
        update_at(&phase(70, 420), &mut clock, at(140));
        update_at(&phase(70, 420), &mut clock, at(200));
        let u = update_at(&step(75, 420), &mut clock, at(205));
        // 5 steps in 5 s since the restart (not 75 in 205 s): 345 s to go.
        assert_eq!((u.step, u.total, u.eta_seconds), (75, 420, Some(345.0)));
    }
}

#[cfg(test)]
mod redact_tests {
    use super::redact_paths;

    #[test]
    fn server_folders_never_reach_a_clients_error_text() {
        let data = tempfile::tempdir().unwrap();
        let blob = data.path().join("blobs/tmp/.tmpAbC");
        let text = format!("cannot read {}: no such file", blob.display());
        let shown = redact_paths(&text, data.path());
        assert_eq!(shown, "cannot read <data>/blobs/tmp/.tmpAbC: no such file");
        let other = std::env::temp_dir().join("x.ply");
        let shown = redact_paths(&format!("at {}", other.display()), data.path());
        assert_eq!(shown, "at <tmp>/x.ply");
        assert_eq!(redact_paths("nothing here", data.path()), "nothing here");
        let tmp = std::env::temp_dir()
            .to_string_lossy()
            .trim_end_matches('/')
            .to_string();
        let near = format!("{tmp}foo/x");
        assert_eq!(redact_paths(&near, data.path()), near);
    }
}
