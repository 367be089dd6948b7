//! What reading a scene file costs in memory, known from its first bytes: the service reserves
//! it from its parse budget before it reads the file (issue 13, defect 4), so the memory of the
//! uploads being checked at once is bounded by the budget, whatever the files declare.

use std::io::Read;
use std::path::Path;

use crate::scene::format::{Format, detect_format};
use crate::scene::ply::{MAX_HEADER_BYTES, parse_header};
use crate::scene::{SceneError, rest_len_for, sog, splat, spz, zip};

/// How many of a file's first bytes [`declared`] needs: a whole PLY header, or enough of a
/// compressed `.spz` stream for its 16-byte header (a zstd block is at most 128 KiB). A bundled
/// SOG declares itself in `meta.json`, found from the ZIP's central directory at its end:
/// [`declared_file`] reads that too.
pub const PROBE_BYTES: usize = 1 << 20;

/// Bytes of a decoded Gaussian besides its higher SH coefficients: position, log-scale,
/// rotation, opacity and DC colour as f32.
const GAUSSIAN_BYTES: u64 = 4 * (3 + 3 + 4 + 1 + 3);

/// Most bytes an `.spz` point takes in its arrays besides its SH coefficients (position 9,
/// alpha 1, colour 3, scale 3, rotation ≤ 4).
const SPZ_POINT_BYTES: u64 = 20;

/// Allocations of a read besides the file, the scene and the arrays: the parsed header (at most
/// [`MAX_HEADER_BYTES`] of text, a few structures per property) and small per-read buffers.
const READ_OVERHEAD: u64 = 4 * MAX_HEADER_BYTES as u64;

/// Bytes a compressed-PLY point takes while it is gathered, besides its SH bytes.
const COMPRESSED_POINT_BYTES: u64 = 17;

/// Bytes a camera file's read may hold per byte of the file, the file included: the cameras
/// (and the matrices parsed on the way) are larger than their text. Measured: 7.3× for bare
/// `transforms.json` frames, the densest valid text; ~1× for real files.
const CAMERA_READ_FACTOR: u64 = 12;

/// What a scene file declares, from its header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Declared {
    pub format: Format,
    /// Gaussians.
    pub count: u64,
    /// Higher SH coefficients per Gaussian (0, 9, 24 or 45 in a valid file).
    pub rest_len: u64,
}

impl Declared {
    /// An upper bound of the memory reading a file of `file_bytes` takes at its peak: the
    /// file's bytes, the decoded scene, the packed arrays an `.spz` or compressed PLY is
    /// gathered into first (whose buffers may have grown to twice their size), a SOG's decoded
    /// images and inflated entries ([`sog::read_overhead`]), and the header's structures.
    /// Checked against a counting allocator in `tests/parse_memory.rs` (SOG aside).
    pub fn read_bytes(&self, file_bytes: u64) -> u64 {
        let scene = self
            .count
            .saturating_mul(GAUSSIAN_BYTES + 4 * self.rest_len);
        let arrays = match self.format {
            Format::Spz => self
                .count
                .saturating_mul(SPZ_POINT_BYTES + self.rest_len)
                .saturating_mul(2),
            // The packed words (16 bytes a point), the SH bytes and the chunks' bounds (144
            // bytes per 256 points), gathered before decoding.
            Format::CompressedPly => self
                .count
                .saturating_mul(COMPRESSED_POINT_BYTES + self.rest_len)
                .saturating_mul(2),
            Format::Sog => sog::read_overhead(self.count, file_bytes),
            Format::Ply | Format::Splat => 0,
        };
        file_bytes
            .saturating_add(scene)
            .saturating_add(arrays)
            .saturating_add(READ_OVERHEAD)
    }
}

/// An upper bound of the memory reading a camera file of `file_bytes` takes at its peak (the
/// file, its JSON values and the cameras): checked in `tests/parse_memory.rs`.
pub fn cameras_read_bytes(file_bytes: u64) -> u64 {
    file_bytes
        .saturating_mul(CAMERA_READ_FACTOR)
        .saturating_add(READ_OVERHEAD)
}

/// The format, Gaussian count and SH size the scene file at `path` declares: [`declared`] on its
/// first [`PROBE_BYTES`], except for a ZIP archive (a bundled SOG) longer than that, whose
/// central directory and `meta.json` are read instead (at most about 2 MiB, whatever its size).
pub fn declared_file(path: &Path, hint_ext: Option<&str>) -> Result<Declared, SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    let mut prefix = Vec::new();
    (&mut f)
        .take(PROBE_BYTES as u64)
        .read_to_end(&mut prefix)
        .map_err(io)?;
    if prefix.starts_with(&zip::LOCAL_MAGIC) && (prefix.len() as u64) < len {
        let (count, degree) = sog::declared_in_file(&mut f, len)?;
        return Ok(Declared {
            format: Format::Sog,
            count,
            rest_len: rest_len_for(degree) as u64,
        });
    }
    declared(&prefix, len, hint_ext)
}

