//! The job queue's consumers: job specs, the work of one job, and the worker pool. The queue
//! itself (jobs, leases, attempts, backoff, dead letters) lives in SQLite ([`crate::store`]).

pub mod run;
pub mod spec;
pub mod worker;

pub use spec::{JobOptions, JobSpec};
pub use worker::{Pool, PoolStatus, WorkerSpec, available_bits, start, weights_path};

use burn::tensor::{Device, DeviceKind};

use crate::config::{Config, DevicePolicy};

/// The workers `cfg` asks for: one per hardware GPU adapter (burn-wgpu) under
/// [`DevicePolicy::Auto`] when there is one, else CPU workers (burn `flex`); `cfg.workers`
/// overrides the count.
pub async fn plan_workers(cfg: &Config) -> Vec<WorkerSpec> {
    let mut devices: Vec<(String, Device)> = match cfg.device {
        DevicePolicy::Cpu => vec![],
        DevicePolicy::Wgpu => vec![("wgpu".into(), Device::wgpu(DeviceKind::DefaultDevice))],
        DevicePolicy::Auto => gpu_adapters().await,
    };
    if devices.is_empty() {
        devices.push(("cpu".into(), Device::flex()));
    }
    let n = cfg.workers.unwrap_or(devices.len());
    (0..n)
        .map(|i| {
            let (kind, device) = devices[i % devices.len()].clone();
            WorkerSpec {
                name: format!("{kind}-{i}"),
                device,
            }
        })
        .collect()
}

/// Hardware GPU adapters (software rasterisers such as Mesa's lavapipe excluded: `flex` is
/// faster on a CPU).
async fn gpu_adapters() -> Vec<(String, Device)> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapters = instance.enumerate_adapters(wgpu::Backends::PRIMARY).await;
    let (mut discrete, mut integrated) = (0, 0);
    let mut out = vec![];
    for a in adapters {
        let info = a.get_info();
        let kind = match info.device_type {
            wgpu::DeviceType::DiscreteGpu => {
                discrete += 1;
                DeviceKind::DiscreteGpu(discrete - 1)
            }
            wgpu::DeviceType::IntegratedGpu => {
                integrated += 1;
                DeviceKind::IntegratedGpu(integrated - 1)
            }
            _ => continue,
        };
        tracing::info!(adapter = %info.name, backend = ?info.backend, "GPU adapter found");
        out.push((format!("gpu{}", out.len()), Device::wgpu(kind)));
    }
    out
}
