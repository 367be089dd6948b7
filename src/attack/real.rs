//! Real (non-differentiable) distortions of 8-bit RGB renders, used to measure how well a
//! watermark survives: a real JPEG round trip, bilinear rotation, resizing, centre crop, Gaussian
//! blur, additive Gaussian noise, brightness and contrast, and chains of these.
//!
//! Parameter names and semantics follow the public attack code of the baselines the paper compares
//! against: 3D-GSW (`kuai-lab/cvpr25_3D-GSW`, `attacker.py`), WateRF (`kuai-lab/cvpr2024_WateRF`,
//! `models/attack.py`) and GuardSplat (`NarcissusEx/GuardSplat`, `attack_utils.py`), which all use
//! torchvision. Every attack works on [`RgbImage`] and returns an [`RgbImage`]; intermediate values
//! are kept in floating point and rounded to the nearest 8-bit value once, at the end of each step.
//!
//! Conventions worth knowing (each variant of [`RealAttack`] documents its own):
//! - **Noise σ is squared**: "Gaussian noise σ = 0.1" adds noise of standard deviation
//!   σ² = 0.01 on [0, 1] images (2.55 on 0–255), as the baselines' `sigma ** 2 * randn` does.
//! - **Crop keeps a fraction of the area**, centred: `keep = 0.4` keeps √0.4 ≈ 63 % of each side.
//! - **Scale is per side and keeps the new size**: `factor = 0.75` turns 800×800 into 600×600.
//! - **Rotation is counter-clockwise** for positive degrees, about the image centre, same size,
//!   black where no input pixel lands (torchvision's `rotate` without `expand`).
//!
//! [`paper_protocol`] lists the distortions of the paper's robustness table.

use image::codecs::jpeg::JpegEncoder;
use image::imageops::{self, FilterType};
use image::{ImageFormat, RgbImage};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Largest image (in pixels) an attack may produce; larger requests fail with
/// [`AttackError::TooLarge`] before anything is allocated (a scale factor of 1000 on a render
/// would otherwise ask for terabytes).
pub const MAX_OUTPUT_PIXELS: u64 = 1 << 26;

/// Largest Gaussian-blur kernel size accepted.
pub const MAX_BLUR_KERNEL: u32 = 1023;

/// Why an attack could not be applied.
#[derive(Debug, thiserror::Error)]
pub enum AttackError {
    /// JPEG quality outside 1..=100.
    #[error("JPEG quality must be in 1..=100, got {0}")]
    JpegQuality(u8),
    /// A parameter is NaN or infinite.
    #[error("{attack}: {param} must be finite, got {value}")]
    NotFinite {
        attack: &'static str,
        param: &'static str,
        value: f32,
    },
    /// A finite parameter outside its allowed range.
    #[error("{attack}: {param} must be {expected}, got {value}")]
    OutOfRange {
        attack: &'static str,
        param: &'static str,
        value: f32,
        expected: &'static str,
    },
    /// Gaussian-blur kernel size that is even, zero or above [`MAX_BLUR_KERNEL`].
    #[error("blur: kernel size must be odd and in 1..={max}, got {kernel}")]
    BadKernel { kernel: u32, max: u32 },
    /// The input image has no pixels.
    #[error("{attack}: the input image is empty ({width}×{height})")]
    EmptyImage {
        attack: &'static str,
        width: u32,
        height: u32,
    },
    /// The attack would leave less than one pixel along a side.
    #[error(
        "{attack}: a {width}×{height} image would become {new_width}×{new_height} (at least 1×1 needed)"
    )]
    TooSmall {
        attack: &'static str,
        width: u32,
        height: u32,
        new_width: u64,
        new_height: u64,
    },
    /// The attack would produce more than [`MAX_OUTPUT_PIXELS`] pixels.
    #[error("{attack}: output of {new_width}×{new_height} exceeds the limit of {max} pixels")]
    TooLarge {
        attack: &'static str,
        new_width: u64,
        new_height: u64,
        max: u64,
    },
    /// The JPEG encoder or decoder failed (e.g. a side above 65 535 px).
    #[error("JPEG round trip failed: {0}")]
    Jpeg(#[from] image::ImageError),
    /// A step of a [`RealAttack::Chain`] failed.
    #[error("chain step {index}: {source}")]
    Chain {
        index: usize,
        #[source]
        source: Box<AttackError>,
    },
}

