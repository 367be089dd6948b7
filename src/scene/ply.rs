//! INRIA 3D Gaussian Splatting PLY: a hardened PLY header parser and element reader (shared with
//! the compressed-PLY reader), the INRIA reader and the INRIA binary little-endian writer.
//!
//! The reader accepts `binary_little_endian`, `binary_big_endian` and `ascii` files, with or
//! without `nx ny nz`, any property order, any scalar property type (converted to f32), and extra
//! properties or elements (ignored). The SH degree follows from the number of `f_rest_*`
//! properties (0, 9, 24, 45 → degree 0..3). INRIA stores `f_rest` channel-major
//! (`f_rest_{c·(K−1)+k}`); [`Gaussians::sh_rest`] is `[k][c]`, and the reader and writer convert.
//!
//! Decoding uses a per-property table of byte offsets computed once from the header; rows are
//! then read with fixed-offset loads, not string matching.

use std::io::Write;

use crate::scene::format::{GaussianBuilder, Limits, RawGaussian};
use crate::scene::{Gaussians, SceneError};

/// A PLY header (everything up to `end_header`) may be at most this long.
pub const MAX_HEADER_BYTES: usize = 64 * 1024;

/// How the data section of a PLY file is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// A PLY scalar property type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScalarType {
    Char,
    UChar,
    Short,
    UShort,
    Int,
    UInt,
    Float,
    Double,
}

impl ScalarType {
    /// Parses a PLY type name (both the classic and the sized spellings).
    pub fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::Char,
            "uchar" | "uint8" => Self::UChar,
            "short" | "int16" => Self::Short,
            "ushort" | "uint16" => Self::UShort,
            "int" | "int32" => Self::Int,
            "uint" | "uint32" => Self::UInt,
            "float" | "float32" => Self::Float,
            "double" | "float64" => Self::Double,
            _ => return None,
        })
    }

    /// Size in bytes in a binary file.
    pub fn size(self) -> usize {
        match self {
            Self::Char | Self::UChar => 1,
            Self::Short | Self::UShort => 2,
            Self::Int | Self::UInt | Self::Float => 4,
            Self::Double => 8,
        }
    }

    /// Whether the type is an integer type.
    pub fn is_integer(self) -> bool {
        !matches!(self, Self::Float | Self::Double)
    }
}

/// One scalar property of an element.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Property {
    pub name: String,
    pub ty: ScalarType,
    /// Byte offset inside a binary row.
    pub offset: usize,
}

/// One element declaration (`element NAME COUNT` and its properties).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Element {
    pub name: String,
    pub count: u64,
    pub properties: Vec<Property>,
    /// Bytes per row in a binary file.
    pub row_bytes: usize,
}

impl Element {
    /// Index and declaration of a property by name.
    pub fn property(&self, name: &str) -> Option<(usize, &Property)> {
        self.properties
            .iter()
            .enumerate()
            .find(|(_, p)| p.name == name)
    }

    /// Index of a property, or [`SceneError::MissingProperty`].
    pub fn require(&self, name: &str) -> Result<usize, SceneError> {
        self.property(name).map(|(i, _)| i).ok_or_else(|| {
            SceneError::MissingProperty(format!("{name}' in element '{}", self.name))
        })
    }
}

/// A parsed PLY header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    pub encoding: Encoding,
    pub elements: Vec<Element>,
    /// Offset of the first data byte (just after `end_header\n`).
    pub data_offset: usize,
}

impl Header {
    /// Index and declaration of an element by name.
    pub fn element(&self, name: &str) -> Option<(usize, &Element)> {
        self.elements
            .iter()
            .enumerate()
            .find(|(_, e)| e.name == name)
    }
}

fn header_err(line: usize, msg: impl std::fmt::Display) -> SceneError {
    SceneError::Header(format!("line {line}: {msg}"))
}

