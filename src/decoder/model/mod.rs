//! The HiDDeN bit decoder D (and the HiDDeN encoder used to pretrain it) as burn modules, the
//! optional Stable-Signature whitening of its logits, and saving/loading of weights.
//!
//! # Decoder input
//!
//! The decoder reads the LL band of a `dwt_levels`-level Haar DWT
//! ([`super::dwt`](mod@super::dwt)) of an RGB image in [0, 1], mapped back to image range and
//! centred: `(LL / 2^levels − 0.5) / 0.5`, i.e.
//! `LL · 2/2^levels − 1` ([`decoder_input`]). LL / 2^levels is the mean of each 2^levels ×
//! 2^levels block, so the decoder sees a 1/2^levels-scale image in [−1, 1], the range HiDDeN's own
//! decoder is trained on. (The baselines feed the raw LL of a [0, 1] image, in [0, 4] for two
//! levels; that is an affine map of ours which the first BatchNorm absorbs, but their decoders are
//! trained for bior4.4 — see [`super::dwt`](mod@super::dwt) — so their weights would not transfer
//! as is anyway.)
//! The map is linear, so ∂(decoder input)/∂image is a constant 2/4^levels per pixel of its block.
//!
//! Any image size works (the DWT edge-pads to a multiple of 2^levels and the decoder ends in a
//! global average pool); at least 64 px per side is recommended, i.e. an LL band of ≥ 16 × 16
//! for two levels, so the 3 × 3 convolutions see more than their own zero padding.
//!
//! # Architecture
//!
//! HiDDeN (Zhu et al. 2018) as used by Stable Signature (Fernandez et al. 2023) and, through it,
//! by WateRF and 3D-GSW: `ConvBNReLU(3→C)`, `depth` × `ConvBNReLU(C→C)`, `ConvBNReLU(C→L)`,
//! global average pool, `Linear(L→L)`, with 3 × 3 convolutions (stride 1, padding 1), C = 64 and
//! BatchNorm ε = 1e-3 (Stable Signature's value). `depth = 7` corresponds to Stable Signature's
//! `num_blocks = 8` (their count includes the first block); the original HiDDeN code's
//! `decoder_blocks = 7` is `depth = 6`.
//!
//! # Frozen use
//!
//! During watermark finetuning the decoder is frozen: call [`HiddenDecoder::frozen`] (burn's
//! [`Module::freeze`]) so that its parameters need no gradient **and** its BatchNorm layers use
//! their running statistics even when the input is on an autodiff device (otherwise burn's
//! BatchNorm takes the training path whenever the input carries autodiff). Gradients still flow
//! to the input image.

mod decoder;
mod encoder;
mod fourier;
mod whitening;

pub use decoder::{HiddenDecoder, HiddenDecoderConfig, decoder_input};
pub use encoder::{HiddenEncoder, HiddenEncoderConfig};
pub use fourier::{FourierHost, FourierPass, HostFeatures, sin_cos};
pub use whitening::{WHITENING_EIGEN_FLOOR, Whitening, WhiteningError, symmetric_eigen};

use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{
    BatchNorm, BatchNormConfig, Gelu, GroupNorm, GroupNormConfig, PaddingConfig2d, Relu,
};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

/// BatchNorm ε of every ConvBNReLU block (Stable Signature's HiDDeN uses 1e-3).
pub const BATCH_NORM_EPS: f64 = 1e-3;

/// How the decoder's blocks normalise and activate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Norm {
    /// BatchNorm + ReLU (HiDDeN, Stable Signature): batch statistics in training, running
    /// statistics at inference — the two paths can diverge (docs/DECODER.md, 32-bit run 2).
    #[default]
    Batch,
    /// GroupNorm (8 groups, or fewer when the channels do not divide) + GELU (VideoSeal's
    /// HiDDeN extractor): per-image statistics, the same computation in training and inference.
    Group,
    /// No normalisation, GELU: with `kernel` = 1 every block is a per-pixel map, so the decoder
    /// is a function of the colours of the LL band pooled over the image — invariant to where
    /// the colours are (rotation, perspective, shifts), which is what views of a 3D asset
    /// share.
    #[serde(rename = "none")]
    Off,
}

