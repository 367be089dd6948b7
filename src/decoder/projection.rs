//! The per-asset view projection: the directions in which an unmarked asset's own pooled
//! decoder features move from one view to the next, removed before the linear head.
//!
//! The colour-Fourier decoder pools F features (F = 128 for the shipped ones) and reads L ≤ F
//! bits from them with a linear head. Seen through different cameras, the unmarked asset's
//! features move (other surfaces, other colours in view), and what moves the features moves
//! every bit: on donut that view-to-view spread of the logits is as large as the whole signal
//! the finetuning can write at 38 dB (docs/RESULTS.md). The spread is low-rank — the views of one
//! asset differ along a few smooth directions — and the head needs only L of the F dimensions,
//! so the owner, who has the original, measures the top `k` principal directions U (k × F,
//! orthonormal rows) of the original's features over many views and decodes
//!
//! ```text
//!     f' = f − Uᵀ·U·(f − μ)        (eq. viewproj; μ the features' mean over those views)
//! ```
//!
//! before the head, so the views of the original all decode near the same logits and the
//! finetuning writes the message into directions the views do not disturb. The projection
//! depends on the original only (never on the message or the secret mask), so the exact
//! binomial p-value of a dispute is unchanged: for any image the decoded bits are fixed and the
//! sealed payload is uniform and independent of them.
//!
//! **The matched head** goes further: instead of the shipped random head, the owner chooses the
//! L directions the bits are read along for this asset. For a direction a in feature space the
//! squared logit one unit of image change can buy is aᵀGa (G = Σ_pixels J_pᵀ J_p over the
//! training views, J_p the decoder's Jacobian at pixel p of the original's renders) and the
//! asset's own noise is aᵀN_λa (N the features' second moment about μ over the calibration
//! views and the nuisance samples — the same views through random image attacks and of
//! perturbed copies of the asset, `embed::calibrate::nuisance_features` —, N_λ = N +
//! λ·tr(N)/F·I); the best directions are the top generalised eigenvectors of (G, N_λ):
//!
//! ```text
//!     A = N_λ^{-1/2}·E·R,   z = Aᵀ(f − μ)        (eq. matchedhead)
//! ```
//!
//! E the top-L eigenvectors of N_λ^{-1/2}·G·N_λ^{-1/2} and R a fixed random rotation of them
//! (every bit gets the same mean gain, not the first bits the best). Each logit is in units of
//! the asset's noise. Where the shipped random head spreads each bit over directions that the
//! asset's colours cannot move independently (2 of 32 bits were written wrong on average), the
//! matched head reads only directions the finetuning can write and the views do not disturb:
//! on donut (32 bits, 256², unseen views, docs/RESULTS.md "matched head") 85.9 % of the bits
//! per view → 97.7 % (λ 0.1), 97.9 % with 200 nuisance samples (the default), at 38–39 dB.
//! Like the projection it depends on the original only, so a dispute's p-value stays exact; the
//! service registers it sealed with the key (`store::keys`).

use burn::tensor::{Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::model::symmetric_eigen;

/// μ and U of eq. `viewproj` ([module docs](self)).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewProjection {
    /// μ, length F.
    pub mean: Vec<f32>,
    /// U, k × F row-major, orthonormal rows.
    pub basis: Vec<f32>,
    /// Share of the features' variance over the calibration views that U spans.
    pub explained: f32,
    /// The matched head A of eq. `matchedhead`, L × F row-major (one direction per bit); when
    /// present the logits are `A·(f − μ)` and neither U, the decoder's head nor its whitening
    /// is used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head: Option<Vec<f32>>,
}

/// Why a projection cannot be fitted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProjectionError {
    #[error("a view projection needs at least 2 feature vectors, got {0}")]
    TooFewSamples(usize),
    #[error("feature vectors of different lengths ({0} and {1})")]
    Ragged(usize, usize),
    #[error("the gain matrix is not {0}×{0}")]
    GainSize(usize),
    #[error("rank {rank} does not leave {bits} of the {features} features for the bits")]
    RankTooLarge {
        rank: usize,
        features: usize,
        bits: usize,
    },
}

