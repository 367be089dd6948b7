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

use std::f64::consts::PI;

use burn::tensor::module::conv2d;
use burn::tensor::ops::{
    ConvOptions, GridSampleOptions, GridSamplePaddingMode, InterpolateMode, InterpolateOptions,
    PadMode,
};
use burn::tensor::{Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};

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

/// Exact sine and cosine at multiples of 90°.
fn sin_cos_degrees(degrees: f32) -> (f64, f64) {
    match f64::from(degrees).rem_euclid(360.0) {
        0.0 => (0.0, 1.0),
        90.0 => (1.0, 0.0),
        180.0 => (0.0, -1.0),
        270.0 => (-1.0, 0.0),
        d => d.to_radians().sin_cos(),
    }
}

fn noise(x: Tensor<4>, sigma: f32, seed: u64) -> Tensor<4> {
    if sigma == 0.0 {
        return x;
    }
    let dims = x.dims();
    let n: usize = dims.iter().product();
    let mut rng = EotRng::new(seed);
    let mut data = Vec::with_capacity(n + 1);
    while data.len() < n {
        let (a, b) = rng.normal_pair();
        data.push(a as f32);
        data.push(b as f32);
    }
    data.truncate(n);
    let std = f64::from(sigma) * f64::from(sigma);
    let noise = Tensor::<4>::from_data(TensorData::new(data, dims), &x.device());
    x.add(noise.mul_scalar(std))
}

/// Normalised 1D Gaussian kernel sampled at integer offsets −k/2..=k/2 (torchvision's).
fn gaussian_kernel(sigma: f32, kernel: u32) -> Vec<f32> {
    let half = i64::from(kernel / 2);
    let sigma = f64::from(sigma);
    let weights: Vec<f64> = (-half..=half)
        .map(|d| (-0.5 * (d as f64 / sigma).powi(2)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.iter().map(|v| (v / total) as f32).collect()
}

/// Separable Gaussian blur (σ in pixels, odd kernel), reflect padding; same size out.
pub fn gaussian_blur(x: Tensor<4>, sigma: f32, kernel: u32) -> Tensor<4> {
    if kernel == 1 {
        return x;
    }
    let [_, c, h, w] = x.dims();
    let k = kernel as usize;
    let half = k / 2;
    let device = x.device();
    let weights = gaussian_kernel(sigma, kernel);
    let mode_for = |len: usize| {
        if half < len {
            PadMode::Reflect
        } else {
            PadMode::Edge
        }
    };
    let depthwise = ConvOptions::new([1, 1], [0, 0], [1, 1], c);
    // Horizontal pass: weight [C, 1, 1, k]; then vertical: [C, 1, k, 1].
    let row: Vec<f32> = (0..c).flat_map(|_| weights.iter().copied()).collect();
    let wx = Tensor::<4>::from_data(TensorData::new(row.clone(), [c, 1, 1, k]), &device);
    let wy = Tensor::<4>::from_data(TensorData::new(row, [c, 1, k, 1]), &device);
    let x = x.pad([(0, 0), (half, half)], mode_for(w));
    let x = conv2d(x, wx, None, depthwise.clone());
    let x = x.pad([(half, half), (0, 0)], mode_for(h));
    conv2d(x, wy, None, depthwise)
}

fn rotate(x: Tensor<4>, degrees: f32) -> Tensor<4> {
    let (sin, cos) = sin_cos_degrees(degrees);
    if sin == 0.0 && cos == 1.0 {
        return x;
    }
    let [_, _, h, w] = x.dims();
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let mut grid = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        let dy = y as f64 - cy;
        for xx in 0..w {
            let dx = xx as f64 - cx;
            // Inverse map of a counter-clockwise rotation in y-down image coordinates (the same
            // formula as the real attack), then pixel → [−1, 1] with half-pixel centres.
            let sx = cx + dx * cos - dy * sin;
            let sy = cy + dx * sin + dy * cos;
            grid.push(((2.0 * sx + 1.0) / w as f64 - 1.0) as f32);
            grid.push(((2.0 * sy + 1.0) / h as f64 - 1.0) as f32);
        }
    }
    sample_grid(x, grid)
}

/// Source position (pixels) of output pixel centre `(u, v)` under [`DiffAttack::Perspective`]:
/// the ray through `(u, v)` meets the picture plane, tilted by `R = R_y(y°)·R_x(x°)` about its
/// centre at depth 1, at `P`; the picture coordinates of `P` are `Rᵀ(P − (0, 0, 1))`.
/// `None` where the ray misses the plane (behind the camera).
pub fn perspective_source(
    u: f64,
    v: f64,
    size: (usize, usize),
    x_degrees: f64,
    y_degrees: f64,
) -> Option<(f64, f64)> {
    let (h, w) = size;
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let f = w as f64;
    let (sx, cxr) = x_degrees.to_radians().sin_cos();
    let (sy, cyr) = y_degrees.to_radians().sin_cos();
    // R = R_y · R_x (columns are the picture's axes in camera space).
    let r = [
        [cyr, sy * sx, sy * cxr],
        [0.0, cxr, -sx],
        [-sy, cyr * sx, cyr * cxr],
    ];
    let ray = [(u - cx) / f, (v - cy) / f, 1.0];
    let n = [r[0][2], r[1][2], r[2][2]];
    let denom = n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2];
    if denom.abs() < 1e-9 {
        return None;
    }
    let t = n[2] / denom;
    if t <= 0.0 {
        return None;
    }
    let p = [t * ray[0], t * ray[1], t * ray[2] - 1.0];
    let qx = r[0][0] * p[0] + r[1][0] * p[1] + r[2][0] * p[2];
    let qy = r[0][1] * p[0] + r[1][1] * p[1] + r[2][1] * p[2];
    Some((cx + f * qx, cy + f * qy))
}

