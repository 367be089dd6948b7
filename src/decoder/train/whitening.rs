//! The logit map of a trained decoder (whitening, centering or none): fitted on clean crops,
//! checked on held-out ones and kept or dropped at the end of training, or re-decided later
//! for a trained artifact (`splatmark decoder calibrate`).

use std::io::Write;
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};

use super::{TrainConfig, TrainError, WhiteningChoice, step_seed};
use crate::attack::diff::EotRng;
use crate::decoder::artifact::{self, Sidecar, WatermarkModel, WhiteningReport};
use crate::decoder::data::{ImageSet, Split};
use crate::decoder::eval::{self, EvalOptions};
use crate::decoder::model::{HiddenDecoder, Whitening};

/// Logits (plain device, inference BatchNorm) of `n` clean crops of `images` at the training
/// size, in batches, from a random stream independent of the training steps.
fn clean_logits(
    decoder: &HiddenDecoder,
    images: &ImageSet,
    c: &TrainConfig,
    device: &Device,
    n: usize,
) -> Vec<Vec<f32>> {
    let mut rng = EotRng::new(step_seed(c.seed ^ 0x5748_4954_454e, usize::MAX));
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let b = (n - out.len()).min(32);
        let px = images.sample_batch(&mut rng, b, c.crop, c.min_scale, true);
        let x = Tensor::<4>::from_data(TensorData::new(px, [b, 3, c.crop, c.crop]), device);
        let z = decoder
            .forward(x)
            .try_into_vec_as::<f32>()
            .unwrap_or_default();
        out.extend(z.chunks_exact(c.bits).map(<[f32]>::to_vec));
    }
    out
}

/// Decides the map applied to the logits of `model`'s decoder (its sidecar's whitening is
/// ignored: the raw logits are used): a [`Whitening`] and a centering are fitted on clean crops
/// of `train` and, with held-out images, both are measured by [`eval::whitening_check`]. `Auto`
/// keeps, of those that pass the rule ([`WhiteningReport::helps`]), the one with the lower
/// unmarked bias (centering on a tie); `Always` keeps the whitening, `Center` the centering,
/// `Never` nothing. The choice and the numbers go to `log`.
pub fn decide_whitening(
    model: &WatermarkModel,
    train: &ImageSet,
    held_out: Option<&ImageSet>,
    c: &TrainConfig,
    choice: WhiteningChoice,
    device: &Device,
    log: &mut dyn Write,
) -> Result<(Option<Whitening>, Option<WhiteningReport>), TrainError> {
    if choice == WhiteningChoice::Never {
        return Ok((None, None));
    }
    let samples = clean_logits(&model.decoder, train, c, device, c.whitening_samples);
    let (white, center) = match (Whitening::fit(&samples), Whitening::centering(&samples)) {
        (Ok(w), Ok(m)) => (w, m),
        (Err(e), _) | (_, Err(e)) => {
            let _ = writeln!(log, "whitening: not fitted ({e})");
            return Ok((None, None));
        }
    };
    let report = match held_out {
        Some(h) => Some(eval::whitening_check(
            model,
            &white,
            Some(&center),
            h,
            c,
            device,
        )?),
        None => None,
    };
    let kept = match choice {
        WhiteningChoice::Never => None,
        WhiteningChoice::Always => Some(("whitening", white)),
        WhiteningChoice::Center => Some(("centering", center)),
        WhiteningChoice::Auto => report.as_ref().and_then(|r| {
            let w = r.helps().then_some(r.bias_whitened);
            let m = r.centering_helps().then_some(r.bias_centered).flatten();
            match (w, m) {
                (Some(bw), Some(bm)) if bw < bm => Some(("whitening", white)),
                (_, Some(_)) => Some(("centering", center)),
                (Some(_), None) => Some(("whitening", white)),
                (None, None) => None,
            }
        }),
    };
    let _ = writeln!(
        log,
        "logit map: {} ({})",
        kept.as_ref().map_or("none", |(k, _)| k),
        report
            .as_ref()
            .map(WhiteningReport::summary)
            .unwrap_or_else(|| "no held-out images to check".into())
    );
    let report = report.map(|r| WhiteningReport {
        applied: kept.is_some(),
        kind: kept.as_ref().map(|(k, _)| (*k).to_string()),
        ..r
    });
    Ok((kept.map(|(_, w)| w), report))
}

