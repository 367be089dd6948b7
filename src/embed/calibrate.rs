//! Calibration of the per-asset view projection ([`crate::decoder::projection`], eq.
//! `viewproj`): the unmarked asset is rendered through many cameras around its training
//! cameras, every render decoded to pooled features as a dispute would (8-bit), and the top
//! principal directions of those features kept.
//!
//! The calibration cameras are the training cameras and copies of them turned about the scene's
//! centre by a random rotation of up to [`ProjectionConfig::max_angle_deg`] and zoomed by up to
//! ± [`ProjectionConfig::zoom`] (log scale) — views a dispute may bring that no training camera
//! shows. They come from a fixed seed, so an embedding stays reproducible.

use glam::{Mat3, Quat, Vec3};
use serde::{Deserialize, Serialize};

use crate::attack::diff::EotRng;
use crate::decoder::WatermarkModel;
use crate::decoder::artifact::rgb8_tensor;
use crate::decoder::dwt::ll_size;
use crate::decoder::model::decoder_input;
use crate::decoder::projection::ViewProjection;
use crate::render::gpu::Rasterizer;
use crate::render::{self, RenderOptions};
use crate::scene::bounds::robust_bounds;
use crate::scene::{Camera, Gaussians};

use super::pipeline::EmbedError;

/// How the view projection is calibrated; `rank` 0 turns it off.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProjectionConfig {
    /// Principal directions removed (k of eq. `viewproj`); at most F − L.
    pub rank: usize,
    /// Calibration cameras besides the training cameras.
    pub views: usize,
    /// Largest turn of a calibration camera about the scene's centre, degrees.
    pub max_angle_deg: f32,
    /// Largest zoom of a calibration camera, as |ln(focal factor)|.
    pub zoom: f32,
    pub seed: u64,
    /// Read the bits through the asset's matched head (eq. `matchedhead`) instead of the
    /// decoder's own head; `rank` is then ignored.
    pub matched: bool,
    /// λ of eq. `matchedhead`: the noise floor added to N, as a share of its mean variance.
    pub lambda: f64,
    /// Nuisance samples added to N of eq. `matchedhead` ([`nuisance_features`]): calibration
    /// views of the original or of a perturbed copy of it (parameter noise, Gaussians removed
    /// or cloned), through a random image attack — so the head reads along directions that
    /// neither the views nor the attacks move.
    pub nuisance: usize,
}

impl ProjectionConfig {
    /// Whether the embedding fits a projection (or a matched head) at all.
    pub fn is_on(&self) -> bool {
        self.rank > 0 || self.matched
    }
}

impl Default for ProjectionConfig {
    fn default() -> Self {
        Self {
            rank: 0,
            views: 96,
            max_angle_deg: 30.0,
            zoom: 0.25,
            seed: 0x5649_4557,
            matched: true,
            lambda: 0.1,
            nuisance: 200,
        }
    }
}

/// The training cameras followed by `cfg.views` turned and zoomed copies of them (round robin).
pub fn calibration_cameras(
    g: &Gaussians,
    cameras: &[Camera],
    cfg: &ProjectionConfig,
) -> Vec<Camera> {
    let pivot = robust_bounds(g, 0.02).map_or(Vec3::ZERO, |b| {
        (Vec3::from(b.min) + Vec3::from(b.max)) * 0.5
    });
    let mut rng = EotRng::new(cfg.seed);
    let mut out = cameras.to_vec();
    if cameras.is_empty() {
        return out;
    }
    for k in 0..cfg.views {
        let c = &cameras[k % cameras.len()];
        let axis = loop {
            let (a, b) = rng.normal_pair();
            let (z, _) = rng.normal_pair();
            let v = Vec3::new(a as f32, b as f32, z as f32);
            if v.length() > 1e-3 {
                break v.normalize();
            }
        };
        let angle = (cfg.max_angle_deg.to_radians()) * rng.range(-1.0, 1.0) as f32;
        let turn = Mat3::from_quat(Quat::from_axis_angle(axis, angle));
        let zoom = (f64::from(cfg.zoom) * rng.range(-1.0, 1.0)).exp() as f32;
        let cam_to_world = turn * c.rotation_mat().transpose();
        let center = pivot + turn * (c.center() - pivot);
        out.push(Camera::from_pose(
            format!("{}_calib{k:03}", c.name),
            c.width,
            c.height,
            c.fx * zoom,
            c.fy * zoom,
            c.cx,
            c.cy,
            cam_to_world,
            center,
        ));
    }
    out
}

