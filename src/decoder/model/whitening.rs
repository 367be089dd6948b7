//! The Stable-Signature whitening of the decoder's logits ([`Whitening`]) and the Jacobi
//! eigen-decomposition it is fitted with.

use burn::tensor::{Tensor, TensorData};
use serde::{Deserialize, Serialize};

/// Why [`Whitening::fit`] failed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WhiteningError {
    /// Fewer than two samples.
    #[error("whitening needs at least 2 logit vectors, got {0}")]
    TooFewSamples(usize),
    /// Samples of different lengths, or of length 0.
    #[error("logit vector {index} has length {len}, expected {expected} (> 0)")]
    Ragged {
        index: usize,
        len: usize,
        expected: usize,
    },
    /// A NaN or infinite logit.
    #[error("logit vector {0} holds a non-finite value")]
    NotFinite(usize),
    /// Every logit is constant: there is no direction to whiten.
    #[error("the logits do not vary")]
    Degenerate,
}

/// Affine whitening of the decoder's logits, `W · (z − μ)`, with μ the mean and W = Σ^(−1/2) =
/// U Λ^(−1/2) Uᵀ (ZCA) for the covariance Σ = U Λ Uᵀ of the decoder's outputs on natural,
/// unwatermarked images — Stable Signature's recipe (their `*_whit` decoders, which WateRF and
/// 3D-GSW load, are HiDDeN plus this layer). After it, the logits of unwatermarked images have
/// zero mean and identity covariance, so their bits are (close to) fair independent coins, which
/// is what the binomial false-positive statistics of verification assume.
///
/// Eigenvalues below `1e-6 · λ_max` are raised to that floor, so directions in which the
/// samples do not vary (fewer samples than bits, or a stuck bit) are not blown up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Whitening {
    /// μ, length L.
    pub mean: Vec<f32>,
    /// W, L × L row-major (symmetric).
    pub matrix: Vec<f32>,
}

/// Relative eigenvalue floor of [`Whitening::fit`].
pub const WHITENING_EIGEN_FLOOR: f64 = 1e-6;

impl Whitening {
    /// The identity map on L logits.
    pub fn identity(bits: usize) -> Self {
        let mut matrix = vec![0.0; bits * bits];
        for i in 0..bits {
            matrix[i * bits + i] = 1.0;
        }
        Self {
            mean: vec![0.0; bits],
            matrix,
        }
    }

    /// Number of logits L.
    pub fn bits(&self) -> usize {
        self.mean.len()
    }

    /// Checks samples for [`fit`](Self::fit) and [`centering`](Self::centering) and returns
    /// their mean (f64).
    fn sample_mean(logits: &[Vec<f32>]) -> Result<Vec<f64>, WhiteningError> {
        let n = logits.len();
        if n < 2 {
            return Err(WhiteningError::TooFewSamples(n));
        }
        let l = logits[0].len();
        for (index, row) in logits.iter().enumerate() {
            if row.len() != l || l == 0 {
                return Err(WhiteningError::Ragged {
                    index,
                    len: row.len(),
                    expected: l,
                });
            }
            if row.iter().any(|v| !v.is_finite()) {
                return Err(WhiteningError::NotFinite(index));
            }
        }
        let mut mean = vec![0.0f64; l];
        for row in logits {
            for (m, &v) in mean.iter_mut().zip(row) {
                *m += v as f64;
            }
        }
        for m in &mut mean {
            *m /= n as f64;
        }
        Ok(mean)
    }

    /// Centering only: μ fitted as in [`fit`](Self::fit), W = identity. It removes the bias of
    /// each bit on natural images (bit i = `z_i > μ_i`) without mixing or rescaling the logits,
    /// so it costs watermarked images far less accuracy than the full whitening when μ is small
    /// next to their logits.
    pub fn centering(logits: &[Vec<f32>]) -> Result<Self, WhiteningError> {
        let mean = Self::sample_mean(logits)?;
        let mut w = Self::identity(mean.len());
        w.mean = mean.into_iter().map(|m| m as f32).collect();
        Ok(w)
    }

    /// Whether W is the identity (a [`centering`](Self::centering)).
    pub fn is_centering(&self) -> bool {
        let l = self.bits();
        self.matrix
            .iter()
            .enumerate()
            .all(|(k, &v)| v == if k / l == k % l { 1.0 } else { 0.0 })
    }