/// Re-decides the logit map ([`decide_whitening`] with `choice`) of the trained artifact at
/// `weights`, on the training and held-out splits of `images` as in training, re-runs the
/// held-out evaluation with `eval`, and writes the artifact (same weights, new sidecar) to `out`
/// (which may be `weights`). `command` is recorded as `record.calibrated_by`.
pub fn calibrate(
    weights: &Path,
    images: &Path,
    out: &Path,
    choice: WhiteningChoice,
    eval: &EvalOptions,
    command: Option<String>,
    log: &mut dyn Write,
) -> Result<Sidecar, TrainError> {
    let mut model = WatermarkModel::load(weights, &Device::flex())?;
    let config = model.sidecar.train_config.clone().ok_or_else(|| {
        TrainError::Config(format!(
            "{}: the sidecar has no training configuration (crop size, seed) to calibrate with",
            artifact::sidecar_path(weights).display()
        ))
    })?;
    if model.encoder.is_none() {
        return Err(artifact::WeightsError::NoEncoder(weights.to_path_buf()).into());
    }
    let train = ImageSet::load(images, Split::Train)?;
    let held_out = ImageSet::load(images, Split::HeldOut)?;
    let device = Device::flex();
    model.sidecar.whitening = None;
    let (whitening, report) = decide_whitening(
        &model,
        &train,
        Some(&held_out),
        &config,
        choice,
        &device,
        log,
    )?;
    model.sidecar.whitening = whitening;
    let _ = writeln!(log, "evaluating on {} held-out images…", held_out.len());
    let evaluation = eval::evaluate_on(&model, &held_out.images, eval, &device)?;
    let record = model.sidecar.record.get_or_insert_default();
    record.whitening = report;
    record.held_out = Some(evaluation);
    record.calibrated_by = command;
    model.save(out)?;
    Ok(model.sidecar)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::train::tests::{synthetic_set, tiny_artifact, tiny_config};

    #[test]
    fn calibrate_redecides_the_logit_map_and_records_it() {
        // An image folder on disk with a held-out image.
        let dir = tempfile::tempdir().unwrap();
        let images = dir.path().join("images");
        std::fs::create_dir_all(&images).unwrap();
        let set = synthetic_set(12, 48, 6);
        let mut held = 0;
        for (i, img) in set.images.iter().enumerate() {
            let name = format!("img{i:02}.png");
            held += usize::from(crate::decoder::data::is_held_out(&name));
            img.to_rgb8().save(images.join(&name)).unwrap();
        }
        assert!(held > 0 && held < 12, "{held} held out");
        let out = dir.path().join("d.bpk");
        let config = TrainConfig {
            steps: 2,
            whitening: WhiteningChoice::Never,
            ..tiny_config()
        };
        tiny_artifact(config, set, &out);
        let opts = EvalOptions {
            size: 32,
            repeats: 1,
            unmarked_messages: 3,
            ..EvalOptions::default()
        };
        let calibrated = dir.path().join("c.bpk");
        let sidecar = calibrate(
            &out,
            &images,
            &calibrated,
            WhiteningChoice::Center,
            &opts,
            Some("splatmark decoder calibrate …".into()),
            &mut Vec::new(),
        )
        .unwrap();
        let w = sidecar.whitening.clone().unwrap();
        assert!(w.is_centering());
        let record = sidecar.record.unwrap();
        assert_eq!(
            record.calibrated_by.as_deref(),
            Some("splatmark decoder calibrate …")
        );
        assert_eq!(record.steps, 2);
        let report = record.whitening.unwrap();
        assert_eq!(report.kind.as_deref(), Some("centering"));
        assert!(report.bias_centered.is_some());
        assert_eq!(record.held_out.unwrap().images, held);
        let model = WatermarkModel::load(&calibrated, &Device::flex()).unwrap();
        assert_eq!(model.sidecar.whitening, Some(w));
        // The same weights: raw logits unchanged.
        let original = WatermarkModel::load(&out, &Device::flex()).unwrap();
        let x = Tensor::<4>::from_data(
            TensorData::new(vec![0.5f32; 3 * 32 * 32], [1, 3, 32, 32]),
            &Device::flex(),
        );
        assert_eq!(model.raw_logits(x.clone()), original.raw_logits(x));
        // Never: no map.
        let none = calibrate(
            &out,
            &images,
            &calibrated,
            WhiteningChoice::Never,
            &opts,
            None,
            &mut Vec::new(),
        )
        .unwrap();
        assert!(none.whitening.is_none());
        // Without a trained model there: a typed error, nothing written.
        let missing = dir.path().join("none.bpk");
        assert!(
            calibrate(
                &missing,
                &images,
                &dir.path().join("x.bpk"),
                WhiteningChoice::Auto,
                &opts,
                None,
                &mut Vec::new()
            )
            .is_err()
        );
        assert!(!dir.path().join("x.bpk").exists());
    }
}
