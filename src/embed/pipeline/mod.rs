//! The whole embedding of one asset, as the CLI and the service run it: targets → prune →
//! Trio-Experts → SBAG → masks → decoupled finetuning → attribution, with progress reports and
//! the figures a user needs (what was chosen, how long each phase took, how the views decode).

use std::ops::ControlFlow;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::attribution::AttributionRecord;
use super::calibrate::{ProjectionConfig, calibration_cameras, fit_projection};
use super::finetune::{
    FinetuneConfig, FinetuneError, Finetuned, StepLog, StretchCheck, View, ViewsCheck,
    check_window, choice_step, finetune, target_views,
};
use super::mask::MaskConfig;
use super::path::{PathConfig, path_cameras};
use super::sbag::Budget;
use super::{EmbedConfig, plan_over};
use crate::decoder::WatermarkModel;
use crate::decoder::projection::ViewProjection;
use crate::decoder::registry::Pair;
use crate::render::gpu::Rasterizer;
use crate::render::{RenderError, RenderOptions};
use crate::scene::{Camera, Gaussians};
use crate::verify::message::to_hex;

mod views;
pub use views::{check_view_scales, scaled_views, split_views, spread_views};

/// Everything that decides an embedding. The default is the recipe measured to carry the
/// message to unseen views ([`FinetuneConfig::default`], decoded relative to the asset);
/// [`EmbedOptions::paper`] is the paper's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EmbedOptions {
    pub plan: EmbedConfig,
    pub finetune: FinetuneConfig,
    /// Ablation `--no-group-mask`: every mask is 1 (routing kept).
    pub no_group_mask: bool,
    /// Decode relative to the asset ([`WatermarkModel::with_reference`]; on by default): the
    /// original scene's mean logits over the training views are measured first, finetuning
    /// writes the message relative to them, and the report carries them
    /// ([`EmbedReport::reference_logits`]) for verification (the service registers them with
    /// the key).
    pub reference: bool,
    /// Resolutions the training views are rendered at, as factors of each camera's own
    /// (`[1.0, 2.0]`: every training camera at its size and at twice it). A dispute renders at
    /// whatever resolution it likes, and the message written at one resolution is weaker at
    /// another (docs/RESULTS.md); each factor in [0.125, 8], every view at least 16 px a side.
    pub view_scales: Vec<f32>,
    /// How the bits are read for this asset (eq. `matchedhead`, [`crate::decoder::projection`]):
    /// by default through the asset's matched head, fitted on the original before finetuning
    /// and reported (`view_projection`); `matched: false` with `rank` k > 0 is the rank-k view
    /// projection (eq. `viewproj`), with rank 0 the decoder's own head.
    pub projection: ProjectionConfig,
    /// Views the finetuning renders besides the training cameras: turned and zoomed copies of
    /// them ([`crate::embed::calibrate::calibration_cameras`], up to `projection.max_angle_deg`
    /// and `projection.zoom`, drawn from a seed of their own), so the message is written for the
    /// views around the training cameras too, not only through them (at most 1000). Measured
    /// (docs/RESULTS.md, "the matched head"): 48 bring plant's unseen views from 91.9 to 93.5 %
    /// (a single one detected in 75 % of cases instead of 50 %) and keep donut at 97.9 %, but
    /// break udon, whose cameras sit close to the scene (turned copies see it from inside or
    /// from nowhere, and the fidelity bound then collapses the writes): 0 by default.
    pub extra_views: usize,
    /// Cameras interpolated along the training cameras' path ([`crate::embed::path`]): in each
    /// gap between consecutive training cameras (in the order given) that turns at most
    /// `path.max_turn_deg`, `path.per_gap` cameras the finetuning renders besides them. Measured
    /// (docs/RESULTS.md, "Views along the capture path"): udon's held-out cameras, which lie
    /// on its capture path between training cameras, read 98.4 % of a 32-bit payload at its
    /// cameras' size (95.3 without), rotation 95.3 (93.8), scaling 96.9 (93.8). The orbits of
    /// the service and the CLI change elevation by 25–80° from one view to the next, so they
    /// get none. [`EmbedOptions::paper`]: none.
    pub path: PathConfig,
    /// Training views SBAG's visibility, the calibration (matched head, decoder gain) and the
    /// reference logits read: at most this many, spread over the training cameras
    /// ([`spread_views`]); 0 reads every one. Those phases' cost grows with the views while a
    /// finetuning step's does not, so a longer orbit costs little more than a short one.
    /// Pruning reads every training view (a Gaussian only an unread view shows stays), and the
    /// finetuning cycles through every one. Only for payloads of at most 32 bits: longer ones
    /// read every view, their matched head needs the gain over all of them (donut, 64 bits, 42
    /// training views: 86.3 % of the bits on unseen views with 24 read, 95.3 % with all;
    /// docs/RESULTS.md).
    pub analysis_views: usize,
    /// When the decoders come as a pair (a coarse one beside the main one,
    /// [`crate::decoder::registry::Pair`]), the finetuning writes for the main one and, at
    /// the check (a fifth of `steps`: step 70 of the default 350), restarts calibration and
    /// finetuning with the coarse one when the training views' PSNR over the last tenth of
    /// `steps` is more than this many dB above `finetune.target_psnr` — an asset the fidelity
    /// bound does not hold has budget to spare, which the coarse decoder's bolder, more robust
    /// changes use. `None`: never (the main decoder only). Default 4.2 dB (docs/RESULTS.md,
    /// "The decoder chosen at step 70": over steps 36–70 of the default 350 donut's training
    /// views read 41.08–41.32 dB for three payloads, plant's 43.05–43.56, udon's ≈ 46.5; 4.2
    /// puts the threshold halfway between donut and plant. The coarse decoder costs donut its
    /// clean target and brings udon's robustness up). Off when `target_psnr` is 0 (no bound to
    /// measure the margin from).
    pub coarse_margin_db: Option<f32>,
    /// How much harder the coarse decoder's finetuning writes after a switch
    /// ([`EmbedOptions::coarse_margin_db`]): its `finetune.wm_lr_scale` is this many times the
    /// main run's. A switch means the main run left the budget free, which the default rate does
    /// not spend: in the coupled recipe the rate and the bound set the write's strength, the
    /// loss weights barely act (docs/RESULTS.md, "What sets the write's strength on udon").
    /// In (0, 16]; 1 keeps the main run's rate. Default 2 (docs/RESULTS.md, "The coarse
    /// run spends the budget the switch finds free").
    pub coarse_wm_lr_factor: f32,
    /// How far below `finetune.target_psnr` the coarse decoder's finetuning holds its
    /// training views after a switch (dB, in [0, 20], and the bound stays above 0): with
    /// `coarse_wm_lr_factor` the budget the switch found free is spent. 0 keeps the main run's
    /// bound. Default 1.5 dB: a 36.5 dB bound under the default 38 (plant's third payload, the
    /// scene that spends the most, then reads 36.9 dB on unseen views; 36.5 at a 2 dB drop,
    /// 37.4 at 1 dB with the same bits).
    pub coarse_bound_drop_db: f32,
}

