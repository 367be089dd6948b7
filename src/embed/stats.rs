//! Quantiles and the paper's "quantile-based min–max normalisation" `Norm(·)`.

use rayon::prelude::*;

/// The `q`-quantile of `values` (linear interpolation between order statistics, numpy's default
/// "type 7"); NaNs are ignored. `None` when there is no finite value.
pub fn quantile(values: &[f32], q: f32) -> Option<f32> {
    quantiles(values, &[q]).map(|v| v[0])
}

/// Several quantiles of `values` with one sort (see [`quantile`]).
pub fn quantiles(values: &[f32], qs: &[f32]) -> Option<Vec<f32>> {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return None;
    }
    v.par_sort_unstable_by(f32::total_cmp);
    Some(qs.iter().map(|&q| sorted_quantile(&v, q)).collect())
}

/// The `q`-quantile of an already sorted, NaN-free, non-empty slice.
pub fn sorted_quantile(sorted: &[f32], q: f32) -> f32 {
    let n = sorted.len();
    let pos = q.clamp(0.0, 1.0) as f64 * (n - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(n - 1);
    let t = pos - lo as f64;
    (sorted[lo] as f64 * (1.0 - t) + sorted[hi] as f64 * t) as f32
}

/// Bounds of a quantile min–max normalisation: `lo` and `hi` such that `x ↦ clip((x − lo) /
/// (hi − lo), 0, 1)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormBounds {
    pub lo: f32,
    pub hi: f32,
}

impl NormBounds {
    /// Bounds at the `q_lo`/`q_hi` quantiles of `values`. When those coincide (a feature with
    /// more than `q_hi − q_lo` of tied values) the full range (min, max) is used instead, so the
    /// few differing values still order; when that is empty too, every value maps to 0.5.
    pub fn fit(values: &[f32], q_lo: f32, q_hi: f32) -> Self {
        let Some(b) = quantiles(values, &[q_lo, q_hi, 0.0, 1.0]) else {
            return Self { lo: 0.0, hi: 0.0 };
        };
        if b[1] - b[0] > f32::EPSILON * (b[0].abs() + b[1].abs()).max(f32::MIN_POSITIVE) {
            Self { lo: b[0], hi: b[1] }
        } else {
            Self { lo: b[2], hi: b[3] }
        }
    }

    /// `clip((x − lo)/(hi − lo), 0, 1)`; 0.5 when the range is empty; NaN maps to 0.
    #[inline]
    pub fn apply(&self, x: f32) -> f32 {
        let d = self.hi - self.lo;
        if !(d > 0.0) {
            return 0.5;
        }
        let v = (x - self.lo) / d;
        if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) }
    }
}

/// `Norm(values)`: quantile min–max normalisation into [0, 1] (see [`NormBounds::fit`]).
pub fn norm(values: &[f32], q_lo: f32, q_hi: f32) -> Vec<f32> {
    let b = NormBounds::fit(values, q_lo, q_hi);
    values.par_iter().map(|&x| b.apply(x)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_like_numpy() {
        let v = [3.0, 1.0, 4.0, 1.0, 5.0, f32::NAN];
        // sorted: 1 1 3 4 5
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&v, 1.0), Some(5.0));
        assert_eq!(quantile(&v, 0.5), Some(3.0));
        assert!((quantile(&v, 0.3).unwrap() - 1.4).abs() < 1e-6); // pos 1.2 → 1 + 0.2·2
        assert_eq!(quantile(&[], 0.5), None);
    }

    #[test]
    fn norm_clips_to_unit_interval_and_handles_ties() {
        let v: Vec<f32> = (0..101).map(|i| i as f32).collect();
        let n = norm(&v, 0.1, 0.9);
        assert_eq!(n[0], 0.0);
        assert_eq!(n[10], 0.0);
        assert!((n[50] - 0.5).abs() < 1e-6);
        assert_eq!(n[95], 1.0);
        // 99 % ties: the quantiles coincide, so the full range is used.
        let mut t = vec![2.0f32; 298];
        t.extend([3.0, 7.0]);
        let n = norm(&t, 0.01, 0.99);
        assert_eq!(n[0], 0.0);
        assert!((n[298] - 0.2).abs() < 1e-6);
        assert_eq!(n[299], 1.0);
        // Constant: 0.5 everywhere.
        assert!(norm(&[4.0; 5], 0.01, 0.99).iter().all(|&x| x == 0.5));
    }
}
