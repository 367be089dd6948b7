//! The D-SSIM term's mean SSIM of two planes and its gradient (the equations in the parent
//! module's header) in three row-local sweeps over the image:
//!
//! 1. along x, per row: the five moments' inputs (x, t, x², t², x·t, reflect-padded) through the
//!    window, into one buffer of five planes;
//! 2. along y, per row: the five windowed moments of that row, then SSIM and the three
//!    per-pixel gradient factors (g_μ, g_xx, g_xt) right there;
//! 3. per row: the transposed window of the three factors (the y sweep's transpose as gather
//!    lists, then the x sweep's as a zero-padded correlation whose padding is folded back onto
//!    the pixels it reflected), combined into ∂(mean SSIM)/∂x.
//!
//! Every output is a fixed-order sum (eight columns at a time in registers), so the bits do
//! not depend on the thread count; each row's work is also compiled for AVX2 and picked where
//! the CPU has it (the same operations, so the same bits).

use rayon::prelude::*;

use crate::attack::diff::gaussian_kernel;

const C1: f32 = 0.01 * 0.01;
const C2: f32 = 0.03 * 0.03;
const SIGMA: f32 = 1.5;
const TAPS: usize = 11;
const HALF: usize = TAPS / 2;
/// Columns a register accumulator holds.
const LANES: usize = 8;

/// The Gaussian window's taps: the burn SSIM's own kernel (symmetric to the last bit).
fn taps() -> [f32; TAPS] {
    let k = gaussian_kernel(SIGMA, TAPS as u32);
    std::array::from_fn(|m| k[m])
}

