//! Niantic `.spz` (reference: `nianticlabs/spz`, `src/cc/load-spz.cc` and `splat-types.h`).
//!
//! Two containers exist:
//! - **versions 1–3**: a gzip stream holding a 16-byte header (`u32 magic 0x5053474e "NGSP"`,
//!   `u32 version`, `u32 numPoints`, `u8 shDegree`, `u8 fractionalBits`, `u8 flags`,
//!   `u8 reserved`) followed by the attribute arrays;
//! - **version 4**: a plaintext 32-byte header (`magic`, `version`, `numPoints`, `shDegree`,
//!   `fractionalBits`, `flags`, `u8 numStreams`, `u32 tocByteOffset`, 12 reserved bytes), optional
//!   extension records up to `tocByteOffset`, a table of contents of `numStreams ×
//!   (u64 compressedSize, u64 uncompressedSize)`, then one zstd frame per non-empty attribute.
//!
//! Attribute arrays, in this order (both containers): positions (3 × 24-bit signed fixed point
//! with `fractionalBits`), alphas (u8, `sigmoid(opacity)·255`), colours (3 × u8,
//! `dc·0.15·255 + 127.5`), scales (3 × u8, `(ln s + 10)·16`), rotations (v2: 3 × u8 `x y z` as
//! `(q + 1)·127.5` with `w ≥ 0` derived; v3+: 4 bytes "smallest three", 2-bit index + 3 × (sign +
//! 9-bit magnitude / 511 · √½)), SH (`[k][c]` u8, `(v − 128)/128`).
//!
//! Coordinates: spz stores RUB (right, up, back); INRIA PLY is RDF (right, down, front). As
//! Niantic's loader does when unpacking to RDF, the y and z axes are flipped: positions
//! `(x, −y, −z)`, quaternion `(w, x, −y, −z)`, and the SH coefficients multiplied by
//! `coordinateConverter(RUB, RDF).flipSh`. Extension records (flag `0x2`) are skipped.
//!
//! Also accepted, leniently: an uncompressed legacy stream (raw `NGSP` magic with version ≤ 3)
//! and a legacy stream wrapped in zstd instead of gzip.
//!
//! Decompression is capped at the size the header's point count implies, after that count has
//! been checked against [`Limits`] and against the file's size ([`MAX_EXPANSION`]: a tiny file
//! of compressible bytes claiming millions of points is refused before anything is
//! decompressed); buffers grow with the data actually decompressed. A legacy stream is then read to
//! its end, so that its container's checksum is verified (gzip's CRC-32 and length, zstd's
//! content checksum when the frame has one: a mismatch is [`SceneError::Checksum`]); at most
//! [`MAX_TRAILING_BYTES`] may follow the arrays there.

use std::io::Read;

use crate::scene::format::{GaussianBuilder, Limits, NGSP_MAGIC, RawGaussian};
use crate::scene::{Gaussians, SceneError, sigmoid};

/// Niantic's scale factor for DC colours (instead of `SH_C0`).
pub const COLOR_SCALE: f32 = 0.15;
/// Largest `fractionalBits` Niantic accepts.
pub const MAX_FRACTIONAL_BITS: u8 = 24;
/// Size of the legacy (v1–v3) header.
pub const LEGACY_HEADER_BYTES: usize = 16;
/// Size of the v4 header.
pub const V4_HEADER_BYTES: usize = 32;
/// Most decompressed bytes a legacy stream may hold after its arrays (extension records of
/// newer writers, ignored). They are decompressed, without being kept, only to reach the
/// checksum at the end of the container.
pub const MAX_TRAILING_BYTES: u64 = 1 << 20;
/// Most a compressed spz may expand: its arrays may hold at most this many times the file's
/// compressed bytes (or [`EXPANSION_FLOOR`], whichever is more). Quantised splat arrays compress
/// by a small factor (positions, rotations and colours are near-random bytes; even all-zero
/// higher SH bands leave the rest); a file past this ratio is a compression bomb, refused before
/// anything is decompressed.
pub const MAX_EXPANSION: u64 = 64;
/// Arrays this small are accepted at any compression ratio.
pub const EXPANSION_FLOOR: u64 = 1 << 20;

/// Refuses arrays of `decoded` bytes from `compressed` bytes past [`MAX_EXPANSION`].
fn check_expansion(
    decoded: u64,
    compressed: u64,
    points: usize,
    what: &str,
) -> Result<(), SceneError> {
    let cap = compressed
        .saturating_mul(MAX_EXPANSION)
        .max(EXPANSION_FLOOR);
    if decoded > cap {
        return Err(SceneError::Corrupt(format!(
            "the {what} data declares {points} points, {decoded} bytes of arrays from {compressed} \
             compressed bytes: more than {MAX_EXPANSION}:1, which no real spz reaches (a \
             compression bomb?)"
        )));
    }
    Ok(())
}

const FLIP_P: [f32; 3] = [1.0, -1.0, -1.0];
/// `coordinateConverter(RUB, RDF).flipSh` for the 15 coefficients of degrees 1–3
/// (x = 1, y = −1, z = −1: `[y, z, x, xy, yz, 1, xz, 1, y, xyz, y, z, x, z, x]`).
const FLIP_SH: [f32; 15] = [
    -1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0,
];

/// Header fields common to both containers.
#[derive(Clone, Copy, Debug)]
struct SpzHeader {
    version: u32,
    num_points: u32,
    sh_degree: u8,
    fractional_bits: u8,
}

