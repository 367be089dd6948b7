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

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::log_sigmoid;
use burn::tensor::{Bytes, Device, DeviceKind, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::artifact::{self, Sidecar, TrainingRecord, WatermarkModel, WhiteningReport};
use super::data::{ImageSet, Split};
use super::encoder::{Encoder, TiledEncoderConfig};
use super::eval::{self, EvalOptions};
use super::model::{HiddenDecoder, HiddenDecoderConfig, HiddenEncoderConfig, Whitening};
use crate::attack::diff::{
    DiffAttack, DiffAttackError, EotConfig, EotRng, random_composition, straight_through_round,
};

/// Where training runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceChoice {
    /// burn's `flex` CPU backend (the fast CPU path, see `../shared/notes/toolchain.md`).
    #[default]
    Flex,
    /// burn-wgpu on the default adapter (a GPU where present; lavapipe on a CPU-only machine,
    /// which works but is slower than `flex`).
    Wgpu,
}

impl DeviceChoice {
    /// The (non-autodiff) device.
    pub fn device(self) -> Device {
        match self {
            Self::Flex => Device::flex(),
            Self::Wgpu => Device::wgpu(DeviceKind::DefaultDevice),
        }
    }
}

/// Whether the final decoder gets a [`Whitening`] of its logits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WhiteningChoice {
    /// Fit the whitening and the centering (μ only), and keep one only if it helps: it must
    /// lower the bit bias of unmarked held-out crops (mean over bits of |2·P(bit = 1) − 1|; a
    /// biased bit makes the binomial false-positive statistics optimistic) **and** cost at most
    /// 0.5 percentage points of bit accuracy on watermarked held-out crops (with the trained
    /// encoder, clean and attacked); of two that pass, the one with the lower bias.
    #[default]
    Auto,
    /// Always apply the whitening.
    Always,
    /// Always apply the centering.
    Center,
    /// Never apply either.
    Never,
}

/// Which encoder is trained with the decoder (see [`super::encoder`](mod@super::encoder)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EncoderKind {
    /// HiDDeN's encoder (message as constant planes): slow to train.
    Hidden,
    /// Message mapped to a tiled spatial pattern: trains far faster.
    #[default]
    Tiled,
}

/// Configuration of a training run (stored in checkpoints and in the artifact's sidecar).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Message length L.
    pub bits: usize,
    /// Side of the square training crops, in pixels (the decoder reads its 2-level DWT LL band,
    /// so 128 px → 32 × 32).
    pub crop: usize,
    /// Crops per step.
    pub batch_size: usize,
    /// Total optimisation steps.
    pub steps: usize,
    /// Adam learning rate at step 0.
    pub lr: f64,
    /// The learning rate decays (cosine) to `lr · lr_min_fraction` at the last step; 1 = constant.
    pub lr_min_fraction: f64,
    /// λ of the image loss `λ · MSE(watermarked, cover)` (images in [0, 1]); it ramps in with the
    /// attacks (× the attack probability of the step).
    pub image_weight: f64,
    /// Embedding strength: watermarked = cover + strength · residual, residual ∈ (−1, 1).
    pub strength: f64,
    /// Attack distribution p(t) after the warm-up.
    pub eot: EotConfig,
    /// Steps without any attack at the start.
    pub warmup_steps: usize,
    /// Steps over which the probability of attacking a group ramps from 0 to 1 after the warm-up.
    pub ramp_steps: usize,
    /// Probability that a group is attacked once the ramp is complete (1 = always; below 1 a
    /// share of the groups stays clean, which the decoder then also learns to read).
    pub attack_prob_max: f64,
    /// Groups the batch is split into, each with its own attack draw.
    pub attack_groups: usize,
    /// Unmarked crops per step whose logits are pulled towards 0 (BCE against ½: "no
    /// watermark decodes to coin tosses"), which keeps the decoder's bits unbiased on natural
    /// images; 0 = off (the HiDDeN recipe). The loss ramps in with the attacks.
    pub unmarked_crops: usize,
    /// Weight of that unmarked loss.
    pub unmarked_weight: f64,
    /// Smallest random downscale of a crop's source window (1 = no downscale).
    pub min_scale: f32,
    /// Seed of every random draw (weights, data, messages, attacks).
    pub seed: u64,
    /// Checkpoint every this many steps (0 = only at the end).
    pub checkpoint_every: usize,
    /// Checkpoints kept.
    pub keep_checkpoints: usize,
    /// A progress line every this many steps (0 = none).
    pub log_every: usize,
    /// Training device.
    pub device: DeviceChoice,
    /// Decoder hidden channels.
    pub decoder_channels: usize,
    /// Decoder `ConvBNReLU(C→C)` blocks.
    pub decoder_depth: usize,
    /// Encoder design.
    pub encoder: EncoderKind,
    /// Side of the tiled encoder's message tile (pixels at the encoder's resolution).
    pub encoder_tile: usize,
    /// Encoder hidden channels.
    pub encoder_channels: usize,
    /// Encoder blocks before the message is concatenated.
    pub encoder_blocks: usize,
    /// The encoder runs at 1/2^levels resolution, its residual upsampled (bilinear): see
    /// [`artifact::encoder_residual`]. 2 = the resolution of the decoder's LL band.
    pub encoder_levels: usize,
    /// Whitening of the final decoder.
    pub whitening: WhiteningChoice,
    /// Clean training crops the whitening is fitted on.
    pub whitening_samples: usize,
    /// Run the held-out evaluation at the end and store it in the sidecar.
    pub final_eval: bool,
    /// Options of that evaluation.
    pub eval: EvalOptions,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            bits: 32,
            crop: 128,
            batch_size: 16,
            steps: 10_000,
            lr: 3e-3,
            lr_min_fraction: 0.05,
            image_weight: 10.0,
            strength: 0.1,
            eot: EotConfig::default(),
            warmup_steps: 1500,
            ramp_steps: 3000,
            attack_prob_max: 1.0,
            attack_groups: 2,
            unmarked_crops: 0,
            unmarked_weight: 1.0,
            min_scale: 0.4,
            seed: 0,
            checkpoint_every: 250,
            keep_checkpoints: 3,
            log_every: 25,
            device: DeviceChoice::Flex,
            decoder_channels: 32,
            decoder_depth: 5,
            encoder: EncoderKind::Tiled,
            encoder_tile: 16,
            encoder_channels: 32,
            encoder_blocks: 2,
            encoder_levels: 2,
            whitening: WhiteningChoice::Auto,
            whitening_samples: 512,
            final_eval: true,
            eval: EvalOptions::default(),
        }
    }
}

