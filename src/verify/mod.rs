//! Verification: deciding whether a rendered image carries a registered watermark message, from
//! the bits a decoder reads out of it.
//!
//! [`stats`] holds the exact detection statistics (binomial p-values, thresholds for a target
//! false-positive rate, multiple-testing correction across registered messages).

pub mod bench;
pub mod dispute;
pub mod eval;
pub mod message;
pub mod paper;
pub mod stats;

use std::ops::ControlFlow;

use crate::embed::pipeline::{Phase, Progress};

pub use stats::{
    Detection, MAX_BITS, StatsError, binomial_tail, corrected_p_value, detect, log10_binomial_tail,
    matches_from_logits, threshold_for_fpr, threshold_for_fpr_among,
};

/// What the benches (`bench quality`, `bench paper`) report as they go: lines of text, and every
/// step of each embedding (what a progress bar draws). A closure taking `&str` is one that keeps
/// only the lines.
pub trait BenchLog {
    /// A line of text.
    fn line(&mut self, text: &str);
    /// Step `step` of `total` of `what` (one embedding of the bench) is done.
    fn step(&mut self, what: &str, step: usize, total: usize) {
        let _ = (what, step, total);
    }
}

impl<F: FnMut(&str)> BenchLog for F {
    fn line(&mut self, text: &str) {
        self(text);
    }
}

/// The progress callback a bench hands one embedding, `what` naming it: every report goes to
/// [`BenchLog::step`] (the finetuning's steps; the phases before it as phases without steps),
/// and every tenth of the finetuning a line of the training views' bits and PSNR. Never stops
/// the embedding.
fn embed_progress<'a>(
    log: &'a mut dyn BenchLog,
    what: &'a str,
) -> impl FnMut(Progress) -> ControlFlow<()> + 'a {
    let mut last = 0;
    move |p| {
        let phase = format!("{what} {}", format!("{:?}", p.phase).to_lowercase());
        let total = if p.phase == Phase::Finetune {
            p.total
        } else {
            0
        };
        log.step(&phase, p.step, total);
        if p.phase == Phase::Calibrate {
            // A tenth from where this decoder's steps start (after a switch, on from the
            // discarded ones).
            last = p.step;
        }
        if p.total > 0 && p.step >= last + (p.total / 10).max(1) {
            last = p.step;
            if let Some(s) = p.log {
                log.line(&format!(
                    "  step {}/{}: train bits {:.3} (EOT {:.3}), {:.1} dB",
                    p.step, p.total, s.bit_acc_clean, s.bit_acc_eot, s.psnr
                ));
            }
        }
        ControlFlow::Continue(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::embed::finetune::StepLog;

    #[derive(Default)]
    struct Recorded {
        lines: Vec<String>,
        steps: Vec<(String, usize, usize)>,
    }

    impl BenchLog for Recorded {
        fn line(&mut self, text: &str) {
            self.lines.push(text.to_string());
        }
        fn step(&mut self, what: &str, step: usize, total: usize) {
            self.steps.push((what.to_string(), step, total));
        }
    }

    #[test]
    fn a_bench_logs_every_step_and_a_line_every_tenth_of_the_finetuning_across_a_switch() {
        let mut log = Recorded::default();
        let report = |phase, step, total| Progress {
            phase,
            step,
            total,
            log: (phase == Phase::Finetune).then(|| StepLog {
                step,
                bit_acc_clean: 0.5,
                bit_acc_eot: 0.25,
                psnr: 40.0,
                ..StepLog::default()
            }),
        };
        {
            let mut p = embed_progress(&mut log, "donut 32");
            let mut send = |phase, step, total| {
                assert_eq!(p(report(phase, step, total)), ControlFlow::Continue(()));
            };
            send(Phase::Targets, 0, 100);
            send(Phase::Calibrate, 0, 100);
            for s in 1..=30 {
                send(Phase::Finetune, s, 100);
            }
            // A switch at step 30: the coarse decoder's 100 steps count on from there.
            send(Phase::Calibrate, 30, 130);
            for s in 31..=130 {
                send(Phase::Finetune, s, 130);
            }
        }
        // Every report reaches the bar, the phases before finetuning without a total.
        assert_eq!(log.steps.len(), 2 + 30 + 1 + 100);
        assert_eq!(log.steps[0], ("donut 32 targets".to_string(), 0, 0));
        assert_eq!(log.steps[2], ("donut 32 finetune".to_string(), 1, 100));
        assert_eq!(log.steps[32], ("donut 32 calibrate".to_string(), 30, 0));
        // A line every tenth: steps 10, 20, 30, then every 13 steps from the switch.
        let at: Vec<String> = log
            .lines
            .iter()
            .map(|l| l.split(':').next().unwrap().trim().to_string())
            .collect();
        let mut want = vec!["step 10/100", "step 20/100", "step 30/100"];
        let after: Vec<String> = (1..=7)
            .map(|k| format!("step {}/130", 30 + 13 * k))
            .collect();
        want.extend(after.iter().map(String::as_str));
        assert_eq!(at, want);
        assert_eq!(
            log.lines[0],
            "  step 10/100: train bits 0.500 (EOT 0.250), 40.0 dB"
        );
    }
}
