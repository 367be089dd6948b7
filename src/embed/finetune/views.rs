//! The training views and how a finetuning step renders them: the rasterizer, or — when the
//! finetuning moves colours only, the default — each view's [`Replay`], recorded the first time
//! the view is drawn, within [`REPLAY_BUDGET_BYTES`].

use serde::{Deserialize, Serialize};

use super::FinetuneError;
use crate::decoder::WatermarkModel;
use crate::decoder::eval::decode_images;
use std::sync::Arc;

use crate::render::gpu::{GpuGrads, GpuRendered, GpuRenderer, GpuScene, Rasterizer};
use crate::render::{self, RenderError, RenderOptions, Rendered, Replay};
use crate::scene::{Camera, Gaussians};

/// Memory the replays of one finetuning may hold; views past it are rasterised every step.
/// (Donut at 512²: ≈ 19 MB a view — peak memory 743 → 1 128 MiB with its 21 views recorded.)
pub const REPLAY_BUDGET_BYTES: usize = 1 << 30;

/// A training view: camera and the original scene's render through it.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    /// Linear RGB, row-major, clamped to [0, 1].
    pub target: Vec<[f32; 3]>,
}

/// Renders the targets (the original scene through each camera, clamped to [0, 1]) with the
/// rasterizer the finetuning will use, so that the unchanged scene matches its targets exactly
/// (a difference of rounding between the CPU and the GPU would otherwise be a gradient, and
/// Adam scales any gradient up to a full step).
pub fn target_views(
    original: &Gaussians,
    cameras: &[Camera],
    opts: &RenderOptions,
    rasterizer: &Rasterizer,
) -> Result<Vec<View>, RenderError> {
    let scene = rasterizer.prepare(original, opts)?;
    cameras
        .iter()
        .map(|c| {
            let (_, _, image) = scene.render_image(c)?;
            Ok(View {
                camera: c.clone(),
                target: image.iter().map(|p| p.map(|v| v.clamp(0.0, 1.0))).collect(),
            })
        })
        .collect()
}

/// How the training views decode, as a dispute decodes them: each rendered at 8 bits, logits
/// averaged over all of them.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewsCheck {
    /// After this many steps.
    pub step: usize,
    /// Bits equal to the message's.
    pub matches: usize,
    pub bits: usize,
    /// Smallest |averaged logit| over the bits.
    pub min_abs_logit: f32,
}

/// The logits of the training views of `g` as a dispute decodes them: each rendered to an
/// 8-bit image, decoded and the logits averaged ([`decode_images`], what `/v1/verify` runs).
pub(crate) fn views_logits(
    g: &Gaussians,
    views: &[View],
    model: &WatermarkModel,
    opts: &RenderOptions,
    rasterizer: &Rasterizer,
) -> Result<Vec<f32>, FinetuneError> {
    cameras_logits(g, views.iter().map(|v| &v.camera), model, opts, rasterizer)
}

/// [`views_logits`] through the cameras alone.
pub(crate) fn cameras_logits<'a>(
    g: &Gaussians,
    cameras: impl IntoIterator<Item = &'a Camera>,
    model: &WatermarkModel,
    opts: &RenderOptions,
    rasterizer: &Rasterizer,
) -> Result<Vec<f32>, FinetuneError> {
    let scene = rasterizer.prepare(g, opts).map_err(RenderError::from)?;
    let images = cameras
        .into_iter()
        .map(|c| {
            let (w, h, image) = scene.render_image(c)?;
            Ok(render::to_rgb8(w, h, &image))
        })
        .collect::<Result<Vec<_>, RenderError>>()?;
    Ok(decode_images(model, &images, &model.device().autodiff()).logits)
}

impl ViewsCheck {
    pub(super) fn new(step: usize, logits: &[f32], message: &[bool]) -> Self {
        Self {
            step,
            matches: logits
                .iter()
                .zip(message)
                .filter(|&(&z, &m)| (z > 0.0) == m)
                .count(),
            bits: message.len(),
            min_abs_logit: logits.iter().map(|z| z.abs()).fold(f32::INFINITY, f32::min),
        }
    }
}