fn perspective(x: Tensor<4>, x_degrees: f32, y_degrees: f32) -> Tensor<4> {
    if x_degrees == 0.0 && y_degrees == 0.0 {
        return x;
    }
    let [_, _, h, w] = x.dims();
    let mut grid = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        for xx in 0..w {
            let (u, v) = (xx as f64 + 0.5, y as f64 + 0.5);
            let (sx, sy) =
                perspective_source(u, v, (h, w), f64::from(x_degrees), f64::from(y_degrees))
                    .unwrap_or((-1e6, -1e6));
            // Pixel position (centres at +0.5) → [−1, 1] without corner alignment.
            grid.push((2.0 * sx / w as f64 - 1.0) as f32);
            grid.push((2.0 * sy / h as f64 - 1.0) as f32);
        }
    }
    sample_grid(x, grid)
}

/// Bilinear sampling of every image of `x` `[B, C, H, W]` at one grid of source positions
/// (`H·W` pairs in [−1, 1], row-major, no corner alignment), black outside.
fn sample_grid(x: Tensor<4>, grid: Vec<f32>) -> Tensor<4> {
    let [b, _, h, w] = x.dims();
    let grid = Tensor::<4>::from_data(TensorData::new(grid, [1, h, w, 2]), &x.device())
        .expand([b, h, w, 2]);
    let options = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    x.grid_sample_2d(grid, options)
}

/// Bilinear resize with half-pixel centres (PyTorch's and burn's `interpolate`, align_corners
/// false, no anti-aliasing). burn's wgpu runtime has no backward pass for its bilinear
/// `interpolate`, so on any device but burn's CPU backend the resize runs one axis at a time,
/// each output row (then column) a blend of two gathered input rows — the same values
/// (tested), 3–4× slower than `interpolate` on the CPU backend, hence kept off it.
pub(crate) fn resize(x: Tensor<4>, size: [usize; 2]) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    if size == [h, w] {
        return x;
    }
    if x.device() == Device::flex() {
        return burn::tensor::module::interpolate(
            x,
            InterpolateOptions::new(InterpolateMode::Bilinear)
                .with_align_corners(false)
                .with_output_size(size),
        );
    }
    let x = resize_axis(x, 2, size[0]);
    resize_axis(x, 3, size[1])
}

