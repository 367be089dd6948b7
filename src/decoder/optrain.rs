//! Decoder training with the optimiser as the encoder (`splatmark decoder train-opt`).
//!
//! The watermark is written into a scene by *optimisation* through the frozen decoder (the 3D
//! finetuning), so the decoder is trained for exactly that use, without an encoder network.
//! Each step k (batch of B crops x, random messages m, U unmarked crops x_u):
//!
//! 1. **Write**: `δ = optimise_marks(D_frozen, x, m)` ([`super::probe::optimise_marks`]) —
//!    `inner_steps` steps of L2-projected gradient descent through the current decoder under the
//!    EOT attacks (perspective tilts included), at the PSNR bound of step k, which ramps from
//!    `psnr_start_db` to `psnr_end_db` over `psnr_ramp_steps` (a strong signal first, as the
//!    HiDDeN / StegaStamp warm-ups advise). x_w = round₈(clamp(x + δ)).
//! 2. **Read**: with a fresh attack t per group (probability p_k, ramped in after
//!    `attack_warmup` steps over `attack_ramp` steps to `attack_prob_max`),
//!    `loss = BCE(D(t(x_w)), m) + λ_u · mean(D(t(x_u))²)`: marked crops decode to their message,
//!    unmarked crops decode to logits near 0 (no bias, and small natural variance — the
//!    decoder must react to the optimiser's changes, not to content).
//! 3. Adam on the decoder only.
//!
//! The decoder is [`Norm::Group`] by default (GroupNorm + GELU: the same computation in training
//! and inference, so the unmarked term cannot be gamed the way the BatchNorm run 2 gamed it).
//! Checkpoints (`OUT.ckpt/step-N/{net.bpk, optim.bpk, state.json}`) resume bit-exactly: step k
//! draws everything from `step_seed(seed, k)`, the Adam state is restored.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::artifact::{
    self, DecoderArch, FORMAT, Sidecar, TrainingRecord, WatermarkModel, WeightsError,
};
use super::data::ImageSet;
use super::model::{HiddenDecoder, HiddenDecoderConfig, Norm};
use super::probe::{OptEmbedOptions, ProbeOptions, ProbeReport, optimise_marks, view_eot};
use super::train::{
    DeviceChoice, LogEntry, TrainError, bce_with_logits, list_checkpoints, psnr_from_mse, step_seed,
};
use crate::attack::diff::{
    DiffAttack, EotConfig, EotRng, random_composition, straight_through_round,
};

/// Configuration of an optimiser-as-encoder run (stored in checkpoints and the sidecar).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OptTrainConfig {
    pub bits: usize,
    /// Side of the square training crops (pixels).
    pub crop: usize,
    /// Marked crops per step.
    pub batch_size: usize,
    /// Unmarked crops per step.
    pub unmarked: usize,
    pub steps: usize,
    pub lr: f64,
    /// Cosine decay to `lr · lr_min_fraction`.
    pub lr_min_fraction: f64,
    /// PSNR bound of the writes at step 0 …
    pub psnr_start_db: f64,
    /// … and after the ramp.
    pub psnr_end_db: f64,
    pub psnr_ramp_steps: usize,
    /// Gradient steps of each write.
    pub inner_steps: usize,
    /// Steps without attacks at the start.
    pub attack_warmup: usize,
    /// Steps over which the attack probability ramps to `attack_prob_max`.
    pub attack_ramp: usize,
    pub attack_prob_max: f64,
    /// Attack distribution (writes and reads).
    pub eot: EotConfig,
    /// Groups of the read pass, each with its own attack.
    pub attack_groups: usize,
    /// λ_u of the unmarked term.
    pub unmarked_weight: f64,
    /// Smallest random downscale of a crop's source window.
    pub min_scale: f32,
    pub seed: u64,
    pub checkpoint_every: usize,
    pub keep_checkpoints: usize,
    pub log_every: usize,
    pub device: DeviceChoice,
    pub decoder_channels: usize,
    pub decoder_depth: usize,
    pub norm: Norm,
    /// Convolution kernel of the decoder (3; 1 = per-pixel).
    pub kernel: usize,
    /// Gain on the decoder's input band.
    pub input_gain: f64,
    /// Colour-Fourier features instead of convolutions (0 = off; [`HiddenDecoderConfig::fourier`]).
    pub fourier: usize,
    /// Standard deviation of their frequencies.
    pub fourier_scale: f64,
    /// Their dark cut-off ([`HiddenDecoderConfig::fourier_dark`]).
    pub fourier_dark: f64,
    /// The probe run on the held-out images at the end (stored in the sidecar); `None` skips it.
    pub final_probe: Option<ProbeOptions>,
    /// Fit a Stable-Signature whitening of the logits on this many clean training crops at the
    /// end (0 = none): unmarked logits then have zero mean and identity covariance, so no bit
    /// starts stuck at the decoder's favourite value.
    pub whitening_samples: usize,
}

