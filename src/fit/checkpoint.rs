//! Checkpoints of a fit: everything [`super::Fitter`] holds, so that a resumed fit continues
//! bit-identically. Layout: a 16-byte magic, a little-endian u64 length and a JSON header
//! (version, configuration, dataset fingerprint, step, random state, the epoch's remaining view
//! order, counts), then little-endian arrays — the scene, Adam's first and second moments
//! (each: means, SH DC, SH rest, opacities, log-scales, rotations), the densification
//! statistics — and a SHA-256 of all that came before. Written to a temporary file and renamed.

use super::adam::{Adam, groups, groups_mut};
use super::densify::DensifyStats;
use super::{Dataset, FitConfig, FitError, Fitter};
use crate::scene::Gaussians;
use crate::scene::synthetic::Rng;
use sha2::{Digest, Sha256};
use std::io::Write;
use std::path::Path;

const MAGIC: &[u8; 16] = b"SPLATMARK-FIT\0\0\x01";
const VERSION: u32 = 1;

#[derive(serde::Serialize, serde::Deserialize)]
struct Header {
    version: u32,
    config: FitConfig,
    fingerprint: String,
    step: usize,
    rng: u64,
    order: Vec<usize>,
    gaussians: usize,
    sh_degree: u8,
    adam_t: i32,
}

fn put_f32s(out: &mut Vec<u8>, xs: &[f32]) {
    out.reserve(xs.len() * 4);
    for x in xs {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

/// The checkpoint's bytes.
pub fn to_bytes(f: &Fitter) -> Vec<u8> {
    let header = Header {
        version: VERSION,
        config: f.cfg.clone(),
        fingerprint: f.fingerprint.clone(),
        step: f.step,
        rng: f.rng.state(),
        order: f.order.clone(),
        gaussians: f.scene.len(),
        sh_degree: f.scene.sh_degree,
        adam_t: f.adam.t,
    };
    let json = serde_json::to_vec(&header).expect("a header serialises");
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend_from_slice(&json);
    for g in [&f.scene, &f.adam.m, &f.adam.v] {
        for arr in groups(g) {
            put_f32s(&mut out, arr);
        }
    }
    put_f32s(&mut out, &f.stats.grad_accum);
    for d in &f.stats.denom {
        out.extend_from_slice(&d.to_le_bytes());
    }
    put_f32s(&mut out, &f.stats.max_radii);
    let digest = Sha256::digest(&out);
    out.extend_from_slice(&digest);
    out
}

/// Writes the checkpoint atomically.
pub fn save(f: &Fitter, path: &Path) -> Result<(), FitError> {
    let bytes = to_bytes(f);
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(|e| FitError::io(path, e))?;
    tmp.write_all(&bytes)
        .and_then(|_| tmp.as_file().sync_all())
        .map_err(|e| FitError::io(path, e))?;
    tmp.persist(path).map_err(|e| FitError::io(path, e.error))?;
    Ok(())
}

/// Reads a checkpoint made on `ds` (any other dataset is refused).
pub fn load(path: &Path, ds: &Dataset) -> Result<Fitter, FitError> {
    let bytes = std::fs::read(path).map_err(|e| FitError::io(path, e))?;
    from_bytes(&bytes, ds)
}

/// [`load`] from bytes.
pub fn from_bytes(bytes: &[u8], ds: &Dataset) -> Result<Fitter, FitError> {
    let bad = |m: &str| FitError::Checkpoint(m.to_string());
    if bytes.len() < MAGIC.len() + 8 + 32 || &bytes[..16] != MAGIC {
        return Err(bad("is not a splatmark fit checkpoint"));
    }
    let (body, digest) = bytes.split_at(bytes.len() - 32);
    if Sha256::digest(body).as_slice() != digest {
        return Err(bad("is damaged (its checksum does not match)"));
    }
    let len = u64::from_le_bytes(body[16..24].try_into().expect("8 bytes"));
    let json_end = 24usize
        .checked_add(usize::try_from(len).map_err(|_| bad("has a bad header length"))?)
        .filter(|&e| e <= body.len())
        .ok_or_else(|| bad("has a bad header length"))?;
    let h: Header = serde_json::from_slice(&body[24..json_end])
        .map_err(|e| FitError::Checkpoint(format!("has an unreadable header: {e}")))?;
    if h.version != VERSION {
        return Err(FitError::Checkpoint(format!(
            "is version {}, this build reads {VERSION}",
            h.version
        )));
    }
    if h.fingerprint != ds.fingerprint {
        return Err(bad(
            "was made on another dataset (or other image options): start afresh or point at \
             the same data",
        ));
    }
    h.config.validate()?;
    if h.sh_degree > 3 || h.order.iter().any(|&v| v >= ds.train.len()) {
        return Err(bad("does not fit this dataset"));
    }
    let mut cur = Cursor(&body[json_end..]);
    let n = h.gaussians;
    let shaped = || {
        let mut g = Gaussians::with_capacity(0, h.sh_degree);
        g.means = vec![[0.0; 3]; n];
        g.log_scales = vec![[0.0; 3]; n];
        g.rotations = vec![[0.0; 4]; n];
        g.opacity_logits = vec![0.0; n];
        g.sh_dc = vec![[0.0; 3]; n];
        g.sh_rest = vec![0.0; n * g.rest_len()];
        g
    };
    let per_gaussian = 3 + 3 + crate::scene::rest_len_for(h.sh_degree) + 1 + 3 + 4;
    if n.checked_mul((3 * per_gaussian + 3) * 4) != Some(cur.0.len()) {
        return Err(bad("has arrays of the wrong size"));
    }
    let read_g = |cur: &mut Cursor| {
        let mut g = shaped();
        for arr in groups_mut(&mut g) {
            let raw = cur.take(arr.len() * 4)?;
            for (x, c) in arr.iter_mut().zip(raw.chunks_exact(4)) {
                *x = f32::from_le_bytes(c.try_into().expect("4 bytes"));
            }
        }
        Ok::<_, FitError>(g)
    };
    let scene = read_g(&mut cur)?;
    let m = read_g(&mut cur)?;
    let v = read_g(&mut cur)?;
    let f32s = |raw: &[u8]| -> Vec<f32> {
        raw.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect()
    };
    let grad_accum = f32s(cur.take(n * 4)?);
    let denom = cur
        .take(n * 4)?
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")))
        .collect();
    let max_radii = f32s(cur.take(n * 4)?);
    Ok(Fitter {
        cfg: h.config,
        scene,
        adam: Adam { m, v, t: h.adam_t },
        stats: DensifyStats {
            grad_accum,
            denom,
            max_radii,
        },
        step: h.step,
        rng: Rng::new(h.rng),
        order: h.order,
        fingerprint: h.fingerprint,
    })
}

struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], FitError> {
        if self.0.len() < n {
            return Err(FitError::Checkpoint("is truncated".into()));
        }
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        Ok(a)
    }
}
