//! Differentiable image attacks for EOT (expectation over transformation) training: the
//! distortions of the paper's robustness table written as burn tensor ops on batches
//! `[B, C, H, W]` of images in [0, 1], so the watermark loss of an attacked render
//! back-propagates to the render (and from there to the Gaussians).
//!
//! Every [`DiffAttack`] variant but `Window` is the differentiable counterpart of the
//! [`super::real`] attack of the same name, with the same parameter semantics (taken from the
//! baselines' public code); `Window` is a partial view for EOT training only (a crop at a random
//! place: the bits must be readable from any part of a view, which is what another view of the
//! asset shows):
//!
//! | attack | output shape | neutral value | gradient |
//! |---|---|---|---|
//! | `Noise { sigma, seed }`: `x + σ²·n`, n ~ N(0, 1) | same | σ = 0 | identity |
//! | `Blur { sigma, kernel }`: separable Gaussian, depthwise conv | same | kernel = 1 | exact |
//! | `Rotate { degrees }`: bilinear `grid_sample`, black outside | same | 0° | exact (a.e.) |
//! | `Scale { factor }`: bilinear resize, keeps the new size | ⌊H·f⌋ × ⌊W·f⌋ | 1 | exact |
//! | `Crop { keep }`: centred crop of a fraction of the area | ⌊H·√k⌋ × ⌊W·√k⌋ | 1 | exact |
//! | `Window { keep, x, y }`: the same crop anywhere in the image | ⌊H·√k⌋ × ⌊W·√k⌋ | 1 | exact |
//! | `Jpeg { quality }`: 8×8 DCT quantisation in YCbCr | same | ≈ 100 | straight-through |
//! | `Brightness { factor }`: `clamp(f·x)` | same | 1 | exact (0 where clipped) |
//! | `Contrast { factor }`: `clamp(f·x + (1−f)·mean luma)` | same | 1 | exact (0 where clipped) |
//! | `Chain(steps)`: the steps in order | composed | empty | composed |
//!
//! Conventions (as in [`super::real`]):
//! - **Noise σ is squared**: "Gaussian noise σ = 0.1" adds noise of standard deviation σ² = 0.01,
//!   as the baselines' `image + sigma ** 2 * torch.randn_like(image)`. The noise is drawn on the
//!   host from `seed` (SplitMix64 + Box–Muller, [`EotRng`]), so an attack value is reproducible.
//!   No clamping (clamping would cut the gradient of the pixels it clips).
//! - **Rotation** is counter-clockwise for positive degrees about the image centre, same size,
//!   black where no input pixel lands (torchvision `rotate`, bilinear, no expand); multiples of
//!   90° use exact sines.
//! - **Scale** is per side and keeps the new size. The bilinear resize (half-pixel centres, as
//!   burn's `interpolate`, written as two gathers so that it back-propagates on the GPU too)
//!   does not anti-alias when shrinking, unlike the real attack's triangle filter; for the
//!   factors of the protocol (≥ 0.7) the difference is small.
//! - **Crop** keeps the fraction `keep` of the area, centred as torchvision's `center_crop`.
//! - **Blur** uses torchvision's kernel (sampled at integer offsets, normalised) and reflect
//!   padding (edge replication where the image is smaller than the kernel radius + 1).
//! - **JPEG** is an approximation of a real JPEG round trip: RGB → YCbCr (JFIF, full range),
//!   level shift, edge padding to a multiple of 8, orthonormal 8×8 DCT (= JPEG's DCT), division
//!   by the standard Annex K tables scaled for `quality` the libjpeg way (4:4:4, no chroma
//!   subsampling, as the real attack), rounding with a straight-through estimator
//!   (`q + (round(q) − q).detach()`, i.e. the forward pass rounds, the backward pass is the
//!   identity), dequantisation, inverse DCT, back to RGB, crop, clamp to [0, 1]. It omits the
//!   final rounding to 8 bits (≤ 0.5/255 per value).
//!
//! [`random_composition`] samples attacks from an [`EotConfig`] (a weighted family of attack
//! kinds with parameter ranges); its default covers the paper's table.

