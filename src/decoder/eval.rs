//! Held-out evaluation of a trained encoder/decoder pair (`splatmark decoder eval`) and decoding
//! of images (`splatmark decode`).
//!
//! # Evaluation protocol
//!
//! On the held-out images of the split ([`super::data`](mod@super::data)), each resized so that
//! its short side is `size` (default 256, triangle filter) and centre-cropped to `size × size`:
//!
//! 1. **Marked**: `repeats` times per image, a uniformly random message is embedded with the
//!    trained encoder at the trained strength, the result is clamped and quantised to 8-bit RGB
//!    (PSNR against the quantised cover is reported), then every attack of
//!    [`paper_protocol`] — plus `clean` (no attack), `rotation_ccw_-30` (the other sign of the
//!    protocol's ±30°) and `blur_0.8` (a blur that acts on 8-bit images, unlike the protocol's
//!    σ = 0.1) — is applied with the real 8-bit attacks, and the decoded bits (logit > 0, after
//!    the whitening if the model has one) are compared with the message. Per attack: mean, std
//!    and min of the bit accuracy over the `images × repeats` samples.
//! 2. **Unmarked**: the clean (quantised) covers are decoded. `unmarked`: each image's bit
//!    accuracy against `unmarked_messages` (64) uniformly random messages, averaged per image;
//!    mean, std and max over images. Against uniformly random messages the expected accuracy is
//!    ½ *whatever the decoder does* (one message per image, as before, only added binomial noise:
//!    ± 2.8 points on the mean of 10 images at 32 bits), so this figure checks the protocol
//!    rather than the decoder. Two statistics that do depend on the decoder follow:
//!    `unmarked_fixed_messages` — for each of `unmarked_messages` random messages *shared by all
//!    images* (a registered owner's message), the mean accuracy of the unmarked images against
//!    it; stats over those messages, so `max` is the worst registered message (a biased decoder
//!    lets every unmarked image match some messages too often) — and `unmarked_bit_bias`, the
//!    mean over bits of |2·P(bit = 1) − 1| over the images.
//!
//! The targets at 32 bits are checked in `targets`.

use std::collections::BTreeMap;
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use super::artifact::{
    WatermarkModel, WeightsError, WhiteningReport, rgb8_batch, rgb8_tensor, tensor_to_rgb8,
};
use super::data::{Image, ImageSet, square_rgb8};
use super::model::Whitening;
use super::train::{TrainConfig, step_seed};
use crate::attack::diff::{EotRng, random_composition};
use crate::attack::{RealAttack, paper_protocol};

/// Options of [`evaluate`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EvalOptions {
    /// Short side (and square crop) of the evaluation images.
    pub size: u32,
    /// Random messages embedded per image.
    pub repeats: usize,
    /// Seed of the messages and of the noise attack.
    pub seed: u64,
    /// Images per decoder/encoder batch.
    pub batch: usize,
    /// Random messages each unmarked image is compared with (and fixed messages tried).
    pub unmarked_messages: usize,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            size: 256,
            repeats: 4,
            seed: 0,
            batch: 8,
            unmarked_messages: 64,
        }
    }
}

/// Mean, standard deviation (population), min and max of samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
    pub n: usize,
}

impl Stats {
    /// Statistics of `xs` (NaN for an empty slice).
    pub fn of(xs: &[f64]) -> Self {
        let n = xs.len();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        Self {
            mean,
            std: var.sqrt(),
            min: xs.iter().copied().fold(f64::INFINITY, f64::min),
            max: xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            n,
        }
    }
}

/// One target of the issue.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Target {
    pub value: f64,
    pub requirement: String,
    pub pass: bool,
}

/// What [`evaluate`] reports (`decoder eval` prints it as JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    pub bits: usize,
    /// Held-out images used.
    pub images: usize,
    pub image_names: Vec<String>,
    pub size: u32,
    pub repeats: usize,
    pub seed: u64,
    pub strength: f64,
    pub whitened: bool,
    /// PSNR (dB) of the quantised watermarked images against the quantised covers.
    pub psnr_db: Stats,
    /// Bit accuracy of watermarked images per attack.
    pub marked: BTreeMap<String, Stats>,
    /// Bit accuracy of unmarked images against random messages (averaged per image over
    /// `unmarked_messages` of them); stats over images.
    pub unmarked: Stats,
    /// For each of `unmarked_messages` fixed random messages, the mean bit accuracy of all
    /// unmarked images against it; stats over the messages (`max`: the worst message).
    #[serde(alias = "unmarked_fixed_message")]
    pub unmarked_fixed_messages: Stats,
    /// Messages per image / fixed messages behind the two figures above (1 in older records).
    #[serde(default = "one")]
    pub unmarked_messages: usize,
    /// Mean over bits of |2·P(bit = 1) − 1| on the unmarked images.
    pub unmarked_bit_bias: f64,
    /// The targets (stated for 32 bits; checked at any length).
    pub targets: BTreeMap<String, Target>,
}

