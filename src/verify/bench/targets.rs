//! The targets and each run's figures checked against them.

use serde::Serialize;

use crate::verify::eval::SceneEval;

/// One figure against its target.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetCheck {
    pub name: String,
    pub value: f64,
    /// `value ≥ target` is met (for "unmarked_detected", 0 = not detected is met).
    pub target: f64,
    pub met: bool,
    /// Bit-accuracy targets: the bits the figure counts (views × message bits, × draws for a
    /// model attack), how many of
    /// them were right, and how many the target needs — the judge's resolution (on udon's two
    /// held-out cameras at 32 bits one bit is 1.6 points).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bits: Option<BitCount>,
}

/// Bits behind a bit-accuracy figure.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct BitCount {
    pub right: usize,
    pub counted: usize,
    pub needed: usize,
}

impl BitCount {
    /// The count behind `accuracy` (a mean over `views` of per-view accuracies of `bits` bits
    /// each) and the fewest right bits that reach `target`.
    pub fn of(accuracy: f64, views: usize, bits: usize, target: f64) -> Self {
        let counted = views * bits;
        let n = counted as f64;
        Self {
            right: (accuracy * n).round() as usize,
            counted,
            // The 1e-9 keeps a product that is an integer up to rounding (0.5 · 64) from
            // asking for one bit more.
            needed: ((target * n - 1e-9).ceil().max(0.0) as usize).min(counted),
        }
    }
}

impl TargetCheck {
    /// How the bench names a missed target: with the bits counted for an accuracy ("clean
    /// (63 of 64 bits; 64 needed)"), the value for PSNR and SSIM, the name alone for a decision.
    pub fn describe(&self) -> String {
        match (self.bits, self.name.as_str()) {
            (Some(b), _) => format!(
                "{} ({} of {} bits; {} needed)",
                self.name, b.right, b.counted, b.needed
            ),
            (None, "psnr") => format!("psnr ({:.2} dB; {} needed)", self.value, self.target),
            (None, "ssim") => format!("ssim ({:.3}; {} needed)", self.value, self.target),
            (None, _) => self.name.clone(),
        }
    }
}

/// The targets for `bits` (unseen views): (row or figure, minimum).
pub fn targets(bits: usize) -> Vec<(&'static str, f64)> {
    match bits {
        32 => vec![
            ("clean", 0.985),
            ("psnr", 36.0),
            ("ssim", 0.98),
            ("noise", 0.912),
            ("rotation", 0.962),
            ("scaling", 0.951),
            ("blur", 0.978),
            ("crop_on_asset", 0.959),
            ("jpeg", 0.930),
            ("combined_on_asset", 0.913),
            ("remove_20", 0.982),
            ("clone_20", 0.975),
            ("noise_0.1_scaled", 0.905),
        ],
        48 => vec![("clean", 0.943), ("psnr", 33.5)],
        _ => vec![("clean", 0.917), ("psnr", 32.7)],
    }
}

/// Checks `eval` against [`targets`], plus "the unmarked scene is not detected" and "the
/// clean views are detected on averaged logits".
pub fn check(eval: &SceneEval, bits: usize) -> Vec<TargetCheck> {
    let mut out = Vec::new();
    for (name, target) in targets(bits) {
        let (value, count) = match name {
            "psnr" => (eval.psnr, None),
            "ssim" => (eval.ssim, None),
            _ => eval
                .rows
                .iter()
                .find(|r| r.name == name)
                .map_or((f64::NAN, None), |r| {
                    // A model attack's row is the mean over its draws: each draw's views count.
                    let views = eval.views * r.draws.len().max(1);
                    let count = BitCount::of(r.bit_accuracy, views, bits, target);
                    (r.bit_accuracy, Some(count))
                }),
        };
        out.push(TargetCheck {
            name: name.into(),
            value,
            target,
            met: value >= target,
            bits: count,
        });
    }
    if let Some(r) = eval.rows.iter().find(|r| r.name == "clean") {
        out.push(TargetCheck {
            name: "clean_detected".into(),
            value: f64::from(u8::from(r.detected)),
            target: 1.0,
            met: r.detected,
            bits: None,
        });
    }
    if let Some(r) = eval.rows.iter().find(|r| r.name == "unmarked") {
        out.push(TargetCheck {
            name: "unmarked_detected".into(),
            value: f64::from(u8::from(r.detected)),
            target: 0.0,
            met: !r.detected,
            bits: None,
        });
    }
    out
}
