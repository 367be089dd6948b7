//! Safety and Budget-Aware Gate (§3.3, eqs. `rk_clip` … `wstar`): ranks Gaussians by the
//! Trio-Experts evidence, sizes the carrier budget from one render of every training view,
//! selects and extends the carrier parents, and splits each into N_s children — one watermark
//! carrier (WM★) and N_s − 1 visual compensators.
//!
//! 1. Ranking: R_k = clip(S_k − β U_k, 0, 1) (eq. `rk_clip`), u_i = (R₁R₂R₃)^⅓ (eq. `ui_sym`).
//! 2. One-shot priors ([`visibility`]): every view rendered once (DC + opacity; colour does not
//!    enter either statistic). v_i = Norm(Σ_t b_i^t / P_t), b_i^t = Σ_p α_i T_i the blend weight
//!    of Gaussian i in view t with P_t pixels; v̄ = mean v_i. Crowding η (eq. `eta_overlap`):
//!    see [`Visibility::eta`] for the per-pixel weight used.
//! 3. Budget (eq. `self_budget_B`): κ_eff = κ₀·v̄·η, B = ⌈M / κ_eff⌉ ([`budget_size`]).
//! 4. Feasible set (eq. `feasible_set_quantile`): R_k ≥ Q_q(R_k) for k = 1..3 and v ≥ Q_q(v),
//!    and (our addition) the Gaussian admits a render-equivalent split ([`compensator_opacity`]);
//!    WM₀ = top-B of 𝓕 by u (eq. `seed_topB`), ties to the lower index.
//! 5. Prototype-based proximity extension (eqs. `evidence_vec`, `parent_set`): e_i =
//!    Norm(R₁, R₂, R₃, v, ρ^hf, ‖h⁰‖) per component; μ = mean e over WM₀; splittable Gaussians
//!    outside WM₀ with u > 0 and cos(e_i, μ) ≥ [`SbagConfig::prox_cos`] are recruited, most
//!    similar first, at most [`SbagConfig::prox_max_frac`]·|WM₀|. "Proximal" is read in
//!    evidence space (the paper recruits "by cosine similarity"), not in 3D.
//! 6. Split (eq. `wstar`): see [`split`] for the render-equivalent opacity rule.
//!
//! Budget modes ([`BudgetMode`]): the paper's adaptive B; a fixed fraction of the Gaussians
//! (the 1 % / 10 % ablation rows: exactly ⌈f·N⌉ parents, no extension, filled beyond 𝓕 by u when
//! 𝓕 is smaller); and random parents, as many as the adaptive run picks (`--no-sbag`).

use super::experts::ExpertScores;
use super::stats::{NormBounds, norm, quantile};
use crate::render::{ALPHA_MAX, ALPHA_MIN, RenderError, RenderOptions, render};
use crate::scene::synthetic::Rng;
use crate::scene::{Camera, Gaussians, logit};
use rayon::prelude::*;
use std::sync::Arc;

/// How many carrier parents to select.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BudgetMode {
    /// B = ⌈M/κ_eff⌉ (the paper); WM₀ never leaves the feasible set.
    Adaptive,
    /// B = ⌈f·N⌉ parents exactly (f in (0, 1]), no proximity extension.
    Fraction(f32),
    /// As many parents as [`BudgetMode::Adaptive`] selects, drawn uniformly at random among the
    /// splittable Gaussians (ablation without SBAG).
    Random { seed: u64 },
}