/// PSNR (dB) of `g`'s renders of every view against the targets (pixels clamped to [0, 1],
/// one MSE over all views), through `renderer` (replayed where recorded: the same images).
pub(super) fn views_psnr(renderer: &mut Renderer, g: &Gaussians) -> Result<f32, RenderError> {
    let (mut sq, mut n) = (0.0f64, 0usize);
    let up = renderer.upload(g)?;
    for v in 0..renderer.views.len() {
        let frame = renderer.render_with(g, v, up.as_ref(), false)?;
        let image = frame.image();
        for (p, q) in image.iter().zip(&renderer.views[v].target) {
            for c in 0..3 {
                sq += f64::from(p[c].clamp(0.0, 1.0) - q[c]).powi(2);
            }
        }
        n += 3 * image.len();
    }
    let mse = sq / n.max(1) as f64;
    Ok(if mse > 0.0 {
        (-10.0 * mse.log10()) as f32
    } else {
        f32::INFINITY
    })
}

/// An edited copy of the scene ([`edited_scene`]), its clones' originals, and its upload.
type EditedUpload = (Arc<Gaussians>, Arc<Vec<usize>>, Option<GpuScene>);

/// One view as a step rendered it.
pub(super) enum Frame {
    Raster(Box<Rendered<f32>>),
    Replayed {
        view: usize,
        image: Vec<[f32; 3]>,
    },
    Gpu(Box<GpuRendered>),
    /// A view with some Gaussians removed or cloned: a replay recomposited with them
    /// ([`Replay::with_copies`]).
    Removed {
        replay: Box<Replay<f32>>,
        image: Vec<[f32; 3]>,
    },
    /// A view with some Gaussians removed or cloned, rasterised: `scene` is the edited scene
    /// ([`edited_scene`]: the removed ones transparent, each clone appended after the scene's
    /// own Gaussians; what `frame` rendered and back-propagates through), `clones` the
    /// Gaussian each appended one copies (their gradients are folded back into it).
    Masked {
        frame: Box<Frame>,
        scene: Arc<Gaussians>,
        clones: Arc<Vec<usize>>,
    },
}

impl Frame {
    /// Linear RGB, row-major, not clamped (a GPU render kept on the device has none here).
    pub fn image(&self) -> &[[f32; 3]] {
        match self {
            Frame::Raster(r) => &r.image,
            Frame::Replayed { image, .. } | Frame::Removed { image, .. } => image,
            Frame::Gpu(r) => {
                debug_assert!(
                    !r.image.is_empty(),
                    "a render kept on the device has no host image (Renderer::image_tensor)"
                );
                &r.image
            }
            Frame::Masked { frame, .. } => frame.image(),
        }
    }
}

/// Renders the training views and back-propagates through them.
pub(super) struct Renderer<'a> {
    views: &'a [View],
    opts: &'a RenderOptions,
    /// Per view, its replay once recorded; `None` when the geometry moves or on the GPU.
    replays: Option<Vec<Option<Replay<f32>>>>,
    bytes: usize,
    rasterizer: Rasterizer,
    /// The step's GPU renders stay on the device ([`Self::keep_on_device`]).
    resident: bool,
}

impl<'a> Renderer<'a> {
    /// `geometry_fixed`: no step will move a mean, scale, rotation or opacity (then views are
    /// replayed on the CPU; the GPU rasterises them every time).
    pub fn new(
        views: &'a [View],
        opts: &'a RenderOptions,
        geometry_fixed: bool,
        rasterizer: Rasterizer,
    ) -> Self {
        let replay = geometry_fixed && rasterizer == Rasterizer::Cpu;
        Self {
            views,
            opts,
            replays: replay.then(|| views.iter().map(|_| None).collect()),
            bytes: 0,
            rasterizer,
            resident: false,
        }
    }

    /// From now on the step's views rendered on the GPU stay on the device — their images are
    /// not read back ([`Frame::image`] is then empty; [`Self::image_tensor`] copies them on the
    /// device) — when `device` is that GPU's burn device. Returns whether they do.
    pub fn keep_on_device(&mut self, device: &burn::tensor::Device) -> Result<bool, RenderError> {
        self.resident = match &self.rasterizer {
            Rasterizer::Gpu(gpu) => gpu.burn_device()? == *device,
            Rasterizer::Cpu => false,
        };
        Ok(self.resident)
    }

    /// Views `vs` of `g`: replayed where recorded, otherwise rasterised (on the GPU from one
    /// upload of `g`).
    pub fn render_views(&mut self, g: &Gaussians, vs: &[usize]) -> Result<Vec<Frame>, RenderError> {
        let up = self.upload(g)?;
        vs.iter()
            .map(|&v| self.render_with(g, v, up.as_ref(), self.resident))
            .collect()
    }

    /// Views `vs` rendered on the GPU from `up` (another scene's upload of `g`'s shape: the
    /// device's live parameters, or a removal's copy of them).
    pub fn render_views_from(
        &mut self,
        g: &Gaussians,
        up: &GpuScene,
        vs: &[usize],
    ) -> Result<Vec<Frame>, RenderError> {
        vs.iter()
            .map(|&v| self.render_with(g, v, Some(up), self.resident))
            .collect()
    }

