//! The NPY (`.npy`) array parser and the lexer of its Python-dict header.

use crate::scene::SceneError;

pub(super) const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// A parsed NPY array of floats (C order), widened to f64.
#[derive(Debug)]
pub(super) struct Npy {
    pub(super) shape: Vec<usize>,
    pub(super) data: Vec<f64>,
}

/// Strict NPY parser: format versions 1.0, 2.0 and 3.0; header dict with exactly `descr`
/// (`'<f8'` or `'<f4'`), `fortran_order` (`False`) and `shape`; the data must be exactly the
/// size the shape implies. Sizes are computed with checked arithmetic and compared with the
/// bytes present before anything is allocated.
pub(super) fn parse_npy(bytes: &[u8]) -> Result<Npy, SceneError> {
    let header_err = |msg: &str| SceneError::Header(format!("NPY: {msg}"));
    if !bytes.starts_with(NPY_MAGIC) {
        return Err(header_err("missing the \\x93NUMPY magic: not an NPY file"));
    }
    let (major, minor) = match bytes.get(6..8) {
        Some(&[a, b]) => (a, b),
        _ => return Err(header_err("file ends inside the preamble")),
    };
    let len_bytes = match (major, minor) {
        (1, 0) => 2,
        (2, 0) | (3, 0) => 4,
        _ => {
            return Err(SceneError::Unsupported(format!(
                "NPY format version {major}.{minor}"
            )));
        }
    };
    let prefix = 8 + len_bytes;
    let header_len = match bytes.get(8..prefix) {
        Some(&[a, b]) => u64::from(u16::from_le_bytes([a, b])),
        Some(&[a, b, c, d]) => u64::from(u32::from_le_bytes([a, b, c, d])),
        _ => return Err(header_err("file ends inside the preamble")),
    };
    let actual = bytes.len() as u64;
    let data_start = (prefix as u64)
        .checked_add(header_len)
        .ok_or_else(|| SceneError::Overflow("NPY header length".into()))?;
    if data_start > actual {
        return Err(SceneError::Truncated {
            expected: data_start,
            actual,
        });
    }
    // data_start ≤ bytes.len(), so it fits in usize.
    let data_start = data_start as usize;
    let header = std::str::from_utf8(&bytes[prefix..data_start])
        .map_err(|_| header_err("header is not text"))?;
    let dict = parse_npy_header(header)?;

    let item = match dict.descr.as_str() {
        "<f8" => 8u64,
        "<f4" => 4u64,
        other => {
            return Err(SceneError::Unsupported(format!(
                "NPY dtype '{other}' (only little-endian float64 '<f8' and float32 '<f4' are)"
            )));
        }
    };
    if dict.fortran_order {
        return Err(SceneError::Unsupported("NPY array in Fortran order".into()));
    }
    let overflow = || SceneError::Overflow(format!("NPY shape {:?}", dict.shape));
    let count = dict
        .shape
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d))
        .ok_or_else(overflow)?;
    let data_bytes = count.checked_mul(item).ok_or_else(overflow)?;
    let expected = (data_start as u64)
        .checked_add(data_bytes)
        .ok_or_else(overflow)?;
    if expected > actual {
        return Err(SceneError::Truncated { expected, actual });
    }
    if expected < actual {
        return Err(SceneError::Corrupt(format!(
            "NPY: {} bytes after the array data that the shape {:?} does not account for",
            actual - expected,
            dict.shape
        )));
    }
    // The data fits in the file, so every size below fits in usize.
    let shape = dict.shape.iter().map(|&d| d as usize).collect();
    let raw = &bytes[data_start..];
    let data = if item == 8 {
        raw.chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect()
    } else {
        raw.chunks_exact(4)
            .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
            .collect()
    };
    Ok(Npy { shape, data })
}

/// The three keys of an NPY header dict.
#[derive(Debug, PartialEq)]
struct NpyHeader {
    descr: String,
    fortran_order: bool,
    shape: Vec<u64>,
}