/// [`resize`] along `dim` (2 or 3) to `out` samples.
fn resize_axis(x: Tensor<4>, dim: usize, out: usize) -> Tensor<4> {
    let len = x.dims()[dim];
    if len == out {
        return x;
    }
    let device = x.device();
    let scale = len as f64 / out as f64;
    let (mut i0, mut i1, mut t) = (
        Vec::with_capacity(out),
        Vec::with_capacity(out),
        Vec::with_capacity(out),
    );
    for i in 0..out {
        // Source position of output sample i, clamped at the edges.
        let src = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
        let a = (src.floor() as usize).min(len - 1);
        i0.push(a as i64);
        i1.push((a + 1).min(len - 1) as i64);
        t.push((src - a as f64).min(1.0) as f32);
    }
    let mut shape = [1usize; 4];
    shape[dim] = out;
    let t = Tensor::<4>::from_data(TensorData::new(t, shape), &device);
    let index = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v, [out]), &device);
    let a = x.clone().select(dim, index(i0));
    let b = x.select(dim, index(i1));
    a.clone().add(b.sub(a).mul(t))
}

fn centre_crop(x: Tensor<4>, ch: usize, cw: usize) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    // torchvision's center_crop: top = int(round((h − ch) / 2)), Python rounds half to even.
    let top = ((h - ch) as f64 / 2.0).round_ties_even() as usize;
    let left = ((w - cw) as f64 / 2.0).round_ties_even() as usize;
    x.narrow(2, top, ch).narrow(3, left, cw)
}

fn contrast(x: Tensor<4>, factor: f32) -> Tensor<4> {
    if factor == 1.0 {
        return x;
    }
    let [b, _, _, _] = x.dims();
    let luma_w = Tensor::<4>::from_data(
        TensorData::new(vec![0.2989f32, 0.587, 0.114], [1, 3, 1, 1]),
        &x.device(),
    );
    let mean = x
        .clone()
        .mul(luma_w)
        .sum_dim(1)
        .mean_dim(2)
        .mean_dim(3)
        .reshape([b, 1, 1, 1]);
    x.mul_scalar(factor)
        .add(mean.mul_scalar(1.0 - factor))
        .clamp(0.0, 1.0)
}

/// The standard JPEG luminance quantisation table (ITU-T T.81 Annex K.1), row-major.
pub const JPEG_LUMA_TABLE: [u16; 64] = [
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56,
    14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113,
    92, 49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99,
];

/// The standard JPEG chrominance quantisation table (ITU-T T.81 Annex K.2), row-major.
pub const JPEG_CHROMA_TABLE: [u16; 64] = [
    17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99, 24, 26, 56, 99, 99, 99, 99, 99,
    47, 66, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
    99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
];

/// `table` scaled for `quality` (1..=100) as libjpeg's `jpeg_quality_scaling` +
/// `jpeg_add_quant_table` with `force_baseline`: scale = 5000/q below 50, 200 − 2q from 50,
/// entries ⌊(t·scale + 50)/100⌋ clamped to 1..=255.
pub fn jpeg_quant_table(table: &[u16; 64], quality: u8) -> [u16; 64] {
    let q = u32::from(quality.clamp(1, 100));
    let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
    table.map(|t| ((u32::from(t) * scale + 50) / 100).clamp(1, 255) as u16)
}

/// Orthonormal 8-point DCT-II matrix D (rows = frequencies): `D X Dᵀ` is JPEG's forward DCT of
/// an 8×8 block X.
fn dct_matrix() -> Vec<f32> {
    let mut d = Vec::with_capacity(64);
    for u in 0..8 {
        let alpha = if u == 0 { (1.0f64 / 8.0).sqrt() } else { 0.5 };
        for x in 0..8 {
            d.push((alpha * (((2 * x + 1) * u) as f64 * PI / 16.0).cos()) as f32);
        }
    }
    d
}

/// `x + (round(x) − x).detach()`: rounds in the forward pass, identity in the backward pass.
pub fn straight_through_round<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    let rounded = x.clone().round().sub(x.clone()).detach();
    x.add(rounded)
}