impl Default for EmbedOptions {
    fn default() -> Self {
        Self {
            plan: EmbedConfig::default(),
            finetune: FinetuneConfig::default(),
            no_group_mask: false,
            reference: true,
            view_scales: vec![1.0],
            projection: ProjectionConfig::default(),
            extra_views: 0,
            path: PathConfig::default(),
            analysis_views: 24,
            coarse_margin_db: Some(4.2),
            coarse_wm_lr_factor: 2.0,
            coarse_bound_drop_db: 1.5,
        }
    }
}

/// Checks [`EmbedOptions::coarse_margin_db`]: a margin in [0, 60] dB, or `None`.
fn check_coarse_margin(margin: Option<f32>) -> Result<(), String> {
    match margin {
        Some(m) if !(0.0..=60.0).contains(&m) => Err(format!(
            "coarse_margin_db is {m}; a margin in [0, 60] dB, or null for never"
        )),
        _ => Ok(()),
    }
}

impl EmbedOptions {
    /// Checks the decoder choice's options: `coarse_margin_db` in [0, 60] dB or `None`, the
    /// coarse run's rate factor and bound drop, and — when a switch may happen — the coarse
    /// run's finetuning options as [`FinetuneConfig::validate`] checks the main run's.
    pub fn check_coarse(&self) -> Result<(), String> {
        check_coarse_margin(self.coarse_margin_db)?;
        let f = self.coarse_wm_lr_factor;
        if !(f > 0.0 && f <= 16.0) {
            return Err(format!(
                "coarse_wm_lr_factor is {f}; a factor in (0, 16] (1 keeps the main run's rate)"
            ));
        }
        let d = self.coarse_bound_drop_db;
        if !(0.0..=20.0).contains(&d) {
            return Err(format!(
                "coarse_bound_drop_db is {d}; a drop in [0, 20] dB (0 keeps the main run's bound)"
            ));
        }
        let t = self.finetune.target_psnr;
        if t > 0.0 && d > 0.0 && t - d <= 0.0 {
            return Err(format!(
                "coarse_bound_drop_db {d} takes the bound finetune.target_psnr {t} to 0 or below"
            ));
        }
        if self.coarse_margin_db.is_some() {
            // Checked before the main run, not at the switch: a job must not fail after it.
            self.coarse_finetune().validate().map_err(|e| {
                format!(
                    "the coarse run's {e} (finetune.wm_lr_scale × coarse_wm_lr_factor, \
                     finetune.target_psnr − coarse_bound_drop_db)"
                )
            })?;
        }
        Ok(())
    }

