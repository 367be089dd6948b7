//! The watermark bit decoder D and the wavelet transform it reads through.
//!
//! The paper ("Where, What, Why", §3, decoupled finetuning) decodes with a frozen HiDDeN decoder
//! D_ψ producing L logits (L ∈ {32, 48, 64}) from the **LL band of a 2-level DWT** of a rendered
//! view, embeds only in that band, and regularises the multi-level DWT subbands with L1
//! distances (L_wav^low on LL, L_wav^high on LH/HL/HH). This module holds:
//!
//! - [`dwt`](mod@dwt): multi-level orthonormal 2D Haar DWT and its inverse on burn tensors
//!   `[B, C, H, W]`, differentiable, any size (edge padding to a multiple of 2^levels). Why Haar
//!   rather than the baselines' `bior4.4`, and the exact band conventions, are in its docs.
//! - [`model`]: [`HiddenDecoder`] (RGB image in [0, 1] → `[B, L]` logits through
//!   [`decoder_input`] = centred LL band), [`HiddenEncoder`] (image-domain HiDDeN encoder used
//!   only to pretrain the decoder), the Stable-Signature [`Whitening`] of the logits, their
//!   configs, and burnpack save/load.
//!
//! - [`data`](mod@data): the image folder, its deterministic held-out split (FNV-1a of the relative
//!   path mod 10 == 0, ≈ 10 %), images in memory and random training crops.
//! - [`encoder`](mod@encoder): the encoder trained with the decoder — HiDDeN's, or (default) a
//!   variant that maps the message to a tiled spatial pattern and trains much faster.
//! - [`train`](mod@train): joint encoder/decoder training with the differentiable attacks
//!   (`splatmark decoder train`), resumable checkpoints, whitening decision, final artifact.
//! - [`eval`](mod@eval): held-out evaluation under the real attacks (`splatmark decoder eval`)
//!   and decoding of images with logit averaging (`splatmark decode`).
//! - [`probe`](mod@probe): the decoder-agnostic probe — messages written by optimisation
//!   through the frozen decoder at a PSNR bound (what the 3D finetuning does), decoded under the
//!   real attacks, perspective tilts and downscales (`splatmark decoder probe`).
//! - [`optrain`](mod@optrain): decoder training with that optimiser as the encoder
//!   (`splatmark decoder train-opt`), GroupNorm decoder, unmarked logits pulled to 0.
//! - [`artifact`]: the artifact files (decoder + encoder burnpacks, JSON sidecar) and the
//!   weights shipped in the binary (`weights/decoder-{32,48,64}.*`).
//! - [`registry`]: which decoder reads an asset's bits — found by the digest its key records
//!   among the current, shipped and archived decoders.
//!
//! Typical finetuning use (`embed::finetune`, planned): build the decoder from its config, load
//! the pretrained weights, [`HiddenDecoder::frozen`], then per view
//! `logits = decoder.forward(attack.apply(render)?)` on an autodiff device, BCE against the
//! message bits, and `backward` to get ∂L/∂render for `render::backward`. The differentiable
//! attacks of the EOT term live in [`crate::attack`] (`attack::diff`). A bit reads as 1 when its
//! (whitened, if a [`Whitening`] is used) logit is > 0.

pub mod artifact;
pub mod data;
pub mod dwt;
pub mod encoder;
pub mod eval;
pub mod model;
pub mod optrain;
pub mod probe;
pub mod projection;
pub mod registry;
pub mod train;

pub use dwt::{Dwt, dwt, haar_level, idwt, inverse_haar_level, ll_band, ll_size, padded_size};
pub use model::{
    BATCH_NORM_EPS, ConvBnRelu, HiddenDecoder, HiddenDecoderConfig, HiddenEncoder,
    HiddenEncoderConfig, Norm, WHITENING_EIGEN_FLOOR, Whitening, WhiteningError, decoder_input,
    group_count, symmetric_eigen,
};

pub use artifact::{Sidecar, WatermarkModel, WeightsError};
pub use eval::{DecodeReport, EvalOptions, EvalReport};
pub use train::{TrainConfig, TrainError, Trainer};
