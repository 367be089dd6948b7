//! The HiDDeN bit decoder: [`HiddenDecoderConfig`], [`HiddenDecoder`] (convolutional or
//! colour-Fourier) and its input band ([`decoder_input`]).

use std::path::Path;

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig};
use burn::store::RecordError;
use burn::tensor::module::adaptive_avg_pool2d;
use burn::tensor::{Device, Tensor, TensorData};

use super::{ConvBnRelu, Norm};
use crate::decoder::dwt::ll_band;

/// The decoder's input for an RGB image `[B, 3, H, W]` in [0, 1]: the LL band of a
/// `levels`-level Haar DWT, scaled back to image range and centred to [−1, 1]:
/// `LL · 2/2^levels − 1`, shape `[B, 3, ⌈H/2^levels⌉, ⌈W/2^levels⌉]`.
pub fn decoder_input(image: Tensor<4>, levels: usize) -> Tensor<4> {
    let scale = 2.0 / (1u64 << levels) as f64;
    ll_band(image, levels).mul_scalar(scale).sub_scalar(1.0)
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
    /// Convolution kernel side (3 = HiDDeN; 1 = per-pixel, see [`Norm::Off`]).
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

    /// Pooled features `[B, F]` of a centred LL band ([`decoder_input`]). A colour-Fourier
    /// decoder reading a band on the CPU without autodiff (calibration, verification,
    /// evaluation) computes them on the host ([`super::FourierHost`]: the same function, fused).
    pub fn pooled_band(&self, band: Tensor<4>) -> Tensor<2> {
        if let Some(host) = (!band.is_autodiff() && band.device() == Device::flex())
            .then(|| self.fourier_host())
            .flatten()
        {
            let [b, _, h, w] = band.dims();
            let values: Vec<f32> = band.try_into_vec_as::<f32>().expect("a band on the host");
            let pooled = host.forward(&values, h, w).pooled;
            return Tensor::from_data(
                TensorData::new(pooled, [b, host.features()]),
                &Device::flex(),
            );
        }
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

    /// The colour-Fourier projection's weights on the host: Ω (`F × 3`, row-major) and β (zeros
    /// without a bias); `None` for the convolutional decoders.
    fn fourier_weights(&self) -> Option<(Vec<f32>, Vec<f32>)> {
        let conv = self.fourier.as_ref()?;
        let omega: Vec<f32> = conv.weight.val().try_into_vec_as::<f32>().ok()?;
        let beta: Vec<f32> = match &conv.bias {
            Some(b) => b.val().try_into_vec_as::<f32>().ok()?,
            None => vec![0.0; omega.len() / 3],
        };
        Some((omega, beta))
    }

    /// The colour-Fourier projection on the host ([`FourierHost`]: the pooled features and
    /// their gradient in one fused pass), or `None` for the convolutional decoders.
    pub fn fourier_host(&self) -> Option<super::FourierHost> {
        let (omega, beta) = self.fourier_weights()?;
        Some(super::FourierHost::new(
            &omega,
            &beta,
            self.input_gain,
            self.fourier_dark,
        ))
    }

    /// ∂(pooled features)/∂(band) of one centred band (`band`: `[3, h, w]`, planar, as
    /// [`decoder_input`] gives it) in closed form: `F` rows of `3·h·w`, row-major — for the
    /// colour-Fourier decoder, whose features are per-pixel (f_j = mean_p sin(ω_j·x_p + β_j)·w_p
    /// / (mean_p w_p + 1e-6), x = gain·u, w_p the dark weight, or 1). `None` for the
    /// convolutional decoders (their Jacobian takes one backward pass per feature).
    pub fn band_jacobian(&self, band: &[f32], h: usize, w: usize) -> Option<Vec<f64>> {
        use rayon::prelude::*;
        let (omega, beta) = self.fourier_weights()?;
        let f = omega.len() / 3;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::model::tests::{Lcg, device, image, small_decoder, to_vec};

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

    /// Band values uniform in [−1, 1), every `every`-th one `dark` (a near-black pixel, where
    /// the dark weight bends).
    fn centred_band(len: usize, every: usize, dark: f32, rng: &mut Lcg) -> Vec<f32> {
        (0..len)
            .map(|k| {
                if k % every == 0 {
                    dark
                } else {
                    2.0 * rng.uniform() - 1.0
                }
            })
            .collect()
    }

    #[test]
    fn the_colour_fourier_jacobian_in_closed_form_is_autodiffs() {
        let (h, w) = (6, 5);
        let band = centred_band(3 * h * w, 7, -0.95, &mut Lcg(5));
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
    fn the_fused_host_features_and_their_gradient_are_burns() {
        // Two images of 37 × 41 (two pixel chunks), 13 features (not a multiple of the lanes).
        let (b, h, w, f) = (2, 37, 41, 13);
        let mut rng = Lcg(9);
        let band = centred_band(b * 3 * h * w, 11, -0.97, &mut rng);
        let g: Vec<f32> = (0..b * f).map(|_| 2.0 * rng.uniform() - 1.0).collect();
        let ad = Device::flex().autodiff();
        for (dark, gain) in [(0.1, 1.0), (0.0, 1.5)] {
            let dec = HiddenDecoderConfig::new(8)
                .with_fourier(f)
                .with_fourier_scale(16.0)
                .with_fourier_dark(dark)
                .with_input_gain(gain)
                .init(&ad);
            let host = dec.fourier_host().expect("colour-Fourier");
            let pass = host.forward(&band, h, w);
            let fused = host.backward(&band, &pass, &g);
            let x = Tensor::<4>::from_data(TensorData::new(band.clone(), [b, 3, h, w]), &ad)
                .require_grad();
            let pooled = dec.pooled_band(x.clone());
            let gt = Tensor::<2>::from_data(TensorData::new(g.clone(), [b, f]), &ad);
            let burn_pooled = pooled.clone().detach().try_into_vec_as::<f32>().unwrap();
            for (k, (a, e)) in pass.pooled.iter().zip(&burn_pooled).enumerate() {
                assert!((a - e).abs() < 2e-5, "dark {dark}, feature {k}: {a} vs {e}");
            }
            let grads = pooled.mul(gt).sum().backward();
            let slow = x.grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap();
            let peak = slow.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            for (k, (a, e)) in fused.iter().zip(&slow).enumerate() {
                assert!(
                    (a - e).abs() < 1e-4 * peak,
                    "dark {dark}, entry {k}: {a} vs {e} (peak {peak})"
                );
            }
        }
        // Without autodiff on the CPU the decoder itself reads its features on the host.
        let dec = HiddenDecoderConfig::new(8)
            .with_fourier(f)
            .with_fourier_scale(16.0)
            .with_fourier_dark(0.1)
            .init(&Device::flex());
        let plain =
            Tensor::<4>::from_data(TensorData::new(band.clone(), [b, 3, h, w]), &Device::flex());
        let on_ad = Tensor::<4>::from_data(TensorData::new(band.clone(), [b, 3, h, w]), &ad);
        let host = dec.pooled_band(plain).try_into_vec_as::<f32>().unwrap();
        let burn = dec.pooled_band(on_ad).try_into_vec_as::<f32>().unwrap();
        assert_eq!(
            host,
            dec.fourier_host().unwrap().forward(&band, h, w).pooled
        );
        for (a, e) in host.iter().zip(&burn) {
            assert!((a - e).abs() < 2e-5, "{a} vs {e}");
        }
        let conv = HiddenDecoderConfig::new(8)
            .with_channels(4)
            .with_depth(1)
            .init(&ad);
        assert!(conv.fourier_host().is_none());
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
}