/// Parses and validates a PLY header: magic, `format`, elements and scalar properties, up to
/// `end_header`, which must come within [`MAX_HEADER_BYTES`]. Rejects list properties,
/// duplicate elements and properties, unknown types and keywords.
pub fn parse_header(bytes: &[u8]) -> Result<Header, SceneError> {
    let mut pos = if bytes.starts_with(b"ply\n") {
        4
    } else if bytes.starts_with(b"ply\r\n") {
        5
    } else {
        return Err(SceneError::UnknownFormat(
            "not a PLY file (no 'ply' magic line)".into(),
        ));
    };
    let limit = bytes.len().min(MAX_HEADER_BYTES);
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut line_no = 1;
    loop {
        line_no += 1;
        let rest = bytes.get(pos..limit).unwrap_or(&[]);
        let (raw, next) = match rest.iter().position(|&b| b == b'\n') {
            Some(nl) => (&rest[..nl], pos + nl + 1),
            // The last header line of a file with no data may lack its newline.
            None if limit == bytes.len() && trim_cr(rest) == b"end_header" => (rest, bytes.len()),
            None if limit < bytes.len() => {
                return Err(SceneError::Header(format!(
                    "no 'end_header' within the first {MAX_HEADER_BYTES} bytes"
                )));
            }
            None => return Err(SceneError::Header("file ends before 'end_header'".into())),
        };
        pos = next;
        let line = std::str::from_utf8(trim_cr(raw))
            .map_err(|_| header_err(line_no, "header line is not valid text"))?;
        let mut toks = line.split_ascii_whitespace();
        let Some(keyword) = toks.next() else { continue };
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                if encoding.is_some() {
                    return Err(header_err(line_no, "'format' declared twice"));
                }
                let enc = match toks.next() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLittleEndian,
                    Some("binary_big_endian") => Encoding::BinaryBigEndian,
                    other => {
                        return Err(header_err(line_no, format!("unknown format {other:?}")));
                    }
                };
                match toks.next() {
                    None => return Err(header_err(line_no, "'format' line lacks a version")),
                    Some("1.0") => {}
                    Some(v) => {
                        let v: String = v.chars().take(16).collect();
                        return Err(header_err(
                            line_no,
                            format!("PLY version {v:?} is not supported (1.0 is)"),
                        ));
                    }
                }
                encoding = Some(enc);
            }
            "element" => {
                let (Some(name), Some(count), None) = (toks.next(), toks.next(), toks.next())
                else {
                    return Err(header_err(line_no, "expected 'element NAME COUNT'"));
                };
                let count: u64 = count
                    .parse()
                    .map_err(|_| header_err(line_no, format!("bad element count '{count}'")))?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(SceneError::DuplicateElement(name.to_string()));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                    row_bytes: 0,
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(header_err(line_no, "'property' before any 'element'"));
                };
                let Some(ty) = toks.next() else {
                    return Err(header_err(line_no, "expected 'property TYPE NAME'"));
                };
                if ty == "list" {
                    let name = toks.nth(2).unwrap_or("?");
                    return Err(SceneError::ListProperty(name.to_string()));
                }
                let (Some(name), None) = (toks.next(), toks.next()) else {
                    return Err(header_err(line_no, "expected 'property TYPE NAME'"));
                };
                let ty = ScalarType::parse(ty)
                    .ok_or_else(|| header_err(line_no, format!("unknown property type '{ty}'")))?;
                if element.properties.iter().any(|p| p.name == name) {
                    return Err(SceneError::DuplicateProperty(format!(
                        "{name}' in element '{}",
                        element.name
                    )));
                }
                let offset = element.row_bytes;
                element.row_bytes = offset
                    .checked_add(ty.size())
                    .ok_or_else(|| SceneError::Overflow("row size".into()))?;
                element.properties.push(Property {
                    name: name.to_string(),
                    ty,
                    offset,
                });
            }
            "end_header" => break,
            other => return Err(header_err(line_no, format!("unexpected keyword '{other}'"))),
        }
    }
    let encoding = encoding.ok_or_else(|| SceneError::Header("no 'format' line".into()))?;
    if elements.is_empty() {
        return Err(SceneError::Header("no elements declared".into()));
    }
    Ok(Header {
        encoding,
        elements,
        data_offset: pos,
    })
}

fn trim_cr(s: &[u8]) -> &[u8] {
    s.strip_suffix(b"\r").unwrap_or(s)
}

/// Where each element's rows lie in a binary file; checks (with checked arithmetic) that the
/// file holds all the data the header declares.
fn binary_spans(bytes: &[u8], header: &Header) -> Result<Vec<std::ops::Range<usize>>, SceneError> {
    let mut spans = Vec::with_capacity(header.elements.len());
    let mut total: u64 = 0;
    for e in &header.elements {
        let size = e.count.checked_mul(e.row_bytes as u64).ok_or_else(|| {
            SceneError::Overflow(format!(
                "element '{}': {} rows of {} bytes",
                e.name, e.count, e.row_bytes
            ))
        })?;
        let start = total;
        total = total
            .checked_add(size)
            .ok_or_else(|| SceneError::Overflow("total size of the elements".into()))?;
        spans.push((start, total));
    }
    let available = (bytes.len() - header.data_offset.min(bytes.len())) as u64;
    if total > available {
        return Err(SceneError::Truncated {
            expected: total,
            actual: available,
        });
    }
    // Anything after the declared data but a final newline or two is not this file's: a
    // second file appended (a polyglot) or a header that lies about the counts.
    let tail = &bytes[header.data_offset + total as usize..];
    if tail.len() > 2 || !tail.iter().all(|b| b.is_ascii_whitespace()) {
        return Err(SceneError::Corrupt(format!(
            "{} bytes follow the data the header declares",
            tail.len()
        )));
    }
    // Every span now fits in the file, hence in usize.
    Ok(spans
        .into_iter()
        .map(|(s, e)| header.data_offset + s as usize..header.data_offset + e as usize)
        .collect())
}

/// Reads `N` bytes at `off` from a row (zeros if out of range, which the offset table rules out).
#[inline(always)]
fn bytes_at<const N: usize>(row: &[u8], off: usize) -> [u8; N] {
    row.get(off..off + N)
        .and_then(|s| s.try_into().ok())
        .unwrap_or([0; N])
}

#[inline(always)]
fn read_scalar<const BE: bool>(row: &[u8], off: usize, ty: ScalarType) -> f64 {
    macro_rules! get {
        ($t:ty, $n:literal) => {{
            let b = bytes_at::<$n>(row, off);
            if BE {
                <$t>::from_be_bytes(b)
            } else {
                <$t>::from_le_bytes(b)
            }
        }};
    }
    match ty {
        ScalarType::Float => get!(f32, 4) as f64,
        ScalarType::Double => get!(f64, 8),
        ScalarType::UChar => get!(u8, 1) as f64,
        ScalarType::Char => get!(i8, 1) as f64,
        ScalarType::UShort => get!(u16, 2) as f64,
        ScalarType::Short => get!(i16, 2) as f64,
        ScalarType::UInt => get!(u32, 4) as f64,
        ScalarType::Int => get!(i32, 4) as f64,
    }
}

