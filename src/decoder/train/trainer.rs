//! The training run in memory: [`Trainer`] (fresh, from an artifact or resumed), one
//! optimisation step, progress lines, checkpoints and the final artifact.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::checkpoint::{load_module_bytes, module_bytes, optimizer, record_err};
use super::{
    CheckpointState, TrainConfig, TrainError, WatermarkNet, bce_with_logits, decide_whitening, hms,
    io_err, psnr_from_mse, read_checkpoint, step_seed, write_checkpoint,
};
use crate::attack::diff::{DiffAttack, EotRng, random_composition, straight_through_round};
use crate::decoder::artifact::{self, Sidecar, TrainingRecord, WatermarkModel};
use crate::decoder::data::ImageSet;
use crate::decoder::eval;

/// Numbers of one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepStats {
    /// 1-based index of the step just done.
    pub step: usize,
    pub loss: f64,
    pub bce: f64,
    pub image_mse: f64,
    /// Bit accuracy of the (attacked) training batch.
    pub bit_accuracy: f64,
    pub attack_probability: f64,
    pub lr: f64,
}

/// A progress line: averages over the `log_every` steps before `step`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogEntry {
    pub step: usize,
    pub loss: f64,
    pub bce: f64,
    pub image_mse: f64,
    pub psnr_db: f64,
    pub bit_accuracy: f64,
    pub attack_probability: f64,
    pub images_per_s: f64,
}

/// A training run in memory.
pub struct Trainer {
    pub config: TrainConfig,
    device: Device,
    pub net: WatermarkNet,
    optim: ModuleOptimizer,
    /// Steps done.
    pub step: usize,
    train: ImageSet,
    /// Wall time of earlier sessions (resumed runs).
    wall_before: f64,
    session_start: Instant,
    session_first_step: usize,
    pub history: Vec<LogEntry>,
    window: Vec<StepStats>,
    window_start: Instant,
    /// The command line, for the training record.
    pub command: Option<String>,
    /// The training data, for the training record.
    pub data: Option<String>,
    /// The artifact this run started from (`--init`), for the training record.
    pub started_from: Option<StartedFrom>,
}

/// The trained artifact a run was initialised from (`--init`): its path and training record, so
/// a fine-tuned model's sidecar keeps its whole history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StartedFrom {
    /// The decoder weights given to `--init`.
    pub path: String,
    /// Their training record.
    pub record: Option<Box<artifact::TrainingRecord>>,
}

impl Trainer {
    /// A fresh run (weights initialised from `config.seed`).
    pub fn new(config: TrainConfig, train: ImageSet) -> Result<Self, TrainError> {
        config.validate()?;
        train.check_crop(config.crop)?;
        let base = config.device.device();
        base.seed(config.seed);
        let device = base.autodiff();
        let net = WatermarkNet {
            encoder: config.init_encoder(&device),
            decoder: config.decoder_config().init(&device),
        };
        Ok(Self::assemble(
            config,
            device,
            net,
            optimizer(),
            0,
            train,
            0.0,
            Vec::new(),
        ))
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        config: TrainConfig,
        device: Device,
        net: WatermarkNet,
        optim: ModuleOptimizer,
        step: usize,
        train: ImageSet,
        wall_before: f64,
        history: Vec<LogEntry>,
    ) -> Self {
        Self {
            config,
            device,
            net,
            optim,
            step,
            train,
            wall_before,
            session_start: Instant::now(),
            session_first_step: step,
            history,
            window: Vec::new(),
            window_start: Instant::now(),
            command: None,
            data: None,
            started_from: None,
        }
    }