mod eot;
mod geometry;
mod jpeg;
mod photometric;

pub use eot::{AttackFamily, EotConfig, EotRng, random_composition};
pub use geometry::perspective_source;
pub(crate) use geometry::resize;
pub use jpeg::{JPEG_CHROMA_TABLE, JPEG_LUMA_TABLE, jpeg_quant_table, straight_through_round};
pub use photometric::gaussian_blur;
pub(crate) use photometric::gaussian_kernel;

use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use geometry::{centre_crop, perspective, rotate};
use jpeg::jpeg;
use photometric::{contrast, noise};

/// Largest image (in pixels per channel) an attack may produce.
pub const MAX_OUTPUT_PIXELS: u64 = 1 << 26;

/// Largest Gaussian-blur kernel accepted.
pub const MAX_BLUR_KERNEL: u32 = 255;

/// Why a differentiable attack could not be applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DiffAttackError {
    /// JPEG quality outside 1..=100.
    #[error("JPEG quality must be in 1..=100, got {0}")]
    JpegQuality(u8),
    /// A parameter is NaN, infinite or out of its range.
    #[error("{attack}: {param} must be {expected}, got {value}")]
    OutOfRange {
        attack: &'static str,
        param: &'static str,
        value: f32,
        expected: &'static str,
    },
    /// Blur kernel even, zero or above [`MAX_BLUR_KERNEL`].
    #[error("blur: kernel size must be odd and in 1..={max}, got {kernel}")]
    BadKernel { kernel: u32, max: u32 },
    /// The attack needs RGB input.
    #[error("{attack}: needs 3 channels, got {channels}")]
    Channels {
        attack: &'static str,
        channels: usize,
    },
    /// The input has no pixels, or the result would have none or too many.
    #[error("{attack}: {height}×{width} input would become {new_height}×{new_width}")]
    BadSize {
        attack: &'static str,
        height: usize,
        width: usize,
        new_height: u64,
        new_width: u64,
    },
    /// A step of a chain failed.
    #[error("chain step {index}: {source}")]
    Chain {
        index: usize,
        source: Box<DiffAttackError>,
    },
}

/// A differentiable attack (see the module docs for each variant's definition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", content = "params", rename_all = "snake_case")]
pub enum DiffAttack {
    /// `x + σ²·n` with n standard normal drawn from `seed`.
    Noise { sigma: f32, seed: u64 },
    /// Gaussian blur, standard deviation `sigma` (> 0, pixels), odd `kernel` size.
    Blur { sigma: f32, kernel: u32 },
    /// Counter-clockwise rotation by `degrees` about the centre, same size, black corners.
    Rotate { degrees: f32 },
    /// The image seen as a flat picture tilted by `x_degrees` about its horizontal axis and
    /// `y_degrees` about its vertical axis (through its centre), through a pinhole camera whose
    /// focal length is the image width: the foreshortening of viewing a surface from another
    /// direction. Same size, bilinear, black outside.
    Perspective { x_degrees: f32, y_degrees: f32 },
    /// Bilinear resize of each side by `factor` (> 0); keeps the new size.
    Scale { factor: f32 },
    /// Centre crop keeping the fraction `keep` ∈ (0, 1] of the area; keeps the cropped size.
    Crop { keep: f32 },
    /// The crop of `Crop { keep }` placed at `x`, `y` ∈ [0, 1] of the free room (0, 0: the top
    /// left corner; 0.5, 0.5: centred); keeps the cropped size.
    Window { keep: f32, x: f32, y: f32 },
    /// Differentiable JPEG approximation at `quality` (1..=100).
    Jpeg { quality: u8 },
    /// `clamp(factor·x, 0, 1)`, factor ≥ 0.
    Brightness { factor: f32 },
    /// `clamp(factor·x + (1 − factor)·mean luma, 0, 1)` per image, factor ≥ 0.
    Contrast { factor: f32 },
    /// The steps in order.
    Chain(Vec<DiffAttack>),
}