/// SBAG constants the paper does not give (defaults in brackets, with the reason).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct SbagConfig {
    /// β of eq. `rk_clip`, shared by the experts [0.25: U is min–max normalised, so it spans
    /// [0, 1]; β = 0.25 lets the most uncertain evidence cost a quarter of the score instead of
    /// zeroing most of the ranking].
    pub beta: f32,
    /// κ₀ of eq. `self_budget_B`: bits carried by one fully visible, uncrowded carrier [0.1:
    /// the paper's budget ablation (storage 164 / 178 / 195 MB at 1 % / adaptive / 10 %) fits
    /// N_s = 3 and an adaptive parent share of ≈ 5 % of ≈ 650k Gaussians, i.e. ≈ 3·10⁴ parents
    /// for M = 32, κ_eff ≈ 1e-3; our v̄·η is ≈ 0.01 on the shared real scenes, so κ₀ ≈ 0.1].
    pub kappa0: f32,
    /// q of the feasible set's quantile constraints [0.5: above the median on each of the four
    /// criteria, ≈ 5–10 % of a scene passes all, the order of the paper's adaptive share].
    pub feasible_q: f32,
    /// N_s, children per parent, 1 = no split [3: see `kappa0`].
    pub n_split: usize,
    /// Cosine similarity to the prototype needed to be recruited by the proximity extension
    /// [0.95].
    pub prox_cos: f32,
    /// At most this many recruits per WM₀ member [0.25, so the extension refines rather than
    /// replaces the top-B seed].
    pub prox_max_frac: f32,
    /// Largest change of a pixel's transmittance (so of its colour, per unit of contrast) that
    /// one split may cause; see [`split`] [0.5/255: half the tested per-pixel bound, leaving room
    /// for overlapping parents].
    pub split_tolerance: f32,
    /// Quantiles of Norm(·) for v and the evidence vector [1 %, 99 %, as the experts].
    pub norm_q: (f32, f32),
    /// ε of eq. `eta_overlap` [1e-6].
    pub eps: f32,
    /// Near plane of the visibility renders.
    pub near: f32,
    pub mode: BudgetMode,
}

impl Default for SbagConfig {
    fn default() -> Self {
        Self {
            beta: 0.25,
            kappa0: 0.1,
            feasible_q: 0.5,
            n_split: 3,
            prox_cos: 0.95,
            prox_max_frac: 0.25,
            split_tolerance: 0.5 / 255.0,
            norm_q: (0.01, 0.99),
            eps: 1e-6,
            near: RenderOptions::default().near,
            mode: BudgetMode::Adaptive,
        }
    }
}

/// One-shot visibility and crowding priors.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Visibility {
    /// v_i ∈ [0, 1].
    pub v: Vec<f32>,
    /// Σ_t b_i^t / P_t: Gaussian i's blend weight per pixel, summed over views.
    pub contribution: Vec<f32>,
    /// v̄.
    pub v_bar: f32,
    /// η ∈ (0, 1], mean of [`Visibility::eta_per_view`] over the views with any coverage.
    ///
    /// The paper's weight w_{i,p} is "the non-negative compositing weight"; read as α_i T_i it
    /// makes eq. `eta_overlap` identically 1 (Σ_i α_i T_i = 1 − T_p ≤ 1, so the min never
    /// binds). We take w_{i,p} = −ln(1 − α_i(p)), each composited splat's optical depth: ≈ α_i
    /// for thin splats, Σ_i w_{i,p} = −ln T_p (≤ ln 10⁴ through the renderer's T cut-off), and
    /// η = Σ_p min(1, −ln T_p) / (Σ_p −ln T_p + ε) measures overdraw: 1 when no pixel is covered
    /// more than once, small in crowded scenes.
    pub eta: f32,
    pub eta_per_view: Vec<f32>,
}

