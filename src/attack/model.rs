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

use serde::{Deserialize, Serialize};

use super::diff::EotRng;
use crate::embed::subset;
use crate::scene::Gaussians;

/// One model-space attack.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", content = "params", rename_all = "snake_case")]
pub enum ModelAttack {
    /// Delete a fraction in [0, 1] of the Gaussians.
    Remove { fraction: f32, seed: u64 },
    /// Duplicate a fraction in [0, 1] of the Gaussians.
    Clone { fraction: f32, seed: u64 },
    /// Parameter noise with the papers' σ (std σ²).
    Noise { sigma: f32, seed: u64 },
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
            ("noise_0.1".into(), ModelAttack::Noise { sigma: 0.1, seed }),
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
            ModelAttack::Noise { sigma, seed } => {
                if !(sigma.is_finite() && sigma >= 0.0) {
                    return Err(ModelAttackError(format!(
                        "noise: sigma {sigma} must be finite and ≥ 0"
                    )));
                }
                let std = f64::from(sigma) * f64::from(sigma);
                let mut rng = EotRng::new(seed);
                let mut noise = move || (rng.normal_pair().0 * std) as f32;
                let mut out = g.clone();
                for v in out.means.iter_mut().flatten() {
                    *v += noise();
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
                seed: 0,
            },
        ] {
            assert!(a.apply(&g).is_err(), "{a:?}");
        }
    }
}