impl DiffAttack {
    /// Short snake_case name (the serde tag).
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Noise { .. } => "noise",
            Self::Blur { .. } => "blur",
            Self::Rotate { .. } => "rotate",
            Self::Perspective { .. } => "perspective",
            Self::Scale { .. } => "scale",
            Self::Crop { .. } => "crop",
            Self::Window { .. } => "window",
            Self::Jpeg { .. } => "jpeg",
            Self::Brightness { .. } => "brightness",
            Self::Contrast { .. } => "contrast",
            Self::Chain(_) => "chain",
        }
    }

    /// Checks the parameters that do not depend on the input.
    pub fn validate(&self) -> Result<(), DiffAttackError> {
        let attack = self.kind();
        let range = |param, value: f32, ok: bool, expected| {
            if ok && value.is_finite() {
                Ok(())
            } else {
                Err(DiffAttackError::OutOfRange {
                    attack,
                    param,
                    value,
                    expected,
                })
            }
        };
        match *self {
            Self::Noise { sigma, .. } => range("sigma", sigma, sigma >= 0.0, "≥ 0"),
            Self::Blur { sigma, kernel } => {
                range("sigma", sigma, sigma > 0.0, "> 0")?;
                if kernel % 2 == 0 || kernel > MAX_BLUR_KERNEL {
                    return Err(DiffAttackError::BadKernel {
                        kernel,
                        max: MAX_BLUR_KERNEL,
                    });
                }
                Ok(())
            }
            Self::Rotate { degrees } => range("degrees", degrees, true, "finite"),
            Self::Perspective {
                x_degrees,
                y_degrees,
            } => {
                range(
                    "x_degrees",
                    x_degrees,
                    x_degrees.abs() < 80.0,
                    "in (−80, 80)",
                )?;
                range(
                    "y_degrees",
                    y_degrees,
                    y_degrees.abs() < 80.0,
                    "in (−80, 80)",
                )
            }
            Self::Scale { factor } => range("factor", factor, factor > 0.0, "> 0"),
            Self::Crop { keep } => range("keep", keep, keep > 0.0 && keep <= 1.0, "in (0, 1]"),
            Self::Window { keep, x, y } => {
                range("keep", keep, keep > 0.0 && keep <= 1.0, "in (0, 1]")?;
                range("x", x, (0.0..=1.0).contains(&x), "in [0, 1]")?;
                range("y", y, (0.0..=1.0).contains(&y), "in [0, 1]")
            }
            Self::Jpeg { quality } => {
                if quality == 0 || quality > 100 {
                    Err(DiffAttackError::JpegQuality(quality))
                } else {
                    Ok(())
                }
            }
            Self::Brightness { factor } | Self::Contrast { factor } => {
                range("factor", factor, factor >= 0.0, "≥ 0")
            }
            Self::Chain(ref steps) => {
                for (index, step) in steps.iter().enumerate() {
                    step.validate().map_err(|e| DiffAttackError::Chain {
                        index,
                        source: Box::new(e),
                    })?;
                }
                Ok(())
            }
        }
    }

    /// Applies the attack to a batch `[B, C, H, W]` of images in [0, 1] (the same attack, with
    /// the same noise stream, to every image of the batch). Differentiable with respect to `x`.
    pub fn apply(&self, x: Tensor<4>) -> Result<Tensor<4>, DiffAttackError> {
        self.validate()?;
        let [_, _, h, w] = x.dims();
        if h == 0 || w == 0 {
            return Err(self.bad_size(h, w, h as u64, w as u64));
        }
        self.apply_unchecked(x)
    }

    fn bad_size(&self, h: usize, w: usize, nh: u64, nw: u64) -> DiffAttackError {
        DiffAttackError::BadSize {
            attack: self.kind(),
            height: h,
            width: w,
            new_height: nh,
            new_width: nw,
        }
    }

    fn apply_unchecked(&self, x: Tensor<4>) -> Result<Tensor<4>, DiffAttackError> {
        let [_, channels, h, w] = x.dims();
        let rgb = |attack| {
            if channels == 3 {
                Ok(())
            } else {
                Err(DiffAttackError::Channels { attack, channels })
            }
        };
        Ok(match *self {
            Self::Noise { sigma, seed } => noise(x, sigma, seed),
            Self::Blur { sigma, kernel } => gaussian_blur(x, sigma, kernel),
            Self::Rotate { degrees } => rotate(x, degrees),
            Self::Perspective {
                x_degrees,
                y_degrees,
            } => perspective(x, x_degrees, y_degrees),
            Self::Scale { factor } => {
                let f = f64::from(factor);
                let (nh, nw) = (scaled_len(h, f), scaled_len(w, f));
                self.check_size(h, w, nh, nw)?;
                resize(x, [nh as usize, nw as usize])
            }
            Self::Crop { keep } => {
                let side = f64::from(keep).sqrt();
                let (ch, cw) = (scaled_len(h, side), scaled_len(w, side));
                self.check_size(h, w, ch, cw)?;
                centre_crop(x, ch as usize, cw as usize)
            }
            Self::Window { keep, x: fx, y: fy } => {
                let side = f64::from(keep).sqrt();
                let (ch, cw) = (scaled_len(h, side), scaled_len(w, side));
                self.check_size(h, w, ch, cw)?;
                let (ch, cw) = (ch as usize, cw as usize);
                let top = ((h - ch) as f64 * f64::from(fy)).round() as usize;
                let left = ((w - cw) as f64 * f64::from(fx)).round() as usize;
                x.narrow(2, top.min(h - ch), ch)
                    .narrow(3, left.min(w - cw), cw)
            }
            Self::Jpeg { quality } => {
                rgb("jpeg")?;
                jpeg(x, quality)
            }
            Self::Brightness { factor } => {
                if factor == 1.0 {
                    x
                } else {
                    x.mul_scalar(factor).clamp(0.0, 1.0)
                }
            }
            Self::Contrast { factor } => {
                rgb("contrast")?;
                contrast(x, factor)
            }
            Self::Chain(ref steps) => {
                let mut x = x;
                for (index, step) in steps.iter().enumerate() {
                    let [_, _, sh, sw] = x.dims();
                    x = if sh == 0 || sw == 0 {
                        Err(step.bad_size(sh, sw, sh as u64, sw as u64))
                    } else {
                        step.apply_unchecked(x)
                    }
                    .map_err(|e| DiffAttackError::Chain {
                        index,
                        source: Box::new(e),
                    })?;
                }
                x
            }
        })
    }

    fn check_size(&self, h: usize, w: usize, nh: u64, nw: u64) -> Result<(), DiffAttackError> {
        match nh.checked_mul(nw) {
            Some(n) if nh > 0 && nw > 0 && n <= MAX_OUTPUT_PIXELS => Ok(()),
            _ => Err(self.bad_size(h, w, nh, nw)),
        }
    }
}

