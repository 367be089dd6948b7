//! The quality bench (`splatmark bench quality`): does the watermark that a user gets with the
//! defaults reach views the finetuning never saw, at the paper's fidelity? (issue 12, the judge)
//!
//! For each scene of `../shared/data/scenes` (donut, plant, udon) and of the posed image sets of
//! `../shared/data/datasets` (lego, fern: fitted by [`crate::fit`] into a cache folder on first
//! use, watermarked through the dataset's training cameras on its own background and judged on
//! its test cameras), and each message length:
//!
//! 1. **Training views as the CLI makes them**: `splatmark embed`'s defaults — 48 orbit views
//!    (or `train_views`) (elevations −20°, 10°, 35°, 60°) at `size`², every `holdout_every`-th held out by
//!    the CLI — or, for a scene with its own cameras (udon), every camera but every
//!    `holdout_every_cameras`-th, at the cameras' own resolution (as `embed --cameras` and a job
//!    render them; `camera_size` resizes them).
//! 2. **Embedding with [`EmbedOptions::default`]** and a uniformly random payload (what the
//!    service embeds: message ⊕ a random mask).
//! 3. **Unseen views**: `eval_views` orbit views at other elevations (0°, 22°, 50°) and azimuths
//!    offset by half a training step from every training azimuth (for udon: its held-out
//!    cameras), evaluated by [`evaluate_scene`]: PSNR / SSIM against the original's renders,
//!    bit accuracy clean, under the paper's image attacks (real 8-bit) and model attacks, the
//!    per-view detection rate and the decision on logits averaged over the views at `fpr`, and
//!    the unmarked scene's row (it must not be detected).
//! 4. Each figure against the issue's target ([`targets`]); `met` says whether all are. The
//!    model-noise target is checked on `noise_0.1_scaled`, the paper's parameter noise carried
//!    to the scene's units ([`crate::attack::model::view_position_scale`]: donut is stored in
//!    metres, 21 cm across, and its unseen views frame 0.19 units either side of its centre
//!    where lego's cameras frame 1.45, so std 0.01 on its means moves it 7.8 times as far in
//!    its images as the paper's attack moved lego in its); the literal world-unit row
//!    `noise_0.1` is reported beside it. Likewise the crop and combined targets are checked on
//!    `crop_on_asset` / `combined_on_asset`, the protocol's 40 % crop centred on the asset in
//!    each view (the paper's objects sit in the centre of their views, so its centred crop is
//!    that crop there; udon's cameras frame it in a corner, where the centred crop keeps none
//!    of it in one held-out view); the centred rows `crop` / `combined` are reported beside.
//!
//! [`markdown`] renders the runs as the table recorded in docs/RESULTS.md.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::decoder::WatermarkModel;
use crate::decoder::registry::Pair;
use crate::embed::pipeline::{EmbedOptions, embed, split_views};
use crate::scene::camera::{read_cameras, resize_all};
use crate::scene::format::read_scene;
use crate::scene::orbit::{OrbitOptions, orbit_cameras};
use crate::scene::{Camera, Gaussians, Limits};
use crate::verify::eval::{EvalSettings, SceneEval, evaluate_scene};

mod markdown;
mod targets;
pub use markdown::markdown;
pub use targets::{BitCount, TargetCheck, check, targets};

/// A scene of the bench.
#[derive(Clone, Debug, Serialize)]
pub struct BenchScene {
    pub name: String,
    /// The scene file, relative to the scenes folder.
    pub file: String,
    /// Its own cameras (relative), if it has them.
    pub cameras: Option<String>,
}

/// The shared scenes: donut and plant (orbit views), udon (its cameras).
pub fn shared_scenes() -> Vec<BenchScene> {
    vec![
        BenchScene {
            name: "donut".into(),
            file: "donut/fused.ply".into(),
            cameras: None,
        },
        BenchScene {
            name: "plant".into(),
            file: "plant/plant.splat".into(),
            cameras: None,
        },
        BenchScene {
            name: "udon".into(),
            file: "udon/point_cloud.ply".into(),
            cameras: Some("udon/cameras.json".into()),
        },
    ]
}

