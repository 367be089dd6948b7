//! Per-Gaussian attribution records (the "why" of §3: where the message is carried and why
//! those carriers were selected), one JSON object per output Gaussian, written as JSON Lines.

use super::experts::ExpertScores;
use super::mask::Masks;
use super::sbag::{Role, Selection, SplitScene, Visibility};
use serde::{Deserialize, Serialize};
use std::io::{self, BufRead, Write};

/// Why one Gaussian of the watermarked scene is what it is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AttributionRecord {
    /// Index in the output (split) scene.
    pub index: u32,
    pub role: Role,
    /// Index of its parent (itself when untouched) in the scene as uploaded, before pruning.
    pub parent: u32,
    /// Child number: 0 = the carrier (or an untouched Gaussian), 1.. = compensators.
    pub child: u8,
    /// R₁..R₃ (geometric stability, appearance safety, redundancy certainty).
    pub r: [f32; 3],
    /// U₁..U₃, the experts' uncertainties.
    pub uncertainty: [f32; 3],
    /// S₁..S₃, the experts' quality scores.
    pub quality: [f32; 3],
    /// u = (R₁R₂R₃)^⅓.
    pub utility: f32,
    /// v, one-shot visibility.
    pub visibility: f32,
    /// Whether the parent was in the feasible set 𝓕.
    pub feasible: bool,
    /// Whether the parent came from WM₀ (top-B) rather than the proximity extension; `None`
    /// for untouched Gaussians.
    pub seed: Option<bool>,
    /// m^wm in channel order dc, rest, opacity, rotation, scale (zeros outside WM★).
    pub mask_wm: [f32; 5],
    /// m^vis in the same order (zeros for carriers).
    pub mask_vis: [f32; 5],
    /// This Gaussian's share of the watermark gradient, filled in by finetuning.
    pub wm_grad_share: Option<f32>,
}

/// One record per Gaussian of `split`. `kept` maps the pruned scene back to the upload
/// ([`super::prune::PruneReport::kept`]); `None` when nothing was pruned.
pub fn attribution_records(
    kept: Option<&[usize]>,
    scores: &ExpertScores,
    selection: &Selection,
    visibility: &Visibility,
    split: &SplitScene,
    masks: &Masks,
) -> Vec<AttributionRecord> {
    let n_in = scores.len();
    let mut seed = vec![None; n_in];
    for &i in &selection.wm0 {
        seed[i as usize] = Some(true);
    }
    for &i in &selection.prox {
        seed[i as usize] = Some(false);
    }
    (0..split.role.len())
        .map(|k| {
            let s = split.source[k] as usize;
            AttributionRecord {
                index: k as u32,
                role: split.role[k],
                parent: kept.map_or(s, |m| m[s]) as u32,
                child: split.child[k],
                r: selection.r[s],
                uncertainty: scores.u[s],
                quality: scores.s[s],
                utility: selection.u[s],
                visibility: visibility.v[s],
                feasible: selection.feasible[s],
                seed: if split.role[k] == Role::Untouched {
                    None
                } else {
                    seed[s]
                },
                mask_wm: masks.wm(k),
                mask_vis: masks.vis(k),
                wm_grad_share: None,
            }
        })
        .collect()
}

/// Writes the records as JSON Lines (one object per line).
pub fn write_jsonl<W: Write>(records: &[AttributionRecord], writer: W) -> io::Result<()> {
    let mut w = io::BufWriter::new(writer);
    for r in records {
        serde_json::to_writer(&mut w, r)?;
        w.write_all(b"\n")?;
    }
    w.flush()
}

/// Reads records written by [`write_jsonl`] (blank lines are skipped).
pub fn read_jsonl<R: BufRead>(reader: R) -> io::Result<Vec<AttributionRecord>> {
    let mut out = Vec::new();
    for line in reader.lines() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        out.push(serde_json::from_str(&line)?);
    }
    Ok(out)
}
