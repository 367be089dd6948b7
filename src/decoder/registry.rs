//! Which decoder reads an asset's bits.
//!
//! A watermark is written for one decoder: its features, whitening and head decide every bit, and
//! the asset's matched head lives in its feature space. Another decoder reads the same images as
//! noise, so a dispute that used whatever decoder the server ships *today* would report "not
//! detected" for every asset marked before an upgrade. The embedding therefore records the
//! decoder's digest ([`digest_of`]: its weights and sidecar) in its report and the service seals
//! it with the key (`store::keys`, migration 0006); a dispute reads each candidate with the
//! decoder of that digest, found among
//!
//! 1. the **current** decoders for its length — `weights_dir/decoder-{bits}.bpk` (and
//!    `decoder-{bits}.coarse.bpk` beside it, when there is one) when the server is configured
//!    with one, else the ones shipped in the binary (what new jobs use: [`Pair`]);
//! 2. the **shipped** ones, when the weights folder overrides them;
//! 3. the **archive**: every `*.bpk` artifact (with its `.json` sidecar) under
//!    `weights_dir/archive/`, where an operator keeps the decoders of earlier releases or
//!    earlier weights folders so that their assets stay verifiable.
//!
//! A digest found nowhere is an answer of its own ([`find`] → `None`), never a silent misread.
//!
//! # The pair a job writes for
//!
//! A length may have two current decoders: the **main** one and a **coarse** one (a lower colour
//! frequency: bolder, more robust changes that cost more of the fidelity budget). The embedding
//! writes for the main one and restarts with the coarse one when the asset leaves the budget
//! free (`embed::pipeline`, `EmbedOptions::coarse_margin_db`); the report and the key name the
//! one it chose. The coarse decoder of an artifact `P` is [`coarse_path`]`(P)`; the shipped
//! ones are `weights/decoder-{bits}.coarse.*` (32 bits only).

use std::path::{Path, PathBuf};

use burn::tensor::Device;

use super::artifact::{
    WatermarkModel, WeightsError, coarse_path, digest_of, shipped_bytes, shipped_coarse_bytes,
    sidecar_path,
};

/// Where a decoder's files are.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Source {
    /// Compiled into the binary for this many bits: the main decoder, or the coarse one.
    Shipped { bits: usize, coarse: bool },
    /// An artifact on disk (decoder weights; the sidecar beside it).
    File(PathBuf),
}

/// A decoder found for a length, with its digest.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Located {
    pub bits: usize,
    pub digest: String,
    pub source: Source,
}

impl Located {
    /// Loads the model; `Mismatch` when its files changed since they were hashed, or it reads
    /// another number of bits.
    pub fn load(&self, device: &Device) -> Result<WatermarkModel, WeightsError> {
        let m = match &self.source {
            Source::Shipped {
                bits,
                coarse: false,
            } => WatermarkModel::shipped(*bits, device)?,
            Source::Shipped { bits, coarse: true } => {
                WatermarkModel::shipped_coarse(*bits, device)?
                    .ok_or(WeightsError::NoShippedWeights { bits: *bits })?
            }
            Source::File(p) => WatermarkModel::load(p, device)?,
        };
        if m.digest() != self.digest || m.bits() != self.bits {
            return Err(WeightsError::Mismatch(format!(
                "the decoder files for {} bits changed while they were being loaded",
                self.bits
            )));
        }
        Ok(m)
    }
}

/// The decoder file for `bits` in the weights folder, when it holds one.
pub fn folder_artifact(weights_dir: Option<&Path>, bits: usize) -> Option<PathBuf> {
    weights_dir
        .map(|d| d.join(format!("decoder-{bits}.bpk")))
        .filter(|p| p.is_file())
}

/// The folder of archived decoders under a weights folder.
pub fn archive_dir(weights_dir: &Path) -> PathBuf {
    weights_dir.join("archive")
}

fn read(p: &Path) -> Result<Vec<u8>, WeightsError> {
    std::fs::read(p).map_err(|source| WeightsError::Io {
        path: p.to_path_buf(),
        source,
    })
}

