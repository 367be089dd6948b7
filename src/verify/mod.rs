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
