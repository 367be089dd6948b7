//! `splatmark explain`: attribution pictures — where the message lives and why, per view.
//!
//! For each view of the watermarked scene it writes the render, the scene with every Gaussian
//! coloured by its role (carriers red, compensators blue, untouched grey), a heatmap of each
//! Gaussian's share of the watermark gradient, and — given the original — the difference to it
//! magnified ×10 (as in the paper's figures); `index.html` shows them side by side.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;

use super::progress::{Progress, ProgressMode};
use super::{LimitArgs, ViewArgs, load, safe_name};
use crate::embed::attribution::{AttributionRecord, read_jsonl};
use crate::embed::sbag::Role;
use crate::render::{RenderOptions, render, to_rgb8};
use crate::scene::{Gaussians, SH_C0};

#[derive(Args, Debug)]
pub(crate) struct ExplainArgs {
    /// The watermarked scene.
    scene: PathBuf,
    /// Its attribution records (JSONL, from `embed --attribution` or the service's
    /// `GET /v1/assets/{id}/attribution`).
    #[arg(long)]
    attribution: PathBuf,
    /// The scene before watermarking: adds the difference to it, ×10.
    #[arg(long)]
    original: Option<PathBuf>,
    #[command(flatten)]
    views: ViewArgs,
    /// At most this many views.
    #[arg(long)]
    limit: Option<usize>,
    /// Output folder (PNG files and index.html).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    limits: LimitArgs,
}

/// Role colours (linear RGB): carriers, compensators, untouched.
const CARRIER: [f32; 3] = [0.95, 0.15, 0.1];
const COMPENSATOR: [f32; 3] = [0.1, 0.35, 0.95];
const UNTOUCHED: [f32; 3] = [0.55, 0.55, 0.55];

/// `g` with every Gaussian's view-independent colour set to `colour(i)` and its
/// view-dependent colour removed.
fn recoloured(g: &Gaussians, colour: impl Fn(usize) -> [f32; 3]) -> Gaussians {
    let mut c = g.clone();
    for i in 0..c.len() {
        c.sh_dc[i] = colour(i).map(|v| (v - 0.5) / SH_C0);
    }
    c.sh_rest.iter_mut().for_each(|v| *v = 0.0);
    c
}

/// A black → red → yellow → white ramp of `t` in [0, 1].
fn heat(t: f32) -> [f32; 3] {
    let t = t.clamp(0.0, 1.0) * 3.0;
    [
        t.min(1.0),
        (t - 1.0).clamp(0.0, 1.0),
        (t - 2.0).clamp(0.0, 1.0),
    ]
}

/// The records, checked against the scene: one per Gaussian, in index order.
fn records_for(g: &Gaussians, path: &Path) -> Result<Vec<AttributionRecord>> {
    let f = std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut recs = read_jsonl(std::io::BufReader::new(f))
        .with_context(|| format!("{} is not attribution JSONL", path.display()))?;
    recs.sort_by_key(|r| r.index);
    if recs.len() != g.len() || recs.iter().enumerate().any(|(i, r)| r.index as usize != i) {
        bail!(
            "{} holds {} records for a scene of {} Gaussians: it is not this scene's attribution",
            path.display(),
            recs.len(),
            g.len()
        );
    }
    Ok(recs)
}