/// A real image distortion. Serialized adjacently tagged, e.g.
/// `{"type":"jpeg","params":{"quality":50}}` or `{"type":"chain","params":[...]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", content = "params", rename_all = "snake_case")]
pub enum RealAttack {
    /// JPEG encode at `quality` (1..=100) with `image`'s baseline encoder, then decode. The encoder
    /// scales the standard quantisation tables the libjpeg way (as OpenCV's `IMWRITE_JPEG_QUALITY`,
    /// used by the baselines, does) but does not subsample chroma (4:4:4; libjpeg defaults to
    /// 4:2:0), so at equal quality it is slightly milder on colour.
    Jpeg { quality: u8 },
    /// Rotation by `degrees`, counter-clockwise for positive values (torchvision's convention),
    /// about the image centre ((w−1)/2, (h−1)/2 in pixel indices). Same output size; bilinear
    /// resampling where pixels outside the input count as black (torchvision's `rotate` on a
    /// tensor with `InterpolationMode.BILINEAR`, no `expand`, no `fill`: `grid_sample` with zero
    /// padding). The baselines call `rotate` with its default NEAREST interpolation and a random
    /// angle in ±30°. Multiples of 90° use exact sines, so 90° moves pixels exactly and 360° is
    /// the identity.
    Rotate { degrees: f32 },
    /// Resize each side by `factor` (> 0) with the `image` crate's triangle filter (bilinear,
    /// widened when shrinking, i.e. anti-aliased like PIL's / torchvision's `resize(...,
    /// antialias=True)`). The result KEEPS the new size, floor(w·factor)×floor(h·factor), as the
    /// baselines do; it is not resized back. Note: 3D-GSW and WateRF read "scaling 75 %" as 75 %
    /// of the area (each side × √0.75 ≈ 0.866); GuardSplat as each side × U(0.75, 1). Here
    /// `factor` is always per side.
    Scale { factor: f32 },
    /// Centre crop keeping the fraction `keep` ∈ (0, 1] of the AREA: each side becomes
    /// floor(side·√keep), the crop is centred as torchvision's `center_crop` centres it, and the
    /// result keeps the cropped size. This is what 3D-GSW and WateRF do (`CropAttack`:
    /// `scale = np.sqrt(self.scale)`, `center_crop`), so "crop 40 %" is `keep = 0.4`, about 63 %
    /// of each side. (GuardSplat instead keeps 40 % of each side, i.e. `keep = 0.16` here.)
    Crop { keep: f32 },
    /// The crop of [`Crop`](Self::Crop) (the same `keep` of the area, the same size) with its
    /// window centred on (`x`, `y`), fractions of the width and height, and moved back inside the
    /// image where it would cross an edge; (0.5, 0.5) is [`Crop`](Self::Crop), pixel for pixel.
    /// The evaluation centres it on the asset in each view ([`RealAttack::at`]): the paper's
    /// objects sit in the centre of their views, so its centred crop is a crop around the
    /// object, which a scene whose cameras frame the asset off-centre only gets this way.
    CropAt { keep: f32, x: f32, y: f32 },
    /// Gaussian blur with standard deviation `sigma` (> 0, pixels) and an odd `kernel` size, as
    /// torchvision's `gaussian_blur`: separable kernel sampled at integer offsets and normalised,
    /// reflect padding (mirror without repeating the edge pixel; repeated for tiny images, where
    /// torch would refuse). Note that σ = 0.1 with kernel 3 (the paper's setting, and 3D-GSW's
    /// code) gives neighbour weights of e⁻⁵⁰ and leaves 8-bit images unchanged; GuardSplat and
    /// WateRF omit σ, so torchvision uses 0.3·((k−1)/2 − 1) + 0.8 = 0.8 for k = 3.
    Blur { sigma: f32, kernel: u32 },
    /// Additive Gaussian noise. `sigma` is the PAPERS' parameter, and the noise added has standard
    /// deviation `sigma²` on [0, 1] images, i.e. `sigma² · 255` on 8-bit values (σ = 0.1 → 0.01 →
    /// 2.55 grey levels), as the baselines' `image + sigma ** 2 * torch.randn_like(image)`. The
    /// result is clamped to [0, 255] and rounded. Deterministic for a given `seed` (SplitMix64 +
    /// Box–Muller, see [`NormalRng`]), independent of the number of threads.
    Noise { sigma: f32, seed: u64 },
    /// Multiply every value by `factor` (≥ 0) and clamp: torchvision's `adjust_brightness`
    /// (blend with black). Rounded to nearest; torchvision truncates uint8 results (≤ 1 level).
    Brightness { factor: f32 },
    /// Blend with the mean grey level: `factor·x + (1 − factor)·mean`, clamped, where `mean` is
    /// the image mean of the uint8 luma 0.2989 R + 0.587 G + 0.114 B (truncated per pixel):
    /// torchvision's `adjust_contrast`. `factor` ≥ 0. Rounded to nearest.
    Contrast { factor: f32 },
    /// The attacks applied in order, the output of one being the input of the next.
    Chain(Vec<RealAttack>),
}

impl RealAttack {
    /// The same attack with every centred crop in it ([`Crop`](Self::Crop), in a chain too)
    /// centred on (`x`, `y`) instead ([`CropAt`](Self::CropAt)); `None` when it crops nothing.
    pub fn at(&self, x: f32, y: f32) -> Option<Self> {
        match self {
            Self::Crop { keep } => Some(Self::CropAt { keep: *keep, x, y }),
            Self::Chain(steps) => {
                let moved: Vec<Option<Self>> = steps.iter().map(|s| s.at(x, y)).collect();
                moved.iter().any(Option::is_some).then(|| {
                    Self::Chain(
                        moved
                            .into_iter()
                            .zip(steps)
                            .map(|(m, s)| m.unwrap_or_else(|| s.clone()))
                            .collect(),
                    )
                })
            }
            _ => None,
        }
    }

    /// Short snake_case name of the variant (the serde tag).
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Jpeg { .. } => "jpeg",
            Self::Rotate { .. } => "rotate",
            Self::Scale { .. } => "scale",
            Self::Crop { .. } => "crop",
            Self::CropAt { .. } => "crop_at",
            Self::Blur { .. } => "blur",
            Self::Noise { .. } => "noise",
            Self::Brightness { .. } => "brightness",
            Self::Contrast { .. } => "contrast",
            Self::Chain(_) => "chain",
        }
    }

    /// Checks the parameters that do not depend on the image (for a chain, every step), so bad
    /// requests fail before any work. [`apply`](Self::apply) calls it too.
    pub fn validate(&self) -> Result<(), AttackError> {
        let name = self.kind();
        match *self {
            Self::Jpeg { quality } => {
                if quality == 0 || quality > 100 {
                    return Err(AttackError::JpegQuality(quality));
                }
            }
            Self::Rotate { degrees } => finite(name, "degrees", degrees)?,
            Self::Scale { factor } => positive(name, "factor", factor)?,
            Self::Crop { keep } => keep_fraction(name, keep)?,
            Self::CropAt { keep, x, y } => {
                keep_fraction(name, keep)?;
                for (param, v) in [("x", x), ("y", y)] {
                    finite(name, param, v)?;
                    if !(0.0..=1.0).contains(&v) {
                        return Err(out_of_range(name, param, v, "in [0, 1]"));
                    }
                }
            }
            Self::Blur { sigma, kernel } => {
                positive(name, "sigma", sigma)?;
                if kernel % 2 == 0 || kernel > MAX_BLUR_KERNEL {
                    return Err(AttackError::BadKernel {
                        kernel,
                        max: MAX_BLUR_KERNEL,
                    });
                }
            }
            Self::Noise { sigma, .. } => non_negative(name, "sigma", sigma)?,
            Self::Brightness { factor } | Self::Contrast { factor } => {
                non_negative(name, "factor", factor)?
            }
            Self::Chain(ref steps) => {
                for (index, step) in steps.iter().enumerate() {
                    step.validate().map_err(|e| AttackError::Chain {
                        index,
                        source: Box::new(e),
                    })?;
                }
            }
        }
        Ok(())
    }

    /// Applies the attack to `img`. Errors on invalid parameters, on an empty input, and when
    /// scaling or cropping would leave less than one pixel (or more than [`MAX_OUTPUT_PIXELS`]).
    pub fn apply(&self, img: &RgbImage) -> Result<RgbImage, AttackError> {
        self.validate()?;
        self.apply_unchecked(img)
    }

    fn apply_unchecked(&self, img: &RgbImage) -> Result<RgbImage, AttackError> {
        if let Self::Chain(steps) = self {
            let mut current = img.clone();
            for (index, step) in steps.iter().enumerate() {
                current = step
                    .apply_unchecked(&current)
                    .map_err(|e| AttackError::Chain {
                        index,
                        source: Box::new(e),
                    })?;
            }
            return Ok(current);
        }
        let (width, height) = img.dimensions();
        if width == 0 || height == 0 {
            return Err(AttackError::EmptyImage {
                attack: self.kind(),
                width,
                height,
            });
        }
        Ok(match *self {
            Self::Jpeg { quality } => jpeg(img, quality)?,
            Self::Rotate { degrees } => rotate(img, degrees),
            Self::Scale { factor } => scale(img, factor)?,
            Self::Crop { keep } => crop(img, keep, 0.5, 0.5)?,
            Self::CropAt { keep, x, y } => crop(img, keep, x, y)?,
            Self::Blur { sigma, kernel } => blur(img, sigma, kernel),
            Self::Noise { sigma, seed } => noise(img, sigma, seed),
            Self::Brightness { factor } => brightness(img, factor),
            Self::Contrast { factor } => contrast(img, factor),
            Self::Chain(_) => unreachable!("handled above"),
        })
    }
}

