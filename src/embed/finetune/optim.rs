//! The optimisers of the two routes: per-Gaussian Adam and the route-normalised momentum
//! ([`super::StepRule`]).

use crate::scene::Gaussians;

/// Per-Gaussian Adam state over all parameters of a scene.
pub(super) struct Adam {
    m: Gaussians,
    v: Gaussians,
    t: i32,
}

pub(super) const BETA1: f32 = 0.9;
pub(super) const BETA2: f32 = 0.999;
pub(super) const ADAM_EPS: f32 = 1e-15;

impl Adam {
    pub(super) fn new(g: &Gaussians) -> Self {
        let zero = g.cast(|_| 0.0f32);
        Self {
            m: zero.clone(),
            v: zero,
            t: 0,
        }
    }

    /// One step of every parameter of `g` along `grad`; `rates(i)` gives the learning rates of
    /// Gaussian i in channel order means, dc, rest, opacity, rotation, scale.
    pub(super) fn step(
        &mut self,
        g: &mut Gaussians,
        grad: &Gaussians,
        rates: impl Fn(usize) -> [f32; 6],
    ) {
        self.t += 1;
        let bc1 = 1.0 - BETA1.powi(self.t);
        let bc2 = 1.0 - BETA2.powi(self.t);
        let upd = |p: &mut f32, gr: f32, m: &mut f32, v: &mut f32, lr: f32| {
            *m = BETA1 * *m + (1.0 - BETA1) * gr;
            *v = BETA2 * *v + (1.0 - BETA2) * gr * gr;
            if lr != 0.0 {
                *p -= lr * (*m / bc1) / ((*v / bc2).sqrt() + ADAM_EPS);
            }
        };
        let rl = g.rest_len();
        for i in 0..g.len() {
            let [lm, ldc, lrest, lo, lr, ls] = rates(i);
            for k in 0..3 {
                upd(
                    &mut g.means[i][k],
                    grad.means[i][k],
                    &mut self.m.means[i][k],
                    &mut self.v.means[i][k],
                    lm,
                );
                upd(
                    &mut g.sh_dc[i][k],
                    grad.sh_dc[i][k],
                    &mut self.m.sh_dc[i][k],
                    &mut self.v.sh_dc[i][k],
                    ldc,
                );
                upd(
                    &mut g.log_scales[i][k],
                    grad.log_scales[i][k],
                    &mut self.m.log_scales[i][k],
                    &mut self.v.log_scales[i][k],
                    ls,
                );
            }
            for k in 0..4 {
                upd(
                    &mut g.rotations[i][k],
                    grad.rotations[i][k],
                    &mut self.m.rotations[i][k],
                    &mut self.v.rotations[i][k],
                    lr,
                );
            }
            upd(
                &mut g.opacity_logits[i],
                grad.opacity_logits[i],
                &mut self.m.opacity_logits[i],
                &mut self.v.opacity_logits[i],
                lo,
            );
            for k in i * rl..(i + 1) * rl {
                upd(
                    &mut g.sh_rest[k],
                    grad.sh_rest[k],
                    &mut self.m.sh_rest[k],
                    &mut self.v.sh_rest[k],
                    lrest,
                );
            }
            // Keep updated quaternions unit (the renderer normalises; files should hold unit
            // ones); leave the others bit-identical.
            let q = g.rotations[i];
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if lr != 0.0 && n > 1e-12 && n.is_finite() {
                g.rotations[i] = q.map(|v| v / n);
            }
        }
    }
}

/// Largest |step| of one parameter in units of its learning rate under
/// [`super::StepRule::RouteNormalized`] (gradients are heavy-tailed: unclipped, a few Gaussians took
/// steps of hundreds of learning rates and the render fell to 10 dB).
pub const ROUTE_CLIP: f32 = 4.0;

