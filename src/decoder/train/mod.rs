//! Joint training of the HiDDeN encoder and decoder with differentiable attack layers
//! (`splatmark decoder train`).
//!
//! # Recipe
//!
//! Per step, on a batch of `batch_size` random `crop × crop` training crops x
//! ([`super::data`](mod@super::data)) and uniformly random messages m ∈ {0, 1}^L:
//!
//! 1. `x_w = q(clamp(x + strength · E(x, m), 0, 1))`, with E the [`HiddenEncoder`] (a residual
//!    in (−1, 1)) and q the 8-bit rounding with a straight-through gradient (the watermarked
//!    image is always saved as 8-bit in practice).
//! 2. The batch is split into `attack_groups` groups; each group gets its own transformation t ~
//!    p(t) drawn by [`random_composition`] from the [`EotConfig`] (attack warm-up: no attack at
//!    all for the first `warmup_steps` steps, then each group is attacked with a probability that
//!    ramps linearly from 0 to 1 over `ramp_steps` steps).
//! 3. `loss = BCE-with-logits(D(t(x_w)), m) + p_k · image_weight · MSE(x_w, x)`, where p_k is
//!    the attack probability of step k: the image loss ramps in together with the attacks, after
//!    the decoder has learnt to read the clean pattern (with the image loss on from step 0 the
//!    encoder shrinks its residual before the decoder can read it, and nothing is learnt).
//!
//! The message loss is the binary cross-entropy on the logits (Stable Signature's choice) rather
//! than HiDDeN's MSE on `tanh`-ed outputs: it gives useful gradients on confidently wrong bits and
//! trains faster. Adam (β = 0.9, 0.999) at `lr` with a cosine decay to `lr · lr_min_fraction`
//! over the run.
//!
//! # Randomness and resuming
//!
//! Every random draw of step `k` (crops, flips, messages, attacks, attack noise) comes from a
//! SplitMix64 stream seeded with `mix(seed, k)` ([`step_seed`]); the only other randomness is the
//! weight initialisation, drawn from burn's device RNG seeded with `seed`. The "RNG state" of a
//! checkpoint is therefore just `(seed, step)`, and a resumed run sees exactly the batches and
//! attacks the uninterrupted run would have seen.
//!
//! Checkpoints go to `<out>.ckpt/step-NNNNNNNN/` (`net.bpk`: encoder + decoder weights with
//! BatchNorm statistics, `optim.bpk`: the **Adam state** — first and second moments and step
//! counts, keyed by parameter id, which burnpack records persist —, `state.json`: step, config,
//! accumulated wall time, progress history). Each is written into a temporary folder that is then
//! renamed into place, so a crash leaves either the previous or the new checkpoint, never half of
//! one; the newest `keep_checkpoints` are kept. `--resume` loads the newest and continues from
//! its step with its config (only `steps`, `log_every` and `checkpoint_every` may be changed).
//!
//! # Final artifact
//!
//! After the last step the decoder is frozen (inference BatchNorm, no gradients), a
//! [`Whitening`] is fitted on its logits of `whitening_samples` clean training crops, and kept
//! or dropped by the rule of [`WhiteningChoice::Auto`]; then the held-out evaluation
//! ([`super::eval`](mod@super::eval)) runs and the artifact is written
//! ([`super::artifact`](mod@super::artifact)): decoder weights at `<out>`, encoder weights at
//! `<out stem>.encoder.bpk`, and the JSON sidecar `<out stem>.json` (architecture, strength,
//! whitening, config, training record).
//!
//! [`random_composition`]: crate::attack::diff::random_composition
//! [`EotConfig`]: crate::attack::diff::EotConfig
//! [`Whitening`]: super::model::Whitening
//! [`HiddenEncoder`]: super::model::HiddenEncoder

mod checkpoint;
mod config;
mod trainer;
mod whitening;

pub use checkpoint::{
    CheckpointState, checkpoint_root, list_checkpoints, read_checkpoint, write_checkpoint,
};
pub use config::{DeviceChoice, EncoderKind, TrainConfig, WhiteningChoice};
pub use trainer::{LogEntry, StartedFrom, StepStats, Trainer};
pub use whitening::{calibrate, decide_whitening};

use std::io::Write;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Tensor;
use burn::tensor::activation::log_sigmoid;

use super::artifact::{self, Sidecar};
use super::data::{ImageSet, Split};
use super::encoder::Encoder;
use super::model::HiddenDecoder;
use crate::attack::diff::DiffAttackError;

