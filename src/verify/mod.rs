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