/// Fits the view projection of `original` (or, with `cfg.matched`, its matched head) for the
/// training cameras `train`: every calibration view ([`calibration_cameras`]) rendered to 8
/// bits and decoded to pooled features by `model`'s decoder; the matched head's gain over the
/// training views ([`decoder_gain`]).
pub fn fit_projection(
    original: &Gaussians,
    train: &[Camera],
    model: &WatermarkModel,
    opts: &RenderOptions,
    cfg: &ProjectionConfig,
    rasterizer: &Rasterizer,
) -> Result<ViewProjection, EmbedError> {
    let cams = calibration_cameras(original, train, cfg);
    // Each view of the original is rendered once: its features, the gain over the training
    // views (the first `train.len()` calibration cameras) and the nuisance samples of the
    // original all read the same 8-bit renders.
    let scene = rasterizer
        .prepare(original, opts)
        .map_err(render::RenderError::from)?;
    let renders = cams
        .iter()
        .map(|c| rgb8(scene.render_image(c)?))
        .collect::<Result<Vec<_>, render::RenderError>>()?;
    let features = features_of(model, &renders);
    let fitted = if cfg.matched {
        let gain = gain_of_renders(&renders[..train.len()], model);
        let nuisance = nuisance_samples(
            original,
            &cams,
            Some(&renders),
            model,
            opts,
            cfg,
            rasterizer,
        )?;
        ViewProjection::fit_matched(
            &features,
            &nuisance,
            &gain,
            model.bits(),
            cfg.lambda,
            cfg.seed,
        )
    } else {
        ViewProjection::fit(&features, cfg.rank, model.bits())
    };
    fitted.map_err(|e| EmbedError::Invalid(e.to_string()))
}

/// `g` through `camera` by `rasterizer`, rounded to 8 bits as a saved image would be.
fn render_rgb8(
    g: &Gaussians,
    camera: &Camera,
    opts: &RenderOptions,
    rasterizer: &Rasterizer,
) -> Result<image::RgbImage, render::RenderError> {
    rgb8(rasterizer.render_image(g, camera, opts)?)
}

/// A render (width, height, linear RGB) rounded to 8 bits as a saved image would be.
fn rgb8((w, h, image): (u32, u32, Vec<[f32; 3]>)) -> Result<image::RgbImage, render::RenderError> {
    Ok(render::to_rgb8(w, h, &image))
}

/// `model`'s pooled features of each image, in order.
fn features_of(model: &WatermarkModel, images: &[image::RgbImage]) -> Vec<Vec<f32>> {
    let device = model.device();
    images
        .iter()
        .flat_map(|img| model.features(rgb8_tensor(img, &device)))
        .collect()
}

/// G of eq. `matchedhead`: Σ over the pixels of the original's renders through `cameras` of
/// J_pᵀ·J_p, J_p the Jacobian of `model`'s pooled features at pixel p (F × 3), averaged over
/// the views; F × F row-major.
///
/// The decoder reads the image only through its centred LL band u = D·x ([`decoder_input`]:
/// the mean of each 2^L × 2^L block, edge-padded, times 2, minus 1), and D's rows have disjoint
/// supports, so D·Dᵀ is diagonal and G = Σ_q d_q·J_qᵀ·J_q over the band's entries q (J_q the
/// Jacobian with respect to u_q, d_q = Σ_p D_qp² — 4/4^L inside the image, more where the edge
/// padding repeats pixels). The Jacobian is taken on the band, 4^L times smaller than the image:
/// one backward pass per feature, batched.
pub fn decoder_gain(
    original: &Gaussians,
    cameras: &[Camera],
    model: &WatermarkModel,
    opts: &RenderOptions,
) -> Result<Vec<f64>, render::RenderError> {
    let renders = cameras
        .iter()
        .map(|c| render_rgb8(original, c, opts, &Rasterizer::Cpu))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(gain_of_renders(&renders, model))
}