/// Renders every view once and measures v_i and η (see [`Visibility`]).
pub fn visibility(
    g: &Gaussians,
    cams: &[Camera],
    cfg: &SbagConfig,
) -> Result<Visibility, RenderError> {
    let n = g.len();
    let white: Arc<[[f32; 3]]> = vec![[1.0f32; 3]; n].into();
    let opts = RenderOptions {
        background: [0.0; 3],
        near: cfg.near,
        sh_degree: Some(0),
        blend_weights: true,
        colors: Some(white),
    };
    let mut contribution = vec![0.0f64; n];
    let mut eta_per_view = Vec::with_capacity(cams.len());
    for cam in cams {
        let r = render(g, cam, &opts)?;
        let per_px = 1.0 / r.image.len() as f64;
        let b = r
            .blend_weights
            .as_ref()
            .expect("blend weights were asked for");
        for (c, &w) in contribution.iter_mut().zip(b) {
            *c += w as f64 * per_px;
        }
        // White colours on black: pixel = Σ_i α_i T_i = 1 − T_p.
        let (num, den) = r
            .image
            .par_iter()
            .map(|p| {
                let t = (1.0 - p[0] as f64).clamp(1e-12, 1.0);
                let tau = -t.ln();
                (tau.min(1.0), tau)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        eta_per_view.push(if den > 0.0 {
            (num / (den + cfg.eps as f64)) as f32
        } else {
            f32::NAN
        });
    }
    let covered: Vec<f32> = eta_per_view
        .iter()
        .copied()
        .filter(|e| !e.is_nan())
        .collect();
    let eta = if covered.is_empty() {
        1.0
    } else {
        covered.iter().sum::<f32>() / covered.len() as f32
    };
    let contribution: Vec<f32> = contribution.into_iter().map(|c| c as f32).collect();
    let v = norm(&contribution, cfg.norm_q.0, cfg.norm_q.1);
    let v_bar = if n == 0 {
        0.0
    } else {
        (v.iter().map(|&x| x as f64).sum::<f64>() / n as f64) as f32
    };
    Ok(Visibility {
        v,
        contribution,
        v_bar,
        eta,
        eta_per_view,
    })
}

/// κ_eff = κ₀·v̄·η and B = ⌈M/κ_eff⌉ (eq. `self_budget_B`); B saturates at `usize::MAX` when
/// κ_eff is 0. The ceiling forgives a relative 1e-6 so that f32 inputs such as κ₀ = 0.02 (not
/// exact in binary) do not push an exact quotient to the next integer.
pub fn budget_size(m_bits: usize, kappa0: f32, v_bar: f32, eta: f32) -> (f32, usize) {
    let k = kappa0 as f64 * v_bar as f64 * eta as f64;
    let b = (m_bits as f64 / k * (1.0 - 1e-6)).ceil();
    let b = if b.is_finite() && b < usize::MAX as f64 {
        b.max(0.0) as usize
    } else {
        usize::MAX
    };
    (k as f32, b)
}

/// Budget and counts of one selection.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Budget {
    pub mode: BudgetMode,
    /// M, message length in bits.
    pub m_bits: usize,
    pub v_bar: f32,
    pub eta: f32,
    pub kappa_eff: f32,
    /// B of the mode: eq. `self_budget_B` (adaptive and random) or ⌈f·N⌉ (fraction).
    pub b: usize,
    /// |𝓕|.
    pub feasible: usize,
    /// Gaussians that admit no render-equivalent split (opacity too low, see
    /// [`compensator_opacity`]); never parents.
    pub unsplittable: usize,
    /// |WM₀|: min(B, |𝓕|) in adaptive mode.
    pub wm0: usize,
    /// WM₀ members taken from outside 𝓕 (fraction mode only).
    pub outside_feasible: usize,
    /// |WM_prox|.
    pub prox: usize,
    /// |WM_parent|.
    pub parents: usize,
}

/// The carrier selection on the (pruned) input scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Selection {
    /// R₁..R₃ per Gaussian.
    pub r: Vec<[f32; 3]>,
    /// u_i.
    pub u: Vec<f32>,
    /// Membership of 𝓕.
    pub feasible: Vec<bool>,
    /// WM₀ in selection order (best first).
    pub wm0: Vec<u32>,
    /// WM_prox in recruitment order.
    pub prox: Vec<u32>,
    /// WM_parent, increasing.
    pub parents: Vec<u32>,
    pub budget: Budget,
}

/// R_k = clip(S_k − βU_k, 0, 1) and u = (R₁R₂R₃)^⅓.
pub fn rank(scores: &ExpertScores, beta: f32) -> (Vec<[f32; 3]>, Vec<f32>) {
    let r: Vec<[f32; 3]> = scores
        .s
        .par_iter()
        .zip(&scores.u)
        .map(|(s, u)| std::array::from_fn(|k| (s[k] - beta * u[k]).clamp(0.0, 1.0)))
        .collect();
    let u = r.par_iter().map(|r| (r[0] * r[1] * r[2]).cbrt()).collect();
    (r, u)
}

