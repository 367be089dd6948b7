//! Trio-Experts (§3.2, eqs. `z1`–`z3` and `evidence_mapping`): per-Gaussian priors computed from
//! the native parameters only (no pixels), each mapped to an evidence package E_k = [U_k, S_k].
//!
//! | expert | features (each quantile-normalised, then averaged) |
//! |---|---|
//! | z₁ geometry (𝒞_geo = {x, s, q}) | Iso = min s / max s; RotCons = (1/k) Σ_{j∈𝒩_k(i)} \|⟨q_i, q_j⟩\|; 1 − Norm(fp̄), fp̄ = exp(⅓ Σ_d log s_d) |
//! | z₂ appearance (𝒞_app = {α, h⁰, h^≥1}) | 1 − ρ^hf (AC energy ratio of the SH colour); g(α) double-sided opacity gate; c = Gaussian band-pass on the DC strength ‖h⁰‖₂ |
//! | z₃ redundancy (𝒞_red = {x, s, q, h⁰}) | (1/k) Σ_j w_ij r_ij, w_ij = exp(−d²_ij / (σ_o² (fp̄_i² + fp̄_j²))), r_ij = colour similarity × shape similarity |
//!
//! Evidence: S_k = Norm(z_k); U_k = Norm(Disp_𝒩(i)(z_k) + λ_k·Penalty_k(i)).
//!
//! Choices the paper leaves open (all in [`ExpertConfig`] or documented here):
//! - `Norm(a, b, c)` of several features is read as "normalise each feature with the quantile
//!   min–max, then average", which keeps z_k in [0, 1]. `Norm` clips at the
//!   [`ExpertConfig::norm_q`] quantiles (1 % / 99 %) so that outliers do not squash the rest.
//! - The k-NN neighbourhood is built on raw world positions (Euclidean, so that d_ij and the
//!   scales in w_ij share units), not on normalised coordinates.
//! - ρ^hf: with c(d) = 0.5 + Σ_l h_l Y_l(d) (orthonormal real SH), the mean colour over the
//!   sphere is m = 0.5 + C₀h⁰ and its variance is C₀² Σ_{l≥1} h_l² (C₀² = 1/4π); ρ^hf is the
//!   variance's share of the second moment, summed over RGB: the fraction of the colour's energy
//!   that is view-dependent. 0 for SH degree 0.
//! - g(α) = σ((α − α_lo)/τ_α)·σ((α_hi − α)/τ_α): low for near-transparent Gaussians (weak,
//!   easily removed carriers) and for near-opaque ones (at the 0.99 α clamp edits saturate and
//!   show).
//! - c_i = exp(−(‖h⁰_i‖ − μ_c)² / (2σ_c²)) with μ_c the scene's median DC strength and σ_c =
//!   [`ExpertConfig::dc_band_width`] × its robust standard deviation (IQR / 1.349): it prefers
//!   typical colours over near-grey (‖h⁰‖ → 0) and saturated (clamped) ones.
//! - r_ij = exp(−‖m_i − m_j‖² / (2τ_c²)) · BC(Σ_i, Σ_j), m the DC colour and BC the
//!   Bhattacharyya coefficient of two zero-mean Gaussians with the two covariances
//!   (det Σ_i det Σ_j)^¼ / det(½(Σ_i + Σ_j))^½ ∈ (0, 1], 1 iff same shape, size and orientation.
//! - σ_o = √2: the overlap integral of two isotropic Gaussians of std s_i, s_j at distance d is
//!   ∝ exp(−d² / (2(s_i² + s_j²))).
//! - Disp = the standard deviation of z_k over {i} ∪ 𝒩_k(i).
//! - Penalties (each in [0, 1]): geometry, isolation d̄_i / (d̄_i + fp̄_i) with d̄_i the mean
//!   neighbour distance (a Gaussian far from all its neighbours gets neighbourhood evidence that
//!   does not describe it); appearance, the share of DC colour channels outside [0, 1] (the
//!   renderer clamps below 0, and channels far outside the display range hide edits
//!   unpredictably); redundancy, 1 / (1 + Σ_j w_ij) (redundancy vouched for by few overlapping
//!   neighbours is uncertain).

