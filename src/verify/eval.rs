//! Evaluation of a watermarked scene against its original (the rows of the paper's Tables 1–3):
//! fidelity (PSNR, SSIM of 8-bit renders against the original's renders), bit accuracy of the
//! clean renders, of the renders under each image attack (`attack::real::paper_protocol`, plus
//! blur σ = 0.8, which does act on 8-bit images), and of renders of the scene under each model
//! attack (`attack::model`: the paper's three, plus parameter noise carried to the scene's units,
//! `noise_0.1_scaled`); and, as a control, the original scene's renders decoded against
//! the same message (an unmarked scene must not be detected).
//!
//! Bit accuracy per row is the mean over views of per-view accuracy (the papers' figure); each
//! row also gives the accuracy of the logits averaged over all views (how a dispute decodes a
//! set of renders of one asset) with its p-value and decision at `fpr`. A model attack's row
//! pools several draws of it (`EvalSettings::model_draws`: which Gaussians are removed or
//! cloned is chance, and one draw is a coarse reading of what the attack does in expectation).

use burn::tensor::Device;
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::attack::model::{ModelAttack, ModelAttackError, view_position_scale};
use crate::attack::{AttackError, RealAttack, paper_protocol};
use crate::decoder::WatermarkModel;
use crate::decoder::artifact::rgb8_tensor;
use crate::decoder::eval::bit_accuracy;
use crate::embed::finetune::ssim;
use crate::render::{RenderError, RenderOptions, render, to_rgb8};
use crate::scene::{Camera, Gaussians};
use crate::verify::stats::{StatsError, detect, matches_from_logits};

/// Why an evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("attack {name}: {source}")]
    Attack { name: String, source: AttackError },
    #[error(transparent)]
    Model(#[from] ModelAttackError),
    #[error(transparent)]
    Stats(#[from] StatsError),
    #[error("no evaluation views")]
    NoViews,
    #[error("the message has {got} bits, the decoder reads {expected}")]
    MessageLength { got: usize, expected: usize },
}

/// One row: a condition and how the message survives it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    pub name: String,
    /// "image", "model" or "clean"/"unmarked".
    pub kind: String,
    /// Mean over views of the per-view bit accuracy.
    pub bit_accuracy: f64,
    /// Bit accuracy of the logits averaged over the views.
    pub bit_accuracy_combined: f64,
    /// p-value of the combined decision (one candidate message).
    pub p_value: f64,
    pub detected: bool,
    /// Share of the views detected each on its own at the same false-positive rate.
    pub detection_rate_per_view: f64,
    /// Model attacks: mean PSNR (dB) of the attacked copy's renders against the original's —
    /// what the attack costs the asset (an attack that ruins the asset needs no watermark to
    /// fail on it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_vs_original: Option<f64>,
    /// Model attacks: the same PSNR over the asset's pixels only ([`psnr_on_asset`]; a frame
    /// mostly background hides what the attack does to the asset itself).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_on_asset_vs_original: Option<f64>,
    /// Model attacks over several draws ([`EvalSettings::model_draws`]): each draw's
    /// `bit_accuracy`, in seed order. The row then reads the draws together: `bit_accuracy`,
    /// `bit_accuracy_combined`, `detection_rate_per_view` and the PSNRs are their means,
    /// `p_value` the largest (the weakest draw's) and `detected` whether every draw was
    /// detected. Empty for other rows (and in reports from before it).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub draws: Vec<f64>,
    /// Each view's bit accuracy, in the order of the views ([`SceneEval::per_view`]); a model
    /// attack's is the mean over its draws. `bit_accuracy` is their mean. Empty in reports
    /// from before it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub view_accuracy: Vec<f64>,
}

impl Row {
    /// The lowest of [`Row::draws`] (`bit_accuracy` for a row of one draw).
    pub fn worst_draw(&self) -> f64 {
        self.draws.iter().copied().fold(self.bit_accuracy, f64::min)
    }

