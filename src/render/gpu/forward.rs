//! The GPU path's forward pass: a scene packed and uploaded ([`GpuScene`]), rendered through a
//! camera ([`GpuRenderer::render_uploaded`]) — project, scan, emit, sort, tile ranges,
//! composite — with what the backward pass needs kept on the device ([`GpuRendered`]).

use super::chunk;
use super::sort;
use super::{GpuError, GpuRenderer, bind, grid, words};
use crate::render::{ALPHA_MIN, RenderError, RenderOptions, TILE, check_camera, check_scene};
use crate::scene::{Camera, Gaussians};

/// A render of the GPU path; keep it to run [`GpuRenderer::backward`].
pub struct GpuRendered {
    pub width: u32,
    pub height: u32,
    /// Linear RGB, row-major, not clamped (as [`crate::render::Rendered::image`]), read back
    /// by [`GpuRenderer::render_uploaded`]; empty after [`GpuRenderer::render_resident`], whose
    /// image stays on the device ([`GpuRenderer::image_tensor`], [`GpuRenderer::read_image`]).
    /// The transmittance left at each pixel stays there too ([`GpuRenderer::read_final_t`]).
    pub image: Vec<[f32; 3]>,
    /// (tile, Gaussian) pairs sorted and composited.
    pub tile_entries: usize,
    pub(super) state: GpuState,
}

impl std::fmt::Debug for GpuRendered {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRendered")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("tile_entries", &self.tile_entries)
            .finish_non_exhaustive()
    }
}

/// A scene packed and uploaded once for several renders ([`GpuRenderer::upload`]): each
/// [`GpuRenderer::render`] packs and uploads its scene (236 B a Gaussian at SH 3), which for
/// many views of one scene — a job's targets and calibration, a step's views, `splatmark
/// render` — is host work and bus traffic repeated for nothing.
pub struct GpuScene {
    pub(super) n: u32,
    pub(super) rest_len: usize,
    /// The scene's SH degree (a render may use fewer).
    pub(super) sh_degree: u8,
    /// Floats a Gaussian in `params` (14 + `rest_len`, + 3 with a colour override).
    pub(super) stride: u32,
    /// Whether the upload carries a colour override per Gaussian (`RenderOptions::colors`).
    pub(super) overrides: bool,
    pub(super) params: wgpu::Buffer,
}

impl std::fmt::Debug for GpuScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuScene")
            .field("gaussians", &self.n)
            .field("sh_degree", &self.sh_degree)
            .field("overrides", &self.overrides)
            .finish_non_exhaustive()
    }
}

impl GpuScene {
    /// Gaussians uploaded.
    pub fn len(&self) -> usize {
        self.n as usize
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }
}

/// What the backward pass needs of a forward pass, on the device.
pub(super) struct GpuState {
    pub(super) n: u32,
    pub(super) total: u32,
    pub(super) tiles: (u32, u32),
    pub(super) rest_len: usize,
    pub(super) sh_degree: u8,
    /// Floats a Gaussian in `params` (the gradients: 14 + `rest_len`).
    pub(super) stride: u32,
    pub(super) cam: wgpu::Buffer,
    pub(super) params: wgpu::Buffer,
    pub(super) splats: wgpu::Buffer,
    pub(super) offsets: wgpu::Buffer,
    pub(super) vals: wgpu::Buffer,
    pub(super) owner: wgpu::Buffer,
    pub(super) ranges: wgpu::Buffer,
    pub(super) final_t: wgpu::Buffer,
    pub(super) n_contrib: wgpu::Buffer,
    /// The image, linear RGB row-major (what `GpuRendered::image` read back).
    pub(super) image: wgpu::Buffer,
}

