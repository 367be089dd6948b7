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
use crate::embed::explain::{Layer, Legend, Pictures};
use crate::scene::Gaussians;

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

/// The file name part of a layer (`diff10`: the difference is magnified ×10).
fn file_kind(layer: Layer) -> &'static str {
    match layer {
        Layer::Diff => "diff10",
        l => l.as_str(),
    }
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

    let pictures = Pictures::new(g, recs, original)?;
    let legend = pictures.legend();
    let layers: Vec<Layer> = Layer::ALL
        .into_iter()
        .filter(|&l| l != Layer::Diff || pictures.has_original())
        .collect();

    let mut rows = String::new();
    let mut bar = Progress::new(progress);
    bar.phase("explain", cams.len() as u64);
    for (k, cam) in cams.iter().enumerate() {
        let stem = format!("{:03}_{}", k, safe_name(&cam.name));
        let (w, h) = (cam.width, cam.height);
        let mut cells = Vec::with_capacity(layers.len());
        for &layer in &layers {
            let name = format!("{stem}_{}.png", file_kind(layer));
            pictures
                .draw_rgb8(layer, cam)?
                .save(a.out.join(&name))
                .with_context(|| format!("cannot write {name}"))?;
            cells.push(name);
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
    let Legend {
        gaussians,
        carriers,
        compensators,
        untouched,
        carrier_share,
        ..
    } = legend;
    let has_original = pictures.has_original();
    let html = format!(
        "<!doctype html>\n<meta charset=\"utf-8\">\n<title>splatmark explain: {scene}</title>\n\
         <style>body{{font-family:sans-serif}}td,th{{padding:4px}}img{{image-rendering:pixelated}}</style>\n\
         <h1>Where the message lives</h1>\n<p>{scene}: {n} Gaussians — {carriers} carriers \
         (red), {compensators} compensators (blue), {untouched} untouched (grey). The carriers \
         hold {share:.1} % of the watermark gradient; the heatmap shows each Gaussian's share \
         (black → red → yellow → white, linear, white at the 99th percentile).{diff}</p>\n\
         <table>\n<tr><th>view</th><th>render</th><th>roles</th><th>watermark gradient</th>{diffcol}</tr>\n{rows}</table>\n",
        scene = html_escape(&a.scene.display().to_string()),
        n = gaussians,
        share = 100.0 * carrier_share,
        diff = if has_original {
            " The last column is |watermarked − original| × 10."
        } else {
            ""
        },
        diffcol = if has_original {
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
            "gaussians": gaussians,
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
