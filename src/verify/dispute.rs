//! A dispute: rendered images are decoded once per decoder (logits and the decoder's pooled
//! features averaged over the images) and tested against every candidate's embedded bits — each
//! candidate's bits read with the decoder they were written for (`decoder::registry`), through
//! its asset's matched head and relative to its asset reference, when it has them — with p-values
//! corrected for the number of candidates tested.

use std::collections::BTreeMap;

use serde::Serialize;
use uuid::Uuid;

use super::message::to_hex;
use super::stats::{Detection, StatsError, detect};
use crate::decoder::projection::ViewProjection;

/// What the images decode to with one decoder, averaged over the images.
#[derive(Clone, Debug, PartialEq)]
pub struct Decoded {
    /// The decoder's own logits (its head and whitening).
    pub logits: Vec<f32>,
    /// The decoder's pooled features (what a matched head reads).
    pub features: Vec<f32>,
}

impl Decoded {
    /// Hex of the decoder's own bits (without any head or reference), for the response.
    pub fn plain_hex(&self) -> String {
        let bits: Vec<bool> = self.logits.iter().map(|&z| z > 0.0).collect();
        to_hex(&bits)
    }
}

/// A registered watermark the images are tested against.
#[derive(Clone, Debug)]
pub struct Candidate {
    pub asset_id: Uuid,
    /// The embedded bits (for the service, the key's payload `message ⊕ mask`).
    pub payload: Vec<bool>,
    /// The asset reference (one logit per bit) subtracted before the bits are read, when the
    /// embedding decoded relative to the asset.
    pub reference: Option<Vec<f32>>,
    /// The asset's matched head ([`ViewProjection::matched_logits_of`]), when the embedding
    /// read the bits through one: the candidate's logits are the head's of the decoded
    /// features instead of the shipped decoder's.
    pub head: Option<ViewProjection>,
    /// The digest of the decoder its bits are read with (the key in [`judge`]'s decodings).
    pub decoder: String,
}

/// One candidate's outcome.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CandidateResult {
    pub asset_id: Uuid,
    /// Whether the bits were read relative to the candidate's asset reference.
    pub reference: bool,
    /// Whether the bits were read through the candidate's matched head.
    pub matched_head: bool,
    /// The digest of the decoder that read them.
    pub decoder: String,
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

/// The logits `candidate` reads from `d`: its matched head's, or the shipped decoder's.
fn candidate_logits<'a>(
    d: &'a Decoded,
    candidate: &Candidate,
) -> Result<std::borrow::Cow<'a, [f32]>, StatsError> {
    match &candidate.head {
        None => Ok(std::borrow::Cow::Borrowed(&d.logits)),
        Some(h) => h
            .matched_logits_of(&d.features)
            .filter(|z| z.len() == candidate.payload.len())
            .map(std::borrow::Cow::Owned)
            .ok_or(StatsError::LengthMismatch {
                decoded: d.features.len(),
                message: h.features(),
            }),
    }
}

