//! The job queue's consumers: job specs, the work of one job, and the worker pool. The queue
//! itself (jobs, leases, attempts, backoff, dead letters) lives in SQLite ([`crate::store`]).

pub mod run;
pub mod spec;
pub mod worker;

pub use spec::{JobOptions, JobSpec};
pub use worker::{Pool, PoolStatus, WorkerSpec, available_bits, start, weights_path};

use std::sync::Arc;

use burn::tensor::Device;

use crate::config::{Config, DevicePolicy};
use crate::render::gpu::{DeviceRequest, GpuRenderer, Rasterizer};

/// The workers `cfg` asks for: under [`DevicePolicy::Auto`], one per hardware GPU adapter
/// (its own wgpu device renders and back-propagates the views) when there is one, else CPU
/// workers; [`DevicePolicy::Wgpu`] takes the best wgpu adapter, Mesa's lavapipe included;
/// `cfg.workers` overrides the count (workers beyond the adapters share them round-robin).
/// A GPU worker's networks (decoder, image losses, attacks) run on burn's wgpu runtime on the
/// same device as its rasterizer ([`Rasterizer::burn_device`]); a CPU worker's on burn's CPU
/// backend.
pub async fn plan_workers(cfg: &Config) -> Vec<WorkerSpec> {
    let mut rasterizers: Vec<(String, Rasterizer)> = match cfg.device {
        DevicePolicy::Cpu => vec![],
        DevicePolicy::Wgpu => match Rasterizer::open(DeviceRequest::Wgpu) {
            Ok(r) => vec![("wgpu".into(), r)],
            Err(e) => {
                tracing::error!(error = %e, "device = wgpu, but no wgpu adapter: CPU workers");
                vec![]
            }
        },
        DevicePolicy::Auto => GpuRenderer::on_every_gpu()
            .into_iter()
            .enumerate()
            .map(|(i, r)| {
                let info = r.adapter();
                tracing::info!(adapter = %info.name, backend = ?info.backend, "GPU adapter found");
                (format!("gpu{i}"), Rasterizer::Gpu(Arc::new(r)))
            })
            .collect(),
    };
    if rasterizers.is_empty() {
        rasterizers.push(("cpu".into(), Rasterizer::Cpu));
    }
    let n = cfg.workers.unwrap_or(rasterizers.len());
    (0..n)
        .map(|i| {
            let (kind, rasterizer) = rasterizers[i % rasterizers.len()].clone();
            let device = rasterizer.burn_device().unwrap_or_else(|e| {
                tracing::error!(error = %e, "burn cannot use the GPU's device: the decoder runs on the CPU");
                Device::flex()
            });
            WorkerSpec {
                name: format!("{kind}-{i}@{}", process_name()),
                device,
                rasterizer,
            }
        })
        .collect()
}

/// `HOST:PID`, which tells the workers of several processes and machines apart in job records,
/// the audit log and `/metrics` (the host name is a Kubernetes pod's name).
fn process_name() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| std::fs::read_to_string("/proc/sys/kernel/hostname").ok())
        .map(|h| {
            h.trim()
                .chars()
                .filter(|c| !c.is_control())
                .take(64)
                .collect::<String>()
        })
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "localhost".into());
    format!("{host}:{}", std::process::id())
}