pub(crate) fn explain_cmd(a: &ExplainArgs, progress: ProgressMode) -> Result<()> {
    let (_, g) = load(&a.scene, &a.limits)?;
    let recs = records_for(&g, &a.attribution)?;
    let original = match &a.original {
        Some(p) => Some(load(p, &a.limits)?.1),
        None => None,
    };
    let mut cams = a.views.cameras(&g)?;
    if let Some(n) = a.limit {
        cams.truncate(n);
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;

    let count = |role: Role| recs.iter().filter(|r| r.role == role).count();
    let shares: Vec<f32> = recs
        .iter()
        .map(|r| r.wm_grad_share.unwrap_or(0.0))
        .collect();
    let carrier_share: f64 = recs
        .iter()
        .zip(&shares)
        .filter(|(r, _)| r.role == Role::Carrier)
        .map(|(_, &s)| f64::from(s))
        .sum();
    // The heat scale: white at the 99th percentile of the non-zero shares (a few Gaussians
    // with most of the gradient would otherwise leave the rest black).
    let mut nonzero: Vec<f32> = shares.iter().copied().filter(|&s| s > 0.0).collect();
    nonzero.sort_by(f32::total_cmp);
    let top = nonzero
        .get(nonzero.len().saturating_sub(1) * 99 / 100)
        .copied()
        .unwrap_or(1.0)
        .max(f32::MIN_POSITIVE);
    let roles = recoloured(&g, |i| match recs[i].role {
        Role::Carrier => CARRIER,
        Role::Compensator => COMPENSATOR,
        _ => UNTOUCHED,
    });
    let heatmap = recoloured(&g, |i| heat(shares[i] / top));
    let black = RenderOptions {
        background: [0.0; 3],
        ..RenderOptions::default()
    };

    let mut rows = String::new();
    let mut bar = Progress::new(progress);
    bar.phase("explain", cams.len() as u64);
    for (k, cam) in cams.iter().enumerate() {
        let stem = format!("{:03}_{}", k, safe_name(&cam.name));
        let save = |kind: &str, w: u32, h: u32, px: &[[f32; 3]]| -> Result<String> {
            let name = format!("{stem}_{kind}.png");
            to_rgb8(w, h, px)
                .save(a.out.join(&name))
                .with_context(|| format!("cannot write {name}"))?;
            Ok(name)
        };
        let marked = render(&g, cam, &black)?;
        let (w, h) = (marked.width, marked.height);
        let mut cells = vec![save("view", w, h, &marked.image)?];
        cells.push(save("roles", w, h, &render(&roles, cam, &black)?.image)?);
        cells.push(save("heat", w, h, &render(&heatmap, cam, &black)?.image)?);
        if let Some(o) = &original {
            let before = render(o, cam, &black)?;
            let diff: Vec<[f32; 3]> = marked
                .image
                .iter()
                .zip(&before.image)
                .map(|(p, q)| {
                    [0, 1, 2].map(|c| {
                        ((p[c].clamp(0.0, 1.0) - q[c].clamp(0.0, 1.0)).abs() * 10.0).min(1.0)
                    })
                })
                .collect();
            cells.push(save("diff10", w, h, &diff)?);
        }
        rows += &format!(
            "<tr><th>{}</th>{}</tr>\n",
            html_escape(&cam.name),
            cells
                .iter()
                .map(|c| format!("<td><a href=\"{c}\"><img src=\"{c}\" width=\"256\"></a></td>"))
                .collect::<String>()
        );
        let line = format!("{} ({w}×{h})", cam.name);
        if bar.lines() {
            bar.println(&line);
        }
        bar.step(k as u64 + 1, &line);
    }
    bar.finish();
    let (carriers, compensators) = (count(Role::Carrier), count(Role::Compensator));
    let html = format!(
        "<!doctype html>\n<meta charset=\"utf-8\">\n<title>splatmark explain: {scene}</title>\n\
         <style>body{{font-family:sans-serif}}td,th{{padding:4px}}img{{image-rendering:pixelated}}</style>\n\
         <h1>Where the message lives</h1>\n<p>{scene}: {n} Gaussians — {carriers} carriers \
         (red), {compensators} compensators (blue), {untouched} untouched (grey). The carriers \
         hold {share:.1} % of the watermark gradient; the heatmap shows each Gaussian's share \
         (black → red → yellow → white, linear, white at the 99th percentile).{diff}</p>\n\
         <table>\n<tr><th>view</th><th>render</th><th>roles</th><th>watermark gradient</th>{diffcol}</tr>\n{rows}</table>\n",
        scene = html_escape(&a.scene.display().to_string()),
        n = g.len(),
        untouched = g.len() - carriers - compensators,
        share = 100.0 * carrier_share,
        diff = if original.is_some() {
            " The last column is |watermarked − original| × 10."
        } else {
            ""
        },
        diffcol = if original.is_some() {
            "<th>difference ×10</th>"
        } else {
            ""
        },
    );
    let index = a.out.join("index.html");
    std::fs::write(&index, html).with_context(|| format!("cannot write {}", index.display()))?;
    println!(
        "{}",
        serde_json::json!({
            "views": cams.len(),
            "gaussians": g.len(),
            "carriers": carriers,
            "compensators": compensators,
            "carrier_share": carrier_share,
            "index": index,
        })
    );
    Ok(())
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}