    /// `g` uploaded for the GPU's renders of it (`None` on the CPU).
    fn upload(&self, g: &Gaussians) -> Result<Option<GpuScene>, RenderError> {
        Ok(match &self.rasterizer {
            Rasterizer::Gpu(gpu) => Some(gpu.upload(g, self.opts)?),
            Rasterizer::Cpu => None,
        })
    }

    /// View `v` of `g`; on the GPU from `up`, `g`'s upload ([`Self::upload`]), its image
    /// left on the device when `resident`.
    fn render_with(
        &mut self,
        g: &Gaussians,
        v: usize,
        up: Option<&GpuScene>,
        resident: bool,
    ) -> Result<Frame, RenderError> {
        if let Rasterizer::Gpu(gpu) = &self.rasterizer {
            let fresh;
            let scene = match up {
                Some(s) => s,
                None => {
                    fresh = gpu.upload(g, self.opts)?;
                    &fresh
                }
            };
            let camera = &self.views[v].camera;
            let r = if resident {
                gpu.render_resident(scene, camera, self.opts)?
            } else {
                gpu.render_uploaded(scene, camera, self.opts)?
            };
            return Ok(Frame::Gpu(Box::new(r)));
        }
        if let Some(r) = self.replay(g, v)? {
            return Ok(Frame::Replayed {
                view: v,
                image: r.render(g)?,
            });
        }
        Ok(Frame::Raster(Box::new(render::render(
            g,
            &self.views[v].camera,
            self.opts,
        )?)))
    }

    /// View `v`'s replay, recorded from `g` the first time (`None` when views are not
    /// replayed, or past the memory budget).
    fn replay(&mut self, g: &Gaussians, v: usize) -> Result<Option<&Replay<f32>>, RenderError> {
        let Some(replays) = &mut self.replays else {
            return Ok(None);
        };
        if replays[v].is_none() && self.bytes < REPLAY_BUDGET_BYTES {
            let r = Replay::record(g, &self.views[v].camera, self.opts)?;
            self.bytes += r.bytes();
            tracing::debug!(
                view = v,
                contributions = r.contributions(),
                bytes = r.bytes(),
                total_bytes = self.bytes,
                "recorded a replay"
            );
            replays[v] = Some(r);
        }
        Ok(replays[v].as_ref())
    }

    /// Views `vs` of `g` with `copies[i]` copies of Gaussian i (scene-indexed; 0 removes it,
    /// 2 clones it, [`Replay::with_copies`]): each recomposited from its replay where there is
    /// one, otherwise rasterised from a copy of the scene edited by [`edited_scene`] (one copy,
    /// and on the GPU one upload, for all such views).
    pub fn render_views_edited(
        &mut self,
        g: &Gaussians,
        vs: &[usize],
        copies: &[u8],
    ) -> Result<Vec<Frame>, RenderError> {
        check_copies(copies, g)?;
        let mut masked: Option<EditedUpload> = None;
        let mut frames = Vec::with_capacity(vs.len());
        for &v in vs {
            if let Some(r) = self.replay(g, v)? {
                let replay = r.with_copies(copies)?;
                let image = replay.render(g)?;
                frames.push(Frame::Removed {
                    replay: Box::new(replay),
                    image,
                });
                continue;
            }
            // No replay of view `v` exists (or may be recorded): this rasterises.
            if masked.is_none() {
                let (m, clones) = self.edited(g, copies)?;
                let up = self.upload(&m)?;
                masked = Some((Arc::new(m), Arc::new(clones), up));
            }
            let (scene, clones, up) = masked.as_ref().expect("set above");
            let frame = self.render_with(scene, v, up.as_ref(), self.resident)?;
            frames.push(Frame::Masked {
                frame: Box::new(frame),
                scene: scene.clone(),
                clones: clones.clone(),
            });
        }
        Ok(frames)
    }

