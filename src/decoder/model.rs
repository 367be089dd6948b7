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

use std::path::Path;

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{
    BatchNorm, BatchNormConfig, Gelu, GroupNorm, GroupNormConfig, Linear, LinearConfig,
    PaddingConfig2d, Relu,
};
use burn::store::RecordError;
use burn::tensor::module::adaptive_avg_pool2d;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::dwt::ll_band;

/// BatchNorm ε of every ConvBNReLU block (Stable Signature's HiDDeN uses 1e-3).
pub const BATCH_NORM_EPS: f64 = 1e-3;

/// The decoder's input for an RGB image `[B, 3, H, W]` in [0, 1]: the LL band of a
/// `levels`-level Haar DWT, scaled back to image range and centred to [−1, 1]:
/// `LL · 2/2^levels − 1`, shape `[B, 3, ⌈H/2^levels⌉, ⌈W/2^levels⌉]`.
pub fn decoder_input(image: Tensor<4>, levels: usize) -> Tensor<4> {
    let scale = 2.0 / (1u64 << levels) as f64;
    ll_band(image, levels).mul_scalar(scale).sub_scalar(1.0)
}

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

/// Configuration of [`HiddenDecoder`].
#[derive(Config, Debug)]
pub struct HiddenDecoderConfig {
    /// Message length L (the paper uses 32, 48 and 64).
    pub bits: usize,
    /// Channels of the hidden convolutions.
    #[config(default = 64)]
    pub channels: usize,
    /// Number of `ConvBNReLU(C→C)` blocks between the first and the last block.
    #[config(default = 7)]
    pub depth: usize,
    /// Levels of the Haar DWT whose LL band the decoder reads.
    #[config(default = 2)]
    pub dwt_levels: usize,
    /// Normalisation of every block.
    #[config(default = "Norm::Batch")]
    pub norm: Norm,
    /// Convolution kernel side (3 = HiDDeN; 1 = per-pixel, see [`Norm::None`]).
    #[config(default = 3)]
    pub kernel: usize,
    /// The input band is multiplied by this before the first block (a steeper function of the
    /// colours for per-pixel decoders).
    #[config(default = 1.0)]
    pub input_gain: f64,
    /// Colour Fourier features instead of the convolutions (0 = off): the decoder becomes
    /// `linear(mean_x sin(Ω·(u(x) + 1)))`, `u` the centred LL band and Ω a random
    /// `fourier × 3` matrix of standard deviation `fourier_scale` — a function of the histogram
    /// of the band's colours, so exactly invariant to where the colours are (rotation,
    /// perspective, crop, scale), and every feature is 0 on black (a black background carries
    /// nothing). See [`HiddenDecoder::forward_band`].
    #[config(default = 0)]
    pub fourier: usize,
    /// Standard deviation of Ω's entries (per unit of the centred band, whose range is 2).
    #[config(default = 8.0)]
    pub fourier_scale: f64,
    /// Pixels darker than this (|rgb| of the band, in [0, 1] units) are left out of the pooled
    /// features, smoothly: weight `1 − exp(−(|v|/τ)⁴)`, `v = u + 1`. A black background,
    /// and the clamped noise or JPEG ringing an attack leaves on it, then carries nothing;
    /// the features are averaged over the pixels that count (not diluted by the background).
    /// 0 = every pixel counts equally.
    #[config(default = 0.0)]
    pub fourier_dark: f64,
    /// Seed of Ω and of the linear head (drawn on the host, so a decoder is reproducible from
    /// its configuration).
    #[config(default = 0)]
    pub fourier_seed: u64,
}

impl HiddenDecoderConfig {
    /// A decoder with freshly initialised weights (burn's default Kaiming-uniform init, drawn
    /// lazily from the device's RNG on first use).
    ///
    /// # Panics
    /// If `bits` or `channels` is 0.
    pub fn init(&self, device: &Device) -> HiddenDecoder {
        assert!(
            self.bits > 0 && self.channels > 0,
            "bits and channels must be positive"
        );
        if self.fourier > 0 {
            return self.init_fourier(device);
        }
        let mut layers = Vec::with_capacity(self.depth + 2);
        let k = self.kernel.max(1) | 1;
        layers.push(ConvBnRelu::with_kernel(
            3,
            self.channels,
            self.norm,
            k,
            device,
        ));
        for _ in 0..self.depth {
            layers.push(ConvBnRelu::with_kernel(
                self.channels,
                self.channels,
                self.norm,
                k,
                device,
            ));
        }
        layers.push(ConvBnRelu::with_kernel(
            self.channels,
            self.bits,
            self.norm,
            k,
            device,
        ));
        HiddenDecoder {
            layers,
            fourier: None,
            fourier_dark: 0.0,
            linear: LinearConfig::new(self.bits, self.bits).init(device),
            bits: self.bits,
            dwt_levels: self.dwt_levels,
            input_gain: self.input_gain,
        }
    }