impl TrainConfig {
    /// Default configuration for `bits`.
    pub fn for_bits(bits: usize) -> Self {
        Self {
            bits,
            ..Self::default()
        }
    }

    /// Checks the values that would otherwise fail later.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |what: &str| Err(TrainError::Config(what.to_string()));
        if self.bits == 0 || self.bits > 256 {
            return bad("bits must be in 1..=256");
        }
        if self.crop < 8 {
            return bad("crop must be at least 8 pixels");
        }
        if self.batch_size == 0 {
            return bad("batch size must be positive");
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr must be positive");
        }
        if !(self.lr_min_fraction >= 0.0 && self.lr_min_fraction <= 1.0) {
            return bad("lr_min_fraction must be in [0, 1]");
        }
        if !(self.image_weight >= 0.0 && self.image_weight.is_finite()) {
            return bad("image weight must be ≥ 0");
        }
        if !(self.strength > 0.0 && self.strength <= 1.0) {
            return bad("strength must be in (0, 1]");
        }
        if !(self.unmarked_weight >= 0.0 && self.unmarked_weight.is_finite()) {
            return bad("unmarked_weight must be ≥ 0");
        }
        if !(self.attack_prob_max >= 0.0 && self.attack_prob_max <= 1.0) {
            return bad("attack_prob_max must be in [0, 1]");
        }
        if !(self.min_scale > 0.0 && self.min_scale <= 1.0) {
            return bad("min_scale must be in (0, 1]");
        }
        if self.encoder_levels > 4 || self.crop < 4 << self.encoder_levels {
            return bad("encoder_levels must be ≤ 4 and leave at least 4 px of the crop");
        }
        if self.decoder_channels == 0
            || self.encoder_channels == 0
            || self.encoder_blocks == 0
            || self.encoder_tile == 0
        {
            return bad("channels and encoder blocks must be positive");
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
    }

    /// A freshly initialised encoder of the configured design.
    pub fn init_encoder(&self, device: &Device) -> Encoder {
        match self.encoder {
            EncoderKind::Hidden => Encoder::Hidden(
                HiddenEncoderConfig::new(self.bits)
                    .with_channels(self.encoder_channels)
                    .with_blocks(self.encoder_blocks)
                    .init(device),
            ),
            EncoderKind::Tiled => Encoder::Tiled(
                TiledEncoderConfig::new(self.bits)
                    .with_channels(self.encoder_channels)
                    .with_blocks(self.encoder_blocks)
                    .with_tile(self.encoder_tile.max(1))
                    .with_seed(self.seed)
                    .init(device),
            ),
        }
    }

    /// The ramp of step `step` (0-based): 0 during the warm-up, then linear to 1 over
    /// `ramp_steps`. It scales the image loss.
    pub fn ramp(&self, step: usize) -> f64 {
        if step < self.warmup_steps {
            0.0
        } else if self.ramp_steps == 0 {
            1.0
        } else {
            ((step - self.warmup_steps + 1) as f64 / self.ramp_steps as f64).min(1.0)
        }
    }

    /// Probability that a group of step `step` (0-based) is attacked: the ramp ×
    /// `attack_prob_max`.
    pub fn attack_probability(&self, step: usize) -> f64 {
        self.ramp(step) * self.attack_prob_max
    }

    /// Learning rate of step `step` (cosine decay).
    pub fn lr_at(&self, step: usize) -> f64 {
        let t = if self.steps > 1 {
            (step as f64 / (self.steps - 1) as f64).min(1.0)
        } else {
            0.0
        };
        let f = self.lr_min_fraction
            + (1.0 - self.lr_min_fraction) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos());
        self.lr * f
    }
}

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

/// Numbers of one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepStats {
    /// 1-based index of the step just done.
    pub step: usize,
    pub loss: f64,
    pub bce: f64,
    pub image_mse: f64,
    /// Bit accuracy of the (attacked) training batch.
    pub bit_accuracy: f64,
    pub attack_probability: f64,
    pub lr: f64,
}

