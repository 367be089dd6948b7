//! Multi-level 2D Haar discrete wavelet transform on burn tensors `[B, C, H, W]`, differentiable
//! (plain reshapes, slices and arithmetic, so autodiff handles it like any other op).
//!
//! # Convention
//!
//! One level maps each 2×2 block `[[a, b], [c, d]]` (a top-left, b top-right, c bottom-left,
//! d bottom-right) to four coefficients, with the **orthonormal** Haar filters (1/√2 per 1D
//! pass, so 1/2 per 2D level):
//!
//! | band | value | what it sees | `pywt.dwt2(x, 'haar')` |
//! |---|---|---|---|
//! | LL | (a + b + c + d) / 2 | block mean × 2 | cA |
//! | LH | (a + b − c − d) / 2 | horizontal edges (high-pass down the rows) | cH |
//! | HL | (a − b + c − d) / 2 | vertical edges (high-pass along a row) | cV |
//! | HH | (a − b − c + d) / 2 | diagonal detail | cD |
//!
//! (the values and signs are those of `pywt.dwt2(x, 'haar')`, whose detail filter gives
//! (x₀ − x₁)/√2). Level k+1 transforms the LL band of level k. After `levels` levels, LL of a
//! constant image c is 2^levels · c: the transform is orthonormal, so `Σx² = ΣLL² + Σ highs²`
//! (Parseval) and the inverse is the transpose.
//!
//! # Sizes not divisible by 2^levels
//!
//! The input is padded once, at the bottom and right, to the next multiple of 2^levels by
//! **replicating the edge pixels** ([`PadMode::Edge`]); [`idwt`] crops back to the original size,
//! so `idwt(dwt(x)) == x` for every size. Why edge padding rather than cropping: a crop would drop
//! up to 2^levels − 1 border rows/columns from every band, so those pixels would get no gradient
//! from the watermark loss (which reads LL) nor from the high-band fidelity loss, and the
//! transform would no longer be invertible on its own. Edge replication keeps every pixel in the
//! bands, adds no artificial edge (so no spurious high-band energy at the border, unlike zero
//! padding) and, unlike reflect padding, works for any size ≥ 1. The price: on padded inputs the
//! transform is no longer exactly energy-preserving (the replicated pixels count twice) and the
//! gradient of a border pixel includes its copies. Renders of 3D-GS scenes used for training are
//! normally multiples of 4 (800×800 Blender, 1008×756 LLFF) and are not padded at all.
//!
//! # Why Haar (and what the baselines use)
//!
//! The baselines' public code does **not** use Haar: 3D-GSW (`kuai-lab/cvpr25_3D-GSW`,
//! `finetuning_gaussian.py`) calls `pytorch_wavelets.DWTForward(wave='bior4.4', J=2,
//! mode='periodization')` on the render in [0, 1] and feeds the LL band straight to its HiDDeN
//! decoder; WateRF (`kuai-lab/cvpr2024_WateRF`, `opt.py`) has the same defaults (`--dwt_wave
//! bior4.4 --dwt_level 2 --dwt_mode periodization`). Their decoders were trained for that
//! transform; ours is trained by us for this one, so the choice is ours. Haar, because:
//! - it is **exact**: no boundary extension (bior4.4 has 9/7-tap filters and needs periodisation
//!   or symmetric extension, which wraps the right edge into the left), and perfect
//!   reconstruction holds to float rounding;
//! - it is **cheap**: one level is two adds and a scale per pixel, no convolutions, so it costs
//!   nothing next to the decoder, forward or backward;
//! - it is **orthonormal** (bior4.4 is only biorthogonal): band energies add up to the image
//!   energy, so an L1/L2 penalty on LL or on the high bands has the same scale as the same
//!   penalty on pixels, and the loss weights λ_wav^low / λ_wav^high mean the same thing at every
//!   level and image size.
//!
//! Both transforms have a low-pass DC gain of √2 per 1D pass, so the LL band of a 2-level
//! transform is 4× the local image mean in either case; the baselines' LL is a smoother
//! (wider-support) local mean than Haar's 4×4 block mean.

use burn::tensor::Tensor;
use burn::tensor::ops::PadMode;