    /// The colour-Fourier decoder: Ω ~ N(0, fourier_scale²), the bias Ω·1 (so each feature is
    /// sin(Ω·(u + 1)), 0 on black), and a linear head with N(0, 1/F) weights and no bias, all
    /// drawn from `fourier_seed` on the host.
    fn init_fourier(&self, device: &Device) -> HiddenDecoder {
        use burn::module::Param;
        let f = self.fourier;
        let mut rng = crate::attack::diff::EotRng::new(self.fourier_seed ^ 0x464f_5552);
        let mut normals = |n: usize, sd: f64| -> Vec<f32> {
            let mut v = Vec::with_capacity(n + 1);
            while v.len() < n {
                let (a, b) = rng.normal_pair();
                v.push((a * sd) as f32);
                v.push((b * sd) as f32);
            }
            v.truncate(n);
            v
        };
        let omega = normals(3 * f, self.fourier_scale);
        let bias: Vec<f32> = omega.chunks_exact(3).map(|w| w.iter().sum()).collect();
        let head = normals(f * self.bits, 1.0 / (f as f64).sqrt());
        let mut conv = Conv2dConfig::new([3, f], [1, 1]).init(device);
        conv.weight = Param::from_tensor(Tensor::<4>::from_data(
            TensorData::new(omega, [f, 3, 1, 1]),
            device,
        ));
        conv.bias = Some(Param::from_tensor(Tensor::<1>::from_data(
            TensorData::new(bias, [f]),
            device,
        )));
        let mut linear = LinearConfig::new(f, self.bits).init(device);
        linear.weight = Param::from_tensor(Tensor::<2>::from_data(
            TensorData::new(head, [f, self.bits]),
            device,
        ));
        linear.bias = Some(Param::from_tensor(Tensor::<1>::zeros([self.bits], device)));
        HiddenDecoder {
            layers: Vec::new(),
            fourier: Some(conv),
            fourier_dark: self.fourier_dark,
            linear,
            bits: self.bits,
            dwt_levels: self.dwt_levels,
            input_gain: self.input_gain,
        }
    }
}

/// HiDDeN message decoder reading the DWT LL band: RGB image → L logits (bit = logit > 0).
#[derive(Module, Debug)]
pub struct HiddenDecoder {
    layers: Vec<ConvBnRelu>,
    /// The colour-Fourier projection ([`HiddenDecoderConfig::fourier`]); `layers` is then empty.
    fourier: Option<Conv2d>,
    fourier_dark: f64,
    linear: Linear,
    bits: usize,
    dwt_levels: usize,
    input_gain: f64,
}

impl HiddenDecoder {
    /// Message length L.
    pub fn bits(&self) -> usize {
        self.bits
    }

    /// DWT levels of the input band.
    pub fn dwt_levels(&self) -> usize {
        self.dwt_levels
    }

    /// Logits `[B, L]` of RGB images `[B, 3, H, W]` in [0, 1] (any H, W ≥ 1; ≥ 64 advised).
    ///
    /// # Panics
    /// If the image does not have 3 channels.
    pub fn forward(&self, image: Tensor<4>) -> Tensor<2> {
        let [_, channels, _, _] = image.dims();
        assert_eq!(
            channels, 3,
            "the decoder reads RGB images, got {channels} channels"
        );
        self.forward_band(decoder_input(image, self.dwt_levels))
    }

    /// Logits `[B, L]` of an already prepared input band `[B, 3, h, w]` ([`decoder_input`]).
    pub fn forward_band(&self, band: Tensor<4>) -> Tensor<2> {
        self.linear.forward(self.pooled_band(band))
    }

    /// The pooled features `[B, F]` the linear head reads (F = `fourier` for the colour-Fourier
    /// decoder, the last block's channels otherwise) of RGB images `[B, 3, H, W]` in [0, 1]:
    /// logits = [`head`](Self::head)(pooled).
    pub fn pooled(&self, image: Tensor<4>) -> Tensor<2> {
        self.pooled_band(decoder_input(image, self.dwt_levels))
    }

    /// Number of pooled features F.
    pub fn feature_count(&self) -> usize {
        self.linear.weight.dims()[0]
    }

    /// The linear head: logits `[B, L]` of pooled features `[B, F]`.
    pub fn head(&self, pooled: Tensor<2>) -> Tensor<2> {
        self.linear.forward(pooled)
    }

    /// Pooled features `[B, F]` of a centred LL band ([`decoder_input`]).
    pub fn pooled_band(&self, band: Tensor<4>) -> Tensor<2> {
        let mut x = if self.input_gain == 1.0 {
            band
        } else {
            band.mul_scalar(self.input_gain)
        };
        if let Some(omega) = &self.fourier {
            let features = omega.forward(x.clone()).sin();
            let [b, f, _, _] = features.dims();
            if self.fourier_dark <= 0.0 {
                return adaptive_avg_pool2d(features, [1, 1]).reshape([b, f]);
            }
            // |v|² / τ², v = u + 1 (the band's colours in [0, 2]).
            let tau2 = (2.0 * self.fourier_dark).powi(2);
            let r = x.add_scalar(1.0).powi_scalar(2).sum_dim(1).div_scalar(tau2);
            let w = r.powi_scalar(2).neg().exp().neg().add_scalar(1.0);
            let num = adaptive_avg_pool2d(features * w.clone(), [1, 1]).reshape([b, f]);
            let den = adaptive_avg_pool2d(w, [1, 1])
                .reshape([b, 1])
                .add_scalar(1e-6);
            return num / den;
        }
        for layer in &self.layers {
            x = layer.forward(x);
        }
        let [b, l, _, _] = x.dims();
        adaptive_avg_pool2d(x, [1, 1]).reshape([b, l])
    }

