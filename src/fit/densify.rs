//! Adaptive density control of 3D-GS (Kerbl et al. 2023, §5.2, and INRIA's
//! `densify_and_prune`): Gaussians whose projected centre keeps being pulled (mean view-space
//! positional gradient ≥ τ) are cloned when small (max scale ≤ `percent_dense`·extent) or split
//! in two when large (children sampled from the parent, scales ÷ 1.6); nearly transparent ones
//! and, after the first opacity reset, ones grown past 0.1·extent in world space are pruned.

use super::adam::Adam;
use crate::embed::subset;
use crate::scene::synthetic::Rng;
use crate::scene::{Gaussians, logit};

/// Per-Gaussian statistics gathered between two densifications.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DensifyStats {
    /// Σ over views of ‖∂L/∂(centre in NDC)‖.
    pub grad_accum: Vec<f32>,
    /// Number of views the Gaussian was drawn in.
    pub denom: Vec<u32>,
    /// Largest screen radius (pixels) seen.
    pub max_radii: Vec<f32>,
}

impl DensifyStats {
    pub fn new(n: usize) -> Self {
        Self {
            grad_accum: vec![0.0; n],
            denom: vec![0; n],
            max_radii: vec![0.0; n],
        }
    }

    /// Adds one view: `radii` the drawn Gaussians (index, screen radius), `screen_xy` the
    /// gradient of the loss with respect to each centre in pixels, for a `width`×`height` image.
    /// NDC spans 2 units over the image, so ∂L/∂ndc = ∂L/∂px · size / 2 (INRIA's `viewspace`
    /// gradient, which its threshold 0.0002 is for).
    pub fn add_view(
        &mut self,
        radii: impl Iterator<Item = (usize, f32)>,
        screen_xy: &[[f32; 2]],
        width: u32,
        height: u32,
    ) {
        let (hw, hh) = (0.5 * width as f32, 0.5 * height as f32);
        for (i, r) in radii {
            if r <= 0.0 {
                continue;
            }
            self.max_radii[i] = self.max_radii[i].max(r);
            let [gx, gy] = screen_xy[i];
            self.grad_accum[i] += (gx * hw).hypot(gy * hh);
            self.denom[i] += 1;
        }
    }

    /// Mean NDC gradient of Gaussian i over the views it was drawn in (0 if none).
    pub fn mean_grad(&self, i: usize) -> f32 {
        match self.denom[i] {
            0 => 0.0,
            d => self.grad_accum[i] / d as f32,
        }
    }
}

/// Thresholds of one densification.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifyParams {
    /// τ on the mean NDC gradient.
    pub grad_threshold: f32,
    /// Clone below, split above this fraction of the extent (largest scale).
    pub percent_dense: f32,
    /// Prune below this opacity.
    pub min_opacity: f32,
    /// Prune Gaussians whose largest scale exceeds this fraction of the extent (`None`: don't).
    pub max_world_scale: Option<f32>,
    /// The scene's extent (INRIA's `cameras_extent`).
    pub extent: f32,
    /// Never grow past this many Gaussians: when the candidates would, those with the largest
    /// gradients go first.
    pub max_gaussians: usize,
}

/// What one densification did.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct DensifyOutcome {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
    pub gaussians: usize,
}

/// Children a split Gaussian becomes.
const SPLIT_N: usize = 2;

enum Source {
    Clone(usize),
    Child(usize, [f32; 3]),
}

