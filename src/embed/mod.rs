//! Embedding preparation (§3 of "Where, What, Why"): everything that happens before the
//! decoupled finetuning — which Gaussians to drop, which to write the message into, how they are
//! split, and which parameter channels each route may update.
//!
//! | file | paper | holds |
//! |---|---|---|
//! | [`prune`] | §3.1 "Prune by contribution" (from 3D-GSW) | V_π = ∂L^aux_π/∂C′ with zero override colours; prune V ≤ 1e-8 in every view |
//! | [`experts`] | §3.2 eqs. `z1`, `z2`, `z3`, `evidence_mapping` | geometry / appearance / redundancy features, E_k = [U_k, S_k] |
//! | [`knn`] | §3.2 𝒩_k(i) | exact k-d tree k-NN, parallel queries |
//! | [`stats`] | §3.2 "quantile-based min–max normalisation" | `Norm(·)`, quantiles |
//! | [`sbag`] | §3.3 eqs. `rk_clip`, `ui_sym`, `eta_overlap`, `self_budget_B`, `feasible_set_quantile`, `seed_topB`, `evidence_vec`, `parent_set`, `wstar` | ranking, one-shot visibility and crowding, budget, feasible set, top-B, proximity extension, render-equivalent split into carrier + compensators |
//! | [`mask`] | §3.4 eqs. `masks`, `gate` | channel-wise group masks, gradient gating per route |
//! | [`path`] | project-specific: the views the finetuning renders | cameras interpolated between consecutive training cameras along their capture path |
//! | [`attribution`] | §1/§5 per-Gaussian attribution | one record per output Gaussian, JSON Lines |
//!
//! [`plan`] runs them in order: prune → experts → SBAG → masks → attribution. The finetuning
//! (§3.5, planned) renders [`Plan::scene`], back-propagates L_wm and L_vis separately, and gates
//! each gradient with [`mask::apply_masks`] before its optimiser step.
//!
//! Every constant the paper does not give lives in a config struct under the paper's symbol
//! ([`experts::ExpertConfig`], [`sbag::SbagConfig`], [`mask::MaskConfig`],
//! [`prune::PruneConfig`]), with the reasons for its value in that module's docs.

pub mod attribution;
pub mod calibrate;
pub mod experts;
pub mod explain;
pub mod finetune;
pub mod knn;
pub mod mask;
pub mod path;
pub mod pipeline;
pub mod prune;
pub mod sbag;
pub mod stats;

use crate::render::RenderError;
use crate::scene::{Camera, Gaussians};

/// The Gaussians `idx` of `g`, in that order.
pub fn subset(g: &Gaussians, idx: &[usize]) -> Gaussians {
    let rl = g.rest_len();
    let mut out = Gaussians::with_capacity(idx.len(), g.sh_degree);
    for &i in idx {
        out.means.push(g.means[i]);
        out.log_scales.push(g.log_scales[i]);
        out.rotations.push(g.rotations[i]);
        out.opacity_logits.push(g.opacity_logits[i]);
        out.sh_dc.push(g.sh_dc[i]);
        out.sh_rest
            .extend_from_slice(&g.sh_rest[i * rl..(i + 1) * rl]);
    }
    out
}

/// Configuration of the whole preparation (default: the paper's pipeline, pruning included).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct EmbedConfig {
    /// `None` skips pruning.
    pub prune: Option<prune::PruneConfig>,
    pub experts: experts::ExpertConfig,
    pub sbag: sbag::SbagConfig,
    pub mask: mask::MaskConfig,
}

impl Default for EmbedConfig {
    fn default() -> Self {
        Self {
            prune: Some(prune::PruneConfig::default()),
            experts: Default::default(),
            sbag: Default::default(),
            mask: Default::default(),
        }
    }
}

/// Everything decided before finetuning.
#[derive(Clone, Debug)]
pub struct Plan {
    pub prune: Option<prune::PruneReport>,
    /// Expert scores of the pruned scene.
    pub scores: experts::ExpertScores,
    pub sbag: sbag::SbagResult,
    /// Masks of the split scene.
    pub masks: mask::Masks,
    /// One record per Gaussian of the split scene.
    pub records: Vec<attribution::AttributionRecord>,
}

impl Plan {
    /// The scene to finetune: pruned and split.
    pub fn scene(&self) -> &Gaussians {
        &self.sbag.split.gaussians
    }
}

/// Prunes `g` (if configured), scores it, selects and splits carriers for an `m_bits` message,
/// and builds the masks and attribution records. `cams` are the training views.
pub fn plan(
    g: &Gaussians,
    cams: &[Camera],
    m_bits: usize,
    cfg: &EmbedConfig,
) -> Result<Plan, RenderError> {
    plan_over(g, cams, cams, m_bits, cfg)
}

/// [`plan`], pruning by contribution over every training view in `cams` and measuring SBAG's
/// visibility over `visible` (a subset of them: [`pipeline::spread_views`]) — a Gaussian that
/// only a view outside the subset shows is kept, never pruned.
pub fn plan_over(
    g: &Gaussians,
    cams: &[Camera],
    visible: &[Camera],
    m_bits: usize,
    cfg: &EmbedConfig,
) -> Result<Plan, RenderError> {
    let (pruned, report) = match &cfg.prune {
        Some(p) => {
            let (s, r) = prune::prune(g, cams, p)?;
            (s, Some(r))
        }
        None => (g.clone(), None),
    };
    let scores = experts::trio_experts(&pruned, &cfg.experts);
    let sb = sbag::sbag(&pruned, &scores, visible, m_bits, &cfg.sbag)?;
    let split = &sb.split;
    let r_out: Vec<[f32; 3]> = split
        .source
        .iter()
        .map(|&s| sb.selection.r[s as usize])
        .collect();
    let w = mask::channel_weights(&r_out);
    let masks = mask::build_masks(&w, &w, &split.is_carrier(), &cfg.mask);
    let records = attribution::attribution_records(
        report.as_ref().map(|r| r.kept.as_slice()),
        &scores,
        &sb.selection,
        &sb.visibility,
        split,
        &masks,
    );
    Ok(Plan {
        prune: report,
        scores,
        sbag: sb,
        masks,
        records,
    })
}

#[cfg(test)]
mod tests;