    /// Views `vs` of a perturbed copy `scene` of the finetuned scene (same Gaussians, moved),
    /// rasterised whatever the replays (they hold the unperturbed geometry), edited by
    /// `copies` when given ([`edited_scene`]). Back-propagating through a frame gives ∂L/∂θ at
    /// the perturbed parameters.
    pub fn rasterise_views(
        &mut self,
        scene: &Gaussians,
        vs: &[usize],
        copies: Option<&[u8]>,
    ) -> Result<Vec<Frame>, RenderError> {
        let (masked, clones) = match copies {
            Some(copies) => {
                check_copies(copies, scene)?;
                self.edited(scene, copies)?
            }
            None => (scene.clone(), Vec::new()),
        };
        let up = self.upload(&masked)?;
        let (masked, clones) = (Arc::new(masked), Arc::new(clones));
        vs.iter()
            .map(|&v| {
                let frame = match &self.rasterizer {
                    Rasterizer::Gpu(gpu) => {
                        let (up, camera) = (up.as_ref().expect("uploaded"), &self.views[v].camera);
                        Frame::Gpu(Box::new(if self.resident {
                            gpu.render_resident(up, camera, self.opts)?
                        } else {
                            gpu.render_uploaded(up, camera, self.opts)?
                        }))
                    }
                    Rasterizer::Cpu => Frame::Raster(Box::new(render::render(
                        &masked,
                        &self.views[v].camera,
                        self.opts,
                    )?)),
                };
                Ok(Frame::Masked {
                    frame: Box::new(frame),
                    scene: masked.clone(),
                    clones: clones.clone(),
                })
            })
            .collect()
    }

    /// `g` edited as `copies` says, for the rasterizer at hand: [`edited_scene`] on the CPU;
    /// on the GPU, whose backward stays scene-shaped, removal only (an error for clones).
    fn edited(&self, g: &Gaussians, copies: &[u8]) -> Result<(Gaussians, Vec<usize>), RenderError> {
        match self.rasterizer {
            Rasterizer::Cpu => Ok(edited_scene(g, copies)),
            Rasterizer::Gpu(_) if copies.iter().any(|&c| c > 1) => Err(RenderError::Device(
                "cloning in the EOT term runs on the CPU rasterizer".into(),
            )),
            Rasterizer::Gpu(_) => Ok((edited_scene(g, copies).0, Vec::new())),
        }
    }

    /// `frame`'s image as a burn tensor `[1, 3, H, W]` on `device`, copied on the device, when
    /// the frame is the GPU's and `device` is that GPU's burn device (`None` otherwise: the
    /// caller uploads the host image).
    pub fn image_tensor(
        &self,
        frame: &Frame,
        device: &burn::tensor::Device,
    ) -> Result<Option<burn::tensor::Tensor<4>>, RenderError> {
        let Rasterizer::Gpu(gpu) = &self.rasterizer else {
            return Ok(None);
        };
        let r = match frame {
            Frame::Gpu(r) => r,
            Frame::Masked { frame, .. } => return self.image_tensor(frame, device),
            _ => return Ok(None),
        };
        if gpu.burn_device()? != *device {
            return Ok(None);
        }
        Ok(Some(gpu.image_tensor(r)?))
    }

    /// ∂L/∂θ from each ∂L/∂image of `frame` in `d_images` (scene-shaped; a replayed view
    /// gives the SH coefficients' gradient only, the geometry being fixed — all of them in one
    /// pass over its weights).
    pub fn backward_each(
        &self,
        g: &Gaussians,
        frame: &Frame,
        d_images: &[&[[f32; 3]]],
    ) -> Result<Vec<Gaussians>, RenderError> {
        match frame {
            Frame::Raster(r) => d_images
                .iter()
                .map(|d| Ok(render::backward(g, r, d)?.params))
                .collect(),
            Frame::Gpu(r) => {
                let Rasterizer::Gpu(gpu) = &self.rasterizer else {
                    unreachable!("a GPU frame comes from the GPU rasterizer")
                };
                d_images
                    .iter()
                    .map(|d| Ok(gpu.backward(g, r, d)?.params))
                    .collect()
            }
            Frame::Replayed { view, .. } => self
                .replays
                .as_ref()
                .and_then(|r| r[*view].as_ref())
                .expect("a replayed frame has its replay")
                .backward_each(g, d_images),
            Frame::Removed { replay, .. } => replay.backward_each(g, d_images),
            Frame::Masked {
                frame,
                scene,
                clones,
            } => Ok(self
                .backward_each(scene, frame, d_images)?
                .into_iter()
                .map(|d| fold_clones(d, clones))
                .collect()),
        }
    }

    /// Σ over `passes` of ∂L/∂θ, each pass a GPU frame and its ∂L/∂image (a burn tensor `[1,
    /// 3, H, W]` on the GPU's burn device): copied into the rasterizer's backward and summed on
    /// the device, read back once (`g` gives the shape; a frame of a copy with Gaussians
    /// removed back-propagates at its own parameters).
    pub fn backward_summed(
        &self,
        g: &Gaussians,
        passes: &[(&Frame, burn::tensor::Tensor<4>)],
    ) -> Result<Gaussians, RenderError> {
        let (gpu, sum) = self.sum_on_device(g, passes)?;
        Ok(gpu.read_grads(g, &sum)?)
    }