impl ViewProjection {
    /// The top-`rank` principal directions of `features` (one vector per view of the unmarked
    /// asset), leaving at least `bits` dimensions for the head.
    pub fn fit(features: &[Vec<f32>], rank: usize, bits: usize) -> Result<Self, ProjectionError> {
        if features.len() < 2 {
            return Err(ProjectionError::TooFewSamples(features.len()));
        }
        let f = features[0].len();
        if let Some(r) = features.iter().find(|r| r.len() != f) {
            return Err(ProjectionError::Ragged(f, r.len()));
        }
        if rank + bits > f {
            return Err(ProjectionError::RankTooLarge {
                rank,
                features: f,
                bits,
            });
        }
        let n = features.len() as f64;
        let mut mean = vec![0.0f64; f];
        for row in features {
            for (m, &x) in mean.iter_mut().zip(row) {
                *m += f64::from(x) / n;
            }
        }
        let cov = covariance(features, &mean);
        let (values, vectors) = symmetric_eigen(&cov, f);
        let mut order: Vec<usize> = (0..f).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let total: f64 = values.iter().map(|v| v.max(0.0)).sum();
        let kept: f64 = order[..rank].iter().map(|&i| values[i].max(0.0)).sum();
        let mut basis = Vec::with_capacity(rank * f);
        for &k in &order[..rank] {
            // Eigenvectors are the columns of `vectors`.
            basis.extend((0..f).map(|r| vectors[r * f + k] as f32));
        }
        Ok(Self {
            mean: mean.into_iter().map(|m| m as f32).collect(),
            basis,
            explained: if total > 0.0 {
                (kept / total) as f32
            } else {
                0.0
            },
            head: None,
        })
    }

    /// The matched head of eq. `matchedhead` for `bits` bits: `features` the unmarked asset's
    /// pooled features over the calibration views (N, μ), `gain` the F × F matrix G
    /// (row-major), `lambda` the regularisation λ, `seed` the rotation R's. U is empty.
    pub fn fit_matched(
        features: &[Vec<f32>],
        nuisance: &[Vec<f32>],
        gain: &[f64],
        bits: usize,
        lambda: f64,
        seed: u64,
    ) -> Result<Self, ProjectionError> {
        let plain = Self::fit(features, 0, bits)?;
        let f = plain.features();
        if gain.len() != f * f {
            return Err(ProjectionError::GainSize(f));
        }
        if let Some(r) = nuisance.iter().find(|r| r.len() != f) {
            return Err(ProjectionError::Ragged(f, r.len()));
        }
        let mean: Vec<f64> = plain.mean.iter().map(|&m| f64::from(m)).collect();
        // N: the second moment about the clean views' mean μ of the clean views and the
        // nuisance samples together (an attack's shift of the features counts as noise).
        let all: Vec<Vec<f32>> = features.iter().chain(nuisance).cloned().collect();
        let mut n = covariance(&all, &mean);
        let tr = (0..f).map(|i| n[i * f + i]).sum::<f64>() / f as f64;
        let floor = (lambda * tr).max(1e-12);
        for i in 0..f {
            n[i * f + i] += floor;
        }
        // W = N_λ^{-1/2}.
        let (vals, vecs) = symmetric_eigen(&n, f);
        let mut w = vec![0.0f64; f * f];
        for i in 0..f {
            for j in i..f {
                let v: f64 = (0..f)
                    .map(|k| vecs[i * f + k] * vecs[j * f + k] / vals[k].max(floor).sqrt())
                    .sum();
                w[i * f + j] = v;
                w[j * f + i] = v;
            }
        }
        let m = matmul(&matmul(&w, gain, f), &w, f);
        let mut m_sym = m.clone();
        for i in 0..f {
            for j in 0..f {
                m_sym[i * f + j] = 0.5 * (m[i * f + j] + m[j * f + i]);
            }
        }
        let (ev, evec) = symmetric_eigen(&m_sym, f);
        let mut order: Vec<usize> = (0..f).collect();
        order.sort_by(|&a, &b| ev[b].total_cmp(&ev[a]));
        let rot = random_rotation(bits, seed);
        // A = W·E·R, stored as rows a_k.
        let mut head = vec![0.0f32; bits * f];
        for k in 0..bits {
            // e = Σ_j E[:, j]·R[j, k]
            let e: Vec<f64> = (0..f)
                .map(|i| {
                    (0..bits)
                        .map(|j| evec[i * f + order[j]] * rot[j * bits + k])
                        .sum()
                })
                .collect();
            for i in 0..f {
                head[k * f + i] = (0..f).map(|j| w[i * f + j] * e[j]).sum::<f64>() as f32;
            }
        }
        Ok(Self {
            head: Some(head),
            ..plain
        })
    }