/// The artifact at `path` with its digest and length (`None` when its sidecar does not say how
/// many bits it reads: not an artifact).
fn locate_file(path: &Path) -> Result<Option<Located>, WeightsError> {
    let decoder = read(path)?;
    let sidecar = read(&sidecar_path(path))?;
    #[derive(serde::Deserialize)]
    struct Bits {
        bits: usize,
    }
    let Ok(Bits { bits }) = serde_json::from_slice::<Bits>(&sidecar) else {
        return Ok(None);
    };
    Ok(Some(Located {
        bits,
        digest: digest_of(&decoder, &sidecar),
        source: Source::File(path.to_path_buf()),
    }))
}

/// The shipped decoder for `bits` (`None` when none is shipped for that length).
fn locate_shipped(bits: usize) -> Option<Located> {
    let (decoder, _, sidecar) = shipped_bytes(bits)?;
    if decoder.is_empty() || sidecar.is_empty() {
        return None;
    }
    Some(Located {
        bits,
        digest: digest_of(decoder, sidecar),
        source: Source::Shipped {
            bits,
            coarse: false,
        },
    })
}

/// The shipped coarse decoder for `bits` (`None` when none is shipped for that length).
fn locate_shipped_coarse(bits: usize) -> Option<Located> {
    let (decoder, sidecar) = shipped_coarse_bytes(bits)?;
    Some(Located {
        bits,
        digest: digest_of(decoder, sidecar),
        source: Source::Shipped { bits, coarse: true },
    })
}

/// The artifact at `p`, which its name says reads `bits` bits.
fn locate_named(p: &Path, bits: usize) -> Result<Located, WeightsError> {
    match locate_file(p)? {
        Some(l) if l.bits == bits => Ok(l),
        Some(l) => Err(WeightsError::Mismatch(format!(
            "{} decodes {} bits, its name says {bits}",
            p.display(),
            l.bits
        ))),
        None => Err(WeightsError::Mismatch(format!(
            "{}: the sidecar does not say how many bits it reads",
            p.display()
        ))),
    }
}

/// The decoder new jobs of `bits` bits use first: the weights folder's, else the shipped one.
pub fn current(weights_dir: Option<&Path>, bits: usize) -> Result<Located, WeightsError> {
    match folder_artifact(weights_dir, bits) {
        Some(p) => locate_named(&p, bits),
        None => locate_shipped(bits).ok_or(if super::artifact::shipped_bytes(bits).is_some() {
            WeightsError::NotShipped { bits }
        } else {
            WeightsError::NoShippedWeights { bits }
        }),
    }
}

/// The coarse decoder new jobs of `bits` bits may switch to (module docs): beside the weights
/// folder's decoder when the folder holds one (`None` when it holds no coarse one: an
/// operator's decoder is never paired with the shipped coarse one), else the shipped one.
pub fn current_coarse(
    weights_dir: Option<&Path>,
    bits: usize,
) -> Result<Option<Located>, WeightsError> {
    match folder_artifact(weights_dir, bits) {
        Some(p) => {
            let c = coarse_path(&p);
            if c.is_file() {
                locate_named(&c, bits).map(Some)
            } else {
                Ok(None)
            }
        }
        None => Ok(locate_shipped_coarse(bits)),
    }
}

/// The decoders an embedding of `bits` bits writes for: the main one and, when there is one,
/// the coarse one it switches to for assets that leave the fidelity budget free
/// (`embed::pipeline::embed`).
#[derive(Clone, Debug)]
pub struct Pair {
    pub main: WatermarkModel,
    pub coarse: Option<WatermarkModel>,
}

impl Pair {
    /// One decoder and no alternative (the paper's recipe; `--weights` files without a coarse
    /// decoder beside them).
    pub fn single(main: WatermarkModel) -> Self {
        Self { main, coarse: None }
    }