/// A progress line: averages over the `log_every` steps before `step`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogEntry {
    pub step: usize,
    pub loss: f64,
    pub bce: f64,
    pub image_mse: f64,
    pub psnr_db: f64,
    pub bit_accuracy: f64,
    pub attack_probability: f64,
    pub images_per_s: f64,
}

/// What a checkpoint's `state.json` holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Format version (1).
    pub version: u32,
    /// Steps done.
    pub step: usize,
    /// The run's configuration.
    pub config: TrainConfig,
    /// The RNG state: step `k` draws from `step_seed(config.seed, k)`.
    pub rng: String,
    /// Training wall time so far, summed over resumed sessions (seconds).
    pub wall_s: f64,
    /// Progress lines so far.
    pub history: Vec<LogEntry>,
    /// The artifact the run started from (`--init`).
    #[serde(default)]
    pub started_from: Option<StartedFrom>,
}

/// A training run in memory.
pub struct Trainer {
    pub config: TrainConfig,
    device: Device,
    pub net: WatermarkNet,
    optim: ModuleOptimizer,
    /// Steps done.
    pub step: usize,
    train: ImageSet,
    /// Wall time of earlier sessions (resumed runs).
    wall_before: f64,
    session_start: Instant,
    session_first_step: usize,
    pub history: Vec<LogEntry>,
    window: Vec<StepStats>,
    window_start: Instant,
    /// The command line, for the training record.
    pub command: Option<String>,
    /// The training data, for the training record.
    pub data: Option<String>,
    /// The artifact this run started from (`--init`), for the training record.
    pub started_from: Option<StartedFrom>,
}

/// The trained artifact a run was initialised from (`--init`): its path and training record, so
/// a fine-tuned model's sidecar keeps its whole history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StartedFrom {
    /// The decoder weights given to `--init`.
    pub path: String,
    /// Their training record.
    pub record: Option<Box<super::artifact::TrainingRecord>>,
}

fn optimizer() -> ModuleOptimizer {
    AdamConfig::new().init()
}

fn record_err(path: &Path, e: impl std::fmt::Display) -> TrainError {
    TrainError::Record {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// A module's weights as burnpack bytes.
fn module_bytes<M: Module>(module: M, path_for_errors: &Path) -> Result<Vec<u8>, TrainError> {
    artifact::to_burnpack(module).map_err(|e| record_err(path_for_errors, e))
}

/// Loads burnpack bytes into `module`.
fn load_module_bytes<M: Module>(module: M, bytes: Vec<u8>, path: &Path) -> Result<M, TrainError> {
    artifact::from_burnpack(module, bytes).map_err(|e| record_err(path, e))
}

/// The checkpoint folder of an output path: `<out>.ckpt`.
pub fn checkpoint_root(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".ckpt");
    PathBuf::from(s)
}

/// Complete checkpoints under `root`, oldest first: `(step, folder)`.
pub fn list_checkpoints(root: &Path) -> Vec<(usize, PathBuf)> {
    let mut out: Vec<(usize, PathBuf)> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let step = name.strip_prefix("step-")?.parse().ok()?;
            let path = e.path();
            path.join("state.json").is_file().then_some((step, path))
        })
        .collect();
    out.sort();
    out
}

/// Reads the checkpoint folder `dir` written by [`write_checkpoint`]: its `state.json` as `S`,
/// the weights' burnpack bytes (`net.bpk`) and the Adam state (`optim.bpk`). Shared by both
/// trainers.
pub fn read_checkpoint<S: serde::de::DeserializeOwned>(
    dir: &Path,
) -> Result<(S, Vec<u8>, ModuleOptimizer), TrainError> {
    let state_path = dir.join("state.json");
    let text = std::fs::read(&state_path).map_err(io_err(&state_path))?;
    let state: S = serde_json::from_slice(&text).map_err(|source| TrainError::Json {
        path: state_path.clone(),
        source,
    })?;
    let net_path = dir.join("net.bpk");
    let net = std::fs::read(&net_path).map_err(io_err(&net_path))?;
    let optim_path = dir.join("optim.bpk");
    let bytes = std::fs::read(&optim_path).map_err(io_err(&optim_path))?;
    let optim = optimizer()
        .from_bytes(Bytes::from_bytes_vec(bytes))
        .map_err(|e| record_err(&optim_path, e))?;
    Ok((state, net, optim))
}

/// Writes `files` as the checkpoint `root/step-NNNNNNNN` atomically (a temporary folder,
/// every file synced, then renamed; a crash leaves whole checkpoints only) and keeps the newest
/// `keep` checkpoints. Shared by both trainers.
pub fn write_checkpoint(
    root: &Path,
    step: usize,
    files: &[(&str, &[u8])],
    keep: usize,
) -> Result<PathBuf, TrainError> {
    std::fs::create_dir_all(root).map_err(io_err(root))?;
    let final_dir = root.join(format!("step-{step:08}"));
    let tmp = tempfile::Builder::new()
        .prefix(".tmp-step-")
        .tempdir_in(root)
        .map_err(io_err(root))?;
    for (name, bytes) in files {
        let p = tmp.path().join(name);
        std::fs::write(&p, bytes).map_err(io_err(&p))?;
        std::fs::File::open(&p)
            .and_then(|f| f.sync_all())
            .map_err(io_err(&p))?;
    }
    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(io_err(&final_dir))?;
    }
    let tmp_path = tmp.keep();
    std::fs::rename(&tmp_path, &final_dir).map_err(io_err(&final_dir))?;
    let all = list_checkpoints(root);
    for (_, old) in all.iter().take(all.len().saturating_sub(keep.max(1))) {
        let _ = std::fs::remove_dir_all(old);
    }
    Ok(final_dir)
}