    /// ∂(pooled features)/∂(band) of one centred band (`band`: `[3, h, w]`, planar, as
    /// [`decoder_input`] gives it) in closed form: `F` rows of `3·h·w`, row-major — for the
    /// colour-Fourier decoder, whose features are per-pixel (f_j = mean_p sin(ω_j·x_p + β_j)·w_p
    /// / (mean_p w_p + 1e-6), x = gain·u, w_p the dark weight, or 1). `None` for the
    /// convolutional decoders (their Jacobian takes one backward pass per feature).
    pub fn band_jacobian(&self, band: &[f32], h: usize, w: usize) -> Option<Vec<f64>> {
        use rayon::prelude::*;
        let conv = self.fourier.as_ref()?;
        let omega: Vec<f32> = conv.weight.val().try_into_vec_as::<f32>().ok()?;
        let f = omega.len() / 3;
        let beta: Vec<f32> = match &conv.bias {
            Some(b) => b.val().try_into_vec_as::<f32>().ok()?,
            None => vec![0.0; f],
        };
        let n = h * w;
        if band.len() != 3 * n || beta.len() != f {
            return None;
        }
        let gain = self.input_gain;
        let x = |ch: usize, p: usize| gain * f64::from(band[ch * n + p]);
        // The dark weight w_p = 1 − exp(−r_p²), r_p = |x_p + 1|² / τ², and its gradient.
        let dark = self.fourier_dark > 0.0;
        let tau2 = (2.0 * self.fourier_dark).powi(2);
        let (wp, dwp): (Vec<f64>, Vec<[f64; 3]>) = (0..n)
            .map(|p| {
                if !dark {
                    return (1.0, [0.0; 3]);
                }
                let v: [f64; 3] = std::array::from_fn(|ch| x(ch, p) + 1.0);
                let r = v.iter().map(|a| a * a).sum::<f64>() / tau2;
                let e = (-r * r).exp();
                (1.0 - e, v.map(|a| e * 2.0 * r * 2.0 * a / tau2))
            })
            .unzip();
        let den = if dark {
            wp.iter().sum::<f64>() / n as f64 + 1e-6
        } else {
            1.0
        };
        let mut rows = vec![0.0f64; f * 3 * n];
        rows.par_chunks_mut(3 * n).enumerate().for_each(|(j, row)| {
            let om: [f64; 3] = std::array::from_fn(|ch| f64::from(omega[3 * j + ch]));
            let (sin, cos): (Vec<f64>, Vec<f64>) = (0..n)
                .map(|p| {
                    let z = (0..3).map(|ch| om[ch] * x(ch, p)).sum::<f64>() + f64::from(beta[j]);
                    z.sin_cos()
                })
                .unzip();
            let num = if dark {
                sin.iter().zip(&wp).map(|(s, w)| s * w).sum::<f64>() / n as f64
            } else {
                0.0
            };
            for p in 0..n {
                for ch in 0..3 {
                    let d = (cos[p] * om[ch] * wp[p] + sin[p] * dwp[p][ch]) / (n as f64 * den)
                        - num / (den * den) * dwp[p][ch] / n as f64;
                    row[ch * n + p] = gain * d;
                }
            }
        });
        Some(rows)
    }

    /// The decoder as used during watermark finetuning: parameters need no gradient and
    /// BatchNorm uses its running statistics even on autodiff inputs ([`Module::freeze`]).
    pub fn frozen(self) -> Self {
        self.freeze()
    }

    /// Saves the weights (BatchNorm running statistics included) to a burnpack file.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), RecordError> {
        self.clone().save_file(path)
    }

    /// Loads weights saved by [`save`](Self::save) into a decoder built from `config`; fails if
    /// the file does not match the architecture (names or shapes).
    pub fn load(
        config: &HiddenDecoderConfig,
        path: impl AsRef<Path>,
        device: &Device,
    ) -> Result<Self, RecordError> {
        config.init(device).try_load_file(path)
    }
}

/// Configuration of [`HiddenEncoder`].
#[derive(Config, Debug)]
pub struct HiddenEncoderConfig {
    /// Message length L.
    pub bits: usize,
    /// Channels of the hidden convolutions.
    #[config(default = 64)]
    pub channels: usize,
    /// Number of `ConvBNReLU` blocks on the image before the message is concatenated (HiDDeN's
    /// `encoder_blocks`, default 4).
    #[config(default = 4)]
    pub blocks: usize,
}

impl HiddenEncoderConfig {
    /// An encoder with freshly initialised weights.
    ///
    /// # Panics
    /// If `bits`, `channels` or `blocks` is 0.
    pub fn init(&self, device: &Device) -> HiddenEncoder {
        assert!(
            self.bits > 0 && self.channels > 0 && self.blocks > 0,
            "bits, channels and blocks must be positive"
        );
        let mut conv_layers = Vec::with_capacity(self.blocks);
        conv_layers.push(ConvBnRelu::new(3, self.channels, device));
        for _ in 1..self.blocks {
            conv_layers.push(ConvBnRelu::new(self.channels, self.channels, device));
        }
        HiddenEncoder {
            conv_layers,
            after_concat: ConvBnRelu::new(self.bits + self.channels + 3, self.channels, device),
            final_layer: Conv2dConfig::new([self.channels, 3], [1, 1]).init(device),
            bits: self.bits,
        }
    }
}