/// The format, Gaussian count and SH size a scene file declares, from its first
/// [`PROBE_BYTES`] (`prefix`; all of it when the file is shorter) and its length. Header errors
/// are the reader's own; what the header does not say is checked when the file is read. A
/// bundled SOG is read from its end: only a whole one is taken here (else
/// [`SceneError::Unsupported`]; [`declared_file`] reads any).
pub fn declared(
    prefix: &[u8],
    file_bytes: u64,
    hint_ext: Option<&str>,
) -> Result<Declared, SceneError> {
    const { assert!(PROBE_BYTES > MAX_HEADER_BYTES) };
    let format = detect_format(prefix, hint_ext)?;
    let (count, rest_len) = match format {
        Format::Ply | Format::CompressedPly => {
            let h = parse_header(prefix)?;
            let count = h.element("vertex").map_or(0, |(_, v)| v.count);
            let rest = match format {
                // One `uchar f_rest_*` property per coefficient in the `sh` element.
                Format::CompressedPly => h.element("sh").map_or(0, |(_, e)| e.properties.len()),
                _ => h.element("vertex").map_or(0, |(_, v)| {
                    v.properties
                        .iter()
                        .filter(|p| p.name.starts_with("f_rest_"))
                        .count()
                }),
            };
            (count, rest as u64)
        }
        Format::Splat => (file_bytes / splat::RECORD_BYTES as u64, 0),
        Format::Spz => {
            let (count, degree) = spz::declared(prefix)?;
            (count, rest_len_for(degree.min(3)) as u64)
        }
        Format::Sog if (prefix.len() as u64) < file_bytes => {
            return Err(SceneError::Unsupported(format!(
                "a bundled SOG declares its size in meta.json, listed at the end of the archive: \
                 the first {} of its {file_bytes} bytes do not say it",
                prefix.len()
            )));
        }
        Format::Sog => {
            let (count, degree) = sog::declared(prefix)?;
            (count, rest_len_for(degree) as u64)
        }
    };
    Ok(Declared {
        format,
        count,
        rest_len,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::object_scene;

    #[test]
    fn the_declared_count_and_sh_size_come_from_each_header() {
        let g = object_scene(40, 3, 1);
        let mut ply = Vec::new();
        crate::scene::write_ply(&g, &mut ply).unwrap();
        let d = declared(&ply[..ply.len().min(PROBE_BYTES)], ply.len() as u64, None).unwrap();
        assert_eq!((d.format, d.count, d.rest_len), (Format::Ply, 40, 45));
        // The scene itself: 40 × (56 + 180) bytes, besides the file and the header.
        assert_eq!(
            d.read_bytes(ply.len() as u64),
            ply.len() as u64 + 40 * 236 + READ_OVERHEAD
        );

        let splat = vec![0u8; 32 * 7];
        let d = declared(&splat, splat.len() as u64, Some("a.splat")).unwrap();
        assert_eq!((d.format, d.count, d.rest_len), (Format::Splat, 7, 0));

        // A gzip .spz that declares 3 million points of SH degree 2 in a few bytes.
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&2u32.to_le_bytes());
        raw.extend_from_slice(&3_000_000u32.to_le_bytes());
        raw.extend_from_slice(&[2, 12, 0, 0]);
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        std::io::Write::write_all(&mut e, &raw).unwrap();
        let spz = e.finish().unwrap();
        let d = declared(&spz, spz.len() as u64, None).unwrap();
        assert_eq!(
            (d.format, d.count, d.rest_len),
            (Format::Spz, 3_000_000, 24)
        );
        assert!(d.read_bytes(spz.len() as u64) > 3_000_000 * (56 + 96));
    }

    #[test]
    fn what_is_not_a_scene_is_the_readers_error() {
        assert!(matches!(
            declared(b"hello", 5, None),
            Err(SceneError::UnknownFormat(_))
        ));
        assert!(matches!(
            declared(b"ply\nformat ascii 1.0\n", 21, None),
            Err(SceneError::Header(_))
        ));
        // gzip that does not hold an spz stream.
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        std::io::Write::write_all(&mut e, b"not an spz stream at all").unwrap();
        let gz = e.finish().unwrap();
        assert!(matches!(
            declared(&gz, gz.len() as u64, None),
            Err(SceneError::Corrupt(_))
        ));
    }
}
