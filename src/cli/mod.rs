//! The `splatmark` command line.

use crate::decoder::WatermarkModel;
use crate::decoder::data::{ImageSet, Split};
use crate::decoder::eval::{self, EvalOptions};
use crate::decoder::registry::Pair;
use crate::decoder::train::{
    self, DeviceChoice, EncoderKind, RunOptions, TrainConfig, WhiteningChoice,
};
use crate::render::{RenderOptions, to_rgb8};
use crate::scene::bounds::{full_bounds, robust_bounds};
use crate::scene::camera::{read_cameras, resize_all};
use crate::scene::format::read_scene_path;
use crate::scene::orbit::{OrbitOptions, UpAxis, orbit_cameras};
use crate::scene::{Camera, Gaussians, Limits};
use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};

mod config;
mod embed;
mod explain;
mod fit;
mod probe;
mod progress;
mod serve;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "splatmark",
    version,
    about = "Watermarking for 3D Gaussian Splatting assets"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Progress of long commands (embed, render, explain, decoder train, bench) on stderr: auto
    /// (a bar on a terminal, nothing otherwise), bar, lines (plain text, for logs), json (one
    /// object per line), none. `decoder train` and `bench` print their log lines in every mode
    /// (above the bar; as `{"message"}` objects in json).
    #[arg(long, global = true, value_enum, default_value = "auto")]
    progress: progress::ProgressMode,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print what a scene file holds, as JSON: format, count, SH degree, bounds.
    Info {
        /// Scene file (.ply, compressed .ply, .splat, .spz).
        scene: PathBuf,
        #[command(flatten)]
        limits: LimitArgs,
    },
    /// Render a scene through its cameras or orbit views to PNG files.
    Render(RenderArgs),
    /// Attribution pictures of a watermarked scene, per view: carriers / compensators /
    /// untouched, each Gaussian's share of the watermark gradient, the difference to the
    /// original ×10; PNG files and an index.html.
    Explain(Box<explain::ExplainArgs>),
    /// Convert a scene between formats: the output's extension picks the format (.ply: INRIA
    /// binary PLY, lossless; .compressed.ply, .splat, .spz: the viewers' quantised formats).
    Convert {
        /// Scene file (.ply, compressed .ply, .splat, .spz).
        scene: PathBuf,
        /// Output file, .ply / .compressed.ply / .splat / .spz (written atomically: a
        /// temporary file renamed into place).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        limits: LimitArgs,
    },
    /// Fit a 3D-GS scene to posed images (NeRF-synthetic or LLFF folder) on the CPU: INRIA's
    /// recipe with densification; resumable; progress on stderr, report JSON on stdout.
    Fit(Box<fit::FitArgs>),
    /// Benchmarks that judge the watermark (docs/RESULTS.md).
    Bench {
        #[command(subcommand)]
        command: probe::BenchCommand,
    },
    /// Train or evaluate the watermark encoder/decoder.
    Decoder {
        #[command(subcommand)]
        command: DecoderCommand,
    },
    /// Decode the message from images (several images of one asset: logits averaged), as JSON.
    Decode(DecodeArgs),
    /// Watermark a scene: prune, Trio-Experts, SBAG, group masks, decoupled EOT finetuning.
    /// Progress on stderr; report JSON on stdout.
    Embed(Box<embed::EmbedArgs>),
    /// Check rendered images against a message: bit accuracy, p-value, decision (JSON).
    Verify(embed::VerifyArgs),
    /// Evaluate a watermarked scene against its original on held-out views: PSNR, SSIM, bit
    /// accuracy clean and under image and model attacks (JSON).
    Eval(Box<embed::EvalSceneArgs>),
    /// Run the HTTP service: uploads, watermarking jobs, verification, audit log.
    Serve(Box<serve::ServeArgs>),
    /// Manage API keys of the service's store.
    Keys {
        #[command(subcommand)]
        command: Box<serve::KeysCommand>,
    },
    /// Back up the service's data folder while it runs: a consistent database snapshot, every
    /// referenced blob and a manifest of SHA-256s (the master key is not included: keep it
    /// apart). Prints the manifest.
    Backup(Box<serve::BackupArgs>),
    /// Restore a backup into a fresh data folder, checking every file against the manifest and
    /// the master key against the database, then the database's integrity and the audit chain.
    Restore(Box<serve::RestoreArgs>),
}

