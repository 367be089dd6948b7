//! Decoupled watermark finetuning (§3.5, eqs. `Lvis`, `avglogits`, `Lwm-eot`, `Lwm`, `gate`).
//!
//! Every step renders a few training views of the split scene once (CPU rasterizer), hands the
//! images to burn for the two objectives, and back-propagates each objective's ∂L/∂image
//! through the same render ([`crate::render::backward`], "two backward passes through one
//! render"):
//!
//! - **L_wm** = λ_clean·BCE(z̄_cl, b) + λ_eot·BCE(z̄(t), b) + λ_low·L1(LL, LL★), where
//!   z̄ = (1/|V|)·Σ_v D(q(I_v)) averages the frozen decoder's logits over the step's views
//!   (eq. `avglogits`; with [`FinetuneConfig::per_view_loss`], the default, each BCE is instead
//!   (1/|V|)·Σ_v BCE(D(q(I_v)), b), so that every view decodes on its own), t ~ p(t) is one draw of the differentiable attack family
//!   ([`crate::attack::diff::random_composition`]) applied to every view of the step, q is the
//!   8-bit quantisation a saved render goes through (straight-through), and LL★ are the bands of
//!   the original scene's render (2-level Haar, [`crate::decoder::dwt`](mod@crate::decoder::dwt)).
//! - **L_vis** = λ_rec·L1 + λ_dssim·(1 − SSIM) + λ_high·Σ_levels L1(LH, HL, HH) against the
//!   original scene's renders. LPIPS needs pretrained network weights that do not ship with the
//!   project; the D-SSIM term takes its place (the `Lvis` weights are a config, so a perceptual
//!   term can be added beside it).
//! - **Gate** (eq. `gate`): carriers (WM★) take ∂L_wm only, every other Gaussian (VIS) ∂L_vis
//!   only, with INRIA's per-channel learning rates. Each route steps by
//!   [`StepRule::RouteNormalized`] (default: momentum, one second moment per channel shared by
//!   the route, so a Gaussian moves in proportion to its gradient) or per-parameter Adam
//!   ([`StepRule::Adam`]). The channel mask m_g(i) scales the *step* of its channel (under Adam a
//!   constant mask on the gradient would cancel), which is what scaling the gradient does under
//!   the SGD update the paper writes. Carriers move colour only unless
//!   [`FinetuneConfig::wm_geometry`]; means move only by
//!   [`crate::embed::mask::MaskConfig::position`] (0 by default).
//! - **Fidelity bound** [`FinetuneConfig::target_psnr`]: when a step's renders fall below it,
//!   the carriers' offsets from the planned scene are scaled back (the 2D probe's projection,
//!   `decoder::probe`), and once more, exactly, on every training view at the end (coupled:
//!   every Gaussian's offset).
//! - `coupled` (the default recipe, and the paper's ablation "w/o decoupling"): one joint loss
//!   λ_vis·L_vis + λ_wm·L_wm, its gradient applied to every Gaussian without masks; by default
//!   on the base colours only ([`LearningRates::colour_only`]). The paper's decoupled recipe is
//!   [`FinetuneConfig::paper`]. Adam divides each colour's step by its gradient's running size,
//!   so λ_wm and λ_vis weigh little here (ten times λ_wm or λ_vis 0 move no figure on udon;
//!   λ_vis 0 costs plant 0.3 dB): the learning rate and the fidelity bound set how strong the
//!   writes are (docs/RESULTS.md, twenty-fifth session). Weighed 0, L_vis is not computed.
//!
//! Per Gaussian, the finetuning also accumulates the norm of its (ungated) ∂L_wm over all
//! steps — over the parameters that move: the SH coefficients when the geometry is fixed —;
//! normalised to sum 1 this is its share of the watermark gradient in the attribution
//! records — a direct check that the watermark loss "lives" on the carriers SBAG chose.
//!
//! When no step moves the geometry (colour-only learning rates, the default), each training
//! view is rendered and back-propagated through its [`crate::render::Replay`]: the same
//! images, bit for bit, without rasterising (docs/BENCHMARKS.md, "Embedding").

use std::ops::ControlFlow;
use std::time::Instant;

