//! EOT sampling: the deterministic random source [`EotRng`], the attack families and the
//! distribution p(t) ([`EotConfig`], [`random_composition`]).

use serde::{Deserialize, Serialize};

use super::DiffAttack;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attack::diff::tests::{smooth, to_vec};

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