    /// Number of bits the matched head reads (0 without one).
    pub fn head_bits(&self) -> usize {
        self.head
            .as_ref()
            .map_or(0, |h| h.len().checked_div(self.mean.len()).unwrap_or(0))
    }

    /// Eq. `matchedhead` on pooled features `[B, F]` (differentiable): logits `[B, L]`.
    ///
    /// # Panics
    /// Without a matched head, or if the features do not have F columns.
    pub fn matched_logits(&self, pooled: Tensor<2>) -> Tensor<2> {
        let head = self.head.as_ref().expect("a matched head");
        let [_, f] = pooled.dims();
        assert_eq!(
            f,
            self.features(),
            "the head has {} features",
            self.features()
        );
        let device = pooled.device();
        let mu = Tensor::<2>::from_data(TensorData::new(self.mean.clone(), [1, f]), &device);
        let a = Tensor::<2>::from_data(
            TensorData::new(head.clone(), [self.head_bits(), f]),
            &device,
        );
        pooled.sub(mu).matmul(a.transpose())
    }

    /// Eq. `matchedhead` on one feature vector, on the host: `A·(f − μ)`; `None` without a
    /// matched head or when `features` does not have F values. Since the head is linear, the
    /// logits of features averaged over several images are the average of their logits.
    pub fn matched_logits_of(&self, features: &[f32]) -> Option<Vec<f32>> {
        let head = self.head.as_ref()?;
        let f = self.features();
        if features.len() != f || f == 0 {
            return None;
        }
        Some(
            head.chunks_exact(f)
                .map(|a| {
                    a.iter()
                        .zip(features.iter().zip(&self.mean))
                        .map(|(&w, (&x, &m))| f64::from(w) * (f64::from(x) - f64::from(m)))
                        .sum::<f64>() as f32
                })
                .collect(),
        )
    }

    /// Number of features F.
    pub fn features(&self) -> usize {
        self.mean.len()
    }

    /// Number of removed directions k.
    pub fn rank(&self) -> usize {
        self.basis.len().checked_div(self.mean.len()).unwrap_or(0)
    }

    /// Eq. `viewproj` on pooled features `[B, F]` (differentiable).
    ///
    /// # Panics
    /// If the features do not have F columns.
    pub fn apply(&self, pooled: Tensor<2>) -> Tensor<2> {
        let [_, f] = pooled.dims();
        assert_eq!(
            f,
            self.features(),
            "the projection has {} features",
            self.features()
        );
        let k = self.rank();
        if k == 0 {
            return pooled;
        }
        let device = pooled.device();
        let mu = Tensor::<2>::from_data(TensorData::new(self.mean.clone(), [1, f]), &device);
        let u = Tensor::<2>::from_data(TensorData::new(self.basis.clone(), [k, f]), &device);
        let coeff = pooled.clone().sub(mu).matmul(u.clone().transpose()); // [B, k]
        pooled.sub(coeff.matmul(u))
    }
}