/// Sizes of the six attribute arrays, once the header has been checked.
#[derive(Clone, Copy, Debug)]
struct Plan {
    n: usize,
    sh_degree: u8,
    fractional_bits: u8,
    smallest_three: bool,
    /// positions, alphas, colours, scales, rotations, SH.
    sizes: [usize; 6],
}

impl Plan {
    fn new(h: SpzHeader, limits: &Limits) -> Result<Self, SceneError> {
        match h.version {
            1 => {
                return Err(SceneError::Unsupported(
                    "spz version 1 (float16 positions, never released) is not supported".into(),
                ));
            }
            2..=4 => {}
            v => {
                return Err(SceneError::Unsupported(format!(
                    "spz version {v} (2, 3 and 4 are supported)"
                )));
            }
        }
        let n = limits.check_count(h.num_points as u64)?;
        if h.sh_degree > 3 {
            return Err(SceneError::UnsupportedShDegree(h.sh_degree as usize));
        }
        if h.fractional_bits > MAX_FRACTIONAL_BITS {
            return Err(SceneError::Corrupt(format!(
                "spz fractionalBits {} is above {MAX_FRACTIONAL_BITS}",
                h.fractional_bits
            )));
        }
        let smallest_three = h.version >= 3;
        let sh_per_point = Gaussians::<f32>::rest_len_for(h.sh_degree);
        let per_point = [9, 1, 3, 3, if smallest_three { 4 } else { 3 }, sh_per_point];
        let mut sizes = [0usize; 6];
        for (s, p) in sizes.iter_mut().zip(per_point) {
            *s = n
                .checked_mul(p)
                .ok_or_else(|| SceneError::Overflow(format!("{n} points × {p} bytes")))?;
        }
        Ok(Self {
            n,
            sh_degree: h.sh_degree,
            fractional_bits: h.fractional_bits,
            smallest_three,
            sizes,
        })
    }

    fn total(&self) -> Result<usize, SceneError> {
        self.sizes
            .iter()
            .try_fold(0usize, |a, &s| a.checked_add(s))
            .ok_or_else(|| SceneError::Overflow("spz payload size".into()))
    }
}

fn u32_at(b: &[u8], off: usize) -> u32 {
    let mut a = [0u8; 4];
    if let Some(s) = b.get(off..off + 4) {
        a.copy_from_slice(s);
    }
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], off: usize) -> u64 {
    let mut a = [0u8; 8];
    if let Some(s) = b.get(off..off + 8) {
        a.copy_from_slice(s);
    }
    u64::from_le_bytes(a)
}

fn corrupt_io(what: &str, e: std::io::Error) -> SceneError {
    SceneError::Corrupt(format!("{what}: {e}"))
}

/// An error at the end of a compressed stream: a checksum mismatch (flate2's and zstd's
/// messages both name the checksum) or a missing trailer.
fn end_of_stream_error(what: &str, e: std::io::Error) -> SceneError {
    let text = e.to_string();
    match what {
        _ if !text.contains("checksum") => match e.kind() {
            std::io::ErrorKind::UnexpectedEof => SceneError::Corrupt(format!(
                "the {what} stream ends before its trailer (the file is truncated)"
            )),
            _ => corrupt_io(what, e),
        },
        "gzip" => SceneError::Checksum("gzip CRC-32 or length"),
        "zstd" => SceneError::Checksum("zstd content checksum"),
        _ => SceneError::Checksum("stream checksum"),
    }
}

/// Reads until `buf` is full or the stream ends; returns how many bytes were read.
fn read_full(r: &mut impl Read, buf: &mut [u8], what: &str) -> Result<usize, SceneError> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
            Err(e) => return Err(corrupt_io(what, e)),
        }
    }
    Ok(got)
}

/// The point count and SH degree an `.spz` file declares, from its first bytes (`prefix`; a
/// compressed stream is decompressed only as far as its 16-byte header). Nothing is checked
/// beyond the magic: [`read`] checks the rest.
pub fn declared(prefix: &[u8]) -> Result<(u64, u8), SceneError> {
    let h = if prefix.starts_with(&[0x1f, 0x8b]) {
        legacy_header(&mut flate2::read::GzDecoder::new(prefix), "gzip")?
    } else if prefix.starts_with(&[0x28, 0xb5, 0x2f, 0xfd]) {
        let mut dec =
            zstd::stream::read::Decoder::with_buffer(prefix).map_err(|e| corrupt_io("zstd", e))?;
        legacy_header(&mut dec, "zstd")?
    } else {
        // A plain stream; version 4's header starts the same way.
        legacy_header(&mut &prefix[..], "spz")?
    };
    Ok((u64::from(h.num_points), h.sh_degree))
}

/// Reads a `.spz` file (any supported container).
pub fn read(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    let compressed = Some(bytes.len() as u64);
    if bytes.starts_with(&[0x1f, 0x8b]) {
        read_legacy(
            flate2::read::GzDecoder::new(bytes),
            limits,
            "gzip",
            compressed,
        )
    } else if bytes.starts_with(&[0x28, 0xb5, 0x2f, 0xfd]) {
        let dec =
            zstd::stream::read::Decoder::with_buffer(bytes).map_err(|e| corrupt_io("zstd", e))?;
        read_legacy(dec, limits, "zstd", compressed)
    } else if bytes.starts_with(&NGSP_MAGIC) {
        if bytes.len() < 8 {
            return Err(SceneError::Truncated {
                expected: 8,
                actual: bytes.len() as u64,
            });
        }
        if u32_at(bytes, 4) >= 4 {
            read_v4(bytes, limits)
        } else {
            read_legacy(bytes, limits, "spz", None)
        }
    } else {
        Err(SceneError::UnknownFormat(
            "not an spz file (no gzip, zstd or NGSP magic)".into(),
        ))
    }
}

