//! The image side of the losses: tensors from renders, SSIM, DWT band L1, 8-bit quantisation.

use burn::tensor::{Device, Tensor, TensorData};

use crate::attack::diff::{gaussian_blur, straight_through_round};
use crate::decoder::dwt::dwt;

/// Row-major RGB → planar `[1, 3, H, W]` tensor.
pub(super) fn to_tensor(pixels: &[[f32; 3]], w: usize, h: usize, device: &Device) -> Tensor<4> {
    let n = w * h;
    let mut data = vec![0.0f32; 3 * n];
    for (i, p) in pixels.iter().enumerate() {
        for c in 0..3 {
            data[c * n + i] = p[c];
        }
    }
    Tensor::from_data(TensorData::new(data, [1, 3, h, w]), device)
}

/// Planar `[1, 3, H, W]` values → row-major RGB.
pub(super) fn from_planar(data: &[f32], n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|i| [data[i], data[n + i], data[2 * n + i]])
        .collect()
}

/// Mean SSIM (11×11 Gaussian window, σ 1.5, C₁ = 0.01², C₂ = 0.03²) of images in [0, 1].
pub fn ssim(x: Tensor<4>, y: Tensor<4>) -> Tensor<1> {
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let win = |t: Tensor<4>| gaussian_blur(t, 1.5, 11);
    let mx = win(x.clone());
    let my = win(y.clone());
    let sxx = win(x.clone().square()).sub(mx.clone().square());
    let syy = win(y.clone().square()).sub(my.clone().square());
    let sxy = win(x.mul(y)).sub(mx.clone().mul(my.clone()));
    let num = mx
        .clone()
        .mul(my.clone())
        .mul_scalar(2.0)
        .add_scalar(c1)
        .mul(sxy.mul_scalar(2.0).add_scalar(c2));
    let den = mx
        .square()
        .add(my.square())
        .add_scalar(c1)
        .mul(sxx.add(syy).add_scalar(c2));
    num.div(den).mean()
}

/// L1 distance of the LL bands (`low`) or of every high band of every level (`!low`).
pub(super) fn band_l1(x: Tensor<4>, y: Tensor<4>, levels: usize, low: bool) -> Tensor<1> {
    let (dx, dy) = (dwt(x, levels), dwt(y, levels));
    if low {
        return dx.ll.sub(dy.ll).abs().mean();
    }
    let mut total: Option<Tensor<1>> = None;
    for (a, b) in dx.highs.into_iter().zip(dy.highs) {
        for (p, q) in a.into_iter().zip(b) {
            let l = p.sub(q).abs().mean();
            total = Some(match total {
                Some(t) => t.add(l),
                None => l,
            });
        }
    }
    total.expect("at least one level")
}

/// The image the decoder sees of a render: clamped to [0, 1] and rounded to 8 bits
/// (straight-through), as a saved PNG would be.
pub(super) fn as_saved(x: Tensor<4>) -> Tensor<4> {
    straight_through_round(x.clamp(0.0, 1.0).mul_scalar(255.0)).div_scalar(255.0)
}
