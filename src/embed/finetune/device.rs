//! A GPU job's Gaussians and their Adam state on the device (`render::gpu::DeviceParams`, the
//! kernels of `shaders/optim.wgsl`): the step renders from the live parameters, sums each
//! route's gradients over its views there, and steps Adam, the attribution statistic and the
//! fidelity bound in place — the host's `Adam::step`, `grad_norms` and `shrink_offsets` with
//! the same routing and rates ([`StepPlan`]). The host reads the parameters back only where it
//! needs them: a parameter-noise copy, an `extra_steps` check, the end.

use std::sync::Arc;

use super::{FinetuneConfig, FinetuneError};
use crate::embed::mask::Masks;
use crate::render::RenderError;
use crate::render::gpu::{DeviceParams, GpuGrads, GpuRenderer, GpuScene, StepPlan};
use crate::scene::Gaussians;

pub(super) struct Stepper {
    gpu: Arc<GpuRenderer>,
    params: DeviceParams,
    coupled: bool,
}

/// Each Gaussian's learning rates, before the watermark route's multiplier, as the host's step
/// forms them: coupled, `lr` for every Gaussian; decoupled, `lr` through the Gaussian's channel
/// mask (and the position mask), a carrier's geometry held unless `wm_geometry`.
fn plan(cfg: &FinetuneConfig, masks: &Masks, bounded: &[bool]) -> StepPlan {
    let lr = &cfg.lr;
    let base = [lr.means, lr.dc, lr.rest, lr.opacity, lr.rotation, lr.scale];
    let rates = (0..masks.mask.len())
        .map(|i| {
            if cfg.coupled {
                return base;
            }
            let m = masks.mask[i];
            // `× 1.0`: the host's `rates(i, 1.0)`, the same values.
            let mut r = [
                base[0] * masks.position * 1.0,
                base[1] * m[0] * 1.0,
                base[2] * m[1] * 1.0,
                base[3] * m[2] * 1.0,
                base[4] * m[3] * 1.0,
                base[5] * m[4] * 1.0,
            ];
            if masks.is_carrier[i] && !cfg.wm_geometry {
                r[0] = 0.0;
                r[3] = 0.0;
                r[4] = 0.0;
                r[5] = 0.0;
            }
            r
        })
        .collect();
    StepPlan {
        rates,
        carrier: masks.is_carrier.clone(),
        bounded: bounded.to_vec(),
    }
}

fn gpu_err(e: crate::render::gpu::GpuError) -> FinetuneError {
    FinetuneError::from(RenderError::from(e))
}

impl Stepper {
    /// `g` uploaded as the live parameters, `base` (the planned scene) as the fidelity bound's
    /// origin.
    pub fn new(
        gpu: Arc<GpuRenderer>,
        g: &Gaussians,
        base: &Gaussians,
        cfg: &FinetuneConfig,
        masks: &Masks,
        bounded: &[bool],
    ) -> Result<Self, FinetuneError> {
        let params = gpu
            .upload_params(g, base, &plan(cfg, masks, bounded))
            .map_err(gpu_err)?;
        Ok(Self {
            gpu,
            params,
            coupled: cfg.coupled,
        })
    }

    /// The live parameters, to render from.
    pub fn scene(&self) -> &GpuScene {
        self.params.scene()
    }

    /// The live parameters with `copies[i]` copies of Gaussian i (0 transparent, 2 as opaque
    /// as two copies together).
    pub fn edited(&self, copies: &[u8]) -> Result<GpuScene, FinetuneError> {
        self.gpu
            .params_edited(&self.params, copies)
            .map_err(gpu_err)
    }

    /// One step: ‖∂L_wm/∂θ_i‖ added to the attribution statistic (SH only when
    /// `colour_only`), then Adam along the routes at the watermark route's multiplier `wm_s`.
    pub fn step(
        &mut self,
        wm: &GpuGrads,
        vis: &GpuGrads,
        colour_only: bool,
        wm_s: f32,
    ) -> Result<(), FinetuneError> {
        self.gpu
            .add_grad_norms(&self.params, wm, colour_only)
            .map_err(gpu_err)?;
        self.gpu
            .adam_step(&mut self.params, wm, vis, self.coupled, wm_s)
            .map_err(gpu_err)
    }

    /// The fidelity bound: the bounded Gaussians' offsets from the planned scene times `f`.
    pub fn shrink(&self, f: f32) -> Result<(), FinetuneError> {
        self.gpu.shrink_offsets(&self.params, f).map_err(gpu_err)
    }

    /// The live parameters, read back.
    pub fn read(&self) -> Result<Gaussians, FinetuneError> {
        self.gpu.read_params(&self.params).map_err(gpu_err)
    }

    /// Σ over the steps of ‖∂L_wm/∂θ_i‖, read back.
    pub fn read_norms(&self) -> Result<Vec<f32>, FinetuneError> {
        self.gpu.read_norms(&self.params).map_err(gpu_err)
    }
}
