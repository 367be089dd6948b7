//! The artifact's JSON sidecar: message length, both architectures, embedding strength, the
//! optional logit whitening, the training configuration and the training record.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{FORMAT, WeightsError};
use crate::decoder::eval::EvalReport;
use crate::decoder::model::{HiddenDecoderConfig, Norm, Whitening};
use crate::decoder::train::{EncoderKind, LogEntry, TrainConfig};

/// Decoder architecture in the sidecar.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecoderArch {
    pub channels: usize,
    pub depth: usize,
    pub dwt_levels: usize,
    /// Block normalisation (absent in sidecars before December 2026: BatchNorm).
    #[serde(default)]
    pub norm: Norm,
    /// Convolution kernel (absent before December 2026: 3).
    #[serde(default = "three")]
    pub kernel: usize,
    /// Gain on the input band (absent before December 2026: 1).
    #[serde(default = "unit")]
    pub input_gain: f64,
    /// Colour-Fourier features (0 = the convolutional decoder; absent before December 2026).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub fourier: usize,
    /// Their scale (meaningless when `fourier` is 0).
    #[serde(default = "eight")]
    pub fourier_scale: f64,
    /// Their dark cut-off (0 when absent).
    #[serde(default)]
    pub fourier_dark: f64,
}

impl From<&HiddenDecoderConfig> for DecoderArch {
    fn from(d: &HiddenDecoderConfig) -> Self {
        Self {
            channels: d.channels,
            depth: d.depth,
            dwt_levels: d.dwt_levels,
            norm: d.norm,
            kernel: d.kernel,
            input_gain: d.input_gain,
            fourier: d.fourier,
            fourier_scale: d.fourier_scale,
            fourier_dark: d.fourier_dark,
        }
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn eight() -> f64 {
    8.0
}

fn three() -> usize {
    3
}

fn unit() -> f64 {
    1.0
}

/// Encoder architecture in the sidecar.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EncoderArch {
    /// Design (`hidden` or `tiled`).
    pub kind: EncoderKind,
    pub channels: usize,
    pub blocks: usize,
    /// Message tile side of the tiled encoder.
    #[serde(default)]
    pub tile: usize,
    /// The encoder runs on the 2^levels-downsampled image ([`encoder_residual`]).
    #[serde(default)]
    pub levels: usize,
}

/// Whether the whitening helped, as measured at the end of training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WhiteningReport {
    /// Whether a map was kept.
    pub applied: bool,
    /// Which one: `"whitening"` (μ and ZCA) or `"centering"` (μ only); absent when none.
    #[serde(default)]
    pub kind: Option<String>,
    /// Unmarked held-out crops decoded.
    pub unmarked_samples: usize,
    /// Mean over bits of |2·P(bit = 1) − 1| on unmarked crops, raw logits.
    pub bias_raw: f64,
    /// The same with whitened logits.
    pub bias_whitened: f64,
    /// Watermarked held-out crops decoded (clean and attacked).
    pub marked_samples: usize,
    /// Their bit accuracy, raw logits.
    pub marked_accuracy_raw: f64,
    /// Their bit accuracy, whitened logits.
    pub marked_accuracy_whitened: f64,
    /// Unmarked bit bias with centred logits (absent in records older than centering).
    #[serde(default)]
    pub bias_centered: Option<f64>,
    /// Marked bit accuracy with centred logits.
    #[serde(default)]
    pub marked_accuracy_centered: Option<f64>,
}

impl WhiteningReport {
    /// The rule of [`super::train::WhiteningChoice::Auto`] for a candidate with unmarked bias
    /// `bias` and marked accuracy `accuracy`: lower bias, and at most 0.5 percentage points of
    /// marked accuracy lost.
    fn passes(&self, bias: f64, accuracy: f64) -> bool {
        bias < self.bias_raw && accuracy >= self.marked_accuracy_raw - 0.005
    }

    /// Whether the full whitening passes the rule.
    pub fn helps(&self) -> bool {
        self.passes(self.bias_whitened, self.marked_accuracy_whitened)
    }

    /// Whether the centering passes the rule.
    pub fn centering_helps(&self) -> bool {
        match (self.bias_centered, self.marked_accuracy_centered) {
            (Some(b), Some(a)) => self.passes(b, a),
            _ => false,
        }
    }