/// [`super::StepRule::RouteNormalized`]: momentum per parameter, one second moment per channel shared
/// by the Gaussians of the route (`on`), bias-corrected like Adam.
pub(super) struct RouteMomentum {
    m: Gaussians,
    /// Second moments: means, dc, rest, opacity, rotation, scale.
    v: [f64; 6],
    t: i32,
}

impl RouteMomentum {
    pub(super) fn new(g: &Gaussians) -> Self {
        Self {
            m: g.cast(|_| 0.0f32),
            v: [0.0; 6],
            t: 0,
        }
    }

    pub(super) fn step(
        &mut self,
        g: &mut Gaussians,
        grad: &Gaussians,
        on: &[bool],
        rates: impl Fn(usize) -> [f32; 6],
    ) {
        self.t += 1;
        let rl = g.rest_len();
        let mut sum = [0.0f64; 6];
        let mut count = [0usize; 6];
        let mut add = |c: usize, xs: &[f32]| {
            for &x in xs {
                sum[c] += f64::from(x) * f64::from(x);
            }
            count[c] += xs.len();
        };
        for i in (0..g.len()).filter(|&i| on[i]) {
            add(0, &grad.means[i]);
            add(1, &grad.sh_dc[i]);
            add(2, &grad.sh_rest[i * rl..(i + 1) * rl]);
            add(3, &[grad.opacity_logits[i]]);
            add(4, &grad.rotations[i]);
            add(5, &grad.log_scales[i]);
        }
        let b2 = f64::from(BETA2);
        for c in 0..6 {
            let ms = if count[c] > 0 {
                sum[c] / count[c] as f64
            } else {
                0.0
            };
            self.v[c] = b2 * self.v[c] + (1.0 - b2) * ms;
        }
        let bc1 = 1.0 - BETA1.powi(self.t);
        let bc2 = 1.0 - b2.powi(self.t);
        let denom: [f32; 6] = self.v.map(|v| ((v / bc2).sqrt() as f32).max(1e-30));
        let upd = |p: &mut [f32], gr: &[f32], m: &mut [f32], lr: f32, d: f32| {
            for ((p, &gr), m) in p.iter_mut().zip(gr).zip(m.iter_mut()) {
                *m = BETA1 * *m + (1.0 - BETA1) * gr;
                if lr != 0.0 {
                    *p -= lr * ((*m / bc1) / d).clamp(-ROUTE_CLIP, ROUTE_CLIP);
                }
            }
        };
        for i in (0..g.len()).filter(|&i| on[i]) {
            let [lm, ldc, lrest, lo, lr, ls] = rates(i);
            upd(
                &mut g.means[i],
                &grad.means[i],
                &mut self.m.means[i],
                lm,
                denom[0],
            );
            upd(
                &mut g.sh_dc[i],
                &grad.sh_dc[i],
                &mut self.m.sh_dc[i],
                ldc,
                denom[1],
            );
            upd(
                &mut g.sh_rest[i * rl..(i + 1) * rl],
                &grad.sh_rest[i * rl..(i + 1) * rl],
                &mut self.m.sh_rest[i * rl..(i + 1) * rl],
                lrest,
                denom[2],
            );
            upd(
                std::slice::from_mut(&mut g.opacity_logits[i]),
                &[grad.opacity_logits[i]],
                std::slice::from_mut(&mut self.m.opacity_logits[i]),
                lo,
                denom[3],
            );
            upd(
                &mut g.rotations[i],
                &grad.rotations[i],
                &mut self.m.rotations[i],
                lr,
                denom[4],
            );
            upd(
                &mut g.log_scales[i],
                &grad.log_scales[i],
                &mut self.m.log_scales[i],
                ls,
                denom[5],
            );
            let q = g.rotations[i];
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if lr != 0.0 && n > 1e-12 && n.is_finite() {
                g.rotations[i] = q.map(|v| v / n);
            }
        }
    }
}

