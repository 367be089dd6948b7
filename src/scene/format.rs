//! Scene file formats: detection, limits and dispatch to the readers.
//!
//! Five formats are read, each into the same [`Gaussians`] (INRIA conventions, see
//! `gaussians.rs`):
//!
//! | format | module | recognised by |
//! |---|---|---|
//! | INRIA 3D-GS PLY (ascii, binary LE/BE) | [`ply`](crate::scene::ply) | `ply\n` magic |
//! | SuperSplat / PlayCanvas compressed PLY | [`compressed_ply`](crate::scene::compressed_ply) | `ply\n` magic + `chunk` element + `packed_position` |
//! | antimatter15 `.splat` | [`splat`](crate::scene::splat) | `.splat` extension, size a multiple of 32 (no magic) |
//! | Niantic `.spz` | [`spz`](crate::scene::spz) | gzip (`1f 8b`), zstd (`28 b5 2f fd`) or `NGSP` magic |
//! | PlayCanvas SOG, bundled `.sog` | [`sog`](crate::scene::sog) | ZIP magic (`PK 03 04`) and a `meta.json` entry, or the `.sog` extension |
//! | PlayCanvas SOG, unbundled | [`sog`](crate::scene::sog) | a path ([`read_scene_path`]): a directory holding `meta.json`, or a `.json` file |
//!
//! Every format but SOG is also written ([`write_scene`]): INRIA binary little-endian PLY
//! losslessly ([`write_ply`]), the other three with their own quantisation; SOG is read-only
//! ([`Format::is_writable`]).
//!
//! Every reader checks sizes against the file and the [`Limits`] before it allocates per-Gaussian
//! storage, uses checked arithmetic on header-declared sizes, and returns a typed [`SceneError`]
//! (never a panic) for malformed input.

use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::scene::{Gaussians, SceneError, normalize_quat};

/// A scene file format.
///
/// Its name ([`Format::as_str`], the serde name) is the one stored in the database
/// (`assets.format`) and shown in the API and in `splatmark info`: `ply`, `compressed_ply`,
/// `splat`, `spz`, `sog`. [`Format::parse`] and serde also accept `compressedply`, the name earlier
/// versions printed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// INRIA 3D Gaussian Splatting PLY (`point_cloud.ply`), ascii or binary.
    Ply,
    /// SuperSplat / PlayCanvas compressed PLY (`*.compressed.ply`).
    #[serde(rename = "compressed_ply", alias = "compressedply")]
    CompressedPly,
    /// antimatter15 `.splat` (32 bytes per Gaussian, no header).
    Splat,
    /// Niantic `.spz` (versions 2 and 3 gzip, version 4 NGSP/zstd).
    Spz,
    /// PlayCanvas SOG (`meta.json` + WebP images, bundled as a ZIP `.sog`); read-only.
    Sog,
}

impl Format {
    /// Every format, in the order of the table above.
    pub const ALL: [Format; 5] = [
        Format::Ply,
        Format::CompressedPly,
        Format::Splat,
        Format::Spz,
        Format::Sog,
    ];

