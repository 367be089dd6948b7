//! L_vis in closed form: its value and ∂L_vis/∂render computed directly, off burn's autodiff
//! graph (the same loss as [`super::losses::ssim`] and [`super::losses::band_l1`] written in
//! burn, checked against them in the tests):
//!
//! L_vis = λ_rec·mean|ŷ − t| + λ_dssim·(1 − mean SSIM(ŷ, t)) + λ_high·Σ_levels Σ_bands mean|Hŷ − Ht|
//!
//! with ŷ = clamp(y, 0, 1) (gradient passed where 0 ≤ y ≤ 1), SSIM with an 11×11 Gaussian
//! window (σ 1.5, reflect padding, C₁ = 0.01², C₂ = 0.03²) and H the Haar detail bands of
//! [`crate::decoder::dwt::dwt`] (edge padding to a multiple of 2^levels). With
//! S = A₁A₂ / (B₁B₂), A₁ = 2μ_xμ_t + C₁, A₂ = 2σ_xt + C₂, B₁ = μ_x² + μ_t² + C₁,
//! B₂ = σ_x² + σ_t² + C₂ and the windowed moments μ_x = G∗x, e_xx = G∗x², e_xt = G∗(x·t):
//!
//! ∂S/∂x = Gᵀ∗g_μ + 2x·(Gᵀ∗g_xx) + t·(Gᵀ∗g_xt), where g_xx = −S/B₂, g_xt = 2A₁/(B₁B₂),
//! g_μ = 2μ_t(A₂ − A₁)/(B₁B₂) − 2μ_x·S/B₁ + 2μ_x·S/B₂.
//!
//! Gᵀ is the exact transpose of the padded blur (reflection folds border weights back); the
//! three sweeps over the image that give S and ∂S/∂x are [`ssim`]'s. Measured on donut at 512²
//! (docs/BENCHMARKS.md, "Embedding"): the burn graph of these terms and its transposed
//! depthwise convolutions were the largest share of a step once the views were replayed.

use super::LossWeights;

mod ssim;

/// Σ over the Haar detail bands of every level of mean|band(x) − band(t)| (each band's mean
/// over its own elements, `planes` planes of h×w sharing the count), and its gradient times
/// `scale`. The bands in f32 (as burn's), their sum in f64.
fn high_bands_l1(
    x: &[f32],
    t: &[f32],
    w: usize,
    h: usize,
    levels: usize,
    planes: usize,
    scale: f64,
) -> (f64, Vec<f32>) {
    let m = 1usize << levels;
    let (pw, ph) = (w.div_ceil(m) * m, h.div_ceil(m) * m);
    let pad = |p: &[f32]| -> Vec<f32> {
        let mut out = vec![0.0f32; pw * ph];
        for (r, dst) in out.chunks_exact_mut(pw).enumerate() {
            let src = &p[r.min(h - 1) * w..(r.min(h - 1) + 1) * w];
            dst[..w].copy_from_slice(src);
            dst[w..].fill(src[w - 1]);
        }
        out
    };
    // Per level: the LL of x and t it starts from, to rebuild the gradient coarse to fine.
    let (mut lx, mut lt) = (pad(x), pad(t));
    let (mut cw, mut ch) = (pw, ph);
    let mut value = 0.0;
    let mut d_bands: Vec<[Vec<f32>; 3]> = Vec::with_capacity(levels);
    let mut sizes = Vec::with_capacity(levels);
    for _ in 0..levels {
        let (hw, hh) = (cw / 2, ch / 2);
        let count = (planes * hw * hh) as f64;
        let step = (scale / count) as f32;
        let mut next = (vec![0.0f32; hw * hh], vec![0.0f32; hw * hh]);
        let mut d: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0.0f32; hw * hh]);
        let mut sum = 0.0f64;
        for by in 0..hh {
            let pair = 2 * by * cw..(2 * by + 2) * cw;
            let ((x0, x1), (t0, t1)) = (lx[pair.clone()].split_at(cw), lt[pair].split_at(cw));
            let mut row_sum = 0.0f32;
            for bx in 0..hw {
                let q = by * hw + bx;
                // ll, [lh, hl, hh] as in `haar_level`
                let bands = |top: &[f32], bottom: &[f32]| {
                    let (a, b) = (top[2 * bx], top[2 * bx + 1]);
                    let (c, e) = (bottom[2 * bx], bottom[2 * bx + 1]);
                    let (s0, s1, d0, d1) = (a + c, b + e, a - c, b - e);
                    (
                        0.5 * (s0 + s1),
                        [0.5 * (d0 + d1), 0.5 * (s0 - s1), 0.5 * (d0 - d1)],
                    )
                };
                let (llx, hx) = bands(x0, x1);
                let (llt, ht) = bands(t0, t1);
                next.0[q] = llx;
                next.1[q] = llt;
                for k in 0..3 {
                    let diff = hx[k] - ht[k];
                    row_sum += diff.abs();
                    d[k][q] = if diff > 0.0 {
                        step
                    } else if diff < 0.0 {
                        -step
                    } else {
                        0.0
                    };
                }
            }
            sum += f64::from(row_sum);
        }
        value += sum / count;
        d_bands.push(d);
        sizes.push((cw, ch));
        (lx, lt) = next;
        (cw, ch) = (cw / 2, ch / 2);
    }
    // Back through the levels, coarsest first: the LL gradient of level l+1's input is the
    // gradient of level l's LL output (zero at the coarsest: the LL band is not in this term).
    let mut d_ll = vec![0.0f32; cw * ch];
    for (d, &(cw, ch)) in d_bands.iter().zip(&sizes).rev() {
        let hw = cw / 2;
        let mut up = vec![0.0f32; cw * ch];
        for by in 0..ch / 2 {
            let (top, bottom) = up[2 * by * cw..(2 * by + 2) * cw].split_at_mut(cw);
            for bx in 0..hw {
                let q = by * hw + bx;
                let (gll, glh, ghl, ghh) = (d_ll[q], d[0][q], d[1][q], d[2][q]);
                top[2 * bx] = 0.5 * (gll + ghl + glh + ghh);
                top[2 * bx + 1] = 0.5 * (gll - ghl + glh - ghh);
                bottom[2 * bx] = 0.5 * (gll + ghl - glh - ghh);
                bottom[2 * bx + 1] = 0.5 * (gll - ghl - glh + ghh);
            }
        }
        d_ll = up;
    }
    // Fold the padding back onto the edge pixels it replicated.
    let mut grad = vec![0.0f32; w * h];
    for (r, src) in d_ll.chunks_exact(pw).enumerate() {
        let dst = &mut grad[r.min(h - 1) * w..(r.min(h - 1) + 1) * w];
        for (o, g) in dst.iter_mut().zip(src) {
            *o += g;
        }
        dst[w - 1] += src[w..].iter().sum::<f32>();
    }
    (value, grad)
}

