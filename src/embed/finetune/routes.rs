//! A step's image side, per route: L_vis of its renders, ∂L/∂image for the watermark route
//! and the visual route, and both back through the rasterizer to ∂L/∂θ.
//!
//! Two homes for the same equations: on a GPU job whose decoder runs on that GPU the renders
//! never leave the device — L_vis is burn's graph ([`super::losses::visual_loss_tensor`]) and
//! one backward pass through L_wm and L_vis gives both routes' ∂L/∂image (each route's renders
//! are leaves of their own), copied into the rasterizer's backward on the device. Otherwise
//! L_vis and its gradient are the closed form ([`super::visual::visual_loss`]) on the host and
//! L_wm's ∂L/∂image is read back from burn.

use burn::tensor::{Device, Tensor};
use rayon::prelude::*;

use super::losses::{from_planar, visual_loss_tensor};
use super::optim::add_into;
use super::views::{Frame, Renderer};
use super::visual::visual_loss;
use super::{FinetuneError, LossWeights};
use crate::decoder::model::{FourierHost, HostFeatures};
use crate::render::RenderError;
use crate::render::gpu::GpuGrads;
use crate::scene::Gaussians;

/// L_vis of a step's views.
pub(super) enum Visual {
    /// On the device: the renders as leaves of their own (apart from the decoder's inputs)
    /// and the loss, averaged over the views.
    Device {
        xs: Vec<Tensor<4>>,
        loss: Box<Tensor<1>>,
    },
    /// On the host, per view: the loss and ∂L_vis/∂image (closed form).
    Host(Vec<(f64, Vec<[f32; 3]>)>),
}

/// ∂L/∂image of each of a step's views, `[watermark route, visual route]`, weighted as the
/// routes step.
pub(super) enum ImageGrads {
    Device(Vec<[Tensor<4>; 2]>),
    Host(Vec<[Vec<[f32; 3]>; 2]>),
}

/// L_vis of `renders` (on the device, `device` the GPU's burn device) against `targets`
/// (`[1, 3, H, W]` on the decoder's autodiff device), and their squared error (clamped
/// renders) summed, with the count of values — read back as two scalars. Without `with_loss`
/// (a coupled step that weighs L_vis 0) L_vis is 0 and not computed; the squared error is.
pub(super) fn visual_on_device(
    renderer: &Renderer,
    device: &Device,
    renders: &[Frame],
    targets: &[Tensor<4>],
    w: &LossWeights,
    levels: usize,
    with_loss: bool,
) -> Result<(Visual, f64, usize), FinetuneError> {
    let mut n_px = 0usize;
    let mut xs = Vec::with_capacity(renders.len());
    let (mut l_vis, mut sq): (Option<Tensor<1>>, Option<Tensor<1>>) = (None, None);
    for (r, t) in renders.iter().zip(targets) {
        let x = renderer
            .image_tensor(r, device)?
            .ok_or_else(|| {
                RenderError::Device("a render that should be on the device is not".into())
            })?
            .autodiff()
            .require_grad();
        let l = if with_loss {
            visual_loss_tensor(x.clone(), t.clone(), w, levels)
        } else {
            Tensor::zeros([1], &t.device())
        };
        let e = x
            .clone()
            .detach()
            .clamp(0.0, 1.0)
            .sub(t.clone())
            .square()
            .sum();
        n_px += x.dims().iter().product::<usize>();
        l_vis = Some(l_vis.map_or(l.clone(), |a| a.add(l)));
        sq = Some(sq.map_or(e.clone(), |a| a.add(e)));
        xs.push(x);
    }
    let loss = l_vis
        .expect("a step has views")
        .div_scalar(renders.len() as f64);
    let sq = f64::from(sq.expect("a step has views").into_scalar::<f32>());
    Ok((
        Visual::Device {
            xs,
            loss: Box::new(loss),
        },
        sq,
        n_px,
    ))
}