use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::mask::Masks;
use crate::attack::diff::{DiffAttack, DiffAttackError, EotRng, random_composition};
use crate::attack::model::ModelAttack;
use crate::decoder::WatermarkModel;
use crate::decoder::model::{FourierHost, HostFeatures, decoder_input};
use crate::render::RenderError;
use crate::render::gpu::Rasterizer;
use crate::scene::Gaussians;

mod config;
mod device;
mod losses;
mod optim;
mod routes;
#[cfg(test)]
mod tests;
mod views;
mod visual;

pub(crate) use visual::reconstruction_loss;

pub use config::{FinetuneConfig, LearningRates, LossWeights, StepRule};
pub use losses::ssim;
use losses::{Margin, as_saved, band_l1, to_tensor, views_bce};
pub use optim::ROUTE_CLIP;
use optim::{Adam, RouteMomentum, add_into, copy_one, grad_norms, shrink_offsets};
use views::{Renderer, views_psnr};
pub use views::{View, ViewsCheck, target_views};
pub(crate) use views::{cameras_logits, views_logits};

/// Why finetuning failed.
#[derive(Debug, thiserror::Error)]
pub enum FinetuneError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Attack(#[from] DiffAttackError),
    #[error("the message has {got} bits, the decoder reads {expected}")]
    MessageLength { got: usize, expected: usize },
    #[error("no training views")]
    NoViews,
    #[error("target {index} has {got} pixels, its camera {expected}")]
    TargetSize {
        index: usize,
        got: usize,
        expected: usize,
    },
    #[error("the masks are for {masks} Gaussians, the scene has {scene}")]
    MaskSize { masks: usize, scene: usize },
    #[error("the loss became {0} at step {1}")]
    Diverged(f32, usize),
    #[error("cancelled after step {step}")]
    Cancelled { step: usize },
    #[error("invalid finetuning options: {0}")]
    Invalid(String),
}

/// Numbers of one step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepLog {
    /// 1-based.
    pub step: usize,
    pub l_wm: f32,
    pub l_vis: f32,
    pub bce_clean: f32,
    pub bce_eot: f32,
    /// Bit accuracy of the step's averaged clean logits.
    pub bit_acc_clean: f32,
    /// Bit accuracy of the step's averaged logits under its EOT draw.
    pub bit_acc_eot: f32,
    /// PSNR of the step's renders against their targets (dB, clamped to [0, 1]).
    pub psnr: f32,
    /// Factor the carriers' offsets were scaled by after this step to hold `target_psnr`
    /// (1 = within the bound).
    #[serde(default = "one")]
    pub wm_projection: f32,
    /// The most steps the finetuning may take as planned at this step: `steps` (twice that
    /// once the schedule stretched, `stretch_bce`) plus `extra_steps`.
    #[serde(default)]
    pub planned: usize,
    pub seconds: f32,
}

fn one() -> f32 {
    1.0
}

/// Seconds a finetuning's steps spent in each of their parts, summed over the steps: where a
/// step's time goes on the rasterizer that ran it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepPhases {
    /// Whether the steps' images stayed on the device: a GPU job whose decoder runs on that
    /// GPU renders, computes L_vis, L_wm and both ∂L/∂image, and back-propagates them there
    /// (only the parameters' gradients and a few scalars are read back). Otherwise images
    /// and ∂L/∂image cross the host between the parts.
    #[serde(default)]
    pub images_on_device: bool,
    /// Whether the Gaussians and their Adam state stayed there too (a GPU job whose Gaussians
    /// step by Adam): a step then reads back only the scalars it logs.
    #[serde(default)]
    pub params_on_device: bool,
    /// The step's views rendered (or replayed), and the EOT copy's.
    pub render: f64,
    /// The decoder on the views (clean and attacked), L_wm and its ∂L/∂image, on burn.
    pub watermark: f64,
    /// L_vis and the step's PSNR (with its ∂L/∂image, in closed form, on the host; on the
    /// device, its gradient comes from the watermark's backward pass, timed there).
    pub visual: f64,
    /// Both routes' ∂L/∂image back through the rasterizer to ∂L/∂θ.
    pub backward: f64,
    /// Gating, the optimiser step, the fidelity bound and the `extra_steps` checks.
    pub update: f64,
}