fn one() -> usize {
    1
}

/// Bit accuracy of logits against a message.
pub fn bit_accuracy(logits: &[f32], message: &[bool]) -> f64 {
    crate::verify::stats::matches_from_logits(logits, message) as f64 / message.len() as f64
}

fn random_message(rng: &mut EotRng, bits: usize) -> Vec<bool> {
    (0..bits).map(|_| rng.next_u64() >> 63 == 1).collect()
}

/// Mean over bits of |2·P(bit = 1) − 1| over the rows of `logits`.
pub fn bit_bias(logits: &[Vec<f32>]) -> f64 {
    let Some(l) = logits.first().map(Vec::len) else {
        return f64::NAN;
    };
    let n = logits.len() as f64;
    (0..l)
        .map(|i| {
            let ones = logits.iter().filter(|z| z[i] > 0.0).count() as f64;
            (2.0 * ones / n - 1.0).abs()
        })
        .sum::<f64>()
        / l as f64
}

/// The attacks of the evaluation, in order: clean, the paper's protocol, and two extras.
pub fn eval_attacks(seed: u64) -> Vec<(String, Option<RealAttack>)> {
    let mut v: Vec<(String, Option<RealAttack>)> = vec![("clean".into(), None)];
    v.extend(
        paper_protocol(seed)
            .into_iter()
            .map(|(n, a)| (n.to_string(), Some(a))),
    );
    v.push((
        "rotation_ccw_-30".into(),
        Some(RealAttack::Rotate { degrees: -30.0 }),
    ));
    v.push((
        "blur_0.8".into(),
        Some(RealAttack::Blur {
            sigma: 0.8,
            kernel: 3,
        }),
    ));
    v
}

pub(crate) fn attack_err(name: &str, e: impl std::fmt::Display) -> WeightsError {
    WeightsError::Attack {
        name: name.to_string(),
        message: e.to_string(),
    }
}

/// Decodes same-size images in batches of `batch`.
fn decode_batches(
    model: &WatermarkModel,
    images: &[RgbImage],
    batch: usize,
    device: &Device,
) -> Vec<Vec<f32>> {
    images
        .chunks(batch.max(1))
        .flat_map(|chunk| model.logits(rgb8_batch(chunk, device)))
        .collect()
}

/// PSNR (dB) of two same-size 8-bit images (∞ when equal).
pub(crate) fn psnr_u8(a: &RgbImage, b: &RgbImage) -> f64 {
    let n = a.as_raw().len() as f64;
    let mse = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum::<f64>()
        / n;
    if mse > 0.0 {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    } else {
        f64::INFINITY
    }
}

/// Runs the evaluation protocol (module docs) of `model` on `images` (the held-out split).
///
/// # Errors
/// Without an encoder, without images, or if an attack fails.
pub fn evaluate(
    model: &WatermarkModel,
    images: &[Image],
    opts: &EvalOptions,
) -> Result<EvalReport, WeightsError> {
    let device = Device::flex();
    evaluate_on(model, images, opts, &device)
}