fn sign(v: f64) -> f64 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// L_vis of one view (`y` the render, unclamped, `t` its target; row-major RGB, `w`×`h`) and
/// ∂L_vis/∂y.
pub(super) fn visual_loss(
    y: &[[f32; 3]],
    t: &[[f32; 3]],
    w: usize,
    h: usize,
    weights: &LossWeights,
    levels: usize,
) -> (f64, Vec<[f32; 3]>) {
    image_loss(y, t, w, h, weights, levels, true)
}

/// 3D-GS's reconstruction loss `rec·mean|y − t| + dssim·(1 − mean SSIM(y, t))` of one view and
/// its gradient, on the render as it is (not clamped, as INRIA's training computes it), for
/// fitting a scene to photographs ([`crate::fit`]).
pub(crate) fn reconstruction_loss(
    y: &[[f32; 3]],
    t: &[[f32; 3]],
    w: usize,
    h: usize,
    rec: f32,
    dssim: f32,
) -> (f64, Vec<[f32; 3]>) {
    let weights = LossWeights {
        rec,
        dssim,
        wav_high: 0.0,
        ..LossWeights::default()
    };
    image_loss(y, t, w, h, &weights, 0, false)
}

/// L_vis with ŷ = clamp(y, 0, 1) when `clamp` is set, ŷ = y otherwise.
fn image_loss(
    y: &[[f32; 3]],
    t: &[[f32; 3]],
    w: usize,
    h: usize,
    weights: &LossWeights,
    levels: usize,
    clamp: bool,
) -> (f64, Vec<[f32; 3]>) {
    let n = w * h;
    assert!(
        y.len() == n && t.len() == n,
        "render and target are {w}×{h}"
    );
    let count = (3 * n) as f64;
    let per_channel: Vec<(f64, Vec<f32>)> = (0..3)
        .map(|c| {
            let x: Vec<f32> = if clamp {
                y.iter().map(|p| p[c].clamp(0.0, 1.0)).collect()
            } else {
                y.iter().map(|p| p[c]).collect()
            };
            let tc: Vec<f32> = t.iter().map(|p| p[c]).collect();
            let (l1, mut grad): (f64, Vec<f32>) = {
                let rec = f64::from(weights.rec) / count;
                let l1: f64 = x
                    .iter()
                    .zip(&tc)
                    .map(|(a, b)| f64::from((a - b).abs()))
                    .sum();
                let g = x
                    .iter()
                    .zip(&tc)
                    .map(|(a, b)| (rec * sign(f64::from(a - b))) as f32)
                    .collect();
                (l1 / count, g)
            };
            let (s, gs) = ssim::ssim_plane(&x, &tc, w, h, -weights.dssim / 3.0 / n as f32);
            let (hb, gh) = if levels > 0 {
                high_bands_l1(&x, &tc, w, h, levels, 3, f64::from(weights.wav_high))
            } else {
                (0.0, vec![0.0; n])
            };
            for (i, g) in grad.iter_mut().enumerate() {
                let v = y[i][c];
                *g = if !clamp || (0.0..=1.0).contains(&v) {
                    *g + gs[i] + gh[i]
                } else {
                    0.0
                };
            }
            let value = f64::from(weights.rec) * l1
                + f64::from(weights.dssim) * (1.0 / 3.0 - s / 3.0)
                + f64::from(weights.wav_high) * hb;
            (value, grad)
        })
        .collect();
    let value = per_channel.iter().map(|(v, _)| v).sum();
    let grad = (0..n)
        .map(|i| std::array::from_fn(|c| per_channel[c].1[i]))
        .collect();
    (value, grad)
}