    /// The decoders for `bits` bits from the artifact `main` (its [`coarse_path`] beside it,
    /// when there is one), or the shipped ones when `main` is `None`.
    pub fn resolve(
        main: Option<&Path>,
        bits: usize,
        device: &Device,
    ) -> Result<Self, WeightsError> {
        let m = WatermarkModel::resolve(main, bits, device)?;
        let coarse = match main {
            Some(p) => {
                let c = coarse_path(p);
                if c.is_file() {
                    Some(WatermarkModel::resolve(Some(&c), bits, device)?)
                } else {
                    None
                }
            }
            None => WatermarkModel::shipped_coarse(bits, device)?,
        };
        Ok(Self { main: m, coarse })
    }

    /// The decoder of this pair whose digest is `digest` (an embedding report's `decoder`).
    pub fn by_digest(&self, digest: &str) -> Option<&WatermarkModel> {
        std::iter::once(&self.main)
            .chain(&self.coarse)
            .find(|m| m.digest() == digest)
    }
}

/// The decoder for `bits` bits whose digest is `digest`: the current one, the shipped one or an
/// archived one (module docs), or `None` when this server holds none. Archive files that are
/// not artifacts (no sidecar, or one without a length) are passed over; one that cannot be read
/// is an error.
pub fn find(
    weights_dir: Option<&Path>,
    bits: usize,
    digest: &str,
) -> Result<Option<Located>, WeightsError> {
    if let Ok(l) = current(weights_dir, bits)
        && l.digest == digest
    {
        return Ok(Some(l));
    }
    if let Ok(Some(l)) = current_coarse(weights_dir, bits)
        && l.digest == digest
    {
        return Ok(Some(l));
    }
    if let Some(l) = locate_shipped(bits)
        .into_iter()
        .chain(locate_shipped_coarse(bits))
        .find(|l| l.digest == digest)
    {
        return Ok(Some(l));
    }
    let Some(dir) = weights_dir.map(archive_dir).filter(|d| d.is_dir()) else {
        return Ok(None);
    };
    let entries = std::fs::read_dir(&dir).map_err(|source| WeightsError::Io {
        path: dir.clone(),
        source,
    })?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.ends_with(".bpk") && !name.ends_with(".encoder.bpk") && p.is_file()
        })
        .filter(|p| sidecar_path(p).is_file())
        .collect();
    paths.sort();
    for p in paths {
        if let Some(l) = locate_file(&p)?
            && l.bits == bits
            && l.digest == digest
        {
            return Ok(Some(l));
        }
    }
    Ok(None)
}

/// The decoders a set of registered keys need, and whether this server holds each.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct InUse {
    pub bits: usize,
    /// The digest the keys name; `None` for keys registered before digests were recorded
    /// (read with the current decoder).
    pub digest: Option<String>,
    /// How many keys name it.
    pub keys: usize,
    /// Where this server finds it: `shipped`, a file's path, or `None` when it holds none.
    pub held: Option<String>,
    /// Whether it is one of the decoders new jobs of its length use (the main or the coarse
    /// one).
    pub current: bool,
}