/// The 16-byte header a legacy stream starts with, its magic checked.
fn legacy_header(r: &mut impl Read, what: &str) -> Result<SpzHeader, SceneError> {
    let mut hdr = [0u8; LEGACY_HEADER_BYTES];
    let got = read_full(r, &mut hdr, what)?;
    if got < LEGACY_HEADER_BYTES {
        return Err(SceneError::Truncated {
            expected: LEGACY_HEADER_BYTES as u64,
            actual: got as u64,
        });
    }
    if hdr[..4] != NGSP_MAGIC {
        return Err(SceneError::Corrupt(format!(
            "{what} stream does not start with the spz magic 'NGSP'"
        )));
    }
    Ok(SpzHeader {
        version: u32_at(&hdr, 4),
        num_points: u32_at(&hdr, 8),
        sh_degree: hdr[12],
        fractional_bits: hdr[13],
    })
}

/// A legacy stream (16-byte header + arrays), from a decompressing reader of a file of
/// `compressed` bytes (`None`: not compressed).
fn read_legacy<R: Read>(
    mut r: R,
    limits: &Limits,
    what: &str,
    compressed: Option<u64>,
) -> Result<Gaussians, SceneError> {
    let h = legacy_header(&mut r, what)?;
    if h.version >= 4 {
        return Err(SceneError::Unsupported(format!(
            "spz version {} inside a {what} stream (version 4 files are not compressed as a whole)",
            h.version
        )));
    }
    let plan = Plan::new(h, limits)?;
    let total = plan.total()?;
    if let Some(c) = compressed {
        check_expansion(total as u64, c, plan.n, what)?;
    }
    // Decompress at most what the header implies; the Vec grows only with real data.
    let mut payload = Vec::new();
    match r.by_ref().take(total as u64).read_to_end(&mut payload) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {}
        Err(e) => return Err(corrupt_io(what, e)),
    }
    if payload.len() < total {
        return Err(SceneError::Truncated {
            expected: (LEGACY_HEADER_BYTES + total) as u64,
            actual: (LEGACY_HEADER_BYTES + payload.len()) as u64,
        });
    }
    // Trailing data (extension records of newer writers) is ignored, but read (bounded) to the
    // end of the stream, where the decompressor checks the container's checksum.
    let trailing = std::io::copy(
        &mut r.by_ref().take(MAX_TRAILING_BYTES + 1),
        &mut std::io::sink(),
    )
    .map_err(|e| end_of_stream_error(what, e))?;
    if trailing > MAX_TRAILING_BYTES {
        return Err(SceneError::Corrupt(format!(
            "more than {MAX_TRAILING_BYTES} bytes follow the spz arrays in the {what} stream"
        )));
    }
    let mut streams: [&[u8]; 6] = [&[]; 6];
    let mut off = 0;
    for (s, &len) in streams.iter_mut().zip(&plan.sizes) {
        *s = &payload[off..off + len];
        off += len;
    }
    decode(&plan, streams)
}

/// The version 4 container: plaintext header, TOC, one zstd frame per attribute.
fn read_v4(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    if bytes.len() < V4_HEADER_BYTES {
        return Err(SceneError::Truncated {
            expected: V4_HEADER_BYTES as u64,
            actual: bytes.len() as u64,
        });
    }
    let h = SpzHeader {
        version: u32_at(bytes, 4),
        num_points: u32_at(bytes, 8),
        sh_degree: bytes[12],
        fractional_bits: bytes[13],
    };
    let num_streams = bytes[15] as usize;
    let toc = u32_at(bytes, 16) as usize;
    let plan = Plan::new(h, limits)?;
    if toc < V4_HEADER_BYTES {
        return Err(SceneError::Corrupt(format!(
            "spz TOC offset {toc} is inside the header"
        )));
    }
    // Empty arrays (SH of degree 0, or no points) have no stream.
    let expected: Vec<(usize, usize)> = plan
        .sizes
        .iter()
        .copied()
        .enumerate()
        .filter(|&(_, s)| s > 0)
        .collect();
    if num_streams != expected.len() {
        return Err(SceneError::Corrupt(format!(
            "spz header declares {num_streams} streams, {} expected for {} points of SH degree {}",
            expected.len(),
            plan.n,
            plan.sh_degree
        )));
    }
    let toc_end = toc
        .checked_add(num_streams * 16)
        .ok_or_else(|| SceneError::Overflow("spz TOC offset".into()))?;
    if toc_end > bytes.len() {
        return Err(SceneError::Truncated {
            expected: toc_end as u64,
            actual: bytes.len() as u64,
        });
    }
    let declared: u64 = expected.iter().map(|&(_, size)| size as u64).sum();
    check_expansion(declared, bytes.len() as u64, plan.n, "spz v4")?;
    let mut buffers: [Vec<u8>; 6] = Default::default();
    let mut offset = toc_end as u64;
    for (j, &(attr, size)) in expected.iter().enumerate() {
        let e = toc + j * 16;
        let compressed = u64_at(bytes, e);
        let uncompressed = u64_at(bytes, e + 8);
        if uncompressed != size as u64 {
            return Err(SceneError::Corrupt(format!(
                "spz stream {j} declares {uncompressed} bytes, {size} expected from the header"
            )));
        }
        let end = offset
            .checked_add(compressed)
            .ok_or_else(|| SceneError::Overflow("spz stream offsets".into()))?;
        if end > bytes.len() as u64 {
            return Err(SceneError::Truncated {
                expected: end,
                actual: bytes.len() as u64,
            });
        }
        // In range of `bytes`, hence of usize.
        let src = &bytes[offset as usize..end as usize];
        let mut dec =
            zstd::stream::read::Decoder::with_buffer(src).map_err(|e| corrupt_io("zstd", e))?;
        let buf = &mut buffers[attr];
        // One byte more than expected, to notice a stream that decompresses to more.
        dec.by_ref()
            .take(size as u64 + 1)
            .read_to_end(buf)
            .map_err(|e| corrupt_io(&format!("zstd stream {j}"), e))?;
        if buf.len() != size {
            return Err(SceneError::Corrupt(format!(
                "spz stream {j} decompresses to {}{} bytes, {size} expected",
                buf.len(),
                if buf.len() > size { "+" } else { "" }
            )));
        }
        offset = end;
    }
    if offset != bytes.len() as u64 {
        return Err(SceneError::Corrupt(format!(
            "{} unexpected bytes after the last spz stream",
            bytes.len() as u64 - offset
        )));
    }
    let streams: [&[u8]; 6] = std::array::from_fn(|k| buffers[k].as_slice());
    decode(&plan, streams)
}