#[derive(Subcommand, Debug)]
enum DecoderCommand {
    /// Train encoder + decoder jointly with the attack layers (HiDDeN recipe); resumable.
    /// Progress on stderr; writes <OUT> (decoder), <OUT stem>.encoder.bpk and <OUT stem>.json.
    Train(Box<TrainArgs>),
    /// Evaluate trained weights on the held-out images under the real attacks; JSON on stdout.
    Eval(EvalArgs),
    /// Re-decide the logit map (whitening / centering) of trained weights and re-run the
    /// held-out evaluation; writes the weights with the new sidecar to --out (JSON on stdout).
    Calibrate(CalibrateArgs),
    /// Write random messages into held-out images by optimisation through the frozen decoder
    /// at fixed PSNR bounds (as the 3D finetuning does) and decode them under the real attacks,
    /// perspective tilts and downscales; JSON on stdout.
    Probe(Box<probe::ProbeArgs>),
    /// Train a decoder with the optimiser as its encoder (no encoder network; GroupNorm;
    /// unmarked logits pulled to 0); resumable; ends with the probe on held-out images.
    TrainOpt(Box<probe::TrainOptArgs>),
}

#[derive(Args, Debug)]
struct CalibrateArgs {
    /// Image folder (the training split fits the map, the held-out split checks it).
    #[arg(long)]
    images: PathBuf,
    /// Trained decoder weights (.bpk with its .json sidecar and .encoder.bpk next to it).
    #[arg(long)]
    weights: PathBuf,
    /// Where to write the calibrated artifact (may be --weights itself).
    #[arg(long)]
    out: PathBuf,
    /// Which map: auto (keep what passes the rule), always (whitening), center, never.
    #[arg(long, value_enum, default_value = "auto")]
    whitening: WhiteningArg,
    /// Held-out evaluation: short side of the images.
    #[arg(long, default_value_t = EvalOptions::default().size)]
    eval_size: u32,
    /// Held-out evaluation: messages per image.
    #[arg(long, default_value_t = EvalOptions::default().repeats)]
    eval_repeats: usize,
}

