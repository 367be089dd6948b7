//! The pixel-value attacks: Gaussian noise, Gaussian blur and contrast.

use burn::tensor::module::conv2d;
use burn::tensor::ops::{ConvOptions, PadMode};
use burn::tensor::{Tensor, TensorData};

use super::EotRng;

pub(super) fn noise(x: Tensor<4>, sigma: f32, seed: u64) -> Tensor<4> {
    if sigma == 0.0 {
        return x;
    }
    let dims = x.dims();
    let n: usize = dims.iter().product();
    let mut rng = EotRng::new(seed);
    let mut data = Vec::with_capacity(n + 1);
    while data.len() < n {
        let (a, b) = rng.normal_pair();
        data.push(a as f32);
        data.push(b as f32);
    }
    data.truncate(n);
    let std = f64::from(sigma) * f64::from(sigma);
    let noise = Tensor::<4>::from_data(TensorData::new(data, dims), &x.device());
    x.add(noise.mul_scalar(std))
}

/// Normalised 1D Gaussian kernel sampled at integer offsets −k/2..=k/2 (torchvision's).
pub(crate) fn gaussian_kernel(sigma: f32, kernel: u32) -> Vec<f32> {
    let half = i64::from(kernel / 2);
    let sigma = f64::from(sigma);
    let weights: Vec<f64> = (-half..=half)
        .map(|d| (-0.5 * (d as f64 / sigma).powi(2)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.iter().map(|v| (v / total) as f32).collect()
}

/// Separable Gaussian blur (σ in pixels, odd kernel), reflect padding; same size out.
pub fn gaussian_blur(x: Tensor<4>, sigma: f32, kernel: u32) -> Tensor<4> {
    if kernel == 1 {
        return x;
    }
    let [_, c, h, w] = x.dims();
    let k = kernel as usize;
    let half = k / 2;
    let device = x.device();
    let weights = gaussian_kernel(sigma, kernel);
    let mode_for = |len: usize| {
        if half < len {
            PadMode::Reflect
        } else {
            PadMode::Edge
        }
    };
    let depthwise = ConvOptions::new([1, 1], [0, 0], [1, 1], c);
    // Horizontal pass: weight [C, 1, 1, k]; then vertical: [C, 1, k, 1].
    let row: Vec<f32> = (0..c).flat_map(|_| weights.iter().copied()).collect();
    let wx = Tensor::<4>::from_data(TensorData::new(row.clone(), [c, 1, 1, k]), &device);
    let wy = Tensor::<4>::from_data(TensorData::new(row, [c, 1, k, 1]), &device);
    let x = x.pad([(0, 0), (half, half)], mode_for(w));
    let x = conv2d(x, wx, None, depthwise.clone());
    let x = x.pad([(half, half), (0, 0)], mode_for(h));
    conv2d(x, wy, None, depthwise)
}

pub(super) fn contrast(x: Tensor<4>, factor: f32) -> Tensor<4> {
    if factor == 1.0 {
        return x;
    }
    let [b, _, _, _] = x.dims();
    let luma_w = Tensor::<4>::from_data(
        TensorData::new(vec![0.2989f32, 0.587, 0.114], [1, 3, 1, 1]),
        &x.device(),
    );
    let mean = x
        .clone()
        .mul(luma_w)
        .sum_dim(1)
        .mean_dim(2)
        .mean_dim(3)
        .reshape([b, 1, 1, 1]);
    x.mul_scalar(factor)
        .add(mean.mul_scalar(1.0 - factor))
        .clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attack::diff::DiffAttack;
    use crate::attack::diff::tests::{device, max_abs_diff, smooth, to_vec};

    #[test]
    fn noise_has_the_squared_sigma_and_is_reproducible() {
        let x = Tensor::<4>::full([1, 3, 64, 64], 0.5, &device());
        let a = DiffAttack::Noise {
            sigma: 0.1,
            seed: 42,
        };
        let y = to_vec(a.apply(x.clone()).unwrap());
        let n = y.len() as f64;
        let var = y.iter().map(|v| (*v as f64 - 0.5).powi(2)).sum::<f64>() / n;
        assert!((var.sqrt() - 0.01).abs() < 0.0005, "std {}", var.sqrt());
        assert_eq!(y, to_vec(a.apply(x).unwrap()));
    }

    #[test]
    fn blur_keeps_constants_and_smooths() {
        let c = Tensor::<4>::full([1, 3, 9, 17], 0.3, &device());
        let b = DiffAttack::Blur {
            sigma: 2.0,
            kernel: 7,
        };
        assert!(max_abs_diff(b.apply(c.clone()).unwrap(), c).abs() < 1e-6);
        // Tiny image (smaller than the kernel radius): edge padding, still the right shape.
        let t = smooth(1, 2, 3);
        assert_eq!(b.apply(t).unwrap().dims(), [1, 3, 2, 3]);
    }
}