    /// The view that keeps the fewest bits (its index in [`Row::view_accuracy`], its accuracy);
    /// the first of equals; `None` for a row without per-view figures.
    pub fn weakest_view(&self) -> Option<(usize, f64)> {
        self.view_accuracy
            .iter()
            .copied()
            .enumerate()
            .fold(None, |w, (i, a)| match w {
                Some((_, b)) if b <= a => w,
                _ => Some((i, a)),
            })
    }
}

/// One row from the rows of several draws of the same attack (see [`Row::draws`]).
fn pooled(draws: Vec<Row>) -> Row {
    let n = draws.len() as f64;
    let mean = |f: &dyn Fn(&Row) -> f64| draws.iter().map(f).sum::<f64>() / n;
    let mean_opt = |f: &dyn Fn(&Row) -> Option<f64>| {
        let v: Vec<f64> = draws.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let first = &draws[0];
    Row {
        name: first.name.clone(),
        kind: first.kind.clone(),
        bit_accuracy: mean(&|r| r.bit_accuracy),
        bit_accuracy_combined: mean(&|r| r.bit_accuracy_combined),
        p_value: draws.iter().map(|r| r.p_value).fold(0.0, f64::max),
        detected: draws.iter().all(|r| r.detected),
        detection_rate_per_view: mean(&|r| r.detection_rate_per_view),
        psnr_vs_original: mean_opt(&|r| r.psnr_vs_original),
        psnr_on_asset_vs_original: mean_opt(&|r| r.psnr_on_asset_vs_original),
        draws: draws.iter().map(|r| r.bit_accuracy).collect(),
        view_accuracy: (0..first.view_accuracy.len())
            .map(|v| mean(&|r| r.view_accuracy[v]))
            .collect(),
    }
}

/// The evaluation of one watermarked scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneEval {
    pub views: usize,
    /// Mean PSNR (dB) of the watermarked scene's 8-bit renders against the original's.
    pub psnr: f64,
    /// Mean SSIM of the same.
    pub ssim: f64,
    /// Mean over the views that show the asset of the PSNR over the asset's pixels only
    /// ([`psnr_on_asset`]): `psnr` counts the background too, which the finetuning leaves
    /// untouched, so a small asset in a large frame reads several dB above what its own pixels
    /// went through (absent in reports from before it, or when no view shows the asset).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_on_asset: Option<f64>,
    pub fpr: f64,
    pub rows: Vec<Row>,
    /// Each view on its own, clean: how much of it shows the asset, its fidelity, its bits.
    pub per_view: Vec<ViewEval>,
    /// The factor of the means' noise in the `noise_0.1_scaled` row
    /// ([`crate::attack::model::view_position_scale`]; absent in reports from before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_position_scale: Option<f32>,
}

/// One evaluation view, clean.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewEval {
    pub camera: String,
    /// Share of the view's pixels where the original's render differs from the background
    /// (the asset's footprint: a view that barely shows the asset cannot carry its bits).
    pub coverage: f64,
    pub psnr: f64,
    /// PSNR over the asset's pixels only ([`psnr_on_asset`]); `None` when the view shows none
    /// of it (or in reports from before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_on_asset: Option<f64>,
    pub bit_accuracy: f64,
    /// Share of the asset's pixels (as [`coverage`] counts them) that the protocol's crop keeps
    /// (a crop that keeps none of the asset leaves nothing to decode); `None` when the view
    /// shows no asset (or in reports from before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub asset_in_crop: Option<f64>,
    /// The same share for the crop centred on the asset (rows `*_on_asset`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub asset_in_crop_on_asset: Option<f64>,
}

/// Centre of the asset's pixels in `img` (as [`coverage`] counts them), as fractions of the
/// width and height (pixel centres); `None` when `img` shows none.
pub fn asset_centre(img: &RgbImage, background: [f32; 3]) -> Option<(f32, f32)> {
    let (mut sx, mut sy, mut n) = (0.0f64, 0.0f64, 0u64);
    let bg = background_levels(background);
    for (x, y, p) in img.enumerate_pixels() {
        if on_asset(p, bg) {
            sx += f64::from(x) + 0.5;
            sy += f64::from(y) + 0.5;
            n += 1;
        }
    }
    (n > 0).then(|| {
        let n = n as f64;
        (
            (sx / n / f64::from(img.width())) as f32,
            (sy / n / f64::from(img.height())) as f32,
        )
    })
}