fn jpeg(x: Tensor<4>, quality: u8) -> Tensor<4> {
    let [b, _, h, w] = x.dims();
    let device = x.device();
    let conv = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
    // RGB in [0, 1] → level-shifted YCbCr on the 0–255 scale (JFIF): Y − 128, Cb − 128, Cr − 128.
    let to_ycc: [f32; 9] = [
        0.299, 0.587, 0.114, //
        -0.168_736, -0.331_264, 0.5, //
        0.5, -0.418_688, -0.081_312,
    ];
    let to_ycc = Tensor::<4>::from_data(
        TensorData::new(to_ycc.map(|v| v * 255.0).to_vec(), [3, 3, 1, 1]),
        &device,
    );
    let shift = Tensor::<1>::from_data(TensorData::new(vec![-128.0f32, 0.0, 0.0], [3]), &device);
    let ycc = conv2d(x, to_ycc, Some(shift), conv.clone());

    // Edge padding to whole 8×8 blocks (what encoders do), then blocks [B, 3, Hb, Wb, 8, 8].
    let (ph, pw) = (h.div_ceil(8) * 8, w.div_ceil(8) * 8);
    let ycc = if (ph, pw) != (h, w) {
        ycc.pad([(0, ph - h), (0, pw - w)], PadMode::Edge)
    } else {
        ycc
    };
    let (hb, wb) = (ph / 8, pw / 8);
    let blocks = ycc
        .reshape([b, 3, hb, 8, wb, 8])
        .permute([0, 1, 2, 4, 3, 5]);

    let d = Tensor::<6>::from_data(TensorData::new(dct_matrix(), [1, 1, 1, 1, 8, 8]), &device);
    let dt = d.clone().transpose();
    let luma = jpeg_quant_table(&JPEG_LUMA_TABLE, quality);
    let chroma = jpeg_quant_table(&JPEG_CHROMA_TABLE, quality);
    let table: Vec<f32> = luma
        .iter()
        .chain(chroma.iter())
        .chain(chroma.iter())
        .map(|&v| f32::from(v))
        .collect();
    let table = Tensor::<6>::from_data(TensorData::new(table, [1, 3, 1, 1, 8, 8]), &device);

    let coeffs = d.clone().matmul(blocks).matmul(dt.clone());
    let quantised = straight_through_round(coeffs.div(table.clone())).mul(table);
    let blocks = dt.matmul(quantised).matmul(d);

    let ycc = blocks.permute([0, 1, 2, 4, 3, 5]).reshape([b, 3, ph, pw]);
    let ycc = if (ph, pw) != (h, w) {
        ycc.narrow(2, 0, h).narrow(3, 0, w)
    } else {
        ycc
    };
    // Level-shifted YCbCr (0–255 scale) → RGB in [0, 1].
    let to_rgb: [f32; 9] = [
        1.0, 0.0, 1.402, //
        1.0, -0.344_136, -0.714_136, //
        1.0, 1.772, 0.0,
    ];
    let to_rgb = Tensor::<4>::from_data(
        TensorData::new(to_rgb.map(|v| v / 255.0).to_vec(), [3, 3, 1, 1]),
        &device,
    );
    let offset = Tensor::<1>::from_data(TensorData::new(vec![128.0f32 / 255.0; 3], [3]), &device);
    conv2d(ycc, to_rgb, Some(offset), conv).clamp(0.0, 1.0)
}

/// Small deterministic random source for EOT sampling and noise: SplitMix64 (Steele, Lea &
/// Flood 2014) for uniform bits, Box–Muller for normals. Not cryptographic.
#[derive(Debug, Clone)]
pub struct EotRng {
    state: u64,
}