    /// One-line summary.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "unmarked bit bias raw {:.3}, whitened {:.3}",
            self.bias_raw, self.bias_whitened
        );
        if let Some(b) = self.bias_centered {
            s += &format!(", centred {b:.3}");
        }
        s += &format!(
            "; marked bit accuracy raw {:.4}, whitened {:.4}",
            self.marked_accuracy_raw, self.marked_accuracy_whitened
        );
        if let Some(a) = self.marked_accuracy_centered {
            s += &format!(", centred {a:.4}");
        }
        s
    }
}

/// How the artifact was trained.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainingRecord {
    /// Optimisation steps done.
    pub steps: usize,
    /// Training wall time, summed over resumed sessions (seconds; evaluation excluded).
    pub wall_s: f64,
    /// Throughput of the last logging window.
    pub images_per_s: Option<f64>,
    /// The last progress line.
    pub final_log: Option<LogEntry>,
    /// The whitening decision.
    pub whitening: Option<WhiteningReport>,
    /// `decoder eval` on the held-out images at the end of training.
    pub held_out: Option<EvalReport>,
    /// The command line.
    pub command: Option<String>,
    /// The training data.
    pub data: Option<String>,
    /// The artifact this run was initialised from (fine-tuning), with its own record.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_from: Option<crate::decoder::train::StartedFrom>,
    /// The `decoder calibrate` command that last re-decided the logit map and re-evaluated.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibrated_by: Option<String>,
}

/// The JSON sidecar of an artifact.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sidecar {
    /// [`FORMAT`].
    pub format: String,
    /// Message length L.
    pub bits: usize,
    pub decoder: DecoderArch,
    /// Absent for a decoder-only artifact.
    pub encoder: Option<EncoderArch>,
    /// Embedding strength the encoder was trained with.
    pub strength: f64,
    /// Applied to the decoder's logits when present.
    pub whitening: Option<Whitening>,
    pub train_config: Option<TrainConfig>,
    pub record: Option<TrainingRecord>,
    /// The configuration of an optimiser-as-encoder run (`decoder train-opt`), which has no
    /// encoder and no `train_config`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub opt_train_config: Option<crate::decoder::optrain::OptTrainConfig>,
    /// The decoder-agnostic probe on held-out images (`decoder probe`), when it was run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probe: Option<crate::decoder::probe::ProbeReport>,
}

impl Sidecar {
    /// The sidecar of a model trained with `config`.
    pub fn new(config: &TrainConfig, whitening: Option<Whitening>) -> Self {
        let d = config.decoder_config();
        Self {
            format: FORMAT.into(),
            bits: config.bits,
            decoder: DecoderArch::from(&d),
            encoder: Some(EncoderArch {
                kind: config.encoder,
                tile: config.encoder_tile,
                channels: config.encoder_channels,
                blocks: config.encoder_blocks,
                levels: config.encoder_levels,
            }),
            strength: config.strength,
            whitening,
            train_config: Some(config.clone()),
            record: None,
            opt_train_config: None,
            probe: None,
        }
    }

    pub(super) fn decoder_config(&self) -> HiddenDecoderConfig {
        HiddenDecoderConfig::new(self.bits)
            .with_channels(self.decoder.channels)
            .with_depth(self.decoder.depth)
            .with_dwt_levels(self.decoder.dwt_levels)
            .with_norm(self.decoder.norm)
            .with_kernel(self.decoder.kernel)
            .with_input_gain(self.decoder.input_gain)
            .with_fourier(self.decoder.fourier)
            .with_fourier_scale(self.decoder.fourier_scale)
            .with_fourier_dark(self.decoder.fourier_dark)
    }

    pub(super) fn encoder_config(&self) -> Option<TrainConfig> {
        self.encoder.as_ref().map(|e| TrainConfig {
            bits: self.bits,
            encoder: e.kind,
            encoder_channels: e.channels,
            encoder_blocks: e.blocks,
            encoder_tile: e.tile.max(1),
            encoder_levels: e.levels,
            ..TrainConfig::default()
        })
    }

    pub(super) fn check(&self, origin: &Path) -> Result<(), WeightsError> {
        if self.format != FORMAT {
            return Err(WeightsError::Mismatch(format!(
                "{}: sidecar format {:?}, expected {FORMAT:?}",
                origin.display(),
                self.format
            )));
        }
        if let Some(w) = &self.whitening
            && (w.bits() != self.bits || w.matrix.len() != self.bits * self.bits)
        {
            return Err(WeightsError::Mismatch(format!(
                "{}: whitening is for {} bits, the decoder has {}",
                origin.display(),
                w.bits(),
                self.bits
            )));
        }
        Ok(())
    }
}
