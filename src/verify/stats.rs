//! Detection statistics: exact binomial tails, detection thresholds and multiple-testing
//! correction for decoded watermark bits.
//!
//! The null hypothesis is "this image carries no (or another) watermark": each of the `n`
//! decoded bits then matches the registered message with probability 1/2, independently, so the
//! number of matching bits is `X ~ Binomial(n, 1/2)`. That holds exactly when the tested bits
//! are uniformly random and independent of the image — which the service guarantees by testing
//! the payload `message ⊕ secret random mask` (`store::keys`) — but not for a fixed, chosen bit
//! string: a decoder's bits are biased on natural images (`docs/DECODER.md`), so for a message
//! that follows the bias these p-values are optimistic. Everything here is computed exactly (no
//! normal approximation):
//!
//! * [`binomial_tail`] — the one-sided p-value `P[X ≥ k]`, and [`log10_binomial_tail`], its
//!   base-10 logarithm, which never underflows;
//! * [`threshold_for_fpr`] — the smallest match count whose p-value is at most a target
//!   false-positive rate;
//! * [`corrected_p_value`] and [`threshold_for_fpr_among`] — the same when an image is searched
//!   against `K` registered messages (Bonferroni / union-bound correction of the family-wise
//!   error rate, valid however the `K` tests depend on each other);
//! * [`detect`] — all of the above for one decoded message, as a serialisable [`Detection`].
//!
//! # Numerics
//!
//! Tails are evaluated in double-double arithmetic (about 106 bits of mantissa) with a separate
//! binary exponent, so neither overflow (`C(4096, 2048) ≈ 10^1231`) nor underflow
//! (`2^-4096`) can occur internally. For `2k > n` the tail is `C(n, k)/2^n · Σ_j C(n, j)/C(n, k)`:
//! `C(n, k)` is the product of `min(k, n − k)` exact ratios and the sum has positive,
//! decreasing terms built by the ratio recurrence `(n − j)/(j + 1) < 1`, truncated once the
//! remainder (bounded by a geometric series) is below `2^-110` of the sum. For `2k ≤ n` the
//! symmetry `P[X ≥ k] = 1 − P[X ≥ n − k + 1]` is used; that value is at least 1/2, so the
//! subtraction loses nothing. The relative error before the final rounding to `f64` is of order
//! `n · 2^-104`, i.e. results are correctly rounded (or within one ulp) for every practical `n`.
//! Cost is `O(min(k, n − k))` plus the (truncated) sum, at most `O(n)`.

use serde::Serialize;

/// Largest message length (in bits) accepted by the threshold functions and [`detect`].
///
/// The statistics themselves work for any `u32`, but a threshold search costs
/// `O(n log n)` and real watermark messages are a few hundred bits at most; the cap also keeps
/// the "never detectable" threshold `n + 1` representable.
pub const MAX_BITS: u32 = 1 << 20;

/// Invalid input to the detection statistics.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum StatsError {
    /// The target false-positive rate is not strictly between 0 and 1 (or is NaN).
    #[error("false-positive rate must lie strictly between 0 and 1, got {0}")]
    InvalidFpr(f64),
    /// The message has no bits (`n = 0`).
    #[error("the message must have at least one bit")]
    EmptyMessage,
    /// The message is longer than [`MAX_BITS`].
    #[error("message of {0} bits is longer than the supported maximum of {MAX_BITS} bits")]
    TooManyBits(usize),
    /// Decoded bits and registered message differ in length.
    #[error("decoded bits ({decoded}) and message ({message}) differ in length")]
    LengthMismatch {
        /// Number of decoded bits.
        decoded: usize,
        /// Number of message bits.
        message: usize,
    },
    /// Zero candidate messages were given for multiple-testing correction.
    #[error("the number of candidate messages must be at least 1")]
    NoCandidates,
}

/// Outcome of testing one decoded bit string against one registered message.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Detection {
    /// Number of decoded bits equal to the message bits.
    pub matches: u32,
    /// Message length `n`.
    pub bits: u32,
    /// `matches / bits`.
    pub bit_accuracy: f64,
    /// One-sided p-value `P[X ≥ matches]`, `X ~ Binomial(bits, 1/2)` (may underflow to 0 for
    /// very long messages; see [`log10_binomial_tail`]).
    pub p_value: f64,
    /// `p_value` corrected for `candidates` messages tested ([`corrected_p_value`]).
    pub p_value_corrected: f64,
    /// Number of registered messages the image was tested against (`K`).
    pub candidates: u64,
    /// Per-candidate match threshold ([`threshold_for_fpr_among`]); `bits + 1` when no match
    /// count can reach the requested rate.
    pub threshold: u32,
    /// `matches >= threshold`.
    pub detected: bool,
    /// Requested family-wise false-positive rate.
    pub fpr: f64,
}