/// HiDDeN message encoder, used only to pretrain the decoder: image + message → residual.
///
/// Works in the **image domain** (as HiDDeN and Stable Signature): convolutions on the centred
/// image `2x − 1`, the message `2m − 1` (±1) broadcast to every pixel and concatenated with the
/// features and the image, a `ConvBNReLU`, a final 1 × 1 convolution to 3 channels and a `tanh`.
/// The decoder reads only the LL band, so training pushes the residual's useful energy into the
/// low frequencies by itself; an encoder working on LL directly would, through the Haar
/// synthesis, paint piecewise-constant 4 × 4 blocks, which are easy to see and to filter out.
#[derive(Module, Debug)]
pub struct HiddenEncoder {
    conv_layers: Vec<ConvBnRelu>,
    after_concat: ConvBnRelu,
    final_layer: Conv2d,
    bits: usize,
}

impl HiddenEncoder {
    /// Message length L.
    pub fn bits(&self) -> usize {
        self.bits
    }

    /// Residual `[B, 3, H, W]` in (−1, 1) for images `[B, 3, H, W]` in [0, 1] and messages
    /// `[B, L]` of bits in {0, 1}.
    ///
    /// # Panics
    /// If the shapes do not fit (3 channels, L bits, same batch).
    pub fn residual(&self, image: Tensor<4>, message: Tensor<2>) -> Tensor<4> {
        let [b, channels, h, w] = image.dims();
        let [mb, bits] = message.dims();
        assert_eq!(channels, 3, "the encoder takes RGB images");
        assert_eq!(mb, b, "one message per image");
        assert_eq!(bits, self.bits, "message length");
        let centred = image.mul_scalar(2.0).sub_scalar(1.0);
        let mut features = centred.clone();
        for layer in &self.conv_layers {
            features = layer.forward(features);
        }
        let message = message
            .mul_scalar(2.0)
            .sub_scalar(1.0)
            .reshape([b, bits, 1, 1])
            .expand([b, bits, h, w]);
        let x = Tensor::cat(vec![message, features, centred], 1);
        self.final_layer
            .forward(self.after_concat.forward(x))
            .tanh()
    }

    /// Watermarked images `image + strength · residual` (not clamped, so the gradient is never
    /// cut; clamp before saving or quantising).
    pub fn embed(&self, image: Tensor<4>, message: Tensor<2>, strength: f64) -> Tensor<4> {
        let residual = self.residual(image.clone(), message);
        image.add(residual.mul_scalar(strength))
    }

    /// Saves the weights to a burnpack file.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), RecordError> {
        self.clone().save_file(path)
    }

    /// Loads weights saved by [`save`](Self::save) into an encoder built from `config`.
    pub fn load(
        config: &HiddenEncoderConfig,
        path: impl AsRef<Path>,
        device: &Device,
    ) -> Result<Self, RecordError> {
        config.init(device).try_load_file(path)
    }
}

/// Why [`Whitening::fit`] failed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WhiteningError {
    /// Fewer than two samples.
    #[error("whitening needs at least 2 logit vectors, got {0}")]
    TooFewSamples(usize),
    /// Samples of different lengths, or of length 0.
    #[error("logit vector {index} has length {len}, expected {expected} (> 0)")]
    Ragged {
        index: usize,
        len: usize,
        expected: usize,
    },
    /// A NaN or infinite logit.
    #[error("logit vector {0} holds a non-finite value")]
    NotFinite(usize),
    /// Every logit is constant: there is no direction to whiten.
    #[error("the logits do not vary")]
    Degenerate,
}

/// Affine whitening of the decoder's logits, `W · (z − μ)`, with μ the mean and W = Σ^(−1/2) =
/// U Λ^(−1/2) Uᵀ (ZCA) for the covariance Σ = U Λ Uᵀ of the decoder's outputs on natural,
/// unwatermarked images — Stable Signature's recipe (their `*_whit` decoders, which WateRF and
/// 3D-GSW load, are HiDDeN plus this layer). After it, the logits of unwatermarked images have
/// zero mean and identity covariance, so their bits are (close to) fair independent coins, which
/// is what the binomial false-positive statistics of verification assume.
///
/// Eigenvalues below `1e-6 · λ_max` are raised to that floor, so directions in which the
/// samples do not vary (fewer samples than bits, or a stuck bit) are not blown up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Whitening {
    /// μ, length L.
    pub mean: Vec<f32>,
    /// W, L × L row-major (symmetric).
    pub matrix: Vec<f32>,
}

/// Relative eigenvalue floor of [`Whitening::fit`].
pub const WHITENING_EIGEN_FLOOR: f64 = 1e-6;

impl Whitening {
    /// The identity map on L logits.
    pub fn identity(bits: usize) -> Self {
        let mut matrix = vec![0.0; bits * bits];
        for i in 0..bits {
            matrix[i * bits + i] = 1.0;
        }
        Self {
            mean: vec![0.0; bits],
            matrix,
        }
    }

    /// Number of logits L.
    pub fn bits(&self) -> usize {
        self.mean.len()
    }