impl StepPhases {
    /// Adds the time since `*mark` to `field` and moves the mark to now.
    fn lap(field: &mut f64, mark: &mut Instant) {
        let now = Instant::now();
        *field += now.duration_since(*mark).as_secs_f64();
        *mark = now;
    }
}

/// What finetuning produced.
#[derive(Clone, Debug)]
pub struct Finetuned {
    pub gaussians: Gaussians,
    /// Per Gaussian, its share of Σ_steps ‖∂L_wm/∂θ_i‖ (sums to 1 unless the gradient was 0).
    pub wm_grad_share: Vec<f32>,
    pub log: Vec<StepLog>,
    /// The last check of the training views (`extra_steps` > 0 only).
    pub check: Option<ViewsCheck>,
    /// What `stretch_bce` measured and decided (when it is on).
    pub stretch: Option<StretchCheck>,
    /// Where the steps' time went.
    pub phases: StepPhases,
    pub seconds: f64,
}

/// The `stretch_bce` decision: the training views' clean watermark loss over the last tenth of
/// `steps` up to and including `step`, and whether the schedule stretched to `2 · steps`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StretchCheck {
    pub step: usize,
    pub bce_clean: f32,
    pub threshold: f32,
    pub stretched: bool,
}

/// Finetunes `scene` (the split scene of the plan) so that its renders decode to `message`
/// under `model`'s frozen decoder, routing the two objectives by `masks`. `model` must live on
/// an autodiff device. `progress` sees every step.
pub fn finetune(
    scene: &Gaussians,
    masks: &Masks,
    views: &[View],
    model: &WatermarkModel,
    message: &[bool],
    cfg: &FinetuneConfig,
    mut progress: impl FnMut(&StepLog) -> ControlFlow<()>,
) -> Result<Finetuned, FinetuneError> {
    let start = Instant::now();
    if message.len() != model.bits() {
        return Err(FinetuneError::MessageLength {
            got: message.len(),
            expected: model.bits(),
        });
    }
    if views.is_empty() {
        return Err(FinetuneError::NoViews);
    }
    cfg.validate().map_err(FinetuneError::Invalid)?;
    if cfg.eot_clone_probability > 0.0 && matches!(cfg.rasterizer, Rasterizer::Gpu(_)) {
        return Err(FinetuneError::Invalid(
            "eot_clone_probability runs on the CPU rasterizer (its backward folds each clone's \
             gradient into its original); the GPU's stays scene-shaped"
                .into(),
        ));
    }
    for (index, v) in views.iter().enumerate() {
        let expected = (v.camera.width * v.camera.height) as usize;
        if v.target.len() != expected {
            return Err(FinetuneError::TargetSize {
                index,
                got: v.target.len(),
                expected,
            });
        }
    }
    if masks.mask.len() != scene.len() {
        return Err(FinetuneError::MaskSize {
            masks: masks.mask.len(),
            scene: scene.len(),
        });
    }
    let render_opts = &cfg.render_options();
    // The decoder's device (burn's CPU backend, or the GPU the views are rendered on).
    let device = model.device().autodiff();
    let l = message.len();
    let bits = Tensor::<2>::from_data(
        TensorData::new(
            message.iter().map(|&b| f32::from(u8::from(b))).collect(),
            [1, l],
        ),
        &device,
    );
    let w = &cfg.weights;
    let mut g = scene.clone();
    let mut adam = Adam::new(&g);
    let mut route = RouteMomentum::new(&g);
    let mut vis_route = RouteMomentum::new(&g);
    let is_compensator: Vec<bool> = masks.is_carrier.iter().map(|&c| !c).collect();
    // The Gaussians the fidelity bound scales back: those on the watermark route.
    let everyone = vec![true; masks.is_carrier.len()];
    let bounded: &[bool] = if cfg.coupled {
        &everyone
    } else {
        &masks.is_carrier
    };
    let mut rng = EotRng::new(cfg.seed);
    let mut order: Vec<usize> = Vec::new();
    let mut wm_norm_sum = vec![0.0f64; g.len()];
    let mut log = Vec::with_capacity(cfg.steps);
    let per_step = cfg.views_per_step.clamp(1, views.len());
    let mut check = None;
    // Colour-only finetuning never moves the geometry: each view is then replayed from its
    // recorded compositing weights (bit-identical images, no rasterisation).
    let lr = &cfg.lr;
    let geometry_fixed = [lr.means, lr.opacity, lr.rotation, lr.scale]
        .iter()
        .all(|&r| r == 0.0);
    let mut renderer = Renderer::new(views, render_opts, geometry_fixed, cfg.rasterizer.clone());
    // A GPU job whose decoder is on that GPU keeps the step's images there: renders, L_vis,
    // ∂L/∂image (`Visual::Device`, `ImageGrads::Device`).
    let resident = renderer.keep_on_device(&model.device())?;
    // And the Gaussians with their Adam state too when they step by Adam: a step then reads
    // back only the scalars it logs (`device::Stepper`).
    let mut on_device = match &cfg.rasterizer {
        Rasterizer::Gpu(gpu) if resident && (cfg.coupled || cfg.step_rule == StepRule::Adam) => {
            Some(device::Stepper::new(
                gpu.clone(),
                &g,
                scene,
                cfg,
                masks,
                bounded,
            )?)
        }
        _ => None,
    };

    // On the CPU the colour-Fourier decoder's features and their gradient are computed on the
    // host in one fused pass (`FourierHost`: the same function, no F × pixels tensors).
    let host_features = (!resident && model.device().without_autodiff() == Device::flex())
        .then(|| model.decoder.fourier_host())
        .flatten();

    // Where the schedule ends: `steps`, or twice that once `stretch_bce` stretched it.
    let mut schedule_end = cfg.steps;
    let mut stretch = None;
    let mut step = 0;
    let mut phases = StepPhases {
        images_on_device: resident,
        params_on_device: on_device.is_some(),
        ..StepPhases::default()
    };
    while step < schedule_end + cfg.extra_steps {
        step += 1;
        let t0 = Instant::now();
        let mut mark = t0;
        // Views of this step: walk shuffled epochs.
        let mut picked = Vec::with_capacity(per_step);
        while picked.len() < per_step {
            if order.is_empty() {
                order = (0..views.len()).collect();
                for i in (1..order.len()).rev() {
                    let j = rng.range_int(0, i as u64) as usize;
                    order.swap(i, j);
                }
            }
            let v = order.pop().expect("refilled");
            if !picked.contains(&v) {
                picked.push(v);
            }
        }
        let renders = match &on_device {
            Some(d) => renderer.render_views_from(&g, d.scene(), &picked)?,
            None => renderer.render_views(&g, &picked)?,
        };
        let dims: Vec<(usize, usize)> = picked
            .iter()
            .map(|&v| {
                let c = &views[v].camera;
                (c.width as usize, c.height as usize)
            })
            .collect();
        let targets: Vec<Tensor<4>> = picked
            .iter()
            .zip(&dims)
            .map(|(&v, &(wd, ht))| to_tensor(&views[v].target, wd, ht, &device))
            .collect();
        let nv = per_step as f64;

        // L_wm. The attack is drawn every step (the random stream does not depend on the
        // ramp); before the ramp is complete it is applied with probability k / ramp.
        let attack = random_composition(&cfg.eot, &mut rng);
        let ramp = f64::from(cfg.eot_ramp) * cfg.steps as f64;
        let p_attack = if ramp >= 1.0 {
            (step as f64 / ramp).min(1.0)
        } else {
            1.0
        };
        let attack = if p_attack < 1.0 && rng.uniform() >= p_attack {
            DiffAttack::Chain(Vec::new())
        } else {
            attack
        };
        // The model attack "remove Gaussians" (drawn only when enabled, so that the random
        // stream of a finetuning without it is unchanged).
        let removed: Option<Vec<bool>> = (cfg.eot_remove_probability > 0.0
            && rng.uniform() < p_attack * f64::from(cfg.eot_remove_probability))
        .then(|| {
            let f = rng.uniform() * f64::from(cfg.eot_remove_max.clamp(0.0, 1.0));
            (0..g.len()).map(|_| rng.uniform() < f).collect()
        });
        // The model attack "parameter noise" (drawn only when enabled, likewise).
        let noised: Option<ModelAttack> = (cfg.eot_noise_probability > 0.0
            && rng.uniform() < p_attack * f64::from(cfg.eot_noise_probability))
        .then(|| ModelAttack::Noise {
            sigma: cfg.eot_noise_std.sqrt(),
            position_scale: 1.0,
            seed: rng.next_u64(),
        });
        // The model attack "clone Gaussians" (drawn only when enabled, likewise).
        let cloned: Option<Vec<bool>> = (cfg.eot_clone_probability > 0.0
            && rng.uniform() < p_attack * f64::from(cfg.eot_clone_probability))
        .then(|| {
            let f = rng.uniform() * f64::from(cfg.eot_clone_max.clamp(0.0, 1.0));
            (0..g.len()).map(|_| rng.uniform() < f).collect()
        });
        // Removal and cloning as copies of each Gaussian: 0 removed, 2 cloned, 1 as is.
        let copies: Option<Vec<u8>> = (removed.is_some() || cloned.is_some()).then(|| {
            (0..g.len())
                .map(|i| {
                    if removed.as_ref().is_some_and(|r| r[i]) {
                        0
                    } else if cloned.as_ref().is_some_and(|c| c[i]) {
                        2
                    } else {
                        1
                    }
                })
                .collect()
        });
        let noised = match noised {
            Some(attack) => {
                if let Some(d) = &on_device {
                    g = d.read()?; // the attack copies the current scene
                }
                Some(attack.apply(&g).expect("σ validated above"))
            }
            None => None,
        };
        let wm_renders = match (&noised, &copies, &on_device) {
            (Some(n), c, _) => Some(renderer.rasterise_views(n, &picked, c.as_deref())?),
            (None, Some(c), Some(d)) => {
                Some(renderer.render_views_from(&g, &d.edited(c)?, &picked)?)
            }
            (None, Some(c), None) => Some(renderer.render_views_edited(&g, &picked, c)?),
            (None, None, _) => None,
        };
        let wm_frames = wm_renders.as_ref().unwrap_or(&renders);
        StepPhases::lap(&mut phases.render, &mut mark);
        let attack = match attack {
            DiffAttack::Chain(c) if c.is_empty() => None,
            a => Some(a),
        };
        // The decoder's inputs: on the GPU's own burn device, copied there from the renders'
        // buffers; otherwise uploaded from the host.
        let xs = wm_frames
            .iter()
            .zip(&dims)
            .map(|(r, &(wd, ht))| {
                Ok(match renderer.image_tensor(r, &model.device())? {
                    Some(t) => t.autodiff(),
                    None => to_tensor(r.image(), wd, ht, &device),
                }
                .require_grad())
            })
            .collect::<Result<Vec<_>, FinetuneError>>()?;
        let (z_cl, z_t, low, on_host) = decode_views(
            model,
            &xs,
            &targets,
            attack.as_ref(),
            cfg.dwt_levels,
            host_features.as_ref(),
        )?;
        let margin = Margin {
            margin: cfg.wm_margin,
            sharpness: cfg.wm_sharpness,
        };
        let bce_cl = views_bce(&z_cl, &bits, cfg.per_view_loss, margin);
        let bce_t = views_bce(&z_t, &bits, cfg.per_view_loss, margin);
        let mean = |zs: Vec<Tensor<2>>| {
            zs.into_iter()
                .reduce(|a, b| a.add(b))
                .expect("views")
                .div_scalar(nv)
        };
        let (z_cl, z_t) = (mean(z_cl), mean(z_t));
        let l_wm = bce_cl
            .clone()
            .mul_scalar(w.wm_clean)
            .add(bce_t.clone().mul_scalar(w.wm_eot))
            .add(low.div_scalar(nv).mul_scalar(w.wav_low));
        StepPhases::lap(&mut phases.watermark, &mut mark);

        // L_vis and the step's squared error (the PSNR the fidelity bound reads); a coupled
        // step that weighs L_vis 0 skips computing it.
        let with_loss = !(cfg.coupled && w.vis == 0.0);
        let host_targets: Vec<&[[f32; 3]]> = picked.iter().map(|&v| &views[v].target[..]).collect();
        let (vis, sq_err, n_px) = if resident {
            routes::visual_on_device(
                &renderer,
                &model.device(),
                &renders,
                &targets,
                w,
                cfg.dwt_levels,
                with_loss,
            )?
        } else {
            routes::visual_on_host(&renders, &host_targets, &dims, w, cfg.dwt_levels, with_loss)
        };
        StepPhases::lap(&mut phases.visual, &mut mark);

        let scalar = |t: &Tensor<1>| t.clone().detach().into_scalar::<f32>();
        let (lw, lv) = (scalar(&l_wm), vis.value());
        if !lw.is_finite() || !lv.is_finite() {
            return Err(FinetuneError::Diverged(
                if lw.is_finite() { lv } else { lw },
                step,
            ));
        }
        let acc = |z: &Tensor<2>| {
            let z: Vec<f32> = z
                .clone()
                .detach()
                .try_into_vec_as::<f32>()
                .unwrap_or_default();
            z.iter()
                .zip(message)
                .filter(|&(&z, &m)| (z > 0.0) == m)
                .count() as f32
                / l as f32
        };
        let (acc_cl, acc_t) = (acc(&z_cl), acc(&z_t));
        let (b_cl, b_t) = (scalar(&bce_cl), scalar(&bce_t));

        let (wm_scale, vis_scale) = if cfg.coupled {
            (w.wm, w.vis)
        } else {
            (1.0, 1.0)
        };
        // ∂L/∂image of each view, one for each route.
        let host = host_features.as_ref().map(|h| (h, on_host));
        let d_images = vis.image_grads(l_wm, &xs, host, wm_scale, vis_scale, &model.device());
        // (burn runs lazily on a GPU: the decoder's time shows where its results are read.)
        StepPhases::lap(&mut phases.watermark, &mut mark);

        // Gate and step: the watermark route's schedule.
        let t = (step.min(schedule_end) as f32 / schedule_end.max(1) as f32).min(1.0);
        let decay = cfg.wm_lr_min_fraction
            + (1.0 - cfg.wm_lr_min_fraction) * 0.5 * (1.0 + (std::f32::consts::PI * t).cos());
        let wm_s = cfg.wm_lr_scale * decay;
        if let Some(d) = &mut on_device {
            // Both routes back through each render, summed over the step's views on the device;
            // Adam steps there.
            let (grad_wm, grad_vis) = routes::backward_on_device(
                &renderer,
                &g,
                &renders,
                wm_renders.as_deref(),
                &d_images,
            )?;
            StepPhases::lap(&mut phases.backward, &mut mark);
            d.step(&grad_wm, &grad_vis, geometry_fixed, wm_s)?;
        } else {
            // Both routes back through each render, summed over the step's views.
            let (mut grad_wm, grad_vis) =
                routes::backward(&renderer, &g, &renders, wm_renders.as_deref(), &d_images)?;
            StepPhases::lap(&mut phases.backward, &mut mark);
            for (s, n) in wm_norm_sum
                .iter_mut()
                .zip(grad_norms(&grad_wm, geometry_fixed))
            {
                *s += f64::from(n);
            }

            let lr = &cfg.lr;
            let base = [lr.means, lr.dc, lr.rest, lr.opacity, lr.rotation, lr.scale];
            if cfg.coupled {
                // Coupled: every Gaussian is on the watermark route, so every rate is scaled and
                // decays with the route's.
                add_into(&mut grad_wm, &grad_vis);
                let scaled = base.map(|b| b * wm_s);
                adam.step(&mut g, &grad_wm, |_| scaled);
            } else {
                let mut routed = grad_vis;
                for i in 0..g.len() {
                    if masks.is_carrier[i] {
                        copy_one(&mut routed, &grad_wm, i);
                    }
                }
                let rates = |i: usize, s: f32| {
                    let m = masks.mask[i];
                    [
                        base[0] * masks.position * s,
                        base[1] * m[0] * s,
                        base[2] * m[1] * s,
                        base[3] * m[2] * s,
                        base[4] * m[3] * s,
                        base[5] * m[4] * s,
                    ]
                };
                let wm_rates = |i: usize| {
                    let mut r = rates(i, wm_s);
                    if !cfg.wm_geometry {
                        r[0] = 0.0;
                        r[3] = 0.0;
                        r[4] = 0.0;
                        r[5] = 0.0;
                    }
                    r
                };
                match cfg.step_rule {
                    StepRule::Adam => adam.step(&mut g, &routed, |i| {
                        if masks.is_carrier[i] {
                            wm_rates(i)
                        } else {
                            rates(i, 1.0)
                        }
                    }),
                    StepRule::RouteNormalized => {
                        route.step(&mut g, &routed, &masks.is_carrier, wm_rates);
                        vis_route.step(&mut g, &routed, &is_compensator, |i| rates(i, 1.0));
                    }
                }
            }
        }

        let mse = sq_err / n_px.max(1) as f64;
        let psnr = if mse > 0.0 {
            (-10.0 * mse.log10()) as f32
        } else {
            f32::INFINITY
        };
        let projection = if cfg.target_psnr > 0.0 && psnr < cfg.target_psnr {
            let f = 10f32.powf((psnr - cfg.target_psnr) / 20.0);
            match &on_device {
                Some(d) => d.shrink(f)?,
                None => shrink_offsets(&mut g, scene, bounded, f),
            }
            f
        } else {
            1.0
        };
        let entry = StepLog {
            step,
            l_wm: lw,
            l_vis: lv,
            bce_clean: b_cl,
            bce_eot: b_t,
            bit_acc_clean: acc_cl,
            bit_acc_eot: acc_t,
            psnr,
            wm_projection: projection,
            planned: schedule_end + cfg.extra_steps,
            seconds: t0.elapsed().as_secs_f32(),
        };
        log.push(entry);
        if cfg.stretch_bce > 0.0 && step == stretch_step(cfg) {
            let c = stretch_check(cfg, &log);
            if c.stretched {
                schedule_end = 2 * cfg.steps;
                log.last_mut().expect("pushed").planned = schedule_end + cfg.extra_steps;
            }
            stretch = Some(c);
        }
        if progress(log.last().expect("pushed")).is_break() {
            return Err(FinetuneError::Cancelled { step });
        }
        if cfg.extra_steps > 0
            && step >= schedule_end
            && ((step - schedule_end).is_multiple_of(cfg.check_every.max(1))
                || step == schedule_end + cfg.extra_steps)
        {
            if let Some(d) = &on_device {
                g = d.read()?;
            }
            let c = ViewsCheck::new(
                step,
                &views_logits(&g, views, model, render_opts, &cfg.rasterizer)?,
                message,
            );
            check = Some(c);
            if c.matches == c.bits {
                StepPhases::lap(&mut phases.update, &mut mark);
                break;
            }
        }
        StepPhases::lap(&mut phases.update, &mut mark);
    }

    if let Some(d) = &on_device {
        g = d.read()?;
        for (s, n) in wm_norm_sum.iter_mut().zip(d.read_norms()?) {
            *s = f64::from(n);
        }
    }

    // The per-step bound acts on the renders before each update; hold it exactly at the end:
    // the mean PSNR of every training view, re-rendered, scaled back onto the bound.
    if cfg.target_psnr > 0.0 {
        for _ in 0..4 {
            let psnr = views_psnr(&mut renderer, &g)?;
            if psnr >= cfg.target_psnr {
                break;
            }
            let f = 10f32.powf((psnr - cfg.target_psnr) / 20.0);
            shrink_offsets(&mut g, scene, bounded, f);
        }
    }

    let total: f64 = wm_norm_sum.iter().sum();
    let wm_grad_share = wm_norm_sum
        .iter()
        .map(|&s| if total > 0.0 { (s / total) as f32 } else { 0.0 })
        .collect();
    Ok(Finetuned {
        gaussians: g,
        wm_grad_share,
        log,
        check,
        stretch,
        phases,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The decoder's logits (`[1, L]` each) of a step's views `xs`, clean and through `attack` (the
/// clean ones again when none is drawn: one decoder pass, the same gradient), and Σ over the
/// views of the LL band's L1 to their `targets`. Views of one size go through the decoder as one
/// batch — the decoder and its heads act on each image alone (GroupNorm, no BatchNorm), so the
/// logits are the per-view ones, for a fraction of the per-call cost; mixed sizes go one by one.
#[allow(clippy::type_complexity)]
fn decode_views(
    model: &WatermarkModel,
    xs: &[Tensor<4>],
    targets: &[Tensor<4>],
    attack: Option<&DiffAttack>,
    levels: usize,
    host: Option<&FourierHost>,
) -> Result<Decoded, FinetuneError> {
    let one_size = xs.windows(2).all(|p| p[0].dims() == p[1].dims());
    let groups: Vec<std::ops::Range<usize>> = if one_size {
        std::iter::once(0..xs.len()).collect()
    } else {
        (0..xs.len()).map(|k| k..k + 1).collect()
    };
    let stack = |ts: &[Tensor<4>]| match ts {
        [one] => one.clone(),
        many => Tensor::cat(many.to_vec(), 0),
    };
    let (mut z_cl, mut z_t) = (Vec::with_capacity(xs.len()), Vec::with_capacity(xs.len()));
    let mut low: Option<Tensor<1>> = None;
    let mut on_host = Vec::new();
    // The decoder's logits; its features computed on the host when `host` is given.
    let mut forward = |images: Tensor<4>| match host {
        Some(h) => {
            let f = h.features_of(decoder_input(images, model.decoder.dwt_levels()));
            let z = model.forward_pooled(f.leaf());
            on_host.push(f);
            z
        }
        None => model.forward(images),
    };
    for r in groups {
        let (x, t, n) = (stack(&xs[r.clone()]), stack(&targets[r.clone()]), r.len());
        // Host features take burn's backward in two passes (∂L/∂features first), so the
        // band L1 reads the views through a stack of its own, not shared with the decoder's.
        let x_low = match host {
            Some(_) => stack(&xs[r]),
            None => x.clone(),
        };
        let saved = as_saved(x);
        let clean = forward(saved.clone());
        let attacked = match attack {
            Some(a) => forward(a.apply(saved)?),
            None => clean.clone(),
        };
        for k in 0..n {
            z_cl.push(clean.clone().narrow(0, k, 1));
            z_t.push(attacked.clone().narrow(0, k, 1));
        }
        // The batch's mean over equal-sized views, times their count: the sum of their means.
        let b = band_l1(x_low, t, levels, true).mul_scalar(n as f64);
        low = Some(low.map_or(b.clone(), |a| a.add(b)));
    }
    Ok((z_cl, z_t, low.expect("a step has views"), on_host))
}

/// [`decode_views`]' logits of the clean and the attacked views, the LL band's L1, and the
/// features computed on the host (empty when burn computed them).
type Decoded = (Vec<Tensor<2>>, Vec<Tensor<2>>, Tensor<1>, Vec<HostFeatures>);

/// The step after which `stretch_bce` decides: three tenths of `steps` (where the EOT ramp
/// of the defaults completes).
pub(crate) fn stretch_step(cfg: &FinetuneConfig) -> usize {
    (cfg.steps * 3 / 10).max(1)
}

/// The step after which the pipeline chooses between its decoders
/// (`EmbedOptions::coarse_margin_db`): a fifth of `steps` (step 70 of the default 350). The
/// training views' PSNR over steps 36–70 separates the scenes as widely as over steps 71–105
/// and varies less between payloads (docs/RESULTS.md, "The decoder chosen at step 70"), and a
/// switch then discards 70 steps of the main decoder instead of 105.
pub(crate) fn choice_step(cfg: &FinetuneConfig) -> usize {
    (cfg.steps / 5).max(1)
}

/// How many steps up to [`stretch_step`] or [`choice_step`] the checks average: the last
/// tenth of `steps`.
pub(crate) fn check_window(cfg: &FinetuneConfig) -> usize {
    (cfg.steps / 10).max(1)
}

/// Whether the schedule stretches to twice `steps` (`stretch_bce`): the training views' clean
/// watermark loss, averaged over the last tenth of `steps` (`log` is not empty), is above the
/// threshold.
fn stretch_check(cfg: &FinetuneConfig, log: &[StepLog]) -> StretchCheck {
    let window = &log[log.len() - check_window(cfg).min(log.len())..];
    let mean = window.iter().map(|s| f64::from(s.bce_clean)).sum::<f64>() / window.len() as f64;
    StretchCheck {
        step: log.len(),
        bce_clean: mean as f32,
        threshold: cfg.stretch_bce,
        stretched: mean > f64::from(cfg.stretch_bce),
    }
}