/// Tests what the images decoded to (`decoded[digest]`, one per decoder) against every
/// candidate, each read with its decoder, through its matched head and relative to its
/// reference when it has them. A candidate whose decoder was not decoded with, or does not read
/// its length, is an error (the caller decodes with every decoder it tests).
///
/// For an image that does not carry a candidate's watermark the test stays exact: the head and
/// the reference are fixed before the image is seen and are independent of the candidate's
/// secret mask (both come from the unmarked original), so each read bit matches the payload
/// with probability ½ (`store::keys`).
pub fn judge(
    decoded: &BTreeMap<String, Decoded>,
    candidates: &[Candidate],
    fpr: f64,
    limit: usize,
) -> Result<Verdict, StatsError> {
    let k = candidates.len() as u64;
    let mut results = candidates
        .iter()
        .map(|c| {
            let d = decoded.get(&c.decoder).ok_or(StatsError::LengthMismatch {
                decoded: 0,
                message: c.payload.len(),
            })?;
            if d.logits.len() != c.payload.len() {
                return Err(StatsError::LengthMismatch {
                    decoded: d.logits.len(),
                    message: c.payload.len(),
                });
            }
            let z = candidate_logits(d, c)?;
            let bits = bits_relative(&z, c.reference.as_deref())?;
            Ok(CandidateResult {
                asset_id: c.asset_id,
                reference: c.reference.is_some(),
                matched_head: c.head.is_some(),
                decoder: c.decoder.clone(),
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A stand-in digest for a decoder of `bits` bits.
    fn dec(bits: usize) -> String {
        format!("decoder-{bits}")
    }

    fn bits(seed: u64, n: usize) -> Vec<bool> {
        (0..n)
            .map(|i| (seed >> (i % 64)) & 1 == 1 || i % 7 == 3)
            .collect()
    }

    fn logits(b: &[bool]) -> Vec<f32> {
        b.iter().map(|&b| if b { 1.5 } else { -1.5 }).collect()
    }

    fn plain(logits: Vec<f32>) -> Decoded {
        Decoded {
            logits,
            features: Vec::new(),
        }
    }

    #[test]
    fn the_true_message_wins_and_the_correction_uses_every_candidate() {
        let m = bits(0xdead_beef_1234_5678, 32);
        let mut d = m.clone();
        d[0] = !d[0]; // 31 of 32
        let decoded = BTreeMap::from([(dec(32), plain(logits(&d)))]);
        let mut cands: Vec<Candidate> = (0..9)
            .map(|i| Candidate {
                asset_id: Uuid::from_u128(i),
                payload: m.iter().map(|&b| !b).collect(), // 1 of 32
                reference: None,
                head: None,
                decoder: dec(32),
            })
            .collect();
        cands.push(Candidate {
            asset_id: Uuid::from_u128(99),
            payload: m,
            reference: None,
            head: None,
            decoder: dec(32),
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
        let decoded = BTreeMap::from([(dec(32), plain(z))]);
        let with = Candidate {
            asset_id: Uuid::from_u128(1),
            payload: m.clone(),
            reference: Some(lean),
            head: None,
            decoder: dec(32),
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
        assert_eq!(decoded[&dec(32)].plain_hex(), "ffffffff");
        // A reference of another length is an error, not a silent misread.
        assert!(bits_relative(&[1.0, 2.0], Some(&[0.0])).is_err());
    }

    #[test]
    fn a_candidate_with_a_matched_head_reads_the_features_through_it() {
        // Two features, two bits: the head reads bit 0 as f1 − f0 and bit 1 as f0 + f1 about
        // μ = (0.5, 0.5); the shipped logits say the opposite of the head's bits.
        let head = ViewProjection {
            mean: vec![0.5, 0.5],
            basis: Vec::new(),
            explained: 0.0,
            head: Some(vec![-1.0, 1.0, 1.0, 1.0]),
        };
        let d = Decoded {
            logits: vec![1.0, 1.0],
            features: vec![0.25, 0.75], // f − μ = (−0.25, 0.25): head logits (0.5, 0)
        };
        let z = head.matched_logits_of(&d.features).unwrap();
        assert_eq!(z, vec![0.5, 0.0]);
        let decoded = BTreeMap::from([(dec(2), d)]);
        let cand = Candidate {
            asset_id: Uuid::from_u128(7),
            payload: vec![true, false],
            reference: Some(vec![0.0, 0.25]),
            head: Some(head.clone()),
            decoder: dec(2),
        };
        let v = judge(&decoded, std::slice::from_ref(&cand), 1e-6, 10).unwrap();
        let r = &v.results[0];
        assert!(r.matched_head && r.reference);
        // Through the head and the reference: (0.5 − 0, 0 − 0.25) → bits (1, 0), both match;
        // the shipped logits would have read (1, 1).
        assert_eq!(r.detection.matches, 2);
        // A head for other features is an error, not a silent misread.
        let wrong = Candidate {
            head: Some(ViewProjection {
                mean: vec![0.0; 3],
                head: Some(vec![1.0; 6]),
                ..head
            }),
            ..cand
        };
        assert!(judge(&decoded, &[wrong], 1e-6, 10).is_err());
    }

    #[test]
    fn no_candidates_is_not_detected_and_missing_lengths_are_errors() {
        let decoded = BTreeMap::from([(dec(32), plain(vec![1.0; 32]))]);
        let v = judge(&decoded, &[], 1e-6, 10).unwrap();
        assert!(!v.detected && v.best.is_none() && v.candidates_tested == 0);
        // A decoder not decoded with, or one that reads another length.
        let c = Candidate {
            asset_id: Uuid::nil(),
            payload: vec![true; 48],
            reference: None,
            head: None,
            decoder: dec(48),
        };
        assert!(judge(&decoded, std::slice::from_ref(&c), 1e-6, 10).is_err());
        let c = Candidate {
            decoder: dec(32),
            ..c
        };
        assert!(judge(&decoded, &[c], 1e-6, 10).is_err());
    }

    #[test]
    fn each_candidate_is_read_with_its_own_decoder() {
        // Two decoders of the same length read the same images differently: each candidate is
        // tested on its own decoder's bits, and the response says which.
        let m = bits(0x5555_0000_ffff_1234, 32);
        let other: Vec<bool> = m.iter().map(|&b| !b).collect();
        let decoded = BTreeMap::from([
            ("old".to_string(), plain(logits(&m))),
            ("new".to_string(), plain(logits(&other))),
        ]);
        let cand = |id: u128, decoder: &str| Candidate {
            asset_id: Uuid::from_u128(id),
            payload: m.clone(),
            reference: None,
            head: None,
            decoder: decoder.into(),
        };
        let v = judge(&decoded, &[cand(1, "new"), cand(2, "old")], 1e-6, 10).unwrap();
        let best = v.best.unwrap();
        assert_eq!(
            (best.asset_id, best.decoder.as_str()),
            (Uuid::from_u128(2), "old")
        );
        assert_eq!(best.detection.matches, 32);
        assert_eq!(v.results[1].detection.matches, 0);
    }
}
