//! antimatter15 `.splat`: a headerless array of 32-byte records, SH degree 0.
//!
//! | bytes | content |
//! |---|---|
//! | 0..12 | position, 3 × f32 LE |
//! | 12..24 | scale, 3 × f32 LE, **linear** (→ `ln`) |
//! | 24..28 | colour RGBA u8: `rgb = 0.5 + SH_C0·dc` ⇒ `dc = (rgb/255 − 0.5)/SH_C0`; `a/255 = sigmoid(opacity)` ⇒ [`logit`] (clamped, finite) |
//! | 28..32 | rotation u8 × 4, `(w, x, y, z)`, stored as `q·128 + 128` ⇒ `q = (b − 128)/128`, then normalised |

use crate::scene::format::{GaussianBuilder, Limits, RawGaussian};
use crate::scene::{Gaussians, SH_C0, SceneError, logit, sigmoid};

/// Bytes per Gaussian.
pub const RECORD_BYTES: usize = 32;

/// Reads a `.splat` file.
pub fn read(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    if !bytes.len().is_multiple_of(RECORD_BYTES) {
        return Err(SceneError::Corrupt(format!(
            ".splat size {} is not a multiple of {RECORD_BYTES} bytes (truncated or not a .splat file)",
            bytes.len()
        )));
    }
    if bytes.is_empty() {
        return Err(SceneError::Corrupt("empty .splat file".into()));
    }
    let n = limits.check_count((bytes.len() / RECORD_BYTES) as u64)?;
    let mut builder = GaussianBuilder::new(n, 0);
    for rec in bytes.chunks_exact(RECORD_BYTES) {
        let f = |k: usize| {
            f32::from_le_bytes([rec[4 * k], rec[4 * k + 1], rec[4 * k + 2], rec[4 * k + 3]])
        };
        let dc = |c: u8| (c as f32 / 255.0 - 0.5) / SH_C0;
        let q = |b: u8| (b as f32 - 128.0) / 128.0;
        builder.push(RawGaussian {
            mean: [f(0), f(1), f(2)],
            // A zero or negative scale gives -inf / NaN, which the builder rejects as NonFinite.
            log_scale: [f(3).ln(), f(4).ln(), f(5).ln()],
            rotation: [q(rec[28]), q(rec[29]), q(rec[30]), q(rec[31])],
            opacity: logit(rec[27] as f32 / 255.0),
            dc: [dc(rec[24]), dc(rec[25]), dc(rec[26])],
            rest: &[],
        })?;
    }
    Ok(builder.finish())
}

/// The `.splat` bytes of `g`, as antimatter15's `convert.py` writes them: positions and scales
/// exact (f32), colour and opacity at 8 bits, rotation at 8 bits a component; the format has
/// no view-dependent colour, so SH degrees above 0 are dropped.
pub fn encode(g: &Gaussians) -> Vec<u8> {
    let mut out = Vec::with_capacity(g.len() * RECORD_BYTES);
    let u8c = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    for i in 0..g.len() {
        g.means[i]
            .iter()
            .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        g.log_scales[i]
            .iter()
            .for_each(|v| out.extend_from_slice(&v.exp().to_le_bytes()));
        for c in 0..3 {
            out.push(u8c((0.5 + SH_C0 * g.sh_dc[i][c]) * 255.0));
        }
        out.push(u8c(sigmoid(g.opacity_logits[i]) * 255.0));
        for k in 0..4 {
            out.push(u8c(g.rotations[i][k] * 128.0 + 128.0));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::format::read_scene_bytes;
    use crate::scene::ply::tests::synthetic;

    fn read_bytes(b: &[u8]) -> Result<Gaussians, SceneError> {
        read_scene_bytes(b, Some("splat"), &Limits::default())
    }

    #[test]
    fn decode_synthetic_within_quantisation() {
        let g = synthetic(500, 0, 5);
        let d = read_bytes(&encode(&g)).unwrap();
        d.validate().unwrap();
        assert_eq!((d.len(), d.sh_degree), (500, 0));
        for i in 0..500 {
            assert_eq!(d.means[i], g.means[i]);
            for c in 0..3 {
                assert!((d.log_scales[i][c] - g.log_scales[i][c]).abs() < 1e-5);
                assert!((d.sh_dc[i][c] - g.sh_dc[i][c]).abs() < 0.5 / 255.0 / SH_C0 + 1e-5);
            }
            assert!(
                (sigmoid(d.opacity_logits[i]) - sigmoid(g.opacity_logits[i])).abs()
                    < 0.5 / 255.0 + 1e-5
            );
            let dot: f32 = (0..4).map(|k| d.rotations[i][k] * g.rotations[i][k]).sum();
            assert!(dot.abs() > 0.999, "{i}: {dot}");
        }
    }

    #[test]
    fn known_record() {
        let mut rec = Vec::new();
        for v in [1.0f32, -2.0, 3.5, 1.0, std::f32::consts::E, 0.5] {
            rec.extend_from_slice(&v.to_le_bytes());
        }
        rec.extend_from_slice(&[255, 0, 128, 255, 255, 128, 128, 128]);
        let g = read_bytes(&rec).unwrap();
        assert_eq!(g.means[0], [1.0, -2.0, 3.5]);
        assert_eq!(g.log_scales[0][0], 0.0);
        assert!((g.log_scales[0][1] - 1.0).abs() < 1e-6);
        assert_eq!(g.sh_dc[0][0], 0.5 / SH_C0);
        assert_eq!(g.sh_dc[0][1], -0.5 / SH_C0);
        assert!(g.opacity_logits[0].is_finite() && g.opacity_logits[0] > 15.0);
        // (127/128, 0, 0, 0) normalised.
        assert!((g.rotations[0][0] - 1.0).abs() < 1e-6);
        assert_eq!(&g.rotations[0][1..], &[0.0, 0.0, 0.0]);
    }

    #[test]
    fn errors() {
        let g = synthetic(3, 0, 1);
        let good = encode(&g);
        // Length not a multiple of 32.
        let e = read_bytes(&good[..good.len() - 1]).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        assert!(matches!(read_bytes(&[]), Err(SceneError::Corrupt(_))));
        // NaN / Inf position, zero scale.
        let mut b = good.clone();
        b[32 + 4..32 + 8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(matches!(
            read_bytes(&b),
            Err(SceneError::NonFinite {
                index: 1,
                field: "position"
            })
        ));
        let mut b = good.clone();
        b[8..12].copy_from_slice(&f32::INFINITY.to_le_bytes());
        assert!(matches!(
            read_bytes(&b),
            Err(SceneError::NonFinite {
                index: 0,
                field: "position"
            })
        ));
        let mut b = good.clone();
        b[64 + 16..64 + 20].copy_from_slice(&0.0f32.to_le_bytes());
        assert!(matches!(
            read_bytes(&b),
            Err(SceneError::NonFinite {
                index: 2,
                field: "scale"
            })
        ));
        // Zero quaternion (all four bytes 128).
        let mut b = good.clone();
        b[28..32].copy_from_slice(&[128; 4]);
        assert!(matches!(
            read_bytes(&b),
            Err(SceneError::ZeroQuaternion { index: 0 })
        ));
        // Too many.
        let limits = Limits {
            max_gaussians: 2,
            ..Limits::default()
        };
        let e = read_scene_bytes(&good, Some("splat"), &limits).unwrap_err();
        assert!(
            matches!(e, SceneError::TooManyGaussians { count: 3, max: 2 }),
            "{e}"
        );
    }
}
