//! The HiDDeN message encoder used to pretrain the decoder: [`HiddenEncoderConfig`],
//! [`HiddenEncoder`].

use std::path::Path;

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::store::RecordError;
use burn::tensor::{Device, Tensor};

use super::ConvBnRelu;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::model::tests::{device, image, small_decoder, to_vec};
    use burn::tensor::TensorData;

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
}