    /// Checks samples for [`fit`](Self::fit) and [`centering`](Self::centering) and returns
    /// their mean (f64).
    fn sample_mean(logits: &[Vec<f32>]) -> Result<Vec<f64>, WhiteningError> {
        let n = logits.len();
        if n < 2 {
            return Err(WhiteningError::TooFewSamples(n));
        }
        let l = logits[0].len();
        for (index, row) in logits.iter().enumerate() {
            if row.len() != l || l == 0 {
                return Err(WhiteningError::Ragged {
                    index,
                    len: row.len(),
                    expected: l,
                });
            }
            if row.iter().any(|v| !v.is_finite()) {
                return Err(WhiteningError::NotFinite(index));
            }
        }
        let mut mean = vec![0.0f64; l];
        for row in logits {
            for (m, &v) in mean.iter_mut().zip(row) {
                *m += v as f64;
            }
        }
        for m in &mut mean {
            *m /= n as f64;
        }
        Ok(mean)
    }

    /// Centering only: μ fitted as in [`fit`](Self::fit), W = identity. It removes the bias of
    /// each bit on natural images (bit i = `z_i > μ_i`) without mixing or rescaling the logits,
    /// so it costs watermarked images far less accuracy than the full whitening when μ is small
    /// next to their logits.
    pub fn centering(logits: &[Vec<f32>]) -> Result<Self, WhiteningError> {
        let mean = Self::sample_mean(logits)?;
        let mut w = Self::identity(mean.len());
        w.mean = mean.into_iter().map(|m| m as f32).collect();
        Ok(w)
    }

    /// Whether W is the identity (a [`centering`](Self::centering)).
    pub fn is_centering(&self) -> bool {
        let l = self.bits();
        self.matrix
            .iter()
            .enumerate()
            .all(|(k, &v)| v == if k / l == k % l { 1.0 } else { 0.0 })
    }

    /// Fits μ and W to decoder outputs on natural images (one vector of L logits per image),
    /// in f64 with a Jacobi eigen-decomposition of the covariance (divided by n, as Stable
    /// Signature does).
    pub fn fit(logits: &[Vec<f32>]) -> Result<Self, WhiteningError> {
        let mean = Self::sample_mean(logits)?;
        let (n, l) = (logits.len(), mean.len());
        let mut cov = vec![0.0f64; l * l];
        for row in logits {
            for i in 0..l {
                let di = row[i] as f64 - mean[i];
                for j in i..l {
                    cov[i * l + j] += di * (row[j] as f64 - mean[j]);
                }
            }
        }
        for i in 0..l {
            for j in i..l {
                let v = cov[i * l + j] / n as f64;
                cov[i * l + j] = v;
                cov[j * l + i] = v;
            }
        }
        let (values, vectors) = symmetric_eigen(&cov, l);
        let max = values.iter().cloned().fold(0.0f64, f64::max);
        if !(max > 0.0) {
            return Err(WhiteningError::Degenerate);
        }
        let floor = max * WHITENING_EIGEN_FLOOR;
        let inv_sqrt: Vec<f64> = values.iter().map(|&v| 1.0 / v.max(floor).sqrt()).collect();
        let mut matrix = vec![0.0f32; l * l];
        for i in 0..l {
            for j in 0..l {
                let w: f64 = (0..l)
                    .map(|k| vectors[i * l + k] * inv_sqrt[k] * vectors[j * l + k])
                    .sum();
                matrix[i * l + j] = w as f32;
            }
        }
        Ok(Self {
            mean: mean.into_iter().map(|m| m as f32).collect(),
            matrix,
        })
    }

    /// Whitened logits `[B, L]` = `(z − μ) Wᵀ` (differentiable).
    ///
    /// # Panics
    /// If `logits` does not have L columns.
    pub fn apply(&self, logits: Tensor<2>) -> Tensor<2> {
        let l = self.bits();
        let [_, cols] = logits.dims();
        assert_eq!(cols, l, "whitening is for {l} logits, got {cols}");
        let device = logits.device();
        let mean = Tensor::<2>::from_data(TensorData::new(self.mean.clone(), [1, l]), &device);
        let w = Tensor::<2>::from_data(TensorData::new(self.matrix.clone(), [l, l]), &device);
        logits.sub(mean).matmul(w.transpose())
    }

    /// [`apply`](Self::apply) on one logit vector, on the host.
    ///
    /// # Panics
    /// If `logits` does not have length L.
    pub fn apply_row(&self, logits: &[f32]) -> Vec<f32> {
        let l = self.bits();
        assert_eq!(logits.len(), l, "whitening is for {l} logits");
        (0..l)
            .map(|i| {
                (0..l)
                    .map(|j| self.matrix[i * l + j] as f64 * (logits[j] - self.mean[j]) as f64)
                    .sum::<f64>() as f32
            })
            .collect()
    }
}