#[cfg(test)]
mod tests {
    use burn::tensor::Device;

    use super::super::losses::{from_planar, to_tensor, visual_loss_tensor};
    use super::*;

    /// The same loss through burn's autodiff (what a GPU job runs).
    fn burn_loss(
        y: &[[f32; 3]],
        t: &[[f32; 3]],
        w: usize,
        h: usize,
        weights: &LossWeights,
        levels: usize,
    ) -> (f64, Vec<[f32; 3]>) {
        let device = Device::flex().autodiff();
        let x = to_tensor(y, w, h, &device).require_grad();
        let t = to_tensor(t, w, h, &device);
        let l = visual_loss_tensor(x.clone(), t, weights, levels);
        let value = f64::from(l.clone().detach().into_scalar::<f32>());
        let grads = l.backward();
        let d: Vec<f32> = x.grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap();
        (value, from_planar(&d, w * h))
    }

    fn image(w: usize, h: usize, seed: u64, spread: f32) -> Vec<[f32; 3]> {
        let mut s = seed;
        let mut next = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        (0..w * h)
            .map(|i| {
                let smooth =
                    0.5 + 0.3 * ((i % w) as f32 * 0.3).sin() * ((i / w) as f32 * 0.2).cos();
                std::array::from_fn(|_| smooth + spread * (next() - 0.5))
            })
            .collect()
    }

    /// A target: a smooth image with a little noise, inside [0, 1].
    fn target(w: usize, h: usize, seed: u64) -> Vec<[f32; 3]> {
        image(w, h, seed, 0.2)
            .into_iter()
            .map(|p| p.map(|v| v.clamp(0.0, 1.0)))
            .collect()
    }

    /// Weights that give every term of L_vis a say.
    fn every_term() -> LossWeights {
        LossWeights {
            rec: 0.8,
            dssim: 0.2,
            wav_high: 0.5,
            ..LossWeights::default()
        }
    }

    #[test]
    fn the_visual_loss_does_not_depend_on_the_thread_count() {
        let weights = every_term();
        let (w, h) = (70, 45);
        let y = image(w, h, 5, 0.9);
        let t = target(w, h, 6);
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a thread pool")
                .install(|| visual_loss(&y, &t, w, h, &weights, 2))
        };
        let (v1, g1) = on(1);
        let (v4, g4) = on(4);
        assert_eq!(v1.to_bits(), v4.to_bits());
        assert!(
            g1.iter()
                .flatten()
                .zip(g4.iter().flatten())
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }

    #[test]
    fn the_closed_form_visual_loss_and_gradient_are_burns() {
        let weights = every_term();
        // Even sizes, odd sizes (edge padding of the DWT), and an axis shorter than the half
        // window (edge padding of the blur); renders stray outside [0, 1] and some pixels equal
        // their target (L1's kink) or sit exactly on 0 (the clamp's edge).
        for (w, h, levels) in [(40, 28, 2), (23, 13, 2), (4, 17, 1), (24, 16, 0)] {
            let mut y = image(w, h, 1 + w as u64, 0.9);
            let t = target(w, h, 99 + h as u64);
            y[3] = t[3];
            y[5] = [0.0; 3];
            let (v, g) = visual_loss(&y, &t, w, h, &weights, levels);
            let (bv, bg) = burn_loss(&y, &t, w, h, &weights, levels);
            assert!(
                (v - bv).abs() <= 1e-5 * bv.abs().max(1e-3),
                "{w}×{h}: {v} vs {bv}"
            );
            let scale = bg.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(scale > 0.0);
            for (i, (a, b)) in g.iter().zip(&bg).enumerate() {
                for c in 0..3 {
                    assert!(
                        (a[c] - b[c]).abs() <= 2e-4 * scale,
                        "{w}×{h} pixel {i} channel {c}: {} vs {} (scale {scale})",
                        a[c],
                        b[c]
                    );
                }
            }
        }
    }
}