/// Selects WM_parent (steps 1, 3–5 of the module docs) from expert scores and one-shot priors.
pub fn select(
    g: &Gaussians,
    scores: &ExpertScores,
    vis: &Visibility,
    m_bits: usize,
    cfg: &SbagConfig,
) -> Selection {
    let n = g.len();
    assert_eq!(scores.len(), n, "expert scores are for another scene");
    assert_eq!(vis.v.len(), n, "visibility is for another scene");
    let (r, u) = rank(scores, cfg.beta);
    let splittable: Vec<bool> = (0..n)
        .into_par_iter()
        .map(|i| compensator_opacity(g.opacity(i), cfg.n_split, cfg.split_tolerance).is_some())
        .collect();
    let unsplittable = splittable.iter().filter(|&&s| !s).count();

    let q = cfg.feasible_q;
    let col = |k: usize| r.iter().map(|v| v[k]).collect::<Vec<f32>>();
    let thr = [
        quantile(&col(0), q).unwrap_or(0.0),
        quantile(&col(1), q).unwrap_or(0.0),
        quantile(&col(2), q).unwrap_or(0.0),
        quantile(&vis.v, q).unwrap_or(0.0),
    ];
    let feasible: Vec<bool> = (0..n)
        .map(|i| {
            splittable[i]
                && r[i][0] >= thr[0]
                && r[i][1] >= thr[1]
                && r[i][2] >= thr[2]
                && vis.v[i] >= thr[3]
        })
        .collect();
    let n_feasible = feasible.iter().filter(|&&f| f).count();

    let (kappa_eff, b_adaptive) = budget_size(m_bits, cfg.kappa0, vis.v_bar, vis.eta);
    let by_utility = |pool: &mut Vec<u32>| {
        pool.sort_by(|&a, &b| u[b as usize].total_cmp(&u[a as usize]).then(a.cmp(&b)));
    };
    let mut in_f: Vec<u32> = (0..n as u32).filter(|&i| feasible[i as usize]).collect();
    by_utility(&mut in_f);
    let (b, mut wm0, outside) = match cfg.mode {
        BudgetMode::Fraction(f) => {
            let b = ((f.clamp(0.0, 1.0) as f64 * n as f64).ceil() as usize).min(n);
            let mut wm0: Vec<u32> = in_f.iter().copied().take(b).collect();
            let mut outside = 0;
            if wm0.len() < b {
                let mut rest: Vec<u32> = (0..n as u32)
                    .filter(|&i| splittable[i as usize] && !feasible[i as usize])
                    .collect();
                by_utility(&mut rest);
                let extra = (b - wm0.len()).min(rest.len());
                wm0.extend_from_slice(&rest[..extra]);
                outside = extra;
            }
            (b, wm0, outside)
        }
        _ => (
            b_adaptive,
            in_f.iter().copied().take(b_adaptive).collect(),
            0,
        ),
    };

    let mut prox = Vec::new();
    if !matches!(cfg.mode, BudgetMode::Fraction(_)) && !wm0.is_empty() {
        prox = proximity_extension(scores, vis, &r, &u, &wm0, &splittable, cfg);
    }
    let mut parents: Vec<u32> = wm0.iter().chain(&prox).copied().collect();
    if let BudgetMode::Random { seed } = cfg.mode {
        let mut pool: Vec<u32> = (0..n as u32).filter(|&i| splittable[i as usize]).collect();
        let take = parents.len().min(pool.len());
        let mut rng = Rng::new(seed);
        for k in 0..take {
            let j = k + (rng.next_u64() % (pool.len() - k) as u64) as usize;
            pool.swap(k, j);
        }
        pool.truncate(take);
        wm0 = pool;
        prox.clear();
        parents = wm0.clone();
    }
    parents.sort_unstable();
    let budget = Budget {
        mode: cfg.mode,
        m_bits,
        v_bar: vis.v_bar,
        eta: vis.eta,
        kappa_eff,
        b,
        feasible: n_feasible,
        unsplittable,
        wm0: wm0.len(),
        outside_feasible: outside,
        prox: prox.len(),
        parents: parents.len(),
    };
    Selection {
        r,
        u,
        feasible,
        wm0,
        prox,
        parents,
        budget,
    }
}

/// e_i = Norm(R₁, R₂, R₃, v, ρ^hf, ‖h⁰‖) (each component normalised separately).
pub fn evidence_vectors(
    scores: &ExpertScores,
    vis: &Visibility,
    r: &[[f32; 3]],
    norm_q: (f32, f32),
) -> Vec<[f32; 6]> {
    let f = &scores.features;
    let cols: [Vec<f32>; 6] = [
        r.iter().map(|v| v[0]).collect(),
        r.iter().map(|v| v[1]).collect(),
        r.iter().map(|v| v[2]).collect(),
        vis.v.clone(),
        f.ac_ratio.clone(),
        f.dc_strength.clone(),
    ];
    let b: [NormBounds; 6] = std::array::from_fn(|c| NormBounds::fit(&cols[c], norm_q.0, norm_q.1));
    (0..r.len())
        .into_par_iter()
        .map(|i| std::array::from_fn(|c| b[c].apply(cols[c][i])))
        .collect()
}