/// Clones, splits and prunes `g` by `stats`, keeping `adam`'s moments aligned (new Gaussians
/// start with zero moments) and resetting `stats` for the new scene.
pub fn densify_and_prune(
    g: &mut Gaussians,
    adam: &mut Adam,
    stats: &mut DensifyStats,
    p: &DensifyParams,
    rng: &mut Rng,
) -> DensifyOutcome {
    let n = g.len();
    let dense = p.percent_dense * p.extent;
    let max_scale = |g: &Gaussians, i: usize| {
        let [a, b, c] = g.log_scales[i];
        a.max(b).max(c).exp()
    };
    let mut candidates: Vec<usize> = (0..n)
        .filter(|&i| stats.mean_grad(i) >= p.grad_threshold)
        .collect();
    let room = p.max_gaussians.saturating_sub(n);
    if candidates.len() > room {
        candidates.sort_by(|&a, &b| {
            stats
                .mean_grad(b)
                .total_cmp(&stats.mean_grad(a))
                .then(a.cmp(&b))
        });
        candidates.truncate(room);
        candidates.sort_unstable();
    }
    let mut split = vec![false; n];
    let mut new: Vec<Source> = Vec::new();
    let (mut cloned, mut n_split) = (0, 0);
    for &i in &candidates {
        if max_scale(g, i) <= dense {
            new.push(Source::Clone(i));
            cloned += 1;
        } else {
            split[i] = true;
            n_split += 1;
        }
    }
    for i in (0..n).filter(|&i| split[i]) {
        let s = g.log_scales[i].map(f32::exp);
        let r = rotation_matrix(g.rotations[i]);
        for _ in 0..SPLIT_N {
            let z = [
                rng.normal() * s[0],
                rng.normal() * s[1],
                rng.normal() * s[2],
            ];
            let off =
                std::array::from_fn(|row| r[row][0] * z[0] + r[row][1] * z[1] + r[row][2] * z[2]);
            new.push(Source::Child(i, off));
        }
    }

    // The scene before pruning: unsplit originals, then clones and children.
    let kept: Vec<usize> = (0..n).filter(|&i| !split[i]).collect();
    let mut next = subset(g, &kept);
    let rl = g.rest_len();
    let shrink = (0.8 * SPLIT_N as f32).ln();
    for s in &new {
        let (i, off) = match *s {
            Source::Clone(i) => (i, None),
            Source::Child(i, off) => (i, Some(off)),
        };
        let mean = match off {
            Some(o) => std::array::from_fn(|k| g.means[i][k] + o[k]),
            None => g.means[i],
        };
        next.means.push(mean);
        next.log_scales.push(match off {
            Some(_) => g.log_scales[i].map(|v| v - shrink),
            None => g.log_scales[i],
        });
        next.rotations.push(g.rotations[i]);
        next.opacity_logits.push(g.opacity_logits[i]);
        next.sh_dc.push(g.sh_dc[i]);
        next.sh_rest
            .extend_from_slice(&g.sh_rest[i * rl..(i + 1) * rl]);
    }
    let min_logit = logit(p.min_opacity);
    let prune = |j: usize| {
        next.opacity_logits[j] < min_logit
            || p.max_world_scale
                .is_some_and(|m| max_scale(&next, j) > m * p.extent)
    };
    let survivors: Vec<usize> = (0..next.len()).filter(|&j| !prune(j)).collect();
    let pruned = next.len() - survivors.len();
    // Adam: surviving originals keep their moments (they come first), new ones start at zero.
    let old_survivors: Vec<usize> = survivors
        .iter()
        .take_while(|&&j| j < kept.len())
        .map(|&j| kept[j])
        .collect();
    let added = survivors.len() - old_survivors.len();
    adam.remap(&old_survivors, added);
    *g = if pruned == 0 {
        next
    } else {
        subset(&next, &survivors)
    };
    *stats = DensifyStats::new(g.len());
    DensifyOutcome {
        cloned,
        split: n_split,
        pruned,
        gaussians: g.len(),
    }
}

/// INRIA's opacity reset: every opacity above `cap` is brought down to it.
pub fn reset_opacity(g: &mut Gaussians, adam: &mut Adam, cap: f32) {
    let l = logit(cap);
    for o in &mut g.opacity_logits {
        *o = o.min(l);
    }
    adam.reset_opacity();
}