#[derive(Args, Debug)]
struct TrainArgs {
    /// Image folder (.png/.jpg, recursive); ~10 % are held out by a hash of the relative path.
    #[arg(long)]
    images: PathBuf,
    /// Message length.
    #[arg(long)]
    bits: usize,
    /// Output decoder weights (e.g. weights/decoder-32.bpk); checkpoints go to <OUT>.ckpt/.
    #[arg(long)]
    out: PathBuf,
    /// Continue from the newest checkpoint in <OUT>.ckpt/ (its settings; --steps may extend).
    #[arg(long, conflicts_with = "init")]
    resume: bool,
    /// Fine-tune: start from these trained weights (architecture and strength from their
    /// sidecar, fresh optimiser) instead of random ones.
    #[arg(long)]
    init: Option<PathBuf>,
    /// JSON file with a TrainConfig to start from, or that JSON inline (flags override it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Optimisation steps.
    #[arg(long)]
    steps: Option<usize>,
    /// Crops per step.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Crop side in pixels.
    #[arg(long)]
    crop: Option<usize>,
    /// Adam learning rate.
    #[arg(long)]
    lr: Option<f64>,
    /// Final learning rate as a fraction of --lr (cosine decay; 1 = constant).
    #[arg(long)]
    lr_min_fraction: Option<f64>,
    /// Weight λ of the image loss λ·MSE(watermarked, cover).
    #[arg(long)]
    image_weight: Option<f64>,
    /// Embedding strength (watermarked = cover + strength·residual).
    #[arg(long)]
    strength: Option<f64>,
    /// Steps without attacks at the start.
    #[arg(long)]
    warmup_steps: Option<usize>,
    /// Steps over which attacks ramp in after the warm-up.
    #[arg(long)]
    ramp_steps: Option<usize>,
    /// Groups per batch, each with its own attack draw.
    #[arg(long)]
    attack_groups: Option<usize>,
    /// Probability that a group is attacked after the ramp (below 1 keeps clean groups).
    #[arg(long)]
    attack_prob_max: Option<f64>,
    /// Unmarked crops per step whose logits are pulled towards 0 (unbiased bits); 0 = off.
    #[arg(long)]
    unmarked_crops: Option<usize>,
    /// Weight of the unmarked loss.
    #[arg(long)]
    unmarked_weight: Option<f64>,
    /// Smallest random downscale of a crop's source window.
    #[arg(long)]
    min_scale: Option<f32>,
    /// Seed of all random draws.
    #[arg(long)]
    seed: Option<u64>,
    /// Checkpoint every N steps.
    #[arg(long)]
    checkpoint_every: Option<usize>,
    /// Checkpoints kept.
    #[arg(long)]
    keep_checkpoints: Option<usize>,
    /// Progress line every N steps.
    #[arg(long)]
    log_every: Option<usize>,
    /// Training device.
    #[arg(long, value_enum)]
    device: Option<DeviceArg>,
    /// Decoder hidden channels.
    #[arg(long)]
    decoder_channels: Option<usize>,
    /// Decoder ConvBNReLU(C→C) blocks.
    #[arg(long)]
    decoder_depth: Option<usize>,
    /// Encoder design: tiled (message → tiled pattern) or hidden (HiDDeN's).
    #[arg(long, value_enum)]
    encoder: Option<EncoderArg>,
    /// Tiled encoder: message tile side (pixels at the encoder's resolution).
    #[arg(long)]
    encoder_tile: Option<usize>,
    /// Encoder hidden channels.
    #[arg(long)]
    encoder_channels: Option<usize>,
    /// Encoder blocks.
    #[arg(long)]
    encoder_blocks: Option<usize>,
    /// The encoder runs at 1/2^levels resolution (residual upsampled bilinearly).
    #[arg(long)]
    encoder_levels: Option<usize>,
    /// Whitening of the final decoder's logits.
    #[arg(long, value_enum)]
    whitening: Option<WhiteningArg>,
    /// Skip the held-out evaluation at the end.
    #[arg(long)]
    no_final_eval: bool,
    /// Held-out evaluation: short side of the images.
    #[arg(long)]
    eval_size: Option<u32>,
    /// Held-out evaluation: messages per image.
    #[arg(long)]
    eval_repeats: Option<usize>,
}

/// `--device`: where the networks (and, for `embed`, the rasterizer) run.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum DeviceArg {
    /// The CPU: burn's `flex` backend and the CPU reference rasterizer.
    #[value(alias = "flex")]
    Cpu,
    /// wgpu on the best adapter, Mesa's software lavapipe included.
    Wgpu,
    /// A hardware GPU when there is one, else the CPU.
    Auto,
}

impl From<DeviceArg> for DeviceChoice {
    fn from(d: DeviceArg) -> Self {
        match d {
            DeviceArg::Cpu => DeviceChoice::Flex,
            DeviceArg::Wgpu => DeviceChoice::Wgpu,
            DeviceArg::Auto => {
                if crate::render::gpu::shared(crate::render::gpu::AdapterChoice::Hardware).is_ok() {
                    DeviceChoice::Wgpu
                } else {
                    DeviceChoice::Flex
                }
            }
        }
    }
}

