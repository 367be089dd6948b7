//! Per-Gaussian kernels over scenes larger than one storage binding. A scene's parameters
//! (`cam.stride` floats a Gaussian: 236 B at SH 3) and their gradients sit in buffers of up to
//! the device's `max_buffer_size` ([`GpuRenderer::sliced_storage`]); `project` and
//! `project_backward` run over them a chunk of Gaussians at a time, each dispatch binding only
//! its chunk's bytes — from an offset aligned to `min_storage_buffer_offset_alignment`, at most
//! `max_storage_buffer_binding_size` long — and reading the chunk's first global index and where
//! its first Gaussian starts inside those bindings from the `Chunk` uniform
//! (`shaders/project.wgsl`). What the kernels index by global Gaussian (splats, footprint
//! rectangles, tile counts, the backward's aux) stays bound whole: at ≤ 48 B a Gaussian it fits
//! one binding much longer (lavapipe's 128 MiB: 2.8 M Gaussians), and `raster` reads splats by
//! global index. Every chunking computes the same values as one dispatch (tested bit for bit).

use std::num::NonZeroU64;

use super::{GpuError, GpuRenderer, words};

/// One chunk's slice of a per-Gaussian buffer: bound from `offset` (aligned), `size` bytes; the
/// chunk's first Gaussian at float `at` of that binding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Slice {
    pub offset: u64,
    pub size: u64,
    pub at: u32,
}

/// The slice holding Gaussians [first, first + count) of a buffer of `bytes_per` bytes a
/// Gaussian (a multiple of 4), bound from a multiple of `align` (a power of two ≥ 4).
pub(crate) fn slice(first: u32, count: u32, bytes_per: u64, align: u64) -> Slice {
    let start = u64::from(first) * bytes_per;
    let offset = start / align * align;
    Slice {
        offset,
        size: start - offset + u64::from(count) * bytes_per,
        at: ((start - offset) / 4) as u32,
    }
}

/// The most Gaussians whose slice ([`slice`]) fits a binding of `limit` bytes wherever the
/// chunk starts: the aligned offset leaves at most `align − 4` bytes before its first Gaussian.
pub(crate) fn most_per_chunk(limit: u64, align: u64, bytes_per: u64) -> u64 {
    limit.saturating_sub(align - 4) / bytes_per.max(1)
}

/// A per-Gaussian buffer a chunked dispatch binds a slice of.
pub(crate) struct Sliced<'a> {
    pub binding: u32,
    pub buffer: &'a wgpu::Buffer,
    /// Floats a Gaussian.
    pub floats: u32,
}

impl GpuRenderer {
    /// A storage buffer the kernels bind only in slices ([`Self::per_gaussian`]): up to the
    /// device's `max_buffer_size` rather than its binding limit.
    pub(crate) fn sliced_storage(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        self.storage_within(label, bytes, self.device.limits().max_buffer_size)
    }

    /// Binding offsets of the sliced buffers: the device's alignment (at least 4).
    fn slice_align(&self) -> u64 {
        u64::from(self.device.limits().min_storage_buffer_offset_alignment).max(4)
    }

    /// Gaussians a dispatch covers when its largest sliced buffer holds `floats` floats a
    /// Gaussian: as many as one binding takes, or fewer when set
    /// ([`Self::with_gaussians_per_dispatch`]).
    pub(super) fn per_chunk(&self, floats: u32) -> Result<u32, GpuError> {
        let limit = self.device.limits().max_storage_buffer_binding_size;
        let bytes = u64::from(floats) * 4;
        let most = most_per_chunk(limit, self.slice_align(), bytes);
        if most == 0 {
            return Err(GpuError::TooLarge {
                needed: bytes + self.slice_align() - 4,
                limit,
            });
        }
        let most = u32::try_from(most).unwrap_or(u32::MAX);
        Ok(self.per_dispatch.map_or(most, |p| p.clamp(1, most)))
    }

    /// Records `pipe` (group 0) over Gaussians [0, n), a chunk a dispatch: `whole` bound whole,
    /// each of `sliced` bound to the chunk's slice, the `Chunk` uniform at binding 8 (the first
    /// index, the count, the float where the chunk starts in the first and second sliced
    /// binding, and `accumulate`: whether `project_backward` adds to its gradients' buffer).
    /// The uniforms go to `keep`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn per_gaussian(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipe: &wgpu::ComputePipeline,
        n: u32,
        whole: &[(u32, &wgpu::Buffer)],
        sliced: &[Sliced],
        accumulate: bool,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let floats = sliced.iter().map(|s| s.floats).max().unwrap_or(1);
        let per = self.per_chunk(floats)?;
        let align = self.slice_align();
        let layout = pipe.get_bind_group_layout(0);
        let mut groups = Vec::new();
        let mut first = 0u32;
        while first < n {
            let count = per.min(n - first);
            let slices: Vec<Slice> = sliced
                .iter()
                .map(|s| slice(first, count, u64::from(s.floats) * 4, align))
                .collect();
            let at = |k: usize| slices.get(k).map_or(0, |s| s.at);
            let uniform = self.uniform(words(&[
                first,
                count,
                at(0),
                at(1),
                u32::from(accumulate),
                0,
                0,
                0,
            ]));
            let mut entries: Vec<wgpu::BindGroupEntry> = whole
                .iter()
                .map(|(b, buf)| wgpu::BindGroupEntry {
                    binding: *b,
                    resource: buf.as_entire_binding(),
                })
                .collect();
            for (s, sl) in sliced.iter().zip(&slices) {
                entries.push(wgpu::BindGroupEntry {
                    binding: s.binding,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: s.buffer,
                        offset: sl.offset,
                        size: NonZeroU64::new(sl.size),
                    }),
                });
            }
            entries.push(wgpu::BindGroupEntry {
                binding: 8,
                resource: uniform.as_entire_binding(),
            });
            let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &layout,
                entries: &entries,
            });
            groups.push((bg, super::grid(count.div_ceil(256))));
            keep.push(uniform);
            first += count;
        }
        if groups.is_empty() {
            return Ok(());
        }
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipe);
        for (bg, (gx, gy)) in &groups {
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(*gx, *gy, 1);
        }
        Ok(())
    }
}
