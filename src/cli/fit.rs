//! `splatmark fit`: a 3D-GS scene from posed images (NeRF-synthetic or LLFF folder).

use crate::fit::{DataOptions, Dataset, FitConfig, Fitter, Quality, checkpoint};
use crate::scene::write_ply;
use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Args, Debug)]
pub struct FitArgs {
    /// Dataset folder: NeRF synthetic (transforms_train.json, transforms_test.json) or LLFF
    /// (poses_bounds.npy, images_N/, sparse/0/points3D.bin).
    pub dataset: PathBuf,
    /// Output INRIA .ply (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Optimisation steps (default 7000).
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Resize images so that their longer side is at most this many pixels.
    #[arg(long)]
    pub max_side: Option<u32>,
    /// Background behind the scene (default: white for NeRF synthetic, black for LLFF).
    #[arg(long, value_enum)]
    pub background: Option<Background>,
    /// LLFF image folder inside DATASET (default: the first of images_8, images_4, images_2,
    /// images).
    #[arg(long)]
    pub images: Option<String>,
    /// JSON file with a FitConfig (learning rates, densification), or that JSON inline; flags
    /// override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[arg(long)]
    pub seed: Option<u64>,
    /// Highest SH degree (0–3).
    #[arg(long)]
    pub sh_degree: Option<u8>,
    /// Densification never grows the scene past this many Gaussians.
    #[arg(long)]
    pub max_gaussians: Option<usize>,
    /// Measure the test views every N steps (0: only at the end).
    #[arg(long, default_value_t = 1000)]
    pub eval_every: usize,
    /// Write a checkpoint every N steps (0: only at the end).
    #[arg(long, default_value_t = 500)]
    pub checkpoint_every: usize,
    /// Checkpoint file (default: OUT with `.fit-ckpt` appended).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Continue from the checkpoint (same dataset and configuration); bit-identical to a run
    /// that was never interrupted.
    #[arg(long)]
    pub resume: bool,
    /// A progress line every N steps.
    #[arg(long, default_value_t = 100)]
    pub log_every: usize,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Background {
    White,
    Black,
}

/// One measurement of the test views during the run.
#[derive(serde::Serialize)]
struct Point {
    step: usize,
    gaussians: usize,
    seconds: f64,
    test: Quality,
}

#[derive(serde::Serialize)]
struct Report<'a> {
    dataset: String,
    kind: crate::fit::DatasetKind,
    train_views: usize,
    test_views: usize,
    width: u32,
    height: u32,
    config: &'a FitConfig,
    gaussians: usize,
    /// The test views at the end (the training views when the dataset has none).
    test: Quality,
    /// Every 8th training view at the end.
    train: Quality,
    /// Seconds of this process's optimisation (not counting reading the data).
    seconds: f64,
    /// Steps this process ran (fewer than the configuration's when resumed).
    steps_run: usize,
    history: Vec<Point>,
    out: String,
    checkpoint: String,
}

fn config_from(a: &FitArgs) -> Result<FitConfig> {
    let mut c = match &a.config {
        Some(p) => super::config::read_json_config(p, "fit options")?,
        None => FitConfig::default(),
    };
    if let Some(v) = a.iterations {
        c.iterations = v;
    }
    if let Some(v) = a.seed {
        c.seed = v;
    }
    if let Some(v) = a.sh_degree {
        c.sh_degree = v;
    }
    if let Some(v) = a.max_gaussians {
        c.densify.max_gaussians = v;
    }
    c.validate()?;
    Ok(c)
}

