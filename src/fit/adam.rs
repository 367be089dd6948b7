//! Adam over a scene whose Gaussians come and go (densification clones, splits and prunes):
//! one moment pair per parameter, laid out like the scene, updated in parallel.

use crate::embed::subset;
use crate::scene::Gaussians;
use rayon::prelude::*;

const BETA1: f32 = 0.9;
const BETA2: f32 = 0.999;
/// INRIA's ε.
const EPS: f32 = 1e-15;

/// Learning rates of one step, per parameter group.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepRates {
    pub means: f32,
    pub sh_dc: f32,
    pub sh_rest: f32,
    pub opacity: f32,
    pub log_scales: f32,
    pub rotations: f32,
}

/// The optimiser's state: first and second moments shaped like the scene, and the step count.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    pub m: Gaussians,
    pub v: Gaussians,
    pub t: i32,
}

/// The six parameter arrays of a scene as flat slices, in a fixed order.
pub(super) fn groups_mut(g: &mut Gaussians) -> [&mut [f32]; 6] {
    [
        g.means.as_flattened_mut(),
        g.sh_dc.as_flattened_mut(),
        &mut g.sh_rest,
        &mut g.opacity_logits,
        g.log_scales.as_flattened_mut(),
        g.rotations.as_flattened_mut(),
    ]
}

/// [`groups_mut`], read only.
pub(super) fn groups(g: &Gaussians) -> [&[f32]; 6] {
    [
        g.means.as_flattened(),
        g.sh_dc.as_flattened(),
        &g.sh_rest,
        &g.opacity_logits,
        g.log_scales.as_flattened(),
        g.rotations.as_flattened(),
    ]
}

impl Adam {
    pub fn new(g: &Gaussians) -> Self {
        let zero = g.cast(|_| 0.0f32);
        Self {
            m: zero.clone(),
            v: zero,
            t: 0,
        }
    }

    /// One Adam step of every parameter of `g` along `grad`.
    pub fn step(&mut self, g: &mut Gaussians, grad: &Gaussians, rates: StepRates) {
        self.t += 1;
        let bc1 = 1.0 - BETA1.powi(self.t);
        let bc2 = 1.0 - BETA2.powi(self.t);
        let lrs = [
            rates.means,
            rates.sh_dc,
            rates.sh_rest,
            rates.opacity,
            rates.log_scales,
            rates.rotations,
        ];
        let ps = groups_mut(g);
        let gs = groups(grad);
        let ms = groups_mut(&mut self.m);
        let vs = groups_mut(&mut self.v);
        for ((((p, gr), m), v), lr) in ps.into_iter().zip(gs).zip(ms).zip(vs).zip(lrs) {
            const CHUNK: usize = 1 << 14;
            p.par_chunks_mut(CHUNK)
                .zip(gr.par_chunks(CHUNK))
                .zip(m.par_chunks_mut(CHUNK))
                .zip(v.par_chunks_mut(CHUNK))
                .for_each(|(((p, gr), m), v)| {
                    for k in 0..p.len() {
                        m[k] = BETA1 * m[k] + (1.0 - BETA1) * gr[k];
                        v[k] = BETA2 * v[k] + (1.0 - BETA2) * gr[k] * gr[k];
                        p[k] -= lr * (m[k] / bc1) / ((v[k] / bc2).sqrt() + EPS);
                    }
                });
        }
    }

    /// Keeps the moments of Gaussians `idx` (in that order) and appends `added` fresh (zero)
    /// ones, as the scene is rebuilt by densification.
    pub fn remap(&mut self, idx: &[usize], added: usize) {
        for s in [&mut self.m, &mut self.v] {
            let mut next = subset(s, idx);
            let rl = next.rest_len();
            next.means.resize(idx.len() + added, [0.0; 3]);
            next.log_scales.resize(idx.len() + added, [0.0; 3]);
            next.rotations.resize(idx.len() + added, [0.0; 4]);
            next.opacity_logits.resize(idx.len() + added, 0.0);
            next.sh_dc.resize(idx.len() + added, [0.0; 3]);
            next.sh_rest.resize((idx.len() + added) * rl, 0.0);
            *s = next;
        }
    }

    /// Forgets the opacity moments (after an opacity reset, as INRIA does).
    pub fn reset_opacity(&mut self) {
        self.m.opacity_logits.fill(0.0);
        self.v.opacity_logits.fill(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::object_scene;

    #[test]
    fn a_step_moves_each_parameter_by_its_own_rate_against_the_gradient() {
        let mut g = object_scene(3, 1, 1);
        let before = g.clone();
        let mut grad = g.cast(|_| 0.0f32);
        grad.means[1][2] = 0.5;
        grad.sh_rest[4] = -2.0;
        grad.opacity_logits[0] = 1e-3;
        let mut adam = Adam::new(&g);
        let rates = StepRates {
            means: 0.1,
            sh_dc: 0.2,
            sh_rest: 0.3,
            opacity: 0.4,
            log_scales: 0.5,
            rotations: 0.6,
        };
        adam.step(&mut g, &grad, rates);
        // The first Adam step is lr·sign(gradient).
        assert!((g.means[1][2] - (before.means[1][2] - 0.1)).abs() < 1e-6);
        assert!((g.sh_rest[4] - (before.sh_rest[4] + 0.3)).abs() < 1e-6);
        assert!((g.opacity_logits[0] - (before.opacity_logits[0] - 0.4)).abs() < 1e-6);
        assert_eq!(g.means[0], before.means[0]);
        assert_eq!(g.rotations, before.rotations);
    }

    #[test]
    fn remap_keeps_the_moments_of_kept_gaussians_and_zeroes_new_ones() {
        let mut g = object_scene(4, 2, 3);
        let mut grad = g.cast(|_| 0.0f32);
        for (i, m) in grad.means.iter_mut().enumerate() {
            *m = [i as f32 + 1.0; 3];
        }
        let mut adam = Adam::new(&g);
        adam.step(
            &mut g,
            &grad,
            StepRates {
                means: 0.01,
                sh_dc: 0.0,
                sh_rest: 0.0,
                opacity: 0.0,
                log_scales: 0.0,
                rotations: 0.0,
            },
        );
        let m3 = adam.m.means[3];
        adam.remap(&[3, 0], 2);
        assert_eq!(adam.m.len(), 4);
        assert_eq!(adam.m.means[0], m3);
        assert_eq!(adam.m.means[2], [0.0; 3]);
        assert_eq!(adam.v.sh_rest.len(), 4 * adam.v.rest_len());
    }
}