/// Share of `img`'s pixels farther than 2 levels from `background` (linear [0, 1]) in any
/// channel.
pub fn coverage(img: &RgbImage, background: [f32; 3]) -> f64 {
    let n = (img.width() as usize * img.height() as usize).max(1);
    let bg = background_levels(background);
    let on = img.pixels().filter(|p| on_asset(p, bg)).count();
    on as f64 / n as f64
}

/// Whether a pixel shows the asset: farther than 2 levels from the background's 8-bit
/// levels ([`background_levels`]) in a channel.
fn on_asset(p: &image::Rgb<u8>, bg: [i32; 3]) -> bool {
    (0..3).any(|c| (i32::from(p.0[c]) - bg[c]).abs() > 2)
}

/// The 8-bit levels of a linear [0, 1] background colour.
fn background_levels(background: [f32; 3]) -> [i32; 3] {
    background.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as i32)
}

/// Share of the asset's pixels in `img` (as [`coverage`] counts them) that are still in
/// `attack(img)` — for a crop, how much of the asset it keeps; `None` when `img` shows none.
pub fn asset_kept(
    img: &RgbImage,
    attack: &RealAttack,
    background: [f32; 3],
) -> Result<Option<f64>, AttackError> {
    let pixels = |im: &RgbImage| f64::from(im.width()) * f64::from(im.height());
    let before = coverage(img, background) * pixels(img);
    if before == 0.0 {
        return Ok(None);
    }
    let kept = attack.apply(img)?;
    Ok(Some(coverage(&kept, background) * pixels(&kept) / before))
}

/// Renders `g` through every camera to 8-bit images.
pub fn render_views(
    g: &Gaussians,
    cams: &[Camera],
    opts: &RenderOptions,
) -> Result<Vec<RgbImage>, RenderError> {
    cams.iter()
        .map(|c| {
            let r = render(g, c, opts)?;
            Ok(to_rgb8(r.width, r.height, &r.image))
        })
        .collect()
}

/// Mean over views of each pair's PSNR (dB).
fn mean_psnr(a: &[RgbImage], b: &[RgbImage]) -> f64 {
    a.iter().zip(b).map(|(x, y)| psnr_u8(x, y)).sum::<f64>() / a.len() as f64
}

fn psnr_u8(a: &RgbImage, b: &RgbImage) -> f64 {
    let n = a.as_raw().len() as f64;
    let mse = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum::<f64>()
        / n;
    psnr_of_mse(mse)
}

/// PSNR (dB) of a mean squared error in 8-bit levels; infinite for identical images.
fn psnr_of_mse(mse: f64) -> f64 {
    if mse > 0.0 {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    } else {
        f64::INFINITY
    }
}

/// PSNR (dB) of `b` against `a` over the pixels where either shows the asset (farther than 2
/// levels from `background`, as [`coverage`] counts them); `None` when neither shows any.
/// Over a whole frame the untouched background dilutes the error: a change confined to the
/// asset reads 10·log₁₀(1 / coverage) dB higher there than on the asset's own pixels.
pub fn psnr_on_asset(a: &RgbImage, b: &RgbImage, background: [f32; 3]) -> Option<f64> {
    let bg = background_levels(background);
    let (mut se, mut n) = (0.0f64, 0u64);
    for (p, q) in a.pixels().zip(b.pixels()) {
        if on_asset(p, bg) || on_asset(q, bg) {
            se += (0..3)
                .map(|c| (f64::from(p.0[c]) - f64::from(q.0[c])).powi(2))
                .sum::<f64>();
            n += 3;
        }
    }
    (n > 0).then(|| psnr_of_mse(se / n as f64))
}