use super::knn::{Knn, knn};
use super::stats::{NormBounds, norm, quantiles};
use crate::scene::{Gaussians, SH_C0, sigmoid};
use rayon::prelude::*;

/// Constants of the Trio-Experts that the paper does not give (see the module docs; defaults
/// in brackets).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ExpertConfig {
    /// k of the neighbourhood 𝒩_k(i) [16, as 3D-GS's own k-NN initialisation uses a few
    /// neighbours; enough for a stable dispersion].
    pub k: usize,
    /// Lower and upper quantiles of `Norm(·)` [1 %, 99 %].
    pub norm_q: (f32, f32),
    /// α_lo of the opacity gate g(α) [0.15].
    pub alpha_lo: f32,
    /// α_hi of the opacity gate g(α) [0.95, below the renderer's 0.99 α clamp].
    pub alpha_hi: f32,
    /// τ_α, the softness of both sides of g(α) [0.05].
    pub alpha_tau: f32,
    /// σ_c of the DC band-pass in units of the robust standard deviation of ‖h⁰‖ [1.0].
    pub dc_band_width: f32,
    /// σ_o of the overlap weight w_ij [√2, the overlap integral of two Gaussians].
    pub sigma_o: f32,
    /// τ_c, the width of the DC-colour similarity in linear RGB distance [0.1 ≈ 25/255].
    pub tau_color: f32,
    /// λ_k, the weight of expert k's penalty in U_k [0.5 each: a penalty of 1 weighs like a
    /// neighbourhood dispersion of 0.5, the largest a [0, 1] score can have].
    pub penalty_weight: [f32; 3],
}

impl Default for ExpertConfig {
    fn default() -> Self {
        Self {
            k: 16,
            norm_q: (0.01, 0.99),
            alpha_lo: 0.15,
            alpha_hi: 0.95,
            alpha_tau: 0.05,
            dc_band_width: 1.0,
            sigma_o: std::f32::consts::SQRT_2,
            tau_color: 0.1,
            penalty_weight: [0.5; 3],
        }
    }
}

/// The raw per-Gaussian features behind z₁..z₃ (before normalisation), kept for attribution and
/// for SBAG's evidence vector.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExpertFeatures {
    /// Iso_i = min(s)/max(s).
    pub iso: Vec<f32>,
    /// RotCons_i = mean |⟨q_i, q_j⟩| over 𝒩_k(i).
    pub rot_cons: Vec<f32>,
    /// fp̄_i = geometric mean of the scales (world units).
    pub footprint: Vec<f32>,
    /// ρ^hf_i, the AC (view-dependent) share of the SH colour energy.
    pub ac_ratio: Vec<f32>,
    /// g(α_i).
    pub opacity_gate: Vec<f32>,
    /// ‖h⁰_i‖₂.
    pub dc_strength: Vec<f32>,
    /// c_i, the band-pass of the DC strength.
    pub dc_band: Vec<f32>,
    /// (1/k) Σ_j w_ij r_ij (z₃ before normalisation).
    pub redundancy: Vec<f32>,
    /// Σ_j w_ij, the effective number of overlapping neighbours.
    pub overlap_mass: Vec<f32>,
    /// Mean distance to the k neighbours.
    pub knn_mean_dist: Vec<f32>,
    /// Expert-specific penalties Penalty_k(i).
    pub penalty: Vec<[f32; 3]>,
    /// Neighbourhood dispersion Disp(z_k).
    pub dispersion: Vec<[f32; 3]>,
}

/// Trio-Experts output for every Gaussian.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpertScores {
    /// z₁, z₂, z₃ ∈ [0, 1].
    pub z: Vec<[f32; 3]>,
    /// S_k = Norm(z_k) ∈ [0, 1]: quality.
    pub s: Vec<[f32; 3]>,
    /// U_k ∈ [0, 1]: uncertainty.
    pub u: Vec<[f32; 3]>,
    pub features: ExpertFeatures,
    /// The neighbourhoods 𝒩_k(i).
    pub knn: Knn,
}

