//! A dispute: rendered images are decoded once per message length and tested against every
//! candidate's embedded bits, with p-values corrected for the number of candidates tested.

use std::collections::BTreeMap;

use serde::Serialize;
use uuid::Uuid;

use super::message::to_hex;
use super::stats::{Detection, StatsError, detect};

/// A registered watermark the images are tested against.
#[derive(Clone, Debug)]
pub struct Candidate {
    pub asset_id: Uuid,
    /// The embedded bits (for the service, the key's payload `message ⊕ mask`).
    pub payload: Vec<bool>,
}

/// One candidate's outcome.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CandidateResult {
    pub asset_id: Uuid,
    #[serde(flatten)]
    pub detection: Detection,
}

/// The verdict over all candidates.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Verdict {
    /// Number of candidate messages tested (`K` of the correction).
    pub candidates_tested: u64,
    /// Whether any candidate is detected at the family-wise false-positive rate `fpr`.
    pub detected: bool,
    /// The candidate with the smallest p-value, if any.
    pub best: Option<CandidateResult>,
    /// Candidates sorted by p-value (smallest first), at most `limit` of them.
    pub results: Vec<CandidateResult>,
    pub fpr: f64,
}

/// Tests decoded bits (`decoded[bits]`, one bit string per message length) against every
/// candidate. A candidate whose length was not decoded is an error (the caller decodes every
/// length it tests).
pub fn judge(
    decoded: &BTreeMap<usize, Vec<bool>>,
    candidates: &[Candidate],
    fpr: f64,
    limit: usize,
) -> Result<Verdict, StatsError> {
    let k = candidates.len() as u64;
    let mut results = candidates
        .iter()
        .map(|c| {
            let d = decoded
                .get(&c.payload.len())
                .ok_or(StatsError::LengthMismatch {
                    decoded: 0,
                    message: c.payload.len(),
                })?;
            Ok(CandidateResult {
                asset_id: c.asset_id,
                detection: detect(d, &c.payload, k, fpr)?,
            })
        })
        .collect::<Result<Vec<_>, StatsError>>()?;
    results.sort_by(|a, b| {
        a.detection
            .p_value
            .total_cmp(&b.detection.p_value)
            .then(b.detection.bits.cmp(&a.detection.bits))
    });
    let detected = results.iter().any(|r| r.detection.detected);
    let best = results.first().cloned();
    results.truncate(limit);
    Ok(Verdict {
        candidates_tested: k,
        detected,
        best,
        results,
        fpr,
    })
}

/// Hex of decoded bits per length, for the response.
pub fn decoded_hex(decoded: &BTreeMap<usize, Vec<bool>>) -> BTreeMap<usize, String> {
    decoded.iter().map(|(&n, b)| (n, to_hex(b))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bits(seed: u64, n: usize) -> Vec<bool> {
        (0..n)
            .map(|i| (seed >> (i % 64)) & 1 == 1 || i % 7 == 3)
            .collect()
    }

    #[test]
    fn the_true_message_wins_and_the_correction_uses_every_candidate() {
        let m = bits(0xdead_beef_1234_5678, 32);
        let mut d = m.clone();
        d[0] = !d[0]; // 31 of 32
        let decoded = BTreeMap::from([(32, d)]);
        let mut cands: Vec<Candidate> = (0..9)
            .map(|i| Candidate {
                asset_id: Uuid::from_u128(i),
                payload: m.iter().map(|&b| !b).collect(), // 1 of 32
            })
            .collect();
        cands.push(Candidate {
            asset_id: Uuid::from_u128(99),
            payload: m,
        });
        let v = judge(&decoded, &cands, 1e-6, 3).unwrap();
        assert_eq!(v.candidates_tested, 10);
        assert!(v.detected);
        let best = v.best.unwrap();
        assert_eq!(best.asset_id, Uuid::from_u128(99));
        assert_eq!(best.detection.matches, 31);
        // 33 / 2^32 for one test, times 10 candidates.
        let p = 33.0 / 2f64.powi(32);
        assert!((best.detection.p_value - p).abs() < 1e-18);
        assert!((best.detection.p_value_corrected - 10.0 * p).abs() < 1e-17);
        assert_eq!(v.results.len(), 3);
    }

    #[test]
    fn no_candidates_is_not_detected_and_missing_lengths_are_errors() {
        let decoded = BTreeMap::from([(32, vec![true; 32])]);
        let v = judge(&decoded, &[], 1e-6, 10).unwrap();
        assert!(!v.detected && v.best.is_none() && v.candidates_tested == 0);
        let c = Candidate {
            asset_id: Uuid::nil(),
            payload: vec![true; 48],
        };
        assert!(judge(&decoded, &[c], 1e-6, 10).is_err());
    }
}