/// Niantic's `unpackQuaternionSmallestThree`, returning `(x, y, z, w)`.
fn unpack_smallest_three(r: &[u8]) -> [f32; 4] {
    let mut comp = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
    const MASK: u32 = (1 << 9) - 1;
    let largest = (comp >> 30) as usize;
    let mut q = [0f32; 4];
    let mut sum_squares = 0f32;
    for i in (0..4).rev() {
        if i != largest {
            let mag = comp & MASK;
            let negbit = (comp >> 9) & 1;
            comp >>= 10;
            q[i] = std::f32::consts::FRAC_1_SQRT_2 * mag as f32 / MASK as f32;
            if negbit == 1 {
                q[i] = -q[i];
            }
            sum_squares += q[i] * q[i];
        }
    }
    q[largest] = (1.0 - sum_squares).sqrt();
    q
}

/// Niantic's `unpackQuaternionFirstThree` (version 2), returning `(x, y, z, w)`.
fn unpack_first_three(r: &[u8]) -> [f32; 4] {
    let xyz = [r[0], r[1], r[2]].map(|b| b as f32 * (1.0 / 127.5) - 1.0);
    let n2 = xyz[0] * xyz[0] + xyz[1] * xyz[1] + xyz[2] * xyz[2];
    [xyz[0], xyz[1], xyz[2], (1.0 - n2).max(0.0).sqrt()]
}

/// Unpacks the six arrays into RDF Gaussians.
fn decode(plan: &Plan, s: [&[u8]; 6]) -> Result<Gaussians, SceneError> {
    let [positions, alphas, colors, scales, rotations, sh] = s;
    for (k, (a, &len)) in s.iter().zip(&plan.sizes).enumerate() {
        if a.len() != len {
            return Err(SceneError::Inconsistent(format!(
                "spz array {k} has {} bytes, {len} expected",
                a.len()
            )));
        }
    }
    let scale = (1.0f64 / (1u32 << plan.fractional_bits) as f64) as f32;
    let rest_len = Gaussians::<f32>::rest_len_for(plan.sh_degree);
    let rot_bytes = if plan.smallest_three { 4 } else { 3 };
    let mut builder = GaussianBuilder::new(plan.n, plan.sh_degree);
    let mut rest = vec![0f32; rest_len];
    for i in 0..plan.n {
        let mut mean = [0f32; 3];
        for (a, m) in mean.iter_mut().enumerate() {
            let p = &positions[(i * 3 + a) * 3..][..3];
            let mut fixed = p[0] as i32 | (p[1] as i32) << 8 | (p[2] as i32) << 16;
            if fixed & 0x80_0000 != 0 {
                fixed |= 0xff00_0000_u32 as i32; // sign extension
            }
            *m = FLIP_P[a] * (fixed as f32 * scale);
        }
        let log_scale = [0, 1, 2].map(|a| scales[i * 3 + a] as f32 / 16.0 - 10.0);
        let r = &rotations[i * rot_bytes..][..rot_bytes];
        let q = if plan.smallest_three {
            unpack_smallest_three(r)
        } else {
            unpack_first_three(r)
        };
        // xyzw → (w, x, y, z), with RUB → RDF flips (y*z, x*z, x*y) = (1, −1, −1) on x, y, z.
        let rotation = [q[3], q[0], -q[1], -q[2]];
        let alpha = (alphas[i] as f32 / 255.0).clamp(1.0 / 255.0, 254.0 / 255.0);
        let opacity = (alpha / (1.0 - alpha)).ln();
        let dc = [0, 1, 2].map(|c| (colors[i * 3 + c] as f32 / 255.0 - 0.5) / COLOR_SCALE);
        for (j, v) in rest.iter_mut().enumerate() {
            // j = k*3 + c, as in the file.
            *v = FLIP_SH[j / 3] * ((sh[i * rest_len + j] as f32 - 128.0) / 128.0);
        }
        builder.push(RawGaussian {
            mean,
            log_scale,
            rotation,
            opacity,
            dc,
            rest: &rest,
        })?;
    }
    Ok(builder.finish())
}

