//! Model-space attacks on a 3D-GS asset (the paper's Table 3): removing or cloning a fraction of
//! the Gaussians and adding noise to their parameters.
//!
//! Conventions (read from the baselines' code, as for the image attacks):
//! - **remove f**: ⌊f·N⌋ Gaussians drawn uniformly without replacement are deleted.
//! - **clone f**: ⌊f·N⌋ Gaussians drawn uniformly without replacement are duplicated with
//!   identical parameters and appended (a clone doubles its Gaussian's coverage where it is
//!   seen — that is the attack).
//! - **noise σ**: every stored parameter (means, log-scales, quaternion components, opacity
//!   logits, SH coefficients) gets independent normal noise of standard deviation σ², the same
//!   "σ = 0.1 means std 0.01" reading as the image noise; quaternions are renormalised.
//!
//! Parameter noise on the means is in the scene's world units, which are arbitrary: the same
//! std 0.01 moves a Gaussian of lego (the paper's Blender scenes, framed 1.45 units either side
//! of the object) by 0.7 % of the half-frame, and one of a 21-cm donut stored in metres (framed
//! 0.19 units either side by `bench quality`) by 5.4 %.
//! `ModelAttack::Noise { position_scale, .. }` multiplies the means' noise only (log-scales,
//! quaternions, opacity logits and SH coefficients are unit-free), and [`view_position_scale`]
//! picks the factor that gives a scene, seen through its cameras, the displacement in the image
//! that the paper's noise gives lego through its own: the paper's attack carried to any scene's
//! units. Both readings are reported by `verify::eval` (`noise_0.1` in world units, the
//! paper's literal protocol; `noise_0.1_scaled`).

use serde::{Deserialize, Serialize};

use glam::Vec3;

use super::diff::EotRng;
use crate::embed::subset;
use crate::scene::bounds::robust_bounds;
use crate::scene::orbit::OrbitOptions;
use crate::scene::{Camera, Gaussians};

/// One model-space attack.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", content = "params", rename_all = "snake_case")]
pub enum ModelAttack {
    /// Delete a fraction in [0, 1] of the Gaussians.
    Remove { fraction: f32, seed: u64 },
    /// Duplicate a fraction in [0, 1] of the Gaussians.
    Clone { fraction: f32, seed: u64 },
    /// Parameter noise with the papers' σ (std σ²; the means' std σ² · `position_scale`).
    Noise {
        sigma: f32,
        /// Factor of the means' noise (1: the world units of the file; see
        /// [`view_position_scale`]).
        #[serde(default = "unit_scale")]
        position_scale: f32,
        seed: u64,
    },
}

fn unit_scale() -> f32 {
    1.0
}

/// Half the narrower side of the view, at the object's centre and in its world units, of the
/// paper's Blender scenes: every lego training camera sits 4.031 units from the origin, which
/// it looks at, with a horizontal field of view of 0.6911 rad (800 × 800), so
/// 4.031 · tan(0.6911 / 2) = 1.451 (checked against `transforms_train.json` by a test).
pub const PAPER_VIEW_HALF_EXTENT: f32 = 1.451;

/// Half the narrower side of `cam`'s view at the depth of `centre`, in world units (`None`
/// when `centre` is not in front of the camera).
pub fn view_half_extent(cam: &Camera, centre: Vec3) -> Option<f32> {
    let z = cam.to_camera(centre).z;
    let half = (0.5 * cam.width as f32 / cam.fx).min(0.5 * cam.height as f32 / cam.fy);
    (z > 0.0 && half.is_finite() && half > 0.0).then_some(z * half)
}

/// The factor for [`ModelAttack::Noise::position_scale`] that moves `g`'s Gaussians, seen
/// through `cams`, by the share of the frame the paper's parameter noise moves lego's by through
/// its cameras: the median over `cams` of [`view_half_extent`] at the centre of `g`'s robust
/// bounds, over [`PAPER_VIEW_HALF_EXTENT`]. `None` when no camera sees that centre in front of
/// it (or `g` is empty).
pub fn view_position_scale(g: &Gaussians, cams: &[Camera]) -> Option<f32> {
    let b = robust_bounds(g, OrbitOptions::default().quantile)?;
    let centre = Vec3::from(b.center());
    let mut h: Vec<f32> = cams
        .iter()
        .filter_map(|c| view_half_extent(c, centre))
        .collect();
    if h.is_empty() {
        return None;
    }
    h.sort_by(f32::total_cmp);
    let n = h.len();
    let median = if n % 2 == 1 {
        h[n / 2]
    } else {
        0.5 * (h[n / 2 - 1] + h[n / 2])
    };
    Some(median / PAPER_VIEW_HALF_EXTENT)
}

/// A parameter outside its range.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("model attack {0}")]
pub struct ModelAttackError(String);

/// `k` distinct indices of `0..n`, drawn uniformly (partial Fisher–Yates), sorted.
fn draw(n: usize, k: usize, rng: &mut EotRng) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..n).collect();
    for i in 0..k.min(n) {
        let j = i + rng.range_int(0, (n - i - 1) as u64) as usize;
        idx.swap(i, j);
    }
    idx.truncate(k.min(n));
    idx.sort_unstable();
    idx
}

