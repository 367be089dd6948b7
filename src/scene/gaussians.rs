//! The in-memory scene: a set of 3D Gaussians as structure-of-arrays f32.

use crate::scene::SceneError;

/// Number of spherical-harmonics coefficients per colour channel for a degree (1, 4, 9, 16).
pub const fn sh_coeffs(degree: u8) -> usize {
    let d = degree as usize + 1;
    d * d
}

/// Number of `sh_rest` floats per Gaussian for a degree (0, 9, 24, 45).
pub const fn rest_len_for(sh_degree: u8) -> usize {
    (sh_coeffs(sh_degree) - 1) * 3
}

/// A 3D Gaussian Splatting scene, structure-of-arrays, every value f32.
///
/// Conventions (those of the INRIA reference implementation):
/// - `means`: world-space centres.
/// - `log_scales`: natural log of the per-axis standard deviations.
/// - `rotations`: unit quaternions `(w, x, y, z)`; readers normalise them and reject zero length.
/// - `opacity_logits`: opacity before the sigmoid.
/// - `sh_dc`: degree-0 SH coefficient per RGB channel (colour = 0.5 + SH_C0 · dc + …).
/// - `sh_rest`: the higher SH coefficients, `n × (sh_coeffs(sh_degree) − 1) × 3`, laid out
///   Gaussian-major, then coefficient, then RGB (`[i][k][c]`). Note INRIA's PLY stores them
///   channel-major (`f_rest_{c·(K−1)+k}`); the PLY reader and writer convert.
///
/// The float type defaults to f32 (what files hold and what the product computes with); the CPU
/// rasterizer is generic so that its gradient tests can run it in f64.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gaussians<T = f32> {
    pub means: Vec<[T; 3]>,
    pub log_scales: Vec<[T; 3]>,
    pub rotations: Vec<[T; 4]>,
    pub opacity_logits: Vec<T>,
    pub sh_dc: Vec<[T; 3]>,
    pub sh_rest: Vec<T>,
    pub sh_degree: u8,
}

impl<T: Copy> Gaussians<T> {
    /// Number of `sh_rest` floats per Gaussian in this scene.
    pub fn rest_len(&self) -> usize {
        rest_len_for(self.sh_degree)
    }

    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// The higher SH coefficients of Gaussian `i`, `[k][c]` flattened.
    pub fn rest_of(&self, i: usize) -> &[T] {
        let r = self.rest_len();
        &self.sh_rest[i * r..(i + 1) * r]
    }

    /// Every parameter in one vector (means, log-scales, rotations, opacity logits, SH DC, the
    /// higher SH coefficients): what tests compare two scenes or two gradients by.
    #[cfg(test)]
    pub fn flat(&self) -> Vec<T> {
        let mut v: Vec<T> = self.means.iter().flatten().copied().collect();
        v.extend(self.log_scales.iter().flatten());
        v.extend(self.rotations.iter().flatten());
        v.extend(&self.opacity_logits);
        v.extend(self.sh_dc.iter().flatten());
        v.extend(&self.sh_rest);
        v
    }

    /// The same scene with every value converted to another float type.
    pub fn cast<U: Copy>(&self, f: impl Fn(T) -> U + Copy) -> Gaussians<U> {
        Gaussians {
            means: self.means.iter().map(|v| v.map(f)).collect(),
            log_scales: self.log_scales.iter().map(|v| v.map(f)).collect(),
            rotations: self.rotations.iter().map(|v| v.map(f)).collect(),
            opacity_logits: self.opacity_logits.iter().map(|&v| f(v)).collect(),
            sh_dc: self.sh_dc.iter().map(|v| v.map(f)).collect(),
            sh_rest: self.sh_rest.iter().map(|&v| f(v)).collect(),
            sh_degree: self.sh_degree,
        }
    }
}

impl Gaussians {
    /// Number of `sh_rest` floats per Gaussian for a degree (0, 9, 24, 45).
    pub const fn rest_len_for(sh_degree: u8) -> usize {
        rest_len_for(sh_degree)
    }

    /// An empty scene of the given SH degree with room for `n` Gaussians.
    pub fn with_capacity(n: usize, sh_degree: u8) -> Self {
        Self {
            means: Vec::with_capacity(n),
            log_scales: Vec::with_capacity(n),
            rotations: Vec::with_capacity(n),
            opacity_logits: Vec::with_capacity(n),
            sh_dc: Vec::with_capacity(n),
            sh_rest: Vec::with_capacity(n * Self::rest_len_for(sh_degree)),
            sh_degree,
        }
    }

    /// Opacity after the sigmoid.
    pub fn opacity(&self, i: usize) -> f32 {
        sigmoid(self.opacity_logits[i])
    }

    /// Checks that every array has the length the count and SH degree imply, and that every
    /// value is finite and every quaternion has non-zero length.
    pub fn validate(&self) -> Result<(), SceneError> {
        let n = self.len();
        if self.sh_degree > 3 {
            return Err(SceneError::UnsupportedShDegree(self.sh_degree as usize));
        }
        let lens = [
            ("log_scales", self.log_scales.len()),
            ("rotations", self.rotations.len()),
            ("opacity_logits", self.opacity_logits.len()),
            ("sh_dc", self.sh_dc.len()),
        ];
        for (name, len) in lens {
            if len != n {
                return Err(SceneError::Inconsistent(format!(
                    "{name} has {len} entries but there are {n} means"
                )));
            }
        }
        if self.sh_rest.len() != n * self.rest_len() {
            return Err(SceneError::Inconsistent(format!(
                "sh_rest has {} values, expected {} for {n} Gaussians of SH degree {}",
                self.sh_rest.len(),
                n * self.rest_len(),
                self.sh_degree
            )));
        }
        for i in 0..n {
            let fields: [(&str, &[f32]); 5] = [
                ("position", &self.means[i]),
                ("scale", &self.log_scales[i]),
                ("rotation", &self.rotations[i]),
                ("opacity", std::slice::from_ref(&self.opacity_logits[i])),
                ("f_dc", &self.sh_dc[i]),
            ];
            for (field, v) in fields {
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(SceneError::NonFinite { index: i, field });
                }
            }
            if self.rest_of(i).iter().any(|x| !x.is_finite()) {
                return Err(SceneError::NonFinite {
                    index: i,
                    field: "f_rest",
                });
            }
            let q = self.rotations[i];
            if q.iter().map(|x| x * x).sum::<f32>() == 0.0 {
                return Err(SceneError::ZeroQuaternion { index: i });
            }
        }
        Ok(())
    }
}

/// Normalises a quaternion; leaves one that is already unit to f32 precision bit-for-bit unchanged,
/// so that read → write → read is exact. Returns `None` for a zero or non-finite length.
pub fn normalize_quat(q: [f32; 4]) -> Option<[f32; 4]> {
    let n2: f64 = q.iter().map(|&x| (x as f64) * (x as f64)).sum();
    if n2.is_nan() || n2 <= 0.0 || !n2.is_finite() {
        return None;
    }
    if (n2 - 1.0).abs() <= 4.0 * f32::EPSILON as f64 {
        return Some(q);
    }
    let inv = 1.0 / n2.sqrt();
    Some(q.map(|x| (x as f64 * inv) as f32))
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Inverse of [`sigmoid`], clamped away from 0 and 1 so that it stays finite.
pub fn logit(p: f32) -> f32 {
    let p = p.clamp(1e-7, 1.0 - 1e-7);
    (p / (1.0 - p)).ln()
}

/// The zeroth-order SH basis constant: colour = 0.5 + SH_C0 · dc.
pub const SH_C0: f32 = 0.282_094_8;
