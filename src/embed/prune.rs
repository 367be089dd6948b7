//! Contribution pruning (§3.1, from 3D-GSW): V_π = ∂L^aux_π/∂C′ per training view π.
//!
//! Per view, the original scene is rendered as the reference GT; then it is rendered again with
//! temporary colours C′ = 0 for every Gaussian (through [`RenderOptions::colors`]: "zero colour"
//! means the composited colour itself is 0 — black — not SH DC = 0, which would be grey 0.5),
//! and L_aux = mean_{p,ch}(|R − GT| · R) with |R − GT| held constant. Then
//!
//!   V_i = ∂L_aux/∂C′_i = Σ_p |R_p − GT_p| · α_i(p)·T_i(p) / (3·P)   (per channel),
//!
//! which is [`crate::render::Gradients::colors`] for ∂L/∂R = |R − GT| / (3P). Both renders use
//! the same background, black by default as in 3D-GSW: then R ≡ 0, |R − GT| = GT, and V_i is
//! Gaussian i's blend weight weighted by the brightness of the reference where it lands. (With
//! another background, R = T_final·bg and |R − GT| is the difference to that.) A Gaussian is
//! pruned when its V (largest channel; every channel is ≥ 0) is ≤ the threshold (1e-8, the
//! paper's) in every view: it is hidden, off screen, or only covers pixels that render black.
//!
//! The threshold is on a mean over pixels, so it depends on the view resolution: 1e-8 means a
//! total GT-weighted blend weight of 3·P·1e-8 (0.019 pixels at 800×800).

use crate::render::{RenderError, RenderOptions, backward, render};
use crate::scene::{Camera, Gaussians};
use std::sync::Arc;

/// How to prune.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct PruneConfig {
    /// Gaussians whose V ≤ this in every view are removed (paper: 1e-8).
    pub threshold: f32,
    /// Background of both renders (3D-GSW: black).
    pub background: [f32; 3],
    /// Near plane of the renders.
    pub near: f32,
}

impl Default for PruneConfig {
    fn default() -> Self {
        Self {
            threshold: 1e-8,
            background: [0.0; 3],
            near: RenderOptions::default().near,
        }
    }
}

/// What pruning found.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PruneReport {
    /// Indices (into the input scene, increasing) of the Gaussians kept.
    pub kept: Vec<usize>,
    /// max over views of V_i (largest channel), per input Gaussian.
    pub v_max: Vec<f32>,
    /// Number of views used.
    pub views: usize,
    pub threshold: f32,
}

impl PruneReport {
    /// Number of Gaussians removed.
    pub fn removed(&self) -> usize {
        self.v_max.len() - self.kept.len()
    }
}

/// Computes V for every Gaussian in every view and decides which to keep.
pub fn contribution(
    g: &Gaussians,
    cams: &[Camera],
    cfg: &PruneConfig,
) -> Result<PruneReport, RenderError> {
    let n = g.len();
    let mut v_max = vec![0.0f32; n];
    let base = RenderOptions {
        background: cfg.background,
        near: cfg.near,
        ..RenderOptions::default()
    };
    let zeros: Arc<[[f32; 3]]> = vec![[0.0f32; 3]; n].into();
    let with_zeros = RenderOptions {
        colors: Some(zeros),
        ..base.clone()
    };
    for cam in cams {
        let gt = render(g, cam, &base)?;
        let r = render(g, cam, &with_zeros)?;
        let scale = 1.0 / (3.0 * r.image.len() as f64);
        let d_image: Vec<[f32; 3]> = r
            .image
            .iter()
            .zip(&gt.image)
            .map(|(a, b)| std::array::from_fn(|c| ((a[c] - b[c]).abs() as f64 * scale) as f32))
            .collect();
        let grads = backward(g, &r, &d_image)?;
        for (vm, c) in v_max.iter_mut().zip(&grads.colors) {
            *vm = vm.max(c[0].max(c[1]).max(c[2]));
        }
    }
    let kept = (0..n).filter(|&i| v_max[i] > cfg.threshold).collect();
    Ok(PruneReport {
        kept,
        v_max,
        views: cams.len(),
        threshold: cfg.threshold,
    })
}

