//! The geometric warps: rotation, perspective tilt, bilinear resize and centre crop.

use burn::tensor::ops::{
    GridSampleOptions, GridSamplePaddingMode, InterpolateMode, InterpolateOptions,
};
use burn::tensor::{Device, Int, Tensor, TensorData};

/// Exact sine and cosine at multiples of 90°.
fn sin_cos_degrees(degrees: f32) -> (f64, f64) {
    match f64::from(degrees).rem_euclid(360.0) {
        0.0 => (0.0, 1.0),
        90.0 => (1.0, 0.0),
        180.0 => (0.0, -1.0),
        270.0 => (-1.0, 0.0),
        d => d.to_radians().sin_cos(),
    }
}

pub(super) fn rotate(x: Tensor<4>, degrees: f32) -> Tensor<4> {
    let (sin, cos) = sin_cos_degrees(degrees);
    if sin == 0.0 && cos == 1.0 {
        return x;
    }
    let [_, _, h, w] = x.dims();
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let mut grid = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        let dy = y as f64 - cy;
        for xx in 0..w {
            let dx = xx as f64 - cx;
            // Inverse map of a counter-clockwise rotation in y-down image coordinates (the same
            // formula as the real attack), then pixel → [−1, 1] with half-pixel centres.
            let sx = cx + dx * cos - dy * sin;
            let sy = cy + dx * sin + dy * cos;
            grid.push(((2.0 * sx + 1.0) / w as f64 - 1.0) as f32);
            grid.push(((2.0 * sy + 1.0) / h as f64 - 1.0) as f32);
        }
    }
    sample_grid(x, grid)
}

/// Source position (pixels) of output pixel centre `(u, v)` under [`DiffAttack::Perspective`]:
/// the ray through `(u, v)` meets the picture plane, tilted by `R = R_y(y°)·R_x(x°)` about its
/// centre at depth 1, at `P`; the picture coordinates of `P` are `Rᵀ(P − (0, 0, 1))`.
/// `None` where the ray misses the plane (behind the camera).
///
/// [`DiffAttack::Perspective`]: super::DiffAttack::Perspective
pub fn perspective_source(
    u: f64,
    v: f64,
    size: (usize, usize),
    x_degrees: f64,
    y_degrees: f64,
) -> Option<(f64, f64)> {
    let (h, w) = size;
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let f = w as f64;
    let (sx, cxr) = x_degrees.to_radians().sin_cos();
    let (sy, cyr) = y_degrees.to_radians().sin_cos();
    // R = R_y · R_x (columns are the picture's axes in camera space).
    let r = [
        [cyr, sy * sx, sy * cxr],
        [0.0, cxr, -sx],
        [-sy, cyr * sx, cyr * cxr],
    ];
    let ray = [(u - cx) / f, (v - cy) / f, 1.0];
    let n = [r[0][2], r[1][2], r[2][2]];
    let denom = n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2];
    if denom.abs() < 1e-9 {
        return None;
    }
    let t = n[2] / denom;
    if t <= 0.0 {
        return None;
    }
    let p = [t * ray[0], t * ray[1], t * ray[2] - 1.0];
    let qx = r[0][0] * p[0] + r[1][0] * p[1] + r[2][0] * p[2];
    let qy = r[0][1] * p[0] + r[1][1] * p[1] + r[2][1] * p[2];
    Some((cx + f * qx, cy + f * qy))
}

pub(super) fn perspective(x: Tensor<4>, x_degrees: f32, y_degrees: f32) -> Tensor<4> {
    if x_degrees == 0.0 && y_degrees == 0.0 {
        return x;
    }
    let [_, _, h, w] = x.dims();
    let mut grid = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        for xx in 0..w {
            let (u, v) = (xx as f64 + 0.5, y as f64 + 0.5);
            let (sx, sy) =
                perspective_source(u, v, (h, w), f64::from(x_degrees), f64::from(y_degrees))
                    .unwrap_or((-1e6, -1e6));
            // Pixel position (centres at +0.5) → [−1, 1] without corner alignment.
            grid.push((2.0 * sx / w as f64 - 1.0) as f32);
            grid.push((2.0 * sy / h as f64 - 1.0) as f32);
        }
    }
    sample_grid(x, grid)
}

/// Bilinear sampling of every image of `x` `[B, C, H, W]` at one grid of source positions
/// (`H·W` pairs in [−1, 1], row-major, no corner alignment), black outside.
fn sample_grid(x: Tensor<4>, grid: Vec<f32>) -> Tensor<4> {
    let [b, _, h, w] = x.dims();
    let grid = Tensor::<4>::from_data(TensorData::new(grid, [1, h, w, 2]), &x.device())
        .expand([b, h, w, 2]);
    let options = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    x.grid_sample_2d(grid, options)
}

/// Bilinear resize with half-pixel centres (PyTorch's and burn's `interpolate`, align_corners
/// false, no anti-aliasing). burn's wgpu runtime has no backward pass for its bilinear
/// `interpolate`, so on any device but burn's CPU backend the resize runs one axis at a time,
/// each output row (then column) a blend of two gathered input rows — the same values
/// (tested), 3–4× slower than `interpolate` on the CPU backend, hence kept off it.
pub(crate) fn resize(x: Tensor<4>, size: [usize; 2]) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    if size == [h, w] {
        return x;
    }
    if x.device() == Device::flex() {
        return burn::tensor::module::interpolate(
            x,
            InterpolateOptions::new(InterpolateMode::Bilinear)
                .with_align_corners(false)
                .with_output_size(size),
        );
    }
    let x = resize_axis(x, 2, size[0]);
    resize_axis(x, 3, size[1])
}