/// [`evaluate`] with the tensors on `device` (where the model lives).
pub fn evaluate_on(
    model: &WatermarkModel,
    images: &[Image],
    opts: &EvalOptions,
    device: &Device,
) -> Result<EvalReport, WeightsError> {
    if model.encoder.is_none() {
        return Err(WeightsError::NoEncoder("the model".into()));
    }
    if images.is_empty() {
        return Err(WeightsError::Mismatch(
            "no held-out images to evaluate on".into(),
        ));
    }
    let l = model.bits();
    let size = opts.size.max(8);
    let covers: Vec<RgbImage> = images
        .iter()
        .map(|i| square_rgb8(&i.to_rgb8(), size))
        .collect();
    let mut rng = EotRng::new(step_seed(opts.seed, 0xE7A1));
    let attacks = eval_attacks(opts.seed);
    let mut acc: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut psnr = Vec::new();
    for _ in 0..opts.repeats.max(1) {
        let messages: Vec<Vec<bool>> = covers.iter().map(|_| random_message(&mut rng, l)).collect();
        let mut marked = Vec::with_capacity(covers.len());
        for (chunk, msgs) in covers
            .chunks(opts.batch.max(1))
            .zip(messages.chunks(opts.batch.max(1)))
        {
            marked.extend(tensor_to_rgb8(model.embed(rgb8_batch(chunk, device), msgs)));
        }
        psnr.extend(marked.iter().zip(&covers).map(|(m, c)| psnr_u8(m, c)));
        for (name, attack) in &attacks {
            let attacked: Vec<RgbImage> = match attack {
                None => marked.clone(),
                Some(a) => marked
                    .iter()
                    .map(|m| a.apply(m).map_err(|e| attack_err(name, e)))
                    .collect::<Result<_, _>>()?,
            };
            let logits = decode_batches(model, &attacked, opts.batch, device);
            let entry = acc.entry(name.clone()).or_default();
            entry.extend(
                logits
                    .iter()
                    .zip(&messages)
                    .map(|(z, m)| bit_accuracy(z, m)),
            );
        }
    }
    let clean_logits = decode_batches(model, &covers, opts.batch, device);
    let k = opts.unmarked_messages.max(1);
    let unmarked: Vec<f64> = clean_logits
        .iter()
        .map(|z| {
            (0..k)
                .map(|_| bit_accuracy(z, &random_message(&mut rng, l)))
                .sum::<f64>()
                / k as f64
        })
        .collect();
    let unmarked_fixed: Vec<f64> = (0..k)
        .map(|_| {
            let fixed = random_message(&mut rng, l);
            clean_logits
                .iter()
                .map(|z| bit_accuracy(z, &fixed))
                .sum::<f64>()
                / clean_logits.len() as f64
        })
        .collect();
    let marked: BTreeMap<String, Stats> =
        acc.iter().map(|(k, v)| (k.clone(), Stats::of(v))).collect();
    let unmarked = Stats::of(&unmarked);
    let targets = targets(&marked, &unmarked);
    Ok(EvalReport {
        bits: l,
        images: images.len(),
        image_names: images.iter().map(|i| i.name.clone()).collect(),
        size,
        repeats: opts.repeats.max(1),
        seed: opts.seed,
        strength: model.sidecar.strength,
        whitened: model.sidecar.whitening.is_some(),
        psnr_db: Stats::of(&psnr),
        marked,
        unmarked,
        unmarked_fixed_messages: Stats::of(&unmarked_fixed),
        unmarked_messages: k,
        unmarked_bit_bias: bit_bias(&clean_logits),
        targets,
    })
}

fn targets(marked: &BTreeMap<String, Stats>, unmarked: &Stats) -> BTreeMap<String, Target> {
    let mut t = BTreeMap::new();
    let mut at_least = |key: &str, name: &str, min: f64| {
        if let Some(s) = marked.get(name) {
            t.insert(
                key.to_string(),
                Target {
                    value: s.mean,
                    requirement: format!("mean bit accuracy ≥ {min}"),
                    pass: s.mean >= min,
                },
            );
        }
    };
    at_least("clean", "clean", 0.99);
    at_least("jpeg_50", "jpeg", 0.95);
    at_least("crop_40", "crop", 0.95);
    at_least("rotation_+30", "rotation", 0.90);
    at_least("rotation_-30", "rotation_ccw_-30", 0.90);
    at_least("noise_0.01", "noise", 0.97);
    t.insert(
        "unmarked_mean".into(),
        Target {
            value: unmarked.mean,
            requirement: "in [0.48, 0.52]".into(),
            pass: (0.48..=0.52).contains(&unmarked.mean),
        },
    );
    t.insert(
        "unmarked_max".into(),
        Target {
            value: unmarked.max,
            requirement: "≤ 0.75".into(),
            pass: unmarked.max <= 0.75,
        },
    );
    t
}