/// [`decoder_gain`] over the 8-bit renders of the views.
fn gain_of_renders(renders: &[image::RgbImage], model: &WatermarkModel) -> Vec<f64> {
    use burn::tensor::{Device, Tensor, TensorData};
    let device = model.device().autodiff();
    let f = model.decoder.feature_count();
    let levels = model.decoder.dwt_levels();
    let mut gain = vec![0.0f64; f * f];
    let views = renders.len().max(1) as f64;
    for img in renders {
        let band = decoder_input(rgb8_tensor(img, &device), levels);
        let [_, ch, h, w] = band.dims();
        let n = ch * h * w;
        let root_d = band_weights(img.height() as usize, img.width() as usize, levels);
        // Row j: ∂f_j/∂u·√d, the whole band — in closed form where the decoder has one.
        let values: Vec<f32> = band.clone().try_into_vec_as::<f32>().unwrap_or_default();
        let jac = model
            .decoder
            .band_jacobian(&values, h, w)
            .unwrap_or_else(|| jacobian_by_backward(model, band, f, &device));
        // G += R·Rᵀ / views, R the F × n rows times √d: one f32 matrix product (gemm), summed
        // into G in f64.
        let rows: Vec<f32> = jac
            .chunks_exact(n)
            .flat_map(|row| {
                row.iter()
                    .enumerate()
                    .map(|(k, &v)| (v * root_d[k % (h * w)]) as f32)
            })
            .collect();
        let r = Tensor::<2>::from_data(TensorData::new(rows, [f, n]), &Device::flex());
        let rrt: Vec<f32> = r
            .clone()
            .matmul(r.transpose())
            .try_into_vec_as::<f32>()
            .expect("a product on the host");
        // (Symmetric up to the product's rounding: kept exactly symmetric.)
        for i in 0..f {
            for j in 0..f {
                let v = 0.5 * (f64::from(rrt[i * f + j]) + f64::from(rrt[j * f + i]));
                gain[i * f + j] += v / views;
            }
        }
    }
    gain
}

/// ∂(pooled features)/∂band of one band `[1, C, h, w]` by back-propagation, one feature per
/// batch row: `f` rows of `C·h·w`, row-major.
fn jacobian_by_backward(
    model: &WatermarkModel,
    band: burn::tensor::Tensor<4>,
    f: usize,
    device: &burn::tensor::Device,
) -> Vec<f64> {
    use burn::tensor::{Tensor, TensorData};
    let [_, ch, h, w] = band.dims();
    let n = ch * h * w;
    let mut jac = Vec::with_capacity(f * n);
    // Batches of the decoder's [B, F, h, w] features of at most 16 M values.
    let chunk = (16_000_000 / (f * h * w).max(1)).clamp(1, f);
    let mut j0 = 0;
    while j0 < f {
        let b = chunk.min(f - j0);
        let x = band.clone().repeat_dim(0, b).require_grad();
        let p = model.decoder.pooled_band(x.clone()); // [b, F]
        // Σ_i p[i, j0 + i]: the batch row i back-propagates feature j0 + i alone.
        let mut sel = vec![0.0f32; b * f];
        for i in 0..b {
            sel[i * f + j0 + i] = 1.0;
        }
        let sel = Tensor::<2>::from_data(TensorData::new(sel, [b, f]), device);
        let grads = (p * sel).sum().backward();
        let d: Vec<f32> = x
            .grad(&grads)
            .and_then(|t| t.try_into_vec_as::<f32>().ok())
            .unwrap_or_else(|| vec![0.0; b * n]);
        jac.extend(d.iter().map(|&v| f64::from(v)));
        j0 += b;
    }
    jac
}

/// √d_q of [`decoder_gain`] for each entry of the LL band (row-major, `ll_size`) of a
/// `height × width` image: d_q = Σ_p D_qp² with D_qp = 2·m_p / 4^L, m_p the number of times
/// pixel p fills the block of q after edge padding.
fn band_weights(height: usize, width: usize, levels: usize) -> Vec<f64> {
    let s = 1usize << levels;
    let [bh, bw] = ll_size(height, width, levels);
    // Σ over a block's rows (columns) of the squared multiplicities of the real rows.
    let sums = |len: usize, blocks: usize| -> Vec<f64> {
        (0..blocks)
            .map(|i| {
                let mut m = vec![0usize; len];
                for r in i * s..(i + 1) * s {
                    m[r.min(len - 1)] += 1;
                }
                m.iter().map(|&k| (k * k) as f64).sum()
            })
            .collect()
    };
    let (rows, cols) = (sums(height, bh), sums(width, bw));
    let c = 4.0 / (s as f64).powi(4);
    let mut out = Vec::with_capacity(bh * bw);
    for r in &rows {
        for q in &cols {
            out.push((c * r * q).sqrt());
        }
    }
    out
}