    /// The canonical name, used in JSON, logs and the database (same as the serde name).
    pub const fn as_str(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::CompressedPly => "compressed_ply",
            Format::Splat => "splat",
            Format::Spz => "spz",
            Format::Sog => "sog",
        }
    }

    /// Whether [`write_scene`] writes this format (every one but SOG).
    pub const fn is_writable(self) -> bool {
        !matches!(self, Format::Sog)
    }

    /// The format a name denotes: the canonical [`Format::as_str`] names, and `compressedply`
    /// (the name earlier versions printed) for [`Format::CompressedPly`].
    pub fn parse(name: &str) -> Option<Format> {
        match name {
            "compressedply" => Some(Format::CompressedPly),
            _ => Format::ALL.into_iter().find(|f| f.as_str() == name),
        }
    }

    /// The usual file extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::CompressedPly => "compressed.ply",
            Format::Splat => "splat",
            Format::Spz => "spz",
            Format::Sog => "sog",
        }
    }

    /// The format a file name asks for by its extension (case-insensitive): `.compressed.ply`,
    /// `.ply`, `.splat`, `.spz`, `.sog`; `None` for anything else.
    pub fn from_path(path: &Path) -> Option<Format> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        [
            Format::CompressedPly,
            Format::Ply,
            Format::Splat,
            Format::Spz,
            Format::Sog,
        ]
        .into_iter()
        .find(|f| name.ends_with(&format!(".{}", f.extension())))
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Resource limits applied while reading untrusted scene files (serde: missing fields take the
/// defaults).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct Limits {
    /// Largest number of Gaussians a file may declare (checked before allocating).
    pub max_gaussians: usize,
    /// Largest file size in bytes accepted by [`read_scene`] / [`read_scene_bytes`]; `None` = no limit.
    pub max_file_bytes: Option<u64>,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_gaussians: 10_000_000,
            max_file_bytes: None,
        }
    }
}

impl Limits {
    /// Checks a declared Gaussian count against [`Limits::max_gaussians`] and converts it to `usize`.
    pub fn check_count(&self, count: u64) -> Result<usize, SceneError> {
        match usize::try_from(count) {
            Ok(n) if n <= self.max_gaussians => Ok(n),
            _ => Err(SceneError::TooManyGaussians {
                count,
                max: self.max_gaussians,
            }),
        }
    }

    /// Checks a file size against [`Limits::max_file_bytes`].
    pub fn check_file_size(&self, size: u64) -> Result<(), SceneError> {
        match self.max_file_bytes {
            Some(max) if size > max => Err(SceneError::FileTooLarge { size, max }),
            _ => Ok(()),
        }
    }
}

/// gzip member magic (legacy `.spz`, versions 1–3).
const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
/// zstd frame magic.
const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];
/// Raw (uncompressed) Niantic header magic, `0x5053474e` little-endian.
pub(crate) const NGSP_MAGIC: [u8; 4] = *b"NGSP";

/// Decides the format of `bytes`, by content first and by the extension hint for `.splat`
/// (which has no magic). `hint_ext` may be `"splat"`, `".splat"` or a whole file name.
///
/// PLY files are told apart (INRIA vs compressed) from their header, which is parsed here;
/// header errors are returned as they are. A ZIP archive is a bundled SOG when its central
/// directory (at its end: `bytes` must be the whole file) lists `meta.json`, or when the hint is
/// `.sog` (the reader then says what is wrong with it).
pub fn detect_format(bytes: &[u8], hint_ext: Option<&str>) -> Result<Format, SceneError> {
    if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
        let header = crate::scene::ply::parse_header(bytes)?;
        return Ok(if crate::scene::compressed_ply::is_compressed(&header) {
            Format::CompressedPly
        } else {
            Format::Ply
        });
    }
    if bytes.starts_with(&GZIP_MAGIC)
        || bytes.starts_with(&ZSTD_MAGIC)
        || bytes.starts_with(&NGSP_MAGIC)
    {
        return Ok(Format::Spz);
    }
    if bytes.starts_with(&crate::scene::zip::LOCAL_MAGIC) {
        if hint_is(hint_ext, "sog") || crate::scene::sog::is_bundle(bytes) {
            return Ok(Format::Sog);
        }
        return Err(SceneError::UnknownFormat(
            "a ZIP archive without meta.json at its root (a bundled SOG holds meta.json and its \
             images)"
                .into(),
        ));
    }
    if hint_is(hint_ext, "splat") {
        // The splat reader reports a size that is not a multiple of 32 as a typed error.
        return Ok(Format::Splat);
    }
    let shown: Vec<String> = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
    Err(SceneError::UnknownFormat(format!(
        "no PLY, gzip, zstd, NGSP or ZIP magic (first bytes: {}){}",
        if shown.is_empty() {
            "none, the file is empty".to_string()
        } else {
            shown.join(" ")
        },
        match hint_ext {
            Some(h) => format!(", and extension hint '{h}' is not .splat"),
            None => String::new(),
        }
    )))
}