/// The whitening check at the end of training (see
/// [`WhiteningChoice::Auto`](super::train::WhiteningChoice::Auto)): on held-out crops of the
/// training size, the bit bias of unmarked crops and the bit accuracy of watermarked crops (half
/// clean, half under random attacks of the training distribution), raw versus whitened.
pub fn whitening_check(
    model: &WatermarkModel,
    whitening: &Whitening,
    centering: Option<&Whitening>,
    held_out: &ImageSet,
    config: &TrainConfig,
    device: &Device,
) -> Result<WhiteningReport, WeightsError> {
    let (c, l) = (config.crop, config.bits);
    let mut rng = EotRng::new(step_seed(config.seed ^ 0xC0FF_EE00, 0));
    let batch = 16;
    let (mut unmarked, mut marked_raw, mut marked_white, mut messages) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let rounds = 16;
    for round in 0..rounds {
        let px = held_out.sample_batch(&mut rng, batch, c, config.min_scale, true);
        let x = Tensor::<4>::from_data(TensorData::new(px, [batch, 3, c, c]), device);
        unmarked.extend(model.raw_logits(x.clone()));
        if round % 2 == 0 {
            let msgs: Vec<Vec<bool>> = (0..batch).map(|_| random_message(&mut rng, l)).collect();
            let wm = tensor_to_rgb8(model.embed(x, &msgs));
            let wm = rgb8_batch(&wm, device);
            let attacked = if round % 4 == 0 {
                wm
            } else {
                random_composition(&config.eot, &mut rng)
                    .apply(wm)
                    .map_err(|e| attack_err("eot", e))?
                    .clamp(0.0, 1.0)
            };
            marked_raw.extend(model.raw_logits(attacked));
            messages.extend(msgs);
        }
    }
    for z in &marked_raw {
        marked_white.push(whitening.apply_row(z));
    }
    let acc = |zs: &[Vec<f32>]| {
        zs.iter()
            .zip(&messages)
            .map(|(z, m)| bit_accuracy(z, m))
            .sum::<f64>()
            / zs.len() as f64
    };
    let mapped = |w: &Whitening, zs: &[Vec<f32>]| -> Vec<Vec<f32>> {
        zs.iter().map(|z| w.apply_row(z)).collect()
    };
    Ok(WhiteningReport {
        applied: false,
        kind: None,
        unmarked_samples: unmarked.len(),
        bias_raw: bit_bias(&unmarked),
        bias_whitened: bit_bias(&mapped(whitening, &unmarked)),
        marked_samples: marked_raw.len(),
        marked_accuracy_raw: acc(&marked_raw),
        marked_accuracy_whitened: acc(&marked_white),
        bias_centered: centering.map(|c| bit_bias(&mapped(c, &unmarked))),
        marked_accuracy_centered: centering.map(|c| acc(&mapped(c, &marked_raw))),
    })
}

/// What `splatmark decode` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecodeReport {
    /// Decoded bits, `'0'`/`'1'`, bit i = logit i > 0.
    pub bits: String,
    /// Per-bit logits (whitened if the model has a whitening), averaged over the images.
    pub logits: Vec<f32>,
    /// Mean over bits of |2·σ(logit) − 1| ∈ [0, 1]: 0 when every logit is 0 (a coin toss per
    /// bit), → 1 when every bit is decided with certainty.
    pub confidence: f64,
    /// Number of images combined.
    pub images: usize,
    /// Bits decoded from each image alone, in the order given.
    pub per_image: Vec<String>,
    /// The decoder's pooled features averaged over the images (what an asset's matched head
    /// reads, [`crate::decoder::projection::ViewProjection::matched_logits_of`]); empty when
    /// combined from logits alone.
    #[serde(skip)]
    pub features: Vec<f32>,
}

/// `'0'`/`'1'` string of `logit > 0`.
pub fn bit_string(logits: &[f32]) -> String {
    logits
        .iter()
        .map(|&z| if z > 0.0 { '1' } else { '0' })
        .collect()
}

/// Decodes images of one asset (each at its own resolution) and combines them by averaging
/// their logits.
///
/// # Panics
/// If `images` is empty.
pub fn decode_images(model: &WatermarkModel, images: &[RgbImage], device: &Device) -> DecodeReport {
    assert!(!images.is_empty(), "no images to decode");
    let f = model.decoder.feature_count();
    let mut features = vec![0.0f64; f];
    let mut per: Vec<Vec<f32>> = Vec::with_capacity(images.len());
    for img in images {
        let pooled = model.decoder.pooled(rgb8_tensor(img, device));
        let p: Vec<f32> = pooled
            .clone()
            .try_into_vec_as::<f32>()
            .expect("features readable");
        for (a, &x) in features.iter_mut().zip(&p) {
            *a += f64::from(x);
        }
        let z: Vec<f32> = model
            .forward_pooled(pooled)
            .try_into_vec_as::<f32>()
            .expect("logits readable");
        per.push(z);
    }
    let mut report = combine_logits(&per);
    let n = images.len() as f64;
    report.features = features.iter().map(|&a| (a / n) as f32).collect();
    report
}

/// Averages per-image logits into one [`DecodeReport`].
///
/// # Panics
/// If `per_image` is empty or ragged.
pub fn combine_logits(per_image: &[Vec<f32>]) -> DecodeReport {
    let l = per_image[0].len();
    assert!(per_image.iter().all(|z| z.len() == l), "ragged logits");
    let n = per_image.len();
    let logits: Vec<f32> = (0..l)
        .map(|i| (per_image.iter().map(|z| f64::from(z[i])).sum::<f64>() / n as f64) as f32)
        .collect();
    let confidence = logits
        .iter()
        .map(|&z| (2.0 / (1.0 + (-f64::from(z)).exp()) - 1.0).abs())
        .sum::<f64>()
        / l as f64;
    DecodeReport {
        bits: bit_string(&logits),
        logits,
        confidence,
        images: n,
        per_image: per_image.iter().map(|z| bit_string(z)).collect(),
        features: Vec::new(),
    }
}