/// `cfg.nuisance` samples of what a dispute may hold besides a clean view, as `model`'s pooled
/// features: each a random camera of `cams` through the original or, half of the time, one of
/// four perturbed copies of it (parameter noise σ 0.1 twice, 20 % of the Gaussians removed,
/// 20 % cloned), rendered to 8 bits and, 4 times in 5, through a random real attack (JPEG 40–90,
/// pixel noise σ 0.1, blur σ 0.5–1, downscale 0.6–0.95, rotation 5–35°, crop 30–80 %, or noise +
/// crop + JPEG). Drawn from `cfg.seed`, so an embedding stays reproducible.
pub fn nuisance_features(
    original: &Gaussians,
    cams: &[Camera],
    model: &WatermarkModel,
    opts: &RenderOptions,
    cfg: &ProjectionConfig,
) -> Result<Vec<Vec<f32>>, EmbedError> {
    nuisance_samples(original, cams, None, model, opts, cfg, &Rasterizer::Cpu)
}

/// [`nuisance_features`], reading the original's views from `renders` (its 8-bit renders
/// through `cams`, in order) when given instead of rendering them again.
fn nuisance_samples(
    original: &Gaussians,
    cams: &[Camera],
    renders: Option<&[image::RgbImage]>,
    model: &WatermarkModel,
    opts: &RenderOptions,
    cfg: &ProjectionConfig,
    rasterizer: &Rasterizer,
) -> Result<Vec<Vec<f32>>, EmbedError> {
    use crate::attack::model::ModelAttack;
    use crate::attack::real::RealAttack;
    if cfg.nuisance == 0 || cams.is_empty() {
        return Ok(Vec::new());
    }
    let mut rng = EotRng::new(cfg.seed ^ 0x4e55_4953_414e_4345);
    let invalid = |e: String| EmbedError::Invalid(e);
    let mut copies = Vec::with_capacity(4);
    for k in 0..4u64 {
        let seed = rng.next_u64();
        let a = match k {
            0 | 1 => ModelAttack::Noise {
                sigma: 0.1,
                position_scale: 1.0,
                seed,
            },
            2 => ModelAttack::Remove {
                fraction: 0.2,
                seed,
            },
            _ => ModelAttack::Clone {
                fraction: 0.2,
                seed,
            },
        };
        copies.push(a.apply(original).map_err(|e| invalid(e.to_string()))?);
    }
    let device = model.device();
    let mut out = Vec::with_capacity(cfg.nuisance);
    for _ in 0..cfg.nuisance {
        let k = rng.range_int(0, cams.len() as u64 - 1) as usize;
        let img = if rng.uniform() < 0.5 {
            match renders {
                Some(r) => r[k].clone(),
                None => render_rgb8(original, &cams[k], opts, rasterizer)?,
            }
        } else {
            render_rgb8(
                &copies[rng.range_int(0, 3) as usize],
                &cams[k],
                opts,
                rasterizer,
            )?
        };
        let noise = RealAttack::Noise {
            sigma: 0.1,
            seed: rng.next_u64(),
        };
        let attack = match rng.range_int(0, 9) {
            0 | 1 => None,
            2 => Some(RealAttack::Jpeg {
                quality: rng.range_int(40, 90) as u8,
            }),
            3 => Some(noise),
            4 => Some(RealAttack::Blur {
                sigma: rng.range(0.5, 1.0) as f32,
                kernel: 3,
            }),
            5 => Some(RealAttack::Scale {
                factor: rng.range(0.6, 0.95) as f32,
            }),
            6 => {
                let deg = rng.range(5.0, 35.0) as f32;
                Some(RealAttack::Rotate {
                    degrees: if rng.uniform() < 0.5 { deg } else { -deg },
                })
            }
            7 => Some(RealAttack::Crop {
                keep: rng.range(0.3, 0.8) as f32,
            }),
            _ => Some(RealAttack::Chain(vec![
                noise,
                RealAttack::Crop {
                    keep: rng.range(0.3, 0.8) as f32,
                },
                RealAttack::Jpeg {
                    quality: rng.range_int(40, 90) as u8,
                },
            ])),
        };
        let img = match attack {
            Some(a) => a.apply(&img).map_err(|e| invalid(e.to_string()))?,
            None => img,
        };
        out.extend(model.features(rgb8_tensor(&img, &device)));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `model`'s pooled features of `g` through each camera, rendered to 8 bits.
    pub(super) fn original_features(
        g: &Gaussians,
        cams: &[Camera],
        model: &WatermarkModel,
        opts: &RenderOptions,
    ) -> Result<Vec<Vec<f32>>, render::RenderError> {
        let renders = cams
            .iter()
            .map(|c| render_rgb8(g, c, opts, &Rasterizer::Cpu))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(features_of(model, &renders))
    }
    use crate::scene::orbit::{OrbitOptions, orbit_cameras};
    use crate::scene::synthetic::object_scene;

    #[test]
    fn calibration_cameras_keep_the_training_cameras_and_look_at_the_scene() {
        let g = object_scene(400, 0, 3);
        let train = orbit_cameras(
            &g,
            &OrbitOptions {
                count: 4,
                width: 32,
                height: 32,
                ..OrbitOptions::default()
            },
        )
        .unwrap();
        let cfg = ProjectionConfig {
            views: 12,
            ..ProjectionConfig::default()
        };
        let cams = calibration_cameras(&g, &train, &cfg);
        assert_eq!(cams.len(), 16);
        assert_eq!(&cams[..4], &train[..]);
        assert_eq!(cams, calibration_cameras(&g, &train, &cfg), "reproducible");
        let opts = RenderOptions::default();
        for c in &cams[4..] {
            c.validate().unwrap();
            let r = render::render(&g, c, &opts).unwrap();
            let lit = r
                .image
                .iter()
                .filter(|p| p.iter().sum::<f32>() > 0.05)
                .count();
            assert!(lit > 20, "{} sees {lit} lit pixels", c.name);
        }
        assert_ne!(cams[4], cams[0]);
    }

    /// G straight from its definition: the Jacobian of the pooled features with respect to
    /// every pixel of the 8-bit render, one backward pass per feature.
    fn gain_by_pixels(
        g: &Gaussians,
        cameras: &[Camera],
        model: &WatermarkModel,
        opts: &RenderOptions,
    ) -> Vec<f64> {
        use burn::tensor::{Tensor, TensorData};
        let device = burn::tensor::Device::flex().autodiff();
        let f = model.decoder.feature_count();
        let mut gain = vec![0.0f64; f * f];
        for c in cameras {
            let r = render::render(g, c, opts).unwrap();
            let img = render::to_rgb8(r.width, r.height, &r.image);
            let x0 = rgb8_tensor(&img, &device);
            let rows: Vec<Vec<f32>> = (0..f)
                .map(|j| {
                    let x = x0.clone().require_grad();
                    let mut sel = vec![0.0f32; f];
                    sel[j] = 1.0;
                    let sel = Tensor::<2>::from_data(TensorData::new(sel, [1, f]), &device);
                    let grads = (model.decoder.pooled(x.clone()) * sel).sum().backward();
                    x.grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap()
                })
                .collect();
            for i in 0..f {
                for j in 0..f {
                    gain[i * f + j] += rows[i]
                        .iter()
                        .zip(&rows[j])
                        .map(|(&a, &b)| f64::from(a) * f64::from(b))
                        .sum::<f64>()
                        / cameras.len() as f64;
                }
            }
        }
        gain
    }

    #[test]
    fn the_gain_taken_on_the_band_equals_the_gain_over_the_pixels() {
        let g = object_scene(400, 0, 3);
        let device = burn::tensor::Device::flex();
        let shipped = WatermarkModel::shipped(32, &device).unwrap();
        // A convolutional decoder too: its Jacobian comes from back-propagation, the
        // colour-Fourier one's in closed form.
        let mut conv = shipped.clone();
        conv.decoder = crate::decoder::model::HiddenDecoderConfig::new(32)
            .with_channels(4)
            .with_depth(1)
            .with_norm(crate::decoder::model::Norm::Group)
            .init(&device);
        let opts = RenderOptions::default();
        // 30 × 22 is not a multiple of the band's 4 × 4 blocks: the edge padding counts too.
        for (model, width, height) in [(&shipped, 32, 24), (&shipped, 30, 22), (&conv, 30, 22)] {
            let cams = orbit_cameras(
                &g,
                &OrbitOptions {
                    count: 2,
                    width,
                    height,
                    ..OrbitOptions::default()
                },
            )
            .unwrap();
            let fast = decoder_gain(&g, &cams, model, &opts).unwrap();
            let slow = gain_by_pixels(&g, &cams, model, &opts);
            let scale = slow.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(scale > 0.0);
            let worst = fast
                .iter()
                .zip(&slow)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                worst < 1e-4 * scale,
                "{width}×{height}: worst difference {worst:e} of {scale:e}"
            );
        }
    }

    #[test]
    fn the_projected_model_decodes_the_views_of_the_original_alike() {
        let g = object_scene(3000, 0, 5);
        let train = orbit_cameras(
            &g,
            &OrbitOptions {
                count: 8,
                width: 64,
                height: 64,
                ..OrbitOptions::default()
            },
        )
        .unwrap();
        let cfg = ProjectionConfig {
            views: 40,
            ..ProjectionConfig::default()
        };
        let cams = calibration_cameras(&g, &train, &cfg);
        let device = burn::tensor::Device::flex();
        let model = WatermarkModel::shipped(32, &device).unwrap();
        let opts = RenderOptions::default();
        let p = fit_projection(
            &g,
            &train,
            &model,
            &opts,
            &ProjectionConfig {
                rank: 32,
                matched: false,
                ..cfg
            },
            &Rasterizer::Cpu,
        )
        .unwrap();
        assert_eq!(
            (p.rank(), p.features()),
            (32, model.decoder.feature_count())
        );
        let projected = model.clone().with_projection(p);
        // The spread of each bit's logit over the calibration views, through the whole model.
        let spread = |m: &WatermarkModel| -> f64 {
            let z: Vec<Vec<f32>> = cams
                .iter()
                .flat_map(|c| {
                    let r = render::render(&g, c, &opts).unwrap();
                    let img = render::to_rgb8(r.width, r.height, &r.image);
                    m.logits(rgb8_tensor(&img, &device))
                })
                .collect();
            let n = z.len() as f64;
            (0..z[0].len())
                .map(|i| {
                    let mean = z.iter().map(|v| f64::from(v[i])).sum::<f64>() / n;
                    z.iter()
                        .map(|v| (f64::from(v[i]) - mean).powi(2))
                        .sum::<f64>()
                        / n
                })
                .sum::<f64>()
                .sqrt()
        };
        let (plain, proj) = (spread(&model), spread(&projected));
        assert!(proj < 0.5 * plain, "spread {plain} → {proj}");
    }

    #[test]
    fn the_matched_head_reads_the_original_in_units_of_its_own_noise_and_is_reproducible() {
        let g = object_scene(3000, 0, 5);
        let train = orbit_cameras(
            &g,
            &OrbitOptions {
                count: 6,
                width: 64,
                height: 64,
                ..OrbitOptions::default()
            },
        )
        .unwrap();
        let cfg = ProjectionConfig {
            views: 24,
            nuisance: 24,
            ..ProjectionConfig::default()
        };
        assert!(cfg.matched, "the default reads through a matched head");
        let device = burn::tensor::Device::flex();
        let model = WatermarkModel::shipped(32, &device).unwrap();
        let opts = RenderOptions::default();
        let p = fit_projection(&g, &train, &model, &opts, &cfg, &Rasterizer::Cpu).unwrap();
        assert_eq!(
            (p.head_bits(), p.rank(), p.features()),
            (32, 0, model.decoder.feature_count())
        );
        assert_eq!(
            p,
            fit_projection(&g, &train, &model, &opts, &cfg, &Rasterizer::Cpu).unwrap()
        );
        let nuisance = nuisance_features(&g, &train, &model, &opts, &cfg).unwrap();
        assert_eq!(nuisance.len(), 24);
        assert_ne!(nuisance[0], nuisance[1]);
        // The original's clean calibration views read as noise of about unit variance per bit
        // around 0 (N holds them, with the nuisance samples and the floor λ).
        let matched = model.clone().with_projection(p.clone());
        let z: Vec<Vec<f32>> = calibration_cameras(&g, &train, &cfg)
            .iter()
            .flat_map(|c| {
                let r = render::render(&g, c, &opts).unwrap();
                let img = render::to_rgb8(r.width, r.height, &r.image);
                matched.logits(rgb8_tensor(&img, &device))
            })
            .collect();
        let n = z.len() as f64;
        let mean_sq = z
            .iter()
            .flatten()
            .map(|&v| f64::from(v).powi(2))
            .sum::<f64>()
            / (n * 32.0);
        assert!(mean_sq > 0.01 && mean_sq < 1.5, "E[z²] {mean_sq}");
        // Another seed draws another rotation of the same directions.
        let other = fit_projection(
            &g,
            &train,
            &model,
            &opts,
            &ProjectionConfig { seed: 1, ..cfg },
            &Rasterizer::Cpu,
        )
        .unwrap();
        assert_ne!(other.head, p.head);
    }
}

