//! The differentiable JPEG approximation: quantisation tables, 8×8 DCT and the
//! straight-through rounding.

use std::f64::consts::PI;

use burn::tensor::module::conv2d;
use burn::tensor::ops::{ConvOptions, PadMode};
use burn::tensor::{Tensor, TensorData};

/// The standard JPEG luminance quantisation table (ITU-T T.81 Annex K.1), row-major.
pub const JPEG_LUMA_TABLE: [u16; 64] = [
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56,
    14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113,
    92, 49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99,
];

/// The standard JPEG chrominance quantisation table (ITU-T T.81 Annex K.2), row-major.
pub const JPEG_CHROMA_TABLE: [u16; 64] = [
    17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99, 24, 26, 56, 99, 99, 99, 99, 99,
    47, 66, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
    99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
];

/// `table` scaled for `quality` (1..=100) as libjpeg's `jpeg_quality_scaling` +
/// `jpeg_add_quant_table` with `force_baseline`: scale = 5000/q below 50, 200 − 2q from 50,
/// entries ⌊(t·scale + 50)/100⌋ clamped to 1..=255.
pub fn jpeg_quant_table(table: &[u16; 64], quality: u8) -> [u16; 64] {
    let q = u32::from(quality.clamp(1, 100));
    let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
    table.map(|t| ((u32::from(t) * scale + 50) / 100).clamp(1, 255) as u16)
}

/// Orthonormal 8-point DCT-II matrix D (rows = frequencies): `D X Dᵀ` is JPEG's forward DCT of
/// an 8×8 block X.
fn dct_matrix() -> Vec<f32> {
    let mut d = Vec::with_capacity(64);
    for u in 0..8 {
        let alpha = if u == 0 { (1.0f64 / 8.0).sqrt() } else { 0.5 };
        for x in 0..8 {
            d.push((alpha * (((2 * x + 1) * u) as f64 * PI / 16.0).cos()) as f32);
        }
    }
    d
}

/// `x + (round(x) − x).detach()`: rounds in the forward pass, identity in the backward pass.
pub fn straight_through_round<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    let rounded = x.clone().round().sub(x.clone()).detach();
    x.add(rounded)
}