/// Reads image files for [`decode_images`].
pub fn read_images(paths: &[impl AsRef<Path>]) -> Result<Vec<RgbImage>, WeightsError> {
    paths
        .iter()
        .map(|p| {
            let p = p.as_ref();
            crate::image_file::open(p)
                .map(|i| i.to_rgb8())
                .map_err(|source| WeightsError::Image {
                    path: p.to_path_buf(),
                    source,
                })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::super::train::Trainer;
    use super::*;

    #[test]
    fn combining_averages_logits() {
        let r = combine_logits(&[vec![2.0, -1.0, 0.5], vec![-1.0, -1.0, 0.1]]);
        assert_eq!(r.logits, vec![0.5, -1.0, 0.3]);
        assert_eq!(r.bits, "101");
        assert_eq!(r.images, 2);
        assert_eq!(r.per_image, ["101", "001"]);
        let sig = |z: f64| 2.0 / (1.0 + (-z).exp()) - 1.0;
        let want = (sig(0.5) + sig(1.0) + sig(0.3)) / 3.0;
        assert!((r.confidence - want).abs() < 1e-6);
        assert_eq!(combine_logits(&[vec![0.0; 4]]).confidence, 0.0);
    }

    #[test]
    fn stats_and_bias() {
        let s = Stats::of(&[0.5, 1.0]);
        assert_eq!(
            (s.mean, s.std, s.min, s.max, s.n),
            (0.75, 0.25, 0.5, 1.0, 2)
        );
        assert_eq!(bit_bias(&[vec![1.0, 1.0], vec![-1.0, 1.0]]), 0.5);
        assert_eq!(
            bit_accuracy(&[1.0, -1.0, 0.0], &[true, false, true]),
            2.0 / 3.0
        );
    }

    /// A tiny trained model: eval JSON has the expected keys; decode of several images of the
    /// same marked content averages their logits; save + load round-trips.
    #[test]
    fn eval_report_keys_and_decode_through_a_saved_artifact() {
        let mut config = super::super::train::tests::tiny_config();
        config.steps = 3;
        let set = super::super::train::tests::synthetic_set(3, 48, 5);
        let mut t = Trainer::new(config.clone(), set.clone()).unwrap();
        while !t.done() {
            t.step().unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("decoder-4.bpk");
        let mut sink = Vec::new();
        let sidecar = t.finish(&out, Some(&set), &mut sink).unwrap();
        assert_eq!(sidecar.bits, 4);
        let model = WatermarkModel::load(&out, &Device::flex()).unwrap();
        assert!(model.encoder.is_some());

        let opts = EvalOptions {
            size: 32,
            repeats: 1,
            seed: 1,
            batch: 4,
            unmarked_messages: 5,
        };
        let report = evaluate(&model, &set.images, &opts).unwrap();
        let json = serde_json::to_value(&report).unwrap();
        for key in [
            "bits",
            "images",
            "psnr_db",
            "marked",
            "unmarked",
            "unmarked_fixed_messages",
            "unmarked_messages",
            "unmarked_bit_bias",
            "targets",
        ] {
            assert!(json.get(key).is_some(), "missing {key}");
        }
        for attack in [
            "clean", "noise", "rotation", "scaling", "blur", "crop", "jpeg", "combined",
        ] {
            let acc = json["marked"][attack]["mean"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&acc), "{attack}");
        }
        for key in ["mean", "std", "max"] {
            assert!(json["unmarked"][key].is_number());
        }
        assert_eq!(json["unmarked"]["n"], 3);
        assert_eq!(json["unmarked_fixed_messages"]["n"], 5);
        assert_eq!(json["unmarked_messages"], 5);

        let imgs: Vec<RgbImage> = set.images.iter().map(|i| i.to_rgb8()).collect();
        let d = Device::flex();
        let single: Vec<Vec<f32>> = imgs
            .iter()
            .flat_map(|i| model.logits(rgb8_tensor(i, &d)))
            .collect();
        let r = decode_images(&model, &imgs, &d);
        assert_eq!(r.images, 3);
        for i in 0..4 {
            let mean = single.iter().map(|z| z[i]).sum::<f32>() / 3.0;
            assert!((r.logits[i] - mean).abs() < 1e-5);
        }
    }
}
