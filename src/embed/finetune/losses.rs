//! The image side of the losses: tensors from renders, SSIM, DWT band L1, 8-bit quantisation.

use burn::tensor::{Device, Tensor, TensorData};

use super::LossWeights;
use crate::attack::diff::{gaussian_blur, straight_through_round};
use crate::decoder::dwt::{dwt, ll_band};
use crate::decoder::train::bce_with_logits;

/// The watermark loss of a step's views (`[1, L]` logits each): the BCE of their average (eq.
/// `avglogits`), or, `per_view`, the average of each view's own BCE — which a view that decodes
/// wrong cannot hide behind views that decode right.
///
/// With a [`Margin`] `(M, β)` each logit z of a bit with sign m = ±1 pays
/// softplus(β·(M − m·z)) / β instead of BCE = softplus(−m·z): a bit past the margin costs
/// (almost) nothing, so the fidelity budget goes to the bits and views still short of it.
/// (M, β) = (0, 1) is the BCE.
///
/// # Panics
/// If `views` is empty.
pub(super) fn views_bce(
    views: &[Tensor<2>],
    bits: &Tensor<2>,
    per_view: bool,
    margin: Margin,
) -> Tensor<1> {
    let n = views.len() as f64;
    assert!(!views.is_empty(), "a step has views");
    let loss = |z: Tensor<2>| -> Tensor<1> {
        if margin.is_bce() {
            return bce_with_logits(z, bits.clone());
        }
        // z' = β·(z − M·m), m = 2b − 1: BCE(z', b) / β = softplus(β(M − m·z)) / β.
        let m = bits.clone().mul_scalar(2.0).sub_scalar(1.0);
        let shifted = z
            .sub(m.mul_scalar(margin.margin))
            .mul_scalar(margin.sharpness);
        bce_with_logits(shifted, bits.clone()).div_scalar(margin.sharpness)
    };
    if per_view {
        views
            .iter()
            .map(|z| loss(z.clone()))
            .reduce(|a, b| a.add(b))
            .expect("views")
            .div_scalar(n)
    } else {
        let mean = views
            .iter()
            .cloned()
            .reduce(|a, b| a.add(b))
            .expect("views")
            .div_scalar(n);
        loss(mean)
    }
}

/// The margin of the watermark loss ([`views_bce`]): `margin` M in logits, `sharpness` β.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Margin {
    pub margin: f32,
    pub sharpness: f32,
}

impl Margin {
    pub(super) const BCE: Self = Self {
        margin: 0.0,
        sharpness: 1.0,
    };

    fn is_bce(self) -> bool {
        self == Self::BCE
    }
}

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
    if low {
        // The LL band alone, without forming the detail bands (the same values).
        return ll_band(x, levels).sub(ll_band(y, levels)).abs().mean();
    }
    let (dx, dy) = (dwt(x, levels), dwt(y, levels));
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

/// L_vis of a render `y` against its target `t` (both `[1, 3, H, W]`) on burn: λ_rec·mean|ŷ −
/// t| + λ_dssim·(1 − SSIM(ŷ, t)) + λ_high·(high bands' L1), ŷ = clamp(y, 0, 1) — the loss
/// [`super::visual::visual_loss`] computes in closed form on the host (the tests hold the two
/// to each other); a GPU job takes this one, on the device its renders are on.
pub(super) fn visual_loss_tensor(
    y: Tensor<4>,
    t: Tensor<4>,
    weights: &LossWeights,
    levels: usize,
) -> Tensor<1> {
    let yc = y.clamp(0.0, 1.0);
    let mut l = yc
        .clone()
        .sub(t.clone())
        .abs()
        .mean()
        .mul_scalar(weights.rec)
        .add(
            ssim(yc.clone(), t.clone())
                .neg()
                .add_scalar(1.0)
                .mul_scalar(weights.dssim),
        );
    if levels > 0 {
        l = l.add(band_l1(yc, t, levels, false).mul_scalar(weights.wav_high));
    }
    l
}

/// The image the decoder sees of a render: clamped to [0, 1] and rounded to 8 bits
/// (straight-through), as a saved PNG would be.
pub(super) fn as_saved(x: Tensor<4>) -> Tensor<4> {
    straight_through_round(x.clamp(0.0, 1.0).mul_scalar(255.0)).div_scalar(255.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: &[f32], device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.to_vec(), [1, v.len()]), device)
    }

    #[test]
    fn a_view_that_decodes_wrong_costs_the_per_view_loss_not_the_averaged_one() {
        let device = Device::flex();
        let bits = t(&[1.0], &device);
        // Two views of bit 1: one confidently right (+3), one wrong (−1). Their average (+1)
        // decodes right, so the averaged BCE is small; the per-view BCE keeps the wrong view.
        let views = [t(&[3.0], &device), t(&[-1.0], &device)];
        let avg = views_bce(&views, &bits, false, Margin::BCE).into_scalar::<f32>();
        let per = views_bce(&views, &bits, true, Margin::BCE).into_scalar::<f32>();
        let softplus = |x: f32| (1.0 + x.exp()).ln();
        assert!((avg - softplus(-1.0)).abs() < 1e-5, "{avg}");
        assert!(
            (per - 0.5 * (softplus(-3.0) + softplus(1.0))).abs() < 1e-5,
            "{per}"
        );
        assert!(per > 2.0 * avg);
        // One view: the same loss either way.
        let one = [t(&[0.4], &device)];
        let (a, b) = (
            views_bce(&one, &bits, false, Margin::BCE).into_scalar::<f32>(),
            views_bce(&one, &bits, true, Margin::BCE).into_scalar::<f32>(),
        );
        assert!((a - b).abs() < 1e-6);
    }

    #[test]
    fn a_bit_past_the_margin_costs_nothing_and_one_short_of_it_costs_its_shortfall() {
        let device = Device::flex();
        // Bits 1 and 0; logits that decode both right, the first far past the margin.
        let bits = t(&[1.0, 0.0], &device);
        let m = Margin {
            margin: 2.0,
            sharpness: 8.0,
        };
        let far = views_bce(&[t(&[6.0, -6.0], &device)], &bits, true, m).into_scalar::<f32>();
        assert!(far < 1e-6, "{far}");
        // Right but short of the margin by 1.5 on the 0 bit: ≈ 1.5 / 2 (the mean over bits).
        let short = views_bce(&[t(&[6.0, -0.5], &device)], &bits, true, m).into_scalar::<f32>();
        assert!((short - 0.75).abs() < 0.01, "{short}");
        // Negative logits of a 0 bit count as right, as the BCE's do.
        let wrong = views_bce(&[t(&[6.0, 0.5], &device)], &bits, true, m).into_scalar::<f32>();
        assert!(wrong > short);
        // (0, 1) is exactly the BCE.
        let z = [t(&[0.3, 0.7], &device)];
        let a = views_bce(&z, &bits, true, Margin::BCE).into_scalar::<f32>();
        let b = views_bce(
            &z,
            &bits,
            true,
            Margin {
                margin: 0.0,
                sharpness: 1.0 + 1e-7,
            },
        )
        .into_scalar::<f32>();
        assert!((a - b).abs() < 1e-5, "{a} vs {b}");
    }
}