/// Mean of the views' [`psnr_on_asset`] over the views that show the asset.
fn mean_psnr_on_asset(a: &[RgbImage], b: &[RgbImage], background: [f32; 3]) -> Option<f64> {
    let v: Vec<f64> = a
        .iter()
        .zip(b)
        .filter_map(|(x, y)| psnr_on_asset(x, y, background))
        .collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Decodes each image alone; returns the row for `message`.
fn row(
    name: &str,
    kind: &'static str,
    images: &[RgbImage],
    model: &WatermarkModel,
    message: &[bool],
    fpr: f64,
    device: &Device,
) -> Result<Row, EvalError> {
    row_of_logits(
        name,
        kind,
        &view_logits(images, model, device),
        message,
        fpr,
    )
}

/// Each image's logits, decoded alone.
fn view_logits(images: &[RgbImage], model: &WatermarkModel, device: &Device) -> Vec<Vec<f32>> {
    images
        .iter()
        .map(|im| {
            model
                .logits(rgb8_tensor(im, device))
                .pop()
                .expect("one image")
        })
        .collect()
}

/// The row for `message` from each view's logits.
fn row_of_logits(
    name: &str,
    kind: &'static str,
    logits: &[Vec<f32>],
    message: &[bool],
    fpr: f64,
) -> Result<Row, EvalError> {
    let view_accuracy: Vec<f64> = logits.iter().map(|z| bit_accuracy(z, message)).collect();
    let per_view = view_accuracy.iter().sum::<f64>() / logits.len() as f64;
    let l = message.len();
    let mean: Vec<f32> = (0..l)
        .map(|j| logits.iter().map(|z| z[j]).sum::<f32>() / logits.len() as f32)
        .collect();
    let decoded: Vec<bool> = mean.iter().map(|&z| z > 0.0).collect();
    let d = detect(&decoded, message, 1, fpr)?;
    let mut alone = 0usize;
    for z in logits {
        let bits: Vec<bool> = z.iter().map(|&v| v > 0.0).collect();
        alone += usize::from(detect(&bits, message, 1, fpr)?.detected);
    }
    debug_assert_eq!(d.matches, matches_from_logits(&mean, message));
    Ok(Row {
        name: name.into(),
        kind: kind.into(),
        bit_accuracy: per_view,
        bit_accuracy_combined: d.bit_accuracy,
        p_value: d.p_value,
        detected: d.detected,
        detection_rate_per_view: alone as f64 / logits.len() as f64,
        psnr_vs_original: None,
        psnr_on_asset_vs_original: None,
        draws: Vec::new(),
        view_accuracy,
    })
}

/// How to evaluate.
#[derive(Clone, Debug)]
pub struct EvalSettings {
    pub render: RenderOptions,
    /// False-positive rate of each row's decision.
    pub fpr: f64,
    /// Seed of the random attacks.
    pub seed: u64,
    /// Draws of each model attack (seeds `seed`, `seed + 1`, …; at least 1): which Gaussians
    /// a removal or a clone hits moves one draw's accuracy by several points on a scene of a
    /// few thousand Gaussians, so the rows report the draws' mean and keep each (see
    /// [`Row::draws`]).
    pub model_draws: usize,
}

/// Draws of each model attack unless told otherwise ([`EvalSettings::model_draws`]).
pub const MODEL_DRAWS: usize = 8;

impl Default for EvalSettings {
    fn default() -> Self {
        Self {
            render: RenderOptions::default(),
            fpr: 1e-6,
            seed: 0,
            model_draws: MODEL_DRAWS,
        }
    }
}

/// Evaluates `marked` against `original` through `cams` (held-out views).
pub fn evaluate_scene(
    original: &Gaussians,
    marked: &Gaussians,
    cams: &[Camera],
    model: &WatermarkModel,
    message: &[bool],
    settings: &EvalSettings,
) -> Result<SceneEval, EvalError> {
    let (opts, fpr, seed) = (&settings.render, settings.fpr, settings.seed);
    if cams.is_empty() {
        return Err(EvalError::NoViews);
    }
    if message.len() != model.bits() {
        return Err(EvalError::MessageLength {
            got: message.len(),
            expected: model.bits(),
        });
    }
    let device = model.device();
    let orig = render_views(original, cams, opts)?;
    let mark = render_views(marked, cams, opts)?;
    let n = cams.len() as f64;
    let psnr = mean_psnr(&orig, &mark);
    let ssim_mean = orig
        .iter()
        .zip(&mark)
        .map(|(a, b)| {
            f64::from(ssim(rgb8_tensor(a, &device), rgb8_tensor(b, &device)).into_scalar::<f32>())
        })
        .sum::<f64>()
        / n;

    let clean = view_logits(&mark, model, &device);
    let mut image_attacks: Vec<(String, RealAttack)> = paper_protocol(seed)
        .into_iter()
        .map(|(n, a)| (n.to_string(), a))
        .collect();
    let crop = image_attacks
        .iter()
        .find(|(_, a)| matches!(a, RealAttack::Crop { .. }))
        .map(|(_, a)| a.clone());
    // Where each view's crops centre on the asset (rows `*_on_asset`; the image's centre where
    // a view shows none of it).
    let centres: Vec<(f32, f32)> = orig
        .iter()
        .map(|a| asset_centre(a, opts.background).unwrap_or((0.5, 0.5)))
        .collect();
    let kept = |a: &RgbImage, attack: Option<RealAttack>| match attack {
        Some(attack) => {
            asset_kept(a, &attack, opts.background).map_err(|source| EvalError::Attack {
                name: "crop".into(),
                source,
            })
        }
        None => Ok(None),
    };
    let mut per_view = Vec::with_capacity(cams.len());
    for (((c, (a, b)), z), &(x, y)) in cams
        .iter()
        .zip(orig.iter().zip(&mark))
        .zip(&clean)
        .zip(&centres)
    {
        let asset_in_crop = kept(a, crop.clone())?;
        let asset_in_crop_on_asset = kept(a, crop.as_ref().and_then(|k| k.at(x, y)))?;
        per_view.push(ViewEval {
            camera: c.name.clone(),
            coverage: coverage(a, opts.background),
            psnr: psnr_u8(a, b),
            psnr_on_asset: psnr_on_asset(a, b, opts.background),
            bit_accuracy: bit_accuracy(z, message),
            asset_in_crop,
            asset_in_crop_on_asset,
        });
    }
    let mut rows = vec![
        row_of_logits("clean", "clean", &clean, message, fpr)?,
        row("unmarked", "unmarked", &orig, model, message, fpr, &device)?,
    ];
    image_attacks.push((
        "blur_0.8".into(),
        RealAttack::Blur {
            sigma: 0.8,
            kernel: 3,
        },
    ));
    for (name, a) in &image_attacks {
        let attacked = mark
            .iter()
            .map(|im| {
                a.apply(im).map_err(|source| EvalError::Attack {
                    name: name.clone(),
                    source,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        rows.push(row(name, "image", &attacked, model, message, fpr, &device)?);
    }
    // The protocol's crops again, each view's centred on its asset.
    for (name, a) in &image_attacks {
        let Some(attacked) = centres
            .iter()
            .zip(&mark)
            .map(|(&(x, y), im)| {
                a.at(x, y).map(|moved| {
                    moved.apply(im).map_err(|source| EvalError::Attack {
                        name: format!("{name}_on_asset"),
                        source,
                    })
                })
            })
            .collect::<Option<Result<Vec<_>, _>>>()
        else {
            continue;
        };
        let name = format!("{name}_on_asset");
        rows.push(row(
            &name, "image", &attacked?, model, message, fpr, &device,
        )?);
    }
    let noise_position_scale = view_position_scale(marked, cams);
    let mut model_attacks = ModelAttack::paper_protocol(seed);
    if let Some(position_scale) = noise_position_scale {
        model_attacks.insert(
            1,
            (
                "noise_0.1_scaled".into(),
                ModelAttack::Noise {
                    sigma: 0.1,
                    position_scale,
                    seed,
                },
            ),
        );
    }
    for (name, a) in model_attacks {
        let draws = (0..settings.model_draws.max(1) as u64)
            .map(|d| {
                let g = a.reseeded(seed.wrapping_add(d)).apply(marked)?;
                let imgs = render_views(&g, cams, opts)?;
                let mut r = row(&name, "model", &imgs, model, message, fpr, &device)?;
                r.psnr_vs_original = Some(mean_psnr(&orig, &imgs));
                r.psnr_on_asset_vs_original = mean_psnr_on_asset(&orig, &imgs, opts.background);
                Ok(r)
            })
            .collect::<Result<Vec<_>, EvalError>>()?;
        rows.push(pooled(draws));
    }
    Ok(SceneEval {
        views: cams.len(),
        psnr,
        ssim: ssim_mean,
        psnr_on_asset: mean_psnr_on_asset(&orig, &mark, opts.background),
        fpr,
        rows,
        per_view,
        noise_position_scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_of_a_model_attack_pool_into_one_row_that_keeps_the_weakest_decision() {
        let draw = |acc: f64, p: f64, detected: bool, psnr: f64| Row {
            name: "remove_20".into(),
            kind: "model".into(),
            bit_accuracy: acc,
            bit_accuracy_combined: acc + 0.01,
            p_value: p,
            detected,
            detection_rate_per_view: if detected { 1.0 } else { 0.5 },
            psnr_vs_original: Some(psnr),
            psnr_on_asset_vs_original: None,
            draws: Vec::new(),
            // Two views: the first keeps every bit, the second loses what the draw loses.
            view_accuracy: vec![1.0, 2.0 * acc - 1.0],
        };
        let r = pooled(vec![
            draw(1.0, 1e-9, true, 30.0),
            draw(0.9, 1e-7, true, 32.0),
            draw(0.8, 1e-3, false, 34.0),
        ]);
        assert_eq!(r.draws, vec![1.0, 0.9, 0.8]);
        assert!((r.bit_accuracy - 0.9).abs() < 1e-12);
        assert!((r.bit_accuracy_combined - 0.91).abs() < 1e-12);
        assert_eq!(r.worst_draw(), 0.8);
        assert_eq!(r.p_value, 1e-3);
        assert!(!r.detected, "one draw undetected: the row is not");
        assert!((r.detection_rate_per_view - 5.0 / 6.0).abs() < 1e-12);
        assert_eq!(r.psnr_vs_original, Some(32.0));
        assert_eq!(r.psnr_on_asset_vs_original, None);
        // Each view's accuracy is its mean over the draws; the second view is the weakest.
        assert_eq!(r.view_accuracy.len(), 2);
        assert!((r.view_accuracy[0] - 1.0).abs() < 1e-12);
        assert!((r.view_accuracy[1] - 0.8).abs() < 1e-12);
        let (v, a) = r.weakest_view().unwrap();
        assert!(v == 1 && (a - 0.8).abs() < 1e-12, "{v} {a}");
        let all = pooled(vec![
            draw(1.0, 1e-9, true, 30.0),
            draw(0.9, 1e-7, true, 32.0),
        ]);
        assert!(all.detected && all.p_value == 1e-7);
        // A row of one draw is its draw.
        let one = pooled(vec![draw(0.9, 1e-7, true, 32.0)]);
        assert_eq!(one.worst_draw(), 0.9);
        assert_eq!(one.bit_accuracy, 0.9);
        assert_eq!(one.view_accuracy, vec![1.0, 2.0 * 0.9 - 1.0]);
        // Equal views: the first is named; no views, no weakest.
        let mut even = one.clone();
        even.view_accuracy = vec![0.75, 0.5, 0.5];
        assert_eq!(even.weakest_view(), Some((1, 0.5)));
        even.view_accuracy.clear();
        assert_eq!(even.weakest_view(), None);
    }

    #[test]
    fn the_crop_keeps_the_asset_only_where_it_sits_in_the_centre() {
        let crop = RealAttack::Crop { keep: 0.4 };
        let black = [0.0; 3];
        let mut img = RgbImage::new(100, 80);
        assert_eq!(asset_kept(&img, &crop, black).unwrap(), None);
        // An asset in the top-left corner (the udon views' case): the centred crop keeps none.
        for x in 0..15 {
            for y in 0..12 {
                img.put_pixel(x, y, image::Rgb([200, 120, 40]));
            }
        }
        assert_eq!(asset_kept(&img, &crop, black).unwrap(), Some(0.0));
        // In the centre: all of it.
        let mut centre = RgbImage::new(100, 80);
        for x in 45..55 {
            for y in 35..45 {
                centre.put_pixel(x, y, image::Rgb([200, 120, 40]));
            }
        }
        assert_eq!(asset_kept(&centre, &crop, black).unwrap(), Some(1.0));
        // Everywhere: the crop's share of the area.
        let full = RgbImage::from_pixel(100, 80, image::Rgb([9, 9, 9]));
        let k = asset_kept(&full, &crop, black).unwrap().unwrap();
        assert!((k - 0.4).abs() < 0.02, "{k}");
    }

    #[test]
    fn the_crop_on_the_asset_keeps_an_asset_in_a_corner() {
        let black = [0.0; 3];
        let mut img = RgbImage::new(100, 80);
        assert_eq!(asset_centre(&img, black), None);
        for x in 0..15 {
            for y in 0..12 {
                img.put_pixel(x, y, image::Rgb([200, 120, 40]));
            }
        }
        let (x, y) = asset_centre(&img, black).unwrap();
        assert!(
            (x - 0.075).abs() < 1e-6 && (y - 0.075).abs() < 1e-6,
            "{x} {y}"
        );
        let crop = RealAttack::Crop { keep: 0.4 };
        assert_eq!(asset_kept(&img, &crop, black).unwrap(), Some(0.0));
        let moved = crop.at(x, y).unwrap();
        assert_eq!(asset_kept(&img, &moved, black).unwrap(), Some(1.0));
    }

    #[test]
    fn coverage_counts_the_pixels_that_differ_from_the_background() {
        let mut img = RgbImage::from_pixel(10, 10, image::Rgb([255, 255, 255]));
        assert_eq!(coverage(&img, [1.0, 1.0, 1.0]), 0.0);
        // Two levels off the background is still background (8-bit rounding of a render).
        img.put_pixel(0, 0, image::Rgb([253, 255, 255]));
        assert_eq!(coverage(&img, [1.0, 1.0, 1.0]), 0.0);
        for x in 0..10 {
            for y in 0..3 {
                img.put_pixel(x, y, image::Rgb([255, 240, 255]));
            }
        }
        assert!((coverage(&img, [1.0, 1.0, 1.0]) - 0.3).abs() < 1e-12);
        assert_eq!(coverage(&img, [0.0, 0.0, 0.0]), 1.0);
    }

    #[test]
    fn the_asset_psnr_reads_the_change_on_the_asset_not_the_background_around_it() {
        let black = [0.0; 3];
        let blank = RgbImage::new(100, 80);
        assert_eq!(psnr_on_asset(&blank, &blank, black), None);
        // An asset on 10 % of the frame, every channel of it changed by 4 levels.
        let mut a = RgbImage::new(100, 80);
        for x in 0..20 {
            for y in 0..40 {
                a.put_pixel(x, y, image::Rgb([120, 90, 60]));
            }
        }
        let mut b = a.clone();
        for x in 0..20 {
            for y in 0..40 {
                b.put_pixel(x, y, image::Rgb([124, 94, 64]));
            }
        }
        let on = psnr_on_asset(&a, &b, black).unwrap();
        let want = 10.0 * (255.0f64 * 255.0 / 16.0).log10();
        assert!((on - want).abs() < 1e-9, "{on} {want}");
        // The frame's PSNR is 10·log10(1 / 0.1) = 10 dB higher for the same change.
        assert!((psnr_u8(&a, &b) - on - 10.0).abs() < 1e-9);
        // A pixel one image shows and the other does not (a hole, a clone) counts.
        let mut holed = a.clone();
        holed.put_pixel(0, 0, image::Rgb([0, 0, 0]));
        let mut grown = a.clone();
        grown.put_pixel(50, 50, image::Rgb([30, 30, 30]));
        let hole = psnr_on_asset(&a, &holed, black).unwrap();
        assert!(hole.is_finite() && hole < psnr_u8(&a, &holed), "{hole}");
        assert_eq!(
            psnr_on_asset(&a, &grown, black).unwrap(),
            psnr_on_asset(&grown, &a, black).unwrap()
        );
        assert_eq!(psnr_on_asset(&a, &a, black), Some(f64::INFINITY));
    }
}