/// Whether an extension hint (`"splat"`, `".splat"`, `"scene.SPLAT"`) names extension `ext`.
fn hint_is(hint: Option<&str>, ext: &str) -> bool {
    let Some(h) = hint else { return false };
    let tail = h.rsplit('.').next().unwrap_or(h);
    tail.eq_ignore_ascii_case(ext)
}

/// Reads a scene file: checks its size against `limits.max_file_bytes` first (from the
/// file's metadata, before reading it), then detects the format and decodes it. See
/// [`read_scene_path`] for the paths taken.
pub fn read_scene(path: impl AsRef<Path>, limits: &Limits) -> Result<Gaussians, SceneError> {
    read_scene_path(path.as_ref(), limits).map(|(_, g)| g)
}

/// Reads the scene at `path`, returning its format too: an unbundled SOG when `path` is a
/// directory (its `meta.json`) or a `.json` file (`meta.json`, the images beside it; each file's
/// size checked against `limits.max_file_bytes`), otherwise a scene file as [`read_scene_bytes`]
/// reads it, its size checked before it is read.
pub fn read_scene_path(path: &Path, limits: &Limits) -> Result<(Format, Gaussians), SceneError> {
    if let Some(meta) = crate::scene::sog::meta_path(path) {
        return Ok((
            Format::Sog,
            crate::scene::sog::read_unbundled(&meta, limits)?,
        ));
    }
    let io_err = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let meta = std::fs::metadata(path).map_err(io_err)?;
    limits.check_file_size(meta.len())?;
    let bytes = std::fs::read(path).map_err(io_err)?;
    let ext = path.extension().and_then(|e| e.to_str());
    read_scene_bytes_detect(&bytes, ext, limits)
}

/// Decodes a scene held in memory. `hint_ext` is the file's extension (or name), used only to
/// recognise `.splat`, which has no magic number, and a `.sog` whose directory is damaged.
pub fn read_scene_bytes(
    bytes: &[u8],
    hint_ext: Option<&str>,
    limits: &Limits,
) -> Result<Gaussians, SceneError> {
    read_scene_bytes_detect(bytes, hint_ext, limits).map(|(_, g)| g)
}

/// Like [`read_scene_bytes`], also returning the detected format.
pub fn read_scene_bytes_detect(
    bytes: &[u8],
    hint_ext: Option<&str>,
    limits: &Limits,
) -> Result<(Format, Gaussians), SceneError> {
    limits.check_file_size(bytes.len() as u64)?;
    let format = detect_format(bytes, hint_ext)?;
    let g = read_as(bytes, format, limits)?;
    Ok((format, g))
}

/// Decodes `bytes` as the given format (no detection).
pub fn read_as(bytes: &[u8], format: Format, limits: &Limits) -> Result<Gaussians, SceneError> {
    limits.check_file_size(bytes.len() as u64)?;
    let g = match format {
        Format::Ply | Format::CompressedPly => crate::scene::ply::read(bytes, limits)?,
        Format::Splat => crate::scene::splat::read(bytes, limits)?,
        Format::Spz => crate::scene::spz::read(bytes, limits)?,
        Format::Sog => crate::scene::sog::read(bytes, limits)?,
    };
    debug_assert!(g.validate().is_ok());
    Ok(g)
}

