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
}

/// Why a projection cannot be fitted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProjectionError {
    #[error("a view projection needs at least 2 feature vectors, got {0}")]
    TooFewSamples(usize),
    #[error("feature vectors of different lengths ({0} and {1})")]
    Ragged(usize, usize),
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
        let mut cov = vec![0.0f64; f * f];
        for row in features {
            let d: Vec<f64> = row
                .iter()
                .zip(&mean)
                .map(|(&x, m)| f64::from(x) - m)
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
        })
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
