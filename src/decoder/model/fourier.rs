//! The colour-Fourier decoder's pooled features and their gradient on the host, fused: chunks
//! of a band's pixels (in parallel) are swept feature by feature, each feature's sin (forward)
//! or sin and cos (backward) from a vectorised polynomial ([`sin_cos`]; AVX2 where the CPU
//! has it, the same bits either way), and nothing of size features × pixels is ever stored.
//!
//! The same function as [`HiddenDecoder::pooled_band`](super::HiddenDecoder::pooled_band) on
//! burn (f_j = Σ_p sin(ω_j·x_p + β_j)·w_p / n / (Σ_p w_p / n + 1e-6), x = gain·u, w_p the dark
//! weight 1 − exp(−r_p²), r_p = |x_p + 1|²/τ², or 1 without it), whose CPU backend forms the
//! `[B, F, h, w]` projections, their sines and, backward, their cosines as separate tensors with
//! a scalar libm call per element. A CPU finetuning step reads its decoder through this
//! ([`crate::embed::finetune`]): the features forward, then, from burn's ∂L/∂features,
//! ∂L/∂band in closed form, handed back to burn for the DWT and the attacks.

use burn::tensor::{Gradients, Tensor, TensorData};
use rayon::prelude::*;

/// Pixels a parallel task takes; partial sums are added in this fixed order, so results do
/// not depend on the number of threads.
const CHUNK: usize = 1024;

/// The colour-Fourier projection of a decoder, read once from its weights
/// ([`HiddenDecoder::fourier_host`](super::HiddenDecoder::fourier_host)).
#[derive(Clone, Debug)]
pub struct FourierHost {
    /// ω_j per colour channel, structure of arrays.
    omega: [Vec<f32>; 3],
    beta: Vec<f32>,
    gain: f32,
    /// τ² of the dark weight, or `None` without it.
    tau2: Option<f32>,
}

/// A forward pass's results that its backward reuses.
#[derive(Clone, Debug)]
pub struct FourierPass {
    /// Pooled features `[B, F]`, row-major.
    pub pooled: Vec<f32>,
    /// Per image: the dark weight's mean + 1e-6 (1 without it).
    den: Vec<f64>,
    h: usize,
    w: usize,
}

impl FourierHost {
    pub(super) fn new(omega: &[f32], beta: &[f32], gain: f64, dark: f64) -> Self {
        let f = beta.len();
        assert_eq!(omega.len(), 3 * f, "ω is F × 3");
        Self {
            omega: std::array::from_fn(|ch| (0..f).map(|j| omega[3 * j + ch]).collect()),
            beta: beta.to_vec(),
            gain: gain as f32,
            tau2: (dark > 0.0).then(|| (2.0 * dark).powi(2) as f32),
        }
    }

    /// Number of features F.
    pub fn features(&self) -> usize {
        self.beta.len()
    }