impl From<DeviceArg> for crate::render::gpu::DeviceRequest {
    fn from(d: DeviceArg) -> Self {
        match d {
            DeviceArg::Cpu => Self::Cpu,
            DeviceArg::Wgpu => Self::Wgpu,
            DeviceArg::Auto => Self::Auto,
        }
    }
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum EncoderArg {
    Tiled,
    Hidden,
}

impl From<EncoderArg> for EncoderKind {
    fn from(e: EncoderArg) -> Self {
        match e {
            EncoderArg::Tiled => EncoderKind::Tiled,
            EncoderArg::Hidden => EncoderKind::Hidden,
        }
    }
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum WhiteningArg {
    Auto,
    Always,
    Center,
    Never,
}

impl From<WhiteningArg> for WhiteningChoice {
    fn from(w: WhiteningArg) -> Self {
        match w {
            WhiteningArg::Auto => WhiteningChoice::Auto,
            WhiteningArg::Always => WhiteningChoice::Always,
            WhiteningArg::Center => WhiteningChoice::Center,
            WhiteningArg::Never => WhiteningChoice::Never,
        }
    }
}

#[derive(Args, Debug)]
struct WeightsArgs {
    /// Message length.
    #[arg(long)]
    bits: usize,
    /// Decoder weights (.bpk with its .json sidecar next to it); default: the shipped weights.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Device for the networks.
    #[arg(long, value_enum, default_value = "cpu")]
    device: DeviceArg,
}

#[derive(Args, Debug)]
struct EvalArgs {
    /// Image folder; only its held-out split is used.
    #[arg(long)]
    images: PathBuf,
    #[command(flatten)]
    weights: WeightsArgs,
    /// Short side the images are resized to, then centre-cropped square.
    #[arg(long, default_value_t = EvalOptions::default().size)]
    size: u32,
    /// Random messages embedded per image.
    #[arg(long, default_value_t = EvalOptions::default().repeats)]
    repeats: usize,
    /// Seed of the messages and of the noise attack.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Args, Debug)]
struct DecodeArgs {
    /// Images (renders of one asset); decoded at their own resolution, logits averaged.
    #[arg(required = true)]
    images: Vec<PathBuf>,
    #[command(flatten)]
    weights: WeightsArgs,
    /// An embedding report (`splatmark embed --report`): decode as its verification does,
    /// relative to its asset reference and through its view projection, when it has them.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct LimitArgs {
    /// Refuse scenes with more Gaussians than this.
    #[arg(long, default_value_t = Limits::default().max_gaussians)]
    max_gaussians: usize,
}

/// Which views: a camera file, or orbit views around the scene.
#[derive(Args, Debug, Clone)]
pub(crate) struct ViewArgs {
    /// Camera file: INRIA cameras.json, NeRF transforms.json or LLFF poses_bounds.npy.
    #[arg(long, conflicts_with = "orbit")]
    cameras: Option<PathBuf>,
    /// N orbit views around the scene's robust bounds instead (default when no --cameras is
    /// given: as the service — 48, `[views]` in the config).
    #[arg(long)]
    orbit: Option<usize>,
    /// Image width (orbit default 512, as the service; with --cameras the camera's own width,
    /// intrinsics scaled).
    #[arg(long)]
    width: Option<u32>,
    /// Image height (orbit default 512, as the service; with --cameras the camera's own height).
    #[arg(long)]
    height: Option<u32>,
    /// Orbit: the scene's up axis (+x, -x, +y, -y, +z, -z).
    #[arg(long, default_value = "-y")]
    up: UpAxis,
    /// Orbit: elevations in degrees, comma separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    elevations: Option<Vec<f32>>,
    /// Orbit: vertical field of view in degrees.
    #[arg(long, default_value_t = 45.0)]
    fov: f32,
    /// Orbit: azimuth of the first view in degrees (another offset gives views between an
    /// orbit's views).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    azimuth_offset: f32,
}

impl ViewArgs {
    /// The cameras these arguments name, for scene `g`.
    pub(crate) fn cameras(&self, g: &Gaussians) -> Result<Vec<Camera>> {
        self.cameras_for(g, 32)
    }