    /// The finetuning options of the coarse decoder's run after a switch: the main run's, at
    /// `coarse_wm_lr_factor` times the rate and `coarse_bound_drop_db` below the bound.
    pub fn coarse_finetune(&self) -> FinetuneConfig {
        let mut f = self.finetune.clone();
        f.wm_lr_scale *= self.coarse_wm_lr_factor;
        if f.target_psnr > 0.0 {
            f.target_psnr -= self.coarse_bound_drop_db;
        }
        f
    }

    /// The paper's recipe: [`FinetuneConfig::paper`], plain decoding (no asset reference, the
    /// decoder's own head), the training cameras only.
    pub fn paper() -> Self {
        Self {
            finetune: FinetuneConfig::paper(),
            reference: false,
            projection: ProjectionConfig {
                matched: false,
                ..ProjectionConfig::default()
            },
            extra_views: 0,
            path: PathConfig {
                per_gap: 0,
                ..PathConfig::default()
            },
            // The paper reads every training view, with one decoder.
            analysis_views: 0,
            coarse_margin_db: None,
            ..Self::default()
        }
    }

    /// Render options of every render of the embedding.
    pub fn render_options(&self) -> RenderOptions {
        self.finetune.render_options()
    }
}

/// Where an embedding is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Targets,
    Plan,
    /// The matched head and the reference logits, measured on the original.
    Calibrate,
    Finetune,
    Done,
}

/// A progress report: phase, and within finetuning the step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Progress {
    pub phase: Phase,
    pub step: usize,
    pub total: usize,
    /// The finetuning step just done, if any.
    pub log: Option<StepLog>,
}

/// Why an embedding failed.
#[derive(Debug, thiserror::Error)]
pub enum EmbedError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Finetune(#[from] FinetuneError),
    #[error("no training views")]
    NoViews,
    #[error("the scene is empty")]
    EmptyScene,
    #[error("cancelled")]
    Cancelled,
    #[error("invalid embedding options: {0}")]
    Invalid(String),
}

