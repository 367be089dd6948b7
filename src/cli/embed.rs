//! `splatmark embed`, `splatmark verify`, `splatmark eval`.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;

use super::progress::{Progress, ProgressMode};
use super::{DeviceArg, LimitArgs, ViewArgs, load};
use crate::decoder::WatermarkModel;
use crate::decoder::eval::read_images;
use crate::decoder::projection::ViewProjection;
use crate::decoder::registry::Pair;
use crate::decoder::train::DeviceChoice;
use crate::embed::attribution::write_jsonl;
use crate::embed::pipeline::{EmbedOptions, Phase, embed, split_views};
use crate::embed::sbag::BudgetMode;
use crate::render::RenderOptions;
use crate::scene::write_ply;
use crate::verify::eval::{EvalSettings, evaluate_scene};
use crate::verify::message::{parse_hex, random_message, to_hex};
use crate::verify::stats::detect;

/// The decoder to use.
#[derive(Args, Debug)]
pub(crate) struct ModelArgs {
    /// Decoder weights (.bpk with its .json sidecar); default: the shipped weights for --bits.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Device: cpu (burn `flex`, the CPU rasterizer), wgpu (any wgpu adapter, lavapipe
    /// included) or auto (a hardware GPU when there is one, else the CPU). `embed` renders
    /// and back-propagates its views there, and runs its decoder, image losses and attacks on
    /// the same device.
    #[arg(long, value_enum, default_value = "auto")]
    device: DeviceArg,
}

/// Carrier budget of `--budget`.
#[derive(Clone, Debug)]
pub(crate) enum BudgetArg {
    Adaptive,
    Percent(f32),
}

impl std::str::FromStr for BudgetArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "adaptive" {
            return Ok(Self::Adaptive);
        }
        let p: f32 = s
            .strip_suffix('%')
            .ok_or_else(|| format!("'{s}': use adaptive or a percentage such as 1% or 10%"))?
            .parse()
            .map_err(|_| format!("'{s}' is not a percentage"))?;
        if !(p > 0.0 && p <= 100.0) {
            return Err(format!("'{s}': the percentage must be in (0, 100]"));
        }
        Ok(Self::Percent(p / 100.0))
    }
}

#[derive(Args, Debug)]
pub(crate) struct EmbedArgs {
    /// Scene file (.ply, compressed .ply, .splat, .spz).
    scene: PathBuf,
    #[command(flatten)]
    views: ViewArgs,
    /// Message length: 32, 48 or 64.
    #[arg(long, default_value_t = 32)]
    bits: usize,
    /// Message as hex (bits/4 digits); default: a fresh random message.
    #[arg(long)]
    message: Option<String>,
    /// Watermarked scene (INRIA binary PLY).
    #[arg(long)]
    out: PathBuf,
    /// Per-Gaussian attribution (JSON Lines).
    #[arg(long)]
    attribution: Option<PathBuf>,
    /// Report (JSON): message, carriers, budget, timings, final metrics.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Every N-th view is held out of training (0: train on all).
    #[arg(long, default_value_t = 8)]
    holdout_every: usize,
    /// JSON file with the embedding options to start from (`EmbedOptions`, as the report's
    /// `options` prints them; any field left out keeps its default), or that JSON inline;
    /// flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Finetuning steps.
    #[arg(long)]
    steps: Option<usize>,
    /// After --steps, at most this many more steps until the training views decode to every bit
    /// (8-bit renders, logits averaged over them; checked every 25 steps)
    #[arg(long)]
    extra_steps: Option<usize>,
    /// Views per step (logits averaged over them).
    #[arg(long)]
    views_per_step: Option<usize>,
    /// Multiplier of the carriers' learning rates.
    #[arg(long)]
    wm_lr_scale: Option<f32>,
    /// Carrier budget: adaptive (the paper's SBAG budget), or a share of the Gaussians, e.g. 1%.
    #[arg(long, default_value = "adaptive")]
    budget: BudgetArg,
    /// Ablation: carriers drawn at random (same budget) instead of by SBAG.
    #[arg(long)]
    no_sbag: bool,
    /// Ablation: no channel-wise group masks (every mask 1, routing kept).
    #[arg(long)]
    no_group_mask: bool,
    /// Decode plainly instead of relative to the asset. By default the original's mean logits
    /// over the training views are measured first and written to the report
    /// (`reference_logits`): pass the report to `splatmark verify --report` / `eval --report`.
    #[arg(long)]
    no_reference: bool,
    /// Read the bits through the decoder's own head instead of the asset's matched head. By
    /// default the embedding fits a matched head on the original (eq. `matchedhead`) and
    /// writes it to the report (`view_projection`): pass the report to `verify --report` /
    /// `eval --report`.
    #[arg(long)]
    no_matched_head: bool,
    /// The paper's recipe instead of the default one: decoupled routes (carriers take the
    /// watermark loss, compensators the visual loss, channel masks), INRIA's learning rates on
    /// every channel, 2 views per step, plain decoding. --no-sbag and --no-group-mask are its
    /// ablations.
    #[arg(long, conflicts_with = "config")]
    paper: bool,
    /// Skip contribution pruning.
    #[arg(long)]
    no_prune: bool,
    /// Background colour r,g,b in [0, 1] (default black).
    #[arg(long, value_delimiter = ',', num_args = 3)]
    background: Option<Vec<f32>>,
    /// Seed of the finetuning's random draws (views, attacks) and of --no-sbag (default 0).
    #[arg(long)]
    seed: Option<u64>,
    /// Render the training views at these factors of their resolution too, comma separated
    /// (e.g. 1,2): the message then holds at the resolutions a dispute may render at.
    #[arg(long, value_delimiter = ',')]
    view_scales: Option<Vec<f32>>,
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    limits: LimitArgs,
}

