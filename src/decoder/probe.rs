//! The decoder-agnostic probe: what an optimiser can make a frozen decoder read with small
//! changes, without the cost of a 3D finetuning (issue 12, deliverable 2).
//!
//! The 3D finetuning does not use the decoder's training encoder: it moves the Gaussians so
//! that renders decode to the message, i.e. it *optimises* the image under the frozen decoder,
//! under the EOT attacks, at a fidelity bound. [`optimise_marks`] does the same on 2D images:
//!
//! 1. δ lives at 1/2^`levels` of the image resolution and is upsampled bilinearly (a smooth
//!    change, as Gaussians make; `levels` = 2 is the decoder's LL band).
//! 2. `iterations` steps of L2 projected gradient descent on BCE(D(t(clamp(x + up(δ)))), m),
//!    each with its own attack t drawn from `eot` (probability `attack_prob`): per image
//!    δ ← δ − η_i · r · g / rms(g), η_i = 1 → 0.1 (cosine), then δ is scaled back onto the ball
//!    rms(up(δ)) ≤ r with r = 10^(−PSNR/20) (images in [0, 1]: PSNR ≥ the target).
//!
//! [`probe`] embeds random messages into images that way at each PSNR, quantises them to
//! 8 bits, and decodes them clean, under the real attacks of the evaluation protocol
//! ([`super::eval::eval_attacks`]), under perspective tilts (a flat picture seen ±15° / ±30° off
//! axis: what moving the camera does to a surface) and downscales (real 8-bit images each
//! time: the warped image is rounded to 8 bits again). It also reports the unmarked bit bias of
//! the covers. `splatmark decoder probe` prints its JSON; docs/DECODER.md records the runs.

use std::collections::BTreeMap;

use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor, TensorData};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use super::artifact::{WatermarkModel, WeightsError, rgb8_batch, tensor_to_rgb8};
use super::eval::{Stats, attack_err, bit_accuracy, bit_bias, eval_attacks, psnr_u8};
use super::train::bce_with_logits;
use crate::attack::diff::{AttackFamily, DiffAttack, EotConfig, EotRng, random_composition};

/// How [`optimise_marks`] writes a message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OptEmbedOptions {
    /// Fidelity bound: rms(change) ≤ 10^(−PSNR/20) (images in [0, 1]).
    pub psnr_db: f64,
    /// Gradient steps.
    pub iterations: usize,
    /// δ is optimised at 1/2^levels resolution and upsampled bilinearly.
    pub levels: usize,
    /// Attacks drawn per step.
    pub eot: EotConfig,
    /// Probability that a step is attacked.
    pub attack_prob: f64,
}

impl Default for OptEmbedOptions {
    fn default() -> Self {
        Self {
            psnr_db: 38.0,
            iterations: 60,
            levels: 2,
            eot: view_eot(),
            attack_prob: 0.8,
        }
    }
}

/// The EOT family for 3D-consistent marks: the paper's attacks ([`EotConfig::default`]) plus
/// perspective tilts of ±30° (the foreshortening a surface shows from other views).
pub fn view_eot() -> EotConfig {
    let mut eot = EotConfig::default();
    eot.families
        .push((AttackFamily::Perspective { max_degrees: 30.0 }, 1.5));
    eot
}

/// The largest rms of a change at `psnr_db` for images in [0, 1].
pub fn rms_for_psnr(psnr_db: f64) -> f64 {
    10f64.powf(-psnr_db / 20.0)
}

/// Per-image root mean square `[B, 1, 1, 1]` of `x` `[B, C, H, W]`.
fn rms_per_image(x: Tensor<4>) -> Tensor<4> {
    x.square()
        .mean_dim(1)
        .mean_dim(2)
        .mean_dim(3)
        .add_scalar(1e-20)
        .sqrt()
}

/// `δ` `[B, 3, h, w]` upsampled to `[B, 3, H, W]` (bilinear; the identity at the same size).
pub fn upsample(delta: Tensor<4>, size: [usize; 2]) -> Tensor<4> {
    let [_, _, h, w] = delta.dims();
    if [h, w] == size {
        return delta;
    }
    interpolate(
        delta,
        InterpolateOptions::new(InterpolateMode::Bilinear)
            .with_align_corners(false)
            .with_output_size(size),
    )
}

/// Scales each image's `delta` down so that rms(up(δ)) ≤ `r`; returns the scaled δ.
fn project(delta: Tensor<4>, size: [usize; 2], r: f64) -> Tensor<4> {
    let rms = rms_per_image(upsample(delta.clone(), size));
    // factor = min(1, r / rms)
    let factor = rms.recip().mul_scalar(r).clamp_max(1.0);
    delta.mul(factor)
}