impl ModelAttack {
    /// The paper's three: remove 20 %, clone 20 %, parameter noise σ = 0.1.
    pub fn paper_protocol(seed: u64) -> Vec<(String, ModelAttack)> {
        vec![
            (
                "noise_0.1".into(),
                ModelAttack::Noise {
                    sigma: 0.1,
                    position_scale: 1.0,
                    seed,
                },
            ),
            (
                "remove_20".into(),
                ModelAttack::Remove {
                    fraction: 0.2,
                    seed,
                },
            ),
            (
                "clone_20".into(),
                ModelAttack::Clone {
                    fraction: 0.2,
                    seed,
                },
            ),
        ]
    }

    /// The same attack with another seed (another draw of the Gaussians it removes or clones,
    /// of the noise it adds).
    pub fn reseeded(&self, seed: u64) -> ModelAttack {
        let mut a = self.clone();
        match &mut a {
            ModelAttack::Remove { seed: s, .. }
            | ModelAttack::Clone { seed: s, .. }
            | ModelAttack::Noise { seed: s, .. } => *s = seed,
        }
        a
    }

    /// The attacked copy of `g`.
    pub fn apply(&self, g: &Gaussians) -> Result<Gaussians, ModelAttackError> {
        let frac_ok = |f: f32| (0.0..=1.0).contains(&f);
        match *self {
            ModelAttack::Remove { fraction, seed } => {
                if !frac_ok(fraction) {
                    return Err(ModelAttackError(format!(
                        "remove: fraction {fraction} is not in [0, 1]"
                    )));
                }
                let n = g.len();
                let drop = draw(
                    n,
                    (fraction as f64 * n as f64) as usize,
                    &mut EotRng::new(seed),
                );
                let mut keep = Vec::with_capacity(n - drop.len());
                let mut d = drop.iter().peekable();
                for i in 0..n {
                    if d.peek() == Some(&&i) {
                        d.next();
                    } else {
                        keep.push(i);
                    }
                }
                Ok(subset(g, &keep))
            }
            ModelAttack::Clone { fraction, seed } => {
                if !frac_ok(fraction) {
                    return Err(ModelAttackError(format!(
                        "clone: fraction {fraction} is not in [0, 1]"
                    )));
                }
                let n = g.len();
                let mut idx: Vec<usize> = (0..n).collect();
                idx.extend(draw(
                    n,
                    (fraction as f64 * n as f64) as usize,
                    &mut EotRng::new(seed),
                ));
                Ok(subset(g, &idx))
            }
            ModelAttack::Noise {
                sigma,
                position_scale,
                seed,
            } => {
                if !(sigma.is_finite() && sigma >= 0.0) {
                    return Err(ModelAttackError(format!(
                        "noise: sigma {sigma} must be finite and ≥ 0"
                    )));
                }
                if !(position_scale.is_finite() && position_scale >= 0.0) {
                    return Err(ModelAttackError(format!(
                        "noise: position_scale {position_scale} must be finite and ≥ 0"
                    )));
                }
                let std = f64::from(sigma) * f64::from(sigma);
                let mut rng = EotRng::new(seed);
                let mut noise = move || (rng.normal_pair().0 * std) as f32;
                let mut out = g.clone();
                for v in out.means.iter_mut().flatten() {
                    *v += position_scale * noise();
                }
                for v in out.log_scales.iter_mut().flatten() {
                    *v += noise();
                }
                for q in out.rotations.iter_mut() {
                    let p = q.map(|v| v + noise());
                    let len = p.iter().map(|v| v * v).sum::<f32>().sqrt();
                    if len > 1e-12 {
                        *q = p.map(|v| v / len);
                    }
                }
                for v in out.opacity_logits.iter_mut() {
                    *v += noise();
                }
                for v in out.sh_dc.iter_mut().flatten() {
                    *v += noise();
                }
                for v in out.sh_rest.iter_mut() {
                    *v += noise();
                }
                Ok(out)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::object_scene;

    #[test]
    fn remove_and_clone_change_the_count_by_the_fraction() {
        let g = object_scene(1000, 2, 7);
        let r = ModelAttack::Remove {
            fraction: 0.2,
            seed: 1,
        }
        .apply(&g)
        .unwrap();
        assert_eq!(r.len(), 800);
        // What is left is a subset of the original, in order.
        let mut j = 0;
        for i in 0..r.len() {
            while g.means[j] != r.means[i] {
                j += 1;
            }
        }
        let c = ModelAttack::Clone {
            fraction: 0.2,
            seed: 1,
        }
        .apply(&g)
        .unwrap();
        assert_eq!(c.len(), 1200);
        assert_eq!(&c.means[..1000], &g.means[..]);
        for m in &c.means[1000..] {
            assert!(g.means.contains(m));
        }
        // Distinct clones.
        let mut extra = c.means[1000..].to_vec();
        extra.sort_by(|a, b| a.partial_cmp(b).unwrap());
        extra.dedup();
        assert_eq!(extra.len(), 200);
    }

    #[test]
    fn noise_has_the_papers_standard_deviation() {
        let g = object_scene(20_000, 0, 3);
        let a = ModelAttack::Noise {
            sigma: 0.1,
            position_scale: 1.0,
            seed: 5,
        }
        .apply(&g)
        .unwrap();
        let d: Vec<f64> = a
            .opacity_logits
            .iter()
            .zip(&g.opacity_logits)
            .map(|(x, y)| f64::from(x - y))
            .collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        let std = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
        assert!((std - 0.01).abs() < 0.0005, "std {std}");
        assert!(mean.abs() < 0.0005);
        for q in &a.rotations {
            let n: f32 = q.iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn bad_parameters_are_rejected() {
        let g = object_scene(10, 0, 1);
        for a in [
            ModelAttack::Remove {
                fraction: 1.5,
                seed: 0,
            },
            ModelAttack::Clone {
                fraction: -0.1,
                seed: 0,
            },
            ModelAttack::Noise {
                sigma: f32::NAN,
                position_scale: 1.0,
                seed: 0,
            },
            ModelAttack::Noise {
                sigma: 0.1,
                position_scale: -1.0,
                seed: 0,
            },
            ModelAttack::Noise {
                sigma: 0.1,
                position_scale: f32::INFINITY,
                seed: 0,
            },
        ] {
            assert!(a.apply(&g).is_err(), "{a:?}");
        }
    }

    /// The scene `g` in units `k` times smaller or larger: means ×k, scales ×k.
    fn rescaled(g: &Gaussians, k: f32) -> Gaussians {
        let mut out = g.clone();
        for m in out.means.iter_mut().flatten() {
            *m *= k;
        }
        for s in out.log_scales.iter_mut().flatten() {
            *s += k.ln();
        }
        out
    }

    #[test]
    fn scaled_noise_does_the_same_to_a_scene_whatever_its_units() {
        use crate::scene::orbit::orbit_cameras;
        let g = object_scene(3000, 1, 11);
        let opts = OrbitOptions {
            count: 8,
            width: 64,
            height: 48,
            ..OrbitOptions::default()
        };
        let s1 = view_position_scale(&g, &orbit_cameras(&g, &opts).unwrap()).unwrap();
        let attack = |g: &Gaussians, s: f32| {
            ModelAttack::Noise {
                sigma: 0.1,
                position_scale: s,
                seed: 9,
            }
            .apply(g)
            .unwrap()
        };
        let a1 = attack(&g, s1);
        for k in [0.1f32, 10.0] {
            let gk = rescaled(&g, k);
            let sk = view_position_scale(&gk, &orbit_cameras(&gk, &opts).unwrap()).unwrap();
            assert!((sk / s1 - k).abs() < 1e-3 * k, "k {k}: {sk} vs {s1}");
            // The attacked copy of the rescaled scene is the rescaled attacked copy.
            let ak = attack(&gk, sk);
            let back = rescaled(&ak, 1.0 / k);
            for (x, y) in back.means.iter().flatten().zip(a1.means.iter().flatten()) {
                assert!((x - y).abs() < 1e-4, "k {k}: {x} vs {y}");
            }
            for (x, y) in back
                .log_scales
                .iter()
                .flatten()
                .zip(a1.log_scales.iter().flatten())
            {
                assert!((x - y).abs() < 1e-4, "k {k}: {x} vs {y}");
            }
            assert_eq!(back.sh_dc, a1.sh_dc);
            // In world units the same attack is k times weaker relative to the scene.
            let raw = rescaled(&attack(&gk, 1.0), 1.0 / k);
            let moved = |a: &Gaussians| {
                a.means
                    .iter()
                    .flatten()
                    .zip(g.means.iter().flatten())
                    .map(|(x, y)| f64::from(x - y).powi(2))
                    .sum::<f64>()
            };
            let ratio = (moved(&raw) / moved(&attack(&g, 1.0))).sqrt();
            assert!(
                (ratio - 1.0 / f64::from(k)).abs() < 0.01 / f64::from(k),
                "k {k}: {ratio}"
            );
        }
        // Only the means see the factor: the other parameters get the same draws.
        let plain = attack(&g, 1.0);
        assert_eq!(plain.sh_dc, a1.sh_dc);
        assert_eq!(plain.opacity_logits, a1.opacity_logits);
        assert_eq!(plain.rotations, a1.rotations);
    }

    #[test]
    fn the_paper_reference_is_legos_view_at_its_centre() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/data/datasets/nerf_synthetic_lego/transforms_train.json");
        if !path.exists() {
            eprintln!("SKIPPED: {} is missing (../shared/data)", path.display());
            return;
        }
        let cams = crate::scene::camera::read_nerf_transforms(&path).unwrap();
        assert_eq!(cams.len(), 100);
        for c in &cams {
            let h = view_half_extent(c, Vec3::ZERO).unwrap();
            assert!(
                (h / PAPER_VIEW_HALF_EXTENT - 1.0).abs() < 0.005,
                "{}: {h}",
                c.name
            );
        }
        // Behind every camera: no extent.
        let c = &cams[0];
        assert_eq!(view_half_extent(c, 3.0 * c.center()), None);
    }
}