/// The pixel that padded position `p` (−HALF ≤ p < n + HALF) of an axis of `n` reads: reflect
/// padding, or edge replication when the axis is not longer than half the window (as the burn
/// blur does).
fn fold(p: isize, n: usize) -> usize {
    let last = n as isize - 1;
    let q = if HALF < n {
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
}

/// `out[i] = Σ_m k[m]·z[i + m]` with `out.len() = z.len() − 2·HALF`, eight outputs at a time.
#[inline(always)]
fn correlate(k: &[f32; TAPS], z: &[f32], out: &mut [f32]) {
    let n = out.len();
    let whole = n / LANES * LANES;
    for c in (0..whole).step_by(LANES) {
        let mut acc = [0.0f32; LANES];
        for (m, &km) in k.iter().enumerate() {
            let zz = &z[c + m..c + m + LANES];
            for l in 0..LANES {
                acc[l] += km * zz[l];
            }
        }
        out[c..c + LANES].copy_from_slice(&acc);
    }
    for (i, o) in out.iter_mut().enumerate().skip(whole) {
        let mut s = 0.0f32;
        for (m, &km) in k.iter().enumerate() {
            s += km * z[i + m];
        }
        *o = s;
    }
}

/// Columns `c..c + L` of one output row in sweep 2: the five windowed moments from the x
/// sweep's `rows` (the window's source rows), SSIM, and the gradient factors written into `out`
/// (`[g_μ, g_xx, g_xt][column]`); returns the columns' SSIM summed.
#[inline(always)]
fn ssim_columns<const L: usize>(
    k: &[f32; TAPS],
    rows: &[&[f32]; TAPS],
    w: usize,
    c: usize,
    scale: f32,
    out: &mut [f32],
) -> f64 {
    let mut acc = [[0.0f32; L]; 5];
    for (row, &km) in rows.iter().zip(k) {
        for (p, a) in acc.iter_mut().enumerate() {
            let v = &row[p * w + c..p * w + c + L];
            for l in 0..L {
                a[l] += km * v[l];
            }
        }
    }
    let mut s_lanes = [0.0f32; L];
    for l in 0..L {
        let (ux, ut) = (acc[0][l], acc[1][l]);
        let sxx = acc[2][l] - ux * ux;
        let stt = acc[3][l] - ut * ut;
        let sxt = acc[4][l] - ux * ut;
        let a1 = 2.0 * ux * ut + C1;
        let a2 = 2.0 * sxt + C2;
        let (b1, b2) = (ux * ux + ut * ut + C1, sxx + stt + C2);
        let den = b1 * b2;
        // Divisions, not reciprocals: identical planes give S = 1 exactly.
        let s = a1 * a2 / den;
        out[c + l] = scale * (2.0 * ut * (a2 - a1) / den - 2.0 * ux * s / b1 + 2.0 * ux * s / b2);
        out[w + c + l] = scale * (-s / b2);
        out[2 * w + c + l] = scale * 2.0 * a1 / den;
        s_lanes[l] = s;
    }
    s_lanes.iter().map(|&s| f64::from(s)).sum()
}

/// A row function and its AVX2 build (the same operations, so the same bits): `$name` picks
/// the AVX2 one where the CPU has it. Rayon's closures are compiled for the baseline target, so
/// the dispatch sits inside each row's work, not around the sweep.
macro_rules! with_avx2 {
    ($(#[$doc:meta])* fn $name:ident / $avx2:ident ($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$doc])*
        fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2, checked just above.
                return unsafe { $avx2($($arg),*) };
            }
            $body
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        fn $avx2($($arg: $ty),*) $(-> $ret)? $body
    };
}

with_avx2! {
    /// Sweep 1 for one row: the five moments' inputs reflect-padded into `z` (five buffers of
    /// w + 2·HALF) and through the window into `out` (`[x, t, xx, tt, xt][column]`).
    fn x_row / x_row_avx2(p: &Planes, r: usize, z: &mut [f32], out: &mut [f32]) {
        let (k, x_fold, w) = (&p.k, &p.x_fold, p.w);
        let (rx, rt) = p.row(r);
        let zl = w + 2 * HALF;
        let (zx, rest) = z.split_at_mut(zl);
        let (zt, rest) = rest.split_at_mut(zl);
        let (zxx, rest) = rest.split_at_mut(zl);
        let (ztt, zxt) = rest.split_at_mut(zl);
        zx[HALF..HALF + w].copy_from_slice(rx);
        zt[HALF..HALF + w].copy_from_slice(rt);
        for q in (0..HALF).chain(w + HALF..zl) {
            (zx[q], zt[q]) = (rx[x_fold[q]], rt[x_fold[q]]);
        }
        for q in 0..zl {
            let (a, b) = (zx[q], zt[q]);
            (zxx[q], ztt[q], zxt[q]) = (a * a, b * b, a * b);
        }
        for (zp, op) in z.chunks_exact(zl).zip(out.chunks_exact_mut(w)) {
            correlate(k, zp, op);
        }
    }
}

with_avx2! {
    /// Sweep 2 for one row: `rows` are the window's source rows of sweep 1; writes the
    /// gradient factors into `out` (`[g_μ, g_xx, g_xt][column]`) and returns the row's SSIM
    /// summed.
    fn y_row / y_row_avx2(k: &[f32; TAPS], rows: &[&[f32]; TAPS], scale: f32, out: &mut [f32]) -> f64 {
        let w = out.len() / 3;
        let mut sum = 0.0f64;
        let whole = w / LANES * LANES;
        for c in (0..whole).step_by(LANES) {
            sum += ssim_columns::<LANES>(k, rows, w, c, scale, out);
        }
        for c in whole..w {
            sum += ssim_columns::<1>(k, rows, w, c, scale, out);
        }
        sum
    }
}

with_avx2! {
    /// Sweep 3 for output row j: the y sweep's transpose (`sources`: the rows of `g` and their
    /// weights) into zero-padded buffers `z`, the x sweep's transpose into `b`, its padding
    /// folded back onto the pixels it reflected, combined as g_μ + 2x·g_xx + t·g_xt.
    fn t_row / t_row_avx2(
        p: &Planes,
        j: usize,
        sources: &[(usize, f32)],
        g: &[f32],
        scratch: &mut (Vec<f32>, Vec<f32>),
        out: &mut [f32],
    ) {
        let (k, x_fold, w) = (&p.k, &p.x_fold, p.w);
        let (z, b) = scratch;
        let (rx, rt) = p.row(j);
        let (zl, bl) = (w + 4 * HALF, w + 2 * HALF);
        z.fill(0.0);
        for &(i, km) in sources {
            let row = &g[i * 3 * w..(i + 1) * 3 * w];
            for p in 0..3 {
                let dst = &mut z[p * zl + 2 * HALF..p * zl + 2 * HALF + w];
                for (d, &v) in dst.iter_mut().zip(&row[p * w..(p + 1) * w]) {
                    *d += km * v;
                }
            }
        }
        for (zp, bp) in z.chunks_exact(zl).zip(b.chunks_exact_mut(bl)) {
            correlate(k, zp, bp);
        }
        let (bm, rest) = b.split_at(bl);
        let (bx, bt) = rest.split_at(bl);
        for col in 0..w {
            let q = col + HALF;
            out[col] = bm[q] + 2.0 * rx[col] * bx[q] + rt[col] * bt[q];
        }
        for q in (0..HALF).chain(w + HALF..bl) {
            let col = x_fold[q];
            out[col] += bm[q] + 2.0 * rx[col] * bx[q] + rt[col] * bt[q];
        }
    }
}

/// The two planes, their width and what every row's work reads: the window and where the x
/// axis's padded positions read.
struct Planes<'a> {
    x: &'a [f32],
    t: &'a [f32],
    w: usize,
    k: [f32; TAPS],
    x_fold: Vec<usize>,
}