/// Parses the Python dict literal of an NPY header, e.g.
/// `{'descr': '<f8', 'fortran_order': False, 'shape': (20, 17), }` (padded with spaces and a
/// newline). Exactly the keys `descr`, `fortran_order` and `shape`, each once.
fn parse_npy_header(text: &str) -> Result<NpyHeader, SceneError> {
    let err = |msg: String| SceneError::Header(format!("NPY header {text:?}: {msg}"));
    let mut p = HeaderLexer {
        s: text.trim_end().as_bytes(),
        i: 0,
    };
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    p.expect(b'{').map_err(&err)?;
    loop {
        p.skip_ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string().map_err(&err)?;
        p.expect(b':').map_err(&err)?;
        p.skip_ws();
        let dup = || err(format!("key '{key}' appears twice"));
        match key.as_str() {
            "descr" => {
                if descr.replace(p.string().map_err(&err)?).is_some() {
                    return Err(dup());
                }
            }
            "fortran_order" => {
                let v = if p.eat_word("True") {
                    true
                } else if p.eat_word("False") {
                    false
                } else {
                    return Err(err("fortran_order must be True or False".into()));
                };
                if fortran.replace(v).is_some() {
                    return Err(dup());
                }
            }
            "shape" => {
                if shape.replace(p.tuple().map_err(&err)?).is_some() {
                    return Err(dup());
                }
            }
            other => return Err(err(format!("unexpected key '{other}'"))),
        }
        p.skip_ws();
        if p.eat(b',') {
            continue;
        }
        p.expect(b'}').map_err(&err)?;
        break;
    }
    p.skip_ws();
    if p.i != p.s.len() {
        return Err(err("text after the closing brace".into()));
    }
    match (descr, fortran, shape) {
        (Some(descr), Some(fortran_order), Some(shape)) => Ok(NpyHeader {
            descr,
            fortran_order,
            shape,
        }),
        _ => Err(err(
            "needs the keys 'descr', 'fortran_order' and 'shape'".into()
        )),
    }
}

/// A cursor over the header text.
struct HeaderLexer<'a> {
    s: &'a [u8],
    i: usize,
}