impl GpuRenderer {
    /// Renders `g` through `camera` (the CPU reference's [`super::render`], on this device).
    /// A failure of the device (validation, out of memory, lost) is an error, not a panic.
    /// Several views of one scene: [`Self::upload`] it once and [`Self::render_uploaded`].
    pub fn render(
        &self,
        g: &Gaussians<f32>,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<GpuRendered, GpuError> {
        check_camera(camera, opts)?;
        let scene = self.upload(g, opts)?;
        self.render_uploaded(&scene, camera, opts)
    }

    /// Packs `g` — with `opts.colors`, its colour override, if any; the other options are
    /// the renders' — and uploads it for [`Self::render_uploaded`].
    pub fn upload(&self, g: &Gaussians<f32>, opts: &RenderOptions) -> Result<GpuScene, GpuError> {
        check_scene(g, opts)?;
        let n = u32::try_from(g.len())
            .map_err(|_| RenderError::BadScene("more than 2³² Gaussians".into()))?;
        let overrides = opts.colors.as_deref();
        let rest = g.rest_len();
        let stride = 14 + rest + if overrides.is_some() { 3 } else { 0 };
        let mut params = Vec::with_capacity(g.len() * stride);
        for i in 0..g.len() {
            params.extend_from_slice(&g.means[i]);
            params.extend_from_slice(&g.log_scales[i]);
            params.extend_from_slice(&g.rotations[i]);
            params.push(g.opacity_logits[i]);
            params.extend_from_slice(&g.sh_dc[i]);
            params.extend_from_slice(g.rest_of(i));
            if let Some(c) = overrides {
                params.extend_from_slice(&c[i]);
            }
        }
        let params = self.scoped(|| {
            let buf = self.sliced_storage("params", params.len() as u64 * 4)?;
            self.queue
                .write_buffer(&buf, 0, bytemuck::cast_slice(&params));
            Ok(buf)
        })?;
        Ok(GpuScene {
            n,
            rest_len: rest,
            sh_degree: g.sh_degree,
            stride: stride as u32,
            overrides: overrides.is_some(),
            params,
        })
    }

    /// Renders an uploaded scene through `camera`: the image [`Self::render`] gives of the
    /// scene `scene` was uploaded from. The colour override is the upload's: `opts.colors`
    /// must be set exactly when the upload's was (its values are not read again).
    pub fn render_uploaded(
        &self,
        scene: &GpuScene,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<GpuRendered, GpuError> {
        self.render_scene(scene, camera, opts, true)
    }

    /// [`Self::render_uploaded`] without reading the image back: it stays on the device for
    /// the decoder and the losses ([`Self::image_tensor`]) and the backward pass
    /// ([`Self::backward_tensor`]); `image` is empty ([`Self::read_image`] reads it).
    pub fn render_resident(
        &self,
        scene: &GpuScene,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<GpuRendered, GpuError> {
        self.render_scene(scene, camera, opts, false)
    }

    /// The checks, then the render (its image read back when `read_image`).
    fn render_scene(
        &self,
        scene: &GpuScene,
        camera: &Camera,
        opts: &RenderOptions,
        read_image: bool,
    ) -> Result<GpuRendered, GpuError> {
        check_camera(camera, opts)?;
        check_override(scene, opts)?;
        self.injected_fault()?;
        self.scoped(|| self.render_checked(scene, camera, opts, read_image))
    }

    /// The image of `r` (linear RGB, row-major, not clamped), read from the device.
    pub fn read_image(&self, r: &GpuRendered) -> Result<Vec<[f32; 3]>, GpuError> {
        let px = u64::from(r.width) * u64::from(r.height);
        let encoder = self.device.create_command_encoder(&Default::default());
        let bytes = self.scoped(|| self.read(encoder, &[(&r.state.image, 0, px * 12)]))?;
        let floats: &[f32] = bytemuck::cast_slice(&bytes);
        Ok(floats.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// The transmittance left at each pixel of `r` (row-major), read from the device.
    pub fn read_final_t(&self, r: &GpuRendered) -> Result<Vec<f32>, GpuError> {
        let px = u64::from(r.width) * u64::from(r.height);
        let encoder = self.device.create_command_encoder(&Default::default());
        let bytes = self.scoped(|| self.read(encoder, &[(&r.state.final_t, 0, px * 4)]))?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }

    fn render_checked(
        &self,
        scene: &GpuScene,
        camera: &Camera,
        opts: &RenderOptions,
        read_image: bool,
    ) -> Result<GpuRendered, GpuError> {
        let n = scene.n;
        let (w, h) = (camera.width, camera.height);
        let sh_degree = if scene.overrides {
            0
        } else {
            opts.sh_degree
                .map_or(scene.sh_degree, |d| d.min(scene.sh_degree))
        };
        let stride = scene.stride;
        let tiles_x = (w as usize).div_ceil(TILE) as u32;
        let tiles_y = (h as usize).div_ceil(TILE) as u32;
        let n_tiles = tiles_x * tiles_y;
        let cam_bytes = camera_uniform(camera, opts, n, sh_degree, stride, tiles_x, tiles_y);
        let cam_buf = self.uniform(&cam_bytes);
        let param_buf = &scene.params;
        let splats = self.storage("splats", u64::from(n) * 48)?;
        let tiles = self.storage("tiles", u64::from(n) * 16)?;
        let counts = self.storage("counts", (u64::from(n) + 1) * 4)?;

        // Project, then scan the tile counts; read the total back to size the key buffers.
        let mut encoder = self.device.create_command_encoder(&Default::default());
        encoder.clear_buffer(&counts, 0, None);
        let mut keep = Vec::new();
        self.per_gaussian(
            &mut encoder,
            &self.pipes.project,
            n,
            &[(0, &cam_buf), (2, &splats), (3, &tiles), (4, &counts)],
            &[chunk::Sliced {
                binding: 1,
                buffer: param_buf,
                floats: stride,
            }],
            false,
            &mut keep,
        )?;
        self.scan(&mut encoder, &counts, n + 1, &mut keep)?;
        let total_bytes = self.read(encoder, &[(&counts, u64::from(n) * 4, 4)])?;
        drop(keep);
        let total = u32::from_le_bytes(total_bytes[..4].try_into().expect("4 bytes"));

        // Emit the keys, sort them, find each tile's range, composite.
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let keys = sort::Pairs::new(self, total)?;
        let owner = self.storage("owner", u64::from(total) * 4)?;
        let ranges = self.storage("ranges", u64::from(n_tiles) * 8)?;
        encoder.clear_buffer(&ranges, 0, None);
        let image = self.storage("image", u64::from(w) * u64::from(h) * 12)?;
        let final_t = self.storage("final T", u64::from(w) * u64::from(h) * 4)?;
        let n_contrib = self.storage("contributors", u64::from(w) * u64::from(h) * 4)?;
        if total > 0 {
            let bg = bind(
                &self.device,
                &self.pipes.emit,
                0,
                &[
                    (0, &cam_buf),
                    (1, &splats),
                    (2, &tiles),
                    (3, &counts),
                    (4, &keys.hi),
                    (5, &keys.lo),
                    (6, &keys.val),
                    (8, &owner),
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            let per_gaussian = grid(n.div_ceil(256));
            pass.set_pipeline(&self.pipes.emit);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(per_gaussian.0, per_gaussian.1, 1);
        }
        let tile_bits = 32 - (n_tiles.max(2) - 1).leading_zeros();
        let mut keep = Vec::new();
        let sorted = self
            .pipes
            .sort
            .sort(self, &mut encoder, keys, total, tile_bits, &mut keep)?;
        if total > 0 {
            let bg = bind(
                &self.device,
                &self.pipes.tile_ranges,
                0,
                &[(0, &cam_buf), (3, &counts), (4, &sorted.hi), (7, &ranges)],
            );
            let per_entry = grid(total.div_ceil(256));
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipes.tile_ranges);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(per_entry.0, per_entry.1, 1);
        }
        {
            let bg0 = bind(
                &self.device,
                &self.pipes.raster,
                0,
                &[
                    (0, &cam_buf),
                    (1, &splats),
                    (6, &sorted.val),
                    (7, &ranges),
                    (8, &owner),
                ],
            );
            let bg1 = bind(
                &self.device,
                &self.pipes.raster,
                1,
                &[(0, &image), (1, &final_t), (2, &n_contrib)],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipes.raster);
            pass.set_bind_group(0, &bg0, &[]);
            pass.set_bind_group(1, &bg1, &[]);
            pass.dispatch_workgroups(tiles_x, tiles_y, 1);
        }
        let px = u64::from(w) * u64::from(h);
        let rgb = if read_image {
            let bytes = self.read(encoder, &[(&image, 0, px * 12)])?;
            let floats: &[f32] = bytemuck::cast_slice(&bytes);
            floats.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        } else {
            self.queue.submit([encoder.finish()]);
            Vec::new()
        };
        drop(keep);
        Ok(GpuRendered {
            width: w,
            height: h,
            image: rgb,
            tile_entries: total as usize,
            state: GpuState {
                n,
                total,
                tiles: (tiles_x, tiles_y),
                rest_len: scene.rest_len,
                sh_degree: scene.sh_degree,
                stride,
                cam: cam_buf,
                params: param_buf.clone(),
                splats,
                offsets: counts,
                vals: sorted.val,
                owner,
                ranges,
                final_t,
                n_contrib,
                image,
            },
        })
    }
}

/// Values laid out as [`GpuRenderer::upload`] packs a scene without a colour override (14 +
/// `rest_len` floats a Gaussian: mean, log-scale, quaternion, opacity logit, SH DC, the rest) —
/// parameters, or their gradients — back into a scene of `n` Gaussians.
pub(super) fn unpack(values: &[f32], n: usize, rest_len: usize, sh_degree: u8) -> Gaussians<f32> {
    let floats = 14 + rest_len;
    let mut g = Gaussians::with_capacity(n, sh_degree);
    for q in values.chunks_exact(floats).take(n) {
        g.means.push([q[0], q[1], q[2]]);
        g.log_scales.push([q[3], q[4], q[5]]);
        g.rotations.push([q[6], q[7], q[8], q[9]]);
        g.opacity_logits.push(q[10]);
        g.sh_dc.push([q[11], q[12], q[13]]);
        g.sh_rest.extend_from_slice(&q[14..]);
    }
    g
}

/// A render asks for a colour override exactly when the upload carries one.
fn check_override(scene: &GpuScene, opts: &RenderOptions) -> Result<(), GpuError> {
    if opts.colors.is_some() != scene.overrides {
        return Err(RenderError::BadScene(format!(
            "the scene was uploaded {} a colour override, the render asks {} one",
            if scene.overrides { "with" } else { "without" },
            if opts.colors.is_some() {
                "for"
            } else {
                "for none of"
            },
        ))
        .into());
    }
    Ok(())
}

/// The `Camera` uniform of the kernels (see `shaders/project.wgsl`).
fn camera_uniform(
    cam: &Camera,
    opts: &RenderOptions,
    n: u32,
    sh_degree: u8,
    stride: u32,
    tiles_x: u32,
    tiles_y: u32,
) -> Vec<u8> {
    let c = crate::render::project::Cam::<f32>::new(cam, opts.near);
    let mut f: Vec<f32> = Vec::with_capacity(40);
    for r in 0..3 {
        f.extend_from_slice(&c.w[r]);
        f.push(0.0);
    }
    f.extend_from_slice(&c.t);
    f.push(0.0);
    f.extend_from_slice(&c.center);
    f.push(0.0);
    f.extend_from_slice(&[
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        c.lim_x,
        c.lim_y,
        c.near,
        ALPHA_MIN as f32,
    ]);
    f.extend_from_slice(&opts.background);
    f.push(0.0);
    let mut bytes: Vec<u8> = bytemuck::cast_slice(&f).to_vec();
    let u = [
        cam.width,
        cam.height,
        tiles_x,
        tiles_y,
        n,
        u32::from(sh_degree),
        stride,
        u32::from(opts.colors.is_some()),
    ];
    bytes.extend_from_slice(words(&u));
    bytes
}
