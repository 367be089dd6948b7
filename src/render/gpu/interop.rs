//! The crossing between the rasterizer and burn on one wgpu device: a render into a burn
//! tensor and burn's ∂L/∂image back into the backward pass, both copied on the device. A burn
//! tensor's storage is reached through its cubecl primitive (`Tensor::try_into_primitive`) and
//! the runtime's `get_resource` (the `wgpu::Buffer` and offset; burn's `cubecl` feature).

use burn::backend::Wgpu;
use burn::backend::wgpu::CubeTensor;
use burn::tensor::Tensor;

use super::{GpuError, GpuGrads, GpuRendered, GpuRenderer};
use crate::render::{Gradients, RenderError};
use crate::scene::Gaussians;

/// `t`'s primitive on burn's wgpu backend.
fn primitive(t: Tensor<4>) -> Result<CubeTensor, GpuError> {
    t.try_into_primitive::<Wgpu>()
        .map_err(|e| GpuError::Device(format!("{e:?}")))
}

/// The other side of a copy with a tensor's storage: `Into` the storage from this buffer, or
/// `From` the storage into it (whole buffers from offset 0).
enum Direction<'a> {
    Into(&'a wgpu::Buffer),
    From(&'a wgpu::Buffer),
}

/// Records in `encoder` a copy of `bytes` bytes between `tensor`'s storage and `other`.
fn copy_with_storage(
    encoder: &mut wgpu::CommandEncoder,
    tensor: &CubeTensor,
    other: Direction<'_>,
    bytes: u64,
) -> Result<(), GpuError> {
    let res = tensor
        .client
        .get_resource::<burn::cubecl::wgpu::WgpuServer<burn::cubecl::wgpu::AutoCompiler>>(
            tensor.handle.clone(),
        )
        .map_err(|e| GpuError::Run(format!("{e:?}")))?;
    let res = res.resource();
    match other {
        Direction::Into(src) => {
            encoder.copy_buffer_to_buffer(src, 0, &res.buffer, res.offset, bytes)
        }
        Direction::From(dst) => {
            encoder.copy_buffer_to_buffer(&res.buffer, res.offset, dst, 0, bytes)
        }
    }
    Ok(())
}

impl GpuRenderer {
    /// The render `r` as a burn tensor `[1, 3, H, W]` on this renderer's burn device
    /// ([`Self::burn_device`]), copied on the device from the render's own buffer — the
    /// decoder's input without a round trip through the host.
    pub fn image_tensor(&self, r: &GpuRendered) -> Result<Tensor<4>, GpuError> {
        let device = self.burn_device()?;
        let (w, h) = (r.width as usize, r.height as usize);
        let prim = primitive(Tensor::<4>::empty([1, h, w, 3], &device))?;
        let mut encoder = self.device.create_command_encoder(&Default::default());
        copy_with_storage(
            &mut encoder,
            &prim,
            Direction::Into(&r.state.image),
            (w * h * 12) as u64,
        )?;
        self.queue.submit([encoder.finish()]);
        Ok(Tensor::<4>::from_primitive::<Wgpu>(prim).permute([0, 3, 1, 2]))
    }

    /// [`Self::backward`] from ∂L/∂image as a burn tensor `[1, 3, H, W]` on this renderer's
    /// burn device ([`Self::burn_device`]), copied on the device: what a finetuning step's
    /// decoder gives back, without a round trip through the host.
    pub fn backward_tensor(
        &self,
        g: &Gaussians<f32>,
        fwd: &GpuRendered,
        d_image: Tensor<4>,
    ) -> Result<Gradients<f32>, GpuError> {
        let fill = self.gradient_fill(fwd, d_image)?;
        self.backward_with(g, fwd, fill)
    }

    /// Σ over `passes` of ∂L/∂θ ([`Self::backward_tensor`]'s parameters' gradients), summed on
    /// the device in the passes' order and read back once: a finetuning step's views for one
    /// route. Each render must be of a scene shaped like `g` (another scene's values may have
    /// rendered it — a copy with Gaussians removed — the gradient is then at its parameters).
    pub fn backward_tensors_summed(
        &self,
        g: &Gaussians<f32>,
        passes: &[(&GpuRendered, Tensor<4>)],
    ) -> Result<Gaussians<f32>, GpuError> {
        let sum = self.backward_tensors_summed_on_device(g, passes)?;
        self.read_grads(g, &sum)
    }

    /// [`Self::backward_tensors_summed`] left on the device, for [`Self::adam_step`].
    pub fn backward_tensors_summed_on_device(
        &self,
        g: &Gaussians<f32>,
        passes: &[(&GpuRendered, Tensor<4>)],
    ) -> Result<GpuGrads, GpuError> {
        type Fill<'a> =
            Box<dyn FnOnce(&mut wgpu::CommandEncoder) -> Result<wgpu::Buffer, GpuError> + 'a>;
        let fills = passes
            .iter()
            .map(|(fwd, d)| Ok((*fwd, Box::new(self.gradient_fill(fwd, d.clone())?) as Fill)))
            .collect::<Result<Vec<_>, GpuError>>()?;
        self.backward_sum_with(g, fills)
    }

    /// Checks ∂L/∂image `d_image` against the render `fwd` and gives what fills the backward's
    /// buffer from it: row-major RGB, materialised (a permuted view cannot be read as one
    /// run), copied on the device.
    fn gradient_fill<'a>(
        &'a self,
        fwd: &GpuRendered,
        d_image: Tensor<4>,
    ) -> Result<
        impl FnOnce(&mut wgpu::CommandEncoder) -> Result<wgpu::Buffer, GpuError> + 'a,
        GpuError,
    > {
        let (w, h) = (fwd.width as usize, fwd.height as usize);
        let dims = d_image.dims();
        if dims != [1, 3, h, w] {
            return Err(RenderError::GradientSize {
                got: dims.iter().product(),
                expected: 3 * w * h,
            }
            .into());
        }
        let prim = primitive(d_image.permute([0, 2, 3, 1]).reshape([1, 1, 1, w * h * 3]))?;
        if !prim.is_contiguous() {
            return Err(GpuError::Device("∂L/∂image is not contiguous".into()));
        }
        Ok(move |encoder: &mut wgpu::CommandEncoder| {
            let bytes = (w * h * 12) as u64;
            let d_buf = self.storage("d image", bytes)?;
            copy_with_storage(encoder, &prim, Direction::From(&d_buf), bytes)?;
            Ok(d_buf)
        })
    }
}