/// Measurements on ../shared/data (ignored tests; docs/RESULTS.md):
/// - `projection_spread`: how much of the unmarked asset's view-to-view logit spread on unseen
///   views the rank-k projection removes;
/// - `head_gain`: whether a head chosen per asset reads more signal per unit of image change
///   than the shipped random head — for each bit direction a (pooled-feature space), the gain
///   aᵀGa ([`decoder_gain`] over the training views) over the asset's own view noise aᵀNa (N the
///   features' covariance over the calibration, training and unseen views).
///
/// `cargo test --release --lib -- --ignored projection_spread head_gain --nocapture`.
#[cfg(test)]
mod measure {
    use super::tests::original_features;
    use super::*;
    use crate::verify::bench::{QualityOptions, views};
    use burn::tensor::{Tensor, TensorData};

    /// Donut with the bench's 256² training and unseen cameras and the shipped 32-bit model;
    /// `None` (after saying so) without ../shared/data.
    fn donut() -> Option<(Gaussians, Vec<Camera>, Vec<Camera>, WatermarkModel)> {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
        let path = dir.join("donut/fused.ply");
        if !path.exists() {
            eprintln!("SKIP: {} is missing", path.display());
            return None;
        }
        let g = crate::scene::read_scene(&path, &crate::scene::Limits::default()).unwrap();
        let opts = QualityOptions {
            size: 256,
            ..QualityOptions::full(dir.clone())
        };
        let scene = crate::verify::bench::shared_scenes().remove(0);
        let (train, unseen) = views(&scene, &g, &opts, 32).unwrap();
        let model = WatermarkModel::shipped(32, &burn::tensor::Device::flex()).unwrap();
        Some((g, train, unseen, model))
    }

