//! Channel-wise group masks (§3.4, eqs. `masks` and `gate`).
//!
//! Five parameter channels g ∈ {δ_dc, ρ_rest, ω_opa, θ_rot, σ_sca}. From point-wise channel
//! weights w_g(j) the masks are
//!
//!   m^vis_g = max(clip(mean(w^vis_g\[VIS\]), 0, cap_g), floor_g),
//!   m^wm_g  = clip(median(w^wm_g\[WM★\]), 0, cap_g),
//!
//! and the gate routes ∂L_wm only to WM★ and ∂L_vis only to VIS, each scaled by its mask:
//! ∇θ_i^g L = m^wm_g ∇L_wm for i ∈ WM★, m^vis_g ∇L_vis for i ∈ VIS ([`apply_masks`], one call
//! per loss: the paper's "two passes").
//!
//! Choices (the paper leaves them open):
//! - Point-wise weights ([`channel_weights`]): the safety R_k of the expert whose parameter
//!   group holds the channel (§3.2's 𝒞_geo = {x, s, q}, 𝒞_app = {α, h⁰, h^≥1}): dc, rest and
//!   opacity take R₂ (appearance safety), rotation and scale take R₁ (geometric stability). The
//!   same weights serve both routes; the routes differ by aggregation (median over WM★, mean over
//!   VIS) and by the floor.
//! - As the equations aggregate over the set, every member of a group gets the same mask
//!   (hence "group mask"); [`MaskConfig::per_point`] instead clips each Gaussian's own weight
//!   with the same caps and floors (an alternative masking strategy for ablations).
//! - caps / floors ([`MaskConfig::default`]): the colour channels (dc, rest) are bounded only by
//!   their weights (cap 1); opacity, rotation and scale get at most half of their gradient
//!   (cap 0.5), because they change coverage and footprints — structure — where colour edits
//!   only tint. The VIS floors (dc 0.1, rest and opacity 0.05) keep every compensator able to
//!   repair colour however low its expert scores; geometry has no floor.
//! - Means are not among the five channels: their gradient is multiplied by
//!   [`MaskConfig::position`] (0 by default: positions stay fixed) on both routes.

use crate::render::Real;
use crate::scene::Gaussians;

/// The five gated channels, in mask order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Channel {
    Dc,
    Rest,
    Opacity,
    Rotation,
    Scale,
}

impl Channel {
    pub const ALL: [Channel; 5] = [
        Channel::Dc,
        Channel::Rest,
        Channel::Opacity,
        Channel::Rotation,
        Channel::Scale,
    ];

    /// Which expert's R_k weighs this channel (0-based k).
    pub fn expert(self) -> usize {
        match self {
            Channel::Dc | Channel::Rest | Channel::Opacity => 1,
            Channel::Rotation | Channel::Scale => 0,
        }
    }
}

/// Caps and floors of the masks.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct MaskConfig {
    /// cap_g, in [`Channel::ALL`] order.
    pub cap: [f32; 5],
    /// floor_g of the VIS masks.
    pub floor: [f32; 5],
    /// Multiplier of the means' gradient on both routes (not one of the five channels).
    pub position: f32,
    /// Per-Gaussian masks instead of the paper's group aggregates.
    pub per_point: bool,
    /// Every mask 1 (routing kept): the ablation without group masks.
    pub uniform: bool,
}

impl Default for MaskConfig {
    fn default() -> Self {
        Self {
            cap: [1.0, 1.0, 0.5, 0.5, 0.5],
            floor: [0.1, 0.05, 0.05, 0.0, 0.0],
            position: 0.0,
            per_point: false,
            uniform: false,
        }
    }
}

/// w_g(j) = R_{k(g)}(j) for every Gaussian (see the module docs).
pub fn channel_weights(r: &[[f32; 3]]) -> Vec<[f32; 5]> {
    r.iter()
        .map(|r| Channel::ALL.map(|c| r[c.expert()]))
        .collect()
}

/// The masks of every Gaussian of the split scene.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Masks {
    /// m^wm_g (group values; with `per_point` the median of the per-point masks, for reports).
    pub wm_group: [f32; 5],
    /// m^vis_g (group values; with `per_point` the mean of the per-point masks).
    pub vis_group: [f32; 5],
    /// Membership of WM★.
    pub is_carrier: Vec<bool>,
    /// Per Gaussian, the mask of its own route (m^wm for carriers, m^vis for the others).
    pub mask: Vec<[f32; 5]>,
    pub position: f32,
}

impl Masks {
    /// m^wm_g(i): 0 for Gaussians outside WM★.
    pub fn wm(&self, i: usize) -> [f32; 5] {
        if self.is_carrier[i] {
            self.mask[i]
        } else {
            [0.0; 5]
        }
    }

    /// m^vis_g(i): 0 for carriers.
    pub fn vis(&self, i: usize) -> [f32; 5] {
        if self.is_carrier[i] {
            [0.0; 5]
        } else {
            self.mask[i]
        }
    }
}