    /// A chunk of pixels `range` of a planar `[3, n]` band: x = gain·u per channel, the dark
    /// weight w and ∂w/∂x per channel.
    fn chunk(&self, img: &[f32], n: usize, range: std::ops::Range<usize>) -> Chunk {
        let x: [Vec<f32>; 3] = std::array::from_fn(|ch| {
            img[ch * n + range.start..ch * n + range.end]
                .iter()
                .map(|v| self.gain * v)
                .collect()
        });
        let m = range.len();
        let (mut w, mut dw) = (
            vec![1.0f32; m],
            [vec![0.0f32; m], vec![0.0; m], vec![0.0; m]],
        );
        if let Some(tau2) = self.tau2 {
            for p in 0..m {
                let v = [x[0][p] + 1.0, x[1][p] + 1.0, x[2][p] + 1.0];
                let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) / tau2;
                let e = (-r * r).exp();
                w[p] = 1.0 - e;
                for ch in 0..3 {
                    dw[ch][p] = e * 2.0 * r * 2.0 * v[ch] / tau2;
                }
            }
        }
        Chunk { x, w, dw }
    }

    /// Pooled features of bands `[B, 3, h, w]` (planar, as burn holds them).
    ///
    /// # Panics
    /// If `band` is not a whole number of `3·h·w` images.
    pub fn forward(&self, band: &[f32], h: usize, w: usize) -> FourierPass {
        let n = h * w;
        assert!(
            n > 0 && band.len().is_multiple_of(3 * n),
            "bands of 3 × {h} × {w}"
        );
        let b = band.len() / (3 * n);
        let f = self.features();
        let chunks = n.div_ceil(CHUNK);
        // Per (image, chunk): Σ_p sin·w per feature, then Σ_p w.
        let partial: Vec<(Vec<f32>, f64)> = (0..b * chunks)
            .into_par_iter()
            .map(|t| {
                let (i, c) = (t / chunks, t % chunks);
                let img = &band[i * 3 * n..(i + 1) * 3 * n];
                let px = self.chunk(img, n, c * CHUNK..((c + 1) * CHUNK).min(n));
                let acc = (0..f)
                    .map(|j| {
                        let o = [self.omega[0][j], self.omega[1][j], self.omega[2][j]];
                        sin_weighted_sum(&px, o, self.beta[j])
                    })
                    .collect();
                (acc, px.w.iter().map(|&v| f64::from(v)).sum())
            })
            .collect();
        let mut pooled = vec![0.0f32; b * f];
        let mut den = Vec::with_capacity(b);
        for i in 0..b {
            let mut sums = vec![0.0f64; f];
            let mut wsum = 0.0f64;
            for (acc, ws) in &partial[i * chunks..(i + 1) * chunks] {
                for (s, a) in sums.iter_mut().zip(acc) {
                    *s += f64::from(*a);
                }
                wsum += ws;
            }
            let d = if self.tau2.is_some() {
                wsum / n as f64 + 1e-6
            } else {
                1.0
            };
            for (o, s) in pooled[i * f..(i + 1) * f].iter_mut().zip(&sums) {
                *o = (s / n as f64 / d) as f32;
            }
            den.push(d);
        }
        FourierPass { pooled, den, h, w }
    }

    /// ∂L/∂band `[B, 3, h, w]` (planar) of the bands `pass` came from, given ∂L/∂features
    /// `grad` `[B, F]`: gain·(w_p·Σ_j g_j ω_j c_jp + ∂w_p/∂x·(Σ_j g_j s_jp − Σ_j g_j f_j)) /
    /// (n·den), s and c the sine and cosine of pixel p's projection on feature j.
    ///
    /// # Panics
    /// If the sizes do not match the forward pass.
    pub fn backward(&self, band: &[f32], pass: &FourierPass, grad: &[f32]) -> Vec<f32> {
        let n = pass.h * pass.w;
        let f = self.features();
        let b = pass.den.len();
        assert_eq!(band.len(), b * 3 * n, "the forward's bands");
        assert_eq!(grad.len(), b * f, "one gradient per feature and image");
        let chunks = n.div_ceil(CHUNK);
        let mut out = vec![0.0f32; band.len()];
        let parts: Vec<(usize, usize, [Vec<f32>; 3])> = (0..b * chunks)
            .into_par_iter()
            .map(|t| {
                let (i, c) = (t / chunks, t % chunks);
                let img = &band[i * 3 * n..(i + 1) * 3 * n];
                let g = &grad[i * f..(i + 1) * f];
                let k: f32 = g
                    .iter()
                    .zip(&pass.pooled[i * f..(i + 1) * f])
                    .map(|(a, p)| f64::from(*a) * f64::from(*p))
                    .sum::<f64>() as f32;
                let scale = (f64::from(self.gain) / (n as f64 * pass.den[i])) as f32;
                let range = c * CHUNK..((c + 1) * CHUNK).min(n);
                let px = self.chunk(img, n, range.clone());
                // Σ_j g_j ω_j,ch c_jp per channel and Σ_j g_j s_jp, feature by feature.
                let m = range.len();
                let mut a: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0.0f32; m]);
                let mut s_sum = vec![0.0f32; m];
                for (j, &gj) in g.iter().enumerate() {
                    let o = [self.omega[0][j], self.omega[1][j], self.omega[2][j]];
                    let coef = Coefficients {
                        omega: o,
                        beta: self.beta[j],
                        g_omega: o.map(|v| gj * v),
                        g: gj,
                    };
                    sin_cos_accumulate(&px, coef, &mut a, &mut s_sum);
                }
                let d: [Vec<f32>; 3] = std::array::from_fn(|ch| {
                    (0..m)
                        .map(|p| (px.w[p] * a[ch][p] + px.dw[ch][p] * (s_sum[p] - k)) * scale)
                        .collect()
                });
                (i, range.start, d)
            })
            .collect();
        for (i, p0, d) in parts {
            let img = &mut out[i * 3 * n..(i + 1) * 3 * n];
            for (ch, plane) in d.iter().enumerate() {
                img[ch * n + p0..ch * n + p0 + plane.len()].copy_from_slice(plane);
            }
        }
        out
    }
}