/// ⌊len · ratio⌋ with a relative slack of 1e-6, so that e.g. 800 · √0.25 gives 400 even when
/// the square root rounds down (same rule as the real attacks).
fn scaled_len(len: usize, ratio: f64) -> u64 {
    let x = len as f64 * ratio;
    (x + x * 1e-6).floor() as u64
}

/// A batch on `device` from host data (helper for callers holding `Vec<f32>` images).
pub fn batch_from_host(data: Vec<f32>, shape: [usize; 4], device: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(data, shape), device)
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::*;

    pub(super) fn device() -> Device {
        Device::flex()
    }

    pub(super) fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    /// Smooth synthetic RGB image in [0.1, 0.9] (gradients + low-frequency sinusoids).
    pub(super) fn smooth(b: usize, h: usize, w: usize) -> Tensor<4> {
        let mut data = Vec::with_capacity(b * 3 * h * w);
        for n in 0..b {
            for c in 0..3 {
                for y in 0..h {
                    for x in 0..w {
                        let (u, v) = (x as f64 / w as f64, y as f64 / h as f64);
                        let val = 0.5
                            + 0.25 * (u - 0.5) * (c as f64 - 1.0)
                            + 0.15 * (2.0 * PI * (u * 1.5 + v + 0.1 * n as f64)).sin()
                            + 0.1 * (2.0 * PI * (v * 2.0 - u * 0.5 + 0.2 * c as f64)).cos();
                        data.push(val as f32);
                    }
                }
            }
        }
        batch_from_host(data, [b, 3, h, w], &device())
    }

    pub(super) fn max_abs_diff(a: Tensor<4>, b: Tensor<4>) -> f32 {
        to_vec(a.sub(b).abs().max())[0]
    }

    pub(super) fn psnr(a: Tensor<4>, b: Tensor<4>) -> f64 {
        let mse = to_vec(a.sub(b).powi_scalar(2).mean())[0] as f64;
        10.0 * (1.0 / mse).log10()
    }

    fn all_attacks() -> Vec<DiffAttack> {
        vec![
            DiffAttack::Noise {
                sigma: 0.1,
                seed: 7,
            },
            DiffAttack::Blur {
                sigma: 1.0,
                kernel: 5,
            },
            DiffAttack::Rotate { degrees: 30.0 },
            DiffAttack::Scale { factor: 0.75 },
            DiffAttack::Crop { keep: 0.4 },
            DiffAttack::Window {
                keep: 0.4,
                x: 0.2,
                y: 0.9,
            },
            DiffAttack::Jpeg { quality: 50 },
            DiffAttack::Brightness { factor: 0.8 },
            DiffAttack::Contrast { factor: 0.7 },
            DiffAttack::Chain(vec![
                DiffAttack::Noise {
                    sigma: 0.1,
                    seed: 1,
                },
                DiffAttack::Crop { keep: 0.4 },
                DiffAttack::Jpeg { quality: 50 },
            ]),
        ]
    }

    #[test]
    fn shapes_are_as_documented() {
        let x = smooth(2, 40, 60);
        let expect = |a: &DiffAttack| -> [usize; 4] {
            match a {
                DiffAttack::Scale { .. } => [2, 3, 30, 45],
                // √0.4 · 40 = 25.3 → 25, √0.4 · 60 = 37.9 → 37.
                DiffAttack::Crop { .. } | DiffAttack::Window { .. } | DiffAttack::Chain(_) => {
                    [2, 3, 25, 37]
                }
                _ => [2, 3, 40, 60],
            }
        };
        for a in all_attacks() {
            let y = a.apply(x.clone()).unwrap();
            assert_eq!(y.dims(), expect(&a), "{a:?}");
        }
    }

    #[test]
    fn a_window_is_the_crop_moved_to_its_place() {
        let x = smooth(1, 40, 60);
        let at = |xf: f32, yf: f32| {
            DiffAttack::Window {
                keep: 0.4,
                x: xf,
                y: yf,
            }
            .apply(x.clone())
            .unwrap()
        };
        // Centred: the centre crop (free room 15 × 23: top 7.5 → 8, left 11.5 → 12).
        let centred = at(0.5, 0.5);
        assert_eq!(centred.dims(), [1, 3, 25, 37]);
        assert_eq!(
            max_abs_diff(centred, x.clone().narrow(2, 8, 25).narrow(3, 12, 37)),
            0.0
        );
        // The corners.
        let tl = x.clone().narrow(2, 0, 25).narrow(3, 0, 37);
        assert_eq!(max_abs_diff(at(0.0, 0.0), tl), 0.0);
        let br = x.clone().narrow(2, 15, 25).narrow(3, 23, 37);
        assert_eq!(max_abs_diff(at(1.0, 1.0), br), 0.0);
        // Out of range places are refused.
        let bad = DiffAttack::Window {
            keep: 0.4,
            x: 1.5,
            y: 0.0,
        };
        assert!(bad.validate().is_err());
        // Drawn from its family: the keep in range, the place anywhere.
        let fam = AttackFamily::Window { keep: (0.2, 0.5) };
        let mut rng = EotRng::new(4);
        let mut xs = Vec::new();
        for _ in 0..50 {
            let Some(DiffAttack::Window { keep, x, y }) = fam.sample(&mut rng) else {
                panic!("not a window")
            };
            assert!((0.2..=0.5).contains(&keep) && (0.0..=1.0).contains(&y));
            xs.push(x);
        }
        assert!(xs.iter().any(|&v| v < 0.2) && xs.iter().any(|&v| v > 0.8));
    }

    #[test]
    fn neutral_parameters_are_the_identity() {
        let x = smooth(1, 24, 32);
        for a in [
            DiffAttack::Noise {
                sigma: 0.0,
                seed: 3,
            },
            DiffAttack::Blur {
                sigma: 2.0,
                kernel: 1,
            },
            DiffAttack::Rotate { degrees: 0.0 },
            DiffAttack::Rotate { degrees: 360.0 },
            DiffAttack::Scale { factor: 1.0 },
            DiffAttack::Crop { keep: 1.0 },
            DiffAttack::Window {
                keep: 1.0,
                x: 0.7,
                y: 0.1,
            },
            DiffAttack::Brightness { factor: 1.0 },
            DiffAttack::Contrast { factor: 1.0 },
            DiffAttack::Chain(vec![]),
        ] {
            let err = max_abs_diff(a.apply(x.clone()).unwrap(), x.clone());
            assert_eq!(err, 0.0, "{a:?}");
        }
        // Four quarter turns of a square image through the sampling path give it back.
        let sq = smooth(1, 20, 20);
        let mut y = sq.clone();
        for _ in 0..4 {
            y = DiffAttack::Rotate { degrees: 90.0 }.apply(y).unwrap();
        }
        let err = max_abs_diff(y, sq);
        assert!(err < 1e-5, "{err}");
        // A vanishing blur σ is the identity up to e^(−50).
        let b = DiffAttack::Blur {
            sigma: 0.1,
            kernel: 3,
        };
        assert!(max_abs_diff(b.apply(x.clone()).unwrap(), x.clone()) < 1e-6);
        // JPEG has no exact neutral quality: at 100 every table entry is 1, so only the
        // rounding of DCT coefficients to integers on the 0–255 scale remains.
        let j = DiffAttack::Jpeg { quality: 100 }.apply(x.clone()).unwrap();
        let p = psnr(j, x);
        assert!(p > 50.0, "JPEG q=100 PSNR {p}");
    }

    #[test]
    fn gradients_flow_through_every_attack() {
        for a in all_attacks() {
            let x = smooth(1, 32, 40).autodiff().require_grad();
            let y = a.apply(x.clone()).unwrap();
            // A non-uniform weighting so that no attack's gradient cancels by symmetry.
            let [_, _, h, w] = y.dims();
            let weights: Vec<f32> = (0..3 * h * w)
                .map(|i| ((i * 7919) % 13) as f32 / 13.0)
                .collect();
            let wt = batch_from_host(weights, [1, 3, h, w], &device()).autodiff();
            let grads = y.mul(wt).sum().backward();
            let g = to_vec(
                x.grad(&grads)
                    .unwrap_or_else(|| panic!("{a:?}: no gradient")),
            );
            assert!(g.iter().all(|v| v.is_finite()), "{a:?}");
            assert!(g.iter().any(|v| *v != 0.0), "{a:?}: zero gradient");
        }
    }

    #[test]
    fn invalid_parameters_are_rejected() {
        let x = smooth(1, 8, 8);
        for a in [
            DiffAttack::Noise {
                sigma: -1.0,
                seed: 0,
            },
            DiffAttack::Blur {
                sigma: 1.0,
                kernel: 4,
            },
            DiffAttack::Blur {
                sigma: 0.0,
                kernel: 3,
            },
            DiffAttack::Rotate { degrees: f32::NAN },
            DiffAttack::Scale { factor: 0.0 },
            DiffAttack::Crop { keep: 1.5 },
            DiffAttack::Jpeg { quality: 0 },
            DiffAttack::Brightness { factor: -0.1 },
            DiffAttack::Scale { factor: 0.01 }, // 8 px → 0 px
            DiffAttack::Chain(vec![DiffAttack::Jpeg { quality: 101 }]),
        ] {
            assert!(a.apply(x.clone()).is_err(), "{a:?}");
        }
        let gray = Tensor::<4>::zeros([1, 1, 8, 8], &device());
        assert!(matches!(
            DiffAttack::Jpeg { quality: 50 }.apply(gray),
            Err(DiffAttackError::Channels { .. })
        ));
    }
}