/// The distortions of the paper's robustness table (Table "bit accuracy under distortions"), in
/// its column order, read as the 3D-GSW code the paper's protocol follows reads them: Gaussian
/// noise σ = 0.1 (std 0.01), rotation ±π/6 (here the fixed worst case +30°), scaling 75 % of the
/// area (each side × √0.75; 3D-GSW/WateRF `ScalingAttack`), Gaussian blur σ = 0.1 with kernel 3,
/// crop 40 % of the area (centred), JPEG quality 50, and combined = noise, then crop, then JPEG.
/// `seed` drives the noise.
///
/// Note: blur σ = 0.1 leaves an 8-bit image unchanged (neighbour weights are e⁻⁵⁰); the paper's
/// figure for it therefore measures nothing. Evaluations may add a σ = 0.8 row (torchvision's
/// default, used by GuardSplat and WateRF) to show a blur that does act.
pub fn paper_protocol(seed: u64) -> Vec<(&'static str, RealAttack)> {
    let noise = RealAttack::Noise { sigma: 0.1, seed };
    let crop = RealAttack::Crop { keep: 0.4 };
    let jpeg = RealAttack::Jpeg { quality: 50 };
    vec![
        ("noise", noise.clone()),
        ("rotation", RealAttack::Rotate { degrees: 30.0 }),
        (
            "scaling",
            RealAttack::Scale {
                factor: 0.75f32.sqrt(),
            },
        ),
        (
            "blur",
            RealAttack::Blur {
                sigma: 0.1,
                kernel: 3,
            },
        ),
        ("crop", crop.clone()),
        ("jpeg", jpeg.clone()),
        ("combined", RealAttack::Chain(vec![noise, crop, jpeg])),
    ]
}

// ---------------------------------------------------------------------------------------------
// Parameter checks

fn finite(attack: &'static str, param: &'static str, value: f32) -> Result<(), AttackError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(AttackError::NotFinite {
            attack,
            param,
            value,
        })
    }
}

fn keep_fraction(attack: &'static str, keep: f32) -> Result<(), AttackError> {
    finite(attack, "keep", keep)?;
    if keep > 0.0 && keep <= 1.0 {
        Ok(())
    } else {
        Err(out_of_range(attack, "keep", keep, "in (0, 1]"))
    }
}

fn out_of_range(
    attack: &'static str,
    param: &'static str,
    value: f32,
    expected: &'static str,
) -> AttackError {
    AttackError::OutOfRange {
        attack,
        param,
        value,
        expected,
    }
}

fn positive(attack: &'static str, param: &'static str, value: f32) -> Result<(), AttackError> {
    finite(attack, param, value)?;
    if value > 0.0 {
        Ok(())
    } else {
        Err(out_of_range(attack, param, value, "> 0"))
    }
}

fn non_negative(attack: &'static str, param: &'static str, value: f32) -> Result<(), AttackError> {
    finite(attack, param, value)?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(out_of_range(attack, param, value, ">= 0"))
    }
}

/// floor(len · ratio), forgiving the f32 representation error of `ratio` (0.7_f32 is
/// 0.69999999, and 10 × 0.7 must still give 7 as it does in the baselines' float64 Python).
fn scaled_len(len: u32, ratio: f64) -> u64 {
    let x = f64::from(len) * ratio;
    (x + x * 1e-6).floor() as u64
}

/// Checks a new size against 1×1 and [`MAX_OUTPUT_PIXELS`].
fn check_size(
    attack: &'static str,
    img: &RgbImage,
    new_width: u64,
    new_height: u64,
) -> Result<(u32, u32), AttackError> {
    let (width, height) = img.dimensions();
    if new_width == 0 || new_height == 0 {
        return Err(AttackError::TooSmall {
            attack,
            width,
            height,
            new_width,
            new_height,
        });
    }
    match new_width.checked_mul(new_height) {
        Some(n) if n <= MAX_OUTPUT_PIXELS => Ok((new_width as u32, new_height as u32)),
        _ => Err(AttackError::TooLarge {
            attack,
            new_width,
            new_height,
            max: MAX_OUTPUT_PIXELS,
        }),
    }
}

#[inline]
fn to_u8(v: f64) -> u8 {
    // `as` saturates, NaN would give 0; the clamp keeps the intent explicit.
    v.clamp(0.0, 255.0).round() as u8
}

// ---------------------------------------------------------------------------------------------
// The attacks

fn jpeg(img: &RgbImage, quality: u8) -> Result<RgbImage, AttackError> {
    let mut bytes = Vec::new();
    JpegEncoder::new_with_quality(&mut bytes, quality).encode_image(img)?;
    Ok(image::load_from_memory_with_format(&bytes, ImageFormat::Jpeg)?.to_rgb8())
}

/// (sin θ, cos θ) with exact values at multiples of 90°.
fn sin_cos_degrees(degrees: f32) -> (f64, f64) {
    let d = f64::from(degrees).rem_euclid(360.0);
    if d == 0.0 {
        (0.0, 1.0)
    } else if d == 90.0 {
        (1.0, 0.0)
    } else if d == 180.0 {
        (0.0, -1.0)
    } else if d == 270.0 {
        (-1.0, 0.0)
    } else {
        d.to_radians().sin_cos()
    }
}