/// Groups keys (their length and recorded digest) by decoder and looks each one up (module
/// docs); sorted by length, then digest.
pub fn survey<'a>(
    weights_dir: Option<&Path>,
    keys: impl IntoIterator<Item = (usize, Option<&'a str>)>,
) -> Result<Vec<InUse>, WeightsError> {
    let mut counts: std::collections::BTreeMap<(usize, Option<&str>), usize> = Default::default();
    for k in keys {
        *counts.entry(k).or_default() += 1;
    }
    counts
        .into_iter()
        .map(|((bits, digest), keys)| {
            let cur = current(weights_dir, bits).ok();
            let cur_coarse = current_coarse(weights_dir, bits).ok().flatten();
            let located = match digest {
                Some(d) => find(weights_dir, bits, d)?,
                None => cur.clone(),
            };
            let is_current =
                |l: &Located| cur.iter().chain(&cur_coarse).any(|c| c.digest == l.digest);
            Ok(InUse {
                bits,
                digest: digest.map(str::to_string),
                keys,
                held: located.as_ref().map(|l| match &l.source {
                    Source::Shipped { coarse: false, .. } => "shipped".to_string(),
                    Source::Shipped { coarse: true, .. } => "shipped (coarse)".to_string(),
                    Source::File(p) => p.display().to_string(),
                }),
                current: located.as_ref().is_some_and(is_current),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Writes the shipped 32-bit artifact to `dir/name.bpk` with its sidecar, `edit` applied to
    /// the sidecar's JSON (a different sidecar is a different decoder).
    fn write_shipped(dir: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
        let (decoder, _, sidecar) = shipped_bytes(32).expect("shipped");
        let mut json: serde_json::Value = serde_json::from_slice(sidecar).expect("json");
        edit(&mut json);
        std::fs::create_dir_all(dir).expect("dir");
        let p = dir.join(format!("{name}.bpk"));
        std::fs::write(&p, decoder).expect("write");
        std::fs::write(sidecar_path(&p), serde_json::to_vec(&json).expect("json")).expect("write");
        p
    }

    #[test]
    fn a_digest_is_found_where_the_decoder_is_and_nowhere_else() {
        let shipped = current(None, 32).expect("shipped 32");
        assert_eq!(
            shipped.source,
            Source::Shipped {
                bits: 32,
                coarse: false
            }
        );
        assert_eq!(shipped.digest.len(), 64);
        // The loaded model knows its own digest.
        let m = shipped.load(&Device::flex()).expect("load");
        assert_eq!(m.digest(), shipped.digest);
        assert_eq!(
            find(None, 32, &shipped.digest).unwrap(),
            Some(shipped.clone())
        );
        // Another length's decoder, or an unknown digest, is not found.
        assert_eq!(find(None, 48, &shipped.digest).unwrap(), None);
        assert_eq!(find(None, 32, &"0".repeat(64)).unwrap(), None);

        // A weights folder overriding 32 bits: it becomes current, the shipped one stays found.
        let dir = tempfile::tempdir().expect("tempdir");
        let own = write_shipped(dir.path(), "decoder-32", |j| j["note"] = "ours".into());
        let cur = current(Some(dir.path()), 32).expect("current");
        assert_eq!(cur.source, Source::File(own));
        assert_ne!(cur.digest, shipped.digest);
        assert_eq!(
            find(Some(dir.path()), 32, &cur.digest).unwrap(),
            Some(cur.clone())
        );
        assert_eq!(
            find(Some(dir.path()), 32, &shipped.digest).unwrap(),
            Some(shipped.clone())
        );

        // An archived decoder is found by its digest; an encoder file or a file without a
        // sidecar beside it is passed over.
        let arch = archive_dir(dir.path());
        let old = write_shipped(&arch, "2026-11", |j| j["note"] = "last month".into());
        std::fs::write(arch.join("stray.bpk"), b"no sidecar").expect("write");
        std::fs::write(arch.join("2026-11.encoder.bpk"), b"").expect("write");
        let old_digest = {
            let d = std::fs::read(&old).unwrap();
            let s = std::fs::read(sidecar_path(&old)).unwrap();
            digest_of(&d, &s)
        };
        let found = find(Some(dir.path()), 32, &old_digest)
            .unwrap()
            .expect("archived");
        assert_eq!(found.source, Source::File(old.clone()));
        let m = found.load(&Device::flex()).expect("load");
        assert_eq!(m.digest(), old_digest);
        // Not for another length.
        assert_eq!(find(Some(dir.path()), 64, &old_digest).unwrap(), None);

        // What the keys need: two keys of the archived decoder, one of the shipped one, one
        // from before digests were recorded, one of a decoder nowhere to be found.
        let unknown = "f".repeat(64);
        let keys = [
            (32, Some(old_digest.as_str())),
            (32, Some(shipped.digest.as_str())),
            (32, None),
            (32, Some(old_digest.as_str())),
            (48, Some(unknown.as_str())),
        ];
        let s = survey(Some(dir.path()), keys).unwrap();
        let row = |d: Option<&str>| s.iter().find(|r| r.digest.as_deref() == d).unwrap();
        assert_eq!(s.len(), 4);
        assert_eq!(row(Some(&old_digest)).keys, 2);
        assert_eq!(row(Some(&old_digest)).held, Some(old.display().to_string()));
        assert!(!row(Some(&old_digest)).current);
        assert_eq!(row(Some(&shipped.digest)).held.as_deref(), Some("shipped"));
        assert!(row(None).current && row(None).held.is_some());
        assert_eq!(
            (row(Some(&unknown)).held.as_ref(), row(Some(&unknown)).bits),
            (None, 48)
        );

        // A file changed after it was found is refused rather than read as another decoder.
        std::fs::write(sidecar_path(&old), b"{\"format\":\"splatmark-decoder/1\"}").unwrap();
        assert!(matches!(
            found.load(&Device::flex()),
            Err(WeightsError::Json { .. } | WeightsError::Mismatch(_))
        ));
    }

    #[test]
    fn the_coarse_decoder_pairs_with_its_main_one_and_is_found_by_digest() {
        let device = Device::flex();
        let main = current(None, 32).expect("shipped 32");
        let coarse = current_coarse(None, 32)
            .expect("readable")
            .expect("a coarse decoder is shipped for 32 bits");
        assert_eq!(
            coarse.source,
            Source::Shipped {
                bits: 32,
                coarse: true
            }
        );
        assert_ne!(coarse.digest, main.digest);
        assert_eq!(
            find(None, 32, &coarse.digest).unwrap(),
            Some(coarse.clone())
        );
        assert_eq!(coarse.load(&device).expect("load").digest(), coarse.digest);
        // None for the lengths it was not measured at.
        assert_eq!(current_coarse(None, 48).unwrap(), None);
        let pair = Pair::resolve(None, 32, &device).expect("pair");
        assert_eq!(pair.main.digest(), main.digest);
        let c = pair.coarse.as_ref().expect("coarse");
        assert_eq!(c.digest(), coarse.digest);
        assert_eq!(
            pair.by_digest(&coarse.digest).map(|m| m.digest()),
            Some(coarse.digest.clone())
        );
        assert!(pair.by_digest(&"0".repeat(64)).is_none());
        assert!(Pair::resolve(None, 48, &device).unwrap().coarse.is_none());

        // A weights folder with its own main decoder and none beside it: no coarse one (the
        // shipped coarse decoder is not paired with an operator's), though the shipped one is
        // still found for the assets written with it.
        let dir = tempfile::tempdir().expect("tempdir");
        let own = write_shipped(dir.path(), "decoder-32", |j| j["note"] = "ours".into());
        assert_eq!(current_coarse(Some(dir.path()), 32).unwrap(), None);
        assert!(
            Pair::resolve(Some(&own), 32, &device)
                .unwrap()
                .coarse
                .is_none()
        );
        assert_eq!(
            find(Some(dir.path()), 32, &coarse.digest).unwrap(),
            Some(coarse.clone())
        );
        // With one beside it, that one.
        let own_coarse = write_shipped(dir.path(), "decoder-32.coarse", |j| {
            j["note"] = "ours, coarse".into()
        });
        assert_eq!(own_coarse, coarse_path(&own));
        let cur = current_coarse(Some(dir.path()), 32)
            .unwrap()
            .expect("folder's coarse");
        assert_eq!(cur.source, Source::File(own_coarse.clone()));
        let pair = Pair::resolve(Some(&own), 32, &device).unwrap();
        assert_eq!(
            pair.coarse.as_ref().map(|m| m.digest()),
            Some(cur.digest.clone())
        );
        // Both count as current for the keys' survey.
        let s = survey(Some(dir.path()), [(32, Some(cur.digest.as_str()))]).unwrap();
        assert!(s[0].current);
        assert_eq!(s[0].held, Some(own_coarse.display().to_string()));
    }
}