    /// Fits μ and W to decoder outputs on natural images (one vector of L logits per image),
    /// in f64 with a Jacobi eigen-decomposition of the covariance (divided by n, as Stable
    /// Signature does).
    pub fn fit(logits: &[Vec<f32>]) -> Result<Self, WhiteningError> {
        let mean = Self::sample_mean(logits)?;
        let (n, l) = (logits.len(), mean.len());
        let mut cov = vec![0.0f64; l * l];
        for row in logits {
            for i in 0..l {
                let di = row[i] as f64 - mean[i];
                for j in i..l {
                    cov[i * l + j] += di * (row[j] as f64 - mean[j]);
                }
            }
        }
        for i in 0..l {
            for j in i..l {
                let v = cov[i * l + j] / n as f64;
                cov[i * l + j] = v;
                cov[j * l + i] = v;
            }
        }
        let (values, vectors) = symmetric_eigen(&cov, l);
        let max = values.iter().cloned().fold(0.0f64, f64::max);
        if !(max > 0.0) {
            return Err(WhiteningError::Degenerate);
        }
        let floor = max * WHITENING_EIGEN_FLOOR;
        let inv_sqrt: Vec<f64> = values.iter().map(|&v| 1.0 / v.max(floor).sqrt()).collect();
        let mut matrix = vec![0.0f32; l * l];
        for i in 0..l {
            for j in 0..l {
                let w: f64 = (0..l)
                    .map(|k| vectors[i * l + k] * inv_sqrt[k] * vectors[j * l + k])
                    .sum();
                matrix[i * l + j] = w as f32;
            }
        }
        Ok(Self {
            mean: mean.into_iter().map(|m| m as f32).collect(),
            matrix,
        })
    }

    /// Whitened logits `[B, L]` = `(z − μ) Wᵀ` (differentiable).
    ///
    /// # Panics
    /// If `logits` does not have L columns.
    pub fn apply(&self, logits: Tensor<2>) -> Tensor<2> {
        let l = self.bits();
        let [_, cols] = logits.dims();
        assert_eq!(cols, l, "whitening is for {l} logits, got {cols}");
        let device = logits.device();
        let mean = Tensor::<2>::from_data(TensorData::new(self.mean.clone(), [1, l]), &device);
        let w = Tensor::<2>::from_data(TensorData::new(self.matrix.clone(), [l, l]), &device);
        logits.sub(mean).matmul(w.transpose())
    }

    /// [`apply`](Self::apply) on one logit vector, on the host.
    ///
    /// # Panics
    /// If `logits` does not have length L.
    pub fn apply_row(&self, logits: &[f32]) -> Vec<f32> {
        let l = self.bits();
        assert_eq!(logits.len(), l, "whitening is for {l} logits");
        (0..l)
            .map(|i| {
                (0..l)
                    .map(|j| self.matrix[i * l + j] as f64 * (logits[j] - self.mean[j]) as f64)
                    .sum::<f64>() as f32
            })
            .collect()
    }
}