/// The result of [`dwt`]: the coarsest low-pass band and the detail bands of every level.
#[derive(Debug, Clone)]
pub struct Dwt {
    /// LL band after the last level: `[B, C, H'/2^levels, W'/2^levels]`, where H', W' are the
    /// input size rounded up to a multiple of 2^levels.
    pub ll: Tensor<4>,
    /// Detail bands `[LH, HL, HH]` of each level, finest first: `highs[0]` is level 1 (half the
    /// padded input size), `highs[levels − 1]` the coarsest, as `pytorch_wavelets`' `yh` list.
    pub highs: Vec<[Tensor<4>; 3]>,
    /// Input height and width before padding; [`idwt`] crops its output to this size.
    pub input_size: [usize; 2],
}

impl Dwt {
    /// Number of levels.
    pub fn levels(&self) -> usize {
        self.highs.len()
    }
}

/// `(H, W)` rounded up to the next multiple of 2^levels: the size the input is padded to.
pub fn padded_size(height: usize, width: usize, levels: usize) -> [usize; 2] {
    let m = 1usize << levels;
    [height.div_ceil(m) * m, width.div_ceil(m) * m]
}

/// Spatial size `(H, W)` of the LL band of a `levels`-level transform of an `height × width`
/// input.
pub fn ll_size(height: usize, width: usize, levels: usize) -> [usize; 2] {
    let [h, w] = padded_size(height, width, levels);
    [h >> levels, w >> levels]
}

/// Forward transform: `levels` Haar levels of `x` (`[B, C, H, W]`, any H, W ≥ 1), padding
/// bottom/right by edge replication to a multiple of 2^levels first (see the module docs).
/// `levels = 0` returns `x` as LL with no detail bands.
pub fn dwt(x: Tensor<4>, levels: usize) -> Dwt {
    let [_, _, height, width] = x.dims();
    let [ph, pw] = padded_size(height, width, levels);
    let mut ll = if ph != height || pw != width {
        x.pad([(0, ph - height), (0, pw - width)], PadMode::Edge)
    } else {
        x
    };
    let mut highs = Vec::with_capacity(levels);
    for _ in 0..levels {
        let (next, bands) = haar_level(ll);
        ll = next;
        highs.push(bands);
    }
    Dwt {
        ll,
        highs,
        input_size: [height, width],
    }
}

/// Inverse of [`dwt`]: reconstructs the image from its bands and crops it to
/// [`Dwt::input_size`]. Bands may have been modified (that is what embedding in LL does).
pub fn idwt(d: Dwt) -> Tensor<4> {
    let Dwt {
        mut ll,
        highs,
        input_size: [height, width],
    } = d;
    for bands in highs.into_iter().rev() {
        ll = inverse_haar_level(ll, bands);
    }
    let [_, _, ph, pw] = ll.dims();
    if ph != height || pw != width {
        ll.narrow(2, 0, height).narrow(3, 0, width)
    } else {
        ll
    }
}

/// Only the LL band of a `levels`-level transform (what the decoder reads); same values as
/// `dwt(x, levels).ll`, computed without keeping the detail bands.
pub fn ll_band(x: Tensor<4>, levels: usize) -> Tensor<4> {
    let [_, _, height, width] = x.dims();
    let [ph, pw] = padded_size(height, width, levels);
    let mut ll = if ph != height || pw != width {
        x.pad([(0, ph - height), (0, pw - width)], PadMode::Edge)
    } else {
        x
    };
    for _ in 0..levels {
        let [b, c, h, w] = ll.dims();
        // Sum over each 2×2 block, times 1/2: the LL formula without forming the details.
        ll = ll
            .reshape([b, c, h / 2, 2, w / 2, 2])
            .sum_dim(5)
            .sum_dim(3)
            .reshape([b, c, h / 2, w / 2])
            .mul_scalar(0.5);
    }
    ll
}

/// One Haar level of `x` (`[B, C, H, W]`, H and W even): `(LL, [LH, HL, HH])`, each
/// `[B, C, H/2, W/2]`.
///
/// # Panics
/// If H or W is odd.
pub fn haar_level(x: Tensor<4>) -> (Tensor<4>, [Tensor<4>; 3]) {
    let [b, c, h, w] = x.dims();
    assert!(
        h % 2 == 0 && w % 2 == 0,
        "haar_level needs even sizes, got {h}×{w}"
    );
    let (h2, w2) = (h / 2, w / 2);
    // [B, C, H/2, 2 (row in block), W/2, 2 (column in block)]
    let x = x.reshape([b, c, h2, 2, w2, 2]);
    let top = x.clone().narrow(3, 0, 1); // a, b
    let bottom = x.narrow(3, 1, 1); // c, d
    let sum = top.clone().add(bottom.clone()); // a+c | b+d
    let diff = top.sub(bottom); // a−c | b−d
    let s0 = sum.clone().narrow(5, 0, 1);
    let s1 = sum.narrow(5, 1, 1);
    let d0 = diff.clone().narrow(5, 0, 1);
    let d1 = diff.narrow(5, 1, 1);
    let shape = [b, c, h2, w2];
    let ll = s0.clone().add(s1.clone()).mul_scalar(0.5).reshape(shape);
    let hl = s0.sub(s1).mul_scalar(0.5).reshape(shape);
    let lh = d0.clone().add(d1.clone()).mul_scalar(0.5).reshape(shape);
    let hh = d0.sub(d1).mul_scalar(0.5).reshape(shape);
    (ll, [lh, hl, hh])
}