/// One-sided p-value `P[X ≥ k]` for `X ~ Binomial(n, 1/2)`: the probability that `k` or more of
/// `n` decoded bits match a message by chance.
///
/// `k = 0` gives 1, `k > n` gives 0 (so `n = 0` gives 1 for `k = 0` and 0 otherwise). The result
/// is accurate to about one ulp; it is 0 only where the true value is below the smallest
/// subnormal `f64` (e.g. `k = n ≥ 1075`), and loses relative precision in the subnormal range
/// (below about `2.2e-308`). Use [`log10_binomial_tail`] there.
pub fn binomial_tail(k: u32, n: u32) -> f64 {
    tail_scaled(k, n).to_f64()
}

/// `log10 P[X ≥ k]` for `X ~ Binomial(n, 1/2)`; never underflows.
///
/// `k = 0` gives `0.0`, `k > n` gives `-inf`. For example `log10_binomial_tail(n, n)` is
/// `-n · log10 2` for any `n`. The absolute error is of order `1e-15 · |result|`.
pub fn log10_binomial_tail(k: u32, n: u32) -> f64 {
    if k == 0 {
        return 0.0;
    }
    tail_scaled(k, n).log10()
}

/// Smallest `k` such that `P[X ≥ k] ≤ fpr` for `X ~ Binomial(n, 1/2)`.
///
/// A detector that reports "detected" when `matches >= k` then has false-positive rate at most
/// `fpr` on unmarked images. Returns `n + 1` when even a perfect match is not significant enough
/// (`2^-n > fpr`), i.e. such a detector never fires.
///
/// The comparison uses the exact (double-double) tail, so `binomial_tail(k, n) <= fpr` always
/// holds for the returned `k`; `binomial_tail(k - 1, n)` exceeds `fpr` except when the true tail
/// lies within rounding of `fpr` (then `k` is the conservative choice).
///
/// Examples at `fpr = 1e-6`: `n = 32 → 30`, `n = 48 → 41`, `n = 64 → 51`.
///
/// # Errors
/// [`StatsError::InvalidFpr`] unless `0 < fpr < 1`; [`StatsError::EmptyMessage`] for `n = 0`;
/// [`StatsError::TooManyBits`] for `n > MAX_BITS`.
pub fn threshold_for_fpr(n: u32, fpr: f64) -> Result<u32, StatsError> {
    validate_bits(n)?;
    validate_fpr(fpr)?;
    Ok(threshold_for_level(n, Scaled::from_f64(fpr)))
}

/// Per-candidate threshold when an image is tested against `k_candidates` registered messages
/// (search mode) and the family-wise false-positive rate must be at most `fpr`.
///
/// Uses the Bonferroni per-test level `α = fpr / K` (computed without underflow) and returns
/// `threshold_for_fpr(n, α)`; `K = 1` gives exactly [`threshold_for_fpr`].
///
/// Tests of one decoded string against several messages are dependent (a message and its
/// complement can never both match well), so a correction that assumes independence (Šidák)
/// carries no guarantee; the union bound does: P[any of the K null tests fires] ≤ K·α = fpr.
///
/// # Errors
/// As [`threshold_for_fpr`], plus [`StatsError::NoCandidates`] for `k_candidates = 0`.
pub fn threshold_for_fpr_among(n: u32, fpr: f64, k_candidates: u64) -> Result<u32, StatsError> {
    validate_bits(n)?;
    validate_fpr(fpr)?;
    if k_candidates == 0 {
        return Err(StatsError::NoCandidates);
    }
    Ok(threshold_for_level(n, bonferroni_level(fpr, k_candidates)))
}

/// Family-wise p-value when the best of `k_candidates` messages is reported: `min(1, K·p)`, the
/// union bound on the probability that at least one of the `K` null tests has a p-value at most
/// `p` (Bonferroni; valid however the tests depend on each other).
///
/// `p` is clamped to `[0, 1]` first and NaN stays NaN. `K = 1` returns `p` exactly; `K = 0`
/// (no test) is treated as `K = 1`. Monotone non-decreasing in both `p` and `K`.
pub fn corrected_p_value(p: f64, k_candidates: u64) -> f64 {
    if p.is_nan() {
        return p;
    }
    let p = p.clamp(0.0, 1.0);
    if k_candidates <= 1 {
        return p;
    }
    // `K as f64` rounds for K > 2^53 (relative 1e-16), which is harmless here.
    (k_candidates as f64 * p).min(1.0)
}