/// What the bench runs.
#[derive(Clone, Debug, Serialize)]
pub struct QualityOptions {
    pub scenes_dir: PathBuf,
    /// Names from [`shared_scenes`] or [`crate::verify::paper::paper_datasets`].
    pub scenes: Vec<String>,
    /// Folder of the posed image sets (lego, fern): fitted into `cache_dir` on first use, then
    /// embedded through their training cameras and judged on their test cameras.
    pub datasets_dir: PathBuf,
    /// Where fitted datasets are kept (`None`: dataset scenes cannot run).
    pub cache_dir: Option<PathBuf>,
    /// Fitting steps of the dataset scenes.
    pub fit_iterations: usize,
    pub bits: Vec<usize>,
    /// Side of the orbit views (training and evaluation), pixels: by default the orbit side of
    /// the CLI and the service (`config::ViewDefaults`, 512).
    pub size: u32,
    /// Longer side of a scene's own cameras (udon), pixels, the aspect kept; `None`: the
    /// cameras' own resolution — what `splatmark embed --cameras` and a job with uploaded
    /// cameras render at unless told a width or height.
    pub camera_size: Option<u32>,
    /// Orbit views to train on; `None`: what the CLI and the service take for the payload
    /// (`config::ViewDefaults::orbit_for`: 48) …
    pub train_views: Option<usize>,
    /// Their elevations (view `i` at `train_elevations[i % len]`; the orbit's default).
    pub train_elevations: Vec<f32>,
    /// … of which it holds out every n-th (its default 8).
    pub holdout_every: usize,
    /// Cameras of a scene's own set held out for evaluation: every n-th.
    pub holdout_every_cameras: usize,
    /// Orbit views around the splat added to a scene's own training cameras (0: its cameras
    /// alone); the held-out cameras stay the unseen views.
    pub camera_orbit: usize,
    /// Unseen orbit views.
    pub eval_views: usize,
    pub eval_elevations: Vec<f32>,
    /// Azimuth of the first unseen view (half a training step of the default orbit: the unseen
    /// views stay the same whatever `train_views`).
    pub eval_azimuth_offset_deg: f32,
    /// The embedding options (the defaults a user gets).
    pub embed: EmbedOptions,
    pub fpr: f64,
    /// Seed of the payloads and attacks.
    pub seed: u64,
    /// Draws of each model attack ([`EvalSettings::model_draws`]; the targets are checked on
    /// their mean).
    pub model_draws: usize,
    /// Folder with `decoder-{bits}.bpk` artifacts; the shipped weights when absent.
    pub weights_dir: Option<PathBuf>,
    /// Folder to keep each embedding in ([`keep_asset`]): the watermarked scene, its report
    /// and its finetuning steps, so that it can be evaluated, attacked or rendered again.
    pub assets_dir: Option<PathBuf>,
}

impl QualityOptions {
    /// The full bench: every shared scene and dataset, 32/48/64 bits, the CLI's defaults.
    pub fn full(scenes_dir: PathBuf) -> Self {
        let datasets_dir = scenes_dir
            .parent()
            .map_or_else(|| PathBuf::from("datasets"), |p| p.join("datasets"));
        Self {
            scenes: shared_scenes()
                .into_iter()
                .map(|s| s.name)
                .chain(
                    crate::verify::paper::paper_datasets()
                        .into_iter()
                        .map(|d| d.name),
                )
                .collect(),
            scenes_dir,
            datasets_dir,
            cache_dir: None,
            fit_iterations: crate::fit::FitConfig::default().iterations,
            bits: vec![32, 48, 64],
            size: crate::config::ViewDefaults::default().width,
            camera_size: None,
            train_views: None,
            train_elevations: OrbitOptions::default().elevations_deg,
            holdout_every: 8,
            holdout_every_cameras: 4,
            camera_orbit: 0,
            eval_views: 12,
            eval_elevations: vec![0.0, 22.0, 50.0],
            eval_azimuth_offset_deg: 0.5 * 360.0 / 24.0,
            embed: EmbedOptions::default(),
            fpr: 1e-6,
            seed: 0,
            model_draws: crate::verify::eval::MODEL_DRAWS,
            weights_dir: None,
            assets_dir: None,
        }
    }