/// Seconds spent per phase.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    pub targets: f64,
    pub plan: f64,
    /// Fitting the matched head (or view projection) and the reference logits on the original.
    #[serde(default)]
    pub calibrate: f64,
    /// The finetuning steps themselves.
    pub finetune: f64,
    /// The finetuning steps' time by part (render, watermark, visual, backward, update).
    #[serde(default)]
    pub steps: crate::embed::finetune::StepPhases,
    pub total: f64,
}

/// The report of one embedding.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EmbedReport {
    pub message_hex: String,
    pub bits: usize,
    /// The decoder the bits were written for ([`WatermarkModel::digest`]): a dispute must read
    /// them with the same one (the service registers it with the key; `splatmark verify
    /// --report` checks it).
    pub decoder: String,
    pub views: usize,
    /// Cameras interpolated along the training cameras' path ([`EmbedOptions::path`]).
    pub path_views: usize,
    /// Training views SBAG's visibility, the calibration and the reference read
    /// ([`EmbedOptions::analysis_views`]).
    pub analysis_views: usize,
    pub input_gaussians: usize,
    pub pruned: usize,
    pub output_gaussians: usize,
    pub carriers: usize,
    pub compensators: usize,
    pub budget: Budget,
    pub mask_wm: [f32; 5],
    pub mask_vis: [f32; 5],
    /// Share of the watermark gradient on the carriers (1 = all of it).
    pub wm_grad_share_carriers: f32,
    /// The last finetuning step.
    pub last_step: Option<StepLog>,
    /// How the training views decoded at the last check (`finetune.extra_steps` > 0 only).
    pub views_check: Option<ViewsCheck>,
    /// Whether the schedule stretched (`finetune.stretch_bce`), and on what loss.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stretch: Option<StretchCheck>,
    /// How the decoder was chosen, when there was a choice ([`EmbedOptions::coarse_margin_db`]
    /// and a coarse decoder): the main decoder's check, and whether the embedding switched.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub choice: Option<DecoderChoice>,
    pub timings: Timings,
    pub options: EmbedOptions,
    /// The original's mean logits over the training views when `options.reference` is on:
    /// verification subtracts them ([`WatermarkModel::with_reference`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_logits: Option<Vec<f32>>,
    /// The asset's matched head (the default, `options.projection.matched`) or rank-k view
    /// projection: verification decodes through it ([`WatermarkModel::with_projection`]); the
    /// service registers a matched head with the key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view_projection: Option<ViewProjection>,
}

/// The choice between the main and the coarse decoder ([`EmbedOptions::coarse_margin_db`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DecoderChoice {
    /// The main decoder's finetuning step at which it was made.
    pub step: usize,
    /// The training views' mean PSNR over the last tenth of `steps` up to `step` (dB).
    pub psnr: f32,
    /// The PSNR above which the embedding switches: `target_psnr` + the margin (dB).
    pub threshold: f32,
    /// Whether it switched: calibration and finetuning restarted with the coarse decoder,
    /// which the report's `decoder` then names.
    pub coarse: bool,
    /// Seconds spent on the main decoder's calibration and finetuning before a switch (0
    /// when it kept the main decoder), included in `timings.total`.
    pub discarded_s: f64,
    /// After a switch: the rate and bound the coarse decoder's finetuning ran at
    /// ([`EmbedOptions::coarse_finetune`]). Absent in reports from before the options existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_run: Option<CoarseRun>,
}

/// The rate and bound of the coarse decoder's finetuning after a switch.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseRun {
    /// `finetune.wm_lr_scale` of the coarse run.
    pub wm_lr_scale: f32,
    /// `finetune.target_psnr` of the coarse run (dB; 0 = no bound).
    pub target_psnr: f32,
}

