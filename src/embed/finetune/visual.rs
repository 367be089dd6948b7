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
//! Gᵀ is the exact transpose of the padded blur (reflection folds border weights back).
//! Measured on donut at 512² (docs/BENCHMARKS.md, "Embedding"): the burn graph of these terms
//! and its transposed depthwise convolutions were the largest share of a step once the views
//! were replayed.

use rayon::prelude::*;

use super::LossWeights;

const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;
const SSIM_SIGMA: f64 = 1.5;
const SSIM_TAPS: usize = 11;

/// A 1D linear operator of length n as gather lists: `out[i] = Σ (j, w) ∈ rows[i]: w·x[j]`;
/// rows `regular` (a range) are the plain kernel `kern` centred on i, applied without lists.
struct Op1d {
    rows: Vec<Vec<(usize, f32)>>,
    kern: Vec<f32>,
    regular: std::ops::Range<usize>,
}

impl Op1d {
    fn new(rows: Vec<Vec<(usize, f32)>>, kern: Vec<f32>) -> Self {
        let half = kern.len() / 2;
        let is_regular = |i: usize, row: &[(usize, f32)]| {
            row.len() == kern.len()
                && row
                    .iter()
                    .enumerate()
                    .all(|(m, &(j, w))| i + m == j + half && w == kern[m])
        };
        let flags: Vec<bool> = rows
            .iter()
            .enumerate()
            .map(|(i, r)| is_regular(i, r))
            .collect();
        let lo = flags.iter().position(|&f| f).unwrap_or(0);
        let hi = flags[lo..]
            .iter()
            .position(|&f| !f)
            .map_or(flags.len(), |k| lo + k);
        Self {
            rows,
            kern,
            regular: lo..hi.max(lo),
        }
    }
}

impl Op1d {
    /// The SSIM window along an axis of length n: Gaussian taps, reflect padding (edge
    /// replication when the axis is shorter than the half window, as the burn blur does).
    fn blur(n: usize) -> Self {
        let half = SSIM_TAPS / 2;
        let raw: Vec<f64> = (0..SSIM_TAPS)
            .map(|k| {
                let d = k as f64 - half as f64;
                (-0.5 * (d / SSIM_SIGMA).powi(2)).exp()
            })
            .collect();
        let total: f64 = raw.iter().sum();
        let taps: Vec<f32> = raw.iter().map(|v| (v / total) as f32).collect();
        let reflect = half < n;
        let index = |p: isize| -> usize {
            let last = n as isize - 1;
            let q = if reflect {
                if p < 0 {
                    -p
                } else if p > last {
                    2 * last - p
                } else {
                    p
                }
            } else {
                p.clamp(0, last)
            };
            q as usize
        };
        let rows = (0..n)
            .map(|i| {
                taps.iter()
                    .enumerate()
                    .map(|(k, &w)| (index(i as isize + k as isize - half as isize), w))
                    .collect()
            })
            .collect();
        Self::new(rows, taps)
    }

    /// The transpose: `out[j] = Σ_i M[i][j]·x[i]` (the kernel is symmetric, so regular rows
    /// stay regular).
    fn transposed(&self) -> Self {
        let mut rows: Vec<Vec<(usize, f32)>> = vec![Vec::new(); self.rows.len()];
        for (i, row) in self.rows.iter().enumerate() {
            for &(j, w) in row {
                rows[j].push((i, w));
            }
        }
        Self::new(rows, self.kern.iter().rev().copied().collect())
    }
}

/// The separable window of one image size and its transpose.
struct Window {
    w: usize,
    x: Op1d,
    y: Op1d,
    xt: Op1d,
    yt: Op1d,
}

impl Window {
    fn new(w: usize, h: usize) -> Self {
        let (x, y) = (Op1d::blur(w), Op1d::blur(h));
        let (xt, yt) = (x.transposed(), y.transposed());
        Self { w, x, y, xt, yt }
    }

    /// Along x, then along y (the order of the burn blur).
    fn blur(&self, plane: &[f32]) -> Vec<f32> {
        along_y(&self.y, &along_x(&self.x, plane, self.w), self.w)
    }

    /// The transpose of [`Window::blur`].
    fn blur_t(&self, plane: &[f32]) -> Vec<f32> {
        along_x(&self.xt, &along_y(&self.yt, plane, self.w), self.w)
    }
}