/// Optimises a change for `cover` `[B, 3, H, W]` (in [0, 1], on an autodiff device) so that
/// `logits(t(cover + change))` decodes `messages` `[B, L]` (bits in {0, 1}) under attacks t, at
/// rms(change) ≤ 10^(−PSNR/20) (module docs). Returns the change `[B, 3, H, W]` (no gradient).
/// `logits` is the frozen decoder (gradients must flow to its input).
///
/// # Errors
/// If an attack cannot be applied to the images.
pub fn optimise_marks(
    logits: &dyn Fn(Tensor<4>) -> Tensor<2>,
    cover: Tensor<4>,
    messages: Tensor<2>,
    opts: &OptEmbedOptions,
    rng: &mut EotRng,
) -> Result<Tensor<4>, crate::attack::diff::DiffAttackError> {
    let [b, c, h, w] = cover.dims();
    let f = 1usize << opts.levels;
    let (hl, wl) = (h.div_ceil(f).max(1), w.div_ceil(f).max(1));
    let r = rms_for_psnr(opts.psnr_db);
    let cover = cover.detach();
    let device = cover.device();
    let mut delta = Tensor::<4>::zeros([b, c, hl, wl], &device);
    let n = opts.iterations.max(1);
    for i in 0..n {
        let eta = 0.1 + 0.9 * 0.5 * (1.0 + (std::f64::consts::PI * i as f64 / n as f64).cos());
        let d = delta.clone().detach().require_grad();
        let x = cover
            .clone()
            .add(upsample(d.clone(), [h, w]))
            .clamp(0.0, 1.0);
        let attack = if rng.uniform() < opts.attack_prob {
            random_composition(&opts.eot, rng)
        } else {
            DiffAttack::Chain(Vec::new())
        };
        let z = logits(attack.apply(x)?);
        let loss = bce_with_logits(z, messages.clone());
        let grads = loss.backward();
        let Some(g) = d.grad(&grads) else {
            break;
        };
        let g = Tensor::<4>::from_data(g.into_data(), &device);
        let step = g.clone().div(rms_per_image(g)).mul_scalar(eta * r);
        delta = project(delta.sub(step), [h, w], r);
    }
    Ok(upsample(delta, [h, w]).detach())
}

/// Options of [`probe`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProbeOptions {
    /// Fidelity bounds to probe.
    pub psnrs: Vec<f64>,
    /// Random messages per image.
    pub repeats: usize,
    /// Images optimised together.
    pub batch: usize,
    /// Seed of messages and attack draws.
    pub seed: u64,
    /// How the messages are written (its `psnr_db` is replaced by each of `psnrs`).
    pub embed: OptEmbedOptions,
}

impl Default for ProbeOptions {
    fn default() -> Self {
        Self {
            psnrs: vec![36.0, 38.0, 40.0],
            repeats: 2,
            batch: 8,
            seed: 0,
            embed: OptEmbedOptions::default(),
        }
    }
}

/// Results at one PSNR bound.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProbeLevel {
    /// The bound.
    pub psnr_target_db: f64,
    /// PSNR of the 8-bit marked images against the 8-bit covers.
    pub psnr_db: Stats,
    /// Bit accuracy per condition (clean, real attacks, perspective, scale).
    pub accuracy: BTreeMap<String, Stats>,
}

/// The probe's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProbeReport {
    pub bits: usize,
    pub images: usize,
    pub options: ProbeOptions,
    /// Unmarked covers: mean over bits of |2·P(bit = 1) − 1|.
    pub unmarked_bit_bias: f64,
    pub levels: Vec<ProbeLevel>,
    /// Wall time, seconds.
    pub wall_s: f64,
}

/// The geometric conditions of the probe beyond the evaluation's attacks: perspective tilts
/// and downscales, as differentiable attacks applied to the 8-bit image and rounded again.
pub fn view_conditions() -> Vec<(String, DiffAttack)> {
    let mut v = Vec::new();
    for deg in [15.0f32, 30.0] {
        v.push((
            format!("perspective_x_{deg}"),
            DiffAttack::Perspective {
                x_degrees: deg,
                y_degrees: 0.0,
            },
        ));
        v.push((
            format!("perspective_y_-{deg}"),
            DiffAttack::Perspective {
                x_degrees: 0.0,
                y_degrees: -deg,
            },
        ));
        v.push((
            format!("perspective_xy_{deg}"),
            DiffAttack::Perspective {
                x_degrees: deg * 0.7,
                y_degrees: deg * 0.7,
            },
        ));
    }
    for f in [0.5f32, 0.75] {
        v.push((format!("downscale_{f}"), DiffAttack::Scale { factor: f }));
    }
    v
}