/// Eigen-decomposition of a symmetric `n × n` matrix (row-major) by the cyclic Jacobi method:
/// returns the eigenvalues and the eigenvectors as the columns of an `n × n` row-major matrix.
/// Accurate to a few ulps for the small (n ≤ 64) covariance matrices it is used on.
pub fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(a.len(), n * n, "matrix is not {n}×{n}");
    let mut a = a.to_vec();
    let mut v = vec![0.0f64; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let norm: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum::<f64>()
            .sqrt();
        if !(off > 1e-15 * norm) {
            break;
        }
        for p in 0..n {
            for q in (p + 1)..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let app = a[p * n + p];
                let aqq = a[q * n + q];
                // Rotation angle zeroing a[p][q] (Golub & Van Loan, Algorithm 8.4.1).
                let theta = (aqq - app) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let akp = a[k * n + p];
                    let akq = a[k * n + q];
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let apk = a[p * n + k];
                    let aqk = a[q * n + k];
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let vkp = v[k * n + p];
                    let vkq = v[k * n + q];
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let values = (0..n).map(|i| a[i * n + i]).collect();
    (values, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device() -> Device {
        Device::flex()
    }

    fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    struct Lcg(u64);
    impl Lcg {
        fn uniform(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        fn normal(&mut self) -> f64 {
            let u1 = (self.uniform() as f64).max(1e-12);
            let u2 = self.uniform() as f64;
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }
    }

    fn image(b: usize, h: usize, w: usize, seed: u64) -> Tensor<4> {
        let mut rng = Lcg(seed);
        let data: Vec<f32> = (0..b * 3 * h * w).map(|_| rng.uniform()).collect();
        Tensor::from_data(TensorData::new(data, [b, 3, h, w]), &device())
    }

    fn small_decoder(bits: usize) -> HiddenDecoder {
        HiddenDecoderConfig::new(bits)
            .with_channels(8)
            .with_depth(2)
            .init(&device())
    }

    #[test]
    fn decoder_input_is_centred_block_mean() {
        let x = Tensor::<4>::full([1, 3, 8, 8], 0.75, &device());
        let band = decoder_input(x, 2);
        assert_eq!(band.dims(), [1, 3, 2, 2]);
        assert!(to_vec(band).iter().all(|v| (v - 0.5).abs() < 1e-6));
    }

    #[test]
    fn output_shape_for_square_and_odd_sizes() {
        let dec = small_decoder(32);
        assert_eq!(dec.forward(image(2, 64, 64, 1)).dims(), [2, 32]);
        assert_eq!(dec.forward(image(1, 100, 150, 2)).dims(), [1, 32]);
        // Default architecture (64 channels, depth 7), 48 bits, one 64 × 64 image.
        let full = HiddenDecoderConfig::new(48).init(&device());
        assert_eq!(full.forward(image(1, 64, 64, 3)).dims(), [1, 48]);
    }

    #[test]
    fn deterministic_and_batch_independent() {
        let dec = small_decoder(16);
        let x = image(3, 64, 64, 4);
        let a = to_vec(dec.forward(x.clone()));
        let b = to_vec(dec.forward(x.clone()));
        assert_eq!(a, b);
        // Inference BatchNorm: an image's logits do not depend on the rest of the batch.
        let single = to_vec(dec.forward(x.narrow(0, 1, 1)));
        for (s, t) in single.iter().zip(&a[16..32]) {
            assert!((s - t).abs() < 1e-5, "{s} vs {t}");
        }
    }

    #[test]
    fn save_load_round_trip_gives_identical_outputs() {
        let config = HiddenDecoderConfig::new(16).with_channels(8).with_depth(1);
        let dec = config.init(&device());
        // One training-mode pass (autodiff input) moves the BatchNorm running statistics away
        // from their initial 0/1, so the test also covers them.
        let _ = dec.forward(image(2, 64, 64, 5).autodiff());
        let x = image(2, 64, 64, 6);
        let before = to_vec(dec.forward(x.clone()));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("decoder.bpk");
        dec.save(&path).unwrap();
        let loaded = HiddenDecoder::load(&config, &path, &device()).unwrap();
        assert_eq!(to_vec(loaded.forward(x.clone())), before);
        // A fresh decoder differs (so the equality above is not vacuous).
        let fresh = config.init(&device());
        assert_ne!(to_vec(fresh.forward(x)), before);
        // Wrong architecture: refused.
        let other = HiddenDecoderConfig::new(32).with_channels(8).with_depth(1);
        assert!(HiddenDecoder::load(&other, &path, &device()).is_err());
    }

    #[test]
    fn the_colour_fourier_jacobian_in_closed_form_is_autodiffs() {
        let (h, w) = (6, 5);
        let mut rng = Lcg(5);
        let band: Vec<f32> = (0..3 * h * w)
            .map(|k| {
                if k % 7 == 0 {
                    -0.95
                } else {
                    2.0 * rng.uniform() - 1.0
                }
            })
            .collect();
        let ad = Device::flex().autodiff();
        for (dark, gain) in [(0.1, 1.0), (0.0, 1.5)] {
            let dec = HiddenDecoderConfig::new(8)
                .with_fourier(6)
                .with_fourier_scale(4.0)
                .with_fourier_dark(dark)
                .with_input_gain(gain)
                .init(&ad);
            let fast = dec.band_jacobian(&band, h, w).expect("colour-Fourier");
            for j in 0..6 {
                let x = Tensor::<4>::from_data(TensorData::new(band.clone(), [1, 3, h, w]), &ad)
                    .require_grad();
                let grads = dec.pooled_band(x.clone()).narrow(1, j, 1).sum().backward();
                let slow = x.grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap();
                for (k, &b) in slow.iter().enumerate() {
                    let a = fast[j * 3 * h * w + k];
                    assert!(
                        (a - f64::from(b)).abs() < 1e-4 * (1.0 + a.abs()),
                        "dark {dark}, feature {j}, entry {k}: {a} vs {b}"
                    );
                }
            }
        }
        let conv = HiddenDecoderConfig::new(8)
            .with_channels(4)
            .with_depth(1)
            .init(&ad);
        assert!(conv.band_jacobian(&band, h, w).is_none());
    }

    #[test]
    fn colour_fourier_decoder_reads_the_colours_not_where_they_are() {
        let config = HiddenDecoderConfig::new(16)
            .with_fourier(32)
            .with_fourier_scale(8.0)
            .with_fourier_dark(0.1);
        let dec = config.init(&device());
        // A 64² object on a black background (its values kept clear of the dark cut-off).
        let object: Vec<f32> = {
            let mut rng = Lcg(11);
            (0..3 * 64 * 64)
                .map(|_| 0.3 + 0.7 * rng.uniform())
                .collect()
        };
        let obj = Tensor::<4>::from_data(TensorData::new(object, [1, 3, 64, 64]), &device());
        let z = to_vec(dec.forward(obj.clone()));
        assert!(z.iter().any(|v| v.abs() > 1e-3), "logits {z:?}");
        let close = |a: &[f32], b: &[f32], what: &str| {
            for (x, y) in a.iter().zip(b) {
                assert!(
                    (x - y).abs() < 1e-4 * (1.0 + x.abs()),
                    "{what}: {a:?} vs {b:?}"
                );
            }
        };
        // Rotated by 90° and mirrored: the LL band's colours are the same multiset.
        let rotated = obj.clone().swap_dims(2, 3).flip([3]);
        close(&z, &to_vec(dec.forward(rotated)), "rotation");
        close(&z, &to_vec(dec.forward(obj.clone().flip([2]))), "mirror");
        // Shown smaller in a larger black frame (more background): the same logits.
        let framed = Tensor::<4>::zeros([1, 3, 128, 192], &device())
            .slice_assign([0..1, 0..3, 32..96, 64..128], obj.clone());
        close(&z, &to_vec(dec.forward(framed)), "black frame");
        // Other colours: other logits.
        let other = to_vec(dec.forward(obj.clone().mul_scalar(0.9)));
        assert!(z.iter().zip(&other).any(|(a, b)| (a - b).abs() > 1e-3));
        // The frozen decoder passes a gradient to the image.
        let x = obj.autodiff().require_grad();
        let grads = dec.frozen().forward(x.clone()).sum().backward();
        let g = to_vec(x.grad(&grads).expect("image gradient"));
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| *v != 0.0));
        // Reproducible from the configuration; another seed, another decoder.
        let dec = config.init(&device());
        let y = image(1, 64, 64, 3);
        let before = to_vec(dec.forward(y.clone()));
        assert_eq!(to_vec(config.init(&device()).forward(y.clone())), before);
        let reseeded = config.clone().with_fourier_seed(1).init(&device());
        assert_ne!(to_vec(reseeded.forward(y.clone())), before);
        // Save / load keeps the random frequencies.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fourier.bpk");
        dec.save(&path).unwrap();
        let loaded = HiddenDecoder::load(&config, &path, &device()).unwrap();
        assert_eq!(to_vec(loaded.forward(y)), before);
    }

    #[test]
    fn frozen_decoder_passes_gradients_to_the_image_only() {
        let dec = small_decoder(8).frozen();
        let x = image(1, 64, 64, 7).autodiff().require_grad();
        let logits = dec.forward(x.clone());
        let grads = logits.sum().backward();
        let g = to_vec(x.grad(&grads).expect("image gradient"));
        assert!(g.iter().all(|v| v.is_finite()));
        assert!(g.iter().any(|v| *v != 0.0));
        assert!(dec.linear.weight.val().grad(&grads).is_none());
        assert!(dec.layers[0].conv.weight.val().grad(&grads).is_none());
        // Running statistics unchanged by the frozen forward: same output on a plain device.
        let y = image(1, 64, 64, 8);
        let dec2 = small_decoder(8);
        let plain = to_vec(dec2.forward(y.clone()));
        let frozen = dec2.clone().frozen();
        let _ = frozen.forward(image(1, 64, 64, 9).autodiff());
        assert_eq!(to_vec(frozen.forward(y)), plain);
    }

    #[test]
    fn encoder_residual_shape_range_and_gradient() {
        let enc = HiddenEncoderConfig::new(16)
            .with_channels(8)
            .with_blocks(2)
            .init(&device());
        let x = image(2, 32, 48, 10);
        let msg = Tensor::<2>::from_data(
            TensorData::new(
                (0..32).map(|i| (i % 3 == 0) as u8 as f32).collect(),
                [2, 16],
            ),
            &device(),
        );
        let r = enc.residual(x.clone(), msg.clone());
        assert_eq!(r.dims(), [2, 3, 32, 48]);
        assert!(to_vec(r).iter().all(|v| v.abs() <= 1.0));
        // End to end: the decoder's loss reaches the encoder's weights and the image.
        let dec = small_decoder(16);
        let xa = x.autodiff().require_grad();
        let wm = enc.embed(xa.clone(), msg.autodiff(), 0.05);
        let grads = dec.forward(wm).sum().backward();
        assert!(xa.grad(&grads).is_some());
    }

    #[test]
    fn jacobi_reconstructs_a_symmetric_matrix() {
        let n = 6;
        let mut rng = Lcg(3);
        let mut a = vec![0.0f64; n * n];
        for i in 0..n {
            for j in i..n {
                let v = rng.normal();
                a[i * n + j] = v;
                a[j * n + i] = v;
            }
        }
        let (values, v) = symmetric_eigen(&a, n);
        for i in 0..n {
            for j in 0..n {
                let r: f64 = (0..n)
                    .map(|k| v[i * n + k] * values[k] * v[j * n + k])
                    .sum();
                assert!((r - a[i * n + j]).abs() < 1e-10);
                let o: f64 = (0..n).map(|k| v[k * n + i] * v[k * n + j]).sum();
                assert!((o - (i == j) as u8 as f64).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn whitening_gives_zero_mean_identity_covariance() {
        // Correlated logits: z = A·g + m with a fixed mixing matrix A.
        let l = 8;
        let mut rng = Lcg(11);
        let mix: Vec<f64> = (0..l * l).map(|_| rng.normal()).collect();
        let samples: Vec<Vec<f32>> = (0..2000)
            .map(|_| {
                let g: Vec<f64> = (0..l).map(|_| rng.normal()).collect();
                (0..l)
                    .map(|i| {
                        let s: f64 = (0..l).map(|k| mix[i * l + k] * g[k]).sum();
                        (s + 3.0 + i as f64) as f32
                    })
                    .collect()
            })
            .collect();
        let w = Whitening::fit(&samples).unwrap();
        let white: Vec<Vec<f32>> = samples.iter().map(|z| w.apply_row(z)).collect();
        for i in 0..l {
            let mean: f64 = white.iter().map(|z| z[i] as f64).sum::<f64>() / white.len() as f64;
            assert!(mean.abs() < 1e-4, "mean {mean}");
            for j in 0..l {
                let c: f64 = white.iter().map(|z| z[i] as f64 * z[j] as f64).sum::<f64>()
                    / white.len() as f64;
                let expected = (i == j) as u8 as f64;
                assert!((c - expected).abs() < 1e-3, "cov[{i}][{j}] = {c}");
            }
        }
        // Tensor path = host path.
        let batch: Vec<f32> = samples[..4].iter().flatten().copied().collect();
        let t = w.apply(Tensor::from_data(TensorData::new(batch, [4, l]), &device()));
        let t = to_vec(t);
        for (r, z) in samples[..4].iter().enumerate() {
            for (i, v) in w.apply_row(z).iter().enumerate() {
                assert!((t[r * l + i] - v).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn whitening_rejects_bad_input_and_survives_rank_deficiency() {
        assert_eq!(
            Whitening::fit(&[vec![1.0, 2.0]]),
            Err(WhiteningError::TooFewSamples(1))
        );
        assert!(matches!(
            Whitening::fit(&[vec![1.0, 2.0], vec![1.0]]),
            Err(WhiteningError::Ragged { index: 1, .. })
        ));
        assert_eq!(
            Whitening::fit(&[vec![1.0, f32::NAN], vec![1.0, 2.0]]),
            Err(WhiteningError::NotFinite(0))
        );
        assert_eq!(
            Whitening::fit(&[vec![1.0, 2.0], vec![1.0, 2.0]]),
            Err(WhiteningError::Degenerate)
        );
        // 3 samples of 8 logits: rank 2, still finite.
        let mut rng = Lcg(5);
        let samples: Vec<Vec<f32>> = (0..3)
            .map(|_| (0..8).map(|_| rng.normal() as f32).collect())
            .collect();
        let w = Whitening::fit(&samples).unwrap();
        assert!(w.matrix.iter().all(|v| v.is_finite()));
        assert_eq!(
            Whitening::identity(4).apply_row(&[1.0, -2.0, 3.0, 0.5]),
            vec![1.0, -2.0, 3.0, 0.5]
        );
    }

    #[test]
    fn centering_removes_the_mean_and_nothing_else() {
        // Bit 0 biased to 1 (+2), bit 1 biased to 0 (−1), bit 2 fair; correlated noise.
        let mut rng = Lcg(3);
        let samples: Vec<Vec<f32>> = (0..4000)
            .map(|_| {
                let g = rng.normal();
                vec![
                    (2.0 + g) as f32,
                    (-1.0 + 0.5 * g) as f32,
                    rng.normal() as f32,
                ]
            })
            .collect();
        let c = Whitening::centering(&samples).unwrap();
        assert!(c.is_centering());
        assert!(!Whitening::fit(&samples).unwrap().is_centering());
        assert!((c.mean[0] - 2.0).abs() < 0.06 && (c.mean[1] + 1.0).abs() < 0.03);
        let z = [5.0, 7.0, -3.0];
        let out = c.apply_row(&z);
        for i in 0..3 {
            assert!((out[i] - (z[i] - c.mean[i])).abs() < 1e-6);
        }
        // The share of ones per bit becomes about one half.
        for i in 0..2 {
            let ones = samples.iter().filter(|s| c.apply_row(s)[i] > 0.0).count() as f64
                / samples.len() as f64;
            assert!((ones - 0.5).abs() < 0.05, "bit {i}: {ones}");
        }
        assert_eq!(
            Whitening::centering(&[vec![1.0]]),
            Err(WhiteningError::TooFewSamples(1))
        );
    }
}
