//! `splatmark decoder probe` and `splatmark decoder train-opt` (see `decoder::probe` and
//! `decoder::optrain`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use image::RgbImage;

use crate::decoder::WatermarkModel;
use crate::decoder::data::{ImageSet, Split};
use crate::decoder::model::Norm;
use crate::decoder::optrain::{self, OptRunOptions, OptTrainConfig};
use crate::decoder::probe::{ProbeOptions, probe};
use crate::decoder::train::DeviceChoice;

/// Which images of a folder.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SplitArg {
    /// The held-out split (FNV-1a of the relative path mod 10 == 0).
    HeldOut,
    /// Every image (e.g. a folder of renders of views no training used).
    All,
}

#[derive(Args, Debug)]
pub struct ProbeArgs {
    /// Image folders (each: .png/.jpg, recursive). Repeatable.
    #[arg(long, required = true)]
    images: Vec<PathBuf>,
    /// Which images of each folder.
    #[arg(long, value_enum, default_value = "held-out")]
    split: SplitArg,
    /// At most this many images per folder (in name order).
    #[arg(long)]
    limit: Option<usize>,
    /// Short side the images are resized to, then centre-cropped square.
    #[arg(long, default_value_t = 256)]
    size: u32,
    /// Message length.
    #[arg(long)]
    bits: usize,
    /// Decoder weights (.bpk with its .json sidecar); default: the shipped weights.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// PSNR bounds, comma separated.
    #[arg(long, value_delimiter = ',', default_value = "36,38,40")]
    psnr: Vec<f64>,
    /// Gradient steps per write.
    #[arg(long, default_value_t = 60)]
    iterations: usize,
    /// Random messages per image.
    #[arg(long, default_value_t = 2)]
    repeats: usize,
    /// Probability that a write step is attacked (EOT).
    #[arg(long, default_value_t = 0.8)]
    attack_prob: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the JSON report here.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Square `size`² images of `dirs` (the chosen split, at most `limit` per folder).
pub fn probe_images(
    dirs: &[PathBuf],
    split: SplitArg,
    limit: Option<usize>,
    size: u32,
) -> Result<Vec<RgbImage>> {
    let mut out = Vec::new();
    for dir in dirs {
        let split = match split {
            SplitArg::HeldOut => Split::HeldOut,
            SplitArg::All => Split::All,
        };
        let set = ImageSet::load(dir, split)
            .with_context(|| format!("cannot load images from {}", dir.display()))?;
        out.extend(
            set.images
                .iter()
                .take(limit.unwrap_or(usize::MAX))
                .map(|img| img.square_rgb8(size)),
        );
    }
    Ok(out)
}

pub fn probe_cmd(a: &ProbeArgs) -> Result<()> {
    let device = DeviceChoice::Flex.device().autodiff();
    let model = WatermarkModel::resolve(a.weights.as_deref(), a.bits, &device)?;
    let images = probe_images(&a.images, a.split, a.limit, a.size)?;
    let mut opts = ProbeOptions {
        psnrs: a.psnr.clone(),
        repeats: a.repeats,
        seed: a.seed,
        ..ProbeOptions::default()
    };
    opts.embed.iterations = a.iterations;
    opts.embed.attack_prob = a.attack_prob;
    eprintln!(
        "probing {} bits on {} images ({}²) at {:?} dB, {} write steps…",
        model.bits(),
        images.len(),
        a.size,
        opts.psnrs,
        opts.embed.iterations
    );
    let report = probe(&model, &images, &opts, &device)?;
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &a.out {
        std::fs::write(out, &json).with_context(|| format!("cannot write {}", out.display()))?;
    }
    println!("{json}");
    Ok(())
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum NormArg {
    Batch,
    Group,
    None,
}

#[derive(Args, Debug)]
pub struct TrainOptArgs {
    /// Training images (.png/.jpg, recursive); the held-out split is left out of training.
    #[arg(long)]
    images: PathBuf,
    #[arg(long)]
    bits: usize,
    /// Output decoder weights; checkpoints go to <OUT>.ckpt/.
    #[arg(long)]
    out: PathBuf,
    /// Continue from the newest checkpoint (its settings; --steps may extend).
    #[arg(long)]
    resume: bool,
    /// Start from a JSON `OptTrainConfig` (a file, or the JSON inline).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Folders whose held-out images the final probe uses (default: --images).
    #[arg(long)]
    probe_images: Vec<PathBuf>,
    /// Skip the final probe.
    #[arg(long)]
    no_final_probe: bool,
    #[arg(long)]
    steps: Option<usize>,
    #[arg(long)]
    batch_size: Option<usize>,
    #[arg(long)]
    unmarked: Option<usize>,
    #[arg(long)]
    crop: Option<usize>,
    #[arg(long)]
    lr: Option<f64>,
    #[arg(long)]
    psnr_start_db: Option<f64>,
    #[arg(long)]
    psnr_end_db: Option<f64>,
    #[arg(long)]
    psnr_ramp_steps: Option<usize>,
    #[arg(long)]
    inner_steps: Option<usize>,
    #[arg(long)]
    attack_warmup: Option<usize>,
    #[arg(long)]
    attack_ramp: Option<usize>,
    #[arg(long)]
    attack_prob_max: Option<f64>,
    #[arg(long)]
    unmarked_weight: Option<f64>,
    #[arg(long)]
    decoder_channels: Option<usize>,
    #[arg(long)]
    decoder_depth: Option<usize>,
    #[arg(long, value_enum)]
    norm: Option<NormArg>,
    /// Decoder convolution kernel (3; 1 = per-pixel).
    #[arg(long)]
    kernel: Option<usize>,
    /// Gain on the decoder's input band.
    #[arg(long)]
    input_gain: Option<f64>,
    /// Colour-Fourier features instead of convolutions (a function of the band's colour
    /// histogram; 0 = convolutional decoder).
    #[arg(long)]
    fourier: Option<usize>,
    /// Standard deviation of the colour frequencies (per unit of the centred band).
    #[arg(long)]
    fourier_scale: Option<f64>,
    /// Colour-Fourier decoder: pixels darker than this (in [0, 1]) do not count.
    #[arg(long)]
    fourier_dark: Option<f64>,
    /// Fit a whitening of the logits on this many clean training crops at the end (0 = none).
    #[arg(long)]
    whitening_samples: Option<usize>,
    #[arg(long)]
    seed: Option<u64>,
    #[arg(long)]
    checkpoint_every: Option<usize>,
    #[arg(long)]
    keep_checkpoints: Option<usize>,
    #[arg(long)]
    log_every: Option<usize>,
}

fn read_config(p: &Path) -> Result<OptTrainConfig> {
    super::config::read_json_config(p, "train-opt options")
}

pub fn train_opt_cmd(a: &TrainOptArgs) -> Result<()> {
    let mut c = match &a.config {
        Some(p) => read_config(p)?,
        None => OptTrainConfig::default(),
    };
    c.bits = a.bits;
    macro_rules! set {
        ($($field:ident),*) => {$(
            if let Some(v) = a.$field {
                c.$field = v;
            }
        )*};
    }
    set!(
        steps,
        batch_size,
        unmarked,
        crop,
        lr,
        psnr_start_db,
        psnr_end_db,
        psnr_ramp_steps,
        inner_steps,
        attack_warmup,
        attack_ramp,
        attack_prob_max,
        unmarked_weight,
        decoder_channels,
        decoder_depth,
        kernel,
        input_gain,
        fourier,
        fourier_scale,
        fourier_dark,
        whitening_samples,
        seed,
        checkpoint_every,
        keep_checkpoints,
        log_every
    );
    if let Some(n) = a.norm {
        c.norm = match n {
            NormArg::Batch => Norm::Batch,
            NormArg::Group => Norm::Group,
            NormArg::None => Norm::Off,
        };
    }
    if a.no_final_probe {
        c.final_probe = None;
    }
    let train = ImageSet::load(&a.images, Split::Train)?;
    let probe_dirs = if a.probe_images.is_empty() {
        vec![a.images.clone()]
    } else {
        a.probe_images.clone()
    };
    let probe_images = if c.final_probe.is_some() {
        probe_images(&probe_dirs, SplitArg::HeldOut, Some(16), 256)?
    } else {
        Vec::new()
    };
    eprintln!(
        "training a {}-bit decoder with the optimiser as encoder on {} images…",
        c.bits,
        train.len()
    );
    let opts = OptRunOptions {
        out: &a.out,
        resume: a.resume,
        probe_images,
        command: Some(super::command_line()),
        data: Some(a.images.display().to_string()),
    };
    let report = optrain::run(c, train, opts, &mut std::io::stderr())?;
    if let Some(r) = report {
        println!("{}", serde_json::to_string_pretty(&r)?);
    }
    Ok(())
}

#[derive(clap::Subcommand, Debug)]
pub enum BenchCommand {
    /// Embed with the defaults a user gets and evaluate on views the finetuning never saw,
    /// against the targets (docs/RESULTS.md). JSON on stdout (and --out), markdown
    /// with --markdown.
    Quality(QualityArgs),
    /// The paper's protocol: fit (or reuse) 3D-GS scenes of its datasets (lego, fern), embed
    /// through their training cameras, evaluate on their test cameras; Tables 1, 2, 3, 5, 6
    /// with the paper's published rows beside ours. JSON on stdout (and --out), markdown with
    /// --markdown.
    Paper(PaperArgs),
}

#[derive(Args, Debug)]
pub struct PaperArgs {
    /// The CI variant: lego at 128², a 300-step fit, 32 bits, 12 training and 4 test views, no
    /// ablations.
    #[arg(long)]
    quick: bool,
    /// Folder holding nerf_synthetic_lego/ and llff_fern/.
    #[arg(long, default_value = "../shared/data/datasets")]
    datasets: PathBuf,
    /// Only these datasets (comma separated: lego, fern).
    #[arg(long, value_delimiter = ',')]
    only: Option<Vec<String>>,
    /// Where fitted scenes are kept and reused (default: $SPLATMARK_CACHE, else
    /// $XDG_CACHE_HOME/splatmark, else ~/.cache/splatmark; fits/ inside).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Fitting steps (default 7000).
    #[arg(long)]
    fit_iterations: Option<usize>,
    /// Longest image side for every dataset (default: lego 400, fern its images_8 size).
    #[arg(long)]
    max_side: Option<u32>,
    /// Message lengths (comma separated; default 32,48,64).
    #[arg(long, value_delimiter = ',')]
    bits: Option<Vec<usize>>,
    /// Seeds (comma separated; default 0): results as mean ± std over them.
    #[arg(long, value_delimiter = ',')]
    seeds: Option<Vec<u64>>,
    /// Skip Tables 5 and 6 (the ablations of the paper's recipe).
    #[arg(long)]
    no_ablations: bool,
    /// Embedding options of Tables 1–3 (a JSON file or the JSON inline, as `embed --config`);
    /// default: the defaults a user gets.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Folder with decoder-{bits}.bpk artifacts (default: the shipped weights).
    #[arg(long)]
    weights_dir: Option<PathBuf>,
    /// Embed and evaluate at this fraction of each camera's resolution (default 1: the
    /// protocol; the fit is reused at its own size). A cheaper run, stated in the output.
    #[arg(long)]
    view_scale: Option<f32>,
    /// Run every embedding again, even those finished before with the same inputs (kept in
    /// the cache's runs/ folder).
    #[arg(long)]
    fresh: bool,
    /// Write the JSON report here too.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the markdown tables here.
    #[arg(long)]
    markdown: Option<PathBuf>,
}

/// The folder fitted scenes are cached in.
fn fit_cache(explicit: Option<&PathBuf>) -> Result<PathBuf> {
    if let Some(p) = explicit {
        return Ok(p.clone());
    }
    let env = |k: &str| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    let base = env("SPLATMARK_CACHE")
        .or_else(|| env("XDG_CACHE_HOME").map(|p| p.join("splatmark")))
        .or_else(|| env("HOME").map(|p| p.join(".cache/splatmark")))
        .context("no cache folder: pass --cache or set SPLATMARK_CACHE")?;
    Ok(base.join("fits"))
}

fn paper_cmd(a: &PaperArgs, progress: super::progress::ProgressMode) -> Result<()> {
    use crate::verify::paper::{self, PaperOptions};
    let cache = fit_cache(a.cache.as_ref())?;
    let mut o = if a.quick {
        PaperOptions::quick(a.datasets.clone(), cache)
    } else {
        PaperOptions::full(a.datasets.clone(), cache)
    };
    if let Some(d) = &a.only {
        o.datasets = d.clone();
    }
    if let Some(n) = a.fit_iterations {
        o.fit_iterations = n;
    }
    if a.max_side.is_some() {
        o.max_side = a.max_side;
    }
    if let Some(b) = &a.bits {
        o.bits = b.clone();
    }
    if let Some(s) = &a.seeds {
        anyhow::ensure!(!s.is_empty(), "--seeds needs at least one seed");
        o.seeds = s.clone();
    }
    o.ablations &= !a.no_ablations;
    if let Some(p) = &a.config {
        o.embed = super::config::read_json_config(p, "embedding options")?;
    }
    o.weights_dir = a.weights_dir.clone();
    if let Some(v) = a.view_scale {
        anyhow::ensure!(
            v.is_finite() && (0.05..=1.0).contains(&v),
            "--view-scale must lie in [0.05, 1] (got {v})"
        );
        o.view_scale = v;
    }
    o.fresh = a.fresh;
    let device = DeviceChoice::Flex.device().autodiff();
    let mut log = super::progress::BenchProgress::new(progress);
    let report = paper::run(&o, &device, &mut log)?;
    log.finish();
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &a.out {
        std::fs::write(out, &json).with_context(|| format!("cannot write {}", out.display()))?;
    }
    let md = paper::markdown(&report);
    if let Some(p) = &a.markdown {
        std::fs::write(p, &md).with_context(|| format!("cannot write {}", p.display()))?;
    }
    eprintln!("{md}");
    eprintln!(
        "bench paper: {} runs in {:.0} s",
        report.runs.len(),
        report.wall_s
    );
    println!("{json}");
    Ok(())
}

#[derive(Args, Debug)]
pub struct QualityArgs {
    /// The CI variant: donut, 32 bits, 128² renders, 16 orbit views (14 trained) and 4 unseen views.
    #[arg(long)]
    quick: bool,
    /// Folder holding donut/, plant/ and udon/.
    #[arg(long, default_value = "../shared/data/scenes")]
    scenes: PathBuf,
    /// Only these scenes (comma separated: donut, plant, udon, lego, fern).
    #[arg(long, value_delimiter = ',')]
    only: Option<Vec<String>>,
    /// Folder holding the posed image sets nerf_synthetic_lego/ and llff_fern/ (default: the
    /// datasets/ folder beside --scenes).
    #[arg(long)]
    datasets: Option<PathBuf>,
    /// Where the fitted lego and fern are kept and reused (as `bench paper --cache`).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Message lengths (comma separated).
    #[arg(long, value_delimiter = ',')]
    bits: Option<Vec<usize>>,
    /// Side of the orbit views in pixels (default 512, the CLI's and the service's).
    #[arg(long)]
    size: Option<u32>,
    /// Longer side in pixels of a scene's own cameras (udon; default: their own resolution, as
    /// `embed --cameras` and a job render them). lego and fern keep their fitted size.
    #[arg(long)]
    camera_size: Option<u32>,
    /// Orbit views to embed through (default 48, the CLI's; every 8th held out); the unseen
    /// views stay the same.
    #[arg(long)]
    train_views: Option<usize>,
    /// Elevations of those views in degrees (comma separated; default −20,10,35,60, the CLI's).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    train_elevations: Option<Vec<f32>>,
    /// Hold out every N-th of those views, as `embed --holdout-every` does (default 8).
    #[arg(long)]
    holdout_every: Option<usize>,
    /// For a scene with its own cameras (udon): also embed through N orbit views around the
    /// splat (at --size, the training elevations); its held-out cameras stay the unseen views.
    #[arg(long)]
    camera_orbit: Option<usize>,
    /// Azimuth of the first unseen view in degrees (default 7.5: half a step of a 24-view
    /// orbit).
    #[arg(long, allow_hyphen_values = true)]
    eval_azimuth_offset: Option<f32>,
    /// Embedding options (a JSON file or the JSON inline, as `embed --config`); default: the
    /// defaults a user gets.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Folder with decoder-{bits}.bpk artifacts (default: the shipped weights).
    #[arg(long)]
    weights_dir: Option<PathBuf>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Draws of each model attack (seeds --seed, --seed + 1, …; default 8, 2 with --quick):
    /// the rows and the targets read their mean, the markdown their worst too.
    #[arg(long)]
    model_draws: Option<usize>,
    /// Keep every embedding in this folder: `{scene}-{bits}-seed{seed}.ply` (the watermarked
    /// scene), `.report.json` (its report, with the message) and `.steps.jsonl` (every
    /// finetuning step), for `splatmark eval`, `verify` or `render` afterwards.
    #[arg(long)]
    assets: Option<PathBuf>,
    /// Write the JSON report here too.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the markdown table here.
    #[arg(long)]
    markdown: Option<PathBuf>,
}

pub fn bench_cmd(c: &BenchCommand, progress: super::progress::ProgressMode) -> Result<()> {
    use crate::verify::bench::{self, QualityOptions};
    let a = match c {
        BenchCommand::Quality(a) => a,
        BenchCommand::Paper(a) => return paper_cmd(a, progress),
    };
    let mut o = if a.quick {
        QualityOptions::quick(a.scenes.clone())
    } else {
        QualityOptions::full(a.scenes.clone())
    };
    if let Some(s) = &a.only {
        o.scenes = s.clone();
    }
    if let Some(d) = &a.datasets {
        o.datasets_dir = d.clone();
    }
    o.cache_dir = fit_cache(a.cache.as_ref()).ok();
    if let Some(b) = &a.bits {
        o.bits = b.clone();
    }
    if let Some(s) = a.size {
        o.size = s;
    }
    if let Some(s) = a.camera_size {
        anyhow::ensure!(s >= 16, "--camera-size must be at least 16");
        o.camera_size = Some(s);
    }
    if let Some(n) = a.train_views {
        anyhow::ensure!(n >= 2, "--train-views must be at least 2");
        o.train_views = Some(n);
    }
    if let Some(e) = &a.train_elevations {
        o.train_elevations = e.clone();
    }
    if let Some(n) = a.holdout_every {
        o.holdout_every = n;
    }
    if let Some(n) = a.camera_orbit {
        o.camera_orbit = n;
    }
    if let Some(d) = a.eval_azimuth_offset {
        anyhow::ensure!(d.is_finite(), "--eval-azimuth-offset must be finite");
        o.eval_azimuth_offset_deg = d;
    }
    if let Some(p) = &a.config {
        o.embed = super::config::read_json_config(p, "embedding options")?;
    }
    o.weights_dir = a.weights_dir.clone();
    o.assets_dir = a.assets.clone();
    o.seed = a.seed;
    if let Some(n) = a.model_draws {
        anyhow::ensure!(n >= 1, "--model-draws must be at least 1");
        o.model_draws = n;
    }
    let device = DeviceChoice::Flex.device().autodiff();
    let mut log = super::progress::BenchProgress::new(progress);
    let report = bench::run(&o, &device, &mut log)?;
    log.finish();
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &a.out {
        std::fs::write(out, &json).with_context(|| format!("cannot write {}", out.display()))?;
    }
    let md = bench::markdown(&report);
    if let Some(p) = &a.markdown {
        std::fs::write(p, &md).with_context(|| format!("cannot write {}", p.display()))?;
    }
    eprintln!("{md}");
    eprintln!(
        "bench quality: {} in {:.0} s",
        if report.met {
            "every target met"
        } else {
            "targets MISSED (see the table)"
        },
        report.wall_s
    );
    println!("{json}");
    Ok(())
}