/// Why training failed.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Invalid configuration.
    #[error("invalid training configuration: {0}")]
    Config(String),
    /// Images could not be loaded.
    #[error(transparent)]
    Data(#[from] super::data::DataError),
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Weights or optimizer state could not be saved or loaded.
    #[error("{path}: {message}")]
    Record { path: PathBuf, message: String },
    /// A checkpoint's state file is not valid.
    #[error("{path}: {source}")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    /// `--resume` without any checkpoint.
    #[error("no checkpoint to resume from in {0}")]
    NoCheckpoint(PathBuf),
    /// The loss became NaN or infinite.
    #[error("the loss is not finite at step {0}")]
    Diverged(usize),
    /// An attack could not be applied.
    #[error(transparent)]
    Attack(#[from] DiffAttackError),
    /// The final evaluation or artifact failed.
    #[error(transparent)]
    Artifact(#[from] artifact::WeightsError),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Encoder and decoder, trained together (one module so one optimizer and one record).
#[derive(Module, Debug)]
pub struct WatermarkNet {
    pub encoder: Encoder,
    pub decoder: HiddenDecoder,
}

/// Seed of step `step`'s random stream: SplitMix64 finaliser of `seed ⊕ step·φ`.
pub fn step_seed(seed: u64, step: usize) -> u64 {
    let mut z = seed
        ^ (step as u64)
            .wrapping_add(1)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Mean binary cross-entropy with logits: `softplus(z) − m·z = −log σ(z) + (1 − m)·z`.
pub fn bce_with_logits(logits: Tensor<2>, targets: Tensor<2>) -> Tensor<1> {
    let one_minus = targets.neg().add_scalar(1.0);
    log_sigmoid(logits.clone())
        .neg()
        .add(logits.mul(one_minus))
        .mean()
}

/// PSNR (dB, peak 1) of a mean squared error.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse > 0.0 {
        -10.0 * mse.log10()
    } else {
        f64::INFINITY
    }
}

/// `1h02m03s`-style duration.
pub fn hms(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{}h{:02}m{:02}s", s / 3600, s / 60 % 60, s % 60)
    } else {
        format!("{}m{:02}s", s / 60, s % 60)
    }
}

/// Options of [`run`] besides the configuration.
pub struct RunOptions<'a> {
    /// Continue from the newest checkpoint in `<out>.ckpt/`.
    pub resume: bool,
    /// Applied to the configuration: on a fresh run to `config`; on a resumed run to the
    /// checkpoint's configuration, of which only `steps`, `log_every`, `checkpoint_every` and
    /// `keep_checkpoints` are then taken (other changes are reported and ignored).
    pub overrides: &'a dyn Fn(&mut TrainConfig),
    /// The command line, for the training record.
    pub command: Option<String>,
    /// Start a fresh run from this trained artifact instead of random weights (see
    /// [`Trainer::from_artifact`]); not with `resume`.
    pub init: Option<&'a Path>,
    /// Called after every step with (step, steps) — a progress bar's feed.
    pub on_step: Option<&'a mut dyn FnMut(usize, usize)>,
}