fn rotate(img: &RgbImage, degrees: f32) -> RgbImage {
    let (w, h) = img.dimensions();
    let (sin, cos) = sin_cos_degrees(degrees);
    let (cx, cy) = ((f64::from(w) - 1.0) / 2.0, (f64::from(h) - 1.0) / 2.0);
    let src = img.as_raw();
    let (wi, hi) = (i64::from(w), i64::from(h));
    let mut out = RgbImage::new(w, h);
    out.par_chunks_mut(w as usize * 3)
        .enumerate()
        .for_each(|(y, row)| {
            let dy = y as f64 - cy;
            for (x, px) in row.chunks_exact_mut(3).enumerate() {
                let dx = x as f64 - cx;
                // Inverse map of a counter-clockwise rotation in y-down image coordinates.
                let sx = cx + dx * cos - dy * sin;
                let sy = cy + dx * sin + dy * cos;
                let (x0, y0) = (sx.floor(), sy.floor());
                let (fx, fy) = (sx - x0, sy - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let mut acc = [0.0f64; 3];
                for (yy, wy) in [(y0, 1.0 - fy), (y0 + 1, fy)] {
                    if wy == 0.0 || yy < 0 || yy >= hi {
                        continue;
                    }
                    for (xx, wx) in [(x0, 1.0 - fx), (x0 + 1, fx)] {
                        if wx == 0.0 || xx < 0 || xx >= wi {
                            continue;
                        }
                        let i = ((yy * wi + xx) * 3) as usize;
                        let wgt = wx * wy;
                        for c in 0..3 {
                            acc[c] += wgt * f64::from(src[i + c]);
                        }
                    }
                }
                for c in 0..3 {
                    px[c] = to_u8(acc[c]);
                }
            }
        });
    out
}

fn scale(img: &RgbImage, factor: f32) -> Result<RgbImage, AttackError> {
    let (w, h) = img.dimensions();
    let f = f64::from(factor);
    let (nw, nh) = check_size("scale", img, scaled_len(w, f), scaled_len(h, f))?;
    if (nw, nh) == (w, h) {
        return Ok(img.clone());
    }
    Ok(imageops::resize(img, nw, nh, FilterType::Triangle))
}

/// The crop of `keep` of the area centred on (`x`, `y`) (fractions of the sides), inside the
/// image. At the centre this is torchvision's `center_crop`: top = int(round((h − ch) / 2)),
/// Python rounding half to even.
fn crop(img: &RgbImage, keep: f32, x: f32, y: f32) -> Result<RgbImage, AttackError> {
    let (w, h) = img.dimensions();
    let side = f64::from(keep).sqrt();
    let (cw, ch) = check_size("crop", img, scaled_len(w, side), scaled_len(h, side))?;
    let start = |len: u32, cut: u32, at: f32| {
        (f64::from(len) * f64::from(at) - f64::from(cut) / 2.0)
            .round_ties_even()
            .clamp(0.0, f64::from(len - cut)) as u32
    };
    Ok(imageops::crop_imm(img, start(w, cw, x), start(h, ch, y), cw, ch).to_image())
}

/// Index into 0..n after reflect padding (…, 2, 1, [0, 1, …, n−1], n−2, …), repeated as needed.
fn reflect(i: i64, n: i64) -> usize {
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - m }) as usize
}

