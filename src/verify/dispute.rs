//! A dispute: rendered images are decoded once per message length (logits averaged over the
//! images) and tested against every candidate's embedded bits — each candidate's bits read
//! relative to its asset reference, when it has one — with p-values corrected for the number of
//! candidates tested.

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
    /// The asset reference (one logit per bit) subtracted before the bits are read, when the
    /// embedding decoded relative to the asset.
    pub reference: Option<Vec<f32>>,
}

/// One candidate's outcome.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CandidateResult {
    pub asset_id: Uuid,
    /// Whether the bits were read relative to the candidate's asset reference.
    pub reference: bool,
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

/// The bits of mean `logits`, relative to `reference` when given (`logit − reference > 0`).
///
/// # Errors
/// [`StatsError::LengthMismatch`] when the reference has another length.
pub fn bits_relative(logits: &[f32], reference: Option<&[f32]>) -> Result<Vec<bool>, StatsError> {
    match reference {
        None => Ok(logits.iter().map(|&z| z > 0.0).collect()),
        Some(r) if r.len() == logits.len() => {
            Ok(logits.iter().zip(r).map(|(&z, &c)| z - c > 0.0).collect())
        }
        Some(r) => Err(StatsError::LengthMismatch {
            decoded: logits.len(),
            message: r.len(),
        }),
    }
}

/// Tests decoded mean logits (`decoded[bits]`, one vector per message length) against every
/// candidate, each read relative to the candidate's reference. A candidate whose length was not
/// decoded is an error (the caller decodes every length it tests).
///
/// For an image that does not carry a candidate's watermark the test stays exact: the
/// reference is fixed before the image is seen and is independent of the candidate's secret
/// mask, so each read bit matches the payload with probability ½ (`store::keys`).
pub fn judge(
    decoded: &BTreeMap<usize, Vec<f32>>,
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
            let bits = bits_relative(d, c.reference.as_deref())?;
            Ok(CandidateResult {
                asset_id: c.asset_id,
                reference: c.reference.is_some(),
                detection: detect(&bits, &c.payload, k, fpr)?,
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

/// Hex of the decoded bits per length (without any reference), for the response.
pub fn decoded_hex(decoded: &BTreeMap<usize, Vec<f32>>) -> BTreeMap<usize, String> {
    decoded
        .iter()
        .map(|(&n, z)| {
            let bits: Vec<bool> = z.iter().map(|&z| z > 0.0).collect();
            (n, to_hex(&bits))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bits(seed: u64, n: usize) -> Vec<bool> {
        (0..n)
            .map(|i| (seed >> (i % 64)) & 1 == 1 || i % 7 == 3)
            .collect()
    }

    fn logits(b: &[bool]) -> Vec<f32> {
        b.iter().map(|&b| if b { 1.5 } else { -1.5 }).collect()
    }

    #[test]
    fn the_true_message_wins_and_the_correction_uses_every_candidate() {
        let m = bits(0xdead_beef_1234_5678, 32);
        let mut d = m.clone();
        d[0] = !d[0]; // 31 of 32
        let decoded = BTreeMap::from([(32, logits(&d))]);
        let mut cands: Vec<Candidate> = (0..9)
            .map(|i| Candidate {
                asset_id: Uuid::from_u128(i),
                payload: m.iter().map(|&b| !b).collect(), // 1 of 32
                reference: None,
            })
            .collect();
        cands.push(Candidate {
            asset_id: Uuid::from_u128(99),
            payload: m,
            reference: None,
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
    fn each_candidate_is_read_relative_to_its_own_reference() {
        // The decoder leans towards 1 on this asset (every logit +2 on the original); the
        // watermark moved each logit by ±1 around that lean, so the plain bits are all 1s.
        let m = bits(0x0123_4567_89ab_cdef, 32);
        let lean = vec![2.0f32; 32];
        let z: Vec<f32> = m.iter().map(|&b| if b { 3.0 } else { 1.0 }).collect();
        let decoded = BTreeMap::from([(32, z)]);
        let with = Candidate {
            asset_id: Uuid::from_u128(1),
            payload: m.clone(),
            reference: Some(lean),
        };
        let without = Candidate {
            reference: None,
            asset_id: Uuid::from_u128(2),
            ..with.clone()
        };
        let v = judge(&decoded, &[with, without], 1e-6, 10).unwrap();
        let best = v.best.unwrap();
        assert_eq!((best.asset_id, best.reference), (Uuid::from_u128(1), true));
        assert_eq!(best.detection.matches, 32);
        let plain = &v.results[1];
        assert!(!plain.reference);
        assert_eq!(
            plain.detection.matches as usize,
            m.iter().filter(|&&b| b).count()
        );
        // The response's decoded bits are the plain ones.
        assert_eq!(decoded_hex(&decoded)[&32], "ffffffff");
        // A reference of another length is an error, not a silent misread.
        assert!(bits_relative(&[1.0, 2.0], Some(&[0.0])).is_err());
    }

    #[test]
    fn no_candidates_is_not_detected_and_missing_lengths_are_errors() {
        let decoded = BTreeMap::from([(32, vec![1.0; 32])]);
        let v = judge(&decoded, &[], 1e-6, 10).unwrap();
        assert!(!v.detected && v.best.is_none() && v.candidates_tested == 0);
        let c = Candidate {
            asset_id: Uuid::nil(),
            payload: vec![true; 48],
            reference: None,
        };
        assert!(judge(&decoded, &[c], 1e-6, 10).is_err());
    }
}