/// L_vis of `renders` against `targets` (row-major RGB) in closed form on the host, view by
/// view, and their squared error (clamped renders) summed, with the count of values. Without
/// `with_loss` (a coupled step that weighs L_vis 0) L_vis and its gradient are 0 and not
/// computed; the squared error is.
pub(super) fn visual_on_host(
    renders: &[Frame],
    targets: &[&[[f32; 3]]],
    dims: &[(usize, usize)],
    w: &LossWeights,
    levels: usize,
    with_loss: bool,
) -> (Visual, f64, usize) {
    let per_view: Vec<(f64, Vec<[f32; 3]>)> = if with_loss {
        renders
            .par_iter()
            .zip(targets)
            .zip(dims)
            .map(|((r, t), &(wd, ht))| visual_loss(r.image(), t, wd, ht, w, levels))
            .collect()
    } else {
        renders
            .iter()
            .map(|r| (0.0, vec![[0.0; 3]; r.image().len()]))
            .collect()
    };
    let mut sq_err = 0.0f64;
    let mut n_px = 0usize;
    for (r, t) in renders.iter().zip(targets) {
        for (p, q) in r.image().iter().zip(t.iter()) {
            for c in 0..3 {
                let d = f64::from(p[c].clamp(0.0, 1.0) - q[c]);
                sq_err += d * d;
            }
        }
        n_px += r.image().len() * 3;
    }
    (Visual::Host(per_view), sq_err, n_px)
}

impl Visual {
    /// L_vis averaged over the step's views.
    pub(super) fn value(&self) -> f32 {
        match self {
            Visual::Device { loss, .. } => loss.as_ref().clone().detach().into_scalar::<f32>(),
            Visual::Host(per_view) => {
                (per_view.iter().map(|(v, _)| v).sum::<f64>() / per_view.len() as f64) as f32
            }
        }
    }

    /// ∂L/∂image of each view for both routes: `l_wm` (on the decoder's inputs `xs`, the
    /// renders the watermark route reads) weighted by `wm_scale`, L_vis by `vis_scale`
    /// (averaged over the views). On the device one backward pass gives both; on the host
    /// L_wm's is read back from burn (`device`: where a missing gradient's zeros go).
    pub(super) fn image_grads(
        self,
        l_wm: Tensor<1>,
        xs: &[Tensor<4>],
        host: Option<(&FourierHost, Vec<HostFeatures>)>,
        wm_scale: f32,
        vis_scale: f32,
        device: &Device,
    ) -> ImageGrads {
        match self {
            Visual::Device { xs: xv, loss } => {
                let grads = l_wm
                    .mul_scalar(wm_scale)
                    .add(loss.mul_scalar(vis_scale))
                    .backward();
                let grad = |x: &Tensor<4>| {
                    x.grad(&grads)
                        .unwrap_or_else(|| Tensor::zeros(x.dims(), device))
                };
                ImageGrads::Device(
                    xs.iter()
                        .zip(&xv)
                        .map(|(x_wm, x_vis)| [grad(x_wm), grad(x_vis)])
                        .collect(),
                )
            }
            Visual::Host(per_view) => {
                let gw = l_wm.mul_scalar(wm_scale).backward();
                // Features the host computed: their gradient on into the bands' graphs.
                let gs = host
                    .and_then(|(h, features)| {
                        features
                            .iter()
                            .filter_map(|f| f.surrogate(h, &gw))
                            .reduce(|a, b| a.add(b))
                    })
                    .map(|s| s.backward());
                let read = |x: &Tensor<4>| {
                    let mut d: Vec<f32> = x
                        .grad(&gw)
                        .map(|t| t.try_into_vec_as::<f32>().unwrap_or_default())
                        .unwrap_or_default();
                    let e: Vec<f32> = gs
                        .as_ref()
                        .and_then(|gs| x.grad(gs))
                        .map(|t| t.try_into_vec_as::<f32>().unwrap_or_default())
                        .unwrap_or_default();
                    if d.len() == e.len() {
                        d.iter_mut().zip(&e).for_each(|(a, b)| *a += b);
                    } else if d.is_empty() {
                        d = e;
                    }
                    d
                };
                let f = (f64::from(vis_scale) / per_view.len() as f64) as f32;
                ImageGrads::Host(
                    xs.iter()
                        .zip(per_view)
                        .map(|(x, (_, d_vis))| {
                            let n = d_vis.len();
                            let d = read(x);
                            let d_wm = if d.len() == 3 * n {
                                from_planar(&d, n)
                            } else {
                                vec![[0.0; 3]; n]
                            };
                            [d_wm, d_vis.iter().map(|d| d.map(|v| v * f)).collect()]
                        })
                        .collect(),
                )
            }
        }
    }
}