    /// `m`'s logits of pooled feature rows (`[n, F]` row-major).
    fn logits_of(m: &WatermarkModel, rows: Vec<f32>, n: usize) -> Vec<f32> {
        let f = m.decoder.feature_count();
        let x =
            Tensor::<2>::from_data(TensorData::new(rows, [n, f]), &burn::tensor::Device::flex());
        m.forward_pooled(x).try_into_vec_as::<f32>().unwrap()
    }

    fn cov(rows: &[Vec<f32>]) -> Vec<f64> {
        let f = rows[0].len();
        let n = rows.len() as f64;
        let mut mean = vec![0.0f64; f];
        for r in rows {
            for (m, &x) in mean.iter_mut().zip(r) {
                *m += f64::from(x) / n;
            }
        }
        let mut c = vec![0.0f64; f * f];
        for r in rows {
            for i in 0..f {
                for j in 0..f {
                    c[i * f + j] += (f64::from(r[i]) - mean[i]) * (f64::from(r[j]) - mean[j]) / n;
                }
            }
        }
        c
    }

    fn quad(m: &[f64], a: &[f64]) -> f64 {
        let f = a.len();
        (0..f)
            .map(|i| a[i] * (0..f).map(|j| m[i * f + j] * a[j]).sum::<f64>())
            .sum()
    }