/// Scales the offsets of the Gaussians in `on` from `base` by `f` (quaternions renormalised).
pub(super) fn shrink_offsets(g: &mut Gaussians, base: &Gaussians, on: &[bool], f: f32) {
    let rl = g.rest_len();
    // Unchanged values stay bit-identical (a replayed view checks that the geometry is).
    let lerp = |x: &mut f32, x0: f32| {
        if *x != x0 {
            *x = x0 + f * (*x - x0);
        }
    };
    for i in (0..g.len()).filter(|&i| on[i]) {
        for k in 0..3 {
            lerp(&mut g.means[i][k], base.means[i][k]);
            lerp(&mut g.sh_dc[i][k], base.sh_dc[i][k]);
            lerp(&mut g.log_scales[i][k], base.log_scales[i][k]);
        }
        for k in i * rl..(i + 1) * rl {
            lerp(&mut g.sh_rest[k], base.sh_rest[k]);
        }
        lerp(&mut g.opacity_logits[i], base.opacity_logits[i]);
        if g.rotations[i] == base.rotations[i] {
            continue; // unchanged quaternions stay bit-identical
        }
        for k in 0..4 {
            lerp(&mut g.rotations[i][k], base.rotations[i][k]);
        }
        let q = g.rotations[i];
        let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if n > 1e-12 && n.is_finite() {
            g.rotations[i] = q.map(|v| v / n);
        }
    }
}

/// Adds `b` to `a`, parameter by parameter.
pub(super) fn add_into(a: &mut Gaussians, b: &Gaussians) {
    let zip3 = |x: &mut [[f32; 3]], y: &[[f32; 3]]| {
        for (p, q) in x.iter_mut().zip(y) {
            for k in 0..3 {
                p[k] += q[k];
            }
        }
    };
    zip3(&mut a.means, &b.means);
    zip3(&mut a.log_scales, &b.log_scales);
    zip3(&mut a.sh_dc, &b.sh_dc);
    for (p, q) in a.rotations.iter_mut().zip(&b.rotations) {
        for k in 0..4 {
            p[k] += q[k];
        }
    }
    for (p, q) in a.opacity_logits.iter_mut().zip(&b.opacity_logits) {
        *p += q;
    }
    for (p, q) in a.sh_rest.iter_mut().zip(&b.sh_rest) {
        *p += q;
    }
}

/// ‖∂L/∂θ_i‖₂ over every parameter of Gaussian i, or over its SH coefficients only when
/// `colour_only` (the parameters colour-only finetuning moves).
pub(super) fn grad_norms(g: &Gaussians, colour_only: bool) -> Vec<f32> {
    let rl = g.rest_len();
    (0..g.len())
        .map(|i| {
            let mut s = 0.0f64;
            let mut add = |v: f32| s += f64::from(v) * f64::from(v);
            if !colour_only {
                g.means[i].iter().for_each(|&v| add(v));
                g.log_scales[i].iter().for_each(|&v| add(v));
                g.rotations[i].iter().for_each(|&v| add(v));
                add(g.opacity_logits[i]);
            }
            g.sh_dc[i].iter().for_each(|&v| add(v));
            g.sh_rest[i * rl..(i + 1) * rl].iter().for_each(|&v| add(v));
            s.sqrt() as f32
        })
        .collect()
}

/// Copies every parameter of Gaussian `i` from `src` into `dst`.
pub(super) fn copy_one(dst: &mut Gaussians, src: &Gaussians, i: usize) {
    let rl = dst.rest_len();
    dst.means[i] = src.means[i];
    dst.log_scales[i] = src.log_scales[i];
    dst.rotations[i] = src.rotations[i];
    dst.opacity_logits[i] = src.opacity_logits[i];
    dst.sh_dc[i] = src.sh_dc[i];
    dst.sh_rest[i * rl..(i + 1) * rl].copy_from_slice(&src.sh_rest[i * rl..(i + 1) * rl]);
}