    /// The CI variant: donut, 32 bits, 128² renders, 16 orbit views (14 trained: the steps,
    /// not the views, set its time) and 4 unseen views half a step away from them. With 8
    /// (7 trained) its margins were within one payload's noise: removal in the EOT term moved
    /// its JPEG row from 30 to 29 of 32 bits, p 1.3e-6, undetected; with 16, 32 of 32 either way
    /// (docs/RESULTS.md).
    pub fn quick(scenes_dir: PathBuf) -> Self {
        Self {
            scenes: vec!["donut".into()],
            bits: vec![32],
            size: 128,
            train_views: Some(16),
            eval_views: 4,
            eval_azimuth_offset_deg: 0.5 * 360.0 / 16.0,
            model_draws: 2,
            ..Self::full(scenes_dir)
        }
    }
}

/// Why the bench could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("unknown bench scene {0:?} (known: donut, plant, udon, lego, fern)")]
    UnknownScene(String),
    #[error("unknown dataset {0:?} (known: lego, fern)")]
    UnknownDataset(String),
    #[error("{path}: {message}")]
    Input { path: PathBuf, message: String },
    #[error(transparent)]
    Weights(#[from] crate::decoder::WeightsError),
    #[error(transparent)]
    Embed(#[from] crate::embed::pipeline::EmbedError),
    #[error(transparent)]
    Eval(#[from] crate::verify::eval::EvalError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("cannot write {path}: {message}")]
    Output { path: PathBuf, message: String },
}

/// One scene at one message length.
#[derive(Clone, Debug, Serialize)]
pub struct QualityRun {
    pub scene: String,
    pub bits: usize,
    /// The decoder the bits were written for ([`crate::decoder::WatermarkModel::digest`]):
    /// the shipped one, or `--weights-dir`'s.
    pub decoder: String,
    pub gaussians: usize,
    pub train_views: usize,
    /// Cameras the finetuning interpolated along the training cameras' path
    /// ([`crate::embed::pipeline::EmbedOptions::path`]).
    pub path_views: usize,
    pub eval_views: usize,
    pub carriers: usize,
    pub compensators: usize,
    pub embed_s: f64,
    /// Finetuning steps run (`steps`, twice that when the schedule stretched).
    pub steps: usize,
    /// What the schedule's stretch measured and decided (`finetune.stretch_bce`).
    pub stretch: Option<crate::embed::finetune::StretchCheck>,
    /// How the decoder was chosen (`embed.coarse_margin_db`, when a coarse decoder was there):
    /// the main decoder's PSNR at the check and whether the run switched (`decoder` then names
    /// the coarse one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub choice: Option<crate::embed::pipeline::DecoderChoice>,
    /// The embedding's seconds per phase (targets, planning, calibration, finetuning).
    pub phases: crate::embed::pipeline::Timings,
    pub eval_s: f64,
    pub eval: SceneEval,
    pub targets: Vec<TargetCheck>,
    pub met: bool,
}

/// The bench's report.
#[derive(Clone, Debug, Serialize)]
pub struct QualityReport {
    pub options: QualityOptions,
    pub runs: Vec<QualityRun>,
    pub wall_s: f64,
    /// Every target of every run met.
    pub met: bool,
}

fn input_err(path: &Path, e: impl std::fmt::Display) -> BenchError {
    BenchError::Input {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Training and unseen cameras of `scene` for a `bits`-bit payload (module docs).
pub fn views(
    scene: &BenchScene,
    g: &Gaussians,
    opts: &QualityOptions,
    bits: usize,
) -> Result<(Vec<Camera>, Vec<Camera>), BenchError> {
    if let Some(c) = &scene.cameras {
        let path = opts.scenes_dir.join(c);
        let cams = read_cameras(&path).map_err(|e| input_err(&path, e))?;
        // The longer side at `camera_size`, the aspect kept; by default as the user gets them.
        let wide = cams.first().is_some_and(|c| c.width >= c.height);
        let cams = match opts.camera_size {
            None => cams,
            Some(n) if wide => resize_all(cams, Some(n), None),
            Some(n) => resize_all(cams, None, Some(n)),
        };
        let every = opts.holdout_every_cameras.max(2);
        let (mut train, held) = split_views(&cams, every);
        if opts.camera_orbit > 0 {
            train.extend(orbit_cameras(
                g,
                &OrbitOptions {
                    count: opts.camera_orbit,
                    elevations_deg: opts.train_elevations.clone(),
                    width: opts.size,
                    height: opts.size,
                    ..OrbitOptions::default()
                },
            )?);
        }
        return Ok((train, held));
    }
    let train_orbit = OrbitOptions {
        count: opts
            .train_views
            .unwrap_or_else(|| crate::config::ViewDefaults::default().orbit_for(bits)),
        elevations_deg: opts.train_elevations.clone(),
        width: opts.size,
        height: opts.size,
        ..OrbitOptions::default()
    };
    let (train, _) = split_views(&orbit_cameras(g, &train_orbit)?, opts.holdout_every);
    let unseen = OrbitOptions {
        count: opts.eval_views,
        elevations_deg: opts.eval_elevations.clone(),
        width: opts.size,
        height: opts.size,
        azimuth_offset_deg: opts.eval_azimuth_offset_deg,
        ..OrbitOptions::default()
    };
    Ok((train, orbit_cameras(g, &unseen)?))
}

/// Writes an embedding into `dir` (created if missing) as `{scene}-{bits}-seed{seed}.ply` (the
/// watermarked scene, INRIA binary PLY), `….report.json` (its report: message, decoder,
/// options, timings) and `….steps.jsonl` (every finetuning step of the run that was kept);
/// returns the scene's path with `.ply` replaced by `.*`. Each file is written whole or not
/// at all.
pub fn keep_asset(
    dir: &Path,
    scene: &str,
    bits: usize,
    seed: u64,
    out: &crate::embed::pipeline::Embedded,
) -> Result<PathBuf, BenchError> {
    let err = |path: &Path, e: &dyn std::fmt::Display| BenchError::Output {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    std::fs::create_dir_all(dir).map_err(|e| err(dir, &e))?;
    let stem = dir.join(format!("{scene}-{bits}-seed{seed}"));
    let with = |ext: &str| stem.with_extension(ext);
    let write = |path: PathBuf, bytes: Vec<u8>| {
        crate::decoder::artifact::write_atomic(&path, &bytes).map_err(|e| match e {
            crate::decoder::WeightsError::Io { source, .. } => err(&path, &source),
            e => err(&path, &e),
        })
    };
    let mut ply = Vec::new();
    crate::scene::write_ply(&out.scene, &mut ply).map_err(|e| err(&with("ply"), &e))?;
    write(with("ply"), ply)?;
    let report =
        serde_json::to_vec_pretty(&out.report).map_err(|e| err(&with("report.json"), &e))?;
    write(with("report.json"), report)?;
    let mut steps = Vec::new();
    for s in &out.log {
        serde_json::to_writer(&mut steps, s).map_err(|e| err(&with("steps.jsonl"), &e))?;
        steps.push(b'\n');
    }
    write(with("steps.jsonl"), steps)?;
    Ok(with("*"))
}

/// The decoder of `bits` bits: from `weights_dir` (`decoder-{bits}.bpk`) or the shipped one.
pub(crate) fn bench_model(
    weights_dir: Option<&Path>,
    bits: usize,
    device: &burn::tensor::Device,
) -> Result<Pair, BenchError> {
    let main = weights_dir.map(|d| d.join(format!("decoder-{bits}.bpk")));
    Ok(Pair::resolve(main.as_deref(), bits, device)?)
}

/// The decoder of `decoders` the report's bits were written for.
pub(crate) fn written_for(
    decoders: &Pair,
    report: &crate::embed::pipeline::EmbedReport,
) -> Result<WatermarkModel, BenchError> {
    decoders.by_digest(&report.decoder).cloned().ok_or_else(|| {
        BenchError::Weights(crate::decoder::WeightsError::Mismatch(format!(
            "the embedding wrote for decoder {}, which is not among the bench's",
            crate::decoder::artifact::short_digest(&report.decoder)
        )))
    })
}

/// `model` as a dispute decodes the asset: through the matched head and relative to the asset
/// reference when the embedding measured them.
pub(crate) fn as_disputed(
    model: WatermarkModel,
    report: &crate::embed::pipeline::EmbedReport,
) -> WatermarkModel {
    let model = match &report.view_projection {
        Some(p) => model.with_projection(p.clone()),
        None => model,
    };
    match &report.reference_logits {
        Some(r) => model.with_reference(r.clone()),
        None => model,
    }
}

/// A dataset scene of the bench, fitted (or reused from the cache) as `bench paper` fits it.
fn fitted_dataset(
    name: &str,
    opts: &QualityOptions,
    log: &mut dyn crate::verify::BenchLog,
) -> Result<crate::fit::cache::Fitted, BenchError> {
    let d = crate::verify::paper::paper_datasets()
        .into_iter()
        .find(|d| d.name == name)
        .ok_or_else(|| BenchError::UnknownScene(name.to_string()))?;
    let dir = opts.datasets_dir.join(&d.dir);
    let cache = opts.cache_dir.as_ref().ok_or_else(|| {
        input_err(
            &dir,
            "a dataset scene needs a cache folder for its fitted scene",
        )
    })?;
    let data = crate::fit::DataOptions {
        max_side: d.max_side,
        ..crate::fit::DataOptions::default()
    };
    let cfg = crate::fit::FitConfig {
        iterations: opts.fit_iterations,
        ..crate::fit::FitConfig::default()
    };
    crate::fit::cache::fitted(name, &dir, &data, &cfg, cache, &mut |s: &str| log.line(s))
        .map_err(|e| input_err(&dir, e))
}

/// The payload of one run: drawn from `seed`, the scene's name and the length, so a rerun of
/// the bench writes the same messages and reports the same figures.
pub fn bench_message(seed: u64, scene: &str, bits: usize) -> Vec<bool> {
    let name = scene.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
    });
    let mut rng = crate::attack::diff::EotRng::new(seed ^ name ^ (bits as u64).rotate_left(32));
    (0..bits).map(|_| rng.next_u64() & 1 == 1).collect()
}

/// Runs the bench; `log` gets a line per phase.
pub fn run(
    opts: &QualityOptions,
    device: &burn::tensor::Device,
    log: &mut dyn crate::verify::BenchLog,
) -> Result<QualityReport, BenchError> {
    let start = Instant::now();
    let all = shared_scenes();
    let mut runs = Vec::new();
    for name in &opts.scenes {
        let mut embed_opts = opts.embed.clone();
        // A shared scene's views depend on the payload (more orbit views for longer ones); a
        // dataset's are its own cameras.
        let (g, cameras) = match all.iter().find(|s| &s.name == name) {
            Some(scene) => {
                let path = opts.scenes_dir.join(&scene.file);
                let g = read_scene(&path, &Limits::default()).map_err(|e| input_err(&path, e))?;
                (g, Err(scene))
            }
            None => {
                let f = fitted_dataset(name, opts, log)?;
                embed_opts.finetune.background = f.dataset.background;
                let cams =
                    |v: &[crate::fit::View]| v.iter().map(|x| x.camera.clone()).collect::<Vec<_>>();
                let v = (cams(&f.dataset.train), cams(&f.dataset.test));
                (f.scene, Ok(v))
            }
        };
        let opts = &QualityOptions {
            embed: embed_opts,
            ..opts.clone()
        };
        for &bits in &opts.bits {
            // Ok: a dataset's own cameras; Err: a shared scene, viewed as the CLI would.
            let (train, unseen) = match &cameras {
                Ok(v) => v.clone(),
                Err(scene) => views(scene, &g, opts, bits)?,
            };
            let decoders = bench_model(opts.weights_dir.as_deref(), bits, device)?;
            let payload = bench_message(opts.seed, name, bits);
            log.line(&format!(
                "{name}, {bits} bits: embedding over {} training views ({} Gaussians, {}×{})…",
                train.len(),
                g.len(),
                train.first().map_or(0, |c| c.width),
                train.first().map_or(0, |c| c.height),
            ));
            let t0 = Instant::now();
            let what = format!("{name} {bits}");
            let out = embed(
                &g,
                &train,
                &payload,
                &decoders,
                &opts.embed,
                super::embed_progress(log, &what),
            )?;
            let embed_s = t0.elapsed().as_secs_f64();
            let t = &out.report.timings;
            let st = &t.steps;
            log.line(&format!(
                "  embedded in {embed_s:.1} s (targets {:.1}, plan {:.1}, calibrate {:.1}, \
                 finetune {:.1}: render {:.1}, watermark {:.1}, visual {:.1}, backward {:.1}, \
                 update {:.1}); evaluating on {} unseen views…",
                t.targets,
                t.plan,
                t.calibrate,
                t.finetune,
                st.render,
                st.watermark,
                st.visual,
                st.backward,
                st.update,
                unseen.len()
            ));
            let t1 = Instant::now();
            let settings = EvalSettings {
                render: opts.embed.render_options(),
                fpr: opts.fpr,
                seed: opts.seed,
                model_draws: opts.model_draws,
            };
            if let Some(c) = &out.report.choice {
                log.line(&format!("  {}", c.describe()));
            }
            // Decoded as a dispute would: with the decoder the bits were written for, relative
            // to the asset when the embedding measured it.
            if let Some(dir) = &opts.assets_dir {
                let files = keep_asset(dir, name, bits, opts.seed, &out)?;
                log.line(&format!("  kept: {}", files.display()));
            }
            let model = as_disputed(written_for(&decoders, &out.report)?, &out.report);
            let eval = evaluate_scene(&g, &out.scene, &unseen, &model, &payload, &settings)?;
            let targets = check(&eval, bits);
            let met = targets.iter().all(|t| t.met);
            runs.push(QualityRun {
                scene: name.clone(),
                bits,
                decoder: out.report.decoder.clone(),
                gaussians: g.len(),
                train_views: train.len(),
                path_views: out.report.path_views,
                eval_views: unseen.len(),
                carriers: out.report.carriers,
                compensators: out.report.compensators,
                embed_s,
                steps: out.report.last_step.map_or(0, |l| l.step),
                stretch: out.report.stretch,
                choice: out.report.choice,
                phases: out.report.timings.clone(),
                eval_s: t1.elapsed().as_secs_f64(),
                eval,
                targets,
                met,
            });
        }
    }
    let met = runs.iter().all(|r| r.met);
    Ok(QualityReport {
        options: opts.clone(),
        runs,
        wall_s: start.elapsed().as_secs_f64(),
        met,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::object_scene;
    use crate::verify::eval::Row;

    #[test]
    fn unseen_views_are_not_training_views_and_every_payload_trains_on_the_service_default() {
        let g = object_scene(200, 0, 3);
        let dir = PathBuf::from("/nonexistent");
        let scene = &shared_scenes()[0];
        for (opts, bits, trained, unseen_n) in [
            (QualityOptions::quick(dir.clone()), 32, 14, 4),
            (QualityOptions::full(dir.clone()), 32, 42, 12),
            (QualityOptions::full(dir.clone()), 48, 42, 12),
            (QualityOptions::full(dir.clone()), 64, 42, 12),
        ] {
            let (train, unseen) = views(scene, &g, &opts, bits).unwrap();
            assert_eq!(
                (train.len(), unseen.len()),
                (trained, unseen_n),
                "{bits} bits"
            );
            assert_unseen(&train, &unseen);
        }
    }

    #[test]
    fn orbit_views_join_a_scenes_own_training_cameras_and_its_held_out_ones_stay_unseen() {
        let g = object_scene(200, 0, 3);
        let dir = tempfile::tempdir().expect("tempdir");
        let cams: Vec<String> = (0..8)
            .map(|i| {
                format!(
                    r#"{{"id": {i}, "img_name": "c{i}", "width": 64, "height": 48,
                    "position": [{x}, 0.0, -5.0],
                    "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "fx": 60.0, "fy": 60.0}}"#,
                    x = 0.2 * i as f32
                )
            })
            .collect();
        std::fs::write(
            dir.path().join("cameras.json"),
            format!("[{}]", cams.join(",")),
        )
        .unwrap();
        let scene = BenchScene {
            name: "own".into(),
            file: "own.ply".into(),
            cameras: Some("cameras.json".into()),
        };
        let mut opts = QualityOptions::full(dir.path().to_path_buf());
        opts.size = 64;
        let (train, held) = views(&scene, &g, &opts, 32).unwrap();
        assert_eq!((train.len(), held.len()), (6, 2));
        // The cameras render at their own resolution, as the CLI and a job render them, unless
        // the bench is given a size for them.
        assert!(
            train
                .iter()
                .chain(&held)
                .all(|c| (c.width, c.height) == (64, 48))
        );
        opts.camera_size = Some(32);
        let (small, small_held) = views(&scene, &g, &opts, 32).unwrap();
        assert!(
            small
                .iter()
                .chain(&small_held)
                .all(|c| (c.width, c.height) == (32, 24))
        );
        opts.camera_size = None;
        opts.camera_orbit = 5;
        let (with_orbit, held_too) = views(&scene, &g, &opts, 32).unwrap();
        assert_eq!(held_too, held, "the unseen views are the held-out cameras");
        assert_eq!(with_orbit.len(), 11);
        assert_eq!(with_orbit[..6], train[..], "the scene's own cameras first");
        assert!(
            with_orbit[6..]
                .iter()
                .all(|c| c.width == 64 && c.height == 64)
        );
    }

    fn assert_unseen(train: &[Camera], unseen: &[Camera]) {
        for u in unseen {
            let nearest = train
                .iter()
                .map(|t| t.center().distance(u.center()))
                .fold(f32::INFINITY, f32::min);
            let radius = u.center().length().max(1e-3);
            assert!(
                nearest > 0.05 * radius,
                "an unseen view sits on a training view"
            );
        }
    }

    fn row(name: &str, acc: f64, detected: bool) -> Row {
        Row {
            name: name.into(),
            kind: "image".into(),
            bit_accuracy: acc,
            bit_accuracy_combined: acc,
            p_value: 0.5,
            detected,
            detection_rate_per_view: 0.0,
            psnr_vs_original: None,
            psnr_on_asset_vs_original: None,
            draws: Vec::new(),
            view_accuracy: Vec::new(),
        }
    }

    #[test]
    fn targets_are_checked_and_a_detected_unmarked_scene_fails() {
        let mut rows = vec![row("clean", 0.99, true), row("unmarked", 0.5, false)];
        for (n, t) in targets(32).into_iter().skip(3) {
            rows.push(row(n, t + 0.001, false));
        }
        let eval = SceneEval {
            views: 4,
            psnr: 36.5,
            ssim: 0.985,
            psnr_on_asset: None,
            fpr: 1e-6,
            rows,
            per_view: vec![],
            noise_position_scale: None,
        };
        assert!(
            check(&eval, 32).iter().all(|t| t.met),
            "{:?}",
            check(&eval, 32)
        );
        let mut worse = eval.clone();
        worse.psnr = 35.9;
        worse.rows[1].detected = true;
        let missed: Vec<String> = check(&worse, 32)
            .into_iter()
            .filter(|t| !t.met)
            .map(|t| t.name)
            .collect();
        assert_eq!(missed, ["psnr", "unmarked_detected"]);
        let described: Vec<String> = check(&worse, 32)
            .iter()
            .filter(|t| !t.met)
            .map(TargetCheck::describe)
            .collect();
        assert_eq!(
            described,
            ["psnr (35.90 dB; 36 needed)", "unmarked_detected"]
        );
        // One bit short over 4 views × 32 bits: the bench says how many bits it counted.
        let mut short = eval.clone();
        short.rows[0].bit_accuracy = (0.96875 + 1.0 + 1.0 + 0.96875) / 4.0;
        let clean = check(&short, 32)
            .into_iter()
            .find(|t| t.name == "clean")
            .expect("a clean target");
        assert!(!clean.met);
        assert_eq!(
            clean.bits,
            Some(BitCount {
                right: 126,
                counted: 128,
                needed: 127
            })
        );
        assert_eq!(clean.describe(), "clean (126 of 128 bits; 127 needed)");
        // A model attack drawn 8 times counts each draw's bits: 4 views × 32 bits × 8.
        let mut drawn = eval.clone();
        let remove = drawn
            .rows
            .iter_mut()
            .find(|r| r.name == "remove_20")
            .unwrap();
        remove.draws = vec![1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.9375];
        remove.bit_accuracy = remove.draws.iter().sum::<f64>() / 8.0;
        let remove = check(&drawn, 32)
            .into_iter()
            .find(|t| t.name == "remove_20")
            .expect("a removal target");
        assert!(remove.met);
        assert_eq!(
            remove.bits,
            Some(BitCount {
                right: 1016,
                counted: 1024,
                needed: 1006
            })
        );
        // A target that is an exact number of bits asks for that number, not one more.
        assert_eq!(BitCount::of(0.5, 2, 32, 0.5).needed, 32);
        assert!(
            markdown(&QualityReport {
                options: QualityOptions::quick(PathBuf::new()),
                runs: vec![],
                wall_s: 0.0,
                met: true,
            })
            .starts_with("| scene |")
        );
    }
}
