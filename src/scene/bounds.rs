//! Robust axis-aligned bounds of a scene: per-axis quantiles of the centres, so that a few
//! far-away floaters do not decide where orbit cameras look.

use crate::scene::Gaussians;

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Bounds {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Bounds {
    pub fn center(&self) -> [f32; 3] {
        std::array::from_fn(|a| 0.5 * (self.min[a] + self.max[a]))
    }
    pub fn extent(&self) -> [f32; 3] {
        std::array::from_fn(|a| self.max[a] - self.min[a])
    }
}

/// Exact bounds of all centres (`None` for an empty scene).
pub fn full_bounds(g: &Gaussians) -> Option<Bounds> {
    let first = *g.means.first()?;
    let mut b = Bounds {
        min: first,
        max: first,
    };
    for m in &g.means {
        b.min = std::array::from_fn(|a| b.min[a].min(m[a]));
        b.max = std::array::from_fn(|a| b.max[a].max(m[a]));
    }
    Some(b)
}

/// Per-axis `q` and `1 − q` quantiles of the centres (e.g. `q = 0.02`), `None` for an empty scene.
pub fn robust_bounds(g: &Gaussians, q: f32) -> Option<Bounds> {
    if g.is_empty() {
        return None;
    }
    let q = q.clamp(0.0, 0.5);
    let mut b = Bounds {
        min: [0.0; 3],
        max: [0.0; 3],
    };
    let mut axis: Vec<f32> = Vec::with_capacity(g.len());
    for a in 0..3 {
        axis.clear();
        axis.extend(g.means.iter().map(|m| m[a]));
        let n = axis.len();
        let lo = ((n - 1) as f32 * q).round() as usize;
        let hi = ((n - 1) as f32 * (1.0 - q)).round() as usize;
        let (_, lo_v, _) = axis.select_nth_unstable_by(lo, f32::total_cmp);
        b.min[a] = *lo_v;
        let (_, hi_v, _) = axis.select_nth_unstable_by(hi, f32::total_cmp);
        b.max[a] = *hi_v;
    }
    Some(b)
}