    /// A run that starts from the trained artifact at `path` (decoder, encoder and sidecar; fresh
    /// Adam state, step 0): fine-tuning. The architecture and the embedding strength come from
    /// the artifact's training configuration; everything else from `config`.
    pub fn from_artifact(
        mut config: TrainConfig,
        train: ImageSet,
        path: &Path,
    ) -> Result<Self, TrainError> {
        let read = |p: &Path| std::fs::read(p).map_err(io_err(p));
        let sidecar_path = artifact::sidecar_path(path);
        let sidecar: Sidecar =
            serde_json::from_slice(&read(&sidecar_path)?).map_err(|source| TrainError::Json {
                path: sidecar_path.clone(),
                source,
            })?;
        let base = sidecar.train_config.as_ref().ok_or_else(|| {
            TrainError::Config(format!(
                "{}: the sidecar has no training configuration to continue from",
                sidecar_path.display()
            ))
        })?;
        if base.bits != config.bits {
            return Err(TrainError::Config(format!(
                "{} decodes {} bits, not {}",
                path.display(),
                base.bits,
                config.bits
            )));
        }
        config.strength = base.strength;
        config.decoder_channels = base.decoder_channels;
        config.decoder_depth = base.decoder_depth;
        config.encoder = base.encoder;
        config.encoder_tile = base.encoder_tile;
        config.encoder_channels = base.encoder_channels;
        config.encoder_blocks = base.encoder_blocks;
        config.encoder_levels = base.encoder_levels;
        config.validate()?;
        train.check_crop(config.crop)?;
        let plain = config.device.device();
        plain.seed(config.seed);
        let device = plain.autodiff();
        let decoder = load_module_bytes(config.decoder_config().init(&device), read(path)?, path)?;
        let enc_path = artifact::encoder_path(path);
        let encoder = load_module_bytes(config.init_encoder(&device), read(&enc_path)?, &enc_path)?;
        let mut t = Self::assemble(
            config,
            device,
            WatermarkNet { encoder, decoder },
            optimizer(),
            0,
            train,
            0.0,
            Vec::new(),
        );
        t.started_from = Some(StartedFrom {
            path: path.display().to_string(),
            record: sidecar.record.map(Box::new),
        });
        Ok(t)
    }

    /// Continues from the checkpoint folder `dir` (one `step-NNNNNNNN`). `adjust` may change
    /// the stored config (only `steps`, `log_every`, `checkpoint_every` and `keep_checkpoints`
    /// are taken from it).
    pub fn resume(
        dir: &Path,
        train: ImageSet,
        adjust: impl FnOnce(&TrainConfig) -> TrainConfig,
    ) -> Result<Self, TrainError> {
        let (state, net_bytes, optim) = read_checkpoint::<CheckpointState>(dir)?;
        let mut config = state.config.clone();
        let wanted = adjust(&config);
        config.steps = wanted.steps;
        config.log_every = wanted.log_every;
        config.checkpoint_every = wanted.checkpoint_every;
        config.keep_checkpoints = wanted.keep_checkpoints;
        config.validate()?;
        train.check_crop(config.crop)?;
        let device = config.device.device().autodiff();
        let fresh = WatermarkNet {
            encoder: config.init_encoder(&device),
            decoder: config.decoder_config().init(&device),
        };
        let net = load_module_bytes(fresh, net_bytes, &dir.join("net.bpk"))?;
        let mut t = Self::assemble(
            config,
            device,
            net,
            optim,
            state.step,
            train,
            state.wall_s,
            state.history,
        );
        t.started_from = state.started_from;
        Ok(t)
    }

    /// Whether all steps are done.
    pub fn done(&self) -> bool {
        self.step >= self.config.steps
    }

    /// Training wall time so far (all sessions), seconds.
    pub fn wall_s(&self) -> f64 {
        self.wall_before + self.session_start.elapsed().as_secs_f64()
    }