/// Writes `g` (validated first) in `format`: [`write_ply`] (lossless), or one of the
/// quantised formats viewers load ([`compressed_ply::encode`](crate::scene::compressed_ply::encode),
/// [`splat::encode`](crate::scene::splat::encode), [`spz::encode`](crate::scene::spz::encode):
/// each documents what it rounds). SOG is not written: [`SceneError::Unsupported`] with
/// [`sog::READ_ONLY`](crate::scene::sog::READ_ONLY).
pub fn write_scene<W: Write>(
    g: &Gaussians,
    format: Format,
    mut writer: W,
) -> Result<(), SceneError> {
    use crate::scene::{compressed_ply, splat, spz};
    g.validate()?;
    let bytes = match format {
        Format::Ply => return crate::scene::ply::write(g, writer),
        Format::CompressedPly => compressed_ply::encode(g),
        Format::Splat => splat::encode(g),
        Format::Spz => spz::encode(g)?,
        Format::Sog => {
            return Err(SceneError::Unsupported(
                crate::scene::sog::READ_ONLY.to_string(),
            ));
        }
    };
    writer.write_all(&bytes).map_err(SceneError::IoPlain)?;
    writer.flush().map_err(SceneError::IoPlain)
}

/// Writes `g` as an INRIA binary little-endian PLY that INRIA's loader, SuperSplat and Spark open
/// (property order `x y z nx ny nz f_dc_0..2 f_rest_0..N-1 opacity scale_0..2 rot_0..3`, all
/// `float`, normals 0). The scene is validated first. Reading the file back gives `g` bit for bit.
pub fn write_ply<W: Write>(g: &Gaussians, writer: W) -> Result<(), SceneError> {
    crate::scene::ply::write(g, writer)
}

/// Accumulates decoded Gaussians, checking each one as it is added (the checks every reader
/// shares): all values finite, quaternion normalised with [`normalize_quat`].
pub(crate) struct GaussianBuilder {
    g: Gaussians,
}

/// One decoded Gaussian before it is checked; `rest` is `[k][c]` (see [`Gaussians`]).
pub(crate) struct RawGaussian<'a> {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    /// `(w, x, y, z)`, not necessarily normalised.
    pub rotation: [f32; 4],
    pub opacity: f32,
    pub dc: [f32; 3],
    pub rest: &'a [f32],
}

/// Largest log-scale a scene may hold: e^40 ≈ 2·10¹⁷ scene units, whose square (the
/// covariance) still fits in an f32; real scenes hold about −15 to 5.
pub const MAX_LOG_SCALE: f32 = 40.0;

impl GaussianBuilder {
    /// Room for `n` Gaussians of SH degree `sh_degree` (the caller has checked `n` against the
    /// limits and the file size).
    pub fn new(n: usize, sh_degree: u8) -> Self {
        Self {
            g: Gaussians::with_capacity(n, sh_degree),
        }
    }