/// Tests `decoded` bits against a registered `message` when the image is searched against
/// `candidates` messages, with family-wise false-positive rate `fpr`.
///
/// `detected` is `matches >= threshold` with `threshold =
/// threshold_for_fpr_among(bits, fpr, candidates)`; equivalently (up to rounding) the corrected
/// p-value is at most `fpr`.
///
/// # Errors
/// [`StatsError::LengthMismatch`] if the lengths differ, [`StatsError::EmptyMessage`] if they
/// are zero, [`StatsError::TooManyBits`] above [`MAX_BITS`], [`StatsError::InvalidFpr`] unless
/// `0 < fpr < 1`, [`StatsError::NoCandidates`] if `candidates == 0`.
pub fn detect(
    decoded: &[bool],
    message: &[bool],
    candidates: u64,
    fpr: f64,
) -> Result<Detection, StatsError> {
    if decoded.len() != message.len() {
        return Err(StatsError::LengthMismatch {
            decoded: decoded.len(),
            message: message.len(),
        });
    }
    let bits = bits_of_len(message.len())?;
    let matches = count_u32(decoded.iter().zip(message).filter(|(d, m)| d == m).count());
    let threshold = threshold_for_fpr_among(bits, fpr, candidates)?;
    let p_value = binomial_tail(matches, bits);
    Ok(Detection {
        matches,
        bits,
        bit_accuracy: f64::from(matches) / f64::from(bits),
        p_value,
        p_value_corrected: corrected_p_value(p_value, candidates),
        candidates,
        threshold,
        detected: matches >= threshold,
        fpr,
    })
}

/// Number of positions where the hard decision `logit > 0` equals the message bit.
///
/// A NaN or non-positive logit decodes as `false`. If the lengths differ, only the common prefix
/// is compared (check lengths beforehand, or use [`detect`] on decoded bits, which does).
pub fn matches_from_logits(logits: &[f32], message: &[bool]) -> u32 {
    count_u32(
        logits
            .iter()
            .zip(message)
            .filter(|&(&logit, &bit)| (logit > 0.0) == bit)
            .count(),
    )
}

// ---------------------------------------------------------------------------------------------
// Validation helpers.

fn validate_fpr(fpr: f64) -> Result<(), StatsError> {
    if fpr > 0.0 && fpr < 1.0 {
        Ok(())
    } else {
        Err(StatsError::InvalidFpr(fpr))
    }
}

fn validate_bits(n: u32) -> Result<(), StatsError> {
    match n {
        0 => Err(StatsError::EmptyMessage),
        n if n > MAX_BITS => Err(StatsError::TooManyBits(n as usize)),
        _ => Ok(()),
    }
}

fn bits_of_len(len: usize) -> Result<u32, StatsError> {
    if len == 0 {
        return Err(StatsError::EmptyMessage);
    }
    match u32::try_from(len) {
        Ok(n) if n <= MAX_BITS => Ok(n),
        _ => Err(StatsError::TooManyBits(len)),
    }
}

fn count_u32(count: usize) -> u32 {
    u32::try_from(count).unwrap_or(u32::MAX)
}

// ---------------------------------------------------------------------------------------------
// Thresholds.

/// Smallest `k` in `0..=n + 1` with `P[X ≥ k] ≤ level`, for `0 < level < 1` and `n ≤ MAX_BITS`.
fn threshold_for_level(n: u32, level: Scaled) -> u32 {
    // Invariant: tail(lo) > level (tail(0) = 1 > level), tail(hi) <= level (tail(n + 1) = 0).
    let (mut lo, mut hi) = (0u32, n + 1);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if tail_scaled(mid, n).le(level) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi
}

/// Bonferroni per-test level `fpr / K` for `0 < fpr < 1`, `K ≥ 1`, without underflow: fpr is
/// scaled up (exactly) before dividing, since `fpr / K` may be below the f64 range.
fn bonferroni_level(fpr: f64, k_candidates: u64) -> Scaled {
    if k_candidates == 1 {
        return Scaled::from_f64(fpr);
    }
    Scaled::new(Dd::from_f64(ldexp(fpr, 600) / k_candidates as f64), -600)
}

// ---------------------------------------------------------------------------------------------
// Exact binomial tails.

/// Relative truncation tolerance of the ratio sum (well below double-double precision).
const TRUNCATION: f64 = 7.703_719_777_548_943e-34; // 2^-110

/// `P[X ≥ k]`, `X ~ Binomial(n, 1/2)`, as a double-double with a binary exponent.
fn tail_scaled(k: u32, n: u32) -> Scaled {
    if k == 0 {
        Scaled::one()
    } else if k > n {
        Scaled::ZERO
    } else if 2 * u64::from(k) > u64::from(n) {
        upper_tail(k, n)
    } else {
        // 1 <= k <= n/2, so k' = n - k + 1 satisfies 2k' > n and the complement is <= 1/2.
        let upper = upper_tail(n - k + 1, n);
        Scaled::new(Dd::ONE.sub_dd(upper.m.scale_pow2(upper.e)), 0)
    }
}

/// `P[X ≥ k]` for `n/2 < k ≤ n`.
fn upper_tail(k: u32, n: u32) -> Scaled {
    let (n, k) = (u64::from(n), u64::from(k));
    debug_assert!(2 * k > n && k <= n);
    // C(n, k) = C(n, m) = Π_{j=1..m} (n − m + j) / j with m = n − k < k; every factor is an
    // exactly representable integer, each step rounds at the double-double level only.
    let m = n - k;
    let mut c = Scaled::one();
    for j in 1..=m {
        c = Scaled::new(c.m.mul_f64((n - m + j) as f64).div_f64(j as f64), c.e);
    }
    // Σ_{j=k..n} C(n, j) / C(n, k): term_j = term_{j−1} · (n − j + 1) / j, all ratios < 1 and
    // decreasing, so after term_j the remainder is at most term_j · r / (1 − r) with
    // r = (n − j) / (j + 1), i.e. term_j · (n − j) / (2j + 1 − n).
    let mut sum = Dd::ONE;
    let mut term = Dd::ONE;
    for j in (k + 1)..=n {
        term = term.mul_f64((n - j + 1) as f64).div_f64(j as f64);
        sum = sum.add_dd(term);
        let remainder_bound = term.hi * (n - j) as f64 / (2 * j + 1 - n) as f64;
        if remainder_bound < sum.hi * TRUNCATION {
            break;
        }
    }
    Scaled::new(c.m.mul_dd(sum), c.e - n as i64)
}

