//! The wgpu twin of the CPU reference rasterizer: the kernels in `shaders/` (WGSL), driven from
//! here. [`GpuRenderer::render`] renders what [`super::render`] renders — the same projection,
//! footprint and compositing rules (see the module docs of [`super`]) — on any wgpu adapter:
//! a hardware GPU in production, Mesa's lavapipe in the tests.
//!
//! One frame: `project` (per Gaussian: screen centre, conic, colour, footprint rectangle, tile
//! count) → exclusive scan of the tile counts → `emit` one (tile, depth) key per tile a
//! Gaussian's rectangle covers → stable radix sort of the keys → `tile_ranges` → `raster`, one
//! 16×16 workgroup per tile. Integer steps (scan, sort) are exact; the floating-point steps
//! follow the reference's formulas in f32, so images agree to rounding (tested: ≤ 1/255 on
//! ≥ 99.9 % of the pixels).
//!
//! The scene's parameters and their gradients may exceed one storage binding: the per-Gaussian
//! kernels bind them a chunk of Gaussians at a time (`chunk.rs`).

mod backward;
mod choice;
mod chunk;
mod forward;
mod interop;
mod params;
mod sort;

pub use choice::{DeviceRequest, PreparedScene, Rasterizer, shared};
use forward::GpuState;
pub use forward::{GpuRendered, GpuScene};
pub use params::{DeviceParams, GpuGrads, StepPlan};

use wgpu::util::DeviceExt;

use super::RenderError;

/// Why the GPU path could not run.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no usable wgpu adapter: {0}")]
    NoAdapter(String),
    #[error("the wgpu device could not be created: {0}")]
    Device(String),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("the GPU could not run the render: {0}")]
    Run(String),
    #[error("the render needs {needed} bytes in one buffer; this adapter allows {limit}")]
    TooLarge { needed: u64, limit: u64 },
}

impl From<GpuError> for RenderError {
    /// A bad input stays the reference's error; a device failure becomes [`RenderError::Device`].
    fn from(e: GpuError) -> Self {
        match e {
            GpuError::Render(r) => r,
            other => RenderError::Device(other.to_string()),
        }
    }
}

/// Which adapters [`GpuRenderer::new`] may take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AdapterChoice {
    /// A discrete or integrated GPU only.
    Hardware,
    /// A hardware GPU if there is one, else a software one (lavapipe): for tests.
    AllowSoftware,
}

/// A wgpu device with the rasterizer's pipelines.
pub struct GpuRenderer {
    instance: wgpu::Instance,
    adapter: wgpu::Adapter,
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    /// burn's handle on this same wgpu device, registered with burn's wgpu runtime on first use
    /// ([`Self::burn_device`]).
    burn: std::sync::OnceLock<Result<burn::tensor::Device, String>>,
    pipes: Pipelines,
    /// Renders or backward passes left to fail as on a lost device ([`Self::inject_device_loss`]).
    faults: std::sync::atomic::AtomicUsize,
    /// At most this many Gaussians per dispatch of the per-Gaussian kernels (`chunk.rs`); unset,
    /// as many as one storage binding holds.
    per_dispatch: Option<u32>,
}

struct Pipelines {
    project: wgpu::ComputePipeline,
    project_backward: wgpu::ComputePipeline,
    raster_backward: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    add_sums: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    tile_ranges: wgpu::ComputePipeline,
    raster: wgpu::ComputePipeline,
    sort: sort::SortPipelines,
    optim: OptimPipelines,
}

/// The optimiser's kernels (`shaders/optim.wgsl`).
struct OptimPipelines {
    adam_step: wgpu::ComputePipeline,
    grad_norm: wgpu::ComputePipeline,
    shrink: wgpu::ComputePipeline,
    edit_copies: wgpu::ComputePipeline,
}

/// Runs a wgpu future to completion (native wgpu resolves them without an executor).
pub(crate) fn block_on<F: std::future::Future>(f: F) -> F::Output {
    let mut f = std::pin::pin!(f);
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    loop {
        if let std::task::Poll::Ready(v) = f.as_mut().poll(&mut cx) {
            return v;
        }
        std::thread::yield_now();
    }
}

fn shader(device: &wgpu::Device, label: &str, src: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(src.into()),
    })
}

pub(crate) fn pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// A bind group of `pipe`'s group `group` with these (binding, buffer) pairs.
pub(crate) fn bind(
    device: &wgpu::Device,
    pipe: &wgpu::ComputePipeline,
    group: u32,
    buffers: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = buffers
        .iter()
        .map(|(b, buf)| wgpu::BindGroupEntry {
            binding: *b,
            resource: buf.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipe.get_bind_group_layout(group),
        entries: &entries,
    })
}

/// Workgroup grid for `groups` workgroups (at most 65 535 along x).
pub(crate) fn grid(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, 65_535);
    (x, groups.div_ceil(x).max(1))
}

fn words(v: &[u32]) -> &[u8] {
    bytemuck::cast_slice(v)
}