impl Default for OptTrainConfig {
    fn default() -> Self {
        Self {
            bits: 32,
            crop: 128,
            batch_size: 12,
            unmarked: 4,
            steps: 6000,
            lr: 1e-3,
            lr_min_fraction: 0.05,
            psnr_start_db: 30.0,
            psnr_end_db: 40.0,
            psnr_ramp_steps: 3000,
            inner_steps: 3,
            attack_warmup: 300,
            attack_ramp: 1500,
            attack_prob_max: 0.8,
            eot: view_eot(),
            attack_groups: 2,
            unmarked_weight: 1.0,
            min_scale: 0.4,
            seed: 0,
            checkpoint_every: 100,
            keep_checkpoints: 2,
            log_every: 10,
            device: DeviceChoice::Flex,
            decoder_channels: 32,
            decoder_depth: 5,
            norm: Norm::Group,
            kernel: 3,
            input_gain: 1.0,
            fourier: 0,
            fourier_scale: 8.0,
            fourier_dark: 0.1,
            final_probe: Some(ProbeOptions {
                psnrs: vec![36.0, 38.0, 40.0],
                repeats: 1,
                ..ProbeOptions::default()
            }),
            whitening_samples: 512,
        }
    }
}

impl OptTrainConfig {
    /// Checks the values that would otherwise fail later.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |what: &str| Err(TrainError::Config(what.to_string()));
        if self.bits == 0 || self.bits > 256 {
            return bad("bits must be in 1..=256");
        }
        if self.crop < 32 {
            return bad("crop must be at least 32 pixels");
        }
        if self.batch_size == 0 || self.attack_groups == 0 {
            return bad("batch size and attack groups must be positive");
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr must be positive");
        }
        if !(0.0..=1.0).contains(&self.lr_min_fraction)
            || !(0.0..=1.0).contains(&self.attack_prob_max)
        {
            return bad("lr_min_fraction and attack_prob_max must be in [0, 1]");
        }
        if !(self.psnr_start_db > 10.0 && self.psnr_end_db > 10.0 && self.psnr_end_db < 80.0) {
            return bad("PSNR bounds must be in (10, 80) dB");
        }
        if !(self.unmarked_weight >= 0.0 && self.unmarked_weight.is_finite()) {
            return bad("unmarked_weight must be ≥ 0");
        }
        if !(self.min_scale > 0.0 && self.min_scale <= 1.0) {
            return bad("min_scale must be in (0, 1]");
        }
        if self.decoder_channels == 0 || self.inner_steps == 0 {
            return bad("decoder channels and inner steps must be positive");
        }
        if self.eot.min_steps > self.eot.max_steps {
            return bad("eot.min_steps > eot.max_steps");
        }
        Ok(())
    }

    /// The decoder architecture.
    pub fn decoder_config(&self) -> HiddenDecoderConfig {
        HiddenDecoderConfig::new(self.bits)
            .with_channels(self.decoder_channels)
            .with_depth(self.decoder_depth)
            .with_norm(self.norm)
            .with_kernel(self.kernel)
            .with_input_gain(self.input_gain)
            .with_fourier(self.fourier)
            .with_fourier_scale(self.fourier_scale)
            .with_fourier_dark(self.fourier_dark)
            .with_fourier_seed(self.seed)
    }

    /// PSNR bound of step `k`.
    pub fn psnr_at(&self, k: usize) -> f64 {
        let t = if self.psnr_ramp_steps == 0 {
            1.0
        } else {
            (k as f64 / self.psnr_ramp_steps as f64).min(1.0)
        };
        self.psnr_start_db + t * (self.psnr_end_db - self.psnr_start_db)
    }

    /// Attack probability of step `k`.
    pub fn attack_probability(&self, k: usize) -> f64 {
        if k < self.attack_warmup {
            0.0
        } else if self.attack_ramp == 0 {
            self.attack_prob_max
        } else {
            ((k - self.attack_warmup + 1) as f64 / self.attack_ramp as f64).min(1.0)
                * self.attack_prob_max
        }
    }

    /// Learning rate of step `k` (cosine decay).
    pub fn lr_at(&self, k: usize) -> f64 {
        let t = if self.steps > 1 {
            (k as f64 / (self.steps - 1) as f64).min(1.0)
        } else {
            0.0
        };
        self.lr
            * (self.lr_min_fraction
                + (1.0 - self.lr_min_fraction) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
    }
}