/// [`resize`] along `dim` (2 or 3) to `out` samples.
fn resize_axis(x: Tensor<4>, dim: usize, out: usize) -> Tensor<4> {
    let len = x.dims()[dim];
    if len == out {
        return x;
    }
    let device = x.device();
    let scale = len as f64 / out as f64;
    let (mut i0, mut i1, mut t) = (
        Vec::with_capacity(out),
        Vec::with_capacity(out),
        Vec::with_capacity(out),
    );
    for i in 0..out {
        // Source position of output sample i, clamped at the edges.
        let src = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
        let a = (src.floor() as usize).min(len - 1);
        i0.push(a as i64);
        i1.push((a + 1).min(len - 1) as i64);
        t.push((src - a as f64).min(1.0) as f32);
    }
    let mut shape = [1usize; 4];
    shape[dim] = out;
    let t = Tensor::<4>::from_data(TensorData::new(t, shape), &device);
    let index = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v, [out]), &device);
    let a = x.clone().select(dim, index(i0));
    let b = x.select(dim, index(i1));
    a.clone().add(b.sub(a).mul(t))
}

pub(super) fn centre_crop(x: Tensor<4>, ch: usize, cw: usize) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    // torchvision's center_crop: top = int(round((h − ch) / 2)), Python rounds half to even.
    let top = ((h - ch) as f64 / 2.0).round_ties_even() as usize;
    let left = ((w - cw) as f64 / 2.0).round_ties_even() as usize;
    x.narrow(2, top, ch).narrow(3, left, cw)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attack::diff::tests::{device, smooth, to_vec};
    use crate::attack::diff::{DiffAttack, batch_from_host};

    #[test]
    fn the_gathered_resize_is_burns_bilinear_interpolate() {
        use burn::tensor::module::interpolate;
        // `resize` keeps burn's own kernel on its CPU backend, training (autodiff) included.
        assert!(Device::flex().autodiff() == Device::flex());
        let (h, w) = (37, 52);
        let data: Vec<f32> = (0..2 * 3 * h * w)
            .map(|k| ((k * 7919) % 1000) as f32 / 1000.0)
            .collect();
        let x = Tensor::<4>::from_data(TensorData::new(data, [2, 3, h, w]), &device());
        for size in [[27, 39], [28, 36], [37, 26], [50, 71], [37, 52], [1, 1]] {
            let ours: Vec<f32> = resize_axis(resize_axis(x.clone(), 2, size[0]), 3, size[1])
                .try_into_vec_as()
                .unwrap();
            let burns: Vec<f32> = interpolate(
                x.clone(),
                InterpolateOptions::new(InterpolateMode::Bilinear)
                    .with_align_corners(false)
                    .with_output_size(size),
            )
            .try_into_vec_as()
            .unwrap();
            assert_eq!(ours.len(), burns.len());
            let gap = ours
                .iter()
                .zip(&burns)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(gap < 1e-5, "{size:?}: differs by {gap}");
        }
    }

    #[test]
    fn rotation_follows_the_real_attack_convention() {
        // 90° counter-clockwise on an 8×8 image moves (x=6, y=2) to (x=2, y=1) (see real.rs).
        let mut data = vec![0.0f32; 3 * 64];
        for c in 0..3 {
            data[c * 64 + 2 * 8 + 6] = 1.0;
        }
        let x = batch_from_host(data, [1, 3, 8, 8], &device());
        let y = to_vec(DiffAttack::Rotate { degrees: 90.0 }.apply(x).unwrap());
        assert!((y[8 + 2] - 1.0).abs() < 1e-5, "{}", y[8 + 2]);
        assert!((y.iter().sum::<f32>() - 3.0).abs() < 1e-4);
    }

    #[test]
    fn perspective_is_the_tilted_picture_seen_through_a_pinhole() {
        let (h, w) = (64usize, 64usize);
        let f = w as f64;
        // A picture point (X, 0) of a plane tilted by θ about the vertical axis sits at
        // (X cos θ, 0, 1 − X sin θ) in camera space and projects to u = cx + f·X cos θ / (1 − X sin θ).
        for theta in [-30.0f64, -10.0, 20.0] {
            let (s, c) = theta.to_radians().sin_cos();
            for xp in [-0.3f64, -0.1, 0.2, 0.4] {
                let u = 32.0 + f * xp * c / (1.0 - xp * s);
                let (sx, sy) = perspective_source(u, 32.0, (h, w), 0.0, theta).unwrap();
                assert!(
                    (sx - (32.0 + f * xp)).abs() < 1e-9,
                    "θ {theta} X {xp}: {sx}"
                );
                assert!((sy - 32.0).abs() < 1e-9);
            }
        }
        // The centre stays; no tilt is the identity; the result keeps its size and is finite.
        let (sx, sy) = perspective_source(32.0, 32.0, (h, w), 25.0, -15.0).unwrap();
        assert!((sx - 32.0).abs() < 1e-9 && (sy - 32.0).abs() < 1e-9);
        let x = smooth(2, h, w);
        let same = DiffAttack::Perspective {
            x_degrees: 0.0,
            y_degrees: 0.0,
        }
        .apply(x.clone())
        .unwrap();
        assert_eq!(to_vec(same), to_vec(x.clone()));
        let tilted = DiffAttack::Perspective {
            x_degrees: 20.0,
            y_degrees: -25.0,
        }
        .apply(x.clone())
        .unwrap();
        assert_eq!(tilted.dims(), [2, 3, h, w]);
        let v = to_vec(tilted);
        assert!(v.iter().all(|v| v.is_finite()));
        assert_ne!(v, to_vec(x));
        assert!(
            DiffAttack::Perspective {
                x_degrees: 85.0,
                y_degrees: 0.0
            }
            .validate()
            .is_err()
        );
    }
}