impl HeaderLexer<'_> {
    fn skip_ws(&mut self) {
        while self.s.get(self.i).is_some_and(|b| b.is_ascii_whitespace()) {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        self.skip_ws();
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected '{}' at byte {}", c as char, self.i))
        }
    }

    fn eat_word(&mut self, w: &str) -> bool {
        let end = self.i + w.len();
        let next_is_ident = self
            .s
            .get(end)
            .is_some_and(|b| b.is_ascii_alphanumeric() || *b == b'_');
        if self.s.get(self.i..end) == Some(w.as_bytes()) && !next_is_ident {
            self.i = end;
            true
        } else {
            false
        }
    }

    /// A single- or double-quoted string without escapes.
    fn string(&mut self) -> Result<String, String> {
        self.skip_ws();
        let quote = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a quoted string at byte {}", self.i)),
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&b| b == quote)
            .ok_or_else(|| "unterminated string".to_string())?;
        let body = &self.s[start..start + len];
        if body.contains(&b'\\') {
            return Err("escapes in strings are not supported".into());
        }
        self.i = start + len + 1;
        Ok(String::from_utf8_lossy(body).into_owned())
    }

    /// A tuple of non-negative integers: `()`, `(5,)`, `(20, 17)` (Python 2's `20L` accepted).
    fn tuple(&mut self) -> Result<Vec<u64>, String> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        let mut commas = 0;
        loop {
            self.skip_ws();
            if self.eat(b')') {
                break;
            }
            let start = self.i;
            while self.s.get(self.i).is_some_and(u8::is_ascii_digit) {
                self.i += 1;
            }
            if start == self.i {
                return Err(format!("expected a dimension at byte {start}"));
            }
            // The digits are ASCII, so this is valid UTF-8; parse fails only on overflow.
            let digits = String::from_utf8_lossy(&self.s[start..self.i]);
            let d = digits
                .parse::<u64>()
                .map_err(|_| format!("dimension {digits} does not fit in 64 bits"))?;
            dims.push(d);
            self.eat(b'L');
            self.skip_ws();
            if self.eat(b',') {
                commas += 1;
                continue;
            }
            self.expect(b')')?;
            break;
        }
        if dims.len() == 1 && commas == 0 {
            // `(5)` is an int in Python, not a tuple.
            return Err("a one-dimensional shape needs a trailing comma: (n,)".into());
        }
        Ok(dims)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::tests::{f8_header, npy_bytes};

    #[test]
    fn npy_accepts_variants() {
        let data: Vec<f64> = (0..6).map(f64::from).collect();
        // Version 1.0, padded to 64 bytes.
        let npy = parse_npy(&npy_bytes(&f8_header("(2, 3)"), &data)).expect("v1");
        assert_eq!((npy.shape, npy.data), (vec![2, 3], data.clone()));
        // Version 2.0, double quotes, no trailing comma, Python 2 longs, unpadded.
        let h = "{\"shape\": (2L, 3L), \"fortran_order\": False, \"descr\": \"<f8\"}\n";
        let mut v2 = b"\x93NUMPY\x02\x00".to_vec();
        v2.extend_from_slice(&(h.len() as u32).to_le_bytes());
        v2.extend_from_slice(h.as_bytes());
        for v in &data {
            v2.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(parse_npy(&v2).expect("v2").data, data);
        // Float32.
        let mut f4 = npy_bytes(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (6,), }",
            &[],
        );
        for v in &data {
            f4.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        let npy = parse_npy(&f4).expect("f4");
        assert_eq!((npy.shape, npy.data), (vec![6], data));
    }

    /// What a rejected file's error must look like.
    type ErrorCheck = fn(&SceneError) -> bool;

    #[test]
    fn npy_rejects_bad_files() {
        let row = [0.0f64; 17];
        let good = npy_bytes(&f8_header("(1, 17)"), &row);
        assert!(parse_npy(&good).is_ok());
        let header = |h: &str| npy_bytes(h, &row);
        let mut wrong_magic = good.clone();
        wrong_magic[1] = b'X';
        let mut version = good.clone();
        version[6] = 4;
        let mut long_header = good.clone();
        long_header[8..10].copy_from_slice(&u16::MAX.to_le_bytes());
        let absurd = header(&f8_header("(18446744073709551615, 17)"));
        let cases: Vec<(&str, Vec<u8>, ErrorCheck)> = vec![
            ("wrong magic", wrong_magic, |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("too short", b"\x93NUMPY\x01".to_vec(), |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("version 4.0", version, |e| {
                matches!(e, SceneError::Unsupported(_))
            }),
            ("header past end", long_header, |e| {
                matches!(e, SceneError::Truncated { .. })
            }),
            (
                "fortran order",
                header("{'descr': '<f8', 'fortran_order': True, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(m) if m.contains("Fortran")),
            ),
            (
                "int dtype",
                header("{'descr': '<i8', 'fortran_order': False, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(m) if m.contains("<i8")),
            ),
            (
                "big endian",
                header("{'descr': '>f8', 'fortran_order': False, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(_)),
            ),
            (
                "shape larger than data",
                header(&f8_header("(2, 17)")),
                |e| matches!(e, SceneError::Truncated { expected, actual } if expected - actual == 136),
            ),
            (
                "shape smaller than data",
                header(&f8_header("(1, 16)")),
                |e| matches!(e, SceneError::Corrupt(_)),
            ),
            ("truncated data", good[..good.len() - 3].to_vec(), |e| {
                matches!(e, SceneError::Truncated { .. })
            }),
            ("overflowing shape", absurd, |e| {
                matches!(e, SceneError::Overflow(_))
            }),
            (
                "dimension beyond u64",
                header(&f8_header("(99999999999999999999, 17)")),
                |e| matches!(e, SceneError::Header(m) if m.contains("64 bits")),
            ),
            (
                "missing key",
                header("{'descr': '<f8', 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Header(_)),
            ),
            (
                "duplicate key",
                header(
                    "{'descr': '<f8', 'descr': '<f8', 'fortran_order': False, 'shape': (1, 17)}",
                ),
                |e| matches!(e, SceneError::Header(m) if m.contains("twice")),
            ),
            (
                "unknown key",
                header("{'descr': '<f8', 'fortran_order': False, 'shape': (1, 17), 'x': 1}"),
                |e| matches!(e, SceneError::Header(_)),
            ),
            ("not a tuple", header(&f8_header("(17)")), |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("negative", header(&f8_header("(-1, 17)")), |e| {
                matches!(e, SceneError::Header(_))
            }),
            (
                "garbage after dict",
                header(&format!("{} x", f8_header("(1, 17)"))),
                |e| matches!(e, SceneError::Header(_)),
            ),
            ("not a dict", header("[1, 17]"), |e| {
                matches!(e, SceneError::Header(_))
            }),
        ];
        for (what, bytes, ok) in cases {
            match parse_npy(&bytes) {
                Ok(n) => panic!("{what}: accepted {n:?}"),
                Err(e) => assert!(ok(&e), "{what}: unexpected error {e:?}"),
            }
        }
    }
}
