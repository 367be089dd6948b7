//! The GPU path's backward pass: ∂L/∂image through `shaders/backward.wgsl` (each tile's entries
//! back to front, a fixed-order sum per entry) and `shaders/project.wgsl`'s `project_backward`
//! (per Gaussian, through the projection) to the CPU reference's [`Gradients`].

use super::chunk::Sliced;
use super::forward::unpack;
use super::{GpuError, GpuGrads, GpuRendered, GpuRenderer, GpuState, bind};
use crate::render::{Gradients, RenderError};
use crate::scene::Gaussians;

impl GpuRenderer {
    /// Back-propagates `d_image` (∂L/∂pixel, row-major RGB) through the GPU render `fwd` of
    /// `g` (the scene that was rendered): the CPU reference's `render::backward`, with the
    /// same [`Gradients`] — deterministic (no float atomics), equal to it up to rounding.
    pub fn backward(
        &self,
        g: &Gaussians<f32>,
        fwd: &GpuRendered,
        d_image: &[[f32; 3]],
    ) -> Result<Gradients<f32>, GpuError> {
        let px = fwd.width as usize * fwd.height as usize;
        if d_image.len() != px {
            return Err(RenderError::GradientSize {
                got: d_image.len(),
                expected: px,
            }
            .into());
        }
        self.backward_with(g, fwd, |_| {
            let d_buf = self.storage("d image", d_image.len() as u64 * 12)?;
            self.queue
                .write_buffer(&d_buf, 0, bytemuck::cast_slice(d_image));
            Ok(d_buf)
        })
    }

    /// The shared part of the backward passes: `d_image` fills ∂L/∂image's buffer (host
    /// upload, or a device copy recorded in the encoder it is given).
    pub(super) fn backward_with(
        &self,
        g: &Gaussians<f32>,
        fwd: &GpuRendered,
        d_image: impl FnOnce(&mut wgpu::CommandEncoder) -> Result<wgpu::Buffer, GpuError>,
    ) -> Result<Gradients<f32>, GpuError> {
        let st = &fwd.state;
        check_shape(g, st)?;
        self.injected_fault()?;
        let (grads, aux) = self.scoped(|| self.backward_checked(st, d_image))?;
        let n = g.len();
        let z3 = [0.0f32; 3];
        let mut colors = vec![z3; n];
        let mut blend_weights = vec![0.0; n];
        let mut screen_xy = vec![[0.0; 2]; n];
        for i in 0..n {
            let a = &aux[i * 6..(i + 1) * 6];
            colors[i] = [a[0], a[1], a[2]];
            blend_weights[i] = a[3];
            screen_xy[i] = [a[4], a[5]];
        }
        Ok(Gradients {
            params: unpack(&grads, g.len(), g.rest_len(), g.sh_degree),
            colors,
            blend_weights,
            screen_xy,
        })
    }