/// The decoders `--weights` names (its coarse decoder beside it, when there is one), else the
/// shipped ones, on `--device`.
fn load_pair(m: &ModelArgs, bits: usize) -> Result<Pair> {
    let device = DeviceChoice::from(m.device).device();
    Ok(Pair::resolve(m.weights.as_deref(), bits, &device)?)
}

fn background(v: &[f32]) -> Result<[f32; 3]> {
    match v {
        [r, g, b] if v.iter().all(|x| (0.0..=1.0).contains(x)) => Ok([*r, *g, *b]),
        _ => bail!("--background needs three values in [0, 1]"),
    }
}

/// Writes `bytes` to `path` atomically (temporary file in the same folder, then rename).
fn write_atomic(path: &Path, f: impl FnOnce(&mut std::fs::File) -> Result<()>) -> Result<()> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot create a file in {}", dir.display()))?;
    f(tmp.as_file_mut())?;
    tmp.as_file().sync_all()?;
    tmp.persist(path)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

pub(crate) fn embed_cmd(a: &EmbedArgs, progress: ProgressMode) -> Result<()> {
    if ![32, 48, 64].contains(&a.bits) {
        bail!("--bits must be 32, 48 or 64, got {}", a.bits);
    }
    let message = match &a.message {
        Some(h) => parse_hex(h, a.bits)?,
        None => random_message(a.bits),
    };
    let (_, g) = load(&a.scene, &a.limits)?;
    let cams = a.views.cameras_for(&g, a.bits)?;
    let (train, held) = split_views(&cams, a.holdout_every);
    if train.is_empty() {
        bail!(
            "no training views left after holding out every {}-th",
            a.holdout_every
        );
    }
    // The splats go where --device says, and the decoder, the image losses and the attacks
    // with them (on a GPU: burn's wgpu runtime on the rasterizer's own device).
    let rasterizer = crate::render::gpu::Rasterizer::open(a.model.device.into())?;
    eprintln!("rasterizer: {}", rasterizer.describe());
    let decoders = Pair::resolve(
        a.model.weights.as_deref(),
        a.bits,
        &rasterizer.burn_device()?.autodiff(),
    )?;
    let mut opts: EmbedOptions = match &a.config {
        Some(p) => super::config::read_json_config(p, "embedding options")?,
        None if a.paper => EmbedOptions::paper(),
        None => EmbedOptions::default(),
    };
    opts.finetune.rasterizer = rasterizer;
    opts.no_group_mask |= a.no_group_mask;
    opts.reference &= !a.no_reference;
    opts.projection.matched &= !a.no_matched_head;
    if let Some(b) = &a.background {
        opts.finetune.background = background(b)?;
    }
    if let Some(s) = a.seed {
        opts.finetune.seed = s;
    }
    if let Some(v) = &a.view_scales {
        opts.view_scales = v.clone();
    }
    let seed = opts.finetune.seed;
    if a.no_prune {
        opts.plan.prune = None;
    }
    opts.plan.sbag.mode = match (&a.budget, a.no_sbag) {
        (BudgetArg::Adaptive, false) => opts.plan.sbag.mode,
        (BudgetArg::Adaptive, true) => BudgetMode::Random { seed },
        (BudgetArg::Percent(f), false) => BudgetMode::Fraction(*f),
        (BudgetArg::Percent(_), true) => {
            bail!("--no-sbag draws as many carriers as the adaptive budget; drop --budget")
        }
    };
    if let Some(s) = a.steps {
        opts.finetune.steps = s;
    }
    if let Some(s) = a.extra_steps {
        opts.finetune.extra_steps = s;
    }
    if let Some(v) = a.views_per_step {
        opts.finetune.views_per_step = v;
    }
    if let Some(s) = a.wm_lr_scale {
        opts.finetune.wm_lr_scale = s;
    }
    eprintln!(
        "embedding {} bits ({}) into {} ({} Gaussians) over {} training views ({} held out)",
        a.bits,
        to_hex(&message),
        a.scene.display(),
        g.len(),
        train.len(),
        held.len()
    );
    let every = (opts.finetune.steps / 20).max(1);
    let mut bar = Progress::new(progress);
    let out = embed(&g, &train, &message, &decoders, &opts, |p| {
        report_progress(&mut bar, &p, every);
        std::ops::ControlFlow::Continue(())
    })?;
    bar.finish();
    let r = &out.report;
    let st = &r.timings.steps;
    if let Some(c) = &r.choice {
        eprintln!("{}", c.describe());
    }
    eprintln!(
        "{} carriers + {} compensators (budget B = {}, {} pruned); carriers hold {:.1} % of the watermark gradient; {:.1} s (finetuning {:.1} s: render {:.1}, watermark {:.1}, visual {:.1}, backward {:.1}, update {:.1}{})",
        r.carriers,
        r.compensators,
        r.budget.b,
        r.pruned,
        100.0 * r.wm_grad_share_carriers,
        r.timings.total,
        r.timings.finetune,
        st.render,
        st.watermark,
        st.visual,
        st.backward,
        st.update,
        if st.images_on_device {
            "; the steps' images stayed on the GPU"
        } else {
            ""
        }
    );
    write_atomic(&a.out, |f| {
        write_ply(&out.scene, std::io::BufWriter::new(f))?;
        Ok(())
    })?;
    if let Some(p) = &a.attribution {
        write_atomic(p, |f| Ok(write_jsonl(&out.records, f)?))?;
    }
    let mut report = serde_json::to_value(&out.report)?;
    report["scene"] = serde_json::json!(a.scene);
    report["output"] = serde_json::json!(a.out);
    report["held_out_views"] = serde_json::json!(held.len());
    // Where the views were rendered and decoded: `cpu`, or the GPU adapter (as a job's report).
    report["rasterizer"] = serde_json::json!(opts.finetune.rasterizer.describe());
    if let Some(p) = &a.report {
        write_atomic(p, |f| {
            serde_json::to_writer_pretty(&mut *f, &report)?;
            f.write_all(b"\n")?;
            Ok(())
        })?;
    }
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

#[derive(Args, Debug)]
pub(crate) struct VerifyArgs {
    /// Rendered images of the disputed asset (PNG/JPEG); logits are averaged over them.
    #[arg(required = true)]
    images: Vec<PathBuf>,
    /// The registered message, hex; its length gives the number of bits.
    #[arg(long)]
    message: String,
    /// Family-wise false-positive rate of the decision.
    #[arg(long, default_value_t = 1e-6)]
    fpr: f64,
    /// The embedding's report (`splatmark embed --report`): when the embedding decoded relative
    /// to the asset (`reference` option), its reference logits are subtracted here too.
    #[arg(long)]
    report: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
}

/// Reports the embedding's progress: a phase per pipeline phase, a step per finetuning step
/// (in `--progress lines`, one line every `every` steps).
fn report_progress(bar: &mut Progress, p: &crate::embed::pipeline::Progress, every: usize) {
    let phase = |bar: &mut Progress, name: &str, total: u64| {
        if bar.lines() {
            bar.println(&format!("{name}…"));
        } else {
            bar.phase(name, total);
        }
    };
    match p.phase {
        Phase::Targets => phase(bar, "rendering targets", 0),
        Phase::Plan => phase(bar, "pruning, scoring, selecting and splitting carriers", 0),
        Phase::Calibrate => phase(
            bar,
            "measuring the original: matched head and reference logits",
            0,
        ),
        Phase::Finetune => {
            let Some(s) = p.log else { return };
            // After a decoder switch `p.step` counts on from the discarded steps (`s.step` is
            // the run's own).
            if s.step == 1 && !bar.lines() {
                bar.phase_from("finetune", p.total as u64, p.step.saturating_sub(1) as u64);
            }
            let line = format!(
                "L_wm {:.4} (bce clean {:.4}, eot {:.4}) | bits clean {:.3} eot {:.3} | L_vis {:.4} | {:.2} dB | {:.2} s/step",
                s.l_wm,
                s.bce_clean,
                s.bce_eot,
                s.bit_acc_clean,
                s.bit_acc_eot,
                s.l_vis,
                s.psnr,
                s.seconds
            );
            if bar.lines() {
                if s.step % every == 0 || s.step == 1 {
                    bar.println(&format!("step {}/{} | {line}", p.step, p.total));
                }
            } else {
                bar.step(p.step as u64, &line);
            }
        }
        Phase::Done => bar.finish(),
    }
}

/// The decoder a report's bits were written for, out of `decoders` (the main one without a
/// report, or when the report predates decoder digests), decoding relative to the asset when
/// the report carries reference logits (and through its view projection when it carries one).
/// An error when the report names a decoder that is not among `decoders`.
pub(crate) fn with_report_reference(
    decoders: Pair,
    report: Option<&Path>,
) -> Result<WatermarkModel> {
    let Some(p) = report else {
        return Ok(decoders.main);
    };
    let text = std::fs::read(p).with_context(|| format!("cannot read {}", p.display()))?;
    let r: serde_json::Value =
        serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", p.display()))?;
    if r.get("message_hex").is_none() {
        bail!("{} is not an embedding report", p.display());
    }
    let reference: Option<Vec<f32>> = serde_json::from_value(r["reference_logits"].clone())
        .with_context(|| format!("{}: reference_logits", p.display()))?;
    let projection: Option<ViewProjection> =
        serde_json::from_value(r["view_projection"].clone())
            .with_context(|| format!("{}: view_projection", p.display()))?;
    // The lengths first (every decoder of the pair reads the same number of bits)…
    let bits = decoders.main.bits();
    if let Some(v) = &projection
        && v.head.is_some()
        && v.head_bits() != bits
    {
        bail!(
            "{}: matched head for {} bits, the message has {bits}",
            p.display(),
            v.head_bits()
        );
    }
    if let Some(z) = &reference
        && z.len() != bits
    {
        bail!(
            "{}: reference for {} bits, the message has {bits}",
            p.display(),
            z.len()
        );
    }
    // …then the decoder: the bits were written for one; another reads them as noise.
    let model = match r.get("decoder").and_then(|d| d.as_str()) {
        None => decoders.main,
        Some(d) => match decoders.by_digest(d) {
            Some(m) => m.clone(),
            None => bail!(
                "{}: the watermark was written for decoder {}…, these weights are decoder {}… \
                 (pass the weights it was embedded with: --weights FILE)",
                p.display(),
                crate::decoder::artifact::short_digest(d),
                crate::decoder::artifact::short_digest(&decoders.main.digest())
            ),
        },
    };
    let model = match projection {
        Some(v) if v.features() != model.decoder.feature_count() => bail!(
            "{}: view projection over {} features, the decoder pools {}",
            p.display(),
            v.features(),
            model.decoder.feature_count()
        ),
        Some(v) => model.with_projection(v),
        None => model,
    };
    Ok(match reference {
        Some(z) => model.with_reference(z),
        None => model,
    })
}

pub(crate) fn verify_cmd(a: &VerifyArgs) -> Result<()> {
    let hex = a.message.trim().trim_start_matches("0x");
    let bits = hex.len() * 4;
    let message = parse_hex(hex, bits)?;
    let model = with_report_reference(load_pair(&a.model, bits)?, a.report.as_deref())?;
    let images = read_images(&a.images)?;
    let device = DeviceChoice::from(a.model.device).device();
    let report = crate::decoder::eval::decode_images(&model, &images, &device);
    let decoded: Vec<bool> = report.logits.iter().map(|&z| z > 0.0).collect();
    let d = detect(&decoded, &message, 1, a.fpr)?;
    let json = serde_json::json!({
        "images": a.images,
        "message": to_hex(&message),
        "decoded": to_hex(&decoded),
        "bit_accuracy": d.bit_accuracy,
        "matches": d.matches,
        "bits": d.bits,
        "p_value": d.p_value,
        "threshold": d.threshold,
        "fpr": d.fpr,
        "detected": d.detected,
    });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

#[derive(Args, Debug)]
pub(crate) struct EvalSceneArgs {
    /// The scene before watermarking.
    original: PathBuf,
    /// The watermarked scene.
    watermarked: PathBuf,
    /// The embedded message, hex.
    #[arg(long)]
    message: String,
    #[command(flatten)]
    views: ViewArgs,
    /// Evaluate on every N-th view (the views `embed --holdout-every N` held out); 0 or 1: all.
    #[arg(long, default_value_t = 8)]
    holdout_every: usize,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0.0, 0.0, 0.0])]
    background: Vec<f32>,
    #[arg(long, default_value_t = 1e-6)]
    fpr: f64,
    /// Seed of the random attacks.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Draws of each model attack (seeds --seed, --seed + 1, …): each row reports their mean
    /// and keeps each draw's accuracy.
    #[arg(long, default_value_t = crate::verify::eval::MODEL_DRAWS)]
    model_draws: usize,
    /// Print JSON (the only output format; accepted for scripts).
    #[arg(long)]
    json: bool,
    /// The embedding's report: its reference logits, if any, are subtracted (as `verify
    /// --report`).
    #[arg(long)]
    report: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    limits: LimitArgs,
}