/// Whitespace-separated tokens of an ascii PLY data section.
struct Tokens<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Tokens<'a> {
    fn next_token(&mut self) -> Option<&'a [u8]> {
        let d = self.data;
        while self.pos < d.len() && d[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        let start = self.pos;
        while self.pos < d.len() && !d[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        (self.pos > start).then(|| &d[start..self.pos])
    }
}

fn parse_ascii(tok: &[u8], ty: ScalarType) -> Option<f64> {
    let s = std::str::from_utf8(tok).ok()?;
    match ty {
        // Parse floats at their own precision so that f32 text round-trips exactly.
        ScalarType::Float => s.parse::<f32>().ok().map(f64::from),
        ScalarType::Double => s.parse::<f64>().ok(),
        _ => s.parse::<i64>().ok().map(|v| v as f64),
    }
}

/// Calls `f(row_index, values)` for every row of element `elem`, where `values[j]` is the value
/// of property `wanted[j]` (an index into the element's properties) as f64 — exact for every
/// PLY scalar type. Checks that the data is present before reading any of it.
pub(crate) fn for_each_row(
    bytes: &[u8],
    header: &Header,
    elem: usize,
    wanted: &[usize],
    mut f: impl FnMut(usize, &[f64]) -> Result<(), SceneError>,
) -> Result<(), SceneError> {
    let element = header
        .elements
        .get(elem)
        .ok_or_else(|| SceneError::Inconsistent(format!("no element {elem}")))?;
    let slots: Vec<(usize, ScalarType)> = wanted
        .iter()
        .map(|&j| {
            element
                .properties
                .get(j)
                .map(|p| (p.offset, p.ty))
                .ok_or_else(|| SceneError::Inconsistent(format!("no property {j}")))
        })
        .collect::<Result<_, _>>()?;
    let mut values = vec![0.0f64; slots.len()];
    match header.encoding {
        Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => {
            let span = binary_spans(bytes, header)?.swap_remove(elem);
            let data = bytes.get(span).unwrap_or(&[]);
            let stride = element.row_bytes;
            if stride == 0 {
                // Rows without properties carry no data.
                for i in 0..element.count {
                    f(i as usize, &values)?;
                }
                return Ok(());
            }
            let be = header.encoding == Encoding::BinaryBigEndian;
            for (i, row) in data.chunks_exact(stride).enumerate() {
                for (v, &(off, ty)) in values.iter_mut().zip(&slots) {
                    *v = if be {
                        read_scalar::<true>(row, off, ty)
                    } else {
                        read_scalar::<false>(row, off, ty)
                    };
                }
                f(i, &values)?;
            }
            Ok(())
        }
        Encoding::Ascii => {
            let data = bytes.get(header.data_offset..).unwrap_or(&[]);
            // Each value takes at least one character and one separator: check that the file can
            // hold what the header declares before reading (and before the caller allocates).
            let mut tokens_before: u64 = 0;
            let mut tokens_total: u64 = 0;
            for (k, e) in header.elements.iter().enumerate() {
                let n = e
                    .count
                    .checked_mul(e.properties.len() as u64)
                    .ok_or_else(|| {
                        SceneError::Overflow(format!(
                            "element '{}': {} rows of {} values",
                            e.name,
                            e.count,
                            e.properties.len()
                        ))
                    })?;
                if k < elem {
                    tokens_before = tokens_before
                        .checked_add(n)
                        .ok_or_else(|| SceneError::Overflow("ascii value count".into()))?;
                }
                tokens_total = tokens_total
                    .checked_add(n)
                    .ok_or_else(|| SceneError::Overflow("ascii value count".into()))?;
            }
            let min_bytes = tokens_total.saturating_mul(2).saturating_sub(1);
            if min_bytes > data.len() as u64 {
                return Err(SceneError::Truncated {
                    expected: min_bytes,
                    actual: data.len() as u64,
                });
            }
            let truncated = || SceneError::Truncated {
                expected: min_bytes,
                actual: data.len() as u64,
            };
            let mut toks = Tokens { data, pos: 0 };
            for _ in 0..tokens_before {
                toks.next_token().ok_or_else(truncated)?;
            }
            let nprops = element.properties.len();
            let mut row: Vec<&[u8]> = Vec::with_capacity(nprops);
            for i in 0..element.count {
                row.clear();
                for _ in 0..nprops {
                    row.push(toks.next_token().ok_or_else(truncated)?);
                }
                for ((v, &(_, ty)), &j) in values.iter_mut().zip(&slots).zip(wanted) {
                    let tok = row.get(j).copied().unwrap_or(b"");
                    *v = parse_ascii(tok, ty).ok_or_else(|| {
                        SceneError::Corrupt(format!(
                            "element '{}' row {i}: '{}' is not a valid {:?}",
                            element.name,
                            String::from_utf8_lossy(&tok[..tok.len().min(40)]),
                            ty
                        ))
                    })?;
                }
                f(i as usize, &values)?;
            }
            if elem + 1 == header.elements.len() && toks.next_token().is_some() {
                return Err(SceneError::Corrupt(
                    "values follow the data the header declares".into(),
                ));
            }
            Ok(())
        }
    }
}

/// SH degree for a number of `f_rest_*` properties (0, 9, 24, 45).
pub(crate) fn degree_for_rest_count(n: usize) -> Result<u8, SceneError> {
    match n {
        0 => Ok(0),
        9 => Ok(1),
        24 => Ok(2),
        45 => Ok(3),
        _ => Err(SceneError::ShRestCount(n)),
    }
}