/// A chunk of a band's pixels, planar: x = gain·u, the dark weight w and ∂w/∂x.
struct Chunk {
    x: [Vec<f32>; 3],
    w: Vec<f32>,
    dw: [Vec<f32>; 3],
}

/// Σ_p sin(ω·x_p + β)·w_p over a chunk, in eight lanes (vectorised; the same order on every
/// machine).
fn sin_weighted_sum(px: &Chunk, o: [f32; 3], beta: f32) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        return unsafe { sin_weighted_sum_avx2(px, o, beta) };
    }
    sin_weighted_sum_body(px, o, beta)
}

/// [`sin_weighted_sum`] compiled for AVX2 (the same operations, so the same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn sin_weighted_sum_avx2(px: &Chunk, o: [f32; 3], beta: f32) -> f32 {
    sin_weighted_sum_body(px, o, beta)
}

#[inline(always)]
fn sin_weighted_sum_body(px: &Chunk, o: [f32; 3], beta: f32) -> f32 {
    const L: usize = 8;
    let mut lanes = [0.0f32; L];
    let [x0, x1, x2] = &px.x;
    for (((a, b), c), w) in x0
        .chunks_exact(L)
        .zip(x1.chunks_exact(L))
        .zip(x2.chunks_exact(L))
        .zip(px.w.chunks_exact(L))
    {
        for l in 0..L {
            let z = o[0] * a[l] + o[1] * b[l] + o[2] * c[l] + beta;
            lanes[l] += sin_cos(z).0 * w[l];
        }
    }
    let whole = px.w.len() / L * L;
    for p in whole..px.w.len() {
        let z = o[0] * x0[p] + o[1] * x1[p] + o[2] * x2[p] + beta;
        lanes[0] += sin_cos(z).0 * px.w[p];
    }
    lanes.iter().sum()
}

/// a_ch[p] += go_ch·cos(z_p), s[p] += g·sin(z_p), z_p = ω·x_p + β, over a chunk.
fn sin_cos_accumulate(px: &Chunk, coef: Coefficients, a: &mut [Vec<f32>; 3], s: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        return unsafe { sin_cos_accumulate_avx2(px, coef, a, s) };
    }
    sin_cos_accumulate_body(px, coef, a, s)
}

/// [`sin_cos_accumulate`] compiled for AVX2 (the same operations, so the same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn sin_cos_accumulate_avx2(px: &Chunk, coef: Coefficients, a: &mut [Vec<f32>; 3], s: &mut [f32]) {
    sin_cos_accumulate_body(px, coef, a, s)
}

/// One feature's numbers in the backward: ω, β, g·ω and g.
#[derive(Clone, Copy)]
struct Coefficients {
    omega: [f32; 3],
    beta: f32,
    g_omega: [f32; 3],
    g: f32,
}

#[inline(always)]
fn sin_cos_accumulate_body(px: &Chunk, k: Coefficients, a: &mut [Vec<f32>; 3], s: &mut [f32]) {
    let m = s.len();
    let (x0, x1, x2) = (&px.x[0][..m], &px.x[1][..m], &px.x[2][..m]);
    let [a0, a1, a2] = a;
    let (a0, a1, a2) = (&mut a0[..m], &mut a1[..m], &mut a2[..m]);
    let o = k.omega;
    for p in 0..m {
        let z = o[0] * x0[p] + o[1] * x1[p] + o[2] * x2[p] + k.beta;
        let (sn, cs) = sin_cos(z);
        a0[p] += k.g_omega[0] * cs;
        a1[p] += k.g_omega[1] * cs;
        a2[p] += k.g_omega[2] * cs;
        s[p] += k.g * sn;
    }
}

/// Pooled features the host computed for a band burn differentiates
/// ([`FourierHost::features_of`]): a leaf tensor stands in for them in burn's graph, and once
/// burn has filled the leaf's gradient, [`surrogate`](Self::surrogate) carries it on into the
/// band's own graph (the DWT, the attacks, the image).
pub struct HostFeatures {
    band: Tensor<4>,
    values: Vec<f32>,
    pass: FourierPass,
    leaf: Tensor<2>,
}