fn proximity_extension(
    scores: &ExpertScores,
    vis: &Visibility,
    r: &[[f32; 3]],
    u: &[f32],
    wm0: &[u32],
    splittable: &[bool],
    cfg: &SbagConfig,
) -> Vec<u32> {
    let e = evidence_vectors(scores, vis, r, cfg.norm_q);
    let mut mu = [0.0f64; 6];
    for &i in wm0 {
        for c in 0..6 {
            mu[c] += e[i as usize][c] as f64;
        }
    }
    let mu = mu.map(|v| (v / wm0.len() as f64) as f32);
    let mu_norm = mu.iter().map(|v| v * v).sum::<f32>().sqrt();
    let mut in_wm0 = vec![false; u.len()];
    for &i in wm0 {
        in_wm0[i as usize] = true;
    }
    let mut cand: Vec<(f32, u32)> = (0..u.len())
        .into_par_iter()
        .filter(|&i| !in_wm0[i] && splittable[i] && u[i] > 0.0)
        .filter_map(|i| {
            let n = e[i].iter().map(|v| v * v).sum::<f32>().sqrt();
            let cos = (0..6).map(|c| e[i][c] * mu[c]).sum::<f32>() / (n * mu_norm);
            (cos >= cfg.prox_cos).then_some((cos, i as u32))
        })
        .collect();
    cand.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let cap = (cfg.prox_max_frac.max(0.0) as f64 * wm0.len() as f64).floor() as usize;
    cand.truncate(cap);
    cand.into_iter().map(|(_, i)| i).collect()
}

/// A Gaussian's part in the decoupled finetuning.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// The child of a parent routed to the watermark branch (WM★).
    Carrier,
    /// Another child of a parent: a visual compensator (in VIS).
    Compensator,
    /// Not a parent: kept as is (in VIS).
    Untouched,
}

/// Opacity of each of the N_s − 1 compensator children of a parent of opacity `o`, or `None`
/// when no render-equivalent split with visible compensators exists (see [`split`]).
///
/// The children are composited together (same depth), so the pixel's transmittance through
/// them is (1 − α_parent(p))·(1 − a·G(p))^m, m = N_s − 1, G the shared footprint, where each
/// compensator only counts where a·G ≥ 1/255. Relative to the parent that changes T by at most
/// m·a·max_{G ∈ [G_c, 1]} G·(1 − min(0.99, o·G)), G_c = (1/255)/a. This is the largest a ≤ o/N_s
/// keeping that bound ≤ `tol`, found by bisection (the bound grows with a); `None` when even
/// a = 1.02/255, barely visible at the centre, exceeds it. For N_s = 3 and tol = 0.5/255 that
/// needs o ≳ 0.77 and gives a ≈ 0.4–0.5 % opacity.
pub fn compensator_opacity(o: f32, n_split: usize, tol: f32) -> Option<f32> {
    if n_split <= 1 {
        return Some(0.0);
    }
    let m = (n_split - 1) as f64;
    let o = o as f64;
    let tol = tol as f64;
    let a_min = ALPHA_MIN * 1.02;
    let hi = o / n_split as f64;
    let bound = |a: f64| {
        let gc = (ALPHA_MIN / a).min(1.0);
        let f = |g: f64| g * (1.0 - (o * g).min(ALPHA_MAX));
        let mut v = f(gc).max(f(1.0));
        let vertex = 0.5 / o;
        if vertex > gc && vertex < 1.0 {
            v = v.max(f(vertex));
        }
        m * a * v
    };
    if !(hi >= a_min) || bound(a_min) > tol {
        return None;
    }
    if bound(hi) <= tol {
        return Some(hi as f32);
    }
    let (mut lo, mut up) = (a_min, hi);
    for _ in 0..60 {
        let mid = 0.5 * (lo + up);
        if bound(mid) <= tol {
            lo = mid;
        } else {
            up = mid;
        }
    }
    Some(lo as f32)
}