/// Numbers of one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OptStepStats {
    pub step: usize,
    pub loss: f64,
    pub bce: f64,
    /// mean(z_u²) of the unmarked crops.
    pub unmarked_sq: f64,
    /// MSE of the writes (8-bit marked vs cover).
    pub image_mse: f64,
    /// Bit accuracy of the attacked marked crops.
    pub bit_accuracy: f64,
    pub attack_probability: f64,
}

/// What a checkpoint's `state.json` holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OptCheckpointState {
    pub version: u32,
    pub step: usize,
    pub config: OptTrainConfig,
    pub wall_s: f64,
    pub history: Vec<LogEntry>,
}

/// A run in memory.
pub struct OptTrainer {
    pub config: OptTrainConfig,
    device: Device,
    pub decoder: HiddenDecoder,
    optim: burn::optim::ModuleOptimizer,
    pub step: usize,
    train: ImageSet,
    wall_before: f64,
    session_start: Instant,
    session_first_step: usize,
    pub history: Vec<LogEntry>,
    window: Vec<OptStepStats>,
    window_start: Instant,
    /// The command line and data, for the record.
    pub command: Option<String>,
    pub data: Option<String>,
}

fn record_err(path: &Path, e: impl std::fmt::Display) -> TrainError {
    TrainError::Record {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

impl OptTrainer {
    /// A fresh run.
    pub fn new(config: OptTrainConfig, train: ImageSet) -> Result<Self, TrainError> {
        config.validate()?;
        train.check_crop(config.crop)?;
        let base = config.device.device();
        base.seed(config.seed);
        let device = base.autodiff();
        let decoder = config.decoder_config().init(&device);
        Ok(Self::assemble(
            config,
            device,
            decoder,
            AdamConfig::new().init(),
            0,
            train,
            0.0,
            Vec::new(),
        ))
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        config: OptTrainConfig,
        device: Device,
        decoder: HiddenDecoder,
        optim: burn::optim::ModuleOptimizer,
        step: usize,
        train: ImageSet,
        wall_before: f64,
        history: Vec<LogEntry>,
    ) -> Self {
        Self {
            config,
            device,
            decoder,
            optim,
            step,
            train,
            wall_before,
            session_start: Instant::now(),
            session_first_step: step,
            history,
            window: Vec::new(),
            window_start: Instant::now(),
            command: None,
            data: None,
        }
    }

    /// Continues from checkpoint folder `dir`; only `steps`, `log_every`, `checkpoint_every`
    /// and `keep_checkpoints` are taken from `adjust`.
    pub fn resume(
        dir: &Path,
        train: ImageSet,
        adjust: impl FnOnce(&OptTrainConfig) -> OptTrainConfig,
    ) -> Result<Self, TrainError> {
        let (state, net_bytes, optim) = super::train::read_checkpoint::<OptCheckpointState>(dir)?;
        let mut config = state.config.clone();
        let wanted = adjust(&config);
        config.steps = wanted.steps;
        config.log_every = wanted.log_every;
        config.checkpoint_every = wanted.checkpoint_every;
        config.keep_checkpoints = wanted.keep_checkpoints;
        config.validate()?;
        train.check_crop(config.crop)?;
        let device = config.device.device().autodiff();
        let decoder = artifact::from_burnpack(config.decoder_config().init(&device), net_bytes)
            .map_err(|e| record_err(&dir.join("net.bpk"), e))?;
        Ok(Self::assemble(
            config,
            device,
            decoder,
            optim,
            state.step,
            train,
            state.wall_s,
            state.history,
        ))
    }

    pub fn done(&self) -> bool {
        self.step >= self.config.steps
    }

    pub fn wall_s(&self) -> f64 {
        self.wall_before + self.session_start.elapsed().as_secs_f64()
    }

    /// One step (module docs).
    pub fn step(&mut self) -> Result<OptStepStats, TrainError> {
        let c = self.config.clone();
        let k = self.step;
        let mut rng = EotRng::new(step_seed(c.seed, k));
        let (b, u, l, s) = (c.batch_size, c.unmarked, c.bits, c.crop);
        let pixels = self
            .train
            .sample_batch(&mut rng, b + u, s, c.min_scale, true);
        let bits: Vec<f32> = (0..b * l).map(|_| (rng.next_u64() >> 63) as f32).collect();
        let all = Tensor::<4>::from_data(TensorData::new(pixels, [b + u, 3, s, s]), &self.device);
        let all = straight_through_round(all.mul_scalar(255.0))
            .div_scalar(255.0)
            .detach();
        let cover = all.clone().narrow(0, 0, b);
        let message = Tensor::<2>::from_data(TensorData::new(bits.clone(), [b, l]), &self.device);
        let p = c.attack_probability(k);

        // 1. Write through the current decoder. Not through a `freeze()`d clone: burn's
        // parameters share their require-grad state between clones, so freezing a clone froze
        // the live decoder too. The write's backward pass also computes parameter gradients,
        // which are dropped.
        let forward = |x: Tensor<4>| self.decoder.forward(x);
        let write = OptEmbedOptions {
            psnr_db: c.psnr_at(k),
            iterations: c.inner_steps,
            levels: 2,
            eot: c.eot.clone(),
            attack_prob: p,
        };
        let change = optimise_marks(&forward, cover.clone(), message.clone(), &write, &mut rng)?;
        let marked = cover.clone().add(change).clamp(0.0, 1.0);
        let marked = straight_through_round(marked.mul_scalar(255.0))
            .div_scalar(255.0)
            .detach();
        let mse = f64::from(
            marked
                .clone()
                .sub(cover)
                .square()
                .mean()
                .into_scalar::<f32>(),
        );

        // 2. Read with fresh attacks; unmarked crops share each group's attack and pass.
        let groups = c.attack_groups.clamp(1, b);
        let unmarked = all.narrow(0, b, u);
        let (mut zm, mut zu) = (Vec::new(), Vec::new());
        let (mut start, mut ustart) = (0, 0);
        for g in 0..groups {
            let len = b / groups + usize::from(g < b % groups);
            let ulen = u / groups + usize::from(g < u % groups);
            let mut parts = vec![marked.clone().narrow(0, start, len)];
            if ulen > 0 {
                parts.push(unmarked.clone().narrow(0, ustart, ulen));
            }
            start += len;
            ustart += ulen;
            let attack = if p > 0.0 && rng.uniform() < p {
                random_composition(&c.eot, &mut rng)
            } else {
                DiffAttack::Chain(Vec::new())
            };
            let z = self.decoder.forward(attack.apply(Tensor::cat(parts, 0))?);
            zm.push(z.clone().narrow(0, 0, len));
            if ulen > 0 {
                zu.push(z.narrow(0, len, ulen));
            }
        }
        let zm = Tensor::cat(zm, 0);
        let bce = bce_with_logits(zm.clone(), message);
        let mut loss = bce.clone();
        let mut usq = None;
        if !zu.is_empty() && c.unmarked_weight > 0.0 {
            let sq = Tensor::cat(zu, 0).square().mean();
            loss = loss.add(sq.clone().mul_scalar(c.unmarked_weight));
            usq = Some(sq);
        }
        let grads = GradientsParams::from_grads(loss.backward(), &self.decoder);
        self.decoder = self.optim.step(c.lr_at(k), self.decoder.clone(), grads);

        let z: Vec<f32> = zm.detach().try_into_vec_as::<f32>().unwrap_or_default();
        let correct = z
            .iter()
            .zip(&bits)
            .filter(|&(&z, &m)| (z > 0.0) == (m > 0.5))
            .count();
        let scalar = |t: Tensor<1>| f64::from(t.detach().into_scalar::<f32>());
        let loss = scalar(loss);
        if !loss.is_finite() {
            return Err(TrainError::Diverged(k + 1));
        }
        self.step += 1;
        let stats = OptStepStats {
            step: self.step,
            loss,
            bce: scalar(bce),
            unmarked_sq: usq.map_or(0.0, scalar),
            image_mse: mse,
            bit_accuracy: correct as f64 / (b * l) as f64,
            attack_probability: p,
        };
        self.window.push(stats);
        Ok(stats)
    }

    /// Closes the logging window (averages) and appends it to the history. `loss` holds the
    /// total loss, `bce` the marked BCE; the unmarked term is in the progress line.
    pub fn log_entry(&mut self) -> Option<(LogEntry, f64)> {
        let n = self.window.len();
        if n == 0 {
            return None;
        }
        let mean = |f: fn(&OptStepStats) -> f64| self.window.iter().map(f).sum::<f64>() / n as f64;
        let mse = mean(|s| s.image_mse);
        let usq = mean(|s| s.unmarked_sq);
        let secs = self.window_start.elapsed().as_secs_f64().max(1e-9);
        let entry = LogEntry {
            step: self.step,
            loss: mean(|s| s.loss),
            bce: mean(|s| s.bce),
            image_mse: mse,
            psnr_db: psnr_from_mse(mse),
            bit_accuracy: mean(|s| s.bit_accuracy),
            attack_probability: mean(|s| s.attack_probability),
            images_per_s: (n * self.config.batch_size) as f64 / secs,
        };
        self.window.clear();
        self.window_start = Instant::now();
        self.history.push(entry.clone());
        Some((entry, usq))
    }

    /// A progress line with the ETA from this session's pace.
    pub fn progress_line(&self, entry: &LogEntry, unmarked_sq: f64) -> String {
        let done = self.step - self.session_first_step;
        let elapsed = self.session_start.elapsed().as_secs_f64();
        let eta = if done > 0 {
            elapsed / done as f64 * self.config.steps.saturating_sub(self.step) as f64
        } else {
            0.0
        };
        format!(
            "step {}/{} | loss {:.4} (bce {:.4}, unmarked z² {:.3}) | writes {:.1} dB | bit acc {:.3} | attack p {:.2} | {:.1} img/s | elapsed {} | ETA {}",
            self.step,
            self.config.steps,
            entry.loss,
            entry.bce,
            unmarked_sq,
            entry.psnr_db,
            entry.bit_accuracy,
            entry.attack_probability,
            entry.images_per_s,
            super::train::hms(self.wall_s()),
            super::train::hms(eta),
        )
    }

    /// Writes a checkpoint under `root` atomically and prunes old ones.
    pub fn save_checkpoint(&self, root: &Path) -> Result<PathBuf, TrainError> {
        let net_path = root.join("net.bpk");
        let net =
            artifact::to_burnpack(self.decoder.clone()).map_err(|e| record_err(&net_path, e))?;
        let optim_path = root.join("optim.bpk");
        let optim = self
            .optim
            .into_bytes()
            .map_err(|e| record_err(&optim_path, e))?;
        let state = OptCheckpointState {
            version: 1,
            step: self.step,
            config: self.config.clone(),
            wall_s: self.wall_s(),
            history: self.history.clone(),
        };
        let json = serde_json::to_vec_pretty(&state).expect("state serialises");
        super::train::write_checkpoint(
            root,
            self.step,
            &[
                ("net.bpk", &net),
                ("optim.bpk", &optim[..]),
                ("state.json", &json),
            ],
            self.config.keep_checkpoints,
        )
    }

    /// The trained decoder as an inference model on `device` (decoder-only artifact).
    pub fn model(&self, device: &Device) -> Result<WatermarkModel, WeightsError> {
        let c = &self.config;
        let bytes =
            artifact::to_burnpack(self.decoder.valid()).map_err(|e| WeightsError::Record {
                path: PathBuf::from("<training>"),
                message: e.to_string(),
            })?;
        let decoder = artifact::from_burnpack(c.decoder_config().init(device), bytes)
            .map_err(|e| WeightsError::Record {
                path: PathBuf::from("<training>"),
                message: e.to_string(),
            })?
            .frozen();
        Ok(WatermarkModel {
            sidecar: Sidecar {
                format: FORMAT.into(),
                bits: c.bits,
                decoder: DecoderArch::from(&c.decoder_config()),
                encoder: None,
                strength: 0.0,
                whitening: None,
                train_config: None,
                record: Some(TrainingRecord {
                    steps: self.step,
                    wall_s: self.wall_s(),
                    images_per_s: self.history.last().map(|e| e.images_per_s),
                    final_log: self.history.last().cloned(),
                    command: self.command.clone(),
                    data: self.data.clone(),
                    ..TrainingRecord::default()
                }),
                opt_train_config: Some(c.clone()),
                probe: None,
            },
            decoder,
            encoder: None,
            reference: None,
            projection: None,
            file_digest: None,
        })
    }
}

/// Options of [`run`].
pub struct OptRunOptions<'a> {
    pub out: &'a Path,
    pub resume: bool,
    /// Held-out images for the final probe (square, one size).
    pub probe_images: Vec<image::RgbImage>,
    pub command: Option<String>,
    pub data: Option<String>,
}

/// Trains (or resumes) to the configured steps, checkpointing, then writes the artifact with
/// the final probe in its record.
pub fn run(
    config: OptTrainConfig,
    train: ImageSet,
    opts: OptRunOptions<'_>,
    log: &mut dyn Write,
) -> Result<Option<ProbeReport>, TrainError> {
    let root = super::train::checkpoint_root(opts.out);
    let mut t = if opts.resume {
        let (_, dir) = list_checkpoints(&root).pop().ok_or_else(|| {
            TrainError::Config(format!("--resume: no checkpoint under {}", root.display()))
        })?;
        let _ = writeln!(log, "resuming from {}", dir.display());
        let wanted = config.clone();
        OptTrainer::resume(&dir, train, move |_| wanted)?
    } else {
        OptTrainer::new(config, train)?
    };
    t.command = opts.command;
    t.data = opts.data;
    while !t.done() {
        t.step()?;
        let (log_every, checkpoint_every) = (t.config.log_every, t.config.checkpoint_every);
        if log_every > 0
            && t.step % log_every == 0
            && let Some((e, usq)) = t.log_entry()
        {
            let _ = writeln!(log, "{}", t.progress_line(&e, usq));
        }
        if checkpoint_every > 0 && t.step % checkpoint_every == 0 {
            t.save_checkpoint(&root)?;
        }
    }
    t.save_checkpoint(&root)?;
    let plain = t.config.device.device();
    let ad = plain.autodiff();
    let mut model = t.model(&ad)?;
    if t.config.whitening_samples > 0 {
        let c = &t.config;
        let mut rng = EotRng::new(step_seed(c.seed ^ 0x5748_4954, 0));
        let mut logits = Vec::new();
        let mut left = c.whitening_samples;
        while left > 0 {
            let n = left.min(32);
            let px = t.train.sample_batch(&mut rng, n, c.crop, c.min_scale, true);
            let x = Tensor::<4>::from_data(TensorData::new(px, [n, 3, c.crop, c.crop]), &ad);
            let x = straight_through_round(x.mul_scalar(255.0)).div_scalar(255.0);
            logits.extend(model.raw_logits(x));
            left -= n;
        }
        model.sidecar.whitening = Some(
            super::model::Whitening::fit(&logits)
                .map_err(|e| TrainError::Config(format!("whitening: {e}")))?,
        );
        let _ = writeln!(log, "whitening fitted on {} crops", logits.len());
    }
    let report = match (&t.config.final_probe, opts.probe_images.is_empty()) {
        (Some(p), false) => {
            let _ = writeln!(
                log,
                "probing on {} held-out images…",
                opts.probe_images.len()
            );
            Some(super::probe::probe(&model, &opts.probe_images, p, &ad)?)
        }
        _ => None,
    };
    model.sidecar.probe = report.clone();
    model.save(opts.out)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::train::tests::synthetic_set;

    fn tiny() -> OptTrainConfig {
        OptTrainConfig {
            bits: 4,
            crop: 32,
            batch_size: 2,
            unmarked: 1,
            steps: 4,
            inner_steps: 2,
            attack_warmup: 1,
            attack_ramp: 1,
            decoder_channels: 8,
            decoder_depth: 1,
            checkpoint_every: 0,
            log_every: 0,
            keep_checkpoints: 2,
            final_probe: None,
            whitening_samples: 0,
            ..OptTrainConfig::default()
        }
    }

    fn outputs(t: &OptTrainer, set: &ImageSet) -> Vec<f32> {
        let mut rng = EotRng::new(5);
        let px = set.sample_batch(&mut rng, 2, 32, 1.0, false);
        let x = Tensor::<4>::from_data(TensorData::new(px, [2, 3, 32, 32]), &t.device);
        t.decoder
            .valid()
            .forward(x.without_autodiff())
            .try_into_vec_as()
            .unwrap()
    }

    #[test]
    fn resume_continues_exactly_and_the_schedules_hold() {
        let c = tiny();
        assert_eq!(c.psnr_at(0), c.psnr_start_db);
        assert_eq!(c.psnr_at(10_000), c.psnr_end_db);
        assert_eq!(c.attack_probability(0), 0.0);
        assert!((c.attack_probability(5) - c.attack_prob_max).abs() < 1e-12);
        assert!(
            OptTrainConfig {
                psnr_end_db: 5.0,
                ..tiny()
            }
            .validate()
            .is_err()
        );

        let set = synthetic_set(3, 48, 7);
        let dir = tempfile::tempdir().unwrap();
        let first = OptTrainer::new(c.clone(), set.clone()).unwrap();
        let start = first.save_checkpoint(&dir.path().join("start")).unwrap();
        let mut straight = OptTrainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        let mut split = OptTrainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        while !straight.done() {
            let s = straight.step().unwrap();
            assert!(s.loss.is_finite() && (0.0..=1.0).contains(&s.bit_accuracy));
        }
        let root = dir.path().join("ckpt");
        for _ in 0..2 {
            split.step().unwrap();
        }
        let ckpt = split.save_checkpoint(&root).unwrap();
        let mut resumed = OptTrainer::resume(&ckpt, set.clone(), |c| c.clone()).unwrap();
        assert_eq!(resumed.step, 2);
        while !resumed.done() {
            resumed.step().unwrap();
        }
        let (a, b) = (outputs(&straight, &set), outputs(&resumed, &set));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-4 * (1.0 + x.abs()), "{a:?} vs {b:?}");
        }
        // Training moved the decoder (the comparison above is not of two untouched copies).
        let c0 = outputs(&first, &set);
        let moved: f32 = a.iter().zip(&c0).map(|(x, y)| (x - y).abs()).sum();
        assert!(moved > 1e-5, "no step changed the decoder");
    }
}
