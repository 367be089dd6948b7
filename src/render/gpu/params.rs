//! A scene's parameters and their optimiser state on the device: what a GPU job's finetuning
//! steps in place, so that a step reads back no image, no gradient and no parameter — only the
//! scalars it logs. Kernels in `shaders/optim.wgsl` (per-Gaussian Adam as the host's
//! `embed::finetune::optim::Adam`, Σ‖∂L_wm/∂θ_i‖, the fidelity bound's offset scaling, a
//! removal's transparent copy); the gradients come from
//! [`GpuRenderer::backward_tensors_summed_on_device`].

use super::chunk::Sliced;
use super::forward::unpack;
use super::{GpuError, GpuRenderer, GpuScene, words};
use crate::render::{RenderError, RenderOptions};
use crate::scene::Gaussians;

/// Adam's β₁, β₂ (the host's).
const BETA1: f32 = 0.9;
const BETA2: f32 = 0.999;

/// How each Gaussian steps: its learning rates (means, dc, rest, opacity, rotation, scale, masks
/// applied, before the route's multiplier), whether it is a carrier (steps on the watermark
/// route's gradient, at the route's multiplier) and whether the fidelity bound scales its
/// offsets.
#[derive(Clone, Debug)]
pub struct StepPlan {
    pub rates: Vec<[f32; 6]>,
    pub carrier: Vec<bool>,
    pub bounded: Vec<bool>,
}

/// The live parameters (a [`GpuScene`] the renders read), the planned scene they started from,
/// Adam's moments and the per-Gaussian statistics, on one device.
pub struct DeviceParams {
    scene: GpuScene,
    base: wgpu::Buffer,
    m1: wgpu::Buffer,
    m2: wgpu::Buffer,
    rates: wgpu::Buffer,
    flags: wgpu::Buffer,
    norms: wgpu::Buffer,
    /// Adam steps taken.
    t: i32,
    sh_degree: u8,
}

impl std::fmt::Debug for DeviceParams {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DeviceParams")
            .field("gaussians", &self.scene.n)
            .field("steps", &self.t)
            .finish_non_exhaustive()
    }
}

impl DeviceParams {
    /// The live parameters, for [`GpuRenderer::render_resident`] and
    /// [`GpuRenderer::render_uploaded`] (no colour override).
    pub fn scene(&self) -> &GpuScene {
        &self.scene
    }

    pub fn len(&self) -> usize {
        self.scene.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scene.is_empty()
    }
}

/// One route's ∂L/∂θ summed over a step's views, on the device
/// ([`GpuRenderer::backward_tensors_summed_on_device`]).
pub struct GpuGrads {
    pub(super) buf: wgpu::Buffer,
    pub(super) n: u32,
    pub(super) rest_len: usize,
}

impl GpuRenderer {
    /// Uploads `g` as the live parameters and `base` (the planned scene, shaped alike) as the
    /// fidelity bound's origin, with Adam's moments at zero.
    pub fn upload_params(
        &self,
        g: &Gaussians<f32>,
        base: &Gaussians<f32>,
        plan: &StepPlan,
    ) -> Result<DeviceParams, GpuError> {
        let n = g.len();
        if base.len() != n
            || base.rest_len() != g.rest_len()
            || plan.rates.len() != n
            || plan.carrier.len() != n
            || plan.bounded.len() != n
        {
            return Err(RenderError::BadScene(format!(
                "device parameters of {n} Gaussians with a base of {} and a plan of {} / {} / {}",
                base.len(),
                plan.rates.len(),
                plan.carrier.len(),
                plan.bounded.len()
            ))
            .into());
        }
        let opts = RenderOptions::default();
        let scene = self.upload(g, &opts)?;
        let base = self.upload(base, &opts)?.params;
        let floats = u64::from(scene.stride);
        self.scoped(|| {
            let bytes = (n as u64 * floats * 4).max(4);
            let m1 = self.sliced_storage("adam m", bytes)?;
            let m2 = self.sliced_storage("adam v", bytes)?;
            let rates: Vec<f32> = plan.rates.iter().flatten().copied().collect();
            let rates = self
                .storage("rates", (rates.len() as u64 * 4).max(4))
                .inspect(|b| {
                    self.queue.write_buffer(b, 0, bytemuck::cast_slice(&rates));
                })?;
            let flags: Vec<u32> = plan
                .carrier
                .iter()
                .zip(&plan.bounded)
                .map(|(&c, &b)| u32::from(c) | (u32::from(b) << 1))
                .collect();
            let flags = self.storage("flags", (n as u64 * 4).max(4)).inspect(|b| {
                self.queue.write_buffer(b, 0, bytemuck::cast_slice(&flags));
            })?;
            let norms = self.storage("norms", (n as u64 * 4).max(4))?;
            let mut encoder = self.device.create_command_encoder(&Default::default());
            encoder.clear_buffer(&m1, 0, None);
            encoder.clear_buffer(&m2, 0, None);
            encoder.clear_buffer(&norms, 0, None);
            self.queue.submit([encoder.finish()]);
            Ok(DeviceParams {
                sh_degree: g.sh_degree,
                scene,
                base,
                m1,
                m2,
                rates,
                flags,
                norms,
                t: 0,
            })
        })
    }