/// Builds the masks (eq. `masks`) from point-wise weights of the watermark and visual routes.
pub fn build_masks(
    w_wm: &[[f32; 5]],
    w_vis: &[[f32; 5]],
    is_carrier: &[bool],
    cfg: &MaskConfig,
) -> Masks {
    let n = is_carrier.len();
    assert!(
        w_wm.len() == n && w_vis.len() == n,
        "weights and roles disagree in length"
    );
    let wm_of = |w: f32, g: usize| {
        if cfg.uniform {
            1.0
        } else {
            w.clamp(0.0, cfg.cap[g])
        }
    };
    let vis_of = |w: f32, g: usize| {
        if cfg.uniform {
            1.0
        } else {
            w.clamp(0.0, cfg.cap[g]).max(cfg.floor[g])
        }
    };
    let mut wm_group = [0.0f32; 5];
    let mut vis_group = [0.0f32; 5];
    for g in 0..5 {
        let mut wm: Vec<f32> = (0..n)
            .filter(|&i| is_carrier[i])
            .map(|i| w_wm[i][g])
            .collect();
        let vis: Vec<f64> = (0..n)
            .filter(|&i| !is_carrier[i])
            .map(|i| w_vis[i][g] as f64)
            .collect();
        wm.sort_by(f32::total_cmp);
        let med = match wm.len() {
            0 => 0.0,
            l if l % 2 == 1 => wm[l / 2],
            l => 0.5 * (wm[l / 2 - 1] + wm[l / 2]),
        };
        let mean = if vis.is_empty() {
            0.0
        } else {
            (vis.iter().sum::<f64>() / vis.len() as f64) as f32
        };
        wm_group[g] = wm_of(med, g);
        vis_group[g] = vis_of(mean, g);
    }
    let mask: Vec<[f32; 5]> = (0..n)
        .map(|i| match (cfg.per_point, is_carrier[i]) {
            (false, true) => wm_group,
            (false, false) => vis_group,
            (true, true) => std::array::from_fn(|g| wm_of(w_wm[i][g], g)),
            (true, false) => std::array::from_fn(|g| vis_of(w_vis[i][g], g)),
        })
        .collect();
    if cfg.per_point {
        // Report the aggregates the group rule would see of the per-point masks.
        for g in 0..5 {
            let mut wm: Vec<f32> = (0..n)
                .filter(|&i| is_carrier[i])
                .map(|i| mask[i][g])
                .collect();
            wm.sort_by(f32::total_cmp);
            wm_group[g] = if wm.is_empty() { 0.0 } else { wm[wm.len() / 2] };
            let vis: Vec<f32> = (0..n)
                .filter(|&i| !is_carrier[i])
                .map(|i| mask[i][g])
                .collect();
            vis_group[g] = if vis.is_empty() {
                0.0
            } else {
                vis.iter().sum::<f32>() / vis.len() as f32
            };
        }
    }
    Masks {
        wm_group,
        vis_group,
        is_carrier: is_carrier.to_vec(),
        mask,
        position: cfg.position,
    }
}

/// Which loss a gradient came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// ∂L_wm: kept on WM★ only, scaled by m^wm.
    Watermark,
    /// ∂L_vis: kept on VIS only, scaled by m^vis.
    Visual,
}

