//! Which rasterizer runs: the CPU reference or the GPU path, as `--device cpu|wgpu|auto` asks,
//! behind one API ([`Rasterizer`]); one GPU renderer per process for each kind of request.

use std::sync::Arc;

use super::{AdapterChoice, GpuError, GpuRenderer, GpuScene};
use crate::render::RenderOptions;
use crate::scene::{Camera, Gaussians};

/// Which rasterizer a command asks for (`--device cpu|wgpu|auto`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeviceRequest {
    /// The CPU reference.
    Cpu,
    /// The GPU path on the best wgpu adapter, a software one (lavapipe) included.
    Wgpu,
    /// A hardware GPU when there is one, else the CPU reference (lavapipe is slower than the
    /// CPU reference: it is for tests, not production).
    #[default]
    Auto,
}

impl std::str::FromStr for DeviceRequest {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "wgpu" => Ok(Self::Wgpu),
            "auto" => Ok(Self::Auto),
            _ => Err(format!("unknown device {s:?}: expected cpu, wgpu or auto")),
        }
    }
}

/// The rasterizer a command renders with: one API over both paths.
#[derive(Clone, Default)]
pub enum Rasterizer {
    #[default]
    Cpu,
    Gpu(Arc<GpuRenderer>),
}

impl std::fmt::Debug for Rasterizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

impl PartialEq for Rasterizer {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Self::Cpu, Self::Cpu) => true,
            (Self::Gpu(a), Self::Gpu(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

impl Rasterizer {
    /// The rasterizer `req` asks for; `Wgpu` without an adapter is an error, `Auto` falls back
    /// to the CPU.
    pub fn open(req: DeviceRequest) -> Result<Self, GpuError> {
        match req {
            DeviceRequest::Cpu => Ok(Self::Cpu),
            DeviceRequest::Wgpu => shared(AdapterChoice::AllowSoftware)
                .map(Self::Gpu)
                .map_err(GpuError::NoAdapter),
            DeviceRequest::Auto => Ok(shared(AdapterChoice::Hardware).map_or(Self::Cpu, Self::Gpu)),
        }
    }

    /// "cpu", or the adapter's name and backend.
    pub fn describe(&self) -> String {
        match self {
            Self::Cpu => "cpu".into(),
            Self::Gpu(r) => format!("wgpu: {} ({:?})", r.info.name, r.info.backend),
        }
    }

    /// The burn device of the networks beside this rasterizer: burn's CPU backend (`flex`)
    /// beside the CPU reference, the GPU's own wgpu device beside the GPU path
    /// ([`GpuRenderer::burn_device`]) — the decoder, the image losses and the attacks then run
    /// where the views are rendered.
    pub fn burn_device(&self) -> Result<burn::tensor::Device, GpuError> {
        match self {
            Self::Cpu => Ok(burn::tensor::Device::flex()),
            Self::Gpu(r) => r.burn_device(),
        }
    }

    /// The image of `g` through `camera`: (width, height, linear RGB, not clamped). Several
    /// views of one scene: [`Self::prepare`] it once.
    pub fn render_image(
        &self,
        g: &Gaussians<f32>,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<(u32, u32, Vec<[f32; 3]>), GpuError> {
        match self {
            Self::Cpu => {
                let r = crate::render::render(g, camera, opts)?;
                Ok((r.width, r.height, r.image))
            }
            Self::Gpu(gpu) => {
                let r = gpu.render(g, camera, opts)?;
                Ok((r.width, r.height, r.image))
            }
        }
    }

    /// `g` made ready for renders through many cameras with `opts`: on the GPU packed and
    /// uploaded once ([`GpuRenderer::upload`]), on the CPU as it is.
    pub fn prepare<'a>(
        &'a self,
        g: &'a Gaussians<f32>,
        opts: &'a RenderOptions,
    ) -> Result<PreparedScene<'a>, GpuError> {
        Ok(PreparedScene {
            g,
            opts,
            gpu: match self {
                Self::Cpu => None,
                Self::Gpu(gpu) => Some((gpu.as_ref(), gpu.upload(g, opts)?)),
            },
        })
    }
}

/// A scene ready to render through many cameras ([`Rasterizer::prepare`]).
pub struct PreparedScene<'a> {
    g: &'a Gaussians<f32>,
    opts: &'a RenderOptions,
    gpu: Option<(&'a GpuRenderer, GpuScene)>,
}

impl PreparedScene<'_> {
    /// [`Rasterizer::render_image`] of the prepared scene.
    pub fn render_image(&self, camera: &Camera) -> Result<(u32, u32, Vec<[f32; 3]>), GpuError> {
        match &self.gpu {
            None => {
                let r = crate::render::render(self.g, camera, self.opts)?;
                Ok((r.width, r.height, r.image))
            }
            Some((gpu, scene)) => {
                let r = gpu.render_uploaded(scene, camera, self.opts)?;
                Ok((r.width, r.height, r.image))
            }
        }
    }
}

/// A shared renderer, opened once per process (the tests' lavapipe device).
pub fn shared(choice: AdapterChoice) -> Result<Arc<GpuRenderer>, String> {
    use std::sync::OnceLock;
    static HW: OnceLock<Result<Arc<GpuRenderer>, String>> = OnceLock::new();
    static SW: OnceLock<Result<Arc<GpuRenderer>, String>> = OnceLock::new();
    let cell = match choice {
        AdapterChoice::Hardware => &HW,
        AdapterChoice::AllowSoftware => &SW,
    };
    cell.get_or_init(|| {
        GpuRenderer::new(choice)
            .map(Arc::new)
            .map_err(|e| e.to_string())
    })
    .clone()
}