    /// One Adam step of every parameter along `wm` (carriers, or every Gaussian when
    /// `coupled`, added to `vis`) and `vis` (the others), the carriers' rates — every rate when
    /// `coupled` — times `wm_scale`: the host's `Adam::step` with the finetuning's routing.
    pub fn adam_step(
        &self,
        p: &mut DeviceParams,
        wm: &GpuGrads,
        vis: &GpuGrads,
        coupled: bool,
        wm_scale: f32,
    ) -> Result<(), GpuError> {
        check_grads(p, wm)?;
        check_grads(p, vis)?;
        self.injected_fault()?;
        p.t += 1;
        let (bc1, bc2) = (1.0 - BETA1.powi(p.t), 1.0 - BETA2.powi(p.t));
        let step = step_uniform(p, u32::from(coupled), 0, [bc1, bc2, wm_scale, 0.0]);
        self.run_optim(
            &self.pipes.optim.adam_step,
            p,
            &[(0, &self.uniform(&step)), (6, &p.rates), (7, &p.flags)],
            &[&p.scene.params, &p.m1, &p.m2, &wm.buf, &vis.buf],
            &[1, 2, 3, 4, 5],
        )
    }

    /// Adds ‖∂L_wm/∂θ_i‖ (over the SH coefficients only when `colour_only`) to each Gaussian's
    /// running sum ([`Self::read_norms`]).
    pub fn add_grad_norms(
        &self,
        p: &DeviceParams,
        wm: &GpuGrads,
        colour_only: bool,
    ) -> Result<(), GpuError> {
        check_grads(p, wm)?;
        let step = step_uniform(p, 0, u32::from(colour_only), [0.0; 4]);
        self.run_optim(
            &self.pipes.optim.grad_norm,
            p,
            &[(0, &self.uniform(&step)), (9, &p.norms)],
            &[&wm.buf],
            &[4],
        )
    }

    /// Scales the bounded Gaussians' offsets from the planned scene by `factor` (quaternions
    /// renormalised; unchanged values stay bit-identical): the host's `shrink_offsets`.
    pub fn shrink_offsets(&self, p: &DeviceParams, factor: f32) -> Result<(), GpuError> {
        let step = step_uniform(p, 0, 0, [0.0, 0.0, 0.0, factor]);
        self.run_optim(
            &self.pipes.optim.shrink,
            p,
            &[(0, &self.uniform(&step)), (7, &p.flags)],
            &[&p.scene.params, &p.base],
            &[1, 10],
        )
    }