impl Trainer {
    /// A fresh run (weights initialised from `config.seed`).
    pub fn new(config: TrainConfig, train: ImageSet) -> Result<Self, TrainError> {
        config.validate()?;
        train.check_crop(config.crop)?;
        let base = config.device.device();
        base.seed(config.seed);
        let device = base.autodiff();
        let net = WatermarkNet {
            encoder: config.init_encoder(&device),
            decoder: config.decoder_config().init(&device),
        };
        Ok(Self::assemble(
            config,
            device,
            net,
            optimizer(),
            0,
            train,
            0.0,
            Vec::new(),
        ))
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        config: TrainConfig,
        device: Device,
        net: WatermarkNet,
        optim: ModuleOptimizer,
        step: usize,
        train: ImageSet,
        wall_before: f64,
        history: Vec<LogEntry>,
    ) -> Self {
        Self {
            config,
            device,
            net,
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
            started_from: None,
        }
    }

    /// A run that starts from the trained artifact at `path` (decoder, encoder and sidecar; fresh
    /// Adam state, step 0): fine-tuning. The architecture and the embedding strength come from
    /// the artifact's training configuration; everything else from `config`.
    pub fn from_artifact(
        mut config: TrainConfig,
        train: ImageSet,
        path: &Path,
    ) -> Result<Self, TrainError> {
        let read = |p: &Path| std::fs::read(p).map_err(io_err(p));
        let sidecar_path = artifact::sidecar_path(path);
        let sidecar: Sidecar =
            serde_json::from_slice(&read(&sidecar_path)?).map_err(|source| TrainError::Json {
                path: sidecar_path.clone(),
                source,
            })?;
        let base = sidecar.train_config.as_ref().ok_or_else(|| {
            TrainError::Config(format!(
                "{}: the sidecar has no training configuration to continue from",
                sidecar_path.display()
            ))
        })?;
        if base.bits != config.bits {
            return Err(TrainError::Config(format!(
                "{} decodes {} bits, not {}",
                path.display(),
                base.bits,
                config.bits
            )));
        }
        config.strength = base.strength;
        config.decoder_channels = base.decoder_channels;
        config.decoder_depth = base.decoder_depth;
        config.encoder = base.encoder;
        config.encoder_tile = base.encoder_tile;
        config.encoder_channels = base.encoder_channels;
        config.encoder_blocks = base.encoder_blocks;
        config.encoder_levels = base.encoder_levels;
        config.validate()?;
        train.check_crop(config.crop)?;
        let plain = config.device.device();
        plain.seed(config.seed);
        let device = plain.autodiff();
        let decoder = load_module_bytes(config.decoder_config().init(&device), read(path)?, path)?;
        let enc_path = artifact::encoder_path(path);
        let encoder = load_module_bytes(config.init_encoder(&device), read(&enc_path)?, &enc_path)?;
        let mut t = Self::assemble(
            config,
            device,
            WatermarkNet { encoder, decoder },
            optimizer(),
            0,
            train,
            0.0,
            Vec::new(),
        );
        t.started_from = Some(StartedFrom {
            path: path.display().to_string(),
            record: sidecar.record.map(Box::new),
        });
        Ok(t)
    }

    /// Continues from the checkpoint folder `dir` (one `step-NNNNNNNN`). `adjust` may change
    /// the stored config (only `steps`, `log_every`, `checkpoint_every` and `keep_checkpoints`
    /// are taken from it).
    pub fn resume(
        dir: &Path,
        train: ImageSet,
        adjust: impl FnOnce(&TrainConfig) -> TrainConfig,
    ) -> Result<Self, TrainError> {
        let (state, net_bytes, optim) = read_checkpoint::<CheckpointState>(dir)?;
        let mut config = state.config.clone();
        let wanted = adjust(&config);
        config.steps = wanted.steps;
        config.log_every = wanted.log_every;
        config.checkpoint_every = wanted.checkpoint_every;
        config.keep_checkpoints = wanted.keep_checkpoints;
        config.validate()?;
        train.check_crop(config.crop)?;
        let device = config.device.device().autodiff();
        let fresh = WatermarkNet {
            encoder: config.init_encoder(&device),
            decoder: config.decoder_config().init(&device),
        };
        let net = load_module_bytes(fresh, net_bytes, &dir.join("net.bpk"))?;
        let mut t = Self::assemble(
            config,
            device,
            net,
            optim,
            state.step,
            train,
            state.wall_s,
            state.history,
        );
        t.started_from = state.started_from;
        Ok(t)
    }

    /// Whether all steps are done.
    pub fn done(&self) -> bool {
        self.step >= self.config.steps
    }

    /// Training wall time so far (all sessions), seconds.
    pub fn wall_s(&self) -> f64 {
        self.wall_before + self.session_start.elapsed().as_secs_f64()
    }