    /// The cameras, with the orbit's default view count for a `bits`-bit payload
    /// ([`crate::config::ViewDefaults::orbit_for`]) when `--orbit` is not given.
    pub(crate) fn cameras_for(&self, g: &Gaussians, bits: usize) -> Result<Vec<Camera>> {
        let cams = match &self.cameras {
            Some(path) => {
                let cams = read_cameras(path)
                    .with_context(|| format!("cannot load cameras {}", path.display()))?;
                resize_all(cams, self.width, self.height)
            }
            None => {
                // The service's defaults for uploads without cameras: the CLI embeds as a job does.
                let d = crate::config::ViewDefaults::default();
                let mut o = OrbitOptions {
                    count: self.orbit.unwrap_or(d.orbit_for(bits)),
                    width: self.width.unwrap_or(d.width),
                    height: self.height.unwrap_or(d.height),
                    fov_y_deg: self.fov,
                    up: self.up,
                    azimuth_offset_deg: self.azimuth_offset,
                    ..OrbitOptions::default()
                };
                if let Some(e) = &self.elevations {
                    o.elevations_deg = e.clone();
                }
                orbit_cameras(g, &o)?
            }
        };
        if cams.is_empty() {
            bail!("no cameras");
        }
        Ok(cams)
    }
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// Scene file (.ply, compressed .ply, .splat, .spz).
    scene: PathBuf,
    #[command(flatten)]
    views: ViewArgs,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0.0, 0.0, 0.0])]
    background: Vec<f32>,
    /// Use at most this SH degree.
    #[arg(long)]
    sh_degree: Option<u8>,
    /// Render only the first N cameras.
    #[arg(long)]
    limit: Option<usize>,
    /// Rasterizer: cpu (the reference), wgpu (the GPU path on any wgpu adapter, Mesa's
    /// lavapipe included) or auto (a hardware GPU if there is one, else the CPU).
    #[arg(long, default_value = "auto")]
    device: crate::render::gpu::DeviceRequest,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    limits: LimitArgs,
}

/// Runs the command line; errors are printed to stderr with their causes.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Info { scene, limits } => info(&scene, &limits),
        Command::Render(args) => render_cmd(&args, cli.progress),
        Command::Explain(args) => explain::explain_cmd(&args, cli.progress),
        Command::Convert { scene, out, limits } => convert(&scene, &out, &limits),
        Command::Decoder {
            command: DecoderCommand::Train(args),
        } => train_cmd(&args, cli.progress),
        Command::Decoder {
            command: DecoderCommand::Eval(args),
        } => eval_cmd(&args),
        Command::Decoder {
            command: DecoderCommand::Calibrate(args),
        } => calibrate_cmd(&args),
        Command::Decoder {
            command: DecoderCommand::Probe(args),
        } => probe::probe_cmd(&args),
        Command::Decoder {
            command: DecoderCommand::TrainOpt(args),
        } => probe::train_opt_cmd(&args),
        Command::Fit(args) => fit::fit_cmd(&args),
        Command::Bench { command } => probe::bench_cmd(&command, cli.progress),
        Command::Decode(args) => decode_cmd(&args),
        Command::Embed(args) => embed::embed_cmd(&args, cli.progress),
        Command::Verify(args) => embed::verify_cmd(&args),
        Command::Eval(args) => embed::eval_scene_cmd(&args),
        Command::Serve(args) => serve::serve_cmd(&args),
        Command::Keys { command } => serve::keys_cmd(&command),
        Command::Backup(args) => serve::backup_cmd(&args),
        Command::Restore(args) => serve::restore_cmd(&args),
    }
}