pub(super) fn jpeg(x: Tensor<4>, quality: u8) -> Tensor<4> {
    let [b, _, h, w] = x.dims();
    let device = x.device();
    let conv = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
    // RGB in [0, 1] → level-shifted YCbCr on the 0–255 scale (JFIF): Y − 128, Cb − 128, Cr − 128.
    let to_ycc: [f32; 9] = [
        0.299, 0.587, 0.114, //
        -0.168_736, -0.331_264, 0.5, //
        0.5, -0.418_688, -0.081_312,
    ];
    let to_ycc = Tensor::<4>::from_data(
        TensorData::new(to_ycc.map(|v| v * 255.0).to_vec(), [3, 3, 1, 1]),
        &device,
    );
    let shift = Tensor::<1>::from_data(TensorData::new(vec![-128.0f32, 0.0, 0.0], [3]), &device);
    let ycc = conv2d(x, to_ycc, Some(shift), conv.clone());

    // Edge padding to whole 8×8 blocks (what encoders do), then blocks [B, 3, Hb, Wb, 8, 8].
    let (ph, pw) = (h.div_ceil(8) * 8, w.div_ceil(8) * 8);
    let ycc = if (ph, pw) != (h, w) {
        ycc.pad([(0, ph - h), (0, pw - w)], PadMode::Edge)
    } else {
        ycc
    };
    let (hb, wb) = (ph / 8, pw / 8);
    let blocks = ycc
        .reshape([b, 3, hb, 8, wb, 8])
        .permute([0, 1, 2, 4, 3, 5]);

    let d = Tensor::<6>::from_data(TensorData::new(dct_matrix(), [1, 1, 1, 1, 8, 8]), &device);
    let dt = d.clone().transpose();
    let luma = jpeg_quant_table(&JPEG_LUMA_TABLE, quality);
    let chroma = jpeg_quant_table(&JPEG_CHROMA_TABLE, quality);
    let table: Vec<f32> = luma
        .iter()
        .chain(chroma.iter())
        .chain(chroma.iter())
        .map(|&v| f32::from(v))
        .collect();
    let table = Tensor::<6>::from_data(TensorData::new(table, [1, 3, 1, 1, 8, 8]), &device);

    let coeffs = d.clone().matmul(blocks).matmul(dt.clone());
    let quantised = straight_through_round(coeffs.div(table.clone())).mul(table);
    let blocks = dt.matmul(quantised).matmul(d);

    let ycc = blocks.permute([0, 1, 2, 4, 3, 5]).reshape([b, 3, ph, pw]);
    let ycc = if (ph, pw) != (h, w) {
        ycc.narrow(2, 0, h).narrow(3, 0, w)
    } else {
        ycc
    };
    // Level-shifted YCbCr (0–255 scale) → RGB in [0, 1].
    let to_rgb: [f32; 9] = [
        1.0, 0.0, 1.402, //
        1.0, -0.344_136, -0.714_136, //
        1.0, 1.772, 0.0,
    ];
    let to_rgb = Tensor::<4>::from_data(
        TensorData::new(to_rgb.map(|v| v / 255.0).to_vec(), [3, 3, 1, 1]),
        &device,
    );
    let offset = Tensor::<1>::from_data(TensorData::new(vec![128.0f32 / 255.0; 3], [3]), &device);
    conv2d(ycc, to_rgb, Some(offset), conv).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attack::diff::DiffAttack;
    use crate::attack::diff::tests::{psnr, smooth, to_vec};

    #[test]
    fn jpeg_q50_changes_a_smooth_image_plausibly() {
        let x = smooth(1, 64, 64);
        let y = DiffAttack::Jpeg { quality: 50 }.apply(x.clone()).unwrap();
        let p = psnr(y.clone(), x.clone());
        assert!((25.0..45.0).contains(&p), "PSNR {p}");
        // Lower quality, more damage.
        let z = DiffAttack::Jpeg { quality: 10 }.apply(x.clone()).unwrap();
        assert!(psnr(z, x) < p);
        // Odd size: padded to blocks and cropped back.
        let odd = smooth(1, 21, 30);
        assert_eq!(
            DiffAttack::Jpeg { quality: 50 }.apply(odd).unwrap().dims(),
            [1, 3, 21, 30]
        );
    }

    #[test]
    fn quant_tables_follow_libjpeg_scaling() {
        assert_eq!(jpeg_quant_table(&JPEG_LUMA_TABLE, 50), JPEG_LUMA_TABLE);
        assert!(
            jpeg_quant_table(&JPEG_LUMA_TABLE, 100)
                .iter()
                .all(|&v| v == 1)
        );
        // q = 10: scale 500, 16 → (16·500 + 50)/100 = 80.
        assert_eq!(jpeg_quant_table(&JPEG_LUMA_TABLE, 10)[0], 80);
        assert_eq!(jpeg_quant_table(&JPEG_CHROMA_TABLE, 1)[63], 255);
    }

    #[test]
    fn jpeg_gradient_is_straight_through() {
        // With the STE, the JPEG approximation's Jacobian is that of the linear pipeline without
        // quantisation, which is the identity (away from clamping): ∂Σy/∂x = 1.
        let x = smooth(1, 16, 16).autodiff().require_grad();
        let grads = DiffAttack::Jpeg { quality: 30 }
            .apply(x.clone())
            .unwrap()
            .sum()
            .backward();
        let g = to_vec(x.grad(&grads).unwrap());
        assert!(g.iter().all(|v| (v - 1.0).abs() < 1e-4), "{:?}", &g[..4]);
    }
}