/// Prunes `g`: the scene of the kept Gaussians and the report.
pub fn prune(
    g: &Gaussians,
    cams: &[Camera],
    cfg: &PruneConfig,
) -> Result<(Gaussians, PruneReport), RenderError> {
    let report = contribution(g, cams, cfg)?;
    Ok((super::subset(g, &report.kept), report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::logit;
    use glam::{Mat3, Vec3};

    fn push(g: &mut Gaussians, mean: [f32; 3], scale: [f32; 3], o: f32, color: [f32; 3]) {
        g.means.push(mean);
        g.log_scales.push(scale.map(f32::ln));
        g.rotations.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logits.push(logit(o));
        g.sh_dc.push(color.map(|c| (c - 0.5) / crate::scene::SH_C0));
    }

    fn front(name: &str, x: f32) -> Camera {
        Camera::from_pose(
            name,
            64,
            48,
            60.0,
            60.0,
            32.0,
            24.0,
            Mat3::IDENTITY,
            Vec3::new(x, 0.0, -4.0),
        )
    }

    #[test]
    fn prunes_hidden_and_off_screen_keeps_visible() {
        let mut g = Gaussians::with_capacity(0, 0);
        // 0, 1: two opaque walls at z = 0 and 0.05 (α clamps at 0.99, so one wall leaves
        // T = 0.01 and compositing stops behind the second).
        push(
            &mut g,
            [0.0, 0.0, 0.0],
            [3.0, 3.0, 0.01],
            0.9999,
            [0.8, 0.6, 0.4],
        );
        push(
            &mut g,
            [0.0, 0.0, 0.05],
            [3.0, 3.0, 0.01],
            0.9999,
            [0.3, 0.7, 0.5],
        );
        // 2: small, bright, well behind both walls.
        push(&mut g, [0.1, 0.0, 1.0], [0.05; 3], 0.9, [1.0, 1.0, 1.0]);
        // 3: far outside every view (and behind the cameras).
        push(&mut g, [0.0, 40.0, -30.0], [0.05; 3], 0.9, [1.0, 1.0, 1.0]);
        // 4: small, in front of the walls: visible.
        push(&mut g, [0.2, 0.1, -1.0], [0.05; 3], 0.5, [0.2, 0.9, 0.1]);
        // 5: visible and nearly black: V weights its blend weight by GT, and GT there is its
        //    dark colour blended over the bright wall, so it is kept.
        push(
            &mut g,
            [-0.3, 0.0, -0.5],
            [0.05; 3],
            0.5,
            [0.05, 0.05, 0.05],
        );
        // 6: a needle-thin, almost transparent Gaussian: never reaches α = 1/255.
        push(&mut g, [0.0, -0.2, -1.0], [0.05; 3], 0.003, [1.0, 1.0, 1.0]);
        let cams = [front("a", 0.0), front("b", 0.3), front("c", -0.3)];
        let (pruned, rep) = prune(&g, &cams, &PruneConfig::default()).unwrap();
        assert_eq!(rep.kept, vec![0, 1, 4, 5], "V: {:?}", rep.v_max);
        assert_eq!(pruned.len(), 4);
        assert_eq!(rep.removed(), 3);
        assert_eq!(rep.v_max[3], 0.0);
        assert_eq!(rep.v_max[2], 0.0);
        assert!(rep.v_max[4] > 1e-4);
        assert_eq!(pruned.means[2], g.means[4]);

        // Pruning does not change the renders (the removed Gaussians never composite).
        for cam in &cams {
            let a = render(&g, cam, &RenderOptions::default()).unwrap();
            let b = render(&pruned, cam, &RenderOptions::default()).unwrap();
            assert_eq!(a.image, b.image);
        }
    }

    #[test]
    fn v_is_the_gt_weighted_blend_weight() {
        // V_i = Σ_p GT_p·α_i T_i / (3P) with a black background: compare with blend weights
        // for a single Gaussian of uniform colour, where GT_p = c·α(p).
        let mut g = Gaussians::with_capacity(0, 0);
        push(&mut g, [0.0, 0.0, 0.0], [0.2; 3], 0.7, [0.5, 0.5, 0.5]);
        let cam = front("a", 0.0);
        let rep = contribution(&g, std::slice::from_ref(&cam), &PruneConfig::default()).unwrap();
        let r = render(&g, &cam, &RenderOptions::default()).unwrap();
        // GT_p = 0.5·α_p and the weight is α_p (T = 1): V = Σ 0.5·α²/(3P).
        let alpha: Vec<f32> = r.image.iter().map(|p| p[0] / 0.5).collect();
        let want: f64 = alpha.iter().map(|&a| 0.5 * (a as f64).powi(2)).sum::<f64>()
            / (3.0 * r.image.len() as f64);
        assert!(
            ((rep.v_max[0] as f64) - want).abs() < 1e-6 * want,
            "{} vs {want}",
            rep.v_max[0]
        );
    }
}