/// Groups of the GroupNorm of a block with `channels` channels: 8, or the largest divisor
/// of `channels` below it.
pub fn group_count(channels: usize) -> usize {
    (1..=8.min(channels))
        .rev()
        .find(|g| channels.is_multiple_of(*g))
        .unwrap_or(1)
}

/// Conv 3 × 3 (stride 1, padding 1) → BatchNorm → ReLU (HiDDeN's building block), or
/// → GroupNorm → GELU ([`Norm::Group`]).
#[derive(Module, Debug)]
pub struct ConvBnRelu {
    conv: Conv2d,
    /// Present for [`Norm::Batch`] (the record keeps HiDDeN's `bn` names).
    bn: Option<BatchNorm>,
    /// Present for [`Norm::Group`].
    gn: Option<GroupNorm>,
    relu: Relu,
    gelu: Gelu,
}

impl ConvBnRelu {
    /// A BatchNorm + ReLU block mapping `channels_in` to `channels_out` channels.
    pub fn new(channels_in: usize, channels_out: usize, device: &Device) -> Self {
        Self::with_norm(channels_in, channels_out, Norm::Batch, device)
    }

    /// A block with the given normalisation.
    pub fn with_norm(channels_in: usize, channels_out: usize, norm: Norm, device: &Device) -> Self {
        Self::with_kernel(channels_in, channels_out, norm, 3, device)
    }

    /// A block with the given normalisation and a `kernel` × `kernel` convolution (odd).
    pub fn with_kernel(
        channels_in: usize,
        channels_out: usize,
        norm: Norm,
        kernel: usize,
        device: &Device,
    ) -> Self {
        let (bn, gn) = match norm {
            Norm::Batch => (
                Some(
                    BatchNormConfig::new(channels_out)
                        .with_epsilon(BATCH_NORM_EPS)
                        .init(device),
                ),
                None,
            ),
            Norm::Group => (
                None,
                Some(GroupNormConfig::new(group_count(channels_out), channels_out).init(device)),
            ),
            Norm::Off => (None, None),
        };
        let pad = kernel / 2;
        Self {
            conv: Conv2dConfig::new([channels_in, channels_out], [kernel, kernel])
                .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
                .init(device),
            bn,
            gn,
            relu: Relu::new(),
            gelu: Gelu::new(),
        }
    }

    /// `[B, C_in, H, W]` → `[B, C_out, H, W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let x = self.conv.forward(x);
        match (&self.bn, &self.gn) {
            (Some(bn), _) => self.relu.forward(bn.forward(x)),
            (None, Some(gn)) => self.gelu.forward(gn.forward(x)),
            (None, None) => self.gelu.forward(x),
        }
    }
}

#[cfg(test)]
mod tests {
    use burn::tensor::TensorData;

    use super::*;

    pub(super) fn device() -> Device {
        Device::flex()
    }

    pub(super) fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    pub(super) struct Lcg(pub(super) u64);
    impl Lcg {
        pub(super) fn uniform(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        pub(super) fn normal(&mut self) -> f64 {
            let u1 = (self.uniform() as f64).max(1e-12);
            let u2 = self.uniform() as f64;
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }
    }

    pub(super) fn image(b: usize, h: usize, w: usize, seed: u64) -> Tensor<4> {
        let mut rng = Lcg(seed);
        let data: Vec<f32> = (0..b * 3 * h * w).map(|_| rng.uniform()).collect();
        Tensor::from_data(TensorData::new(data, [b, 3, h, w]), &device())
    }

    pub(super) fn small_decoder(bits: usize) -> HiddenDecoder {
        HiddenDecoderConfig::new(bits)
            .with_channels(8)
            .with_depth(2)
            .init(&device())
    }
}