/// Runs a whole training job: loads the split under `images`, starts fresh or resumes from the
/// newest checkpoint in `<out>.ckpt/`, trains with progress lines on `log`, checkpoints, and
/// writes the final artifact.
pub fn run(
    config: TrainConfig,
    images: &Path,
    out: &Path,
    mut options: RunOptions<'_>,
    log: &mut dyn Write,
) -> Result<Sidecar, TrainError> {
    let root = checkpoint_root(out);
    let train = ImageSet::load(images, Split::Train)?;
    let held_out = match ImageSet::load(images, Split::HeldOut) {
        Ok(h) => Some(h),
        Err(super::data::DataError::Empty { .. }) => None,
        Err(e) => return Err(e.into()),
    };
    let n_train = train.len();
    if options.resume && options.init.is_some() {
        return Err(TrainError::Config(
            "--init starts a new run; it cannot be combined with --resume".into(),
        ));
    }
    let mut trainer = if options.resume {
        let (_, latest) = list_checkpoints(&root)
            .pop()
            .ok_or_else(|| TrainError::NoCheckpoint(root.clone()))?;
        let mut ignored = None;
        let t = Trainer::resume(&latest, train, |stored| {
            let mut wanted = stored.clone();
            (options.overrides)(&mut wanted);
            let mut kept = wanted.clone();
            kept.steps = stored.steps;
            kept.log_every = stored.log_every;
            kept.checkpoint_every = stored.checkpoint_every;
            kept.keep_checkpoints = stored.keep_checkpoints;
            if kept != *stored {
                ignored = Some(());
            }
            wanted
        })?;
        if ignored.is_some() {
            let _ = writeln!(
                log,
                "note: on --resume only --steps, --log-every, --checkpoint-every and \
                 --keep-checkpoints change the run; other settings come from the checkpoint"
            );
        }
        if t.config.bits != config.bits {
            return Err(TrainError::Config(format!(
                "the checkpoint trains {} bits, not {}",
                t.config.bits, config.bits
            )));
        }
        let _ = writeln!(
            log,
            "resuming from {} (step {} of {})",
            latest.display(),
            t.step,
            t.config.steps
        );
        t
    } else {
        let mut config = config;
        (options.overrides)(&mut config);
        match options.init {
            Some(path) => {
                let t = Trainer::from_artifact(config, train, path)?;
                let _ = writeln!(
                    log,
                    "starting from {} (its architecture and strength {}; fresh Adam state)",
                    path.display(),
                    t.config.strength
                );
                t
            }
            None => Trainer::new(config, train)?,
        }
    };
    trainer.command = options.command;
    trainer.data = Some(format!(
        "{}: {} training images, {} held out (FNV-1a-64 of the relative path mod 10 == 0)",
        images.display(),
        n_train,
        held_out.as_ref().map_or(0, ImageSet::len)
    ));
    let c = trainer.config.clone();
    let _ = writeln!(
        log,
        "training {} bits on {} images ({} held out) under {}: {} steps of {} × {}² crops on {:?}",
        c.bits,
        n_train,
        held_out.as_ref().map_or(0, ImageSet::len),
        images.display(),
        c.steps,
        c.batch_size,
        c.crop,
        c.device
    );
    while !trainer.done() {
        trainer.step()?;
        let k = trainer.step;
        if let Some(f) = options.on_step.as_mut() {
            f(k, c.steps);
        }
        if c.log_every > 0
            && (k % c.log_every == 0 || k == c.steps)
            && let Some(entry) = trainer.log_entry()
        {
            let _ = writeln!(log, "{}", trainer.progress_line(&entry));
        }
        if c.checkpoint_every > 0 && k % c.checkpoint_every == 0 && k < c.steps {
            let dir = trainer.save_checkpoint(&root)?;
            let _ = writeln!(log, "checkpoint {}", dir.display());
        }
    }
    if trainer.history.last().map(|e| e.step) != Some(trainer.step) {
        trainer.log_entry();
    }
    let dir = trainer.save_checkpoint(&root)?;
    let _ = writeln!(log, "checkpoint {}", dir.display());
    let sidecar = trainer.finish(out, held_out.as_ref(), log)?;
    let _ = writeln!(
        log,
        "wrote {} (+ {}, {})",
        out.display(),
        artifact::encoder_path(out).display(),
        artifact::sidecar_path(out).display()
    );
    Ok(sidecar)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::data::Image;
    use super::super::eval::EvalOptions;
    use super::*;
    use crate::attack::diff::EotRng;
    use burn::tensor::{Device, TensorData};

    /// Smooth random-ish synthetic images (sums of a few sinusoids).
    pub(crate) fn synthetic_set(n: usize, size: usize, seed: u64) -> ImageSet {
        let mut rng = EotRng::new(seed);
        let images = (0..n)
            .map(|i| {
                let f: Vec<f64> = (0..12).map(|_| rng.range(0.5, 4.0)).collect();
                let ph: Vec<f64> = (0..12)
                    .map(|_| rng.range(0.0, std::f64::consts::TAU))
                    .collect();
                let img = image::RgbImage::from_fn(size as u32, size as u32, |x, y| {
                    let (u, v) = (x as f64 / size as f64, y as f64 / size as f64);
                    image::Rgb(std::array::from_fn(|c| {
                        let k = 4 * c;
                        let val = 0.5
                            + 0.2 * (f[k] * std::f64::consts::TAU * u + ph[k]).sin()
                            + 0.15 * (f[k + 1] * std::f64::consts::TAU * v + ph[k + 1]).sin()
                            + 0.1 * (f[k + 2] * std::f64::consts::TAU * (u + v) + ph[k + 2]).cos();
                        (val.clamp(0.0, 1.0) * 255.0) as u8
                    }))
                });
                Image::from_rgb8(format!("syn{i}.png"), &img)
            })
            .collect();
        ImageSet { images }
    }

    pub(crate) fn tiny_config() -> TrainConfig {
        TrainConfig {
            bits: 4,
            crop: 32,
            batch_size: 8,
            steps: 40,
            lr: 1e-2,
            lr_min_fraction: 1.0,
            image_weight: 0.0,
            strength: 0.3,
            warmup_steps: 1000,
            ramp_steps: 0,
            attack_groups: 2,
            min_scale: 1.0,
            seed: 7,
            checkpoint_every: 0,
            log_every: 0,
            decoder_channels: 8,
            decoder_depth: 1,
            encoder_channels: 8,
            encoder_blocks: 1,
            encoder_levels: 1,
            encoder_tile: 8,
            whitening_samples: 32,
            final_eval: false,
            eval: EvalOptions {
                size: 32,
                repeats: 1,
                ..EvalOptions::default()
            },
            ..TrainConfig::default()
        }
    }

    /// Trains `config` for its steps on `set` and writes the artifact (with its encoder) to
    /// `out`, without the held-out evaluation.
    pub(super) fn tiny_artifact(config: TrainConfig, set: ImageSet, out: &Path) -> Trainer {
        let mut t = Trainer::new(config, set).unwrap();
        while !t.done() {
            t.step().unwrap();
        }
        t.finish(out, None, &mut Vec::new()).unwrap();
        t
    }

    #[test]
    fn bce_matches_the_formula() {
        let d = Device::flex();
        let z = Tensor::<2>::from_data(TensorData::new(vec![2.0f32, -1.0, 0.0, 30.0], [2, 2]), &d);
        let m = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 1.0, 0.0, 0.0], [2, 2]), &d);
        let got = bce_with_logits(z, m).into_scalar::<f32>() as f64;
        let sp = |x: f64| (1.0 + x.exp()).ln();
        let want = (sp(2.0) - 2.0 + sp(-1.0) + 1.0 + sp(0.0) + 30.0) / 4.0;
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
    }
}
