//! The configuration of a training run: [`TrainConfig`], its schedules (attack ramp, learning
//! rate) and the choices it names (device, encoder design, whitening).

use burn::tensor::{Device, DeviceKind};
use serde::{Deserialize, Serialize};

use super::TrainError;
use crate::attack::diff::EotConfig;
use crate::decoder::encoder::{Encoder, TiledEncoderConfig};
use crate::decoder::eval::EvalOptions;
use crate::decoder::model::{HiddenDecoderConfig, HiddenEncoderConfig};

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

/// Whether the final decoder gets a [`Whitening`](crate::decoder::model::Whitening) of its logits.
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

/// Which encoder is trained with the decoder (see [`super::encoder`](mod@crate::decoder::encoder)).
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
    /// [`artifact::encoder_residual`](crate::decoder::artifact::encoder_residual). 2 = the resolution of the decoder's LL band.
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::train::step_seed;

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
}
