//! Stable LSD radix sort of (64-bit key, u32 value) pairs on the GPU (`shaders/sort.wgsl`),
//! 4 bits a pass: the depth half of the key (32 bits) first, then as many bits of the tile half
//! as the tile count needs. Each pass: per-block digit histograms, their exclusive scan
//! (digit-major), a stable scatter. Exact, and the same order on every device.

use super::{GpuError, GpuRenderer, bind, grid, pipeline, words};

/// Key halves and values in three buffers.
pub(crate) struct Pairs {
    pub hi: wgpu::Buffer,
    pub lo: wgpu::Buffer,
    pub val: wgpu::Buffer,
}

impl Pairs {
    pub fn new(r: &GpuRenderer, n: u32) -> Result<Self, GpuError> {
        let bytes = u64::from(n) * 4;
        Ok(Self {
            hi: r.storage("keys hi", bytes)?,
            lo: r.storage("keys lo", bytes)?,
            val: r.storage("values", bytes)?,
        })
    }
}

pub(crate) struct SortPipelines {
    count: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
}

impl SortPipelines {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("sort"),
            source: wgpu::ShaderSource::Wgsl(include_str!("../../../shaders/sort.wgsl").into()),
        });
        Self {
            count: pipeline(device, &module, "count"),
            scatter: pipeline(device, &module, "scatter"),
        }
    }

    /// Records the sort of the first `n` pairs of `pairs` by (hi, lo), using the low
    /// `hi_bits` bits of `hi`; returns the buffers that hold the result.
    pub fn sort(
        &self,
        r: &GpuRenderer,
        encoder: &mut wgpu::CommandEncoder,
        pairs: Pairs,
        n: u32,
        hi_bits: u32,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<Pairs, GpuError> {
        if n <= 1 {
            return Ok(pairs);
        }
        let blocks = n.div_ceil(256);
        let (gx, gy) = grid(blocks);
        let hist = r.storage("histogram", u64::from(blocks) * 16 * 4)?;
        let mut src = pairs;
        let mut dst = Pairs::new(r, n)?;
        let shifts = (0..32)
            .step_by(4)
            .chain((32..32 + hi_bits.min(32)).step_by(4));
        for shift in shifts {
            let params = r.uniform(words(&[n, blocks, gx, shift]));
            let count_bg = bind(
                &r.device,
                &self.count,
                0,
                &[(0, &params), (1, &src.hi), (2, &src.lo), (7, &hist)],
            );
            {
                let mut pass = encoder.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.count);
                pass.set_bind_group(0, &count_bg, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
            r.scan(encoder, &hist, blocks * 16, keep)?;
            let scatter_bg = bind(
                &r.device,
                &self.scatter,
                0,
                &[
                    (0, &params),
                    (1, &src.hi),
                    (2, &src.lo),
                    (3, &src.val),
                    (4, &dst.hi),
                    (5, &dst.lo),
                    (6, &dst.val),
                    (7, &hist),
                ],
            );
            {
                let mut pass = encoder.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.scatter);
                pass.set_bind_group(0, &scatter_bg, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
            keep.push(params);
            std::mem::swap(&mut src, &mut dst);
        }
        keep.extend([hist, dst.hi, dst.lo, dst.val]);
        Ok(src)
    }
}