fn train_cmd(a: &TrainArgs, progress: progress::ProgressMode) -> Result<()> {
    let base = match &a.config {
        Some(p) => {
            let mut c: TrainConfig = config::read_json_config(p, "training options")?;
            c.bits = a.bits;
            c
        }
        None => TrainConfig::for_bits(a.bits),
    };
    let overrides = |c: &mut TrainConfig| {
        macro_rules! set {
            ($($field:ident),*) => {$(
                if let Some(v) = a.$field {
                    c.$field = v.into();
                }
            )*};
        }
        set!(
            steps,
            batch_size,
            crop,
            lr,
            lr_min_fraction,
            image_weight,
            strength,
            warmup_steps,
            ramp_steps,
            attack_prob_max,
            unmarked_crops,
            unmarked_weight,
            attack_groups,
            min_scale,
            seed,
            checkpoint_every,
            keep_checkpoints,
            log_every,
            device,
            decoder_channels,
            decoder_depth,
            encoder,
            encoder_tile,
            encoder_channels,
            encoder_blocks,
            encoder_levels
        );
        if let Some(w) = a.whitening {
            c.whitening = w.into();
        }
        if a.no_final_eval {
            c.final_eval = false;
        }
        if let Some(s) = a.eval_size {
            c.eval.size = s;
        }
        if let Some(r) = a.eval_repeats {
            c.eval.repeats = r;
        }
    };
    let bar = std::cell::RefCell::new(progress::Progress::new(progress));
    let mut total = 0;
    let mut on_step = |step: usize, steps: usize| {
        let mut b = bar.borrow_mut();
        if steps != total {
            total = steps;
            b.phase("train", steps as u64);
        }
        b.step(step as u64, "");
    };
    let options = RunOptions {
        resume: a.resume,
        overrides: &overrides,
        command: Some(command_line()),
        init: a.init.as_deref(),
        on_step: Some(&mut on_step),
    };
    let mut log = progress::LogLines::new(&bar);
    let sidecar = train::run(base, &a.images, &a.out, options, &mut log)?;
    std::io::Write::flush(&mut log)?;
    bar.borrow_mut().finish();
    if let Some(eval) = sidecar.record.as_ref().and_then(|r| r.held_out.as_ref()) {
        println!("{}", serde_json::to_string_pretty(eval)?);
    }
    Ok(())
}

/// The command line as typed (arguments with spaces quoted), for records.
fn command_line() -> String {
    std::env::args()
        .map(|s| if s.contains(' ') { format!("'{s}'") } else { s })
        .collect::<Vec<_>>()
        .join(" ")
}

fn calibrate_cmd(a: &CalibrateArgs) -> Result<()> {
    let opts = EvalOptions {
        size: a.eval_size,
        repeats: a.eval_repeats,
        ..EvalOptions::default()
    };
    let sidecar = train::calibrate(
        &a.weights,
        &a.images,
        &a.out,
        a.whitening.into(),
        &opts,
        Some(command_line()),
        &mut std::io::stderr(),
    )?;
    if let Some(eval) = sidecar.record.as_ref().and_then(|r| r.held_out.as_ref()) {
        println!("{}", serde_json::to_string_pretty(eval)?);
    }
    Ok(())
}

fn load_model(w: &WeightsArgs) -> Result<(WatermarkModel, burn::tensor::Device)> {
    let device = DeviceChoice::from(w.device).device();
    let model = WatermarkModel::resolve(w.weights.as_deref(), w.bits, &device)?;
    Ok((model, device))
}