/// [`backward`] for device-side gradients, left on the device: (∂L_wm/∂θ, ∂L_vis/∂θ), each
/// summed over the step's views there.
pub(super) fn backward_on_device(
    renderer: &Renderer,
    g: &Gaussians,
    renders: &[Frame],
    wm_renders: Option<&[Frame]>,
    d_images: &ImageGrads,
) -> Result<(GpuGrads, GpuGrads), FinetuneError> {
    let ImageGrads::Device(d) = d_images else {
        return Err(RenderError::Device("host gradients for the device's optimiser".into()).into());
    };
    let (wm, vis) = route_passes(renders, wm_renders, d);
    Ok((
        renderer.backward_summed_on_device(g, &wm)?,
        renderer.backward_summed_on_device(g, &vis)?,
    ))
}

/// Each route's (frame, ∂L/∂image) over the step's views.
#[allow(clippy::type_complexity)]
fn route_passes<'a>(
    renders: &'a [Frame],
    wm_renders: Option<&'a [Frame]>,
    d: &[[Tensor<4>; 2]],
) -> (Vec<(&'a Frame, Tensor<4>)>, Vec<(&'a Frame, Tensor<4>)>) {
    let wm = d
        .iter()
        .enumerate()
        .map(|(k, [d_wm, _])| (wm_renders.map_or(&renders[k], |wm| &wm[k]), d_wm.clone()))
        .collect();
    let vis = renders
        .iter()
        .zip(d)
        .map(|(r, [_, d_vis])| (r, d_vis.clone()))
        .collect();
    (wm, vis)
}

/// Both routes' ∂L/∂image back through each render — the watermark route's through
/// `wm_renders` where the EOT term read other renders of the step's views — summed over the
/// step's views: (∂L_wm/∂θ, ∂L_vis/∂θ). On the device each route's views are summed there and
/// read back once.
pub(super) fn backward(
    renderer: &Renderer,
    g: &Gaussians,
    renders: &[Frame],
    wm_renders: Option<&[Frame]>,
    d_images: &ImageGrads,
) -> Result<(Gaussians, Gaussians), FinetuneError> {
    let wm_frame = |k: usize| wm_renders.map_or(&renders[k], |wm| &wm[k]);
    match d_images {
        ImageGrads::Device(d) => {
            let (wm, vis) = route_passes(renders, wm_renders, d);
            Ok((
                renderer.backward_summed(g, &wm)?,
                renderer.backward_summed(g, &vis)?,
            ))
        }
        ImageGrads::Host(d) => {
            let mut grad_wm = g.cast(|_| 0.0f32);
            let mut grad_vis = grad_wm.clone();
            for (k, (r, [d_wm, d_vis])) in renders.iter().zip(d).enumerate() {
                let [by_wm, by_vis]: [Gaussians; 2] = if wm_renders.is_none() {
                    renderer.backward_each(g, r, &[d_wm, d_vis])?
                } else {
                    let mut by_wm = renderer.backward_each(g, wm_frame(k), &[d_wm])?;
                    by_wm.extend(renderer.backward_each(g, r, &[d_vis])?);
                    by_wm
                }
                .try_into()
                .expect("two gradients");
                add_into(&mut grad_wm, &by_wm);
                add_into(&mut grad_vis, &by_vis);
            }
            Ok((grad_wm, grad_vis))
        }
    }
}