impl DecoderChoice {
    /// One line for a log: what was measured and chosen.
    pub fn describe(&self) -> String {
        if self.coarse {
            let run = self.coarse_run.map_or(String::new(), |r| {
                format!(
                    "; the coarse run writes at wm_lr_scale {:.1} to a {:.1} dB bound",
                    r.wm_lr_scale, r.target_psnr
                )
            });
            format!(
                "decoder: coarse (the training views read {:.1} dB at step {}, above {:.1}: the \
                 asset leaves the fidelity budget free; {:.0} s of the main decoder's run \
                 discarded{run})",
                self.psnr, self.step, self.threshold, self.discarded_s
            )
        } else {
            format!(
                "decoder: main (the training views read {:.1} dB at step {}, at most {:.1})",
                self.psnr, self.step, self.threshold
            )
        }
    }
}

/// The watermarked asset and its explanation.
#[derive(Clone, Debug)]
pub struct Embedded {
    pub scene: Gaussians,
    pub records: Vec<AttributionRecord>,
    pub report: EmbedReport,
    /// Every finetuning step.
    pub log: Vec<StepLog>,
}

/// Embeds `message` into `g`, training on `cameras` (the caller keeps its held-out views out of
/// them). `decoders` are the frozen decoders on an autodiff device: the main one, and the
/// coarse one it may switch to ([`EmbedOptions::coarse_margin_db`]); the report's `decoder`
/// names the one the bits were written for ([`Pair::by_digest`]). `progress` is called at each
/// phase and finetuning step (a switch starts the calibration and the steps again); returning
/// [`ControlFlow::Break`] stops the embedding with [`EmbedError::Cancelled`].
pub fn embed(
    g: &Gaussians,
    cameras: &[Camera],
    message: &[bool],
    decoders: &Pair,
    opts: &EmbedOptions,
    mut progress: impl FnMut(Progress) -> ControlFlow<()>,
) -> Result<Embedded, EmbedError> {
    let t_all = Instant::now();
    if g.is_empty() {
        return Err(EmbedError::EmptyScene);
    }
    if cameras.is_empty() {
        return Err(EmbedError::NoViews);
    }
    opts.finetune.validate().map_err(EmbedError::Invalid)?;
    opts.path.validate().map_err(EmbedError::Invalid)?;
    opts.check_coarse().map_err(EmbedError::Invalid)?;
    // What the coarse run changes (rate, bound) is checked by `check_coarse`; the rest is
    // `opts.finetune`, validated above.
    let coarse_ft = opts.coarse_finetune();
    // The most steps finetuning may take (it may stop early when `extra_steps` > 0).
    let total = opts.finetune.steps + opts.finetune.extra_steps;
    // A phase's report: `done` steps already done (those a decoder switch discarded).
    let report_phase =
        |p: &mut dyn FnMut(Progress) -> ControlFlow<()>, phase, done| match p(Progress {
            phase,
            step: done,
            total: done + total,
            log: None,
        }) {
            ControlFlow::Continue(()) => Ok(()),
            ControlFlow::Break(()) => Err(EmbedError::Cancelled),
        };
    report_phase(&mut progress, Phase::Targets, 0)?;
    let ro = opts.render_options();
    let t = Instant::now();
    let mut finetune_cameras = cameras.to_vec();
    let path_views = path_cameras(cameras, &opts.path);
    let path_count = path_views.len();
    finetune_cameras.extend(path_views);
    if opts.extra_views > 0 {
        if opts.extra_views > 1000 {
            return Err(EmbedError::Invalid(format!(
                "extra_views is {}; at most 1000",
                opts.extra_views
            )));
        }
        let jitter = ProjectionConfig {
            views: opts.extra_views,
            seed: opts.projection.seed ^ 0x4558_5452_4156_4945,
            ..opts.projection.clone()
        };
        finetune_cameras.extend(calibration_cameras(g, cameras, &jitter).split_off(cameras.len()));
    }
    let views: Vec<View> = target_views(
        g,
        &scaled_views(&finetune_cameras, &opts.view_scales)?,
        &ro,
        &opts.finetune.rasterizer,
    )?;
    let t_targets = t.elapsed().as_secs_f64();
    // What planning and calibration read: every training view, or a spread subset of them.
    let cap = if message.len() > 32 {
        0
    } else {
        opts.analysis_views
    };
    let pick = spread_views(cameras, cap);
    let analysis: Vec<Camera> = pick.iter().map(|&i| cameras[i].clone()).collect();
    // The reference reads every finetuning view, or the picked cameras at every scale.
    let reference_cameras: Vec<&Camera> = if pick.len() == cameras.len() {
        views.iter().map(|v| &v.camera).collect()
    } else {
        let per_scale = finetune_cameras.len();
        let views = &views;
        (0..opts.view_scales.len())
            .flat_map(|s| pick.iter().map(move |&i| &views[s * per_scale + i].camera))
            .collect()
    };

    report_phase(&mut progress, Phase::Plan, 0)?;
    let t = Instant::now();
    let mut cfg = opts.plan.clone();
    if opts.no_group_mask {
        cfg.mask = MaskConfig {
            uniform: true,
            ..cfg.mask
        };
    }
    let p = plan_over(g, cameras, &analysis, message.len(), &cfg)?;
    let t_plan = t.elapsed().as_secs_f64();

    // The decoder: the main one, or the coarse one when the check says the asset leaves the
    // fidelity budget free (`coarse_margin_db`); the switch restarts calibration and
    // finetuning, which depend only on their seeds, so the result is the coarse decoder's
    // own embedding at the coarse run's rate and bound (`coarse_finetune`).
    let threshold = match (&decoders.coarse, opts.coarse_margin_db) {
        (Some(_), Some(m)) if opts.finetune.target_psnr > 0.0 => {
            Some(opts.finetune.target_psnr + m)
        }
        _ => None,
    };
    let check_at = choice_step(&opts.finetune);
    let window = check_window(&opts.finetune);
    let t_first = Instant::now();
    let mut writer = &decoders.main;
    let mut ft_cfg = &opts.finetune;
    let mut choice: Option<DecoderChoice> = None;
    // Steps a switch discarded: progress counts on from them, so that it never runs backwards.
    let mut discarded_steps = 0;
    let (projection, reference, ft, t_calibrate, t_ft) = loop {
        report_phase(&mut progress, Phase::Calibrate, discarded_steps)?;
        let t = Instant::now();
        let projection = if opts.projection.is_on() {
            let mut plain = writer.clone();
            plain.reference = None;
            plain.projection = None;
            Some(fit_projection(
                g,
                &analysis,
                &plain,
                &ro,
                &opts.projection,
                &opts.finetune.rasterizer,
            )?)
        } else {
            None
        };
        let model = match &projection {
            Some(p) => writer.clone().with_projection(p.clone()),
            None => writer.clone(),
        };
        let reference = if opts.reference {
            Some(reference_logits(
                g,
                reference_cameras.iter().copied(),
                &model,
                &ro,
                &opts.finetune.rasterizer,
            )?)
        } else {
            None
        };
        let model = match &reference {
            Some(r) => model.with_reference(r.clone()),
            None => model,
        };
        let t_calibrate = t.elapsed().as_secs_f64();

        report_phase(&mut progress, Phase::Finetune, discarded_steps)?;
        let t = Instant::now();
        let deciding = threshold.filter(|_| choice.is_none());
        let mut psnrs = Vec::new();
        let mut made = None;
        let mut stopped = false;
        let r = finetune(p.scene(), &p.masks, &views, &model, message, ft_cfg, |s| {
            if let Some(threshold) = deciding {
                psnrs.push(f64::from(s.psnr));
                if s.step == check_at {
                    let w = &psnrs[psnrs.len() - window.min(psnrs.len())..];
                    let psnr = w.iter().sum::<f64>() / w.len() as f64;
                    let c = DecoderChoice {
                        step: s.step,
                        psnr: psnr as f32,
                        threshold,
                        coarse: psnr > f64::from(threshold),
                        discarded_s: 0.0,
                        coarse_run: None,
                    };
                    made = Some(c);
                }
            }
            let flow = progress(Progress {
                phase: Phase::Finetune,
                step: discarded_steps + s.step,
                total: discarded_steps + s.planned,
                log: Some(*s),
            });
            stopped = flow.is_break();
            if !stopped && s.step == check_at && made.is_some_and(|c| c.coarse) {
                return ControlFlow::Break(());
            }
            flow
        });
        match r {
            Ok(ft) => {
                choice = choice.or(made);
                break (
                    projection,
                    reference,
                    ft,
                    t_calibrate,
                    t.elapsed().as_secs_f64(),
                );
            }
            Err(FinetuneError::Cancelled { .. }) if !stopped && made.is_some_and(|c| c.coarse) => {
                choice = made.map(|c| DecoderChoice {
                    discarded_s: t_first.elapsed().as_secs_f64(),
                    coarse_run: Some(CoarseRun {
                        wm_lr_scale: coarse_ft.wm_lr_scale,
                        target_psnr: coarse_ft.target_psnr,
                    }),
                    ..c
                });
                discarded_steps = check_at;
                ft_cfg = &coarse_ft;
                writer = decoders
                    .coarse
                    .as_ref()
                    .expect("a threshold only with a coarse decoder");
            }
            Err(FinetuneError::Cancelled { .. }) => return Err(EmbedError::Cancelled),
            Err(e) => return Err(e.into()),
        }
    };
    let ft: Finetuned = ft;
    let ft_steps = ft.log.last().map_or(total, |s| s.step);

    let mut records = p.records;
    for (r, &s) in records.iter_mut().zip(&ft.wm_grad_share) {
        r.wm_grad_share = Some(s);
    }
    let carriers = p.masks.is_carrier.iter().filter(|&&c| c).count();
    let compensators = records
        .iter()
        .filter(|r| r.role == super::sbag::Role::Compensator)
        .count();
    let share: f32 = ft
        .wm_grad_share
        .iter()
        .zip(&p.masks.is_carrier)
        .filter(|&(_, &c)| c)
        .map(|(s, _)| s)
        .sum();
    let report = EmbedReport {
        message_hex: to_hex(message),
        bits: message.len(),
        views: cameras.len(),
        path_views: path_count,
        analysis_views: pick.len(),
        input_gaussians: g.len(),
        pruned: p.prune.as_ref().map_or(0, |r| r.removed()),
        output_gaussians: ft.gaussians.len(),
        carriers,
        compensators,
        budget: p.sbag.selection.budget.clone(),
        mask_wm: p.masks.wm_group,
        mask_vis: p.masks.vis_group,
        wm_grad_share_carriers: share,
        last_step: ft.log.last().copied(),
        views_check: ft.check,
        stretch: ft.stretch,
        choice,
        timings: Timings {
            targets: t_targets,
            plan: t_plan,
            calibrate: t_calibrate,
            finetune: t_ft,
            steps: ft.phases,
            total: t_all.elapsed().as_secs_f64(),
        },
        options: opts.clone(),
        reference_logits: reference,
        view_projection: projection,
        decoder: writer.digest(),
    };
    // Every step taken, the discarded ones too: the last report reads done.
    let done = discarded_steps + ft_steps;
    let _ = progress(Progress {
        phase: Phase::Done,
        step: done,
        total: done,
        log: None,
    });
    Ok(Embedded {
        scene: ft.gaussians,
        records,
        report,
        log: ft.log,
    })
}

/// The asset reference of `original`: its logits through `cameras` as a dispute decodes them
/// (each view rendered to 8 bits, decoded, the logits averaged), with `model`'s own reference,
/// if any, left out.
pub fn reference_logits<'a>(
    original: &Gaussians,
    cameras: impl IntoIterator<Item = &'a Camera>,
    model: &WatermarkModel,
    opts: &RenderOptions,
    rasterizer: &Rasterizer,
) -> Result<Vec<f32>, EmbedError> {
    let mut plain = model.clone();
    plain.reference = None;
    Ok(super::finetune::cameras_logits(
        original, cameras, &plain, opts, rasterizer,
    )?)
}

#[cfg(test)]
mod tests;