fn to_u8(x: f32) -> u8 {
    x.round().clamp(0.0, 255.0) as u8
}

/// The six attribute arrays of `g` as Niantic's `packGaussians` makes them (RDF → RUB flips,
/// 12 fractional bits), with every SH coefficient at 8 bits (Niantic's writer keeps 5 bits
/// for degree 1 and 4 above; readers take the byte either way). `flip: false` stores values
/// as given (tests).
fn pack(g: &Gaussians, version: u32, flip: bool) -> [Vec<u8>; 6] {
    let n = g.len();
    let fp = if flip { FLIP_P } else { [1.0; 3] };
    let mut out: [Vec<u8>; 6] = Default::default();
    for i in 0..n {
        for (f, m) in fp.iter().zip(g.means[i]) {
            let fixed = (f * m * (1u32 << WRITE_FRACTIONAL_BITS) as f32).round() as i32;
            out[0].extend_from_slice(&[
                (fixed & 0xff) as u8,
                ((fixed >> 8) & 0xff) as u8,
                ((fixed >> 16) & 0xff) as u8,
            ]);
        }
        out[1].push(to_u8(sigmoid(g.opacity_logits[i]) * 255.0));
        for c in 0..3 {
            out[2].push(to_u8(g.sh_dc[i][c] * (COLOR_SCALE * 255.0) + 0.5 * 255.0));
        }
        for a in 0..3 {
            out[3].push(to_u8((g.log_scales[i][a] + 10.0) * 16.0));
        }
        let [w, x, y, z] = g.rotations[i];
        let q = if flip { [x, -y, -z, w] } else { [x, y, z, w] }; // xyzw
        if version >= 3 {
            let largest = (0..4).fold(0, |b, k| if q[k].abs() > q[b].abs() { k } else { b });
            let negate = q[largest] < 0.0;
            let mut comp = largest as u32;
            for (k, &qk) in q.iter().enumerate() {
                if k != largest {
                    let negbit = ((qk < 0.0) ^ negate) as u32;
                    let mag = ((511.0 * (qk.abs() / std::f32::consts::FRAC_1_SQRT_2) + 0.5) as u32)
                        .min(511);
                    comp = (comp << 10) | (negbit << 9) | mag;
                }
            }
            out[4].extend_from_slice(&comp.to_le_bytes());
        } else {
            let s = if q[3] < 0.0 { -127.5 } else { 127.5 };
            for &qk in &q[..3] {
                out[4].push(to_u8(qk * s + 127.5));
            }
        }
        let rest = g.rest_of(i);
        for (j, &v) in rest.iter().enumerate() {
            let f = if flip { FLIP_SH[j / 3] } else { 1.0 };
            out[5].push(((f * v * 128.0).round() + 128.0).clamp(0.0, 255.0) as u8);
        }
    }
    out
}

fn legacy_bytes(g: &Gaussians, version: u32, flip: bool) -> Vec<u8> {
    let mut raw = b"NGSP".to_vec();
    raw.extend_from_slice(&version.to_le_bytes());
    raw.extend_from_slice(&(g.len() as u32).to_le_bytes());
    raw.extend_from_slice(&[g.sh_degree, WRITE_FRACTIONAL_BITS, 0, 0]);
    for s in pack(g, version, flip) {
        raw.extend_from_slice(&s);
    }
    raw
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(raw).expect("writing to memory");
    e.finish().expect("writing to memory")
}

/// Fractional bits of the positions in the files [`encode`] writes (Niantic's default).
pub const WRITE_FRACTIONAL_BITS: u8 = 12;