impl EotRng {
    /// A stream determined by `seed`.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// Next 64 uniform bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi) (lo when the range is empty).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        if hi > lo {
            lo + (hi - lo) * self.uniform()
        } else {
            lo
        }
    }

    /// Uniform integer in lo..=hi (lo when hi < lo).
    pub fn range_int(&mut self, lo: u64, hi: u64) -> u64 {
        if hi > lo {
            lo + self.next_u64() % (hi - lo + 1)
        } else {
            lo
        }
    }

    /// Two independent standard normal numbers (Box–Muller).
    pub fn normal_pair(&mut self) -> (f64, f64) {
        let u1 = ((self.next_u64() >> 11) + 1) as f64 / (1u64 << 53) as f64; // (0, 1]
        let u2 = self.uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        (r * c, r * s)
    }
}

/// One kind of attack with the range its parameter is drawn from (uniformly, bounds included
/// up to rounding).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", content = "params", rename_all = "snake_case")]
pub enum AttackFamily {
    /// No attack (the clean render).
    Identity,
    /// Noise with the papers' σ (std σ²) in `sigma`.
    Noise { sigma: (f32, f32) },
    /// Blur with σ in `sigma`, fixed odd `kernel`.
    Blur { sigma: (f32, f32), kernel: u32 },
    /// Rotation by an angle in ±`max_degrees`.
    Rotate { max_degrees: f32 },
    /// Perspective tilt, each axis's angle in ±`max_degrees`.
    Perspective { max_degrees: f32 },
    /// Resize by a per-side factor in `factor`.
    Scale { factor: (f32, f32) },
    /// Centre crop keeping an area fraction in `keep`.
    Crop { keep: (f32, f32) },
    /// A crop keeping an area fraction in `keep`, anywhere in the image (uniform placement).
    Window { keep: (f32, f32) },
    /// JPEG approximation at a quality in `quality` (inclusive).
    Jpeg { quality: (u8, u8) },
    /// Brightness factor in `factor`.
    Brightness { factor: (f32, f32) },
    /// Contrast factor in `factor`.
    Contrast { factor: (f32, f32) },
}

impl AttackFamily {
    /// Draws one attack of this family (`None` for [`AttackFamily::Identity`]).
    pub fn sample(&self, rng: &mut EotRng) -> Option<DiffAttack> {
        let r = |rng: &mut EotRng, (lo, hi): (f32, f32)| rng.range(lo.into(), hi.into()) as f32;
        Some(match *self {
            Self::Identity => return None,
            Self::Noise { sigma } => DiffAttack::Noise {
                sigma: r(rng, sigma),
                seed: rng.next_u64(),
            },
            Self::Blur { sigma, kernel } => DiffAttack::Blur {
                sigma: r(rng, sigma),
                kernel,
            },
            Self::Rotate { max_degrees } => DiffAttack::Rotate {
                degrees: r(rng, (-max_degrees, max_degrees)),
            },
            Self::Perspective { max_degrees } => DiffAttack::Perspective {
                x_degrees: r(rng, (-max_degrees, max_degrees)),
                y_degrees: r(rng, (-max_degrees, max_degrees)),
            },
            Self::Scale { factor } => DiffAttack::Scale {
                factor: r(rng, factor),
            },
            Self::Crop { keep } => DiffAttack::Crop { keep: r(rng, keep) },
            Self::Window { keep } => DiffAttack::Window {
                keep: r(rng, keep),
                x: r(rng, (0.0, 1.0)),
                y: r(rng, (0.0, 1.0)),
            },
            Self::Jpeg { quality: (lo, hi) } => DiffAttack::Jpeg {
                quality: rng.range_int(lo.into(), hi.into()) as u8,
            },
            Self::Brightness { factor } => DiffAttack::Brightness {
                factor: r(rng, factor),
            },
            Self::Contrast { factor } => DiffAttack::Contrast {
                factor: r(rng, factor),
            },
        })
    }
}

/// The distribution p(t) of EOT training: `steps` attacks (a uniform count in
/// `min_steps..=max_steps`), each drawn from `families` with probability proportional to its
/// weight, applied in the order drawn.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EotConfig {
    /// Families and their (non-negative) sampling weights.
    pub families: Vec<(AttackFamily, f32)>,
    /// Fewest attacks composed.
    pub min_steps: usize,
    /// Most attacks composed.
    pub max_steps: usize,
}