fn covariance(rows: &[Vec<f32>], mean: &[f64]) -> Vec<f64> {
    let f = mean.len();
    let n = rows.len() as f64;
    let mut cov = vec![0.0f64; f * f];
    for row in rows {
        let d: Vec<f64> = row
            .iter()
            .zip(mean)
            .map(|(&x, &m)| f64::from(x) - m)
            .collect();
        for i in 0..f {
            for j in i..f {
                cov[i * f + j] += d[i] * d[j] / n;
            }
        }
    }
    for i in 0..f {
        for j in 0..i {
            cov[i * f + j] = cov[j * f + i];
        }
    }
    cov
}

fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0f64; n * n];
    for i in 0..n {
        for k in 0..n {
            let x = a[i * n + k];
            if x != 0.0 {
                for j in 0..n {
                    c[i * n + j] += x * b[k * n + j];
                }
            }
        }
    }
    c
}

/// A random n × n orthogonal matrix (Gram–Schmidt of Gaussian columns), row-major.
fn random_rotation(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = crate::attack::diff::EotRng::new(seed ^ 0x524f_5441);
    let mut cols: Vec<Vec<f64>> = Vec::with_capacity(n);
    while cols.len() < n {
        let mut v: Vec<f64> = (0..n).map(|_| rng.normal_pair().0).collect();
        for c in &cols {
            let d: f64 = v.iter().zip(c).map(|(a, b)| a * b).sum();
            for (x, y) in v.iter_mut().zip(c) {
                *x -= d * y;
            }
        }
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm > 1e-6 {
            cols.push(v.into_iter().map(|x| x / norm).collect());
        }
    }
    let mut r = vec![0.0f64; n * n];
    for (j, c) in cols.iter().enumerate() {
        for (i, &x) in c.iter().enumerate() {
            r[i * n + j] = x;
        }
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    fn device() -> Device {
        Device::flex()
    }

    /// Samples that vary along two known directions plus a little isotropic noise.
    fn samples() -> (Vec<Vec<f32>>, [Vec<f32>; 2]) {
        let f = 8;
        let a: Vec<f32> = (0..f).map(|i| if i < 4 { 0.5 } else { 0.0 }).collect();
        let b: Vec<f32> = (0..f)
            .map(|i| if i >= 4 { 0.5 } else { 0.0 })
            .collect::<Vec<_>>();
        let mut rng = crate::attack::diff::EotRng::new(7);
        let rows = (0..64)
            .map(|_| {
                let (s, t) = rng.normal_pair();
                (0..f)
                    .map(|i| {
                        1.0 + 3.0 * s as f32 * a[i]
                            + 2.0 * t as f32 * b[i]
                            + 0.01 * rng.range(-1.0, 1.0) as f32
                    })
                    .collect()
            })
            .collect();
        (rows, [a, b])
    }

    #[test]
    fn removes_the_directions_the_samples_vary_along() {
        let (rows, _) = samples();
        let p = ViewProjection::fit(&rows, 2, 4).unwrap();
        assert_eq!((p.features(), p.rank()), (8, 2));
        assert!(p.explained > 0.99, "{}", p.explained);
        // Orthonormal rows.
        let u = &p.basis;
        for r in 0..2 {
            for s in 0..2 {
                let dot: f32 = (0..8).map(|i| u[r * 8 + i] * u[s * 8 + i]).sum();
                assert!(
                    (dot - f32::from(u8::from(r == s))).abs() < 1e-4,
                    "{r}·{s} = {dot}"
                );
            }
        }
        // Projected, the samples barely vary; a change outside the span passes untouched.
        let flat: Vec<f32> = rows.iter().flatten().copied().collect();
        let x = Tensor::<2>::from_data(TensorData::new(flat, [rows.len(), 8]), &device());
        let y: Vec<f32> = p.apply(x).try_into_vec_as::<f32>().unwrap();
        for row in y.chunks_exact(8) {
            for (v, m) in row.iter().zip(&p.mean) {
                assert!((v - m).abs() < 0.05, "{v} vs {m}");
            }
        }
        let off: Vec<f32> = (0..8)
            .map(|i| p.mean[i] + [1., -1., 0., 0., 1., -1., 0., 0.][i])
            .collect();
        let x = Tensor::<2>::from_data(TensorData::new(off.clone(), [1, 8]), &device());
        let y: Vec<f32> = p.apply(x).try_into_vec_as::<f32>().unwrap();
        for (a, b) in y.iter().zip(&off) {
            assert!((a - b).abs() < 1e-3, "{a} vs {b}");
        }
    }

    #[test]
    fn the_matched_head_reads_where_the_gain_is_and_the_noise_is_not() {
        // Noise along a and b (samples()); gain along a (noisy, cheap) and c (quiet, cheap).
        let (rows, [a, _]) = samples();
        let f = 8;
        let c: Vec<f64> = [0.5, -0.5, 0., 0., 0.5, -0.5, 0., 0.].to_vec();
        let a: Vec<f64> = a.iter().map(|&x| f64::from(x)).collect();
        let mut gain = vec![0.0f64; f * f];
        for i in 0..f {
            for j in 0..f {
                gain[i * f + j] =
                    5.0 * a[i] * a[j] + c[i] * c[j] + 0.001 * f64::from(u8::from(i == j));
            }
        }
        let p = ViewProjection::fit_matched(&rows, &[], &gain, 1, 0.01, 3).unwrap();
        assert_eq!((p.head_bits(), p.rank()), (1, 0));
        let h: Vec<f64> = p
            .head
            .as_ref()
            .unwrap()
            .iter()
            .map(|&x| f64::from(x))
            .collect();
        // The head is c (up to sign and scale): a buys more logit but is drowned in noise.
        let cos = |u: &[f64], v: &[f64]| {
            let d: f64 = u.iter().zip(v).map(|(x, y)| x * y).sum();
            d / (u.iter().map(|x| x * x).sum::<f64>() * v.iter().map(|x| x * x).sum::<f64>()).sqrt()
        };
        assert!(cos(&h, &c).abs() > 0.95, "head {h:?}");
        assert!(cos(&h, &a).abs() < 0.1, "head {h:?}");
        // Logits: A·(f − μ), in units of the views' noise: near 0 on the samples.
        let flat: Vec<f32> = rows.iter().flatten().copied().collect();
        let x = Tensor::<2>::from_data(TensorData::new(flat, [rows.len(), f]), &device());
        let z: Vec<f32> = p.matched_logits(x).try_into_vec_as::<f32>().unwrap();
        let var = z.iter().map(|v| v * v).sum::<f32>() / z.len() as f32;
        assert!(var < 1.0, "noise variance {var}");
        let mean: f32 = z.iter().sum::<f32>() / z.len() as f32;
        assert!(mean.abs() < 1e-3, "{mean}");
        // Several bits: N_λ-orthonormal directions, reproducible from the seed, serialisable.
        let q = ViewProjection::fit_matched(&rows, &[], &gain, 3, 0.01, 3).unwrap();
        assert_eq!(
            q,
            ViewProjection::fit_matched(&rows, &[], &gain, 3, 0.01, 3).unwrap()
        );
        assert_ne!(
            q,
            ViewProjection::fit_matched(&rows, &[], &gain, 3, 0.01, 4).unwrap()
        );
        let json = serde_json::to_string(&q).unwrap();
        assert_eq!(serde_json::from_str::<ViewProjection>(&json).unwrap(), q);
        assert_eq!(
            ViewProjection::fit_matched(&rows, &[], &gain[1..], 3, 0.01, 3),
            Err(ProjectionError::GainSize(8))
        );
    }

    #[test]
    fn bad_inputs_are_refused() {
        let (rows, _) = samples();
        assert_eq!(
            ViewProjection::fit(&rows[..1], 1, 1),
            Err(ProjectionError::TooFewSamples(1))
        );
        assert!(matches!(
            ViewProjection::fit(&rows, 5, 4),
            Err(ProjectionError::RankTooLarge { .. })
        ));
        let mut ragged = rows.clone();
        ragged[3].pop();
        assert_eq!(
            ViewProjection::fit(&ragged, 1, 1),
            Err(ProjectionError::Ragged(8, 7))
        );
    }
}