/// Inverse of [`haar_level`]: the `[B, C, 2h, 2w]` image whose level is `ll` and `[lh, hl, hh]`
/// (all `[B, C, h, w]`).
///
/// # Panics
/// If the four bands do not have the same shape.
pub fn inverse_haar_level(ll: Tensor<4>, [lh, hl, hh]: [Tensor<4>; 3]) -> Tensor<4> {
    let shape = ll.dims();
    assert!(
        lh.dims() == shape && hl.dims() == shape && hh.dims() == shape,
        "inverse_haar_level: band shapes differ: LL {:?}, LH {:?}, HL {:?}, HH {:?}",
        shape,
        lh.dims(),
        hl.dims(),
        hh.dims()
    );
    let [b, c, h2, w2] = shape;
    let s0 = ll.clone().add(hl.clone()); // a + c
    let s1 = ll.sub(hl); // b + d
    let d0 = lh.clone().add(hh.clone()); // a − c
    let d1 = lh.sub(hh); // b − d
    let a = s0.clone().add(d0.clone()).mul_scalar(0.5);
    let c_ = s0.sub(d0).mul_scalar(0.5);
    let b_ = s1.clone().add(d1.clone()).mul_scalar(0.5);
    let d_ = s1.sub(d1).mul_scalar(0.5);
    let top: Tensor<5> = Tensor::stack(vec![a, b_], 4); // [B, C, h, w, 2]
    let bottom: Tensor<5> = Tensor::stack(vec![c_, d_], 4);
    let blocks: Tensor<6> = Tensor::stack(vec![top, bottom], 3); // [B, C, h, 2, w, 2]
    blocks.reshape([b, c, h2 * 2, w2 * 2])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn device() -> Device {
        Device::flex()
    }

    fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    /// Deterministic pseudo-random image in [0, 1].
    fn image(b: usize, c: usize, h: usize, w: usize, seed: u64) -> Tensor<4> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let data: Vec<f32> = (0..b * c * h * w)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 24) as f32
            })
            .collect();
        Tensor::from_data(TensorData::new(data, [b, c, h, w]), &device())
    }

    fn max_abs_diff(a: Tensor<4>, b: Tensor<4>) -> f32 {
        to_vec(a.sub(b).abs().max())[0]
    }

    fn energy(t: Tensor<4>) -> f64 {
        to_vec(t).iter().map(|&v| (v as f64) * (v as f64)).sum()
    }

    #[test]
    fn perfect_reconstruction_divisible_and_not() {
        for (h, w, levels) in [(16, 16, 2), (12, 20, 1), (13, 7, 2), (5, 9, 3), (1, 1, 2)] {
            let x = image(2, 3, h, w, (h * 31 + w) as u64);
            let d = dwt(x.clone(), levels);
            assert_eq!(d.levels(), levels);
            let [lh, lw] = ll_size(h, w, levels);
            assert_eq!(d.ll.dims(), [2, 3, lh, lw]);
            let y = idwt(d);
            assert_eq!(y.dims(), [2, 3, h, w]);
            let err = max_abs_diff(x, y);
            assert!(err < 1e-5, "{h}×{w}, {levels} levels: max err {err}");
        }
    }

    #[test]
    fn energy_is_preserved() {
        let x = image(1, 3, 16, 24, 7);
        let d = dwt(x.clone(), 2);
        let mut bands = energy(d.ll.clone());
        for level in &d.highs {
            for band in level {
                bands += energy(band.clone());
            }
        }
        let pixels = energy(x);
        assert!(
            ((bands - pixels) / pixels).abs() < 1e-5,
            "{bands} vs {pixels}"
        );
    }

    #[test]
    fn constant_image_ll_is_two_to_the_levels_times_c() {
        let c = 0.37f32;
        for levels in 1..=3 {
            let x = Tensor::<4>::full([1, 3, 16, 16], c, &device());
            let d = dwt(x, levels);
            let expected = (1u32 << levels) as f32 * c;
            for v in to_vec(d.ll) {
                assert!((v - expected).abs() < 1e-5, "{v} vs {expected}");
            }
            for level in d.highs {
                for band in level {
                    assert!(to_vec(band).iter().all(|v| v.abs() < 1e-6));
                }
            }
        }
    }

    #[test]
    fn known_values_on_a_4x4_example() {
        // x[i][j] = 4i + j.
        let x = Tensor::<4>::from_data(
            TensorData::new((0..16).map(|v| v as f32).collect::<Vec<_>>(), [1, 1, 4, 4]),
            &device(),
        );
        let (ll, [lh, hl, hh]) = haar_level(x.clone());
        // Block [[0, 1], [4, 5]]: LL = 10/2 = 5, LH = (0+1−4−5)/2 = −4, HL = (0−1+4−5)/2 = −1,
        // HH = (0−1−4+5)/2 = 0. Every block is that one plus 2j + 8i.
        assert_eq!(to_vec(ll), vec![5.0, 9.0, 21.0, 25.0]);
        assert_eq!(to_vec(lh), vec![-4.0; 4]);
        assert_eq!(to_vec(hl), vec![-1.0; 4]);
        assert_eq!(to_vec(hh), vec![0.0; 4]);
        // Level 2 on [[5, 9], [21, 25]]: LL = 60/2 = 30, LH = (5+9−21−25)/2 = −16,
        // HL = (5−9+21−25)/2 = −4, HH = 0. LL = 2² × mean(x) = 4 × 7.5.
        let d = dwt(x, 2);
        assert_eq!(to_vec(d.ll), vec![30.0]);
        assert_eq!(to_vec(d.highs[1][0].clone()), vec![-16.0]);
        assert_eq!(to_vec(d.highs[1][1].clone()), vec![-4.0]);
        assert_eq!(to_vec(d.highs[1][2].clone()), vec![0.0]);
    }

    #[test]
    fn ll_band_matches_dwt() {
        let x = image(2, 3, 10, 14, 3);
        let a = ll_band(x.clone(), 2);
        let b = dwt(x, 2).ll;
        assert!(max_abs_diff(a, b) < 1e-6);
    }

    #[test]
    fn gradient_of_sum_ll_is_one_over_two_to_the_levels() {
        // Each level-L LL coefficient is Σ(its 2^L × 2^L pixels) / 2^L, and every pixel lies in
        // exactly one block, so ∂ΣLL/∂x = 1/2^L everywhere (0.25 for 2 levels).
        for levels in 1..=3 {
            let x = image(1, 3, 16, 16, 11).autodiff().require_grad();
            let grads = dwt(x.clone(), levels).ll.sum().backward();
            let g = to_vec(x.grad(&grads).expect("gradient"));
            let expected = 1.0 / (1u32 << levels) as f32;
            assert!(
                g.iter().all(|v| (v - expected).abs() < 1e-6),
                "{levels}: {g:?}"
            );
            // Same through ll_band.
            let x = image(1, 3, 16, 16, 11).autodiff().require_grad();
            let grads = ll_band(x.clone(), levels).sum().backward();
            let g = to_vec(x.grad(&grads).expect("gradient"));
            assert!(g.iter().all(|v| (v - expected).abs() < 1e-6));
        }
    }

    #[test]
    fn gradient_flows_through_padding_and_inverse() {
        // 6×6 with 2 levels pads to 8×8: the last row/column are copied twice more, so their
        // gradient of ΣLL is larger (replicated pixels count once per copy).
        let x = image(1, 1, 6, 6, 5).autodiff().require_grad();
        let grads = dwt(x.clone(), 2).ll.sum().backward();
        let g = to_vec(x.grad(&grads).unwrap());
        assert!((g[0] - 0.25).abs() < 1e-6);
        assert!((g[5] - 0.75).abs() < 1e-6, "{}", g[5]); // column 5 appears 3×
        assert!((g[35] - 2.25).abs() < 1e-6, "{}", g[35]); // corner appears 9×
        // idwt(dwt(x)) = x, so ∂Σ idwt(dwt(x))/∂x = 1 (divisible size).
        let x = image(1, 2, 8, 8, 9).autodiff().require_grad();
        let grads = idwt(dwt(x.clone(), 2)).sum().backward();
        let g = to_vec(x.grad(&grads).unwrap());
        assert!(g.iter().all(|v| (v - 1.0).abs() < 1e-5));
    }
}