    /// [`Self::backward_summed`] left on the device (for its Adam step).
    pub fn backward_summed_on_device(
        &self,
        g: &Gaussians,
        passes: &[(&Frame, burn::tensor::Tensor<4>)],
    ) -> Result<GpuGrads, RenderError> {
        Ok(self.sum_on_device(g, passes)?.1)
    }

    fn sum_on_device(
        &self,
        g: &Gaussians,
        passes: &[(&Frame, burn::tensor::Tensor<4>)],
    ) -> Result<(&GpuRenderer, GpuGrads), RenderError> {
        let Rasterizer::Gpu(gpu) = &self.rasterizer else {
            return Err(not_on_the_gpu());
        };
        let passes = passes
            .iter()
            .map(|(frame, d)| Ok((gpu_render(frame).ok_or_else(not_on_the_gpu)?, d.clone())))
            .collect::<Result<Vec<_>, RenderError>>()?;
        Ok((gpu, gpu.backward_tensors_summed_on_device(g, &passes)?))
    }
}

/// The GPU render of a frame, through a removal's copy.
fn gpu_render(frame: &Frame) -> Option<&GpuRendered> {
    match frame {
        Frame::Gpu(r) => Some(r),
        Frame::Masked { frame, .. } => gpu_render(frame),
        _ => None,
    }
}

fn not_on_the_gpu() -> RenderError {
    RenderError::Device("a device-side gradient for a frame that is not on the GPU".into())
}

/// A count of copies for each Gaussian of the scene.
fn check_copies(copies: &[u8], g: &Gaussians) -> Result<(), RenderError> {
    if copies.len() != g.len() {
        return Err(RenderError::BadScene(format!(
            "copies of {} Gaussians for a scene of {}",
            copies.len(),
            g.len()
        )));
    }
    Ok(())
}

/// `g` as the model attacks edit it, in a form the rasterizer back-propagates through: the
/// Gaussians with 0 copies made transparent (their gradient is then 0), and c − 1 more copies
/// of those with c > 1 appended, as [`crate::attack::model::ModelAttack::Clone`] appends them;
/// returns the scene and, for each appended Gaussian, the one it copies.
pub(super) fn edited_scene(g: &Gaussians, copies: &[u8]) -> (Gaussians, Vec<usize>) {
    let mut m = g.clone();
    // α = sigmoid(−40) ≈ 4e-18, far below the 1/255 a Gaussian needs to be drawn.
    for (o, &c) in m.opacity_logits.iter_mut().zip(copies) {
        if c == 0 {
            *o = -40.0;
        }
    }
    let clones: Vec<usize> = copies
        .iter()
        .enumerate()
        .flat_map(|(i, &c)| std::iter::repeat_n(i, usize::from(c.saturating_sub(1))))
        .collect();
    if clones.is_empty() {
        return (m, clones);
    }
    let idx: Vec<usize> = (0..g.len()).chain(clones.iter().copied()).collect();
    (crate::embed::subset(&m, &idx), clones)
}

/// The gradient of an [`edited_scene`] folded back onto the scene: each appended copy's
/// gradient added to its original's (they share every parameter).
fn fold_clones(mut d: Gaussians, clones: &[usize]) -> Gaussians {
    if clones.is_empty() {
        return d;
    }
    let n = d.len() - clones.len();
    let rl = d.rest_len();
    for (k, &i) in clones.iter().enumerate() {
        let j = n + k;
        let add = |a: &mut [f32], b: &[f32]| a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        let (m, s, r, dc) = (d.means[j], d.log_scales[j], d.rotations[j], d.sh_dc[j]);
        add(&mut d.means[i], &m);
        add(&mut d.log_scales[i], &s);
        add(&mut d.rotations[i], &r);
        add(&mut d.sh_dc[i], &dc);
        d.opacity_logits[i] += d.opacity_logits[j];
        let rest: Vec<f32> = d.sh_rest[j * rl..(j + 1) * rl].to_vec();
        add(&mut d.sh_rest[i * rl..(i + 1) * rl], &rest);
    }
    d.means.truncate(n);
    d.log_scales.truncate(n);
    d.rotations.truncate(n);
    d.opacity_logits.truncate(n);
    d.sh_dc.truncate(n);
    d.sh_rest.truncate(n * rl);
    d
}