    /// A copy of the live parameters with the Gaussians of 0 `copies` transparent, for the
    /// renders of the EOT term's removal. Clones (c > 1) are refused: the device's backward
    /// is scene-shaped, and one Gaussian as opaque as its copies is not their render (it is
    /// fainter towards its edges).
    pub fn params_edited(&self, p: &DeviceParams, copies: &[u8]) -> Result<GpuScene, GpuError> {
        if copies.len() != p.len() || copies.iter().any(|&c| c > 1) {
            return Err(RenderError::BadScene(format!(
                "copies of {} Gaussians for a scene of {} (on the GPU 0 or 1 each: cloning \
                 in the EOT term runs on the CPU rasterizer)",
                copies.len(),
                p.len()
            ))
            .into());
        }
        let bytes = p.scene.params.size();
        let copy = self.scoped(|| {
            let copy = self.sliced_storage("params without", bytes)?;
            let flags: Vec<u32> = copies.iter().map(|&c| u32::from(c)).collect();
            let copies = self.storage("copies", (flags.len() as u64 * 4).max(4))?;
            self.queue
                .write_buffer(&copies, 0, bytemuck::cast_slice(&flags));
            let mut encoder = self.device.create_command_encoder(&Default::default());
            encoder.copy_buffer_to_buffer(&p.scene.params, 0, &copy, 0, bytes);
            self.queue.submit([encoder.finish()]);
            let step = step_uniform(p, 0, 0, [0.0; 4]);
            self.run_optim(
                &self.pipes.optim.edit_copies,
                p,
                &[(0, &self.uniform(&step)), (11, &copies)],
                &[&copy],
                &[1],
            )?;
            Ok(copy)
        })?;
        Ok(GpuScene {
            n: p.scene.n,
            rest_len: p.scene.rest_len,
            sh_degree: p.scene.sh_degree,
            stride: p.scene.stride,
            overrides: false,
            params: copy,
        })
    }

    /// Gradients computed elsewhere (shaped like the scene), uploaded for [`Self::adam_step`].
    pub fn upload_grads(&self, grads: &Gaussians<f32>) -> Result<GpuGrads, GpuError> {
        let n = u32::try_from(grads.len())
            .map_err(|_| RenderError::BadScene("more than 2³² Gaussians".into()))?;
        let scene = self.upload(grads, &RenderOptions::default())?;
        Ok(GpuGrads {
            buf: scene.params,
            n,
            rest_len: grads.rest_len(),
        })
    }

    /// The live parameters, read back.
    pub fn read_params(&self, p: &DeviceParams) -> Result<Gaussians<f32>, GpuError> {
        let n = p.len();
        let floats = p.scene.stride as usize;
        let encoder = self.device.create_command_encoder(&Default::default());
        let bytes =
            self.scoped(|| self.read(encoder, &[(&p.scene.params, 0, (n * floats * 4) as u64)]))?;
        Ok(unpack(
            bytemuck::cast_slice(&bytes),
            n,
            p.scene.rest_len,
            p.sh_degree,
        ))
    }

    /// Each Gaussian's Σ‖∂L_wm/∂θ_i‖ so far, read back.
    pub fn read_norms(&self, p: &DeviceParams) -> Result<Vec<f32>, GpuError> {
        let encoder = self.device.create_command_encoder(&Default::default());
        let bytes = self.scoped(|| self.read(encoder, &[(&p.norms, 0, p.len() as u64 * 4)]))?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }

    /// Records and submits `pipe` over the Gaussians of `p`, `whole` bound whole and `sliced`
    /// (one layout, 14 + rest floats a Gaussian) at `bindings`.
    fn run_optim(
        &self,
        pipe: &wgpu::ComputePipeline,
        p: &DeviceParams,
        whole: &[(u32, &wgpu::Buffer)],
        sliced: &[&wgpu::Buffer],
        bindings: &[u32],
    ) -> Result<(), GpuError> {
        let sliced: Vec<Sliced> = sliced
            .iter()
            .zip(bindings)
            .map(|(buffer, &binding)| Sliced {
                binding,
                buffer,
                floats: p.scene.stride,
            })
            .collect();
        self.scoped(|| {
            let mut encoder = self.device.create_command_encoder(&Default::default());
            let mut keep = Vec::new();
            self.per_gaussian(
                &mut encoder,
                pipe,
                p.scene.n,
                whole,
                &sliced,
                false,
                &mut keep,
            )?;
            self.queue.submit([encoder.finish()]);
            drop(keep);
            Ok(())
        })
    }
}

/// The `Step` uniform of `shaders/optim.wgsl`.
fn step_uniform(p: &DeviceParams, coupled: u32, colour_only: u32, f: [f32; 4]) -> Vec<u8> {
    let mut bytes = words(&[p.scene.stride, coupled, colour_only, 0]).to_vec();
    bytes.extend_from_slice(bytemuck::cast_slice(&f));
    bytes
}

fn check_grads(p: &DeviceParams, g: &GpuGrads) -> Result<(), GpuError> {
    if g.n != p.scene.n || g.rest_len != p.scene.rest_len {
        return Err(RenderError::BadScene(format!(
            "gradients of {} Gaussians for parameters of {}",
            g.n, p.scene.n
        ))
        .into());
    }
    Ok(())
}