/// Gates a gradient in place (eq. `gate`): each Gaussian's dc, rest, opacity, rotation and
/// scale gradients are multiplied by its mask for `route` (0 outside the route's set), its
/// mean gradient by the position multiplier (0 outside the set).
pub fn apply_masks<T: Real>(grad: &mut Gaussians<T>, masks: &Masks, route: Route) {
    let n = grad.len();
    assert_eq!(n, masks.mask.len(), "masks are for another scene");
    let rl = grad.rest_len();
    for i in 0..n {
        let on = masks.is_carrier[i] == (route == Route::Watermark);
        let m = if on { masks.mask[i] } else { [0.0; 5] };
        let [dc, rest, opa, rot, sca] = m.map(T::from_f32);
        let pos = T::from_f32(if on { masks.position } else { 0.0 });
        grad.means[i] = grad.means[i].map(|v| v * pos);
        grad.sh_dc[i] = grad.sh_dc[i].map(|v| v * dc);
        for v in &mut grad.sh_rest[i * rl..(i + 1) * rl] {
            *v = *v * rest;
        }
        grad.opacity_logits[i] = grad.opacity_logits[i] * opa;
        grad.rotations[i] = grad.rotations[i].map(|v| v * rot);
        grad.log_scales[i] = grad.log_scales[i].map(|v| v * sca);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn group_masks_follow_the_equations() {
        let is_carrier = [true, false, true, false, false, true];
        let w: Vec<[f32; 5]> = (0..6)
            .map(|i| std::array::from_fn(|g| (i as f32 + 1.0) * 0.1 + g as f32 * 0.01))
            .collect();
        let cfg = MaskConfig {
            cap: [1.0, 0.3, 1.0, 0.2, 1.0],
            floor: [0.0, 0.0, 0.9, 0.0, 0.0],
            ..MaskConfig::default()
        };
        let m = build_masks(&w, &w, &is_carrier, &cfg);
        // WM★ = {0, 2, 5}: weights 0.1, 0.3, 0.6 (+ 0.01 g); median 0.3 + 0.01 g, then caps.
        let want_wm = [0.3, 0.3, 0.32, 0.2, 0.34];
        // VIS = {1, 3, 4}: weights 0.2, 0.4, 0.5; mean 0.3667 + 0.01 g, caps, then floors.
        let want_vis = [0.366_667, 0.3, 0.9, 0.2, 0.406_667];
        for g in 0..5 {
            assert!(
                (m.wm_group[g] - want_wm[g]).abs() < 1e-5,
                "{:?}",
                m.wm_group
            );
            assert!(
                (m.vis_group[g] - want_vis[g]).abs() < 1e-5,
                "{:?}",
                m.vis_group
            );
        }
        assert_eq!(m.wm(0), m.wm_group);
        assert_eq!(m.vis(0), [0.0; 5]);
        assert_eq!(m.vis(1), m.vis_group);
        assert_eq!(m.wm(1), [0.0; 5]);
        // An even number of carriers takes the mean of the middle two.
        let m2 = build_masks(&w, &w, &[true, true, false, false, false, false], &cfg);
        assert!((m2.wm_group[0] - 0.15).abs() < 1e-6);
    }

    #[test]
    fn per_point_masks_clip_each_weight() {
        let w = vec![[2.0, -1.0, 0.5, 0.5, 0.5], [0.01, 0.01, 0.01, 0.01, 0.01]];
        let cfg = MaskConfig {
            per_point: true,
            ..MaskConfig::default()
        };
        let m = build_masks(&w, &w, &[true, false], &cfg);
        assert_eq!(m.mask[0], [1.0, 0.0, 0.5, 0.5, 0.5]);
        assert_eq!(m.mask[1], [0.1, 0.05, 0.05, 0.01, 0.01]);
    }

    #[test]
    fn channel_weights_take_the_channel_experts_r() {
        let w = channel_weights(&[[0.1, 0.2, 0.3]]);
        assert_eq!(w[0], [0.2, 0.2, 0.2, 0.1, 0.1]);
    }

    /// A gradient whose every entry is 1, for `n` Gaussians of SH degree 1.
    fn ones(n: usize) -> Gaussians<f64> {
        Gaussians {
            means: vec![[1.0; 3]; n],
            log_scales: vec![[1.0; 3]; n],
            rotations: vec![[1.0; 4]; n],
            opacity_logits: vec![1.0; n],
            sh_dc: vec![[1.0; 3]; n],
            sh_rest: vec![1.0; n * 9],
            sh_degree: 1,
        }
    }

    #[test]
    fn gate_zeroes_exactly_the_other_route_and_scales_its_own() {
        let is_carrier = [false, true, false, true];
        let m = Masks {
            wm_group: [0.9, 0.8, 0.7, 0.6, 0.5],
            vis_group: [0.1, 0.2, 0.3, 0.4, 0.0],
            is_carrier: is_carrier.to_vec(),
            mask: is_carrier
                .iter()
                .map(|&c| {
                    if c {
                        [0.9, 0.8, 0.7, 0.6, 0.5]
                    } else {
                        [0.1, 0.2, 0.3, 0.4, 0.0]
                    }
                })
                .collect(),
            position: 0.25,
        };
        for route in [Route::Watermark, Route::Visual] {
            let mut g = ones(4);
            apply_masks(&mut g, &m, route);
            for (i, &carrier) in is_carrier.iter().enumerate() {
                let on = carrier == (route == Route::Watermark);
                let want = if on { m.mask[i] } else { [0.0; 5] };
                let want_f = want.map(|v| v as f64);
                assert_eq!(g.sh_dc[i], [want_f[0]; 3], "{route:?} {i}");
                assert!(
                    g.sh_rest[i * 9..(i + 1) * 9]
                        .iter()
                        .all(|&v| v == want_f[1])
                );
                assert_eq!(g.opacity_logits[i], want_f[2]);
                assert_eq!(g.rotations[i], [want_f[3]; 4]);
                assert_eq!(g.log_scales[i], [want_f[4]; 3]);
                assert_eq!(g.means[i], [if on { 0.25 } else { 0.0 }; 3]);
            }
        }
        // The two routes partition the Gaussians: summing both gated passes of the same
        // gradient never gives a Gaussian both.
        let mut a = ones(4);
        let mut b = ones(4);
        apply_masks(&mut a, &m, Route::Watermark);
        apply_masks(&mut b, &m, Route::Visual);
        for i in 0..4 {
            assert!(a.sh_dc[i][0] == 0.0 || b.sh_dc[i][0] == 0.0);
        }
    }
}