fn blur(img: &RgbImage, sigma: f32, kernel: u32) -> RgbImage {
    let (w, h) = img.dimensions();
    let (wu, hu) = (w as usize, h as usize);
    let half = i64::from(kernel / 2);
    let sigma = f64::from(sigma);
    let mut weights: Vec<f64> = (-half..=half)
        .map(|d| (-0.5 * (d as f64 / sigma).powi(2)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.iter_mut().for_each(|v| *v /= total);

    let src = img.as_raw();
    // Horizontal pass into f64, then vertical pass with rounding.
    let mut tmp = vec![0.0f64; wu * hu * 3];
    tmp.par_chunks_mut(wu * 3).enumerate().for_each(|(y, row)| {
        let line = &src[y * wu * 3..(y + 1) * wu * 3];
        for x in 0..wu {
            let mut acc = [0.0f64; 3];
            for (k, wk) in weights.iter().enumerate() {
                let sx = reflect(x as i64 + k as i64 - half, i64::from(w));
                for c in 0..3 {
                    acc[c] += wk * f64::from(line[sx * 3 + c]);
                }
            }
            row[x * 3..x * 3 + 3].copy_from_slice(&acc);
        }
    });
    let mut out = RgbImage::new(w, h);
    out.par_chunks_mut(wu * 3).enumerate().for_each(|(y, row)| {
        let mut acc = vec![0.0f64; wu * 3];
        for (k, wk) in weights.iter().enumerate() {
            let sy = reflect(y as i64 + k as i64 - half, i64::from(h));
            let line = &tmp[sy * wu * 3..(sy + 1) * wu * 3];
            for (a, v) in acc.iter_mut().zip(line) {
                *a += wk * v;
            }
        }
        for (o, a) in row.iter_mut().zip(&acc) {
            *o = to_u8(*a);
        }
    });
    out
}

/// Subpixels per parallel work item of the noise attack (even, so pairs never straddle items).
const NOISE_CHUNK: usize = 1 << 14;

fn noise(img: &RgbImage, sigma: f32, seed: u64) -> RgbImage {
    let std = f64::from(sigma) * f64::from(sigma) * 255.0;
    let mut out = img.clone();
    if std == 0.0 {
        return out;
    }
    out.par_chunks_mut(NOISE_CHUNK)
        .enumerate()
        .for_each(|(chunk, values)| {
            // Subpixel i uses normal number i of the stream, whatever the chunking.
            let mut rng = NormalRng::new(seed);
            rng.skip_normals((chunk * NOISE_CHUNK) as u64);
            for pair in values.chunks_mut(2) {
                let (z0, z1) = rng.normal_pair();
                for (v, z) in pair.iter_mut().zip([z0, z1]) {
                    *v = to_u8(f64::from(*v) + std * z);
                }
            }
        });
    out
}

fn brightness(img: &RgbImage, factor: f32) -> RgbImage {
    let f = f64::from(factor);
    let mut out = img.clone();
    out.par_chunks_mut(NOISE_CHUNK)
        .for_each(|vs| vs.iter_mut().for_each(|v| *v = to_u8(f * f64::from(*v))));
    out
}

fn contrast(img: &RgbImage, factor: f32) -> RgbImage {
    let f = f64::from(factor);
    let sum: u64 = img
        .pixels()
        .map(|p| {
            let [r, g, b] = p.0;
            // torchvision's rgb_to_grayscale in float32, then `.to(uint8)` (truncation).
            let l = 0.2989f32 * f32::from(r) + 0.587f32 * f32::from(g) + 0.114f32 * f32::from(b);
            l as u64
        })
        .sum();
    let mean = sum as f64 / (u64::from(img.width()) * u64::from(img.height())) as f64;
    let offset = (1.0 - f) * mean;
    let mut out = img.clone();
    out.par_chunks_mut(NOISE_CHUNK).for_each(|vs| {
        vs.iter_mut()
            .for_each(|v| *v = to_u8(f * f64::from(*v) + offset))
    });
    out
}

// ---------------------------------------------------------------------------------------------
// Deterministic normal random numbers

const SPLITMIX_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// A small deterministic source of standard normal numbers: SplitMix64 (Steele, Lea & Flood
/// 2014) for uniform bits, Box–Muller for pairs of normals. SplitMix64 is a counter, so
/// [`skip_normals`](Self::skip_normals) jumps ahead in O(1): streams can be split across threads
/// and still give the same numbers. Not cryptographic.
#[derive(Debug, Clone)]
pub struct NormalRng {
    state: u64,
}

impl NormalRng {
    /// A stream determined by `seed`.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// Next 64 uniform bits (SplitMix64).
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(SPLITMIX_GAMMA);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Skips `n` normal numbers (n/2 pairs; `n` should be even to stay pair-aligned).
    pub fn skip_normals(&mut self, n: u64) {
        self.state = self.state.wrapping_add(n.wrapping_mul(SPLITMIX_GAMMA));
    }

    /// Two independent standard normal numbers (Box–Muller), consuming two `u64`s.
    pub fn normal_pair(&mut self) -> (f64, f64) {
        const TWO_POW_M53: f64 = 1.0 / (1u64 << 53) as f64;
        // u1 in (0, 1] so ln(u1) is finite; u2 in [0, 1).
        let u1 = ((self.next_u64() >> 11) + 1) as f64 * TWO_POW_M53;
        let u2 = (self.next_u64() >> 11) as f64 * TWO_POW_M53;
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        (r * c, r * s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    /// A smooth colour gradient.
    fn gradient(w: u32, h: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| {
            Rgb([
                (40 + x * 160 / w) as u8,
                (30 + y * 180 / h) as u8,
                (60 + (x + y) * 120 / (w + h)) as u8,
            ])
        })
    }

    /// Gradient plus texture, so JPEG quality matters.
    fn textured(w: u32, h: u32) -> RgbImage {
        let mut rng = NormalRng::new(7);
        let g = gradient(w, h);
        RgbImage::from_fn(w, h, |x, y| {
            let p = g.get_pixel(x, y).0;
            let t = if (x / 3 + y / 2) % 2 == 0 {
                30.0
            } else {
                -30.0
            };
            let mut q = [0u8; 3];
            for c in 0..3 {
                q[c] = to_u8(f64::from(p[c]) + t + 10.0 * rng.normal_pair().0);
            }
            Rgb(q)
        })
    }

    fn constant(w: u32, h: u32, v: u8) -> RgbImage {
        RgbImage::from_pixel(w, h, Rgb([v, v, v]))
    }

    fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
        assert_eq!(a.dimensions(), b.dimensions());
        let mse = a
            .as_raw()
            .iter()
            .zip(b.as_raw())
            .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
            .sum::<f64>()
            / a.as_raw().len() as f64;
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }

    fn mean_var(vs: impl Iterator<Item = f64>) -> (f64, f64) {
        let v: Vec<f64> = vs.collect();
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        (m, v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n)
    }

    fn run(a: RealAttack, img: &RgbImage) -> RgbImage {
        a.apply(img).unwrap()
    }

    #[test]
    fn jpeg_q100_is_close_and_q10_worse_than_q90() {
        let g = gradient(64, 48);
        let q100 = run(RealAttack::Jpeg { quality: 100 }, &g);
        assert_eq!(q100.dimensions(), g.dimensions());
        let p = psnr(&g, &q100);
        assert!(p > 40.0, "q=100 PSNR {p}");

        let t = textured(64, 48);
        let p90 = psnr(&t, &run(RealAttack::Jpeg { quality: 90 }, &t));
        let p10 = psnr(&t, &run(RealAttack::Jpeg { quality: 10 }, &t));
        assert!(p10 + 3.0 < p90, "q=10 {p10} dB vs q=90 {p90} dB");
        // A real round trip changes the image even at q=90.
        assert!(p90.is_finite());
    }

    #[test]
    fn rotate_identity_90_and_360() {
        let t = textured(20, 14);
        assert_eq!(run(RealAttack::Rotate { degrees: 0.0 }, &t), t);
        assert_eq!(run(RealAttack::Rotate { degrees: 360.0 }, &t), t);
        assert_eq!(run(RealAttack::Rotate { degrees: -720.0 }, &t), t);

        // 90° counter-clockwise on a square image: a pixel right of and above the centre goes
        // above and left of it. Centre (3.5, 3.5); (6, 2) = (+2.5, −1.5) → (−1.5, −2.5) = (2, 1).
        let mut img = constant(8, 8, 0);
        img.put_pixel(6, 2, Rgb([255, 128, 7]));
        let r = run(RealAttack::Rotate { degrees: 90.0 }, &img);
        assert_eq!(r.get_pixel(2, 1).0, [255, 128, 7]);
        assert_eq!(
            r.as_raw().iter().map(|&v| u32::from(v)).sum::<u32>(),
            255 + 128 + 7
        );
        // −90° goes the other way: (+2.5, −1.5) → (+1.5, +2.5) = (5, 6).
        let r = run(RealAttack::Rotate { degrees: -90.0 }, &img);
        assert_eq!(r.get_pixel(5, 6).0, [255, 128, 7]);
        // Four quarter turns give the input back.
        let sq = textured(9, 9);
        let mut q = sq.clone();
        for _ in 0..4 {
            q = run(RealAttack::Rotate { degrees: 90.0 }, &q);
        }
        assert_eq!(q, sq);
    }

    #[test]
    fn rotate_arbitrary_angle_is_bilinear_with_black_corners() {
        // A constant image rotated by 30°: interior stays constant, corners turn black,
        // and the centre pixel of an odd-sized image stays put.
        let img = constant(31, 31, 200);
        let r = run(RealAttack::Rotate { degrees: 30.0 }, &img);
        assert_eq!(r.dimensions(), (31, 31));
        assert_eq!(r.get_pixel(15, 15).0, [200; 3]);
        assert_eq!(r.get_pixel(10, 15).0, [200; 3]);
        assert_eq!(r.get_pixel(0, 0).0, [0; 3]);
        assert_eq!(r.get_pixel(30, 30).0, [0; 3]);
        // Bilinear: a sample half-way between two pixels averages them. A 1-px vertical line at
        // x = 4 in a 9×9 image rotated by a tiny angle stays a (slightly smeared) line.
        let mut line = constant(9, 9, 0);
        for y in 0..9 {
            line.put_pixel(4, y, Rgb([200; 3]));
        }
        let r = run(RealAttack::Rotate { degrees: 1.0 }, &line);
        assert!(r.get_pixel(4, 4).0[0] == 200);
        assert!(r.get_pixel(4, 0).0[0] > 150 && r.get_pixel(4, 0).0[0] < 200);
        assert!(r.get_pixel(3, 0).0[0] > 0 || r.get_pixel(5, 0).0[0] > 0);
    }

    #[test]
    fn scale_size_and_identity() {
        let g = gradient(64, 48);
        let s = run(RealAttack::Scale { factor: 0.75 }, &g);
        assert_eq!(s.dimensions(), (48, 36));
        assert_eq!(run(RealAttack::Scale { factor: 1.0 }, &g), g);
        // 0.7_f32 is below 0.7; 10 × 0.7 must still be 7 (as in float64 Python).
        let s = run(RealAttack::Scale { factor: 0.7 }, &constant(10, 10, 90));
        assert_eq!(s.dimensions(), (7, 7));
        assert!(s.pixels().all(|p| p.0 == [90; 3]));
        let up = run(RealAttack::Scale { factor: 2.0 }, &g);
        assert_eq!(up.dimensions(), (128, 96));
        // Downscaling a gradient keeps its range (anti-aliased triangle filter, no overshoot).
        let small = run(RealAttack::Scale { factor: 0.5 }, &g);
        assert_eq!(small.dimensions(), (32, 24));
        let (lo, hi) = (small.get_pixel(0, 0).0[0], small.get_pixel(31, 0).0[0]);
        assert!(
            (40..50).contains(&lo) && (186..=200).contains(&hi),
            "{lo} {hi}"
        );
    }

    #[test]
    fn crop_keeps_centre_area_fraction() {
        let t = textured(100, 80);
        let c = run(RealAttack::Crop { keep: 0.4 }, &t);
        // √0.4 = 0.6325: 63 × 50; left = round_half_even(37 / 2 = 18.5) = 18, top = 15.
        assert_eq!(c.dimensions(), (63, 50));
        for y in 0..50 {
            for x in 0..63 {
                assert_eq!(c.get_pixel(x, y), t.get_pixel(x + 18, y + 15));
            }
        }
        let q = run(RealAttack::Crop { keep: 0.25 }, &t);
        assert_eq!(q.dimensions(), (50, 40));
        assert_eq!(q.get_pixel(0, 0), t.get_pixel(25, 20));
        assert_eq!(run(RealAttack::Crop { keep: 1.0 }, &t), t);
    }

    #[test]
    fn a_crop_centred_elsewhere_keeps_its_size_and_stays_inside_the_image() {
        let t = textured(100, 80);
        let at = |x, y| run(RealAttack::CropAt { keep: 0.4, x, y }, &t);
        // At the centre it is the protocol's crop, pixel for pixel.
        assert_eq!(at(0.5, 0.5), run(RealAttack::Crop { keep: 0.4 }, &t));
        // Centred on (30, 48): left = round(30 − 31.5) clamped to 0, top = 48 − 25 = 23.
        let c = at(0.3, 0.6);
        assert_eq!(c.dimensions(), (63, 50));
        for (x, y) in [(0, 0), (62, 0), (0, 49), (62, 49)] {
            assert_eq!(c.get_pixel(x, y), t.get_pixel(x, y + 23));
        }
        // Towards the bottom-right corner the window stops at the edges.
        let c = at(1.0, 1.0);
        assert_eq!(c.get_pixel(62, 49), t.get_pixel(99, 79));
        assert_eq!(c.get_pixel(0, 0), t.get_pixel(37, 30));
        for (x, y) in [(-0.1, 0.5), (0.5, 1.5), (f32::NAN, 0.5)] {
            assert!(matches!(
                RealAttack::CropAt { keep: 0.4, x, y }.validate(),
                Err(AttackError::OutOfRange { .. } | AttackError::NotFinite { .. })
            ));
        }
    }

    #[test]
    fn moving_the_crop_changes_only_the_crops_of_an_attack() {
        let combined = paper_protocol(3)
            .into_iter()
            .find(|(n, _)| *n == "combined")
            .unwrap()
            .1;
        let RealAttack::Chain(steps) = combined.at(0.2, 0.9).unwrap() else {
            panic!("a chain stays a chain");
        };
        assert!(matches!(steps[0], RealAttack::Noise { seed: 3, .. }));
        assert_eq!(
            steps[1],
            RealAttack::CropAt {
                keep: 0.4,
                x: 0.2,
                y: 0.9
            }
        );
        assert_eq!(steps[2], RealAttack::Jpeg { quality: 50 });
        assert_eq!(RealAttack::Jpeg { quality: 50 }.at(0.2, 0.9), None);
    }

    #[test]
    fn blur_constant_exact_and_checkerboard_smoothed() {
        let c = constant(17, 9, 123);
        let b = run(
            RealAttack::Blur {
                sigma: 2.0,
                kernel: 7,
            },
            &c,
        );
        assert_eq!(b, c);

        let board = RgbImage::from_fn(16, 16, |x, y| {
            if (x + y) % 2 == 0 {
                Rgb([220; 3])
            } else {
                Rgb([30; 3])
            }
        });
        let var = |img: &RgbImage| mean_var(img.as_raw().iter().map(|&v| f64::from(v))).1;
        let b = run(
            RealAttack::Blur {
                sigma: 1.0,
                kernel: 3,
            },
            &board,
        );
        assert!(
            var(&b) < 0.5 * var(&board),
            "{} vs {}",
            var(&b),
            var(&board)
        );
        // Reflect padding keeps the border of a checkerboard symmetric with the interior.
        assert_eq!(b.get_pixel(0, 0), b.get_pixel(2, 2));

        // The paper's setting (σ = 0.1, k = 3) does not change 8-bit images; kernel 1 neither.
        let p = RealAttack::Blur {
            sigma: 0.1,
            kernel: 3,
        };
        assert_eq!(run(p, &board), board);
        let k1 = RealAttack::Blur {
            sigma: 5.0,
            kernel: 1,
        };
        assert_eq!(run(k1, &board), board);
        // Huge kernel on a tiny image: reflection repeats instead of failing.
        let tiny = textured(2, 3);
        let big = RealAttack::Blur {
            sigma: 3.0,
            kernel: 11,
        };
        assert_eq!(run(big, &tiny).dimensions(), (2, 3));
    }

    #[test]
    fn blur_matches_torchvision_weights() {
        // k = 3, σ = 0.8 (torchvision's default for k = 3): weights e^(-1/1.28) ≈ 0.4578, 1.
        let w = (-0.5f64 / 0.64).exp();
        let (side, mid) = (w / (1.0 + 2.0 * w), 1.0 / (1.0 + 2.0 * w));
        let mut img = constant(5, 5, 0);
        img.put_pixel(2, 2, Rgb([255; 3]));
        let b = run(
            RealAttack::Blur {
                sigma: 0.8,
                kernel: 3,
            },
            &img,
        );
        assert_eq!(b.get_pixel(2, 2).0[0], to_u8(255.0 * mid * mid));
        assert_eq!(b.get_pixel(1, 2).0[0], to_u8(255.0 * side * mid));
        assert_eq!(b.get_pixel(1, 1).0[0], to_u8(255.0 * side * side));
        assert_eq!(b.get_pixel(0, 0).0[0], 0);
    }

    #[test]
    fn noise_is_seeded_and_has_sigma_squared_std() {
        let grey = constant(128, 128, 128);
        let a = run(
            RealAttack::Noise {
                sigma: 0.3,
                seed: 1,
            },
            &grey,
        );
        let b = run(
            RealAttack::Noise {
                sigma: 0.3,
                seed: 1,
            },
            &grey,
        );
        let c = run(
            RealAttack::Noise {
                sigma: 0.3,
                seed: 2,
            },
            &grey,
        );
        assert_eq!(a, b);
        assert_ne!(a, c);
        // σ = 0.3 → std 0.09 on [0, 1] = 22.95 levels (clamping at 128 ± 5.6 std is negligible);
        // rounding adds 1/12 to the variance.
        let (m, v) = mean_var(a.as_raw().iter().map(|&x| f64::from(x)));
        let expected = 0.3f64 * 0.3 * 255.0;
        assert!((m - 128.0).abs() < 0.3, "mean {m}");
        let sd = (v - 1.0 / 12.0).sqrt();
        assert!((sd / expected - 1.0).abs() < 0.02, "std {sd} vs {expected}");

        // The paper's σ = 0.1 → 2.55 levels.
        let p = run(
            RealAttack::Noise {
                sigma: 0.1,
                seed: 9,
            },
            &grey,
        );
        let sd = (mean_var(p.as_raw().iter().map(|&x| f64::from(x))).1 - 1.0 / 12.0).sqrt();
        assert!((sd / 2.55 - 1.0).abs() < 0.03, "std {sd}");

        assert_eq!(
            run(
                RealAttack::Noise {
                    sigma: 0.0,
                    seed: 3
                },
                &grey
            ),
            grey
        );

        // Clamped at the ends of the range.
        let white = run(
            RealAttack::Noise {
                sigma: 0.5,
                seed: 4,
            },
            &constant(8, 8, 255),
        );
        assert!(white.as_raw().iter().any(|&v| v < 255));
    }

    #[test]
    fn noise_stream_does_not_depend_on_chunking() {
        // An image larger than one work item: compare with a sequential stream.
        let img = constant(100, 100, 100);
        let out = run(
            RealAttack::Noise {
                sigma: 0.2,
                seed: 77,
            },
            &img,
        );
        let mut rng = NormalRng::new(77);
        let std = 0.2f64 * 0.2 * 255.0;
        let raw = img.as_raw();
        for i in (0..raw.len()).step_by(2) {
            let (z0, z1) = rng.normal_pair();
            assert_eq!(out.as_raw()[i], to_u8(f64::from(raw[i]) + std * z0));
            assert_eq!(out.as_raw()[i + 1], to_u8(f64::from(raw[i + 1]) + std * z1));
        }
    }

    #[test]
    fn normal_rng_moments() {
        let mut rng = NormalRng::new(123);
        let v: Vec<f64> = (0..100_000)
            .flat_map(|_| {
                let (a, b) = rng.normal_pair();
                [a, b]
            })
            .collect();
        let (m, var) = mean_var(v.iter().copied());
        assert!(m.abs() < 0.01, "mean {m}");
        assert!((var - 1.0).abs() < 0.02, "var {var}");
        assert!(v.iter().all(|x| x.is_finite()));
        let mut skipped = NormalRng::new(123);
        skipped.skip_normals(10);
        let mut stepped = NormalRng::new(123);
        for _ in 0..5 {
            stepped.normal_pair();
        }
        assert_eq!(skipped.normal_pair(), stepped.normal_pair());
    }

    #[test]
    fn brightness_and_contrast() {
        let t = textured(20, 10);
        assert_eq!(run(RealAttack::Brightness { factor: 1.0 }, &t), t);
        assert_eq!(run(RealAttack::Contrast { factor: 1.0 }, &t), t);
        let half = run(RealAttack::Brightness { factor: 0.5 }, &constant(4, 4, 101));
        assert!(half.pixels().all(|p| p.0 == [51; 3])); // 50.5 rounds to 51 (ties away)
        let dbl = run(RealAttack::Brightness { factor: 2.0 }, &constant(4, 4, 200));
        assert!(dbl.pixels().all(|p| p.0 == [255; 3]));
        // Contrast 0: every value becomes the mean luma (two halves 0 and 200 → 100).
        let two = RgbImage::from_fn(4, 4, |x, _| if x < 2 { Rgb([0; 3]) } else { Rgb([200; 3]) });
        let flat = run(RealAttack::Contrast { factor: 0.0 }, &two);
        // luma of 200 grey in float32 is 199.99..., truncated to 199 as in torchvision.
        let l = (0.2989f32 * 200.0 + 0.587f32 * 200.0 + 0.114f32 * 200.0) as u8;
        let expected = to_u8(f64::from(l) / 2.0);
        assert!(flat.pixels().all(|p| p.0 == [expected; 3]), "{expected}");
        let more = run(RealAttack::Contrast { factor: 1.5 }, &two);
        assert_eq!(more.get_pixel(0, 0).0[0], 0);
        assert_eq!(more.get_pixel(3, 0).0[0], 250); // 1.5·200 − 0.5·99.5 = 250.25
    }

    #[test]
    fn chain_applies_in_order() {
        let img = constant(10, 10, 200);
        let up_down = RealAttack::Chain(vec![
            RealAttack::Brightness { factor: 2.0 },
            RealAttack::Brightness { factor: 0.5 },
        ]);
        let down_up = RealAttack::Chain(vec![
            RealAttack::Brightness { factor: 0.5 },
            RealAttack::Brightness { factor: 2.0 },
        ]);
        assert!(run(up_down, &img).pixels().all(|p| p.0 == [128; 3])); // 255 / 2 → 128
        assert_eq!(run(down_up, &img), img);

        let t = textured(40, 30);
        let steps = vec![
            RealAttack::Crop { keep: 0.5 },
            RealAttack::Rotate { degrees: 10.0 },
            RealAttack::Jpeg { quality: 70 },
        ];
        let mut manual = t.clone();
        for s in &steps {
            manual = s.apply(&manual).unwrap();
        }
        assert_eq!(run(RealAttack::Chain(steps), &t), manual);
        assert_eq!(run(RealAttack::Chain(vec![]), &t), t);
    }

    #[test]
    fn invalid_parameters_are_errors() {
        use AttackError as E;
        let t = textured(8, 8);
        let err = |a: RealAttack| a.apply(&t).unwrap_err();
        assert!(matches!(
            err(RealAttack::Jpeg { quality: 0 }),
            E::JpegQuality(0)
        ));
        assert!(matches!(
            err(RealAttack::Jpeg { quality: 101 }),
            E::JpegQuality(101)
        ));
        assert!(matches!(
            err(RealAttack::Rotate { degrees: f32::NAN }),
            E::NotFinite { .. }
        ));
        assert!(matches!(
            err(RealAttack::Rotate {
                degrees: f32::INFINITY
            }),
            E::NotFinite { .. }
        ));
        for factor in [0.0, -1.0] {
            assert!(matches!(
                err(RealAttack::Scale { factor }),
                E::OutOfRange { .. }
            ));
        }
        assert!(matches!(
            err(RealAttack::Scale { factor: f32::NAN }),
            E::NotFinite { .. }
        ));
        for keep in [0.0, -0.1, 1.01] {
            assert!(matches!(
                err(RealAttack::Crop { keep }),
                E::OutOfRange { .. }
            ));
        }
        assert!(matches!(
            err(RealAttack::Crop { keep: f32::NAN }),
            E::NotFinite { .. }
        ));
        for kernel in [0, 2, 4, MAX_BLUR_KERNEL + 2] {
            assert!(matches!(
                err(RealAttack::Blur { sigma: 1.0, kernel }),
                E::BadKernel { .. }
            ));
        }
        assert!(matches!(
            err(RealAttack::Blur {
                sigma: 0.0,
                kernel: 3
            }),
            E::OutOfRange { .. }
        ));
        assert!(matches!(
            err(RealAttack::Noise {
                sigma: -0.1,
                seed: 0
            }),
            E::OutOfRange { .. }
        ));
        assert!(matches!(
            err(RealAttack::Noise {
                sigma: f32::NAN,
                seed: 0
            }),
            E::NotFinite { .. }
        ));
        assert!(matches!(
            err(RealAttack::Brightness { factor: -0.5 }),
            E::OutOfRange { .. }
        ));
        assert!(matches!(
            err(RealAttack::Contrast { factor: f32::NAN }),
            E::NotFinite { .. }
        ));
        // Size-dependent failures.
        assert!(matches!(
            err(RealAttack::Scale { factor: 0.1 }),
            E::TooSmall {
                new_width: 0,
                new_height: 0,
                ..
            }
        ));
        assert!(matches!(
            err(RealAttack::Crop { keep: 0.01 }),
            E::TooSmall { .. }
        ));
        assert!(matches!(
            err(RealAttack::Scale { factor: 1e6 }),
            E::TooLarge { .. }
        ));
        assert!(matches!(
            RealAttack::Jpeg { quality: 50 }.apply(&RgbImage::new(0, 4)),
            Err(E::EmptyImage { .. })
        ));
        // A bad step fails the chain before anything runs, and says which step.
        let chain = RealAttack::Chain(vec![
            RealAttack::Jpeg { quality: 50 },
            RealAttack::Crop { keep: 2.0 },
        ]);
        match err(chain) {
            E::Chain { index: 1, source } => {
                assert!(matches!(*source, E::OutOfRange { param: "keep", .. }))
            }
            e => panic!("unexpected {e:?}"),
        }
        // Messages are readable.
        let msg = err(RealAttack::Crop { keep: 2.0 }).to_string();
        assert_eq!(msg, "crop: keep must be in (0, 1], got 2");
    }

    #[test]
    fn serde_round_trip() {
        let mut all: Vec<RealAttack> = paper_protocol(42).into_iter().map(|(_, a)| a).collect();
        all.extend([
            RealAttack::Brightness { factor: 1.5 },
            RealAttack::Contrast { factor: 0.5 },
            RealAttack::Chain(vec![]),
        ]);
        for a in &all {
            let json = serde_json::to_string(a).unwrap();
            let back: RealAttack = serde_json::from_str(&json).unwrap();
            assert_eq!(&back, a, "{json}");
        }
        let json = serde_json::to_value(RealAttack::Jpeg { quality: 50 }).unwrap();
        assert_eq!(
            json,
            serde_json::json!({"type": "jpeg", "params": {"quality": 50}})
        );
        let chain: RealAttack = serde_json::from_str(
            r#"{"type":"chain","params":[{"type":"noise","params":{"sigma":0.1,"seed":7}},
                {"type":"crop","params":{"keep":0.4}}]}"#,
        )
        .unwrap();
        assert_eq!(
            chain,
            RealAttack::Chain(vec![
                RealAttack::Noise {
                    sigma: 0.1,
                    seed: 7
                },
                RealAttack::Crop { keep: 0.4 }
            ])
        );
        assert!(serde_json::from_str::<RealAttack>(r#"{"type":"sharpen","params":{}}"#).is_err());
    }

    #[test]
    fn paper_protocol_runs() {
        let p = paper_protocol(5);
        let names: Vec<&str> = p.iter().map(|(n, _)| *n).collect();
        assert_eq!(
            names,
            [
                "noise", "rotation", "scaling", "blur", "crop", "jpeg", "combined"
            ]
        );
        let img = textured(80, 60);
        for (name, attack) in &p {
            let out = attack.apply(&img).unwrap();
            let expected = match *name {
                "scaling" => (69, 51),           // √0.75 · (80, 60) = (69.3, 51.96)
                "crop" | "combined" => (50, 37), // √0.4 · (80, 60) = (50.6, 37.9)
                _ => (80, 60),
            };
            assert_eq!(out.dimensions(), expected, "{name}");
        }
        // Noise σ = 0.1 really perturbs by ~2.55 levels.
        let noisy = p[0].1.apply(&img).unwrap();
        assert!(psnr(&img, &noisy) > 35.0 && psnr(&img, &noisy) < 42.0);
        assert_eq!(
            p[6].1,
            RealAttack::Chain(vec![p[0].1.clone(), p[4].1.clone(), p[5].1.clone()])
        );
    }
}