/// Property indices of `f_rest_0 .. f_rest_{N-1}` in an element, in file (channel-major) order,
/// and the SH degree they imply. Every index from 0 to N−1 must be present.
pub(crate) fn rest_properties(element: &Element) -> Result<(Vec<usize>, u8), SceneError> {
    let n = element
        .properties
        .iter()
        .filter(|p| {
            p.name
                .strip_prefix("f_rest_")
                .is_some_and(|s| s.parse::<usize>().is_ok())
        })
        .count();
    let degree = degree_for_rest_count(n)?;
    let idx = (0..n)
        .map(|j| element.require(&format!("f_rest_{j}")))
        .collect::<Result<_, _>>()?;
    Ok((idx, degree))
}

/// Reads a PLY file: INRIA 3D-GS, or a SuperSplat compressed PLY (detected from its elements
/// and handed to [`crate::scene::compressed_ply`]).
pub fn read(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    let header = parse_header(bytes)?;
    if crate::scene::compressed_ply::is_compressed(&header) {
        return crate::scene::compressed_ply::read_with_header(bytes, &header, limits);
    }
    read_inria_with_header(bytes, &header, limits)
}

/// Reads an INRIA 3D-GS PLY whose header has already been parsed.
pub fn read_inria_with_header(
    bytes: &[u8],
    header: &Header,
    limits: &Limits,
) -> Result<Gaussians, SceneError> {
    let (vi, vertex) = header
        .element("vertex")
        .ok_or_else(|| SceneError::Header("no 'vertex' element".into()))?;
    let n = limits.check_count(vertex.count)?;

    // The property table, in the order RawGaussian wants the values.
    let mut wanted = Vec::with_capacity(14 + 45);
    for name in [
        "x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        "opacity", "f_dc_0", "f_dc_1", "f_dc_2",
    ] {
        wanted.push(vertex.require(name)?);
    }
    let (rest_file, degree) = rest_properties(vertex)?;
    let per_channel = rest_file.len() / 3;
    // Our [k][c] slot k*3+c reads file property f_rest_{c*per_channel+k}.
    for k in 0..per_channel {
        for c in 0..3 {
            wanted.push(rest_file[c * per_channel + k]);
        }
    }

    // Size checks (Overflow / Truncated) happen in for_each_row before its first callback, so
    // allocate lazily on the first row.
    let mut builder: Option<GaussianBuilder> = None;
    let mut rest = vec![0f32; rest_file.len()];
    for_each_row(bytes, header, vi, &wanted, |_, v| {
        let b = builder.get_or_insert_with(|| GaussianBuilder::new(n, degree));
        let f = |j: usize| v[j] as f32;
        for (r, &x) in rest.iter_mut().zip(&v[14..]) {
            *r = x as f32;
        }
        b.push(RawGaussian {
            mean: [f(0), f(1), f(2)],
            log_scale: [f(3), f(4), f(5)],
            rotation: [f(6), f(7), f(8), f(9)],
            opacity: f(10),
            dc: [f(11), f(12), f(13)],
            rest: &rest,
        })
    })?;
    Ok(builder.map_or_else(
        || GaussianBuilder::new(0, degree).finish(),
        GaussianBuilder::finish,
    ))
}

/// The INRIA vertex property names in INRIA's order for a given SH degree.
fn inria_property_names(sh_degree: u8) -> Vec<String> {
    let mut names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    names.extend((0..Gaussians::<f32>::rest_len_for(sh_degree)).map(|j| format!("f_rest_{j}")));
    names.extend(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .iter()
        .map(|s| s.to_string()),
    );
    names
}

/// Calls `f` with the row of INRIA property values of each Gaussian (normals 0).
fn for_each_inria_row(
    g: &Gaussians,
    mut f: impl FnMut(&[f32]) -> Result<(), SceneError>,
) -> Result<(), SceneError> {
    let rest_len = g.rest_len();
    let per_channel = rest_len / 3;
    let mut row = vec![0f32; 17 + rest_len];
    for i in 0..g.len() {
        row[0..3].copy_from_slice(&g.means[i]);
        row[3..6].fill(0.0);
        row[6..9].copy_from_slice(&g.sh_dc[i]);
        let rest = g.rest_of(i);
        for c in 0..3 {
            for k in 0..per_channel {
                row[9 + c * per_channel + k] = rest[k * 3 + c];
            }
        }
        let t = 9 + rest_len;
        row[t] = g.opacity_logits[i];
        row[t + 1..t + 4].copy_from_slice(&g.log_scales[i]);
        row[t + 4..t + 8].copy_from_slice(&g.rotations[i]);
        f(&row)?;
    }
    Ok(())
}

fn header_text(g: &Gaussians, format: &str) -> String {
    let mut h = format!("ply\nformat {format} 1.0\nelement vertex {}\n", g.len());
    for name in inria_property_names(g.sh_degree) {
        h.push_str("property float ");
        h.push_str(&name);
        h.push('\n');
    }
    h.push_str("end_header\n");
    h
}