pub(crate) fn eval_scene_cmd(a: &EvalSceneArgs) -> Result<()> {
    anyhow::ensure!(a.model_draws >= 1, "--model-draws must be at least 1");
    let hex = a.message.trim().trim_start_matches("0x");
    let message = parse_hex(hex, hex.len() * 4)?;
    let (_, original) = load(&a.original, &a.limits)?;
    let (_, marked) = load(&a.watermarked, &a.limits)?;
    // Views are placed around the original, so both scenes are seen from the same cameras.
    let cams = a.views.cameras(&original)?;
    let held = if a.holdout_every <= 1 {
        cams
    } else {
        split_views(&cams, a.holdout_every).1
    };
    if held.is_empty() {
        bail!("no held-out views; use more views or --holdout-every 1");
    }
    let model = with_report_reference(load_pair(&a.model, message.len())?, a.report.as_deref())?;
    let settings = EvalSettings {
        render: RenderOptions {
            background: background(&a.background)?,
            ..RenderOptions::default()
        },
        fpr: a.fpr,
        seed: a.seed,
        model_draws: a.model_draws,
    };
    eprintln!("evaluating on {} held-out views…", held.len());
    let t = std::time::Instant::now();
    let mut e = serde_json::to_value(evaluate_scene(
        &original, &marked, &held, &model, &message, &settings,
    )?)?;
    e["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
    e["message"] = serde_json::json!(to_hex(&message));
    println!("{}", serde_json::to_string_pretty(&e)?);
    Ok(())
}