impl FourierHost {
    /// The pooled features `[B, F]` of a centred band `[B, 3, h, w]` on an autodiff device, as
    /// a leaf tensor that needs a gradient ([`HostFeatures::leaf`]).
    pub fn features_of(&self, band: Tensor<4>) -> HostFeatures {
        let [b, _, h, w] = band.dims();
        let values: Vec<f32> = band
            .clone()
            .detach()
            .try_into_vec_as::<f32>()
            .expect("a band on the host");
        let pass = self.forward(&values, h, w);
        let leaf = Tensor::<2>::from_data(
            TensorData::new(pass.pooled.clone(), [b, self.features()]),
            &band.device(),
        )
        .require_grad();
        HostFeatures {
            band,
            values,
            pass,
            leaf,
        }
    }
}

impl HostFeatures {
    /// The features as burn sees them.
    pub fn leaf(&self) -> Tensor<2> {
        self.leaf.clone()
    }

    /// Σ band ⊙ ∂L/∂band, ∂L/∂band from the leaf's gradient in `grads` ([`FourierHost::backward`]):
    /// its backward gives the band's graph the gradient burn's own decoder would have. `None`
    /// when `grads` has no gradient for the leaf.
    pub fn surrogate(&self, host: &FourierHost, grads: &Gradients) -> Option<Tensor<1>> {
        let g: Vec<f32> = self.leaf.grad(grads)?.try_into_vec_as::<f32>().ok()?;
        let d = host.backward(&self.values, &self.pass, &g);
        let dims = self.band.dims();
        let d = Tensor::<4>::from_data(TensorData::new(d, dims), &self.band.device()).detach();
        Some(self.band.clone().mul(d).sum())
    }
}

/// sin and cos of an f32 (|x| ≲ 10⁴; relative error ≈ 1e-7 of the result there): Cody–Waite
/// reduction by π/2 in three parts, then Cephes' minimax polynomials on [−π/4, π/4]. Written
/// without branches or calls so that loops over it vectorise.
#[inline(always)]
pub fn sin_cos(x: f32) -> (f32, f32) {
    const FRAC_2_PI: f32 = std::f32::consts::FRAC_2_PI;
    // π/2 = P1 + P2 + P3, P1 and P2 with few enough bits that q·P is exact.
    const P1: f32 = 1.570_312_5;
    const P2: f32 = 4.837_513e-4;
    const P3: f32 = 7.549_79e-8;
    // Round to nearest by the 1.5·2²³ trick (no libm call): the sum's low mantissa bits are
    // the quadrant q itself, read as an integer without a (saturating, scalar) float → int
    // conversion.
    const MAGIC: f32 = 12_582_912.0;
    let y = x * FRAC_2_PI + MAGIC;
    let q = y - MAGIC;
    let qi = (y.to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32);
    let r = ((x - q * P1) - q * P2) - q * P3;
    let r2 = r * r;
    let s = r + r * r2 * (-1.666_665_5e-1 + r2 * (8.332_161e-3 + r2 * -1.951_529_6e-4));
    let c =
        1.0 - 0.5 * r2 + r2 * r2 * (4.166_664_6e-2 + r2 * (-1.388_731_6e-3 + r2 * 2.443_315_7e-5));
    let odd = (qi & 1) as f32;
    let (sr, cr) = (s + odd * (c - s), c + odd * (s - c));
    let sign_s = 1.0 - (qi & 2) as f32;
    let sign_c = 1.0 - ((qi + 1) & 2) as f32;
    (sign_s * sr, sign_c * cr)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sin_cos_agrees_with_the_standard_library_over_the_features_range() {
        let mut worst = 0.0f64;
        for i in -200_000..=200_000 {
            let x = i as f32 * 1e-3 * 1.7; // ±340
            let (s, c) = sin_cos(x);
            let (es, ec) = f64::from(x).sin_cos();
            worst = worst
                .max((f64::from(s) - es).abs())
                .max((f64::from(c) - ec).abs());
        }
        // f32's own rounding of x·2/π and of the reduced argument: a few 1e-6 at |x| ≈ 300.
        assert!(worst < 1e-5, "worst error {worst}");
        let (s, c) = sin_cos(0.0);
        assert_eq!((s, c), (0.0, 1.0));
    }
}