pub fn fit_cmd(a: &FitArgs) -> Result<()> {
    let cfg = config_from(a)?;
    let ckpt_path = a.checkpoint.clone().unwrap_or_else(|| {
        let mut s = a.out.clone().into_os_string();
        s.push(".fit-ckpt");
        PathBuf::from(s)
    });
    let opts = DataOptions {
        max_side: a.max_side,
        background: a.background.map(|b| match b {
            Background::White => [1.0; 3],
            Background::Black => [0.0; 3],
        }),
        images: a.images.clone(),
        llff_hold: None,
    };
    let t0 = Instant::now();
    let ds = Dataset::open(&a.dataset, &opts)
        .with_context(|| format!("cannot read the dataset {}", a.dataset.display()))?;
    let (w, h) = ds.size();
    eprintln!(
        "{}: {:?}, {} training and {} test views at {w}×{h}, extent {:.3} (read in {:.1} s)",
        a.dataset.display(),
        ds.kind,
        ds.train.len(),
        ds.test.len(),
        ds.extent,
        t0.elapsed().as_secs_f64()
    );
    let mut f = if a.resume {
        let f = checkpoint::load(&ckpt_path, &ds)
            .with_context(|| format!("cannot resume from {}", ckpt_path.display()))?;
        if f.cfg != cfg {
            bail!(
                "{} was made with another configuration (iterations, seed, rates…): resume with \
                 the same flags and --config, or start afresh without --resume",
                ckpt_path.display()
            );
        }
        eprintln!(
            "resumed at step {} with {} Gaussians",
            f.step,
            f.scene.len()
        );
        f
    } else {
        Fitter::new(&ds, cfg)?
    };
    let eval_views = if ds.test.is_empty() {
        &ds.train[..]
    } else {
        &ds.test[..]
    };
    let total = f.cfg.iterations;
    let start_step = f.step;
    let t_fit = Instant::now();
    let mut history = Vec::new();
    let (mut loss_sum, mut psnr_sum, mut n_sum) = (0.0, 0.0, 0usize);
    while f.step < total {
        let r = f.step(&ds)?;
        loss_sum += r.loss;
        psnr_sum += r.psnr;
        n_sum += 1;
        let done = f.step - start_step;
        if a.log_every > 0 && (f.step % a.log_every == 0 || f.step == total) {
            let rate = t_fit.elapsed().as_secs_f64() / done as f64;
            eprintln!(
                "step {}/{total}  loss {:.4}  train PSNR {:.2} dB  {} Gaussians  SH {}  {:.3} s/step  \
                 ETA {:.0} s",
                f.step,
                loss_sum / n_sum as f64,
                psnr_sum / n_sum as f64,
                r.gaussians,
                f.active_sh_degree(),
                rate,
                rate * (total - f.step) as f64
            );
            (loss_sum, psnr_sum, n_sum) = (0.0, 0.0, 0);
        }
        if a.eval_every > 0 && f.step % a.eval_every == 0 && f.step < total {
            let q = f.evaluate(&ds, eval_views)?;
            eprintln!(
                "step {}: test views PSNR {:.2} dB, SSIM {:.4}",
                f.step, q.psnr, q.ssim
            );
            history.push(Point {
                step: f.step,
                gaussians: f.scene.len(),
                seconds: t_fit.elapsed().as_secs_f64(),
                test: q,
            });
        }
        if a.checkpoint_every > 0 && f.step % a.checkpoint_every == 0 && f.step < total {
            checkpoint::save(&f, &ckpt_path)?;
        }
    }
    let seconds = t_fit.elapsed().as_secs_f64();
    checkpoint::save(&f, &ckpt_path)?;
    write_scene(&f, &a.out)?;
    let test = f.evaluate(&ds, eval_views)?;
    let train_sample: Vec<_> = ds.train.iter().step_by(8).cloned().collect();
    let train = f.evaluate(&ds, &train_sample)?;
    history.push(Point {
        step: f.step,
        gaussians: f.scene.len(),
        seconds,
        test: test.clone(),
    });
    eprintln!(
        "done: {} Gaussians, test views PSNR {:.2} dB, SSIM {:.4} → {}",
        f.scene.len(),
        test.psnr,
        test.ssim,
        a.out.display()
    );
    let report = Report {
        dataset: a.dataset.display().to_string(),
        kind: ds.kind,
        train_views: ds.train.len(),
        test_views: ds.test.len(),
        width: w,
        height: h,
        config: &f.cfg,
        gaussians: f.scene.len(),
        test,
        train,
        seconds,
        steps_run: f.step - start_step,
        history,
        out: a.out.display().to_string(),
        checkpoint: ckpt_path.display().to_string(),
    };
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn write_scene(f: &Fitter, out: &Path) -> Result<()> {
    let g = f.output();
    crate::fit::cache::write_atomic(out, |w| write_ply(&g, w).map_err(std::io::Error::other))
        .with_context(|| format!("cannot write {}", out.display()))
}