impl ExpertScores {
    pub fn len(&self) -> usize {
        self.z.len()
    }

    pub fn is_empty(&self) -> bool {
        self.z.is_empty()
    }
}

/// Per-Gaussian quantities needed by the neighbourhood pass.
struct Basic {
    scale: [f32; 3],
    quat: [f32; 4],
    color: [f32; 3],
    /// Covariance (xx, xy, xz, yy, yz, zz), f64 for the determinants of tiny Gaussians.
    cov: [f64; 6],
    /// ln det Σ.
    ln_det: f64,
}

fn basic(g: &Gaussians, i: usize) -> Basic {
    let ls = g.log_scales[i];
    let scale = ls.map(f32::exp);
    let q = g.rotations[i];
    let n = (q.iter().map(|v| v * v).sum::<f32>()).sqrt().max(1e-12);
    let quat = q.map(|v| v / n);
    let color = g.sh_dc[i].map(|d| 0.5 + SH_C0 * d);
    let r = crate::render::rotation_matrix(quat.map(f64::from));
    let s2 = ls.map(|v| (2.0 * v as f64).exp());
    let c = |a: usize, b: usize| (0..3).map(|k| r[a][k] * r[b][k] * s2[k]).sum::<f64>();
    Basic {
        scale,
        quat,
        color,
        cov: [c(0, 0), c(0, 1), c(0, 2), c(1, 1), c(1, 2), c(2, 2)],
        ln_det: 2.0 * ls.iter().map(|&v| v as f64).sum::<f64>(),
    }
}

fn det_sym(c: [f64; 6]) -> f64 {
    let [a, b, cc, d, e, f] = c;
    a * (d * f - e * e) - b * (b * f - e * cc) + cc * (b * e - d * cc)
}

/// Bhattacharyya coefficient of two zero-mean Gaussians: 1 for equal covariances.
fn shape_similarity(a: &Basic, b: &Basic) -> f32 {
    let avg: [f64; 6] = std::array::from_fn(|k| 0.5 * (a.cov[k] + b.cov[k]));
    let det = det_sym(avg);
    if !(det > 0.0) {
        return 0.0;
    }
    let ln_bc = 0.25 * (a.ln_det + b.ln_det) - 0.5 * det.ln();
    (ln_bc.exp() as f32).clamp(0.0, 1.0)
}

/// ρ^hf of Gaussian `i` (see the module docs).
fn ac_ratio(g: &Gaussians, i: usize) -> f32 {
    let rest = g.rest_of(i);
    let c02 = SH_C0 * SH_C0;
    let mut mean2 = 0.0f32;
    let mut var = 0.0f32;
    for ch in 0..3 {
        let m = 0.5 + SH_C0 * g.sh_dc[i][ch];
        mean2 += m * m;
        var += c02 * rest.iter().skip(ch).step_by(3).map(|v| v * v).sum::<f32>();
    }
    let total = mean2 + var;
    if total > 0.0 { var / total } else { 0.0 }
}