fn eval_cmd(a: &EvalArgs) -> Result<()> {
    let (model, device) = load_model(&a.weights)?;
    let held_out = ImageSet::load(&a.images, Split::HeldOut)?;
    let opts = EvalOptions {
        size: a.size,
        repeats: a.repeats,
        seed: a.seed,
        ..EvalOptions::default()
    };
    eprintln!(
        "evaluating {} bits on {} held-out images ({}², {} messages each)…",
        model.bits(),
        held_out.len(),
        opts.size,
        opts.repeats
    );
    let report = eval::evaluate_on(&model, &held_out.images, &opts, &device)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn decode_cmd(a: &DecodeArgs) -> Result<()> {
    let device = DeviceChoice::from(a.weights.device).device();
    let decoders = Pair::resolve(a.weights.weights.as_deref(), a.weights.bits, &device)?;
    let model = embed::with_report_reference(decoders, a.report.as_deref())?;
    let images = eval::read_images(&a.images)?;
    let report = eval::decode_images(&model, &images, &device);
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn convert(path: &Path, out: &Path, limits: &LimitArgs) -> Result<()> {
    let Some(to) = crate::scene::Format::from_path(out).filter(|f| f.is_writable()) else {
        bail!(
            "{}: the output's extension must be .ply, .compressed.ply, .splat or .spz{}",
            out.display(),
            match crate::scene::Format::from_path(out) {
                Some(_) => format!(" ({})", crate::scene::sog::READ_ONLY),
                None => String::new(),
            }
        );
    };
    let (format, g) = load(path, limits)?;
    let dir = out
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot create a file in {}", dir.display()))?;
    crate::scene::write_scene(&g, to, std::io::BufWriter::new(tmp.as_file_mut()))?;
    tmp.as_file().sync_all()?;
    tmp.persist(out)
        .with_context(|| format!("cannot write {}", out.display()))?;
    eprintln!(
        "{} ({format}, {} Gaussians, SH {}) → {} ({to})",
        path.display(),
        g.len(),
        g.sh_degree,
        out.display()
    );
    Ok(())
}

/// A scene file, or an unbundled SOG (a directory holding `meta.json`, or that `.json` file).
fn load(path: &Path, limits: &LimitArgs) -> Result<(crate::scene::Format, Gaussians)> {
    let limits = Limits {
        max_gaussians: limits.max_gaussians,
        ..Limits::default()
    };
    read_scene_path(path, &limits).with_context(|| format!("cannot load scene {}", path.display()))
}

fn info(path: &Path, limits: &LimitArgs) -> Result<()> {
    let (format, g) = load(path, limits)?;
    let json = serde_json::json!({
        "path": path,
        "format": format,
        "count": g.len(),
        "sh_degree": g.sh_degree,
        "bounds": full_bounds(&g),
        "robust_bounds_2pct": robust_bounds(&g, 0.02),
        // A file's size (for an unbundled SOG: its meta.json's, none for its directory).
        "file_bytes": std::fs::metadata(path).ok().filter(|m| m.is_file()).map(|m| m.len()),
    });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

fn render_cmd(a: &RenderArgs, progress: progress::ProgressMode) -> Result<()> {
    let (_, g) = load(&a.scene, &a.limits)?;
    let mut cams = a.views.cameras(&g)?;
    if let Some(n) = a.limit {
        cams.truncate(n);
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let opts = RenderOptions {
        background: [a.background[0], a.background[1], a.background[2]],
        sh_degree: a.sh_degree,
        ..RenderOptions::default()
    };
    let rasterizer = crate::render::gpu::Rasterizer::open(a.device)?;
    eprintln!("rendering on {}", rasterizer.describe());
    let mut bar = progress::Progress::new(progress);
    bar.phase("render", cams.len() as u64);
    let scene = rasterizer
        .prepare(&g, &opts)
        .context("preparing the scene")?;
    for (k, cam) in cams.iter().enumerate() {
        let t = std::time::Instant::now();
        let (w, h, image) = scene
            .render_image(cam)
            .with_context(|| format!("rendering {}", cam.name))?;
        let file = a.out.join(format!("{:03}_{}.png", k, safe_name(&cam.name)));
        to_rgb8(w, h, &image)
            .save(&file)
            .with_context(|| format!("cannot write {}", file.display()))?;
        let line = format!(
            "{} ({w}×{h}) in {:.0} ms",
            file.display(),
            t.elapsed().as_secs_f64() * 1e3
        );
        if bar.lines() {
            bar.println(&line);
        }
        bar.step(k as u64 + 1, &line);
    }
    bar.finish();
    Ok(())
}

/// A camera name reduced to characters that are safe in a file name.
fn safe_name(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(64)
        .collect();
    if s.is_empty() { "view".into() } else { s }
}