    /// One optimisation step.
    pub fn step(&mut self) -> Result<StepStats, TrainError> {
        let c = &self.config;
        let k = self.step;
        let mut rng = EotRng::new(step_seed(c.seed, k));
        let (b, l, s) = (c.batch_size, c.bits, c.crop);
        let pixels = self.train.sample_batch(&mut rng, b, s, c.min_scale, true);
        let bits: Vec<f32> = (0..b * l).map(|_| (rng.next_u64() >> 63) as f32).collect();
        let cover = Tensor::<4>::from_data(TensorData::new(pixels, [b, 3, s, s]), &self.device);
        let message = Tensor::<2>::from_data(TensorData::new(bits.clone(), [b, l]), &self.device);

        let residual = artifact::encoder_residual(
            &self.net.encoder,
            cover.clone(),
            message.clone(),
            c.encoder_levels,
        );
        let marked = cover
            .clone()
            .add(residual.mul_scalar(c.strength))
            .clamp(0.0, 1.0);
        let marked = straight_through_round(marked.mul_scalar(255.0)).div_scalar(255.0);
        let mse = marked.clone().sub(cover).square().mean();

        // Unmarked crops (drawn only when enabled, so runs without them keep their random
        // streams).
        let mut unmarked = (c.unmarked_crops > 0 && c.unmarked_weight > 0.0).then(|| {
            let u = c.unmarked_crops;
            let px = self.train.sample_batch(&mut rng, u, s, c.min_scale, true);
            let x = Tensor::<4>::from_data(TensorData::new(px, [u, 3, s, s]), &self.device);
            straight_through_round(x.mul_scalar(255.0)).div_scalar(255.0)
        });
        let mut unmarked_logits = None;
        let p = c.attack_probability(k);
        let groups = c.attack_groups.clamp(1, b);
        let mut logits = Vec::with_capacity(groups);
        let mut start = 0;
        for g in 0..groups {
            let len = b / groups + usize::from(g < b % groups);
            let part = marked.clone().narrow(0, start, len);
            start += len;
            let attack = if p > 0.0 && rng.uniform() < p {
                random_composition(&c.eot, &mut rng)
            } else {
                DiffAttack::Chain(Vec::new())
            };
            // The unmarked crops join the first group: same attack, same forward pass (and
            // BatchNorm batch), so they are treated like the watermarked images they must be
            // told apart from.
            if g == 0
                && let Some(u) = unmarked.take()
            {
                let z = self
                    .net
                    .decoder
                    .forward(attack.apply(Tensor::cat(vec![part, u], 0))?);
                unmarked_logits = Some(z.clone().narrow(0, len, c.unmarked_crops));
                logits.push(z.narrow(0, 0, len));
            } else {
                logits.push(self.net.decoder.forward(attack.apply(part)?));
            }
        }
        let logits = Tensor::cat(logits, 0);
        let bce = bce_with_logits(logits.clone(), message);
        let mut loss = bce
            .clone()
            .add(mse.clone().mul_scalar(c.image_weight * c.ramp(k)));
        if let Some(z) = unmarked_logits {
            // Ramped in like the image loss: from step 0 it holds every logit at 0 before the
            // decoder has learnt to tell marked from unmarked images (measured: still at chance,
            // 50.1 %, after 950 steps).
            let half = z.zeros_like().add_scalar(0.5);
            loss = loss.add(bce_with_logits(z, half).mul_scalar(c.unmarked_weight * c.ramp(k)));
        }

        let grads = GradientsParams::from_grads(loss.backward(), &self.net);
        let lr = c.lr_at(k);
        self.net = self.optim.step(lr, self.net.clone(), grads);

        let z: Vec<f32> = logits.detach().try_into_vec_as::<f32>().unwrap_or_default();
        let correct = z
            .iter()
            .zip(&bits)
            .filter(|&(&z, &m)| (z > 0.0) == (m > 0.5))
            .count();
        let scalar = |t: Tensor<1>| f64::from(t.detach().into_scalar::<f32>());
        let (loss, bce, mse) = (scalar(loss), scalar(bce), scalar(mse));
        if !loss.is_finite() {
            return Err(TrainError::Diverged(k + 1));
        }
        self.step += 1;
        let stats = StepStats {
            step: self.step,
            loss,
            bce,
            image_mse: mse,
            bit_accuracy: correct as f64 / (b * l) as f64,
            attack_probability: p,
            lr,
        };
        self.window.push(stats);
        Ok(stats)
    }