/// Runs the three experts on every Gaussian of `g`.
pub fn trio_experts(g: &Gaussians, cfg: &ExpertConfig) -> ExpertScores {
    let n = g.len();
    let (qlo, qhi) = cfg.norm_q;
    let nb = knn(&g.means, cfg.k);
    let k = nb.k;
    let basics: Vec<Basic> = (0..n).into_par_iter().map(|i| basic(g, i)).collect();

    // Point-wise features.
    let iso: Vec<f32> = basics
        .par_iter()
        .map(|b| {
            let mx = b.scale.iter().copied().fold(f32::MIN, f32::max);
            let mn = b.scale.iter().copied().fold(f32::MAX, f32::min);
            if mx > 0.0 { mn / mx } else { 1.0 }
        })
        .collect();
    let footprint: Vec<f32> = (0..n)
        .into_par_iter()
        .map(|i| (g.log_scales[i].iter().sum::<f32>() / 3.0).exp())
        .collect();
    let ac: Vec<f32> = (0..n).into_par_iter().map(|i| ac_ratio(g, i)).collect();
    let gate = |a: f32| {
        sigmoid((a - cfg.alpha_lo) / cfg.alpha_tau) * sigmoid((cfg.alpha_hi - a) / cfg.alpha_tau)
    };
    let opacity_gate: Vec<f32> = (0..n).into_par_iter().map(|i| gate(g.opacity(i))).collect();
    let dc_strength: Vec<f32> = g
        .sh_dc
        .par_iter()
        .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
        .collect();
    let dc_band = {
        let q = quantiles(&dc_strength, &[0.25, 0.5, 0.75]).unwrap_or(vec![0.0; 3]);
        let sigma = (cfg.dc_band_width * (q[2] - q[0]) / 1.349).max(1e-6);
        dc_strength
            .par_iter()
            .map(|&c| (-(c - q[1]).powi(2) / (2.0 * sigma * sigma)).exp())
            .collect::<Vec<f32>>()
    };

    // Neighbourhood features.
    let inv_tc2 = 1.0 / (2.0 * cfg.tau_color * cfg.tau_color);
    let so2 = cfg.sigma_o * cfg.sigma_o;
    let neigh: Vec<[f32; 4]> = (0..n)
        .into_par_iter()
        .map(|i| {
            if k == 0 {
                return [0.0; 4];
            }
            let (bi, fi) = (&basics[i], footprint[i]);
            let (mut rot, mut red, mut mass, mut dist) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
            for (&j, &d2) in nb.of(i).iter().zip(nb.dist2_of(i)) {
                let (bj, fj) = (&basics[j as usize], footprint[j as usize]);
                let dot: f32 = (0..4).map(|a| bi.quat[a] * bj.quat[a]).sum();
                rot += dot.abs().min(1.0);
                let denom = so2 * (fi * fi + fj * fj);
                let w = if denom > 0.0 {
                    (-d2 / denom).exp()
                } else {
                    0.0
                };
                let dc: f32 = (0..3).map(|c| (bi.color[c] - bj.color[c]).powi(2)).sum();
                let r = (-dc * inv_tc2).exp() * shape_similarity(bi, bj);
                red += w * r;
                mass += w;
                dist += d2.sqrt();
            }
            let kf = k as f32;
            [rot / kf, red / kf, mass, dist / kf]
        })
        .collect();
    let rot_cons: Vec<f32> = neigh.iter().map(|v| v[0]).collect();
    let redundancy: Vec<f32> = neigh.iter().map(|v| v[1]).collect();
    let overlap_mass: Vec<f32> = neigh.iter().map(|v| v[2]).collect();
    let knn_mean_dist: Vec<f32> = neigh.iter().map(|v| v[3]).collect();

    // z_k: each feature normalised, then averaged.
    let n_iso = norm(&iso, qlo, qhi);
    let n_rot = norm(&rot_cons, qlo, qhi);
    let n_fp = norm(&footprint, qlo, qhi);
    let one_minus_ac: Vec<f32> = ac.iter().map(|v| 1.0 - v).collect();
    let n_ac = norm(&one_minus_ac, qlo, qhi);
    let n_gate = norm(&opacity_gate, qlo, qhi);
    let n_band = norm(&dc_band, qlo, qhi);
    let z1: Vec<f32> = (0..n)
        .map(|i| (n_iso[i] + n_rot[i] + (1.0 - n_fp[i])) / 3.0)
        .collect();
    let z2: Vec<f32> = (0..n)
        .map(|i| (n_ac[i] + n_gate[i] + n_band[i]) / 3.0)
        .collect();
    let z3 = norm(&redundancy, qlo, qhi);
    let zs = [z1, z2, z3];

    // Evidence packages.
    let penalty: Vec<[f32; 3]> = (0..n)
        .into_par_iter()
        .map(|i| {
            let d = knn_mean_dist[i];
            let iso_pen = if d + footprint[i] > 0.0 {
                d / (d + footprint[i])
            } else {
                0.0
            };
            let clamped = (0..3)
                .filter(|&c| !(0.0..=1.0).contains(&basics[i].color[c]))
                .count() as f32
                / 3.0;
            [iso_pen, clamped, 1.0 / (1.0 + overlap_mass[i])]
        })
        .collect();
    let dispersion: Vec<[f32; 3]> = (0..n)
        .into_par_iter()
        .map(|i| {
            std::array::from_fn(|e| {
                let z = &zs[e];
                let vals = std::iter::once(z[i]).chain(nb.of(i).iter().map(|&j| z[j as usize]));
                let m = (k + 1) as f32;
                let mean = vals.clone().sum::<f32>() / m;
                (vals.map(|v| (v - mean).powi(2)).sum::<f32>() / m).sqrt()
            })
        })
        .collect();
    let mut s = vec![[0.0f32; 3]; n];
    let mut u = vec![[0.0f32; 3]; n];
    for e in 0..3 {
        let se = norm(&zs[e], qlo, qhi);
        let raw: Vec<f32> = (0..n)
            .map(|i| dispersion[i][e] + cfg.penalty_weight[e] * penalty[i][e])
            .collect();
        let b = NormBounds::fit(&raw, qlo, qhi);
        for i in 0..n {
            s[i][e] = se[i];
            u[i][e] = b.apply(raw[i]);
        }
    }
    let z = (0..n).map(|i| [zs[0][i], zs[1][i], zs[2][i]]).collect();
    ExpertScores {
        z,
        s,
        u,
        features: ExpertFeatures {
            iso,
            rot_cons,
            footprint,
            ac_ratio: ac,
            opacity_gate,
            dc_strength,
            dc_band,
            redundancy,
            overlap_mass,
            knn_mean_dist,
            penalty,
            dispersion,
        },
        knn: nb,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::logit;
    use crate::scene::synthetic::{Rng, object_scene};

    fn push(
        g: &mut Gaussians,
        mean: [f32; 3],
        scales: [f32; 3],
        q: [f32; 4],
        o: f32,
        dc: [f32; 3],
    ) {
        g.means.push(mean);
        g.log_scales.push(scales.map(f32::ln));
        g.rotations.push(q);
        g.opacity_logits.push(logit(o));
        g.sh_dc.push(dc);
        let r = g.rest_len();
        g.sh_rest.extend(std::iter::repeat_n(0.0, r));
    }

    /// A jittered grid of similar Gaussians with random colours and rotations.
    fn grid(rng: &mut Rng) -> Gaussians {
        let mut g = Gaussians::with_capacity(0, 0);
        for x in 0..14 {
            for y in 0..14 {
                for z in 0..3 {
                    let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
                    let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
                    push(
                        &mut g,
                        [
                            x as f32 * 0.1 + rng.range(-0.01, 0.01),
                            y as f32 * 0.1 + rng.range(-0.01, 0.01),
                            z as f32 * 0.1,
                        ],
                        [
                            rng.range(0.02, 0.04),
                            rng.range(0.02, 0.04),
                            rng.range(0.01, 0.02),
                        ],
                        q.map(|v| v / l),
                        rng.range(0.3, 0.9),
                        [
                            rng.range(-1.5, 1.5),
                            rng.range(-1.5, 1.5),
                            rng.range(-1.5, 1.5),
                        ],
                    );
                }
            }
        }
        g
    }

    #[test]
    fn scores_are_in_unit_interval() {
        let g = object_scene(3000, 3, 11);
        let sc = trio_experts(&g, &ExpertConfig::default());
        assert_eq!(sc.len(), 3000);
        for v in sc.z.iter().chain(&sc.s).chain(&sc.u) {
            assert!(v.iter().all(|x| (0.0..=1.0).contains(x)), "{v:?}");
        }
        // Normalisation spreads every score over the unit interval.
        for e in 0..3 {
            let lo = sc.s.iter().map(|v| v[e]).fold(1.0, f32::min);
            let hi = sc.s.iter().map(|v| v[e]).fold(0.0, f32::max);
            assert!(lo == 0.0 && hi == 1.0, "S_{e} spans [{lo}, {hi}]");
        }
        // SH degree 3 scenes have view-dependent energy; degree 0 has none.
        assert!(
            sc.features
                .ac_ratio
                .iter()
                .all(|&r| (0.0..1.0).contains(&r))
        );
        assert!(sc.features.ac_ratio.iter().any(|&r| r > 0.0));
        let g0 = object_scene(500, 0, 11);
        let s0 = trio_experts(&g0, &ExpertConfig::default());
        assert!(s0.features.ac_ratio.iter().all(|&r| r == 0.0));
    }

    #[test]
    fn isotropic_beats_needle_in_geometry() {
        let mut rng = Rng::new(5);
        let mut g = grid(&mut rng);
        // Two Gaussians with the same footprint (geometric mean 0.03), rotation and context:
        // one a ball, one a needle (Iso = 0.1), at neighbouring grid positions.
        let (a, b) = (7 * 42 + 7 * 3 + 1, 6 * 42 + 6 * 3 + 1);
        g.log_scales[a] = [0.03f32.ln(); 3];
        let e = 10f32.powf(2.0 / 3.0);
        g.log_scales[b] = [
            (0.03 * e).ln(),
            (0.03 / e.sqrt()).ln(),
            (0.03 / e.sqrt()).ln(),
        ];
        g.rotations[b] = g.rotations[a];
        let sc = trio_experts(&g, &ExpertConfig::default());
        assert!((sc.features.footprint[a] - sc.features.footprint[b]).abs() < 1e-5);
        assert!(sc.features.iso[a] > 0.99 && sc.features.iso[b] < 0.11);
        assert!(
            sc.z[a][0] > sc.z[b][0] + 0.2,
            "z1 ball {} needle {}",
            sc.z[a][0],
            sc.z[b][0]
        );
        // A huge footprint lowers geometric stability too.
        let c = 5 * 42 + 5 * 3 + 1;
        let before = sc.z[c][0];
        g.log_scales[c] = g.log_scales[c].map(|v| v + 3.0);
        let sc2 = trio_experts(&g, &ExpertConfig::default());
        assert!(sc2.z[c][0] < before - 0.2, "{} vs {before}", sc2.z[c][0]);
    }

    #[test]
    fn duplicate_is_more_redundant_than_unique() {
        let mut rng = Rng::new(6);
        let mut g = grid(&mut rng);
        let a = 7 * 42 + 7 * 3 + 1;
        let unique = 4 * 42 + 9 * 3 + 1;
        // An exact twin of `a` a hair away.
        let mut m = g.means[a];
        m[0] += 1e-3;
        let (scales, q, o, dc) = (
            g.log_scales[a].map(f32::exp),
            g.rotations[a],
            g.opacity(a),
            g.sh_dc[a],
        );
        push(&mut g, m, scales, q, o, dc);
        let sc = trio_experts(&g, &ExpertConfig::default());
        let f = &sc.features;
        assert!(
            sc.z[a][2] > 0.9 && sc.z[unique][2] < 0.5,
            "z3 duplicate {} unique {} (raw {} {})",
            sc.z[a][2],
            sc.z[unique][2],
            f.redundancy[a],
            f.redundancy[unique]
        );
        assert!(sc.s[a][2] > sc.s[unique][2]);
        // The twin is vouched for by an overlapping neighbour: lower redundancy penalty.
        assert!(f.penalty[a][2] < f.penalty[unique][2]);
        // Changing the twin's colour far away removes the redundancy.
        let twin = g.len() - 1;
        g.sh_dc[twin] = g.sh_dc[a].map(|v| -v - 1.0);
        let sc2 = trio_experts(&g, &ExpertConfig::default());
        assert!(sc2.features.redundancy[a] < 0.5 * f.redundancy[a]);
    }

    #[test]
    fn appearance_prefers_mid_opacity_and_view_independent_colour() {
        let mut rng = Rng::new(8);
        let mut g = grid(&mut rng);
        let (mid, faint, opaque) = (100, 200, 300);
        let dc = g.sh_dc[mid];
        for i in [mid, faint, opaque] {
            g.sh_dc[i] = dc;
        }
        g.opacity_logits[mid] = logit(0.6);
        g.opacity_logits[faint] = logit(0.02);
        g.opacity_logits[opaque] = logit(0.999);
        let sc = trio_experts(&g, &ExpertConfig::default());
        let gate = &sc.features.opacity_gate;
        assert!(
            gate[mid] > 0.95 && gate[faint] < 0.1 && gate[opaque] < 0.4,
            "{gate:?}"
        );
        assert!(sc.z[mid][1] > sc.z[faint][1] && sc.z[mid][1] > sc.z[opaque][1]);

        // With SH degree 1, strong view-dependent colour lowers z₂.
        let mut g1 = g.clone();
        g1.sh_degree = 1;
        g1.sh_rest = vec![0.0; g1.len() * 9];
        for v in &mut g1.sh_rest[9 * 300..9 * 300 + 9] {
            *v = 1.0;
        }
        g1.sh_dc[300] = dc;
        g1.opacity_logits[300] = logit(0.6);
        let sc1 = trio_experts(&g1, &ExpertConfig::default());
        assert!(sc1.features.ac_ratio[300] > 0.3 && sc1.features.ac_ratio[mid] == 0.0);
        assert!(sc1.z[mid][1] > sc1.z[300][1] + 0.2);
    }

    #[test]
    fn uncertainty_rises_for_isolated_and_clamped_gaussians() {
        let mut rng = Rng::new(9);
        let mut g = grid(&mut rng);
        // A far-away floater: isolated (geometry penalty) and with no overlapping neighbours.
        let f = 10;
        g.means[f] = [30.0, -20.0, 5.0];
        g.sh_dc[f] = [4.0, -4.0, 4.0]; // every DC channel outside [0, 1]
        let sc = trio_experts(&g, &ExpertConfig::default());
        let med = |e: usize| {
            let mut v: Vec<f32> = sc.u.iter().map(|u| u[e]).collect();
            v.sort_by(f32::total_cmp);
            v[v.len() / 2]
        };
        assert!(sc.features.penalty[f][0] > 0.99);
        assert_eq!(sc.features.penalty[f][1], 1.0);
        for e in 0..3 {
            assert!(
                sc.u[f][e] > med(e),
                "U_{e} {} vs median {}",
                sc.u[f][e],
                med(e)
            );
        }
    }

    #[test]
    fn empty_and_single_gaussian_scenes() {
        let sc = trio_experts(&Gaussians::default(), &ExpertConfig::default());
        assert!(sc.is_empty());
        let g = object_scene(1, 1, 2);
        let sc = trio_experts(&g, &ExpertConfig::default());
        assert_eq!(sc.len(), 1);
        assert_eq!(sc.knn.k, 0);
        assert!(
            sc.s[0]
                .iter()
                .chain(&sc.u[0])
                .all(|x| (0.0..=1.0).contains(x))
        );
    }

    #[test]
    #[ignore = "timing: cargo test --lib experts_million -- --ignored --nocapture"]
    fn experts_million() {
        let g = object_scene(1_000_000, 3, 5);
        let t = std::time::Instant::now();
        let sc = trio_experts(&g, &ExpertConfig::default());
        eprintln!(
            "Trio-Experts, 1M Gaussians (SH 3): {:.2} s",
            t.elapsed().as_secs_f64()
        );
        assert_eq!(sc.len(), 1_000_000);
    }
}