    /// One optimisation step.
    pub fn step(&mut self) -> Result<StepStats, TrainError> {
        let c = &self.config;
        let k = self.step;
        let mut rng = EotRng::new(step_seed(c.seed, k));
        let (b, l, s) = (c.batch_size, c.bits, c.crop);
        let pixels = self.train.sample_batch(&mut rng, b, s, c.min_scale, true);
        let bits: Vec<f32> = (0..b * l).map(|_| (rng.next_u64() >> 63) as f32).collect();
        let cover = Tensor::<4>::from_data(TensorData::new(pixels, [b, 3, s, s]), &self.device);
        let message = Tensor::<2>::from_data(TensorData::new(bits.clone(), [b, l]), &self.device);

        let residual = artifact::encoder_residual(
            &self.net.encoder,
            cover.clone(),
            message.clone(),
            c.encoder_levels,
        );
        let marked = cover
            .clone()
            .add(residual.mul_scalar(c.strength))
            .clamp(0.0, 1.0);
        let marked = straight_through_round(marked.mul_scalar(255.0)).div_scalar(255.0);
        let mse = marked.clone().sub(cover).square().mean();

        // Unmarked crops (drawn only when enabled, so runs without them keep their random
        // streams).
        let mut unmarked = (c.unmarked_crops > 0 && c.unmarked_weight > 0.0).then(|| {
            let u = c.unmarked_crops;
            let px = self.train.sample_batch(&mut rng, u, s, c.min_scale, true);
            let x = Tensor::<4>::from_data(TensorData::new(px, [u, 3, s, s]), &self.device);
            straight_through_round(x.mul_scalar(255.0)).div_scalar(255.0)
        });
        let mut unmarked_logits = None;
        let p = c.attack_probability(k);
        let groups = c.attack_groups.clamp(1, b);
        let mut logits = Vec::with_capacity(groups);
        let mut start = 0;
        for g in 0..groups {
            let len = b / groups + usize::from(g < b % groups);
            let part = marked.clone().narrow(0, start, len);
            start += len;
            let attack = if p > 0.0 && rng.uniform() < p {
                random_composition(&c.eot, &mut rng)
            } else {
                DiffAttack::Chain(Vec::new())
            };
            // The unmarked crops join the first group: same attack, same forward pass (and
            // BatchNorm batch), so they are treated like the watermarked images they must be
            // told apart from.
            if g == 0
                && let Some(u) = unmarked.take()
            {
                let z = self
                    .net
                    .decoder
                    .forward(attack.apply(Tensor::cat(vec![part, u], 0))?);
                unmarked_logits = Some(z.clone().narrow(0, len, c.unmarked_crops));
                logits.push(z.narrow(0, 0, len));
            } else {
                logits.push(self.net.decoder.forward(attack.apply(part)?));
            }
        }
        let logits = Tensor::cat(logits, 0);
        let bce = bce_with_logits(logits.clone(), message);
        let mut loss = bce
            .clone()
            .add(mse.clone().mul_scalar(c.image_weight * c.ramp(k)));
        if let Some(z) = unmarked_logits {
            // Ramped in like the image loss: from step 0 it holds every logit at 0 before the
            // decoder has learnt to tell marked from unmarked images (measured: still at chance,
            // 50.1 %, after 950 steps).
            let half = z.zeros_like().add_scalar(0.5);
            loss = loss.add(bce_with_logits(z, half).mul_scalar(c.unmarked_weight * c.ramp(k)));
        }

        let grads = GradientsParams::from_grads(loss.backward(), &self.net);
        let lr = c.lr_at(k);
        self.net = self.optim.step(lr, self.net.clone(), grads);

        let z: Vec<f32> = logits.detach().try_into_vec_as::<f32>().unwrap_or_default();
        let correct = z
            .iter()
            .zip(&bits)
            .filter(|&(&z, &m)| (z > 0.0) == (m > 0.5))
            .count();
        let scalar = |t: Tensor<1>| f64::from(t.detach().into_scalar::<f32>());
        let (loss, bce, mse) = (scalar(loss), scalar(bce), scalar(mse));
        if !loss.is_finite() {
            return Err(TrainError::Diverged(k + 1));
        }
        self.step += 1;
        let stats = StepStats {
            step: self.step,
            loss,
            bce,
            image_mse: mse,
            bit_accuracy: correct as f64 / (b * l) as f64,
            attack_probability: p,
            lr,
        };
        self.window.push(stats);
        Ok(stats)
    }

    /// Closes the current logging window: its averages as a [`LogEntry`], appended to the
    /// history.
    pub fn log_entry(&mut self) -> Option<LogEntry> {
        let n = self.window.len();
        if n == 0 {
            return None;
        }
        let mean = |f: fn(&StepStats) -> f64| self.window.iter().map(f).sum::<f64>() / n as f64;
        let mse = mean(|s| s.image_mse);
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
        Some(entry)
    }