fn along_x(op: &Op1d, plane: &[f32], w: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; plane.len()];
    out.par_chunks_mut(w)
        .zip(plane.par_chunks(w))
        .for_each(|(o, row)| {
            let (lo, hi) = (op.regular.start, op.regular.end);
            let half = op.kern.len() / 2;
            for (i, (v, taps)) in o.iter_mut().zip(&op.rows).enumerate() {
                if !(lo..hi).contains(&i) {
                    *v = taps.iter().map(|&(j, t)| t * row[j]).sum();
                }
            }
            // Interior: tap by tap over the whole run (vectorised).
            if lo >= hi {
                return;
            }
            for (m, &t) in op.kern.iter().enumerate() {
                for (v, &x) in o[lo..hi].iter_mut().zip(&row[lo + m - half..hi + m - half]) {
                    *v += t * x;
                }
            }
        });
    out
}

fn along_y(op: &Op1d, plane: &[f32], w: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; plane.len()];
    out.par_chunks_mut(w).zip(&op.rows).for_each(|(o, taps)| {
        for &(j, t) in taps {
            for (v, &s) in o.iter_mut().zip(&plane[j * w..(j + 1) * w]) {
                *v += t * s;
            }
        }
    });
    out
}

/// Mean SSIM of two planes and, when asked, ∂(mean SSIM)/∂x times `scale`.
fn ssim_plane(win: &Window, x: &[f32], t: &[f32], scale: f64) -> (f64, Vec<f32>) {
    let n = x.len();
    let prod = |a: &[f32], b: &[f32]| -> Vec<f32> { a.iter().zip(b).map(|(p, q)| p * q).collect() };
    let mx = win.blur(x);
    let mt = win.blur(t);
    let exx = win.blur(&prod(x, x));
    let ett = win.blur(&prod(t, t));
    let ext = win.blur(&prod(x, t));
    let mut g_mu = vec![0.0f32; n];
    let mut g_xx = vec![0.0f32; n];
    let mut g_xt = vec![0.0f32; n];
    let sum: f64 = (0..n)
        .into_par_iter()
        .zip(g_mu.par_iter_mut())
        .zip(g_xx.par_iter_mut())
        .zip(g_xt.par_iter_mut())
        .map(|(((i, gm), gx), gt)| {
            let (ux, ut) = (f64::from(mx[i]), f64::from(mt[i]));
            let sxx = f64::from(exx[i]) - ux * ux;
            let stt = f64::from(ett[i]) - ut * ut;
            let sxt = f64::from(ext[i]) - ux * ut;
            let a1 = 2.0 * ux * ut + C1;
            let a2 = 2.0 * sxt + C2;
            let b1 = ux * ux + ut * ut + C1;
            let b2 = sxx + stt + C2;
            let s = a1 * a2 / (b1 * b2);
            *gm = (scale
                * (2.0 * ut * (a2 - a1) / (b1 * b2) - 2.0 * ux * s / b1 + 2.0 * ux * s / b2))
                as f32;
            *gx = (scale * (-s / b2)) as f32;
            *gt = (scale * 2.0 * a1 / (b1 * b2)) as f32;
            s
        })
        .sum();
    let (bm, bx, bt) = (win.blur_t(&g_mu), win.blur_t(&g_xx), win.blur_t(&g_xt));
    let grad = (0..n)
        .map(|i| bm[i] + 2.0 * x[i] * bx[i] + t[i] * bt[i])
        .collect();
    (sum / n as f64, grad)
}

