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
use crate::decoder::projection::ViewProjection;
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
}

impl Default for ProjectionConfig {
    fn default() -> Self {
        Self {
            rank: 0,
            views: 96,
            max_angle_deg: 30.0,
            zoom: 0.25,
            seed: 0x5649_4557,
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

/// Fits the view projection of `original` over `cameras` (see [`calibration_cameras`]):
/// every view rendered to 8 bits and decoded to pooled features by `model`'s decoder.
pub fn fit_projection(
    original: &Gaussians,
    cameras: &[Camera],
    model: &WatermarkModel,
    opts: &RenderOptions,
    rank: usize,
) -> Result<ViewProjection, EmbedError> {
    let features = original_features(original, cameras, model, opts)?;
    ViewProjection::fit(&features, rank, model.bits())
        .map_err(|e| EmbedError::Invalid(e.to_string()))
}

/// `model`'s pooled features of `original` through each camera, rendered to 8 bits as a dispute
/// decodes them.
fn original_features(
    original: &Gaussians,
    cameras: &[Camera],
    model: &WatermarkModel,
    opts: &RenderOptions,
) -> Result<Vec<Vec<f32>>, render::RenderError> {
    let device = burn::tensor::Device::flex();
    let mut features = Vec::with_capacity(cameras.len());
    for c in cameras {
        let r = render::render(original, c, opts)?;
        let img = render::to_rgb8(r.width, r.height, &r.image);
        features.extend(model.features(rgb8_tensor(&img, &device)));
    }
    Ok(features)
}

#[cfg(test)]
mod tests {
    use super::*;
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
        let p = fit_projection(&g, &cams, &model, &opts, 32).unwrap();
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
}

/// How much of the unmarked asset's view-to-view logit spread on unseen views the projection
/// removes (docs/RESULTS.md, "view projection"): `cargo test --release -- --ignored
/// projection_spread --nocapture` with ../shared/data.
#[cfg(test)]
mod measure {
    use super::*;
    use crate::verify::bench::{QualityOptions, views};

    #[test]
    #[ignore = "a measurement on ../shared/data (about a minute)"]
    fn projection_spread() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
        let path = dir.join("donut/fused.ply");
        if !path.exists() {
            eprintln!("SKIP: {} is missing", path.display());
            return;
        }
        let g = crate::scene::read_scene(&path, &crate::scene::Limits::default()).unwrap();
        let opts = QualityOptions {
            size: 256,
            ..QualityOptions::full(dir.clone())
        };
        let scene = crate::verify::bench::shared_scenes().remove(0);
        let (train, unseen) = views(&scene, &g, &opts).unwrap();
        let device = burn::tensor::Device::flex();
        let model = WatermarkModel::shipped(32, &device).unwrap();
        let ro = RenderOptions::default();
        let feats = |cams: &[Camera]| original_features(&g, cams, &model, &ro).unwrap();
        let cal = feats(&calibration_cameras(
            &g,
            &train,
            &ProjectionConfig::default(),
        ));
        let test = feats(&unseen);
        let trainf = feats(&train);
        let spread = |m: &WatermarkModel, f: &[Vec<f32>]| -> f64 {
            // Logits from features: the head (and whitening) on a batch of pooled features.
            let logits: Vec<Vec<f32>> = f
                .iter()
                .map(|row| {
                    let x = burn::tensor::Tensor::<2>::from_data(
                        burn::tensor::TensorData::new(row.clone(), [1, row.len()]),
                        &device,
                    );
                    let x = match &m.projection {
                        Some(p) => p.apply(x),
                        None => x,
                    };
                    let z = m.decoder.head(x);
                    let z = match &m.sidecar.whitening {
                        Some(w) => w.apply(z),
                        None => z,
                    };
                    z.try_into_vec_as::<f32>().unwrap()
                })
                .collect();
            let l = logits[0].len();
            let n = logits.len() as f64;
            let mut var = 0.0;
            for i in 0..l {
                let mean: f64 = logits.iter().map(|z| f64::from(z[i])).sum::<f64>() / n;
                var += logits
                    .iter()
                    .map(|z| (f64::from(z[i]) - mean).powi(2))
                    .sum::<f64>()
                    / n;
            }
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
}