    /// A human-readable progress line for `entry`, with the ETA from this session's pace.
    pub fn progress_line(&self, entry: &LogEntry) -> String {
        let done = self.step - self.session_first_step;
        let elapsed = self.session_start.elapsed().as_secs_f64();
        let eta = if done > 0 {
            elapsed / done as f64 * (self.config.steps.saturating_sub(self.step)) as f64
        } else {
            0.0
        };
        format!(
            "step {}/{} | loss {:.4} (bce {:.4}, mse {:.2e} → {:.1} dB) | bit acc {:.3} | attack p {:.2} | lr {:.1e} | {:.1} img/s | elapsed {} | ETA {}",
            self.step,
            self.config.steps,
            entry.loss,
            entry.bce,
            entry.image_mse,
            entry.psnr_db,
            entry.bit_accuracy,
            entry.attack_probability,
            self.config.lr_at(self.step.saturating_sub(1)),
            entry.images_per_s,
            hms(self.wall_s()),
            hms(eta),
        )
    }

    /// Writes a checkpoint of the current state under `root` (atomically) and prunes old ones.
    pub fn save_checkpoint(&self, root: &Path) -> Result<PathBuf, TrainError> {
        // BatchNorm running statistics hold their newest update in a per-thread slot until the
        // next forward pass; `valid` folds it in (shared state), so the record is current.
        let _ = self.net.valid();
        let net_path = root.join("net.bpk");
        let net = module_bytes(self.net.clone(), &net_path)?;
        let optim_path = root.join("optim.bpk");
        let optim = self
            .optim
            .into_bytes()
            .map_err(|e| record_err(&optim_path, e))?;
        let state = CheckpointState {
            version: 1,
            step: self.step,
            config: self.config.clone(),
            rng: format!(
                "step k draws from SplitMix64(step_seed({}, k)); next k = {}",
                self.config.seed, self.step
            ),
            wall_s: self.wall_s(),
            history: self.history.clone(),
            started_from: self.started_from.clone(),
        };
        let json = serde_json::to_vec_pretty(&state).expect("state serialises");
        write_checkpoint(
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

    /// The trained model as used after training: frozen decoder and encoder on the plain
    /// device, the whitening not yet decided. A deep copy (through a burnpack record): freezing
    /// a `valid()` snapshot in place would also switch off the BatchNorm training flags of the
    /// live network, which shares them, and silently change the following training steps.
    pub fn model(&self) -> WatermarkModel {
        let c = &self.config;
        let device = c.device.device();
        let _ = self.net.valid(); // folds pending BatchNorm statistics in
        let bytes = artifact::to_burnpack(self.net.valid()).expect("weights serialise");
        let fresh = WatermarkNet {
            encoder: c.init_encoder(&device),
            decoder: c.decoder_config().init(&device),
        };
        let net = artifact::from_burnpack(fresh, bytes).expect("own weights load");
        WatermarkModel {
            sidecar: Sidecar::new(c, None),
            decoder: net.decoder.frozen(),
            encoder: Some(net.encoder.freeze()),
            reference: None,
            projection: None,
        }
    }

    /// Freezes the decoder, decides on the whitening, evaluates on `held_out` (if configured)
    /// and writes the artifact to `out`. Returns the sidecar written.
    pub fn finish(
        &self,
        out: &Path,
        held_out: Option<&ImageSet>,
        log: &mut dyn Write,
    ) -> Result<Sidecar, TrainError> {
        let c = &self.config;
        let mut model = self.model();
        let device = c.device.device();
        let (whitening, report) =
            decide_whitening(&model, &self.train, held_out, c, c.whitening, &device, log)?;
        model.sidecar.whitening = whitening;
        let evaluation = match (c.final_eval, held_out) {
            (true, Some(h)) => {
                let _ = writeln!(log, "evaluating on {} held-out images…", h.len());
                let r = eval::evaluate_on(&model, &h.images, &c.eval, &device)?;
                Some(r)
            }
            _ => None,
        };
        model.sidecar.record = Some(TrainingRecord {
            steps: self.step,
            wall_s: self.wall_s(),
            images_per_s: self.history.last().map(|e| e.images_per_s),
            final_log: self.history.last().cloned(),
            whitening: report,
            held_out: evaluation,
            command: self.command.clone(),
            data: self.data.clone(),
            started_from: self.started_from.clone(),
            calibrated_by: None,
        });
        model.save(out)?;
        Ok(model.sidecar)
    }
}

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
    use super::*;

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

    #[test]
    fn schedule_and_probability() {
        let c = TrainConfig {
            steps: 101,
            warmup_steps: 10,
            ramp_steps: 20,
            ..TrainConfig::default()
        };
        assert_eq!(c.attack_probability(0), 0.0);
        assert_eq!(c.attack_probability(9), 0.0);
        assert!((c.attack_probability(10) - 0.05).abs() < 1e-12);
        assert_eq!(c.attack_probability(29), 1.0);
        assert_eq!(c.attack_probability(1000), 1.0);
        // A ceiling on the attack probability leaves the ramp (and the image loss) alone.
        let capped = TrainConfig {
            attack_prob_max: 0.25,
            ..c.clone()
        };
        assert_eq!(capped.attack_probability(1000), 0.25);
        assert_eq!(capped.ramp(1000), 1.0);
        assert_eq!(capped.ramp(9), 0.0);
        assert!(
            TrainConfig {
                attack_prob_max: 1.5,
                ..c.clone()
            }
            .validate()
            .is_err()
        );
        assert!((c.lr_at(0) - c.lr).abs() < 1e-15);
        assert!((c.lr_at(100) - c.lr * c.lr_min_fraction).abs() < 1e-12);
        assert!(c.lr_at(50) < c.lr && c.lr_at(50) > c.lr * c.lr_min_fraction);
        assert_ne!(step_seed(0, 0), step_seed(0, 1));
        assert_ne!(step_seed(0, 0), step_seed(1, 0));
        // The config round-trips through JSON, and partial JSON takes defaults.
        let json = serde_json::to_string(&c).unwrap();
        assert_eq!(serde_json::from_str::<TrainConfig>(&json).unwrap(), c);
        let partial: TrainConfig = serde_json::from_str(r#"{"bits": 48}"#).unwrap();
        assert_eq!(partial, TrainConfig::for_bits(48));
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

    #[test]
    fn a_few_steps_reduce_the_loss_and_checkpoint() {
        let set = synthetic_set(6, 48, 1);
        let config = TrainConfig {
            steps: 80,
            decoder_channels: 16,
            encoder_channels: 16,
            attack_groups: 1,
            ..tiny_config()
        };
        let mut t = Trainer::new(config, set).unwrap();
        // (Weight initialisation draws from burn's global RNG, which tests running in parallel
        // share, so the exact curve varies from run to run; the margin is generous.)
        let losses: Vec<f64> = (0..80).map(|_| t.step().unwrap().loss).collect();
        let first: f64 = losses[..10].iter().sum::<f64>() / 10.0;
        let last: f64 = losses[70..].iter().sum::<f64>() / 10.0;
        assert!(last < first - 0.03, "loss {first} → {last}: {losses:?}");
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("d.bpk.ckpt");
        let saved = t.save_checkpoint(&root).unwrap();
        assert_eq!(saved.file_name().unwrap(), "step-00000080");
        for f in ["net.bpk", "optim.bpk", "state.json"] {
            assert!(saved.join(f).is_file(), "{f}");
        }
        assert_eq!(list_checkpoints(&root), vec![(80, saved)]);
        // No temporary folders left behind.
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
    }

    #[test]
    fn resume_continues_exactly_where_it_stopped() {
        let mut config = tiny_config();
        config.steps = 6;
        // Attacks from the third step on, so the resumed steps draw attacks too.
        config.warmup_steps = 2;
        config.ramp_steps = 1;
        config.keep_checkpoints = 2;
        let set = synthetic_set(4, 48, 2);
        let outputs = probe_outputs(&set, 99);

        // Both runs start from the same weights (burn's weight-init RNG is global, so two
        // `Trainer::new` in parallel tests need not draw the same ones).
        let dir = tempfile::tempdir().unwrap();
        let mut first = Trainer::new(config.clone(), set.clone()).unwrap();
        let start = first.save_checkpoint(&dir.path().join("start")).unwrap();
        let mut straight = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        for _ in 0..6 {
            straight.step().unwrap();
        }

        let root = dir.path().join("ckpt");
        for _ in 0..3 {
            first.step().unwrap();
            first.save_checkpoint(&root).unwrap();
        }
        // Pruned to the newest two.
        let steps: Vec<usize> = list_checkpoints(&root).iter().map(|c| c.0).collect();
        assert_eq!(steps, [2, 3]);
        let latest = list_checkpoints(&root).pop().unwrap().1;
        let mut resumed = Trainer::resume(&latest, set.clone(), |c| c.clone()).unwrap();
        assert_eq!(resumed.step, 3);
        assert_eq!(outputs(&resumed), outputs(&first));
        while !resumed.done() {
            resumed.step().unwrap();
        }
        assert_eq!(resumed.step, 6);
        let (a, b) = (outputs(&straight), outputs(&resumed));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-3 * (1.0 + x.abs()), "{a:?} vs {b:?}");
        }

        // Without the Adam state the continuation differs (the test above is not vacuous).
        let mut no_adam = Trainer::resume(&latest, set, |c| c.clone()).unwrap();
        no_adam.optim = optimizer();
        while !no_adam.done() {
            no_adam.step().unwrap();
        }
        let c = outputs(&no_adam);
        let diff: f32 = a.iter().zip(&c).map(|(x, y)| (x - y).abs()).sum();
        assert!(diff > 1e-3, "Adam state made no difference");

        // Extending the run on resume.
        let longer = Trainer::resume(&latest, synthetic_set(4, 48, 2), |c| TrainConfig {
            steps: 10,
            lr: 123.0, // ignored
            ..c.clone()
        })
        .unwrap();
        assert_eq!(longer.config.steps, 10);
        assert_eq!(longer.config.lr, config.lr);
    }

    /// The decoder logits (inference mode) of a trainer on two fixed 32² crops of `set`.
    fn probe_outputs(set: &ImageSet, seed: u64) -> impl Fn(&Trainer) -> Vec<f32> + use<> {
        let probe = Tensor::<4>::from_data(
            TensorData::new(
                set.sample_batch(&mut EotRng::new(seed), 2, 32, 1.0, false),
                [2, 3, 32, 32],
            ),
            &Device::flex(),
        );
        move |t: &Trainer| {
            t.model()
                .decoder
                .forward(probe.clone())
                .try_into_vec_as::<f32>()
                .unwrap()
        }
    }

    /// Trains `config` for its steps on `set` and writes the artifact (with its encoder) to
    /// `out`, without the held-out evaluation.
    fn tiny_artifact(config: TrainConfig, set: ImageSet, out: &Path) -> Trainer {
        let mut t = Trainer::new(config, set).unwrap();
        while !t.done() {
            t.step().unwrap();
        }
        t.finish(out, None, &mut Vec::new()).unwrap();
        t
    }

    #[test]
    fn init_starts_a_fine_tune_from_a_trained_artifact() {
        let set = synthetic_set(4, 48, 3);
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("base.bpk");
        let base = TrainConfig {
            steps: 3,
            whitening: WhiteningChoice::Never,
            ..tiny_config()
        };
        let trained = tiny_artifact(base.clone(), set.clone(), &out);
        let outputs = probe_outputs(&set, 5);

        // Another architecture and strength asked for: the artifact's win; the rest is ours.
        let wanted = TrainConfig {
            decoder_channels: 16,
            encoder_tile: 4,
            strength: 0.9,
            lr: 5e-4,
            steps: 2,
            ..base.clone()
        };
        let mut ft = Trainer::from_artifact(wanted, set.clone(), &out).unwrap();
        assert_eq!(ft.step, 0);
        assert_eq!(ft.config.decoder_channels, base.decoder_channels);
        assert_eq!(ft.config.encoder_tile, base.encoder_tile);
        assert_eq!(ft.config.strength, base.strength);
        assert_eq!(ft.config.lr, 5e-4);
        assert_eq!(outputs(&ft), outputs(&trained));
        let from = ft.started_from.clone().unwrap();
        assert_eq!(from.path, out.display().to_string());
        assert_eq!(from.record.as_ref().unwrap().steps, 3);
        while !ft.done() {
            ft.step().unwrap();
        }
        assert_ne!(outputs(&ft), outputs(&trained));
        // The lineage survives a checkpoint round trip and lands in the new artifact.
        let ckpt = ft.save_checkpoint(&dir.path().join("ft.ckpt")).unwrap();
        let resumed = Trainer::resume(&ckpt, set.clone(), |c| c.clone()).unwrap();
        assert_eq!(resumed.started_from, ft.started_from);
        let out2 = dir.path().join("ft.bpk");
        let sidecar = ft.finish(&out2, None, &mut Vec::new()).unwrap();
        assert_eq!(
            sidecar
                .record
                .unwrap()
                .started_from
                .unwrap()
                .record
                .unwrap()
                .steps,
            3
        );

        // Bad starts are typed errors.
        let wrong_bits = TrainConfig {
            bits: 8,
            ..base.clone()
        };
        assert!(matches!(
            Trainer::from_artifact(wrong_bits, set.clone(), &out),
            Err(TrainError::Config(_))
        ));
        assert!(matches!(
            Trainer::from_artifact(base, set, &dir.path().join("missing.bpk")),
            Err(TrainError::Io { .. })
        ));
    }

    #[test]
    fn the_unmarked_loss_adds_a_coin_toss_term() {
        // Two runs from one checkpoint, one with the unmarked loss: its loss carries
        // weight · BCE(z, ½) ≥ weight · ln 2 on top of (about) the same watermark loss.
        let set = synthetic_set(4, 48, 4);
        let dir = tempfile::tempdir().unwrap();
        let t = Trainer::new(tiny_config(), set.clone()).unwrap();
        let start = t.save_checkpoint(&dir.path().join("c")).unwrap();
        // In the warm-up the term is off (it ramps in with the attacks).
        let mut warm = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        warm.config.unmarked_crops = 3;
        warm.config.unmarked_weight = 10.0;
        let w = warm.step().unwrap();
        assert!(w.loss - w.bce < 1e-6, "{w:?}");
        let mut plain = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        let mut with = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        // After the ramp (resume keeps the schedule of the checkpoint, so set it here).
        for t in [&mut plain, &mut with] {
            t.config.warmup_steps = 0;
            t.config.ramp_steps = 0;
        }
        with.config.unmarked_crops = 3;
        with.config.unmarked_weight = 10.0;
        let (a, b) = (plain.step().unwrap(), with.step().unwrap());
        assert!(
            b.loss - b.bce >= 10.0 * std::f64::consts::LN_2 - 1e-3,
            "{a:?} vs {b:?}"
        );
        assert!(a.loss - a.bce < 1e-6, "no image loss (weight 0): {a:?}");
        // Training with it drives the unmarked logits towards 0 (coin tosses).
        let mean_abs = |t: &Trainer| {
            let m = t.model();
            let px = set.sample_batch(&mut EotRng::new(8), 8, 32, 1.0, false);
            let x = Tensor::<4>::from_data(TensorData::new(px, [8, 3, 32, 32]), &Device::flex());
            let z = m.decoder.forward(x).try_into_vec_as::<f32>().unwrap();
            z.iter().map(|v| v.abs()).sum::<f32>() / z.len() as f32
        };
        for _ in 0..30 {
            plain.step().unwrap();
            with.step().unwrap();
        }
        let (za, zb) = (mean_abs(&plain), mean_abs(&with));
        assert!(
            zb < za,
            "unmarked |logit| {zb} with the loss vs {za} without"
        );
    }

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
            held += usize::from(super::super::data::is_held_out(&name));
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