/// Rotation matrix (row-major) of a quaternion (w, x, y, z), normalised first.
fn rotation_matrix(q: [f32; 4]) -> [[f32; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    crate::render::rotation_matrix(q.map(|v| v / n))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four Gaussians: 0 small and pulled, 1 large and pulled, 2 quiet, 3 nearly transparent.
    fn scene() -> Gaussians {
        let mut g = Gaussians::with_capacity(4, 1);
        for (i, (scale, o)) in [(0.001f32, 0.5f32), (0.2, 0.5), (0.001, 0.5), (0.001, 0.001)]
            .into_iter()
            .enumerate()
        {
            g.means.push([i as f32, 0.0, 0.0]);
            g.log_scales
                .push([scale.ln(), (scale * 0.5).ln(), (scale * 0.25).ln()]);
            g.rotations.push([1.0, 0.0, 0.0, 0.0]);
            g.opacity_logits.push(logit(o));
            g.sh_dc.push([i as f32; 3]);
            g.sh_rest.extend([i as f32; 9]);
        }
        g
    }

    fn params() -> DensifyParams {
        DensifyParams {
            grad_threshold: 2e-4,
            percent_dense: 0.01,
            min_opacity: 0.005,
            max_world_scale: None,
            extent: 4.0,
            max_gaussians: 1_000,
        }
    }

    fn pulled(n: usize, which: &[usize]) -> DensifyStats {
        let mut s = DensifyStats::new(n);
        for &i in which {
            s.grad_accum[i] = 1e-3 * 3.0;
            s.denom[i] = 3;
        }
        s
    }

    #[test]
    fn the_ndc_gradient_is_the_pixel_gradient_times_half_the_image_size() {
        let mut s = DensifyStats::new(2);
        s.add_view(
            [(0, 3.0), (1, 0.0)].into_iter(),
            &[[1e-6, 0.0], [5.0, 5.0]],
            400,
            200,
        );
        s.add_view([(0, 5.0)].into_iter(), &[[0.0, 2e-6], [0.0, 0.0]], 400, 200);
        assert!((s.mean_grad(0) - (2e-4 + 2e-4) / 2.0).abs() < 1e-9);
        assert_eq!((s.denom[1], s.max_radii[0]), (0, 5.0));
    }

    #[test]
    fn small_pulled_gaussians_are_cloned_large_ones_split_and_transparent_ones_pruned() {
        let mut g = scene();
        let mut adam = Adam::new(&g);
        adam.m.means[2] = [7.0; 3];
        let mut stats = pulled(4, &[0, 1]);
        let out = densify_and_prune(&mut g, &mut adam, &mut stats, &params(), &mut Rng::new(1));
        assert_eq!((out.cloned, out.split, out.pruned), (1, 1, 1));
        // 0 and 2 kept, 3 pruned, 1 replaced: then the clone of 0 and 1's two children.
        assert_eq!(out.gaussians, 5);
        assert_eq!(g.len(), 5);
        assert_eq!(g.sh_dc[0], [0.0; 3]);
        assert_eq!(g.sh_dc[1], [2.0; 3]);
        assert_eq!(g.means[2], g.means[0]);
        for child in 3..5 {
            assert_eq!(g.sh_dc[child], [1.0; 3]);
            assert_eq!(g.sh_rest[child * 9..child * 9 + 9], [1.0; 9]);
            let ratio = (g.log_scales[child][0] - 0.2f32.ln()).exp();
            assert!((ratio - 1.0 / 1.6).abs() < 1e-5, "{ratio}");
            // Sampled within a few standard deviations of the parent.
            assert!((g.means[child][0] - 1.0).abs() < 0.2 * 5.0);
            assert_ne!(g.means[child], [1.0, 0.0, 0.0]);
        }
        // Moments follow their Gaussians; new ones start at zero; statistics restart.
        assert_eq!(adam.m.means[1], [7.0; 3]);
        assert_eq!(adam.m.means[2], [0.0; 3]);
        assert_eq!(adam.m.len(), 5);
        assert_eq!(stats, DensifyStats::new(5));
    }

    #[test]
    fn growth_stops_at_the_cap_taking_the_strongest_gradients_first() {
        let mut g = scene();
        let mut adam = Adam::new(&g);
        let mut stats = pulled(4, &[0, 2]);
        stats.grad_accum[2] *= 2.0;
        let p = DensifyParams {
            max_gaussians: 5,
            min_opacity: 0.0,
            ..params()
        };
        let out = densify_and_prune(&mut g, &mut adam, &mut stats, &p, &mut Rng::new(1));
        assert_eq!((out.cloned, out.split, out.gaussians), (1, 0, 5));
        assert_eq!(g.sh_dc[4], [2.0; 3]);
    }

    #[test]
    fn large_world_scales_are_pruned_only_when_asked() {
        let mut g = scene();
        let mut adam = Adam::new(&g);
        let p = DensifyParams {
            max_world_scale: Some(0.04),
            ..params()
        };
        let out = densify_and_prune(
            &mut g,
            &mut adam,
            &mut DensifyStats::new(4),
            &p,
            &mut Rng::new(1),
        );
        // 1 (0.2 > 0.04·4) and 3 (transparent) go.
        assert_eq!((out.pruned, out.gaussians), (2, 2));
        assert_eq!(g.sh_dc[1], [2.0; 3]);
    }

    #[test]
    fn an_opacity_reset_caps_opacities_and_forgets_their_moments() {
        let mut g = scene();
        let mut adam = Adam::new(&g);
        adam.v.opacity_logits[1] = 3.0;
        reset_opacity(&mut g, &mut adam, 0.01);
        assert!((g.opacity(0) - 0.01).abs() < 1e-6);
        assert!((g.opacity(3) - 0.001).abs() < 1e-6);
        assert_eq!(adam.v.opacity_logits[1], 0.0);
    }

    #[test]
    fn rotation_matrices_are_orthonormal_and_match_a_quarter_turn() {
        let r = rotation_matrix([0.5f32.sqrt(), 0.0, 0.0, 0.5f32.sqrt()]);
        // 90° about z: x → y.
        assert!((r[1][0] - 1.0).abs() < 1e-6 && r[0][0].abs() < 1e-6);
        let r = rotation_matrix([0.3, -0.4, 0.5, 0.2]);
        for a in 0..3 {
            for b in 0..3 {
                let dot: f32 = (0..3).map(|k| r[a][k] * r[b][k]).sum();
                assert!((dot - if a == b { 1.0 } else { 0.0 }).abs() < 1e-5);
            }
        }
    }
}