    /// Closes the current logging window: its averages as a [`LogEntry`], appended to the
    /// history.
    pub fn log_entry(&mut self) -> Option<LogEntry> {
        let n = self.window.len();
        if n == 0 {
            return None;
        }
        let mean = |f: fn(&StepStats) -> f64| self.window.iter().map(f).sum::<f64>() / n as f64;
        let mse = mean(|s| s.image_mse);
        let secs = self.window_start.elapsed().as_secs_f64().max(1e-9);
        let entry = LogEntry {
            step: self.step,
            loss: mean(|s| s.loss),
            bce: mean(|s| s.bce),
            image_mse: mse,
            psnr_db: psnr_from_mse(mse),
            bit_accuracy: mean(|s| s.bit_accuracy),
            attack_probability: mean(|s| s.attack_probability),
            images_per_s: (n * self.config.batch_size) as f64 / secs,
        };
        self.window.clear();
        self.window_start = Instant::now();
        self.history.push(entry.clone());
        Some(entry)
    }

    /// A human-readable progress line for `entry`, with the ETA from this session's pace.
    pub fn progress_line(&self, entry: &LogEntry) -> String {
        let done = self.step - self.session_first_step;
        let elapsed = self.session_start.elapsed().as_secs_f64();
        let eta = if done > 0 {
            elapsed / done as f64 * (self.config.steps.saturating_sub(self.step)) as f64
        } else {
            0.0
        };
        format!(
            "step {}/{} | loss {:.4} (bce {:.4}, mse {:.2e} → {:.1} dB) | bit acc {:.3} | attack p {:.2} | lr {:.1e} | {:.1} img/s | elapsed {} | ETA {}",
            self.step,
            self.config.steps,
            entry.loss,
            entry.bce,
            entry.image_mse,
            entry.psnr_db,
            entry.bit_accuracy,
            entry.attack_probability,
            self.config.lr_at(self.step.saturating_sub(1)),
            entry.images_per_s,
            hms(self.wall_s()),
            hms(eta),
        )
    }

    /// Writes a checkpoint of the current state under `root` (atomically) and prunes old ones.
    pub fn save_checkpoint(&self, root: &Path) -> Result<PathBuf, TrainError> {
        // BatchNorm running statistics hold their newest update in a per-thread slot until the
        // next forward pass; `valid` folds it in (shared state), so the record is current.
        let _ = self.net.valid();
        let net_path = root.join("net.bpk");
        let net = module_bytes(self.net.clone(), &net_path)?;
        let optim_path = root.join("optim.bpk");
        let optim = self
            .optim
            .into_bytes()
            .map_err(|e| record_err(&optim_path, e))?;
        let state = CheckpointState {
            version: 1,
            step: self.step,
            config: self.config.clone(),
            rng: format!(
                "step k draws from SplitMix64(step_seed({}, k)); next k = {}",
                self.config.seed, self.step
            ),
            wall_s: self.wall_s(),
            history: self.history.clone(),
            started_from: self.started_from.clone(),
        };
        let json = serde_json::to_vec_pretty(&state).expect("state serialises");
        write_checkpoint(
            root,
            self.step,
            &[
                ("net.bpk", &net),
                ("optim.bpk", &optim[..]),
                ("state.json", &json),
            ],
            self.config.keep_checkpoints,
        )
    }