/// Eigen-decomposition of a symmetric `n × n` matrix (row-major) by the cyclic Jacobi method:
/// returns the eigenvalues and the eigenvectors as the columns of an `n × n` row-major matrix.
/// Accurate to a few ulps for the small (n ≤ 64) covariance matrices it is used on.
pub fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(a.len(), n * n, "matrix is not {n}×{n}");
    let mut a = a.to_vec();
    let mut v = vec![0.0f64; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let norm: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum::<f64>()
            .sqrt();
        if !(off > 1e-15 * norm) {
            break;
        }
        for p in 0..n {
            for q in (p + 1)..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let app = a[p * n + p];
                let aqq = a[q * n + q];
                // Rotation angle zeroing a[p][q] (Golub & Van Loan, Algorithm 8.4.1).
                let theta = (aqq - app) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let akp = a[k * n + p];
                    let akq = a[k * n + q];
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let apk = a[p * n + k];
                    let aqk = a[q * n + k];
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let vkp = v[k * n + p];
                    let vkq = v[k * n + q];
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let values = (0..n).map(|i| a[i * n + i]).collect();
    (values, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::model::tests::{Lcg, device, to_vec};

    #[test]
    fn jacobi_reconstructs_a_symmetric_matrix() {
        let n = 6;
        let mut rng = Lcg(3);
        let mut a = vec![0.0f64; n * n];
        for i in 0..n {
            for j in i..n {
                let v = rng.normal();
                a[i * n + j] = v;
                a[j * n + i] = v;
            }
        }
        let (values, v) = symmetric_eigen(&a, n);
        for i in 0..n {
            for j in 0..n {
                let r: f64 = (0..n)
                    .map(|k| v[i * n + k] * values[k] * v[j * n + k])
                    .sum();
                assert!((r - a[i * n + j]).abs() < 1e-10);
                let o: f64 = (0..n).map(|k| v[k * n + i] * v[k * n + j]).sum();
                assert!((o - (i == j) as u8 as f64).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn whitening_gives_zero_mean_identity_covariance() {
        // Correlated logits: z = A·g + m with a fixed mixing matrix A.
        let l = 8;
        let mut rng = Lcg(11);
        let mix: Vec<f64> = (0..l * l).map(|_| rng.normal()).collect();
        let samples: Vec<Vec<f32>> = (0..2000)
            .map(|_| {
                let g: Vec<f64> = (0..l).map(|_| rng.normal()).collect();
                (0..l)
                    .map(|i| {
                        let s: f64 = (0..l).map(|k| mix[i * l + k] * g[k]).sum();
                        (s + 3.0 + i as f64) as f32
                    })
                    .collect()
            })
            .collect();
        let w = Whitening::fit(&samples).unwrap();
        let white: Vec<Vec<f32>> = samples.iter().map(|z| w.apply_row(z)).collect();
        for i in 0..l {
            let mean: f64 = white.iter().map(|z| z[i] as f64).sum::<f64>() / white.len() as f64;
            assert!(mean.abs() < 1e-4, "mean {mean}");
            for j in 0..l {
                let c: f64 = white.iter().map(|z| z[i] as f64 * z[j] as f64).sum::<f64>()
                    / white.len() as f64;
                let expected = (i == j) as u8 as f64;
                assert!((c - expected).abs() < 1e-3, "cov[{i}][{j}] = {c}");
            }
        }
        // Tensor path = host path.
        let batch: Vec<f32> = samples[..4].iter().flatten().copied().collect();
        let t = w.apply(Tensor::from_data(TensorData::new(batch, [4, l]), &device()));
        let t = to_vec(t);
        for (r, z) in samples[..4].iter().enumerate() {
            for (i, v) in w.apply_row(z).iter().enumerate() {
                assert!((t[r * l + i] - v).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn whitening_rejects_bad_input_and_survives_rank_deficiency() {
        assert_eq!(
            Whitening::fit(&[vec![1.0, 2.0]]),
            Err(WhiteningError::TooFewSamples(1))
        );
        assert!(matches!(
            Whitening::fit(&[vec![1.0, 2.0], vec![1.0]]),
            Err(WhiteningError::Ragged { index: 1, .. })
        ));
        assert_eq!(
            Whitening::fit(&[vec![1.0, f32::NAN], vec![1.0, 2.0]]),
            Err(WhiteningError::NotFinite(0))
        );
        assert_eq!(
            Whitening::fit(&[vec![1.0, 2.0], vec![1.0, 2.0]]),
            Err(WhiteningError::Degenerate)
        );
        // 3 samples of 8 logits: rank 2, still finite.
        let mut rng = Lcg(5);
        let samples: Vec<Vec<f32>> = (0..3)
            .map(|_| (0..8).map(|_| rng.normal() as f32).collect())
            .collect();
        let w = Whitening::fit(&samples).unwrap();
        assert!(w.matrix.iter().all(|v| v.is_finite()));
        assert_eq!(
            Whitening::identity(4).apply_row(&[1.0, -2.0, 3.0, 0.5]),
            vec![1.0, -2.0, 3.0, 0.5]
        );
    }

    #[test]
    fn centering_removes_the_mean_and_nothing_else() {
        // Bit 0 biased to 1 (+2), bit 1 biased to 0 (−1), bit 2 fair; correlated noise.
        let mut rng = Lcg(3);
        let samples: Vec<Vec<f32>> = (0..4000)
            .map(|_| {
                let g = rng.normal();
                vec![
                    (2.0 + g) as f32,
                    (-1.0 + 0.5 * g) as f32,
                    rng.normal() as f32,
                ]
            })
            .collect();
        let c = Whitening::centering(&samples).unwrap();
        assert!(c.is_centering());
        assert!(!Whitening::fit(&samples).unwrap().is_centering());
        assert!((c.mean[0] - 2.0).abs() < 0.06 && (c.mean[1] + 1.0).abs() < 0.03);
        let z = [5.0, 7.0, -3.0];
        let out = c.apply_row(&z);
        for i in 0..3 {
            assert!((out[i] - (z[i] - c.mean[i])).abs() < 1e-6);
        }
        // The share of ones per bit becomes about one half.
        for i in 0..2 {
            let ones = samples.iter().filter(|s| c.apply_row(s)[i] > 0.0).count() as f64
                / samples.len() as f64;
            assert!((ones - 0.5).abs() < 0.05, "bit {i}: {ones}");
        }
        assert_eq!(
            Whitening::centering(&[vec![1.0]]),
            Err(WhiteningError::TooFewSamples(1))
        );
    }
}