// ---------------------------------------------------------------------------------------------
// Double-double arithmetic with an external binary exponent.

/// Unevaluated sum `hi + lo` with `|lo| ≤ ulp(hi) / 2` (about 106 significant bits).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Dd {
    hi: f64,
    lo: f64,
}

/// `s + e = a + b` exactly.
fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    (s, (a - (s - bb)) + (b - bb))
}

/// `s + e = a + b` exactly, assuming `|a| ≥ |b|` (or `a = 0`).
fn quick_two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    (s, b - (s - a))
}

/// `p + e = a · b` exactly (barring underflow), via fused multiply-add.
fn two_prod(a: f64, b: f64) -> (f64, f64) {
    let p = a * b;
    (p, a.mul_add(b, -p))
}

impl Dd {
    const ZERO: Dd = Dd { hi: 0.0, lo: 0.0 };
    const ONE: Dd = Dd { hi: 1.0, lo: 0.0 };

    fn from_f64(x: f64) -> Dd {
        Dd { hi: x, lo: 0.0 }
    }

    fn from_pair((hi, lo): (f64, f64)) -> Dd {
        Dd { hi, lo }
    }

    fn add_dd(self, o: Dd) -> Dd {
        let (s, e) = two_sum(self.hi, o.hi);
        let (t, f) = two_sum(self.lo, o.lo);
        let (s, e) = quick_two_sum(s, e + t);
        Dd::from_pair(quick_two_sum(s, e + f))
    }

    fn sub_dd(self, o: Dd) -> Dd {
        self.add_dd(Dd {
            hi: -o.hi,
            lo: -o.lo,
        })
    }

    fn mul_dd(self, o: Dd) -> Dd {
        let (p, e) = two_prod(self.hi, o.hi);
        Dd::from_pair(quick_two_sum(p, e + (self.hi * o.lo + self.lo * o.hi)))
    }

    fn mul_f64(self, b: f64) -> Dd {
        let (p, e) = two_prod(self.hi, b);
        Dd::from_pair(quick_two_sum(p, e + self.lo * b))
    }

    fn div_f64(self, b: f64) -> Dd {
        let q1 = self.hi / b;
        let (p1, p2) = two_prod(q1, b);
        let (s, e) = two_sum(self.hi, -p1);
        let q2 = (s + (e - p2 + self.lo)) / b;
        Dd::from_pair(quick_two_sum(q1, q2))
    }

    /// `self · 2^e` (exact unless a component leaves the normal range).
    fn scale_pow2(self, e: i64) -> Dd {
        Dd {
            hi: ldexp(self.hi, e),
            lo: ldexp(self.lo, e),
        }
    }
}

/// Non-negative value `m · 2^e` with `m.hi ∈ [1/2, 1)`, or zero (`m = 0`, `e = 0`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Scaled {
    m: Dd,
    e: i64,
}

impl Scaled {
    const ZERO: Scaled = Scaled { m: Dd::ZERO, e: 0 };

    fn one() -> Scaled {
        Scaled::new(Dd::ONE, 0)
    }

    /// Normalised `m · 2^e`.
    fn new(m: Dd, e: i64) -> Scaled {
        if m.hi == 0.0 {
            return Scaled::ZERO;
        }
        let (f, h) = frexp(m.hi);
        Scaled {
            m: Dd {
                hi: f,
                lo: ldexp(m.lo, -h),
            },
            e: e + h,
        }
    }

    fn from_f64(x: f64) -> Scaled {
        Scaled::new(Dd::from_f64(x), 0)
    }

    fn is_zero(self) -> bool {
        self.m.hi == 0.0
    }

    /// Nearest `f64` (`m.hi` is already `m` rounded to nearest; scaling is exact in the normal
    /// range).
    fn to_f64(self) -> f64 {
        ldexp(self.m.hi, self.e)
    }

    fn log10(self) -> f64 {
        if self.is_zero() {
            return f64::NEG_INFINITY;
        }
        let correction = self.m.lo / (self.m.hi * std::f64::consts::LN_10);
        if (-1000..=1000).contains(&self.e) {
            ldexp(self.m.hi, self.e).log10() + correction
        } else {
            self.m.hi.log10() + self.e as f64 * std::f64::consts::LOG10_2 + correction
        }
    }