/// The `.spz` bytes of `g`: version 3 in gzip, the container every spz reader opens
/// (Niantic's `saveSpz` before version 4). Lossy: positions in 24-bit fixed point with
/// [`WRITE_FRACTIONAL_BITS`] (1/4096 of a unit), colour at 8 bits of `dc·0.15`, opacity and
/// log-scales at 8 bits, rotations "smallest three" at 3 × 9 bits, SH at 8 bits. A position
/// beyond ±2048 units does not fit and is refused.
pub fn encode(g: &Gaussians) -> Result<Vec<u8>, SceneError> {
    let limit = (1u32 << 23) as f32 / (1u32 << WRITE_FRACTIONAL_BITS) as f32;
    if let Some(i) = (0..g.len()).find(|&i| g.means[i].iter().any(|m| m.abs() >= limit)) {
        return Err(SceneError::Unsupported(format!(
            "spz keeps positions within ±{limit} units (24 bits, {WRITE_FRACTIONAL_BITS} \
             fractional); Gaussian {i} is at {:?}",
            g.means[i]
        )));
    }
    Ok(gzip(&legacy_bytes(g, 3, true)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::format::read_scene_bytes;
    use crate::scene::ply::tests::synthetic;
    use std::io::Write;

    /// Test-only v4 encoder following Niantic's `saveSpz` (version ≥ 4 branch).
    fn encode_v4_streams(g: &Gaussians, streams: &[Vec<u8>], sizes: &[usize]) -> Vec<u8> {
        let mut out = b"NGSP".to_vec();
        out.extend_from_slice(&4u32.to_le_bytes());
        out.extend_from_slice(&(g.len() as u32).to_le_bytes());
        out.extend_from_slice(&[g.sh_degree, 12, 0, streams.len() as u8]);
        out.extend_from_slice(&32u32.to_le_bytes());
        out.extend_from_slice(&[0u8; 12]);
        for (s, &u) in streams.iter().zip(sizes) {
            out.extend_from_slice(&(s.len() as u64).to_le_bytes());
            out.extend_from_slice(&(u as u64).to_le_bytes());
        }
        for s in streams {
            out.extend_from_slice(s);
        }
        out
    }

    fn encode_v4(g: &Gaussians) -> Vec<u8> {
        let arrays: Vec<Vec<u8>> = pack(g, 4, true)
            .into_iter()
            .filter(|a| !a.is_empty())
            .collect();
        let sizes: Vec<usize> = arrays.iter().map(|a| a.len()).collect();
        let streams: Vec<Vec<u8>> = arrays
            .iter()
            .map(|a| zstd::bulk::compress(a, 12).unwrap())
            .collect();
        encode_v4_streams(g, &streams, &sizes)
    }

    fn read_spz(b: &[u8]) -> Result<Gaussians, SceneError> {
        read_scene_bytes(b, Some("spz"), &Limits::default())
    }

    fn check_close(d: &Gaussians, g: &Gaussians, rot_dot: f32) {
        assert_eq!((d.len(), d.sh_degree), (g.len(), g.sh_degree));
        d.validate().unwrap();
        for i in 0..g.len() {
            for a in 0..3 {
                assert!(
                    (d.means[i][a] - g.means[i][a]).abs() <= 0.5 / 4096.0 + 1e-6,
                    "pos {i}"
                );
                assert!(
                    (d.log_scales[i][a] - g.log_scales[i][a]).abs() <= 1.0 / 32.0 + 1e-5,
                    "scale {i}"
                );
                assert!(
                    (d.sh_dc[i][a] - g.sh_dc[i][a]).abs() <= 0.5 / (COLOR_SCALE * 255.0) + 1e-5,
                    "dc {i}"
                );
            }
            let dot: f32 = (0..4).map(|k| d.rotations[i][k] * g.rotations[i][k]).sum();
            assert!(dot.abs() > rot_dot, "rotation {i}: {dot}");
            assert!(
                (sigmoid(d.opacity_logits[i]) - sigmoid(g.opacity_logits[i])).abs()
                    <= 0.5 / 255.0 + 1e-5
            );
            for (a, b) in d.rest_of(i).iter().zip(g.rest_of(i)) {
                assert!((a - b).abs() <= 0.5 / 128.0 + 1e-6, "sh {i}: {a} vs {b}");
            }
        }
    }

    /// A scene whose values fit spz's ranges (opacity within the clamped alpha range).
    fn scene(n: usize, degree: u8, seed: u64) -> Gaussians {
        let mut g = synthetic(n, degree, seed);
        for o in &mut g.opacity_logits {
            *o = o.clamp(-5.0, 5.0);
        }
        g
    }

    #[test]
    fn v2_v3_gzip_and_v4_zstd_decode_within_quantisation() {
        for degree in 0..=3u8 {
            let g = scene(400, degree, 31 + degree as u64);
            check_close(
                &read_spz(&gzip(&legacy_bytes(&g, 2, true))).unwrap(),
                &g,
                0.99,
            );
            check_close(
                &read_spz(&gzip(&legacy_bytes(&g, 3, true))).unwrap(),
                &g,
                0.9999,
            );
            let v4 = encode_v4(&g);
            assert!(v4.starts_with(b"NGSP"));
            check_close(&read_spz(&v4).unwrap(), &g, 0.9999);
            // Lenient containers: raw legacy stream, zstd-wrapped legacy stream.
            check_close(&read_spz(&legacy_bytes(&g, 3, true)).unwrap(), &g, 0.9999);
            let z = zstd::bulk::compress(&legacy_bytes(&g, 3, true), 3).unwrap();
            check_close(&read_spz(&z).unwrap(), &g, 0.9999);
        }
    }

    #[test]
    fn rub_to_rdf_conversion() {
        // Values stored as-is (RUB) come out with y and z flipped, like Niantic's unpack to RDF.
        let mut g = scene(1, 1, 3);
        g.means[0] = [1.0, 2.0, -3.0];
        g.rotations[0] = crate::scene::normalize_quat([0.8, 0.2, 0.4, 0.4]).unwrap();
        g.sh_rest = vec![0.5, 0.5, 0.5, 0.25, 0.25, 0.25, -0.125, -0.125, -0.125];
        let d = read_spz(&gzip(&legacy_bytes(&g, 3, false))).unwrap();
        assert_eq!(d.means[0], [1.0, -2.0, 3.0]);
        let q = g.rotations[0];
        let expect = [q[0], q[1], -q[2], -q[3]];
        for k in 0..4 {
            assert!(
                (d.rotations[0][k] - expect[k]).abs() < 2e-3,
                "{:?} vs {expect:?}",
                d.rotations[0]
            );
        }
        // flipSh for degree 1 is (y, z, x) = (−1, −1, 1).
        assert_eq!(
            d.sh_rest,
            vec![
                -0.5, -0.5, -0.5, -0.25, -0.25, -0.25, -0.125, -0.125, -0.125
            ]
        );
    }

    #[test]
    fn known_header_values() {
        // fractionalBits other than 12, negative fixed-point positions.
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&2u32.to_le_bytes());
        raw.extend_from_slice(&1u32.to_le_bytes());
        raw.extend_from_slice(&[0, 8, 0, 0]);
        raw.extend_from_slice(&[0x00, 0xff, 0xff, 0x80, 0x00, 0x00, 0x00, 0x00, 0x80]); // -256, 128, -2^23
        raw.extend_from_slice(&[255, 128, 128, 128, 160, 160, 160, 127, 128, 128]);
        let d = read_spz(&gzip(&raw)).unwrap();
        assert_eq!(d.means[0], [-1.0, -0.5, 32768.0]);
        assert_eq!(d.log_scales[0], [0.0, 0.0, 0.0]);
        assert_eq!(
            d.opacity_logits[0],
            (254.0f32 / 255.0 / (1.0 - 254.0 / 255.0)).ln()
        );
        assert_eq!(d.sh_dc[0], [(128.0f32 / 255.0 - 0.5) / COLOR_SCALE; 3]);
    }

    #[test]
    fn errors() {
        let g = scene(5, 1, 1);
        let raw = legacy_bytes(&g, 3, true);
        let with = |f: &dyn Fn(&mut Vec<u8>)| {
            let mut r = raw.clone();
            f(&mut r);
            gzip(&r)
        };
        // Truncated payload and header.
        let e = read_spz(&gzip(&raw[..raw.len() - 1])).unwrap_err();
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        let e = read_spz(&gzip(&raw[..10])).unwrap_err();
        assert!(
            matches!(
                e,
                SceneError::Truncated {
                    expected: 16,
                    actual: 10
                }
            ),
            "{e}"
        );
        let gz = gzip(&raw);
        assert!(read_spz(&gz[..gz.len() / 2]).is_err());
        // Bad magic inside gzip; unsupported versions; SH degree 4; fractional bits.
        let e = read_spz(&with(&|r| r[0] = b'X')).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        for v in [0u32, 1, 5, 99] {
            let e = read_spz(&with(&|r| r[4..8].copy_from_slice(&v.to_le_bytes()))).unwrap_err();
            assert!(matches!(e, SceneError::Unsupported(_)), "{v}: {e}");
        }
        let e = read_spz(&with(&|r| r[12] = 4)).unwrap_err();
        assert!(matches!(e, SceneError::UnsupportedShDegree(4)), "{e}");
        let e = read_spz(&with(&|r| r[13] = 30)).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Too many Gaussians: refused before decompressing.
        let limits = Limits {
            max_gaussians: 4,
            ..Limits::default()
        };
        let e = read_scene_bytes(&gz, None, &limits).unwrap_err();
        assert!(
            matches!(e, SceneError::TooManyGaussians { count: 5, max: 4 }),
            "{e}"
        );
        // A header claiming 9 million points in a small file: refused from the header alone
        // (more than 64:1), nothing decompressed; uncompressed, the same lie is Truncated.
        let lie = |r: &mut Vec<u8>| r[8..12].copy_from_slice(&9_000_000u32.to_le_bytes());
        let e = read_spz(&with(&lie)).unwrap_err();
        assert!(e.to_string().contains("compression bomb"), "{e}");
        let mut r = raw.clone();
        lie(&mut r);
        let e = read_spz(&r).unwrap_err();
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        // Garbage after the gzip magic.
        let e = read_spz(&[0x1f, 0x8b, 1, 2, 3, 4, 5]).unwrap_err();
        assert!(
            matches!(e, SceneError::Corrupt(_) | SceneError::Truncated { .. }),
            "{e}"
        );
        assert!(matches!(
            read_spz(b"NGSP"),
            Err(SceneError::Truncated { .. })
        ));
    }

    #[test]
    fn decompression_bombs_are_capped() {
        // gzip: 5 points declared, followed by 64 MiB of zeros. Only the 5 points' bytes and
        // MAX_TRAILING_BYTES + 1 more are decompressed before the file is refused.
        let g = scene(5, 0, 2);
        let mut raw = legacy_bytes(&g, 3, true);
        let arrays = raw.len();
        raw.resize(arrays + (64 << 20), 0);
        let bomb = gzip(&raw);
        assert!(bomb.len() < 200_000);
        let e = read_spz(&bomb).unwrap_err();
        assert!(
            matches!(&e, SceneError::Corrupt(m) if m.contains("follow the spz arrays")),
            "{e}"
        );
        // Up to MAX_TRAILING_BYTES of trailing data (extension records) are still accepted.
        let mut ok = raw[..arrays].to_vec();
        ok.resize(arrays + MAX_TRAILING_BYTES as usize, 7);
        assert_eq!(read_spz(&gzip(&ok)).unwrap().len(), 5);
        // v4: a stream whose TOC says 45 bytes but which decompresses to 64 MiB.
        let arrays: Vec<Vec<u8>> = pack(&g, 4, true)
            .into_iter()
            .filter(|a| !a.is_empty())
            .collect();
        let sizes: Vec<usize> = arrays.iter().map(|a| a.len()).collect();
        let mut streams: Vec<Vec<u8>> = arrays
            .iter()
            .map(|a| zstd::bulk::compress(a, 3).unwrap())
            .collect();
        streams[0] = zstd::bulk::compress(&vec![0u8; 64 << 20], 3).unwrap();
        let e = read_spz(&encode_v4_streams(&g, &streams, &sizes)).unwrap_err();
        assert!(
            matches!(&e, SceneError::Corrupt(m) if m.contains("46+")),
            "{e}"
        );

        // A zstd-wrapped legacy stream with trailing zeros: capped too.
        let z = zstd::bulk::compress(&raw, 3).unwrap();
        let e = read_spz(&z).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        let z = zstd::bulk::compress(&ok, 3).unwrap();
        assert_eq!(read_spz(&z).unwrap().len(), 5);
    }

    #[test]
    fn compression_bombs_are_refused_before_decompressing() {
        // 200 000 points of zeros (≈ 4 MB of arrays) gzip to a few kilobytes: a 1000:1 file.
        let n: u32 = 200_000;
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&2u32.to_le_bytes());
        raw.extend_from_slice(&n.to_le_bytes());
        raw.extend_from_slice(&[0, 12, 0, 0]);
        raw.resize(raw.len() + n as usize * 19, 0);
        let gz = gzip(&raw);
        assert!(gz.len() < 20_000, "{}", gz.len());
        let e = read_spz(&gz).unwrap_err();
        assert!(
            matches!(&e, SceneError::Corrupt(m) if m.contains("compression bomb")),
            "{e}"
        );
        let z = zstd::bulk::compress(&raw, 3).unwrap();
        let e = read_spz(&z).unwrap_err();
        assert!(e.to_string().contains("compression bomb"), "{e}");
        // The same arrays uncompressed are a real (if dull) scene of 200 000 points.
        assert_eq!(read_spz(&raw).unwrap().len(), n as usize);
        // Real arrays compress far less: a scene of random Gaussians with SH 3.
        let g = scene(20_000, 3, 11);
        let gz = gzip(&legacy_bytes(&g, 3, true));
        assert!(
            legacy_bytes(&g, 3, true).len() as u64 > EXPANSION_FLOOR,
            "the check must apply"
        );
        check_close(&read_spz(&gz).unwrap(), &g, 0.9999);
    }

    #[test]
    fn container_checksums_are_verified() {
        let g = scene(50, 1, 5);
        let raw = legacy_bytes(&g, 3, true);
        let gz = gzip(&raw);
        check_close(&read_spz(&gz).unwrap(), &g, 0.9999);
        // gzip ends with CRC-32 (4 bytes) and the length mod 2^32 (4 bytes).
        let n = gz.len();
        for at in [n - 8, n - 5, n - 4, n - 1] {
            let mut bad = gz.clone();
            bad[at] ^= 0x01;
            let e = read_spz(&bad).unwrap_err();
            assert!(
                matches!(e, SceneError::Checksum("gzip CRC-32 or length")),
                "byte {at}: {e}"
            );
            assert!(e.to_string().contains("does not match"), "{e}");
        }
        // A missing trailer is refused too.
        for cut in [1, 4, 8] {
            let e = read_spz(&gz[..n - cut]).unwrap_err();
            assert!(matches!(e, SceneError::Corrupt(_)), "cut {cut}: {e}");
        }
        // zstd frames with a content checksum.
        let mut enc = zstd::stream::write::Encoder::new(Vec::new(), 3).unwrap();
        enc.include_checksum(true).unwrap();
        enc.write_all(&raw).unwrap();
        let z = enc.finish().unwrap();
        check_close(&read_spz(&z).unwrap(), &g, 0.9999);
        let mut bad = z.clone();
        let last = bad.len() - 1;
        bad[last] ^= 0x01;
        let e = read_spz(&bad).unwrap_err();
        assert!(
            matches!(e, SceneError::Checksum("zstd content checksum")),
            "{e}"
        );
    }

    #[test]
    fn v4_container_errors() {
        let g = scene(10, 2, 4);
        let good = encode_v4(&g);
        check_close(&read_spz(&good).unwrap(), &g, 0.9999);
        let edit = |f: &dyn Fn(&mut Vec<u8>)| {
            let mut b = good.clone();
            f(&mut b);
            read_spz(&b).unwrap_err()
        };
        // Header shorter than 32 bytes.
        assert!(matches!(
            read_spz(&good[..20]),
            Err(SceneError::Truncated { expected: 32, .. })
        ));
        // Wrong stream count.
        let e = edit(&|b| b[15] = 5);
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // TOC offset inside the header / past the end.
        let e = edit(&|b| b[16..20].copy_from_slice(&8u32.to_le_bytes()));
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        let e = edit(&|b| b[16..20].copy_from_slice(&u32::MAX.to_le_bytes()));
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        // A stream's compressed size past the end (and one that overflows u64 arithmetic).
        let e = edit(&|b| b[32..40].copy_from_slice(&(1u64 << 40).to_le_bytes()));
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        let e = edit(&|b| b[32..40].copy_from_slice(&u64::MAX.to_le_bytes()));
        assert!(matches!(e, SceneError::Overflow(_)), "{e}");
        // Uncompressed size disagreeing with the header.
        let e = edit(&|b| b[40..48].copy_from_slice(&89u64.to_le_bytes()));
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Truncated file; trailing garbage.
        let e = read_spz(&good[..good.len() - 3]).unwrap_err();
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        let e = edit(&|b| b.push(0));
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Version above 4.
        let e = edit(&|b| b[4..8].copy_from_slice(&5u32.to_le_bytes()));
        assert!(matches!(e, SceneError::Unsupported(_)), "{e}");
    }

    #[test]
    fn never_panics_on_mutations() {
        let g = scene(20, 1, 9);
        let files = [
            gzip(&legacy_bytes(&g, 2, true)),
            legacy_bytes(&g, 3, true),
            encode_v4(&g),
        ];
        let mut rng = crate::scene::ply::tests::Rng(4242);
        for f in &files {
            for cut in 0..f.len() {
                let _ = read_spz(&f[..cut]);
            }
            for _ in 0..2000 {
                let mut m = f.clone();
                let at = (rng.next_u64() as usize) % m.len();
                m[at] = rng.next_u64() as u8;
                let _ = read_spz(&m);
            }
        }
    }
}