    #[test]
    #[ignore = "a measurement on ../shared/data (about a minute)"]
    fn projection_spread() {
        let Some((g, train, unseen, model)) = donut() else {
            return;
        };
        let ro = RenderOptions::default();
        let feats = |cams: &[Camera]| original_features(&g, cams, &model, &ro).unwrap();
        let cal = feats(&calibration_cameras(
            &g,
            &train,
            &ProjectionConfig::default(),
        ));
        let (test, trainf) = (feats(&unseen), feats(&train));
        let spread = |m: &WatermarkModel, f: &[Vec<f32>]| -> f64 {
            let l = m.bits();
            let z = logits_of(m, f.concat(), f.len());
            let n = f.len() as f64;
            let var: f64 = (0..l)
                .map(|i| {
                    let mean = z
                        .iter()
                        .skip(i)
                        .step_by(l)
                        .map(|&v| f64::from(v))
                        .sum::<f64>()
                        / n;
                    z.iter()
                        .skip(i)
                        .step_by(l)
                        .map(|&v| (f64::from(v) - mean).powi(2))
                        .sum::<f64>()
                        / n
                })
                .sum();
            (var / l as f64).sqrt()
        };
        for rank in [0usize, 4, 8, 16, 32, 48, 64, 96] {
            let m = if rank == 0 {
                model.clone()
            } else {
                model
                    .clone()
                    .with_projection(ViewProjection::fit(&cal, rank, 32).unwrap())
            };
            let ex = m.projection.as_ref().map_or(0.0, |p| p.explained);
            eprintln!(
                "rank {rank:3}: explains {:.3} of the calibration variance; logit spread (std) training views {:.3}, unseen views {:.3}",
                ex,
                spread(&m, &trainf),
                spread(&m, &test)
            );
        }
    }