    /// Σ over `passes` of ∂L/∂θ — each pass a render of a scene shaped like `g` and ∂L/∂image
    /// filling its buffer (as [`Self::backward_with`]) — summed on the device in the passes'
    /// order (`project_backward` adding to one buffer), left there.
    pub(super) fn backward_sum_with<'a>(
        &self,
        g: &Gaussians<f32>,
        passes: impl IntoIterator<
            Item = (
                &'a GpuRendered,
                Box<dyn FnOnce(&mut wgpu::CommandEncoder) -> Result<wgpu::Buffer, GpuError> + 'a>,
            ),
        >,
    ) -> Result<GpuGrads, GpuError> {
        let passes: Vec<_> = passes.into_iter().collect();
        for (fwd, _) in &passes {
            check_shape(g, &fwd.state)?;
        }
        self.injected_fault()?;
        let n = g.len() as u64;
        let gs = 14 + g.rest_len() as u64;
        let buf = self.scoped(|| {
            let grads = self.sliced_storage("gradients", (n * gs * 4).max(4))?;
            let aux = self.storage("aux", (n * 24).max(4))?;
            let mut encoder = self.device.create_command_encoder(&Default::default());
            if passes.is_empty() {
                encoder.clear_buffer(&grads, 0, None);
            }
            let mut keep = Vec::new();
            for (k, (fwd, d_image)) in passes.into_iter().enumerate() {
                let d_buf = d_image(&mut encoder)?;
                self.encode_backward(
                    &mut encoder,
                    &fwd.state,
                    &d_buf,
                    &grads,
                    &aux,
                    k > 0,
                    &mut keep,
                )?;
                keep.push(d_buf);
            }
            self.queue.submit([encoder.finish()]);
            drop(keep);
            Ok(grads)
        })?;
        Ok(GpuGrads {
            buf,
            n: g.len() as u32,
            rest_len: g.rest_len(),
        })
    }

    /// `grads` read back, as a scene shaped like `g`.
    pub fn read_grads(
        &self,
        g: &Gaussians<f32>,
        grads: &GpuGrads,
    ) -> Result<Gaussians<f32>, GpuError> {
        if grads.n as usize != g.len() || grads.rest_len != g.rest_len() {
            return Err(RenderError::BadScene(format!(
                "gradients of {} Gaussians for a scene of {}",
                grads.n,
                g.len()
            ))
            .into());
        }
        let bytes = (g.len() * (14 + g.rest_len()) * 4) as u64;
        let encoder = self.device.create_command_encoder(&Default::default());
        let data = self.scoped(|| self.read(encoder, &[(&grads.buf, 0, bytes)]))?;
        Ok(unpack(
            bytemuck::cast_slice(&data),
            g.len(),
            g.rest_len(),
            g.sh_degree,
        ))
    }

    /// The device work of [`Self::backward`]: parameter gradients and the auxiliary outputs,
    /// read back.
    fn backward_checked(
        &self,
        st: &GpuState,
        d_image: impl FnOnce(&mut wgpu::CommandEncoder) -> Result<wgpu::Buffer, GpuError>,
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let d_buf = d_image(&mut encoder)?;
        let n = u64::from(st.n);
        let gs = 14 + st.rest_len as u64;
        let grads = self.sliced_storage("gradients", n * gs * 4)?;
        let aux = self.storage("aux", n * 24)?;
        let mut keep = Vec::new();
        self.encode_backward(&mut encoder, st, &d_buf, &grads, &aux, false, &mut keep)?;
        // Gradients and aux through one readback.
        let (gbytes, abytes) = (n * gs * 4, n * 24);
        let bytes = self.read(encoder, &[(&grads, 0, gbytes), (&aux, 0, abytes)])?;
        drop(keep);
        let floats: &[f32] = bytemuck::cast_slice(&bytes);
        let (g, a) = floats.split_at(gbytes as usize / 4);
        Ok((g.to_vec(), a.to_vec()))
    }

    /// Records one backward pass of the render `st` from ∂L/∂image in `d_buf`: the entries'
    /// slots, then `project_backward` writing — or, `accumulate`, adding — the parameters'
    /// gradients into `grads` and the auxiliary outputs into `aux`. Buffers the encoder still
    /// needs go to `keep`.
    #[allow(clippy::too_many_arguments)]
    fn encode_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        st: &GpuState,
        d_buf: &wgpu::Buffer,
        grads: &wgpu::Buffer,
        aux: &wgpu::Buffer,
        accumulate: bool,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let slots = self.storage("entry slots", u64::from(st.total) * 40)?;
        let gs = 14 + st.rest_len as u64;
        encoder.clear_buffer(&slots, 0, None);
        if st.total > 0 {
            let bg0 = bind(
                &self.device,
                &self.pipes.raster_backward,
                0,
                &[
                    (0, &st.cam),
                    (1, &st.splats),
                    (2, &st.vals),
                    (3, &st.owner),
                    (4, &st.ranges),
                    (5, &st.final_t),
                    (6, &st.n_contrib),
                    (7, d_buf),
                ],
            );
            let bg1 = bind(&self.device, &self.pipes.raster_backward, 1, &[(0, &slots)]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipes.raster_backward);
            pass.set_bind_group(0, &bg0, &[]);
            pass.set_bind_group(1, &bg1, &[]);
            pass.dispatch_workgroups(st.tiles.0, st.tiles.1, 1);
        }
        self.per_gaussian(
            encoder,
            &self.pipes.project_backward,
            st.n,
            &[(0, &st.cam), (4, &st.offsets), (5, &slots), (7, aux)],
            &[
                Sliced {
                    binding: 1,
                    buffer: &st.params,
                    floats: st.stride,
                },
                Sliced {
                    binding: 6,
                    buffer: grads,
                    floats: gs as u32,
                },
            ],
            accumulate,
            keep,
        )?;
        keep.push(slots);
        Ok(())
    }
}

/// A render's backward pass must be of a scene shaped like `g`.
fn check_shape(g: &Gaussians<f32>, st: &GpuState) -> Result<(), GpuError> {
    if g.len() != st.n as usize || g.rest_len() != st.rest_len || g.sh_degree != st.sh_degree {
        return Err(RenderError::BadScene(format!(
            "the render was of {} Gaussians, the scene has {}",
            st.n,
            g.len()
        ))
        .into());
    }
    Ok(())
}