    /// Checks and appends one Gaussian.
    pub fn push(&mut self, r: RawGaussian<'_>) -> Result<(), SceneError> {
        let index = self.g.len();
        let finite = |v: &[f32], field: &'static str| {
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(SceneError::NonFinite { index, field })
            }
        };
        finite(&r.mean, "position")?;
        finite(&r.log_scale, "scale")?;
        if let Some(&v) = r.log_scale.iter().find(|&&v| v > MAX_LOG_SCALE) {
            return Err(SceneError::Corrupt(format!(
                "Gaussian {index}: log-scale {v} is above {MAX_LOG_SCALE} (its covariance would \
                 overflow)"
            )));
        }
        finite(&r.rotation, "rotation")?;
        finite(std::slice::from_ref(&r.opacity), "opacity")?;
        finite(&r.dc, "f_dc")?;
        finite(r.rest, "f_rest")?;
        if r.rest.len() != self.g.rest_len() {
            return Err(SceneError::Inconsistent(format!(
                "Gaussian {index} has {} f_rest values, expected {}",
                r.rest.len(),
                self.g.rest_len()
            )));
        }
        let q = normalize_quat(r.rotation).ok_or(SceneError::ZeroQuaternion { index })?;
        self.g.means.push(r.mean);
        self.g.log_scales.push(r.log_scale);
        self.g.rotations.push(q);
        self.g.opacity_logits.push(r.opacity);
        self.g.sh_dc.push(r.dc);
        self.g.sh_rest.extend_from_slice(r.rest);
        Ok(())
    }

    /// The finished scene.
    pub fn finish(self) -> Gaussians {
        self.g
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{SH_C0, sigmoid};
    use std::path::PathBuf;

    fn data_dir() -> PathBuf {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"))
    }

    /// Returns the path if the real-data file exists, printing a loud SKIPPED line otherwise.
    fn real(rel: &str) -> Option<PathBuf> {
        let p = data_dir().join(rel);
        if p.is_file() {
            Some(p)
        } else {
            eprintln!("SKIPPED: real-data test, {} missing", p.display());
            None
        }
    }

    fn assert_bits_eq(a: &Gaussians, b: &Gaussians) {
        assert_eq!(a.len(), b.len());
        assert_eq!(a.sh_degree, b.sh_degree);
        let bits = |g: &Gaussians| -> Vec<u32> {
            let mut v = Vec::new();
            for i in 0..g.len() {
                v.extend(g.means[i].iter().map(|x| x.to_bits()));
                v.extend(g.log_scales[i].iter().map(|x| x.to_bits()));
                v.extend(g.rotations[i].iter().map(|x| x.to_bits()));
                v.push(g.opacity_logits[i].to_bits());
                v.extend(g.sh_dc[i].iter().map(|x| x.to_bits()));
            }
            v.extend(g.sh_rest.iter().map(|x| x.to_bits()));
            v
        };
        assert!(bits(a) == bits(b), "scenes differ bitwise");
    }

    #[test]
    fn format_serde_names() {
        assert_eq!(serde_json::to_string(&Format::Ply).unwrap(), "\"ply\"");
        assert_eq!(
            serde_json::to_string(&Format::CompressedPly).unwrap(),
            "\"compressed_ply\""
        );
        // The name earlier versions wrote is still read.
        assert_eq!(
            serde_json::from_str::<Format>("\"compressedply\"").unwrap(),
            Format::CompressedPly
        );
        assert_eq!(Format::parse("compressedply"), Some(Format::CompressedPly));
        assert_eq!(Format::parse("compressed_ply"), Some(Format::CompressedPly));
        assert_eq!(Format::parse("PLY"), None);
        assert_eq!(Format::parse(""), None);
        assert_eq!(serde_json::to_string(&Format::Splat).unwrap(), "\"splat\"");
        assert_eq!(serde_json::to_string(&Format::Spz).unwrap(), "\"spz\"");
        assert_eq!(serde_json::to_string(&Format::Sog).unwrap(), "\"sog\"");
        for f in Format::ALL {
            let s = serde_json::to_string(&f).unwrap();
            assert_eq!(s, format!("\"{}\"", f.as_str()));
            assert_eq!(serde_json::from_str::<Format>(&s).unwrap(), f);
            assert_eq!(Format::parse(f.as_str()), Some(f));
        }
    }

    #[test]
    fn limits_default() {
        let l = Limits::default();
        assert_eq!(l.max_gaussians, 10_000_000);
        assert_eq!(l.max_file_bytes, None);
        assert!(matches!(
            l.check_count(10_000_001),
            Err(SceneError::TooManyGaussians {
                count: 10_000_001,
                max: 10_000_000
            })
        ));
        assert_eq!(l.check_count(3).unwrap(), 3);
        let parsed: Limits = serde_json::from_str(r#"{"max_file_bytes": 5}"#).unwrap();
        assert_eq!(
            parsed,
            Limits {
                max_file_bytes: Some(5),
                ..Limits::default()
            }
        );
    }

    #[test]
    fn detection_by_content_and_hint() {
        let ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n";
        assert_eq!(detect_format(ply, None).unwrap(), Format::Ply);
        let crlf =
            b"ply\r\nformat ascii 1.0\r\nelement vertex 0\r\nproperty float x\r\nend_header\r\n";
        assert_eq!(detect_format(crlf, None).unwrap(), Format::Ply);
        let cply = b"ply\nformat binary_little_endian 1.0\nelement chunk 0\nproperty float min_x\n\
element vertex 0\nproperty uint packed_position\nend_header\n";
        assert_eq!(detect_format(cply, None).unwrap(), Format::CompressedPly);
        assert_eq!(
            detect_format(&[0x1f, 0x8b, 8, 0], None).unwrap(),
            Format::Spz
        );
        assert_eq!(
            detect_format(&[0x28, 0xb5, 0x2f, 0xfd, 0], None).unwrap(),
            Format::Spz
        );
        assert_eq!(detect_format(b"NGSP\x04\0\0\0", None).unwrap(), Format::Spz);
        assert_eq!(
            detect_format(&[0u8; 64], Some("splat")).unwrap(),
            Format::Splat
        );
        assert_eq!(
            detect_format(&[0u8; 64], Some(".SPLAT")).unwrap(),
            Format::Splat
        );
        assert_eq!(
            detect_format(&[0u8; 64], Some("scene.splat")).unwrap(),
            Format::Splat
        );
        assert!(matches!(
            detect_format(&[0u8; 64], None),
            Err(SceneError::UnknownFormat(_))
        ));
        assert!(matches!(
            detect_format(&[0u8; 64], Some("ply")),
            Err(SceneError::UnknownFormat(_))
        ));
        assert!(matches!(
            detect_format(b"", None),
            Err(SceneError::UnknownFormat(_))
        ));
        // Content wins over the hint.
        assert_eq!(detect_format(ply, Some("splat")).unwrap(), Format::Ply);
    }

    #[test]
    fn unknown_format_error_message() {
        let e = read_scene_bytes(b"hello world", Some("txt"), &Limits::default()).unwrap_err();
        assert!(matches!(e, SceneError::UnknownFormat(_)));
        let msg = e.to_string();
        assert!(msg.contains("68 65 6c 6c"), "{msg}");
    }

    #[test]
    fn splat_with_bad_length_is_typed_error() {
        let e = read_scene_bytes(&[0u8; 33], Some("splat"), &Limits::default()).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
    }

    #[test]
    fn max_file_bytes_enforced() {
        let limits = Limits {
            max_file_bytes: Some(10),
            ..Limits::default()
        };
        let e = read_scene_bytes(&[0u8; 64], Some("splat"), &limits).unwrap_err();
        assert!(
            matches!(e, SceneError::FileTooLarge { size: 64, max: 10 }),
            "{e}"
        );

        let dir =
            std::env::temp_dir().join(format!("splatmark-format-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("big.splat");
        std::fs::write(&path, [0u8; 64]).unwrap();
        let e = read_scene(&path, &limits).unwrap_err();
        assert!(
            matches!(e, SceneError::FileTooLarge { size: 64, max: 10 }),
            "{e}"
        );
        let e = read_scene(dir.join("missing.ply"), &limits).unwrap_err();
        assert!(matches!(e, SceneError::Io { .. }), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn builder_rejects_bad_values() {
        let ok = RawGaussian {
            mean: [0.0; 3],
            log_scale: [0.0; 3],
            rotation: [2.0, 0.0, 0.0, 0.0],
            opacity: 0.0,
            dc: [0.0; 3],
            rest: &[],
        };
        let mut b = GaussianBuilder::new(1, 0);
        b.push(RawGaussian { ..ok }).unwrap();
        assert_eq!(b.finish().rotations[0], [1.0, 0.0, 0.0, 0.0]);
        let mut b = GaussianBuilder::new(1, 0);
        let e = b
            .push(RawGaussian {
                rotation: [0.0; 4],
                ..ok
            })
            .unwrap_err();
        assert!(matches!(e, SceneError::ZeroQuaternion { index: 0 }));
        let e = b
            .push(RawGaussian {
                opacity: f32::NAN,
                ..ok
            })
            .unwrap_err();
        assert!(matches!(
            e,
            SceneError::NonFinite {
                index: 0,
                field: "opacity"
            }
        ));
        let e = b
            .push(RawGaussian {
                mean: [0.0, f32::INFINITY, 0.0],
                ..ok
            })
            .unwrap_err();
        assert!(matches!(
            e,
            SceneError::NonFinite {
                index: 0,
                field: "position"
            }
        ));
        let e = b.push(RawGaussian { rest: &[1.0], ..ok }).unwrap_err();
        assert!(matches!(e, SceneError::Inconsistent(_)));
    }

    // ---- real data --------------------------------------------------------------------------

    #[test]
    fn real_udon_inria_sh3_with_normals_roundtrip() {
        let Some(path) = real("scenes/udon/point_cloud.ply") else {
            return;
        };
        let limits = Limits::default();
        let g = read_scene(&path, &limits).unwrap();
        assert_eq!(g.len(), 2153);
        assert_eq!(g.sh_degree, 3);
        g.validate().unwrap();

        // The f_rest layout: ours is [i][k][c], INRIA's file is f_rest_{c*15+k}.
        let raw = std::fs::read(&path).unwrap();
        let header = crate::scene::ply::parse_header(&raw).unwrap();
        let stride = header.elements[0].row_bytes;
        let f = |i: usize, prop: usize| {
            let o = header.data_offset + i * stride + prop * 4;
            f32::from_le_bytes([raw[o], raw[o + 1], raw[o + 2], raw[o + 3]])
        };
        for i in [0, 1, 1000, 2152] {
            assert_eq!(g.means[i], [f(i, 0), f(i, 1), f(i, 2)]);
            assert_eq!(g.sh_dc[i], [f(i, 6), f(i, 7), f(i, 8)]);
            for k in 0..15 {
                for c in 0..3 {
                    assert_eq!(
                        g.rest_of(i)[k * 3 + c].to_bits(),
                        f(i, 9 + c * 15 + k).to_bits()
                    );
                }
            }
            assert_eq!(g.opacity_logits[i], f(i, 54));
            assert_eq!(g.log_scales[i], [f(i, 55), f(i, 56), f(i, 57)]);
        }

        // read -> write -> read is bit-exact, and write -> read -> write gives identical bytes.
        let mut bytes = Vec::new();
        write_ply(&g, &mut bytes).unwrap();
        let g2 = read_scene_bytes(&bytes, Some("ply"), &limits).unwrap();
        assert_bits_eq(&g, &g2);
        assert_eq!(g, g2);
        let mut bytes2 = Vec::new();
        write_ply(&g2, &mut bytes2).unwrap();
        assert!(bytes == bytes2, "second write differs");
        // Same size as INRIA's own file (same properties, normals included).
        assert_eq!(bytes.len(), raw.len());
    }

    #[test]
    fn real_donut_sh0_without_normals() {
        let Some(path) = real("scenes/donut/fused.ply") else {
            return;
        };
        let g = read_scene(&path, &Limits::default()).unwrap();
        assert_eq!(g.len(), 45_624);
        assert_eq!(g.sh_degree, 0);
        assert!(g.sh_rest.is_empty());
        g.validate().unwrap();
        let mut bytes = Vec::new();
        write_ply(&g, &mut bytes).unwrap();
        let g2 = read_scene_bytes(&bytes, None, &Limits::default()).unwrap();
        assert_bits_eq(&g, &g2);
        // Limits are enforced on real files too.
        let small = Limits {
            max_gaussians: 1000,
            ..Limits::default()
        };
        assert!(matches!(
            read_scene(&path, &small),
            Err(SceneError::TooManyGaussians {
                count: 45_624,
                max: 1000
            })
        ));
    }

    #[test]
    fn real_plant_splat() {
        let Some(path) = real("scenes/plant/plant.splat") else {
            return;
        };
        let g = read_scene(&path, &Limits::default()).unwrap();
        assert_eq!(g.len(), 113_648);
        assert_eq!(g.sh_degree, 0);
        g.validate().unwrap();
        // Colours decode back into the byte range they came from.
        let raw = std::fs::read(&path).unwrap();
        for i in [0usize, 5000, 113_647] {
            let o = i * 32;
            for c in 0..3 {
                let col = (0.5 + SH_C0 * g.sh_dc[i][c]) * 255.0;
                assert!((col - raw[o + 24 + c] as f32).abs() < 1e-2);
            }
            let a = sigmoid(g.opacity_logits[i]) * 255.0;
            assert!(
                (a - raw[o + 27] as f32).abs() < 0.05,
                "{a} vs {}",
                raw[o + 27]
            );
        }
    }
}

#[cfg(test)]
mod writer_tests {
    use super::*;
    use crate::scene::ply::tests::synthetic;

    #[test]
    fn every_format_is_written_and_reads_back_within_its_quantisation() {
        let g = synthetic(700, 3, 41);
        for format in Format::ALL.into_iter().filter(|f| f.is_writable()) {
            let mut bytes = Vec::new();
            write_scene(&g, format, &mut bytes).unwrap();
            let back = read_scene_bytes(&bytes, Some(format.extension()), &Limits::default())
                .unwrap_or_else(|e| panic!("{format}: {e}"));
            assert_eq!(
                detect_format(&bytes, Some(format.extension())).unwrap(),
                format
            );
            assert_eq!(back.len(), g.len(), "{format}");
            // .splat has no view-dependent colour; the others keep the degree.
            let degree = if format == Format::Splat { 0 } else { 3 };
            assert_eq!(back.sh_degree, degree, "{format}");
            let worst = |a: &[[f32; 3]], b: &[[f32; 3]]| {
                a.iter()
                    .zip(b)
                    .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs()))
                    .fold(0.0f32, f32::max)
            };
            let (pos, dc) = (worst(&back.means, &g.means), worst(&back.sh_dc, &g.sh_dc));
            let (pos_tol, dc_tol) = match format {
                Format::Ply | Format::Splat => {
                    (0.0, if format == Format::Ply { 0.0 } else { 0.01 })
                }
                // 11/10/11 bits across a 256-Gaussian chunk's extent; colour at 8 bits there.
                Format::CompressedPly => (0.01, 0.02),
                // 1/4096 of a unit; colour 1/(0.15·255) in DC.
                Format::Spz => (1.0 / 8192.0 + 1e-6, 0.014),
                Format::Sog => unreachable!("SOG is not written"),
            };
            assert!(pos <= pos_tol, "{format}: positions off by {pos}");
            assert!(dc <= dc_tol, "{format}: colours off by {dc}");
        }
    }

    #[test]
    fn the_output_format_follows_the_file_name() {
        for (name, f) in [
            ("a.ply", Some(Format::Ply)),
            ("b.compressed.ply", Some(Format::CompressedPly)),
            ("C.SPLAT", Some(Format::Splat)),
            ("dir.ply/d.spz", Some(Format::Spz)),
            ("scene.SOG", Some(Format::Sog)),
            ("e.ksplat", None),
            ("ply", None),
        ] {
            assert_eq!(Format::from_path(Path::new(name)), f, "{name}");
        }
    }

    #[test]
    fn sog_is_read_only() {
        let g = synthetic(3, 0, 1);
        let mut out = Vec::new();
        let e = write_scene(&g, Format::Sog, &mut out).unwrap_err();
        assert!(matches!(e, SceneError::Unsupported(_)), "{e}");
        assert!(e.to_string().contains("SOG is read-only"), "{e}");
        assert!(out.is_empty());
        assert!(!Format::Sog.is_writable());
        assert!(
            Format::ALL
                .iter()
                .all(|&f| f.is_writable() == (f != Format::Sog))
        );
    }

    #[test]
    fn spz_refuses_positions_it_cannot_hold() {
        let mut g = synthetic(3, 0, 1);
        g.means[1] = [0.0, 5000.0, 0.0];
        let mut out = Vec::new();
        let e = write_scene(&g, Format::Spz, &mut out).unwrap_err();
        assert!(e.to_string().contains("Gaussian 1"), "{e}");
    }
}