/// Runs the probe (module docs) of `model` (loaded on the autodiff `device`) on same-size
/// `images`.
///
/// # Errors
/// Without images, with images of different sizes, or if an attack fails.
pub fn probe(
    model: &WatermarkModel,
    images: &[RgbImage],
    opts: &ProbeOptions,
    device: &Device,
) -> Result<ProbeReport, WeightsError> {
    let start = std::time::Instant::now();
    let first = images
        .first()
        .ok_or_else(|| WeightsError::Mismatch("the probe needs at least one image".into()))?;
    if images.iter().any(|i| i.dimensions() != first.dimensions()) {
        return Err(WeightsError::Mismatch(
            "the probe's images must all have one size".into(),
        ));
    }
    let l = model.bits();
    let unmarked: Vec<Vec<f32>> = images
        .chunks(opts.batch.max(1))
        .flat_map(|c| model.logits(rgb8_batch(c, device)))
        .collect();
    let unmarked_bit_bias = bit_bias(&unmarked);
    let forward = |x: Tensor<4>| model.forward(x);
    let real = eval_attacks(opts.seed);
    let views = view_conditions();
    let mut levels = Vec::new();
    for &psnr in &opts.psnrs {
        let embed = OptEmbedOptions {
            psnr_db: psnr,
            ..opts.embed.clone()
        };
        let mut rng = EotRng::new(opts.seed ^ psnr.to_bits());
        let mut acc: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        let mut psnrs = Vec::new();
        for _ in 0..opts.repeats.max(1) {
            for chunk in images.chunks(opts.batch.max(1)) {
                let messages: Vec<Vec<bool>> = chunk
                    .iter()
                    .map(|_| (0..l).map(|_| rng.next_u64() >> 63 == 1).collect())
                    .collect();
                let flat: Vec<f32> = messages
                    .iter()
                    .flatten()
                    .map(|&b| f32::from(u8::from(b)))
                    .collect();
                let m = Tensor::<2>::from_data(TensorData::new(flat, [chunk.len(), l]), device);
                let cover = rgb8_batch(chunk, device);
                let change = optimise_marks(&forward, cover.clone(), m, &embed, &mut rng)
                    .map_err(|e| attack_err("eot", e))?;
                let marked = tensor_to_rgb8(cover.add(change).clamp(0.0, 1.0));
                for (c, w) in chunk.iter().zip(&marked) {
                    psnrs.push(psnr_u8(w, c));
                }
                let mut score = |name: &str, imgs: &[RgbImage]| {
                    let z = model.logits(rgb8_batch(imgs, device));
                    let e = acc.entry(name.to_string()).or_default();
                    for (zi, mi) in z.iter().zip(&messages) {
                        e.push(bit_accuracy(zi, mi));
                    }
                };
                for (name, attack) in &real {
                    let attacked: Vec<RgbImage> = match attack {
                        None => marked.clone(),
                        Some(a) => marked
                            .iter()
                            .map(|img| a.apply(img).map_err(|e| attack_err(name, e)))
                            .collect::<Result<_, _>>()?,
                    };
                    // The real crop/scale change sizes per image identically, so one batch.
                    score(name, &attacked);
                }
                for (name, attack) in &views {
                    let x = attack
                        .apply(rgb8_batch(&marked, device))
                        .map_err(|e| attack_err(name, e))?;
                    score(name, &tensor_to_rgb8(x.clamp(0.0, 1.0)));
                }
            }
        }
        levels.push(ProbeLevel {
            psnr_target_db: psnr,
            psnr_db: Stats::of(&psnrs),
            accuracy: acc.into_iter().map(|(k, v)| (k, Stats::of(&v))).collect(),
        });
    }
    Ok(ProbeReport {
        bits: l,
        images: images.len(),
        options: opts.clone(),
        unmarked_bit_bias,
        levels,
        wall_s: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::{HiddenDecoderConfig, Norm};

    #[test]
    fn optimised_marks_respect_the_bound_and_move_the_bits() {
        let device = Device::flex().autodiff();
        device.seed(3);
        let decoder = HiddenDecoderConfig::new(8)
            .with_channels(8)
            .with_depth(1)
            .with_norm(Norm::Group)
            .init(&device)
            .frozen();
        let forward = |x: Tensor<4>| decoder.forward(x);
        let cover = Tensor::<4>::full([2, 3, 32, 32], 0.5, &device)
            .add(Tensor::<4>::random(
                [2, 3, 32, 32],
                burn::tensor::Distribution::Uniform(-0.2, 0.2),
                &device,
            ))
            .detach();
        let m: Vec<f32> = (0..16).map(|i| f32::from(u8::from(i % 3 == 0))).collect();
        let m = Tensor::<2>::from_data(TensorData::new(m, [2, 8]), &device);
        let bce =
            |x: Tensor<4>| f64::from(bce_with_logits(forward(x), m.clone()).into_scalar::<f32>());
        let before = bce(cover.clone());
        let opts = OptEmbedOptions {
            psnr_db: 30.0,
            iterations: 20,
            attack_prob: 0.0,
            ..OptEmbedOptions::default()
        };
        let change = optimise_marks(
            &forward,
            cover.clone(),
            m.clone(),
            &opts,
            &mut EotRng::new(1),
        )
        .unwrap();
        let rms: Vec<f32> = rms_per_image(change.clone()).try_into_vec_as().unwrap();
        let r = rms_for_psnr(30.0) as f32;
        for v in rms {
            assert!(v <= r * 1.001 && v > 0.5 * r, "rms {v} vs bound {r}");
        }
        let after = bce(cover.add(change));
        assert!(after < before, "BCE {before} → {after}");
    }
}