/// Σ over the Haar detail bands of every level of mean|band(x) − band(t)| (each band's mean
/// over its own elements, `planes` planes of h×w sharing the count), and its gradient times
/// `scale`.
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
    let pad = |p: &[f32]| -> Vec<f64> {
        (0..ph * pw)
            .map(|k| f64::from(p[(k / pw).min(h - 1) * w + (k % pw).min(w - 1)]))
            .collect()
    };
    // Per level: the LL of x and t it starts from, to rebuild the gradient coarse to fine.
    let (mut lx, mut lt) = (pad(x), pad(t));
    let (mut cw, mut ch) = (pw, ph);
    let mut value = 0.0;
    let mut d_bands: Vec<[Vec<f64>; 3]> = Vec::with_capacity(levels);
    let mut sizes = Vec::with_capacity(levels);
    for _ in 0..levels {
        let (hw, hh) = (cw / 2, ch / 2);
        let count = (planes * hw * hh) as f64;
        let mut next = (vec![0.0; hw * hh], vec![0.0; hw * hh]);
        let mut d: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; hw * hh]);
        for by in 0..hh {
            for bx in 0..hw {
                let q = by * hw + bx;
                let bands = |p: &[f64]| {
                    let (a, b) = (p[2 * by * cw + 2 * bx], p[2 * by * cw + 2 * bx + 1]);
                    let (c, e) = (
                        p[(2 * by + 1) * cw + 2 * bx],
                        p[(2 * by + 1) * cw + 2 * bx + 1],
                    );
                    let (s0, s1, d0, d1) = (a + c, b + e, a - c, b - e);
                    // ll, [lh, hl, hh] as in `haar_level`
                    (
                        0.5 * (s0 + s1),
                        [0.5 * (d0 + d1), 0.5 * (s0 - s1), 0.5 * (d0 - d1)],
                    )
                };
                let (llx, hx) = bands(&lx);
                let (llt, ht) = bands(&lt);
                next.0[q] = llx;
                next.1[q] = llt;
                for k in 0..3 {
                    let diff = hx[k] - ht[k];
                    value += diff.abs() / count;
                    d[k][q] = scale * sign(diff) / count;
                }
            }
        }
        d_bands.push(d);
        sizes.push((cw, ch));
        (lx, lt) = next;
        (cw, ch) = (cw / 2, ch / 2);
    }
    // Back through the levels, coarsest first: the LL gradient of level l+1's input is the
    // gradient of level l's LL output (zero at the coarsest: the LL band is not in this term).
    let mut d_ll = vec![0.0f64; cw * ch];
    for (d, &(cw, ch)) in d_bands.iter().zip(&sizes).rev() {
        let hw = cw / 2;
        let mut up = vec![0.0f64; cw * ch];
        for by in 0..ch / 2 {
            for bx in 0..hw {
                let q = by * hw + bx;
                let (gll, glh, ghl, ghh) = (d_ll[q], d[0][q], d[1][q], d[2][q]);
                up[2 * by * cw + 2 * bx] = 0.5 * (gll + ghl + glh + ghh);
                up[2 * by * cw + 2 * bx + 1] = 0.5 * (gll - ghl + glh - ghh);
                up[(2 * by + 1) * cw + 2 * bx] = 0.5 * (gll + ghl - glh - ghh);
                up[(2 * by + 1) * cw + 2 * bx + 1] = 0.5 * (gll - ghl - glh + ghh);
            }
        }
        d_ll = up;
    }
    // Fold the padding back onto the edge pixels it replicated.
    let mut grad = vec![0.0f32; w * h];
    let mut acc = vec![0.0f64; w * h];
    for (k, g) in d_ll.iter().enumerate() {
        acc[(k / pw).min(h - 1) * w + (k % pw).min(w - 1)] += g;
    }
    for (o, a) in grad.iter_mut().zip(acc) {
        *o = a as f32;
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
    let win = Window::new(w, h);
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
            let (s, gs) = ssim_plane(&win, &x, &tc, -f64::from(weights.dssim) / 3.0 / n as f64);
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

    #[test]
    fn the_closed_form_visual_loss_and_gradient_are_burns() {
        let weights = LossWeights {
            rec: 0.8,
            dssim: 0.2,
            wav_high: 0.5,
            ..LossWeights::default()
        };
        // Even sizes, odd sizes (edge padding of the DWT), and an axis shorter than the half
        // window (edge padding of the blur); renders stray outside [0, 1] and some pixels equal
        // their target (L1's kink) or sit exactly on 0 (the clamp's edge).
        for (w, h, levels) in [(40, 28, 2), (23, 13, 2), (4, 17, 1), (24, 16, 0)] {
            let mut y = image(w, h, 1 + w as u64, 0.9);
            let t: Vec<[f32; 3]> = image(w, h, 99 + h as u64, 0.2)
                .into_iter()
                .map(|p| p.map(|v| v.clamp(0.0, 1.0)))
                .collect();
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