    #[test]
    #[ignore = "a measurement on ../shared/data (a few minutes)"]
    fn head_gain() {
        let Some((g, train, unseen, model)) = donut() else {
            return;
        };
        let ro = RenderOptions::default();
        let f = model.decoder.feature_count();
        let cfg = ProjectionConfig::default();
        let feats = |cams: &[Camera]| original_features(&g, cams, &model, &ro).unwrap();
        let cal = feats(&calibration_cameras(&g, &train, &cfg));
        let noise = [
            ("calibration", cov(&cal)),
            ("training", cov(&feats(&train))),
            ("unseen", cov(&feats(&unseen))),
        ];
        let t = std::time::Instant::now();
        let gm = decoder_gain(&g, &train, &model, &ro).unwrap();
        eprintln!(
            "gain over {} views in {:.1} s",
            train.len(),
            t.elapsed().as_secs_f64()
        );
        // The shipped head's directions: z(e_j) − z(0) through head and whitening.
        let shipped: Vec<Vec<f64>> = {
            let mut eye = vec![0.0f32; f * f];
            for i in 0..f {
                eye[i * f + i] = 1.0;
            }
            let (ze, z0) = (
                logits_of(&model, eye, f),
                logits_of(&model, vec![0.0; f], 1),
            );
            (0..32)
                .map(|k| (0..f).map(|j| f64::from(ze[j * 32 + k] - z0[k])).collect())
                .collect()
        };
        let report = |name: &str, dirs: &[Vec<f64>]| {
            let k = dirs.len() as f64;
            let ratio = |n: &[f64]| dirs.iter().map(|a| quad(&gm, a) / quad(n, a)).sum::<f64>() / k;
            let parts: Vec<String> = noise
                .iter()
                .map(|(name, n)| format!("{name} {:.3e}", ratio(n)))
                .collect();
            eprintln!("{name}: mean gain/noise — {}", parts.join(", "));
        };
        report("shipped head", &shipped);
        for lambda in [1e-3, 1e-2, 3e-2, 1e-1, 1.0] {
            let p = ViewProjection::fit_matched(&cal, &[], &gm, 32, lambda, cfg.seed).unwrap();
            let head = p.head.unwrap();
            let dirs: Vec<Vec<f64>> = head
                .chunks_exact(f)
                .map(|r| r.iter().map(|&x| f64::from(x)).collect())
                .collect();
            report(&format!("matched head, λ {lambda:.0e}"), &dirs);
        }
    }
}