    /// The trained model as used after training: frozen decoder and encoder on the plain
    /// device, the whitening not yet decided. A deep copy (through a burnpack record): freezing
    /// a `valid()` snapshot in place would also switch off the BatchNorm training flags of the
    /// live network, which shares them, and silently change the following training steps.
    pub fn model(&self) -> WatermarkModel {
        let c = &self.config;
        let device = c.device.device();
        let _ = self.net.valid(); // folds pending BatchNorm statistics in
        let bytes = artifact::to_burnpack(self.net.valid()).expect("weights serialise");
        let fresh = WatermarkNet {
            encoder: c.init_encoder(&device),
            decoder: c.decoder_config().init(&device),
        };
        let net = artifact::from_burnpack(fresh, bytes).expect("own weights load");
        WatermarkModel {
            sidecar: Sidecar::new(c, None),
            decoder: net.decoder.frozen(),
            encoder: Some(net.encoder.freeze()),
            reference: None,
            projection: None,
            file_digest: None,
        }
    }

    /// Freezes the decoder, decides on the whitening, evaluates on `held_out` (if configured)
    /// and writes the artifact to `out`. Returns the sidecar written.
    pub fn finish(
        &self,
        out: &Path,
        held_out: Option<&ImageSet>,
        log: &mut dyn Write,
    ) -> Result<Sidecar, TrainError> {
        let c = &self.config;
        let mut model = self.model();
        let device = c.device.device();
        let (whitening, report) =
            decide_whitening(&model, &self.train, held_out, c, c.whitening, &device, log)?;
        model.sidecar.whitening = whitening;
        let evaluation = match (c.final_eval, held_out) {
            (true, Some(h)) => {
                let _ = writeln!(log, "evaluating on {} held-out images…", h.len());
                let r = eval::evaluate_on(&model, &h.images, &c.eval, &device)?;
                Some(r)
            }
            _ => None,
        };
        model.sidecar.record = Some(TrainingRecord {
            steps: self.step,
            wall_s: self.wall_s(),
            images_per_s: self.history.last().map(|e| e.images_per_s),
            final_log: self.history.last().cloned(),
            whitening: report,
            held_out: evaluation,
            command: self.command.clone(),
            data: self.data.clone(),
            started_from: self.started_from.clone(),
            calibrated_by: None,
        });
        model.save(out)?;
        Ok(model.sidecar)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::train::tests::{synthetic_set, tiny_artifact, tiny_config};
    use crate::decoder::train::{WhiteningChoice, list_checkpoints};

    #[test]
    fn a_few_steps_reduce_the_loss_and_checkpoint() {
        let set = synthetic_set(6, 48, 1);
        let config = TrainConfig {
            steps: 80,
            decoder_channels: 16,
            encoder_channels: 16,
            attack_groups: 1,
            ..tiny_config()
        };
        let mut t = Trainer::new(config, set).unwrap();
        // (Weight initialisation draws from burn's global RNG, which tests running in parallel
        // share, so the exact curve varies from run to run; the margin is generous.)
        let losses: Vec<f64> = (0..80).map(|_| t.step().unwrap().loss).collect();
        let first: f64 = losses[..10].iter().sum::<f64>() / 10.0;
        let last: f64 = losses[70..].iter().sum::<f64>() / 10.0;
        assert!(last < first - 0.03, "loss {first} → {last}: {losses:?}");
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("d.bpk.ckpt");
        let saved = t.save_checkpoint(&root).unwrap();
        assert_eq!(saved.file_name().unwrap(), "step-00000080");
        for f in ["net.bpk", "optim.bpk", "state.json"] {
            assert!(saved.join(f).is_file(), "{f}");
        }
        assert_eq!(list_checkpoints(&root), vec![(80, saved)]);
        // No temporary folders left behind.
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
    }

    #[test]
    fn resume_continues_exactly_where_it_stopped() {
        let mut config = tiny_config();
        config.steps = 6;
        // Attacks from the third step on, so the resumed steps draw attacks too.
        config.warmup_steps = 2;
        config.ramp_steps = 1;
        config.keep_checkpoints = 2;
        let set = synthetic_set(4, 48, 2);
        let outputs = probe_outputs(&set, 99);

        // Both runs start from the same weights (burn's weight-init RNG is global, so two
        // `Trainer::new` in parallel tests need not draw the same ones).
        let dir = tempfile::tempdir().unwrap();
        let mut first = Trainer::new(config.clone(), set.clone()).unwrap();
        let start = first.save_checkpoint(&dir.path().join("start")).unwrap();
        let mut straight = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        for _ in 0..6 {
            straight.step().unwrap();
        }

        let root = dir.path().join("ckpt");
        for _ in 0..3 {
            first.step().unwrap();
            first.save_checkpoint(&root).unwrap();
        }
        // Pruned to the newest two.
        let steps: Vec<usize> = list_checkpoints(&root).iter().map(|c| c.0).collect();
        assert_eq!(steps, [2, 3]);
        let latest = list_checkpoints(&root).pop().unwrap().1;
        let mut resumed = Trainer::resume(&latest, set.clone(), |c| c.clone()).unwrap();
        assert_eq!(resumed.step, 3);
        assert_eq!(outputs(&resumed), outputs(&first));
        while !resumed.done() {
            resumed.step().unwrap();
        }
        assert_eq!(resumed.step, 6);
        let (a, b) = (outputs(&straight), outputs(&resumed));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-3 * (1.0 + x.abs()), "{a:?} vs {b:?}");
        }