impl Planes<'_> {
    /// Row `r` of x and of t.
    fn row(&self, r: usize) -> (&[f32], &[f32]) {
        let span = r * self.w..(r + 1) * self.w;
        (&self.x[span.clone()], &self.t[span])
    }
}

/// Mean SSIM of two `w`×`h` planes and ∂(mean SSIM)/∂x times `scale`.
pub(super) fn ssim_plane(x: &[f32], t: &[f32], w: usize, h: usize, scale: f32) -> (f64, Vec<f32>) {
    let n = w * h;
    assert!(x.len() == n && t.len() == n, "planes are {w}×{h}");
    let k = taps();
    let planes = Planes {
        x,
        t,
        w,
        k,
        x_fold: (0..w + 2 * HALF)
            .map(|q| fold(q as isize - HALF as isize, w))
            .collect(),
    };
    let y_fold: Vec<usize> = (0..h + 2 * HALF)
        .map(|q| fold(q as isize - HALF as isize, h))
        .collect();

    // 1. Along x.
    let mut hz = vec![0.0f32; 5 * n];
    hz.par_chunks_mut(5 * w).enumerate().for_each_init(
        || vec![0.0f32; 5 * (w + 2 * HALF)],
        |z, (r, out)| x_row(&planes, r, z, out),
    );

    // 2. Along y, SSIM and the gradient factors.
    let mut g = vec![0.0f32; 3 * n];
    let row_sums: Vec<f64> = g
        .par_chunks_mut(3 * w)
        .enumerate()
        .map(|(i, out)| {
            let rows: [&[f32]; TAPS] = std::array::from_fn(|m| {
                let r = y_fold[i + m];
                &hz[r * 5 * w..(r + 1) * 5 * w]
            });
            y_row(&k, &rows, scale, out)
        })
        .collect();

    // 3. The transposed window, combined.
    let mut sources: Vec<Vec<(usize, f32)>> = vec![Vec::new(); h];
    for i in 0..h {
        for (m, &km) in k.iter().enumerate() {
            sources[y_fold[i + m]].push((i, km));
        }
    }
    let mut grad = vec![0.0f32; n];
    grad.par_chunks_mut(w).enumerate().for_each_init(
        || {
            (
                vec![0.0f32; 3 * (w + 4 * HALF)],
                vec![0.0f32; 3 * (w + 2 * HALF)],
            )
        },
        |scratch, (j, out)| t_row(&planes, j, &sources[j], &g, scratch, out),
    );
    (row_sums.iter().sum::<f64>() / n as f64, grad)
}