/// The scene after splitting: per output Gaussian its role, the index of its source in the
/// input scene and its child number (0 = carrier; 0 for untouched Gaussians too).
#[derive(Clone, Debug, PartialEq)]
pub struct SplitScene {
    pub gaussians: Gaussians,
    pub role: Vec<Role>,
    pub source: Vec<u32>,
    pub child: Vec<u8>,
}

impl SplitScene {
    /// Membership of WM★ per output Gaussian.
    pub fn is_carrier(&self) -> Vec<bool> {
        self.role.iter().map(|&r| r == Role::Carrier).collect()
    }
}

/// Splits every parent into `n_split` children in place (children consecutive, carrier first;
/// other Gaussians keep their order).
///
/// Rule: every child has the parent's mean, scales, rotation and SH. The carrier keeps the
/// parent's opacity logit bit for bit; each compensator gets opacity a =
/// [`compensator_opacity`]. Why not the even split o_c = 1 − (1 − o)^(1/N_s): stacked children
/// then match the parent only at the footprint's peak; with α = o·G the stack gives 1 − (1 −
/// o_c·G)^N_s, far from o·G in the tails (≈ 0.25 off at G = 0.3 for o = 0.99, N_s = 3). No split
/// into several visible children can match everywhere: every child only counts where its own
/// α ≥ 1/255, so at the parent's footprint edge (α = 1/255) only one child can be visible, and
/// it must be the parent itself. Hence one child with the parent's exact opacity and faint
/// compensators that appear, inside the footprint, behind enough parent opacity to stay under
/// the tolerance. Parents without such a split are not selected (see [`select`]).
///
/// Panics when a parent is unsplittable or out of range.
pub fn split(g: &Gaussians, parents: &[u32], n_split: usize, tol: f32) -> SplitScene {
    let n = g.len();
    let mut is_parent = vec![false; n];
    for &p in parents {
        is_parent[p as usize] = true;
    }
    let extra = parents.len() * n_split.saturating_sub(1);
    let rl = g.rest_len();
    let mut out = Gaussians::with_capacity(n + extra, g.sh_degree);
    let mut role = Vec::with_capacity(n + extra);
    let mut source = Vec::with_capacity(n + extra);
    let mut child = Vec::with_capacity(n + extra);
    let mut push = |i: usize, logit_o: f32, r: Role, c: u8| {
        out.means.push(g.means[i]);
        out.log_scales.push(g.log_scales[i]);
        out.rotations.push(g.rotations[i]);
        out.opacity_logits.push(logit_o);
        out.sh_dc.push(g.sh_dc[i]);
        out.sh_rest
            .extend_from_slice(&g.sh_rest[i * rl..(i + 1) * rl]);
        role.push(r);
        source.push(i as u32);
        child.push(c);
    };
    for (i, &parent) in is_parent.iter().enumerate() {
        if !parent {
            push(i, g.opacity_logits[i], Role::Untouched, 0);
            continue;
        }
        push(i, g.opacity_logits[i], Role::Carrier, 0);
        if n_split > 1 {
            let a = compensator_opacity(g.opacity(i), n_split, tol)
                .unwrap_or_else(|| panic!("parent {i} admits no render-equivalent split"));
            for c in 1..n_split {
                push(i, logit(a), Role::Compensator, c as u8);
            }
        }
    }
    SplitScene {
        gaussians: out,
        role,
        source,
        child,
    }
}

/// Everything SBAG decides.
#[derive(Clone, Debug)]
pub struct SbagResult {
    pub visibility: Visibility,
    pub selection: Selection,
    pub split: SplitScene,
}

/// Runs SBAG end to end: one-shot priors, selection, split.
pub fn sbag(
    g: &Gaussians,
    scores: &ExpertScores,
    cams: &[Camera],
    m_bits: usize,
    cfg: &SbagConfig,
) -> Result<SbagResult, RenderError> {
    let visibility = visibility(g, cams, cfg)?;
    let selection = select(g, scores, &visibility, m_bits, cfg);
    let split = split(g, &selection.parents, cfg.n_split, cfg.split_tolerance);
    Ok(SbagResult {
        visibility,
        selection,
        split,
    })
}