        // Without the Adam state the continuation differs (the test above is not vacuous).
        let mut no_adam = Trainer::resume(&latest, set, |c| c.clone()).unwrap();
        no_adam.optim = optimizer();
        while !no_adam.done() {
            no_adam.step().unwrap();
        }
        let c = outputs(&no_adam);
        let diff: f32 = a.iter().zip(&c).map(|(x, y)| (x - y).abs()).sum();
        assert!(diff > 1e-3, "Adam state made no difference");

        // Extending the run on resume.
        let longer = Trainer::resume(&latest, synthetic_set(4, 48, 2), |c| TrainConfig {
            steps: 10,
            lr: 123.0, // ignored
            ..c.clone()
        })
        .unwrap();
        assert_eq!(longer.config.steps, 10);
        assert_eq!(longer.config.lr, config.lr);
    }

    /// The decoder logits (inference mode) of a trainer on two fixed 32² crops of `set`.
    fn probe_outputs(set: &ImageSet, seed: u64) -> impl Fn(&Trainer) -> Vec<f32> + use<> {
        let probe = Tensor::<4>::from_data(
            TensorData::new(
                set.sample_batch(&mut EotRng::new(seed), 2, 32, 1.0, false),
                [2, 3, 32, 32],
            ),
            &Device::flex(),
        );
        move |t: &Trainer| {
            t.model()
                .decoder
                .forward(probe.clone())
                .try_into_vec_as::<f32>()
                .unwrap()
        }
    }

    #[test]
    fn init_starts_a_fine_tune_from_a_trained_artifact() {
        let set = synthetic_set(4, 48, 3);
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("base.bpk");
        let base = TrainConfig {
            steps: 3,
            whitening: WhiteningChoice::Never,
            ..tiny_config()
        };
        let trained = tiny_artifact(base.clone(), set.clone(), &out);
        let outputs = probe_outputs(&set, 5);

        // Another architecture and strength asked for: the artifact's win; the rest is ours.
        let wanted = TrainConfig {
            decoder_channels: 16,
            encoder_tile: 4,
            strength: 0.9,
            lr: 5e-4,
            steps: 2,
            ..base.clone()
        };
        let mut ft = Trainer::from_artifact(wanted, set.clone(), &out).unwrap();
        assert_eq!(ft.step, 0);
        assert_eq!(ft.config.decoder_channels, base.decoder_channels);
        assert_eq!(ft.config.encoder_tile, base.encoder_tile);
        assert_eq!(ft.config.strength, base.strength);
        assert_eq!(ft.config.lr, 5e-4);
        assert_eq!(outputs(&ft), outputs(&trained));
        let from = ft.started_from.clone().unwrap();
        assert_eq!(from.path, out.display().to_string());
        assert_eq!(from.record.as_ref().unwrap().steps, 3);
        while !ft.done() {
            ft.step().unwrap();
        }
        assert_ne!(outputs(&ft), outputs(&trained));
        // The lineage survives a checkpoint round trip and lands in the new artifact.
        let ckpt = ft.save_checkpoint(&dir.path().join("ft.ckpt")).unwrap();
        let resumed = Trainer::resume(&ckpt, set.clone(), |c| c.clone()).unwrap();
        assert_eq!(resumed.started_from, ft.started_from);
        let out2 = dir.path().join("ft.bpk");
        let sidecar = ft.finish(&out2, None, &mut Vec::new()).unwrap();
        assert_eq!(
            sidecar
                .record
                .unwrap()
                .started_from
                .unwrap()
                .record
                .unwrap()
                .steps,
            3
        );

        // Bad starts are typed errors.
        let wrong_bits = TrainConfig {
            bits: 8,
            ..base.clone()
        };
        assert!(matches!(
            Trainer::from_artifact(wrong_bits, set.clone(), &out),
            Err(TrainError::Config(_))
        ));
        assert!(matches!(
            Trainer::from_artifact(base, set, &dir.path().join("missing.bpk")),
            Err(TrainError::Io { .. })
        ));
    }

    #[test]
    fn the_unmarked_loss_adds_a_coin_toss_term() {
        // Two runs from one checkpoint, one with the unmarked loss: its loss carries
        // weight · BCE(z, ½) ≥ weight · ln 2 on top of (about) the same watermark loss.
        let set = synthetic_set(4, 48, 4);
        let dir = tempfile::tempdir().unwrap();
        let t = Trainer::new(tiny_config(), set.clone()).unwrap();
        let start = t.save_checkpoint(&dir.path().join("c")).unwrap();
        // In the warm-up the term is off (it ramps in with the attacks).
        let mut warm = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        warm.config.unmarked_crops = 3;
        warm.config.unmarked_weight = 10.0;
        let w = warm.step().unwrap();
        assert!(w.loss - w.bce < 1e-6, "{w:?}");
        let mut plain = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        let mut with = Trainer::resume(&start, set.clone(), |c| c.clone()).unwrap();
        // After the ramp (resume keeps the schedule of the checkpoint, so set it here).
        for t in [&mut plain, &mut with] {
            t.config.warmup_steps = 0;
            t.config.ramp_steps = 0;
        }
        with.config.unmarked_crops = 3;
        with.config.unmarked_weight = 10.0;
        let (a, b) = (plain.step().unwrap(), with.step().unwrap());
        assert!(
            b.loss - b.bce >= 10.0 * std::f64::consts::LN_2 - 1e-3,
            "{a:?} vs {b:?}"
        );
        assert!(a.loss - a.bce < 1e-6, "no image loss (weight 0): {a:?}");
        // Training with it drives the unmarked logits towards 0 (coin tosses).
        let mean_abs = |t: &Trainer| {
            let m = t.model();
            let px = set.sample_batch(&mut EotRng::new(8), 8, 32, 1.0, false);
            let x = Tensor::<4>::from_data(TensorData::new(px, [8, 3, 32, 32]), &Device::flex());
            let z = m.decoder.forward(x).try_into_vec_as::<f32>().unwrap();
            z.iter().map(|v| v.abs()).sum::<f32>() / z.len() as f32
        };
        for _ in 0..30 {
            plain.step().unwrap();
            with.step().unwrap();
        }
        let (za, zb) = (mean_abs(&plain), mean_abs(&with));
        assert!(
            zb < za,
            "unmarked |logit| {zb} with the loss vs {za} without"
        );
    }
}