impl Default for EotConfig {
    /// Covers the paper's robustness table (noise σ = 0.1, rotation ±30°, scaling 75 % — per
    /// side or, as 3D-GSW reads it, of the area —, blur σ = 0.1, crop 40 % of the area, JPEG 50,
    /// and the noise + crop + JPEG combination through 3-step chains) with some margin, plus
    /// mild brightness/contrast changes and the clean image.
    fn default() -> Self {
        Self {
            families: vec![
                (AttackFamily::Identity, 1.0),
                (AttackFamily::Noise { sigma: (0.0, 0.12) }, 1.0),
                (
                    AttackFamily::Blur {
                        sigma: (0.1, 1.0),
                        kernel: 3,
                    },
                    1.0,
                ),
                (AttackFamily::Rotate { max_degrees: 30.0 }, 1.0),
                (AttackFamily::Scale { factor: (0.7, 1.0) }, 1.0),
                (AttackFamily::Crop { keep: (0.35, 1.0) }, 1.0),
                (AttackFamily::Jpeg { quality: (40, 90) }, 1.0),
                (AttackFamily::Brightness { factor: (0.8, 1.2) }, 0.5),
                (AttackFamily::Contrast { factor: (0.8, 1.2) }, 0.5),
            ],
            min_steps: 1,
            max_steps: 3,
        }
    }
}

impl EotConfig {
    /// Draws one family index by weight (`None` if no weight is positive).
    fn pick(&self, rng: &mut EotRng) -> Option<usize> {
        let total: f64 = self
            .families
            .iter()
            .map(|(_, w)| f64::from(w.max(0.0)))
            .sum();
        if !(total > 0.0) {
            return None;
        }
        let mut t = rng.uniform() * total;
        for (i, (_, w)) in self.families.iter().enumerate() {
            let w = f64::from(w.max(0.0));
            if t < w {
                return Some(i);
            }
            t -= w;
        }
        self.families.iter().rposition(|(_, w)| *w > 0.0)
    }
}

/// Draws one transformation t ~ p(t) from `config`: a chain of `min_steps..=max_steps` attacks
/// (identity draws dropped, so the chain may be empty, i.e. the identity).
pub fn random_composition(config: &EotConfig, rng: &mut EotRng) -> DiffAttack {
    let steps = rng.range_int(config.min_steps as u64, config.max_steps as u64) as usize;
    let mut chain = Vec::with_capacity(steps);
    for _ in 0..steps {
        if let Some(i) = config.pick(rng)
            && let Some(attack) = config.families[i].0.sample(rng)
        {
            chain.push(attack);
        }
    }
    DiffAttack::Chain(chain)
}