    /// `self ≤ other` exactly (both non-negative and normalised).
    fn le(self, other: Scaled) -> bool {
        if self.is_zero() {
            return true;
        }
        if other.is_zero() {
            return false;
        }
        // A normalised value lies in [1/2 − 2^-54, 1 + 2^-54) · 2^e.
        if self.e >= other.e + 2 {
            return false;
        }
        if self.e + 2 <= other.e {
            return true;
        }
        self.m.scale_pow2(self.e - other.e).sub_dd(other.m).hi <= 0.0
    }
}

/// `2^e` for `-1022 ≤ e ≤ 1023`.
fn pow2(e: i64) -> f64 {
    debug_assert!((-1022..=1023).contains(&e));
    f64::from_bits(((e + 1023) as u64) << 52)
}

/// `x · 2^e`, rounding at most once (when the result is subnormal).
fn ldexp(mut x: f64, mut e: i64) -> f64 {
    while e > 1000 {
        x *= pow2(1000);
        e -= 1000;
        if x.is_infinite() {
            return x;
        }
    }
    while e < -1000 {
        x *= pow2(-1000);
        e += 1000;
        if x == 0.0 {
            return x;
        }
    }
    x * pow2(e)
}

/// `(f, e)` with `x = f · 2^e` and `|f| ∈ [1/2, 1)`, for finite non-zero `x`.
fn frexp(x: f64) -> (f64, i64) {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i64;
    if biased == 0 {
        // Subnormal: renormalise first.
        let (f, e) = frexp(x * pow2(64));
        return (f, e - 64);
    }
    let f = f64::from_bits((bits & !(0x7ff << 52)) | (1022 << 52));
    (f, biased - 1022)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rel_err(a: f64, b: f64) -> f64 {
        if a == b {
            0.0
        } else {
            (a - b).abs() / a.abs().max(b.abs())
        }
    }

    /// Independent reference for n ≤ 100: exact u128 Pascal triangle, one rounding.
    fn tail_u128(k: u32, n: u32) -> f64 {
        assert!(n <= 100);
        let mut row = vec![1u128];
        for _ in 0..n {
            let mut next = vec![1u128; row.len() + 1];
            for (i, pair) in row.windows(2).enumerate() {
                next[i + 1] = pair[0] + pair[1];
            }
            row = next;
        }
        let sum: u128 = row.iter().skip(k as usize).sum();
        // `as f64` rounds to nearest; dividing by 2^n is exact.
        sum as f64 / 2f64.powi(n as i32)
    }

    /// Minimal unsigned big integer (little-endian u32 limbs) for exact references at large n.
    #[derive(Clone)]
    struct Big(Vec<u32>);

    impl Big {
        fn one() -> Big {
            Big(vec![1])
        }
        fn mul_small(&mut self, m: u32) {
            let mut carry = 0u64;
            for limb in &mut self.0 {
                let v = u64::from(*limb) * u64::from(m) + carry;
                *limb = v as u32;
                carry = v >> 32;
            }
            if carry > 0 {
                self.0.push(carry as u32);
            }
        }
        /// Exact division (asserts the remainder is zero).
        fn div_small(&mut self, d: u32) {
            let mut rem = 0u64;
            for limb in self.0.iter_mut().rev() {
                let v = (rem << 32) | u64::from(*limb);
                *limb = (v / u64::from(d)) as u32;
                rem = v % u64::from(d);
            }
            assert_eq!(rem, 0);
            while self.0.len() > 1 && *self.0.last().unwrap() == 0 {
                self.0.pop();
            }
        }
        fn add(&mut self, o: &Big) {
            if self.0.len() < o.0.len() {
                self.0.resize(o.0.len(), 0);
            }
            let mut carry = 0u64;
            for (i, limb) in self.0.iter_mut().enumerate() {
                let v = u64::from(*limb) + u64::from(o.0.get(i).copied().unwrap_or(0)) + carry;
                *limb = v as u32;
                carry = v >> 32;
            }
            if carry > 0 {
                self.0.push(carry as u32);
            }
        }
        /// `(top, shift)` with `self ≈ top · 2^shift`, `top` the leading (at most) 64 bits.
        fn top_bits(&self) -> (u64, i64) {
            let len = self.0.len();
            let mut acc: u128 = 0;
            let take = len.min(3);
            for &limb in self.0.iter().rev().take(take) {
                acc = (acc << 32) | u128::from(limb);
            }
            let shift_limbs = (len - take) as i64 * 32;
            let bits = 128 - acc.leading_zeros() as i64;
            let drop = (bits - 64).max(0);
            ((acc >> drop) as u64, shift_limbs + drop)
        }
    }

    /// Exact `Σ_{i ≥ k} C(n, i)` as `(top, shift)`; the tail is `top · 2^(shift − n)`.
    fn tail_big(k: u32, n: u32) -> (u64, i64) {
        let mut c = Big::one();
        for j in 1..=k {
            c.mul_small(n - k + j);
            c.div_small(j);
        }
        let mut sum = c.clone();
        for i in k..n {
            c.mul_small(n - i);
            c.div_small(i + 1);
            sum.add(&c);
        }
        sum.top_bits()
    }

    #[test]
    fn known_thresholds_at_1e_minus_6() {
        assert_eq!(threshold_for_fpr(32, 1e-6), Ok(30));
        assert_eq!(threshold_for_fpr(48, 1e-6), Ok(41));
        assert_eq!(threshold_for_fpr(64, 1e-6), Ok(51));
    }

    #[test]
    fn thresholds_are_minimal() {
        for n in [1u32, 2, 7, 16, 32, 48, 64, 100, 256, 1000] {
            for fpr in [0.5, 0.05, 1e-3, 1e-6, 1e-9, 1e-12, 1e-30] {
                let k = threshold_for_fpr(n, fpr).unwrap();
                assert!((1..=n + 1).contains(&k));
                assert!(binomial_tail(k, n) <= fpr, "n={n} fpr={fpr} k={k}");
                assert!(binomial_tail(k - 1, n) > fpr, "n={n} fpr={fpr} k={k}");
            }
        }
        // Not reachable: 2^-8 > 1e-6, so the detector never fires.
        assert_eq!(threshold_for_fpr(8, 1e-6), Ok(9));
        // Boundary exactly representable: P[X ≥ 4 | n = 4] = 1/16.
        assert_eq!(threshold_for_fpr(4, 1.0 / 16.0), Ok(4));
        assert_eq!(threshold_for_fpr(4, 5.0 / 16.0), Ok(3));
        assert_eq!(threshold_for_fpr(4, 5.0 / 16.0 - 1e-15), Ok(4));
        // 2^-1000 > f64::MIN_POSITIVE: unreachable; 2^-1100 < 1e-320: reachable.
        assert_eq!(threshold_for_fpr(1000, f64::MIN_POSITIVE), Ok(1001));
        assert!(threshold_for_fpr(1100, 1e-320).unwrap() <= 1100);
    }

    #[test]
    fn exact_small_cases() {
        assert_eq!(binomial_tail(3, 4), 5.0 / 16.0);
        assert_eq!(binomial_tail(4, 4), 1.0 / 16.0);
        assert_eq!(binomial_tail(0, 4), 1.0);
        assert_eq!(binomial_tail(1, 4), 15.0 / 16.0);
        assert_eq!(binomial_tail(2, 4), 11.0 / 16.0);
        assert_eq!(binomial_tail(5, 4), 0.0);
        assert_eq!(binomial_tail(0, 0), 1.0);
        assert_eq!(binomial_tail(1, 0), 0.0);
        assert_eq!(binomial_tail(u32::MAX, 3), 0.0);
        assert_eq!(binomial_tail(1, 1), 0.5);
        assert_eq!(binomial_tail(32, 32), 2f64.powi(-32));
    }

    #[test]
    fn symmetry() {
        for n in [1u32, 2, 3, 10, 31, 32, 33, 100, 257, 1000, 4096] {
            for k in 0..=n + 1 {
                let s = binomial_tail(k, n) + binomial_tail(n + 1 - k, n);
                assert!((s - 1.0).abs() <= 4.0 * f64::EPSILON, "n={n} k={k} sum={s}");
            }
        }
    }

    #[test]
    fn monotone_in_k() {
        for n in [1u32, 5, 32, 52, 64, 100, 500] {
            for k in 0..=n {
                let (next, this) = (binomial_tail(k + 1, n), binomial_tail(k, n));
                // Strict unless the tail is within rounding of 1 (P[X ≥ 1] = 1 − 2^-n).
                assert!(
                    if n <= 52 || 2 * k > n {
                        next < this
                    } else {
                        next <= this
                    },
                    "n={n} k={k}"
                );
            }
        }
        for n in [2000u32, 4096] {
            for k in 0..=n {
                assert!(
                    binomial_tail(k + 1, n) <= binomial_tail(k, n),
                    "n={n} k={k}"
                );
                let (next, this) = (log10_binomial_tail(k + 1, n), log10_binomial_tail(k, n));
                // Strict where the tail is not within rounding of 1.
                assert!(
                    if 2 * k > n { next < this } else { next <= this },
                    "n={n} k={k}"
                );
            }
        }
    }

    #[test]
    fn agrees_with_u128_reference() {
        for n in 0..=100u32 {
            for k in 0..=n + 1 {
                let (ours, exact) = (binomial_tail(k, n), tail_u128(k, n));
                assert!(
                    rel_err(ours, exact) <= 1e-12,
                    "n={n} k={k}: {ours} vs {exact}"
                );
            }
        }
    }

    #[test]
    fn agrees_with_bigint_reference_at_large_n() {
        for n in [1000u32, 2000, 4096] {
            let mut ks: Vec<u32> = (0..=n).step_by(37).collect();
            ks.extend([1, n / 2, n / 2 + 1, n - 1, n]);
            for k in ks {
                let (top, shift) = tail_big(k, n);
                let log10_exact = (top as f64).log10()
                    + (shift - i64::from(n)) as f64 * std::f64::consts::LOG10_2;
                let log10_ours = log10_binomial_tail(k, n);
                assert!(
                    (log10_ours - log10_exact).abs() <= 1e-12 * log10_exact.abs().max(1.0),
                    "n={n} k={k}: {log10_ours} vs {log10_exact}"
                );
                let exact = ldexp(top as f64, shift - i64::from(n));
                if exact >= f64::MIN_POSITIVE {
                    let ours = binomial_tail(k, n);
                    assert!(
                        rel_err(ours, exact) <= 1e-12,
                        "n={n} k={k}: {ours} vs {exact}"
                    );
                }
            }
        }
    }

    #[test]
    fn log10_matches_direct_and_never_underflows() {
        for n in [10u32, 64, 500, 1000] {
            for k in 0..=n {
                let p = binomial_tail(k, n);
                if p >= f64::MIN_POSITIVE {
                    let l = log10_binomial_tail(k, n);
                    assert!(
                        (l - p.log10()).abs() <= 1e-13 * p.log10().abs().max(1.0),
                        "n={n} k={k}"
                    );
                }
            }
        }
        let l = log10_binomial_tail(2000, 2000);
        assert!(l.is_finite());
        assert!((l + 2000.0 * std::f64::consts::LOG10_2).abs() < 1e-9, "{l}");
        assert_eq!(binomial_tail(2000, 2000), 0.0);
        assert!(log10_binomial_tail(4000, 4096).is_finite());
        assert_eq!(log10_binomial_tail(0, 7), 0.0);
        assert_eq!(log10_binomial_tail(0, 0), 0.0);
        assert_eq!(log10_binomial_tail(8, 7), f64::NEG_INFINITY);
        assert_eq!(log10_binomial_tail(1, 0), f64::NEG_INFINITY);
    }

    #[test]
    fn corrected_p_value_properties() {
        for p in [0.0, 1e-300, 1e-12, 1e-6, 0.01, 0.3, 0.999, 1.0] {
            assert_eq!(corrected_p_value(p, 1), p);
            assert_eq!(corrected_p_value(p, 0), p);
        }
        for k in [2u64, 10, 1000, 1_000_000] {
            let p = 1e-15;
            let c = corrected_p_value(p, k);
            assert!(rel_err(c, k as f64 * p) < 1e-9, "K={k}: {c}");
        }
        assert!(rel_err(corrected_p_value(1e-300, 1000), 1e-297) < 1e-12);
        let mut last = 0.0;
        for k in [1u64, 2, 3, 10, 100, 10_000, 1 << 40, u64::MAX] {
            let c = corrected_p_value(1e-6, k);
            assert!(c >= last && (0.0..=1.0).contains(&c), "K={k}: {c}");
            last = c;
        }
        assert_eq!(corrected_p_value(1.0, 5), 1.0);
        assert_eq!(corrected_p_value(0.0, 5), 0.0);
        assert_eq!(corrected_p_value(0.5, 2), 1.0);
        assert_eq!(corrected_p_value(0.25, 2), 0.5);
        assert_eq!(corrected_p_value(-0.5, 3), 0.0);
        assert!(corrected_p_value(f64::NAN, 3).is_nan());
    }

    #[test]
    fn threshold_among_candidates() {
        for n in [1u32, 16, 32, 48, 64, 128, 1000] {
            for fpr in [0.5, 1e-3, 1e-6, 1e-12] {
                assert_eq!(
                    threshold_for_fpr_among(n, fpr, 1),
                    threshold_for_fpr(n, fpr)
                );
            }
        }
        // Monotone in K, and the per-test level is Bonferroni's fpr / K.
        let mut last = 0;
        for k in [1u64, 2, 10, 1000, 1 << 20, 1 << 40, u64::MAX] {
            let t = threshold_for_fpr_among(64, 1e-6, k).unwrap();
            assert!(t >= last);
            last = t;
            let alpha = 1e-6 / k as f64;
            assert!(binomial_tail(t, 64) <= alpha);
            assert!(binomial_tail(t - 1, 64) > alpha);
        }
        // The family-wise rate K · P[X ≥ t] is at most fpr.
        let t = threshold_for_fpr_among(256, 1e-6, 1000).unwrap();
        assert!(1000.0 * binomial_tail(t, 256) <= 1e-6);
        // Tiny fpr with huge K: the level fpr/K is below the f64 range, still well defined.
        let t = threshold_for_fpr_among(2000, 1e-300, u64::MAX).unwrap();
        assert!(t > threshold_for_fpr(2000, 1e-300).unwrap() && t <= 2000);
        assert!(log10_binomial_tail(t, 2000) <= -300.0 - (u64::MAX as f64).log10() + 1e-9);
        assert!(log10_binomial_tail(t - 1, 2000) > -300.0 - (u64::MAX as f64).log10() - 1e-9);
    }

    #[test]
    fn detect_perfect_match() {
        let message: Vec<bool> = (0..32).map(|i| (i * 7 + 3) % 5 < 2).collect();
        let d = detect(&message, &message, 1, 1e-6).unwrap();
        assert_eq!(d.matches, 32);
        assert_eq!(d.bits, 32);
        assert_eq!(d.bit_accuracy, 1.0);
        assert_eq!(d.p_value, 2f64.powi(-32));
        assert_eq!(d.p_value_corrected, d.p_value);
        assert_eq!(d.threshold, 30);
        assert!(d.detected);
        assert_eq!(d.candidates, 1);
        assert_eq!(d.fpr, 1e-6);

        let d = detect(&message, &message, 1000, 1e-6).unwrap();
        assert!(d.detected);
        assert!(rel_err(d.p_value_corrected, 1000.0 * 2f64.powi(-32)) < 1e-6);
        assert_eq!(
            d.threshold,
            threshold_for_fpr_among(32, 1e-6, 1000).unwrap()
        );
    }

    #[test]
    fn detect_random_half_match_is_not_detected() {
        // Deterministic pseudo-random bits (LCG), independent of the message pattern.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let decoded: Vec<bool> = (0..64)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1);
                state >> 63 == 1
            })
            .collect();
        let message: Vec<bool> = (0..64).map(|i| i % 2 == 0).collect();
        let d = detect(&decoded, &message, 1, 1e-6).unwrap();
        assert!(d.matches > 20 && d.matches < 44, "{}", d.matches);
        assert!(!d.detected);
        assert!(d.p_value > 1e-3);
        assert_eq!(d.threshold, 51);

        // Exactly half the bits match.
        let flipped: Vec<bool> = message
            .iter()
            .enumerate()
            .map(|(i, &b)| if i < 32 { !b } else { b })
            .collect();
        let d = detect(&flipped, &message, 1, 1e-6).unwrap();
        assert_eq!(d.matches, 32);
        assert_eq!(d.bit_accuracy, 0.5);
        assert!(!d.detected);
        assert!(d.p_value > 0.5);
    }

    #[test]
    fn detection_serialises_with_all_fields() {
        fn assert_serialize<T: Serialize>(_: &T) {}
        let d = detect(&[true, false], &[true, true], 1, 0.1).unwrap();
        assert_serialize(&d);
        assert_eq!(d.matches, 1);
        assert_eq!(d.p_value, 0.75);
        assert_eq!(d.threshold, 3);
        assert!(!d.detected);
    }

    #[test]
    fn invalid_inputs_are_errors() {
        for fpr in [0.0, 1.0, -0.1, 1.5, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                threshold_for_fpr(32, fpr),
                Err(StatsError::InvalidFpr(_))
            ));
            assert!(matches!(
                threshold_for_fpr_among(32, fpr, 4),
                Err(StatsError::InvalidFpr(_))
            ));
            assert!(matches!(
                detect(&[true], &[true], 1, fpr),
                Err(StatsError::InvalidFpr(_))
            ));
        }
        assert_eq!(threshold_for_fpr(0, 1e-6), Err(StatsError::EmptyMessage));
        assert_eq!(
            threshold_for_fpr_among(0, 1e-6, 3),
            Err(StatsError::EmptyMessage)
        );
        assert_eq!(
            threshold_for_fpr(MAX_BITS + 1, 1e-6),
            Err(StatsError::TooManyBits(MAX_BITS as usize + 1))
        );
        assert_eq!(
            threshold_for_fpr_among(32, 1e-6, 0),
            Err(StatsError::NoCandidates)
        );
        assert_eq!(detect(&[], &[], 1, 1e-6), Err(StatsError::EmptyMessage));
        assert_eq!(
            detect(&[true, false], &[true], 1, 1e-6),
            Err(StatsError::LengthMismatch {
                decoded: 2,
                message: 1
            })
        );
        assert_eq!(
            detect(&[true], &[true], 0, 1e-6),
            Err(StatsError::NoCandidates)
        );
        assert!(!StatsError::InvalidFpr(2.0).to_string().is_empty());
    }

    #[test]
    fn logits_to_matches() {
        let logits = [2.5f32, -1.0, 0.0, f32::NAN, 0.1, -0.0];
        let message = [true, false, false, false, true, true];
        assert_eq!(matches_from_logits(&logits, &message), 5);
        assert_eq!(matches_from_logits(&logits, &[true, true]), 1);
        assert_eq!(matches_from_logits(&[], &[]), 0);
    }

    #[test]
    fn frexp_ldexp_roundtrip() {
        for x in [1.0, 0.5, 3.0, 1e-310, f64::MIN_POSITIVE, f64::MAX, 5e-324] {
            let (f, e) = frexp(x);
            assert!((0.5..1.0).contains(&f), "{x}: {f}");
            assert_eq!(ldexp(f, e), x);
        }
        assert_eq!(ldexp(1.0, -1074), 5e-324);
        assert_eq!(ldexp(1.0, -1076), 0.0);
        assert_eq!(ldexp(0.5, 1024), 2f64.powi(1023));
        assert_eq!(ldexp(1.0, 2000), f64::INFINITY);
    }
}