impl GpuRenderer {
    /// Opens the best adapter `choice` allows (discrete, then integrated, then software).
    pub fn new(choice: AdapterChoice) -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
            wgpu::DeviceType::DiscreteGpu => Some(0),
            wgpu::DeviceType::IntegratedGpu => Some(1),
            wgpu::DeviceType::Cpu if choice == AdapterChoice::AllowSoftware => {
                // Prefer Vulkan's lavapipe over GL's llvmpipe.
                Some(if a.get_info().backend == wgpu::Backend::Vulkan {
                    2
                } else {
                    3
                })
            }
            _ => None,
        };
        let seen: Vec<String> = adapters
            .iter()
            .map(|a| {
                let i = a.get_info();
                format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
            })
            .collect();
        let adapter = adapters
            .into_iter()
            .filter_map(|a| rank(&a).map(|r| (r, a)))
            .min_by_key(|(r, _)| *r)
            .map(|(_, a)| a)
            .ok_or_else(|| {
                GpuError::NoAdapter(if seen.is_empty() {
                    "wgpu found none".into()
                } else {
                    format!("found only {}", seen.join(", "))
                })
            })?;
        Self::on_adapter(&instance, &adapter)
    }

    /// One renderer on every hardware adapter (discrete and integrated GPUs; software
    /// rasterisers left out), each on a device of its own; adapters that fail to open are
    /// logged and skipped.
    pub fn on_every_gpu() -> Vec<Self> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        block_on(instance.enumerate_adapters(wgpu::Backends::all()))
            .into_iter()
            .filter(|a| {
                matches!(
                    a.get_info().device_type,
                    wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu
                )
            })
            .filter_map(|a| match Self::on_adapter(&instance, &a) {
                Ok(r) => Some(r),
                Err(e) => {
                    tracing::warn!(adapter = %a.get_info().name, error = %e, "GPU adapter unusable");
                    None
                }
            })
            .collect()
    }

    /// A renderer on `adapter` (of `instance`).
    pub fn on_adapter(
        instance: &wgpu::Instance,
        adapter: &wgpu::Adapter,
    ) -> Result<Self, GpuError> {
        let info = adapter.get_info();
        // Every feature the adapter has, as burn's wgpu runtime asks for its own devices: the
        // decoder's kernels run on this device too ([`Self::burn_device`]) and burn picks its
        // code paths (64-bit integers, subgroups, f16) from the adapter's features.
        let (device, queue) = block_on(
            adapter.request_device(&wgpu::DeviceDescriptor {
                label: Some("splatmark"),
                required_features: adapter
                    .features()
                    .difference(wgpu::Features::MAPPABLE_PRIMARY_BUFFERS),
                required_limits: adapter.limits(),
                ..Default::default()
            }),
        )
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let invalid = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let pipes = Self::pipelines(&device);
        if let Some(e) = block_on(invalid.pop()) {
            return Err(GpuError::Device(format!("the kernels do not build: {e}")));
        }
        Ok(Self {
            instance: instance.clone(),
            adapter: adapter.clone(),
            device,
            queue,
            info,
            pipes,
            burn: Default::default(),
            faults: Default::default(),
            per_dispatch: None,
        })
    }

    /// This renderer with at most `n` Gaussians per dispatch of the per-Gaussian kernels, so
    /// that small scenes go through several chunks, as scenes past one binding do.
    #[cfg(test)]
    pub(crate) fn with_gaussians_per_dispatch(mut self, n: u32) -> Self {
        self.per_dispatch = Some(n);
        self
    }

    /// burn's device on this renderer's wgpu device and queue (registered with burn's wgpu
    /// runtime once; every call returns a clone of that one device): the decoder, the image
    /// losses and the attacks of a finetuning then run on the GPU that renders its views.
    pub fn burn_device(&self) -> Result<burn::tensor::Device, GpuError> {
        self.burn
            .get_or_init(|| {
                let setup = burn::tensor::wgpu::WgpuSetup {
                    instance: self.instance.clone(),
                    adapter: self.adapter.clone(),
                    device: self.device.clone(),
                    queue: self.queue.clone(),
                    backend: self.info.backend,
                };
                burn::tensor::Device::wgpu_options()
                    .setup(setup)
                    .init()
                    .map_err(|e| e.to_string())
            })
            .clone()
            .map_err(GpuError::Device)
    }

    fn pipelines(device: &wgpu::Device) -> Pipelines {
        let device = device.clone();
        let project = shader(
            &device,
            "project",
            concat!(
                include_str!("../../../shaders/common.wgsl"),
                include_str!("../../../shaders/chunk.wgsl"),
                include_str!("../../../shaders/project.wgsl")
            ),
        );
        let scan = shader(&device, "scan", include_str!("../../../shaders/scan.wgsl"));
        let raster = shader(
            &device,
            "raster",
            concat!(
                include_str!("../../../shaders/common.wgsl"),
                include_str!("../../../shaders/raster.wgsl")
            ),
        );
        let backward = shader(
            &device,
            "backward",
            concat!(
                include_str!("../../../shaders/common.wgsl"),
                include_str!("../../../shaders/backward.wgsl")
            ),
        );
        let optim = shader(
            &device,
            "optim",
            concat!(
                include_str!("../../../shaders/chunk.wgsl"),
                include_str!("../../../shaders/optim.wgsl")
            ),
        );
        Pipelines {
            project: pipeline(&device, &project, "project"),
            project_backward: pipeline(&device, &project, "project_backward"),
            raster_backward: pipeline(&device, &backward, "raster_backward"),
            scan_blocks: pipeline(&device, &scan, "scan_blocks"),
            add_sums: pipeline(&device, &scan, "add_sums"),
            emit: pipeline(&device, &raster, "emit"),
            tile_ranges: pipeline(&device, &raster, "tile_ranges"),
            raster: pipeline(&device, &raster, "raster"),
            sort: sort::SortPipelines::new(&device),
            optim: OptimPipelines {
                adam_step: pipeline(&device, &optim, "adam_step"),
                grad_norm: pipeline(&device, &optim, "grad_norm"),
                shrink: pipeline(&device, &optim, "shrink"),
                edit_copies: pipeline(&device, &optim, "edit_copies"),
            },
        }
    }

    /// The adapter this renderer runs on.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Fault drill: the next `n` renders or backward passes fail with the error a lost device
    /// gives ([`GpuError::Run`]), so that what a worker does then can be tested and rehearsed.
    pub fn inject_device_loss(&self, n: usize) {
        self.faults.store(n, std::sync::atomic::Ordering::SeqCst);
    }

    /// Consumes one injected fault, if any is left.
    fn injected_fault(&self) -> Result<(), GpuError> {
        use std::sync::atomic::Ordering;
        match self
            .faults
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
        {
            Ok(_) => Err(GpuError::Run("device lost (injected fault)".into())),
            Err(_) => Ok(()),
        }
    }

    /// A storage buffer the kernels bind whole: at most the device's binding limit.
    fn storage(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        let limit = self.device.limits().max_storage_buffer_binding_size;
        self.storage_within(label, bytes, limit)
    }

    fn storage_within(
        &self,
        label: &str,
        bytes: u64,
        limit: u64,
    ) -> Result<wgpu::Buffer, GpuError> {
        let size = bytes.max(64).next_multiple_of(4);
        if size > limit {
            return Err(GpuError::TooLarge {
                needed: size,
                limit,
            });
        }
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }))
    }

    fn uniform(&self, bytes: &[u8]) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: None,
                contents: bytes,
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    /// Submits `encoder` and reads back the `(buffer, offset, bytes)` parts, one after the other
    /// (offsets and sizes multiples of 4).
    fn read(
        &self,
        mut encoder: wgpu::CommandEncoder,
        parts: &[(&wgpu::Buffer, u64, u64)],
    ) -> Result<Vec<u8>, GpuError> {
        let size: u64 = parts.iter().map(|p| p.2).sum();
        let limit = self.device.limits().max_buffer_size;
        if size > limit {
            return Err(GpuError::TooLarge {
                needed: size,
                limit,
            });
        }
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: size.max(4),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut at = 0;
        for &(buf, offset, bytes) in parts.iter().filter(|p| p.2 > 0) {
            encoder.copy_buffer_to_buffer(buf, offset, &staging, at, bytes);
            at += bytes;
        }
        self.queue.submit([encoder.finish()]);
        let slice = staging.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Run(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Run(e.to_string()))?
            .map_err(|e| GpuError::Run(e.to_string()))?;
        let bytes = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Run(e.to_string()))?[..size as usize]
            .to_vec();
        staging.unmap();
        Ok(bytes)
    }

    /// Records an exclusive prefix sum of the first `n` u32 of `data` (in place).
    fn scan(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        n: u32,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let blocks = n.div_ceil(256).max(1);
        let sums = self.storage("scan sums", u64::from(blocks) * 4)?;
        let (gx, gy) = grid(blocks);
        let params = self.uniform(words(&[n, gx, 0, 0]));
        let scan_bg = bind(
            &self.device,
            &self.pipes.scan_blocks,
            0,
            &[(0, &params), (1, data), (2, &sums)],
        );
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipes.scan_blocks);
            pass.set_bind_group(0, &scan_bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        if blocks > 1 {
            self.scan(encoder, &sums, blocks, keep)?;
            let add_bg = bind(
                &self.device,
                &self.pipes.add_sums,
                0,
                &[(0, &params), (1, data), (2, &sums)],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipes.add_sums);
            pass.set_bind_group(0, &add_bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        keep.push(sums);
        keep.push(params);
        Ok(())
    }

    /// Runs `f` inside error scopes: a failure of the device (validation, out of memory) in
    /// it is an error, not a panic.
    fn scoped<T>(&self, f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let invalid = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        let errors = [block_on(invalid.pop()), block_on(oom.pop())];
        match errors.into_iter().flatten().next() {
            Some(e) => Err(GpuError::Run(e.to_string())),
            None => out,
        }
    }
}

#[cfg(test)]
mod tests;