/// A batch on `device` from host data (helper for callers holding `Vec<f32>` images).
pub fn batch_from_host(data: Vec<f32>, shape: [usize; 4], device: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(data, shape), device)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device() -> Device {
        Device::flex()
    }

    #[test]
    fn the_gathered_resize_is_burns_bilinear_interpolate() {
        use burn::tensor::module::interpolate;
        // `resize` keeps burn's own kernel on its CPU backend, training (autodiff) included.
        assert!(Device::flex().autodiff() == Device::flex());
        let (h, w) = (37, 52);
        let data: Vec<f32> = (0..2 * 3 * h * w)
            .map(|k| ((k * 7919) % 1000) as f32 / 1000.0)
            .collect();
        let x = Tensor::<4>::from_data(TensorData::new(data, [2, 3, h, w]), &device());
        for size in [[27, 39], [28, 36], [37, 26], [50, 71], [37, 52], [1, 1]] {
            let ours: Vec<f32> = resize_axis(resize_axis(x.clone(), 2, size[0]), 3, size[1])
                .try_into_vec_as()
                .unwrap();
            let burns: Vec<f32> = interpolate(
                x.clone(),
                InterpolateOptions::new(InterpolateMode::Bilinear)
                    .with_align_corners(false)
                    .with_output_size(size),
            )
            .try_into_vec_as()
            .unwrap();
            assert_eq!(ours.len(), burns.len());
            let gap = ours
                .iter()
                .zip(&burns)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(gap < 1e-5, "{size:?}: differs by {gap}");
        }
    }

    fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    /// Smooth synthetic RGB image in [0.1, 0.9] (gradients + low-frequency sinusoids).
    fn smooth(b: usize, h: usize, w: usize) -> Tensor<4> {
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

    fn max_abs_diff(a: Tensor<4>, b: Tensor<4>) -> f32 {
        to_vec(a.sub(b).abs().max())[0]
    }

    fn psnr(a: Tensor<4>, b: Tensor<4>) -> f64 {
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
    fn rotation_follows_the_real_attack_convention() {
        // 90° counter-clockwise on an 8×8 image moves (x=6, y=2) to (x=2, y=1) (see real.rs).
        let mut data = vec![0.0f32; 3 * 64];
        for c in 0..3 {
            data[c * 64 + 2 * 8 + 6] = 1.0;
        }
        let x = batch_from_host(data, [1, 3, 8, 8], &device());
        let y = to_vec(DiffAttack::Rotate { degrees: 90.0 }.apply(x).unwrap());
        assert!((y[8 + 2] - 1.0).abs() < 1e-5, "{}", y[8 + 2]);
        assert!((y.iter().sum::<f32>() - 3.0).abs() < 1e-4);
    }

    #[test]
    fn perspective_is_the_tilted_picture_seen_through_a_pinhole() {
        let (h, w) = (64usize, 64usize);
        let f = w as f64;
        // A picture point (X, 0) of a plane tilted by θ about the vertical axis sits at
        // (X cos θ, 0, 1 − X sin θ) in camera space and projects to u = cx + f·X cos θ / (1 − X sin θ).
        for theta in [-30.0f64, -10.0, 20.0] {
            let (s, c) = theta.to_radians().sin_cos();
            for xp in [-0.3f64, -0.1, 0.2, 0.4] {
                let u = 32.0 + f * xp * c / (1.0 - xp * s);
                let (sx, sy) = perspective_source(u, 32.0, (h, w), 0.0, theta).unwrap();
                assert!(
                    (sx - (32.0 + f * xp)).abs() < 1e-9,
                    "θ {theta} X {xp}: {sx}"
                );
                assert!((sy - 32.0).abs() < 1e-9);
            }
        }
        // The centre stays; no tilt is the identity; the result keeps its size and is finite.
        let (sx, sy) = perspective_source(32.0, 32.0, (h, w), 25.0, -15.0).unwrap();
        assert!((sx - 32.0).abs() < 1e-9 && (sy - 32.0).abs() < 1e-9);
        let x = smooth(2, h, w);
        let same = DiffAttack::Perspective {
            x_degrees: 0.0,
            y_degrees: 0.0,
        }
        .apply(x.clone())
        .unwrap();
        assert_eq!(to_vec(same), to_vec(x.clone()));
        let tilted = DiffAttack::Perspective {
            x_degrees: 20.0,
            y_degrees: -25.0,
        }
        .apply(x.clone())
        .unwrap();
        assert_eq!(tilted.dims(), [2, 3, h, w]);
        let v = to_vec(tilted);
        assert!(v.iter().all(|v| v.is_finite()));
        assert_ne!(v, to_vec(x));
        assert!(
            DiffAttack::Perspective {
                x_degrees: 85.0,
                y_degrees: 0.0
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn noise_has_the_squared_sigma_and_is_reproducible() {
        let x = Tensor::<4>::full([1, 3, 64, 64], 0.5, &device());
        let a = DiffAttack::Noise {
            sigma: 0.1,
            seed: 42,
        };
        let y = to_vec(a.apply(x.clone()).unwrap());
        let n = y.len() as f64;
        let var = y.iter().map(|v| (*v as f64 - 0.5).powi(2)).sum::<f64>() / n;
        assert!((var.sqrt() - 0.01).abs() < 0.0005, "std {}", var.sqrt());
        assert_eq!(y, to_vec(a.apply(x).unwrap()));
    }

    #[test]
    fn blur_keeps_constants_and_smooths() {
        let c = Tensor::<4>::full([1, 3, 9, 17], 0.3, &device());
        let b = DiffAttack::Blur {
            sigma: 2.0,
            kernel: 7,
        };
        assert!(max_abs_diff(b.apply(c.clone()).unwrap(), c).abs() < 1e-6);
        // Tiny image (smaller than the kernel radius): edge padding, still the right shape.
        let t = smooth(1, 2, 3);
        assert_eq!(b.apply(t).unwrap().dims(), [1, 3, 2, 3]);
    }

    #[test]
    fn jpeg_q50_changes_a_smooth_image_plausibly() {
        let x = smooth(1, 64, 64);
        let y = DiffAttack::Jpeg { quality: 50 }.apply(x.clone()).unwrap();
        let p = psnr(y.clone(), x.clone());
        assert!((25.0..45.0).contains(&p), "PSNR {p}");
        // Lower quality, more damage.
        let z = DiffAttack::Jpeg { quality: 10 }.apply(x.clone()).unwrap();
        assert!(psnr(z, x) < p);
        // Odd size: padded to blocks and cropped back.
        let odd = smooth(1, 21, 30);
        assert_eq!(
            DiffAttack::Jpeg { quality: 50 }.apply(odd).unwrap().dims(),
            [1, 3, 21, 30]
        );
    }

    #[test]
    fn quant_tables_follow_libjpeg_scaling() {
        assert_eq!(jpeg_quant_table(&JPEG_LUMA_TABLE, 50), JPEG_LUMA_TABLE);
        assert!(
            jpeg_quant_table(&JPEG_LUMA_TABLE, 100)
                .iter()
                .all(|&v| v == 1)
        );
        // q = 10: scale 500, 16 → (16·500 + 50)/100 = 80.
        assert_eq!(jpeg_quant_table(&JPEG_LUMA_TABLE, 10)[0], 80);
        assert_eq!(jpeg_quant_table(&JPEG_CHROMA_TABLE, 1)[63], 255);
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
    fn jpeg_gradient_is_straight_through() {
        // With the STE, the JPEG approximation's Jacobian is that of the linear pipeline without
        // quantisation, which is the identity (away from clamping): ∂Σy/∂x = 1.
        let x = smooth(1, 16, 16).autodiff().require_grad();
        let grads = DiffAttack::Jpeg { quality: 30 }
            .apply(x.clone())
            .unwrap()
            .sum()
            .backward();
        let g = to_vec(x.grad(&grads).unwrap());
        assert!(g.iter().all(|v| (v - 1.0).abs() < 1e-4), "{:?}", &g[..4]);
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

    #[test]
    fn random_composition_is_deterministic_and_valid() {
        let config = EotConfig::default();
        let mut a = EotRng::new(9);
        let mut b = EotRng::new(9);
        let x = smooth(1, 64, 64);
        let mut kinds = std::collections::BTreeSet::new();
        for _ in 0..200 {
            let t = random_composition(&config, &mut a);
            assert_eq!(t, random_composition(&config, &mut b));
            t.validate().unwrap();
            let DiffAttack::Chain(steps) = &t else {
                panic!("not a chain")
            };
            assert!(steps.len() <= config.max_steps);
            kinds.extend(steps.iter().map(|s| s.kind()));
        }
        assert_eq!(kinds.len(), 8, "{kinds:?}");
        // A few draws applied end to end.
        let mut rng = EotRng::new(1);
        for _ in 0..5 {
            let t = random_composition(&config, &mut rng);
            let y = t.apply(x.clone()).unwrap();
            assert!(to_vec(y).iter().all(|v| v.is_finite()));
        }
        // Serde round trip of the config and of an attack.
        let json = serde_json::to_string(&config).unwrap();
        assert_eq!(serde_json::from_str::<EotConfig>(&json).unwrap(), config);
        let t = random_composition(&config, &mut rng);
        let json = serde_json::to_string(&t).unwrap();
        assert_eq!(serde_json::from_str::<DiffAttack>(&json).unwrap(), t);
    }
}