/// Writes an INRIA binary little-endian PLY (see [`crate::scene::write_ply`]).
pub fn write<W: Write>(g: &Gaussians, mut w: W) -> Result<(), SceneError> {
    g.validate()?;
    w.write_all(header_text(g, "binary_little_endian").as_bytes())?;
    const FLUSH: usize = 1 << 20;
    let mut buf = Vec::with_capacity(FLUSH + 512);
    for_each_inria_row(g, |row| {
        for v in row {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        if buf.len() >= FLUSH {
            w.write_all(&buf)?;
            buf.clear();
        }
        Ok(())
    })?;
    w.write_all(&buf)?;
    w.flush()?;
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::scene::format::{read_scene_bytes, write_ply};

    /// A small deterministic PRNG (xorshift) so that tests need no extra crates.
    pub(crate) struct Rng(pub u64);
    impl Rng {
        pub fn next_u64(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        /// Uniform in [lo, hi).
        pub fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
            let u = (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
            lo + (hi - lo) * u
        }
    }

    /// A random valid scene (unit quaternions, as readers produce).
    pub(crate) fn synthetic(n: usize, sh_degree: u8, seed: u64) -> Gaussians {
        let mut r = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
        let mut g = Gaussians::with_capacity(n, sh_degree);
        for _ in 0..n {
            g.means.push([
                r.uniform(-3.0, 3.0),
                r.uniform(-3.0, 3.0),
                r.uniform(-3.0, 3.0),
            ]);
            g.log_scales.push([
                r.uniform(-6.0, -1.0),
                r.uniform(-6.0, -1.0),
                r.uniform(-6.0, -1.0),
            ]);
            let q = [
                r.uniform(-1.0, 1.0),
                r.uniform(-1.0, 1.0),
                r.uniform(-1.0, 1.0),
                r.uniform(-1.0, 1.0),
            ];
            g.rotations
                .push(crate::scene::normalize_quat(q).unwrap_or([1.0, 0.0, 0.0, 0.0]));
            g.opacity_logits.push(r.uniform(-4.0, 4.0));
            g.sh_dc.push([
                r.uniform(-1.5, 1.5),
                r.uniform(-1.5, 1.5),
                r.uniform(-1.5, 1.5),
            ]);
            for _ in 0..g.rest_len() {
                let v = r.uniform(-0.5, 0.5);
                g.sh_rest.push(v);
            }
        }
        g
    }

    /// Test-only encoder: the INRIA layout as ascii PLY (f32 `Display` is shortest round-trip).
    fn write_ascii(g: &Gaussians) -> Vec<u8> {
        let mut out = header_text(g, "ascii").into_bytes();
        for_each_inria_row(g, |row| {
            let line: Vec<String> = row.iter().map(|v| v.to_string()).collect();
            out.extend_from_slice(line.join(" ").as_bytes());
            out.push(b'\n');
            Ok(())
        })
        .unwrap();
        out
    }

    /// Test-only encoder: the INRIA layout as big-endian binary PLY.
    fn write_be(g: &Gaussians) -> Vec<u8> {
        let mut out = header_text(g, "binary_big_endian").into_bytes();
        for_each_inria_row(g, |row| {
            row.iter()
                .for_each(|v| out.extend_from_slice(&v.to_be_bytes()));
            Ok(())
        })
        .unwrap();
        out
    }

    fn le_bytes(g: &Gaussians) -> Vec<u8> {
        let mut out = Vec::new();
        write_ply(g, &mut out).unwrap();
        out
    }

    fn read(bytes: &[u8]) -> Result<Gaussians, SceneError> {
        read_scene_bytes(bytes, Some("ply"), &Limits::default())
    }

    fn bits(g: &Gaussians) -> Vec<u32> {
        let mut v: Vec<u32> = Vec::new();
        v.extend(g.means.iter().flatten().map(|x| x.to_bits()));
        v.extend(g.log_scales.iter().flatten().map(|x| x.to_bits()));
        v.extend(g.rotations.iter().flatten().map(|x| x.to_bits()));
        v.extend(g.opacity_logits.iter().map(|x| x.to_bits()));
        v.extend(g.sh_dc.iter().flatten().map(|x| x.to_bits()));
        v.extend(g.sh_rest.iter().map(|x| x.to_bits()));
        v
    }

    /// A hand-written binary LE PLY with the given property names, all float, and rows.
    fn custom_ply(props: &[&str], rows: &[Vec<f32>]) -> Vec<u8> {
        let mut h = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
            rows.len()
        );
        for p in props {
            h.push_str(&format!("property float {p}\n"));
        }
        h.push_str("end_header\n");
        let mut out = h.into_bytes();
        for r in rows {
            r.iter()
                .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        }
        out
    }

    const MINIMAL: [&str; 14] = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    fn minimal_row() -> Vec<f32> {
        vec![
            1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.5, -1.0, -2.0, -3.0, 1.0, 0.0, 0.0, 0.0,
        ]
    }

    #[test]
    fn roundtrip_binary_le_all_degrees_bit_exact() {
        for degree in 0..=3u8 {
            let g = synthetic(300, degree, degree as u64 + 1);
            let bytes = le_bytes(&g);
            let back = read(&bytes).unwrap();
            assert_eq!(bits(&back), bits(&g), "degree {degree}");
            assert_eq!(back, g);
            // write -> read -> write gives identical bytes.
            assert!(le_bytes(&back) == bytes);
        }
    }

    #[test]
    fn roundtrip_ascii_and_big_endian() {
        for degree in [0u8, 1, 3] {
            let mut g = synthetic(50, degree, 7 + degree as u64);
            g.means[0] = [-0.0, 1e-30, 3.4e38]; // signed zero, tiny, huge
            let a = read(&write_ascii(&g)).unwrap();
            assert_eq!(bits(&a), bits(&g), "ascii degree {degree}");
            let b = read(&write_be(&g)).unwrap();
            assert_eq!(bits(&b), bits(&g), "big-endian degree {degree}");
        }
    }

    #[test]
    fn ascii_with_crlf_and_comments() {
        let g = synthetic(3, 1, 99);
        let text = String::from_utf8(write_ascii(&g)).unwrap();
        let text = text.replacen(
            "format ascii 1.0\n",
            "format ascii 1.0\ncomment made by a test\nobj_info x\n",
            1,
        );
        let crlf = text.replace('\n', "\r\n");
        assert_eq!(bits(&read(crlf.as_bytes()).unwrap()), bits(&g));
    }

    #[test]
    fn property_order_types_and_extras_are_free() {
        // Shuffled order, doubles, an extra property and an extra element before the vertices.
        let mut h = String::from(
            "ply\nformat binary_little_endian 1.0\nelement camera 1\nproperty uchar id\n",
        );
        h += "element vertex 1\nproperty double rot_3\nproperty float opacity\nproperty float x\n";
        h += "property float y\nproperty float z\nproperty uchar flags\nproperty float scale_0\n";
        h += "property float scale_1\nproperty float scale_2\nproperty float rot_0\nproperty float rot_1\n";
        h += "property float rot_2\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nend_header\n";
        let mut b = h.into_bytes();
        b.push(42); // camera id
        b.extend_from_slice(&0.0f64.to_le_bytes()); // rot_3
        for v in [0.25f32, 1.0, 2.0, 3.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.push(7); // flags
        for v in [-1.0f32, -2.0, -3.0, 2.0, 0.0, 0.0, 0.5, 0.6, 0.7] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let g = read(&b).unwrap();
        assert_eq!(g.means[0], [1.0, 2.0, 3.0]);
        assert_eq!(g.opacity_logits[0], 0.25);
        assert_eq!(g.log_scales[0], [-1.0, -2.0, -3.0]);
        assert_eq!(g.rotations[0], [1.0, 0.0, 0.0, 0.0]); // normalised from (2, 0, 0, 0)
        assert_eq!(g.sh_dc[0], [0.5, 0.6, 0.7]);
    }

    #[test]
    fn f_rest_is_channel_major_in_the_file() {
        // Degree 1: f_rest_{c*3+k}; write value 10*c + k into each.
        let mut props: Vec<String> = MINIMAL.iter().map(|s| s.to_string()).collect();
        props.extend((0..9).map(|j| format!("f_rest_{j}")));
        let mut row = minimal_row();
        for c in 0..3 {
            for k in 0..3 {
                row.push((10 * c + k) as f32);
            }
        }
        let p: Vec<&str> = props.iter().map(|s| s.as_str()).collect();
        let g = read(&custom_ply(&p, &[row])).unwrap();
        assert_eq!(g.sh_degree, 1);
        for k in 0..3 {
            for c in 0..3 {
                assert_eq!(g.sh_rest[k * 3 + c], (10 * c + k) as f32);
            }
        }
    }

    #[test]
    fn header_written_in_inria_order() {
        let g = synthetic(2, 3, 5);
        let bytes = le_bytes(&g);
        let header = parse_header(&bytes).unwrap();
        let names: Vec<&str> = header.elements[0]
            .properties
            .iter()
            .map(|p| p.name.as_str())
            .collect();
        assert_eq!(names.len(), 62);
        assert_eq!(
            &names[..10],
            &[
                "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0"
            ]
        );
        assert_eq!(names[53], "f_rest_44");
        assert_eq!(
            &names[54..],
            &[
                "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"
            ]
        );
        assert!(
            header.elements[0]
                .properties
                .iter()
                .all(|p| p.ty == ScalarType::Float)
        );
        assert_eq!(header.encoding, Encoding::BinaryLittleEndian);
        assert_eq!(bytes.len(), header.data_offset + 2 * 62 * 4);
        // Normals are zero.
        let o = header.data_offset + 12;
        assert_eq!(&bytes[o..o + 12], &[0u8; 12]);
        assert!(bytes.starts_with(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
        ));
    }

    #[test]
    fn empty_scene_roundtrips() {
        let g = synthetic(0, 2, 1);
        let back = read(&le_bytes(&g)).unwrap();
        assert_eq!(back.len(), 0);
        assert_eq!(back.sh_degree, 2);
    }

    #[test]
    fn writer_rejects_invalid_scene() {
        let mut g = synthetic(2, 0, 1);
        g.opacity_logits[1] = f32::NAN;
        assert!(matches!(
            write_ply(&g, Vec::new()),
            Err(SceneError::NonFinite { index: 1, .. })
        ));
        let mut g = synthetic(2, 1, 1);
        g.sh_rest.pop();
        assert!(matches!(
            write_ply(&g, Vec::new()),
            Err(SceneError::Inconsistent(_))
        ));
    }

    // ---- malformed input: one crafted file per case ------------------------------------------

    #[test]
    fn err_truncated_binary() {
        let mut b = custom_ply(&MINIMAL, &[minimal_row(), minimal_row()]);
        b.truncate(b.len() - 3);
        let e = read(&b).unwrap_err();
        assert!(
            matches!(
                e,
                SceneError::Truncated {
                    expected: 112,
                    actual: 109
                }
            ),
            "{e}"
        );
        // Header claiming a billion vertices in a tiny file: Truncated, no allocation.
        let b = custom_ply(&MINIMAL, &[minimal_row()]);
        let text = String::from_utf8_lossy(&b).replacen(
            "element vertex 1",
            "element vertex 1000000000",
            1,
        );
        let limits = Limits {
            max_gaussians: usize::MAX,
            ..Limits::default()
        };
        let e = read_scene_bytes(text.as_bytes(), None, &limits).unwrap_err();
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
    }

    #[test]
    fn err_bytes_after_the_declared_data() {
        // A final newline is tolerated; a second file appended is not.
        let mut b = custom_ply(&MINIMAL, &[minimal_row()]);
        b.push(b'\n');
        assert!(read(&b).is_ok());
        b.extend_from_slice(b"PK\x03\x04 a zip archive riding along");
        let e = read(&b).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        assert!(e.to_string().contains("follow the data"), "{e}");
        let g = synthetic(2, 0, 3);
        let mut a = write_ascii(&g);
        assert!(read(&a).is_ok());
        a.extend_from_slice(b"\n1 2 3\n");
        let e = read(&a).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
    }

    #[test]
    fn err_unsupported_version_and_overflowing_scales() {
        let b = custom_ply(&MINIMAL, &[minimal_row()]);
        let text = String::from_utf8_lossy(&b).replacen(" 1.0\n", " 2.0\n", 1);
        let e = read(text.as_bytes()).unwrap_err();
        assert!(matches!(e, SceneError::Header(_)), "{e}");
        assert!(e.to_string().contains("version"), "{e}");
        // log-scale 100: finite, but e^100 overflows every covariance.
        let mut g = synthetic(2, 0, 3);
        g.log_scales[1] = [-3.0, 100.0, -3.0];
        let e = read(&write_ascii(&g)).unwrap_err();
        assert!(e.to_string().contains("log-scale"), "{e}");
    }

    #[test]
    fn err_truncated_ascii() {
        let g = synthetic(4, 0, 3);
        let mut a = write_ascii(&g);
        a.truncate(a.len() - 20);
        assert!(matches!(read(&a), Err(SceneError::Truncated { .. })));
        let text = String::from_utf8(write_ascii(&g)).unwrap().replacen(
            "element vertex 4",
            "element vertex 4000000",
            1,
        );
        assert!(matches!(
            read(text.as_bytes()),
            Err(SceneError::Truncated { .. })
        ));
    }

    #[test]
    fn err_ascii_bad_number() {
        let g = synthetic(2, 0, 3);
        let text = String::from_utf8(write_ascii(&g)).unwrap();
        let (head, data) = text.split_once("end_header\n").unwrap();
        let bad = format!(
            "{head}end_header\nbanana{}",
            &data[data.find(' ').unwrap()..]
        );
        let e = read(bad.as_bytes()).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        assert!(e.to_string().contains("banana"));
    }

    #[test]
    fn err_overflow() {
        // A second element whose size overflows u64.
        let mut b = custom_ply(&MINIMAL, &[minimal_row()]);
        let text = String::from_utf8_lossy(&b).replacen(
            "end_header\n",
            "element junk 4611686018427387904\nproperty double a\nproperty double b\nend_header\n",
            1,
        );
        let data_start = b.len() - 56;
        let mut crafted = text.as_bytes()[..text.find("end_header\n").unwrap() + 11].to_vec();
        crafted.extend_from_slice(&b.split_off(data_start));
        let e = read(&crafted).unwrap_err();
        assert!(matches!(e, SceneError::Overflow(_)), "{e}");
        // The same in ascii.
        let t = format!(
            "ply\nformat ascii 1.0\nelement vertex 1\n{}element junk 18446744073709551615\n\
property float a\nproperty float b\nend_header\n1 2 3 0 0 0 0 0 0 0 1 0 0 0\n",
            MINIMAL
                .iter()
                .map(|p| format!("property float {p}\n"))
                .collect::<String>()
        );
        let e = read(t.as_bytes()).unwrap_err();
        assert!(matches!(e, SceneError::Overflow(_)), "{e}");
    }

    #[test]
    fn err_list_property() {
        let t = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n\
property list uchar int vertex_indices\nend_header\n";
        let e = read(t.as_bytes()).unwrap_err();
        assert!(
            matches!(&e, SceneError::ListProperty(n) if n == "vertex_indices"),
            "{e}"
        );
    }

    #[test]
    fn err_duplicate_element_and_property() {
        let t = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement vertex 1\nend_header\n";
        assert!(
            matches!(read(t.as_bytes()), Err(SceneError::DuplicateElement(n)) if n == "vertex")
        );
        let t = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty double x\nend_header\n";
        assert!(matches!(
            read(t.as_bytes()),
            Err(SceneError::DuplicateProperty(_))
        ));
    }

    #[test]
    fn err_non_finite_values() {
        for (col, field) in [
            (0, "position"),
            (6, "opacity"),
            (4, "f_dc"),
            (8, "scale"),
            (12, "rotation"),
        ] {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut r = minimal_row();
                r[col] = bad;
                let e = read(&custom_ply(&MINIMAL, &[minimal_row(), r])).unwrap_err();
                assert!(
                    matches!(e, SceneError::NonFinite { index: 1, field: f } if f == field),
                    "{e} for column {col}"
                );
            }
        }
        // f_rest, and NaN spelled in ascii.
        let g = synthetic(2, 1, 3);
        let mut be = write_be(&g);
        let n = be.len();
        be[n - 17 * 4 + 4..n - 17 * 4 + 8].copy_from_slice(&f32::NAN.to_be_bytes()); // a f_rest value
        let e = read(&be).unwrap_err();
        assert!(
            matches!(
                e,
                SceneError::NonFinite {
                    index: 1,
                    field: "f_rest"
                }
            ),
            "{e}"
        );
        let t = format!(
            "ply\nformat ascii 1.0\nelement vertex 1\n{}end_header\nnan 0 0 0 0 0 0 0 0 0 1 0 0 0\n",
            MINIMAL
                .iter()
                .map(|p| format!("property float {p}\n"))
                .collect::<String>()
        );
        assert!(matches!(
            read(t.as_bytes()),
            Err(SceneError::NonFinite {
                index: 0,
                field: "position"
            })
        ));
    }

    #[test]
    fn err_zero_quaternion() {
        let mut r = minimal_row();
        r[10] = 0.0;
        let e = read(&custom_ply(&MINIMAL, &[r])).unwrap_err();
        assert!(matches!(e, SceneError::ZeroQuaternion { index: 0 }), "{e}");
    }

    #[test]
    fn err_too_many_gaussians() {
        let b = custom_ply(&MINIMAL, &[minimal_row(), minimal_row(), minimal_row()]);
        let limits = Limits {
            max_gaussians: 2,
            ..Limits::default()
        };
        let e = read_scene_bytes(&b, None, &limits).unwrap_err();
        assert!(
            matches!(e, SceneError::TooManyGaussians { count: 3, max: 2 }),
            "{e}"
        );
        // A count beyond u64-as-usize is TooManyGaussians too (checked before any size arithmetic).
        let t = "ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\nproperty float x\nend_header\n";
        assert!(matches!(
            read(t.as_bytes()),
            Err(SceneError::TooManyGaussians { .. })
        ));
    }

    #[test]
    fn err_missing_required_property() {
        for missing in MINIMAL {
            let props: Vec<&str> = MINIMAL.iter().copied().filter(|p| *p != missing).collect();
            let row: Vec<f32> = vec![0.5; props.len()];
            let e = read(&custom_ply(&props, &[row])).unwrap_err();
            assert!(
                matches!(&e, SceneError::MissingProperty(p) if p.starts_with(missing)),
                "{e}"
            );
        }
        let t = "ply\nformat ascii 1.0\nelement face 0\nproperty float x\nend_header\n";
        assert!(matches!(read(t.as_bytes()), Err(SceneError::Header(_))));
    }

    #[test]
    fn err_f_rest_count_and_gaps() {
        let mut props: Vec<String> = MINIMAL.iter().map(|s| s.to_string()).collect();
        props.extend((0..10).map(|j| format!("f_rest_{j}")));
        let p: Vec<&str> = props.iter().map(|s| s.as_str()).collect();
        let e = read(&custom_ply(&p, &[vec![1.0; p.len()]])).unwrap_err();
        assert!(matches!(e, SceneError::ShRestCount(10)), "{e}");
        // Nine f_rest properties, but f_rest_4 is missing (f_rest_40 instead).
        props.truncate(MINIMAL.len() + 9);
        props[MINIMAL.len() + 4] = "f_rest_40".into();
        let p: Vec<&str> = props.iter().map(|s| s.as_str()).collect();
        let e = read(&custom_ply(&p, &[vec![1.0; p.len()]])).unwrap_err();
        assert!(
            matches!(&e, SceneError::MissingProperty(n) if n.starts_with("f_rest_4'")),
            "{e}"
        );
    }

    #[test]
    fn err_header_too_long_or_unterminated() {
        // No end_header within 64 KiB of comments.
        let mut t = String::from("ply\nformat binary_little_endian 1.0\n");
        while t.len() < MAX_HEADER_BYTES + 100 {
            t.push_str("comment padding padding padding padding padding padding\n");
        }
        t.push_str("element vertex 0\nproperty float x\nend_header\n");
        let e = read(t.as_bytes()).unwrap_err();
        assert!(
            matches!(&e, SceneError::Header(m) if m.contains("end_header")),
            "{e}"
        );
        // One absurdly long line.
        let mut b = b"ply\nformat ascii 1.0\ncomment ".to_vec();
        b.extend(std::iter::repeat_n(b'a', 1 << 20));
        let e = read(&b).unwrap_err();
        assert!(
            matches!(&e, SceneError::Header(m) if m.contains("end_header")),
            "{e}"
        );
        // Ends before end_header.
        let e = read(b"ply\nformat ascii 1.0\nelement vertex 1\n").unwrap_err();
        assert!(matches!(e, SceneError::Header(_)), "{e}");
    }

    #[test]
    fn err_header_syntax() {
        let cases: &[&str] = &[
            "ply\nelement vertex 1\nproperty float x\nend_header\n", // no format
            "ply\nformat binary_middle_endian 1.0\nelement vertex 1\nend_header\n", // bad format
            "ply\nformat ascii 1.0\nproperty float x\nelement vertex 1\nend_header\n", // property first
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n", // bad type
            "ply\nformat ascii 1.0\nelement vertex -1\nproperty float x\nend_header\n", // bad count
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float\nend_header\n",    // no name
            "ply\nformat ascii 1.0\nbogus line\nend_header\n", // unknown keyword
            "ply\nformat ascii 1.0\nend_header\n",             // no elements
            "ply\nformat ascii 1.0\nformat ascii 1.0\nelement v 0\nend_header\n", // format twice
        ];
        for c in cases {
            let e = read(c.as_bytes()).unwrap_err();
            assert!(matches!(e, SceneError::Header(_)), "{c:?}: {e}");
        }
        let mut b = b"ply\nformat ascii 1.0\ncomment \xff\xfe\nend_header\n".to_vec();
        assert!(matches!(read(&b), Err(SceneError::Header(_))));
        b.clear();
        assert!(matches!(
            parse_header(b"plx\n"),
            Err(SceneError::UnknownFormat(_))
        ));
    }

    #[test]
    fn never_panics_on_mutations() {
        // Every prefix, and many single-byte corruptions, of small valid files.
        let g = synthetic(3, 1, 11);
        for file in [le_bytes(&g), write_be(&g), write_ascii(&g)] {
            for cut in 0..file.len() {
                let _ = read(&file[..cut]);
            }
            let mut rng = Rng(12345);
            for _ in 0..3000 {
                let mut f = file.clone();
                let at = (rng.next_u64() as usize) % f.len();
                f[at] = rng.next_u64() as u8;
                let _ = read(&f);
            }
        }
    }
}
