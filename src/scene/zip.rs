//! A small reader of ZIP archives, for bundled SOG scenes (`.sog`, see [`sog`](crate::scene::sog)).
//!
//! Reference: PKWARE's APPNOTE.TXT 6.3.10, §4.3 (the archive layout), §4.4 (header fields). Only
//! what a bundled SOG needs is read: the end-of-central-directory record (§4.3.16, searched for in
//! the last 22 + 65 535 bytes, the largest comment), the central directory (§4.3.12), each entry's
//! local header only for where its data starts (§4.3.7: its sizes may be zero when bit 3 of the
//! flags says a data descriptor follows the data, which is how PlayCanvas's `splat-transform`
//! writes `.sog`; the central directory's sizes are used), and entries "stored" (method 0) or
//! "deflate" (method 8, through `flate2`). ZIP64, multi-part archives, encryption and other
//! methods are refused with [`SceneError::Unsupported`].
//!
//! Every size read from the file is bounded before it is used: the central directory by
//! [`MAX_DIRECTORY_BYTES`] and [`MAX_ENTRIES`], an entry's data by the file's length, and what is
//! inflated by the caller's bound for that entry and by [`INFLATE_RATIO`] × the archive's size in
//! all (a "zip bomb" is refused before it is inflated); every entry read is checked against its
//! CRC-32. Names must be relative paths that stay inside the archive ([`is_safe_name`]).

use std::borrow::Cow;
use std::cell::Cell;
use std::io::{Read, Seek, SeekFrom};

use crate::scene::SceneError;

/// A ZIP archive's first bytes: a local file header's signature.
pub const LOCAL_MAGIC: [u8; 4] = *b"PK\x03\x04";
const LOCAL_SIG: u32 = 0x0403_4b50;
const CENTRAL_SIG: u32 = 0x0201_4b50;
const EOCD_SIG: u32 = 0x0605_4b50;
const LOCAL_HEADER_BYTES: usize = 30;
const CENTRAL_HEADER_BYTES: usize = 46;
const EOCD_BYTES: usize = 22;
/// Largest central directory read (a SOG's lists ten names or so).
pub const MAX_DIRECTORY_BYTES: u64 = 1 << 20;
/// Most entries an archive may list.
pub const MAX_ENTRIES: usize = 1024;
/// How many of an archive's last bytes hold its end record and central directory, at most.
pub const TAIL_BYTES: u64 = (EOCD_BYTES + 0xFFFF) as u64 + MAX_DIRECTORY_BYTES;
/// An archive's deflated entries may inflate to at most this many times its size in all (plus
/// [`INFLATE_FLOOR`]): WebP textures do not deflate, so a real SOG inflates to about its size.
pub const INFLATE_RATIO: u64 = 2;
/// What any archive may inflate to, whatever its size (room for a well-compressed `meta.json`).
pub const INFLATE_FLOOR: u64 = 1 << 20;

/// One file of the archive, as the central directory lists it.
#[derive(Clone, Debug)]
pub struct Entry {
    pub name: String,
    method: u16,
    crc32: u32,
    /// Bytes of the entry's data in the archive.
    pub compressed: u64,
    /// Bytes of the file once extracted.
    pub size: u64,
    header_offset: u64,
}

/// The central directory: the archive's entries.
#[derive(Debug)]
pub struct Directory {
    pub entries: Vec<Entry>,
    /// Where the central directory starts; every entry's data ends before it.
    start: u64,
}

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}

fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

/// Whether `name` is a relative path that stays where it is resolved: `/`-separated components,
/// none empty, `.` or `..`, no backslash, drive letter or NUL, at most 255 bytes.
pub fn is_safe_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 255
        && !name.contains(['\\', '\0', ':'])
        && name
            .split('/')
            .all(|c| !c.is_empty() && c != "." && c != "..")
}

impl Directory {
    /// Parses the end record and the central directory from `tail`, the archive's last bytes
    /// (all of it, or at least its last [`TAIL_BYTES`]), which start at `tail_start` in an
    /// archive of `file_len` bytes.
    pub fn parse(tail: &[u8], tail_start: u64, file_len: u64) -> Result<Self, SceneError> {
        let not_zip = |why: &str| {
            SceneError::Corrupt(format!(
                "not a complete ZIP archive: {why} (is it truncated?)"
            ))
        };
        // The end record is the last signature whose comment reaches the end of the file.
        let eocd = (0..=tail.len().saturating_sub(EOCD_BYTES))
            .rev()
            .take(EOCD_BYTES + 0xFFFF)
            .find(|&p| {
                tail.len() >= p + EOCD_BYTES
                    && u32_at(tail, p) == EOCD_SIG
                    && p + EOCD_BYTES + usize::from(u16_at(tail, p + 20)) == tail.len()
            })
            .ok_or_else(|| not_zip("no end-of-central-directory record at its end"))?;
        let e = &tail[eocd..];
        let (disk, cd_disk) = (u16_at(e, 4), u16_at(e, 6));
        let (on_disk, total) = (u16_at(e, 8), u16_at(e, 10));
        let (cd_size, cd_offset) = (u32_at(e, 12), u32_at(e, 16));
        if on_disk == 0xFFFF || total == 0xFFFF || cd_size == u32::MAX || cd_offset == u32::MAX {
            return Err(SceneError::Unsupported(
                "ZIP64 archives (over 4 GiB or 65 535 entries) are not read".into(),
            ));
        }
        if disk != 0 || cd_disk != 0 || on_disk != total {
            return Err(SceneError::Unsupported(
                "multi-part ZIP archives are not read".into(),
            ));
        }
        let total = usize::from(total);
        if total > MAX_ENTRIES || u64::from(cd_size) > MAX_DIRECTORY_BYTES {
            return Err(SceneError::Unsupported(format!(
                "a ZIP archive of {total} entries and a {cd_size}-byte directory (at most \
                 {MAX_ENTRIES} entries and {MAX_DIRECTORY_BYTES} bytes are read)"
            )));
        }
        let eocd_at = tail_start + eocd as u64;
        let (start, end) = (
            u64::from(cd_offset),
            u64::from(cd_offset) + u64::from(cd_size),
        );
        if end > eocd_at || start < tail_start {
            return Err(not_zip(&format!(
                "its central directory ({start}..{end}) is not before its end record at {eocd_at}"
            )));
        }
        let mut cd = &tail[(start - tail_start) as usize..(end - tail_start) as usize];
        let mut entries: Vec<Entry> = Vec::with_capacity(total);
        for k in 0..total {
            if cd.len() < CENTRAL_HEADER_BYTES || u32_at(cd, 0) != CENTRAL_SIG {
                return Err(not_zip(&format!(
                    "central directory entry {k} is cut short"
                )));
            }
            let flags = u16_at(cd, 8);
            let lens = [u16_at(cd, 28), u16_at(cd, 30), u16_at(cd, 32)].map(usize::from);
            let record = CENTRAL_HEADER_BYTES + lens.iter().sum::<usize>();
            if cd.len() < record {
                return Err(not_zip(&format!(
                    "central directory entry {k} is cut short"
                )));
            }
            let raw = &cd[CENTRAL_HEADER_BYTES..CENTRAL_HEADER_BYTES + lens[0]];
            let name = std::str::from_utf8(raw)
                .map_err(|_| SceneError::Corrupt(format!("ZIP entry {k}'s name is not UTF-8")))?;
            if !is_safe_name(name) {
                return Err(SceneError::Corrupt(format!(
                    "ZIP entry name {name:?} is not a relative path inside the archive"
                )));
            }
            if flags & 0x41 != 0 {
                return Err(SceneError::Unsupported(format!(
                    "ZIP entry '{name}' is encrypted"
                )));
            }
            let entry = Entry {
                name: name.to_string(),
                method: u16_at(cd, 10),
                crc32: u32_at(cd, 16),
                compressed: u64::from(u32_at(cd, 20)),
                size: u64::from(u32_at(cd, 24)),
                header_offset: u64::from(u32_at(cd, 42)),
            };
            if [entry.compressed, entry.size, entry.header_offset].contains(&u64::from(u32::MAX)) {
                return Err(SceneError::Unsupported(format!(
                    "ZIP entry '{name}' has ZIP64 sizes, which are not read"
                )));
            }
            if entries.iter().any(|e| e.name == entry.name) {
                return Err(SceneError::Corrupt(format!(
                    "ZIP entry '{name}' appears twice"
                )));
            }
            if entry.header_offset + entry.compressed > start || start > file_len {
                return Err(SceneError::Corrupt(format!(
                    "ZIP entry '{name}' ({} bytes at {}) runs into the central directory at \
                     {start}",
                    entry.compressed, entry.header_offset
                )));
            }
            entries.push(entry);
            cd = &cd[record..];
        }
        Ok(Self { entries, start })
    }

    pub fn get(&self, name: &str) -> Option<&Entry> {
        self.entries.iter().find(|e| e.name == name)
    }

    /// Where `e`'s data starts, from the first [`LOCAL_HEADER_BYTES`] of its local header; its
    /// data must end before the central directory.
    fn data_start(&self, e: &Entry, local: &[u8]) -> Result<u64, SceneError> {
        if local.len() < LOCAL_HEADER_BYTES || u32_at(local, 0) != LOCAL_SIG {
            return Err(SceneError::Corrupt(format!(
                "ZIP entry '{}' has no local header at offset {}",
                e.name, e.header_offset
            )));
        }
        let skip = u64::from(u16_at(local, 26)) + u64::from(u16_at(local, 28));
        let data = e.header_offset + LOCAL_HEADER_BYTES as u64 + skip;
        if data + e.compressed > self.start {
            return Err(SceneError::Truncated {
                expected: data + e.compressed,
                actual: self.start,
            });
        }
        Ok(data)
    }
}

/// Extracts `e` from its `raw` data (exactly `e.compressed` bytes): at most `max` bytes, and, when
/// inflated, at most `budget` (which is reduced by what was inflated). The CRC-32 is checked.
fn extract<'a>(
    e: &Entry,
    raw: &'a [u8],
    max: u64,
    budget: &Cell<u64>,
) -> Result<Cow<'a, [u8]>, SceneError> {
    if e.size > max {
        return Err(SceneError::Corrupt(format!(
            "ZIP entry '{}' declares {} bytes, more than the {max} it may hold",
            e.name, e.size
        )));
    }
    let out: Cow<'a, [u8]> = match e.method {
        0 if e.size == e.compressed => Cow::Borrowed(raw),
        0 => {
            return Err(SceneError::Corrupt(format!(
                "stored ZIP entry '{}' declares {} bytes but holds {}",
                e.name, e.size, e.compressed
            )));
        }
        8 => {
            let left = budget.get();
            if e.size > left {
                return Err(SceneError::Corrupt(format!(
                    "ZIP entry '{}' would inflate to {} bytes, past {INFLATE_RATIO}× the \
                     archive's size ({left} bytes left): not a SOG (a compression bomb?)",
                    e.name, e.size
                )));
            }
            budget.set(left - e.size);
            let mut out = Vec::with_capacity(e.size as usize);
            flate2::read::DeflateDecoder::new(raw)
                .take(e.size + 1)
                .read_to_end(&mut out)
                .map_err(|err| {
                    SceneError::Corrupt(format!("ZIP entry '{}' does not inflate: {err}", e.name))
                })?;
            if out.len() as u64 != e.size {
                return Err(SceneError::Corrupt(format!(
                    "ZIP entry '{}' inflates to {} bytes, not the {} its directory declares",
                    e.name,
                    out.len(),
                    e.size
                )));
            }
            Cow::Owned(out)
        }
        m => {
            return Err(SceneError::Unsupported(format!(
                "ZIP entry '{}' uses compression method {m} (stored and deflate are read)",
                e.name
            )));
        }
    };
    let mut crc = flate2::Crc::new();
    crc.update(&out);
    if crc.sum() != e.crc32 {
        return Err(SceneError::Checksum("CRC-32 of a ZIP entry"));
    }
    Ok(out)
}

/// A whole archive held in memory; stored entries are read in place.
pub struct Archive<'a> {
    bytes: &'a [u8],
    dir: Directory,
    budget: Cell<u64>,
}

impl<'a> Archive<'a> {
    pub fn open(bytes: &'a [u8]) -> Result<Self, SceneError> {
        let dir = Directory::parse(bytes, 0, bytes.len() as u64)?;
        let budget = (bytes.len() as u64)
            .saturating_mul(INFLATE_RATIO)
            .saturating_add(INFLATE_FLOOR);
        Ok(Self {
            bytes,
            dir,
            budget: Cell::new(budget),
        })
    }

    pub fn contains(&self, name: &str) -> bool {
        self.dir.get(name).is_some()
    }

    /// The file `name`, at most `max` bytes once extracted; `None` when the archive has none.
    pub fn read(&self, name: &str, max: u64) -> Result<Option<Cow<'a, [u8]>>, SceneError> {
        let Some(e) = self.dir.get(name) else {
            return Ok(None);
        };
        let local = &self.bytes[e.header_offset as usize..];
        let start = self.dir.data_start(e, local)? as usize;
        let raw = &self.bytes[start..start + e.compressed as usize];
        extract(e, raw, max, &self.budget).map(Some)
    }
}

/// Reads the file `name` (at most `max` bytes) from the archive `r` of `file_len` bytes without
/// reading the rest: its end, the entry's local header and data. `None` when it has no such file.
pub fn read_entry<R: Read + Seek>(
    r: &mut R,
    file_len: u64,
    name: &str,
    max: u64,
) -> Result<Option<Vec<u8>>, SceneError> {
    let mut read_at = |offset: u64, len: u64| -> Result<Vec<u8>, SceneError> {
        let mut buf = Vec::with_capacity(len as usize);
        r.seek(SeekFrom::Start(offset))?;
        r.by_ref().take(len).read_to_end(&mut buf)?;
        Ok(buf)
    };
    let tail_start = file_len.saturating_sub(TAIL_BYTES);
    let tail = read_at(tail_start, file_len - tail_start)?;
    let dir = Directory::parse(&tail, tail_start, file_len)?;
    let Some(e) = dir.get(name) else {
        return Ok(None);
    };
    if e.compressed > max.saturating_mul(2).saturating_add(1024) {
        return Err(SceneError::Corrupt(format!(
            "ZIP entry '{name}' holds {} bytes, more than the {max} it may hold",
            e.compressed
        )));
    }
    let local = read_at(e.header_offset, LOCAL_HEADER_BYTES as u64)?;
    let start = dir.data_start(e, &local)?;
    let raw = read_at(start, e.compressed)?;
    let budget = Cell::new(max);
    Ok(Some(extract(e, &raw, max, &budget)?.into_owned()))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::io::Write;

    /// A ZIP archive of `files` (name, data, deflate?) the way `splat-transform` writes `.sog`:
    /// local headers with zero sizes and bit 3 set, a data descriptor after each entry.
    pub(crate) fn zip(files: &[(&str, &[u8], bool)]) -> Vec<u8> {
        let (mut out, mut central) = (Vec::new(), Vec::new());
        for (name, data, deflate) in files {
            let mut crc = flate2::Crc::new();
            crc.update(data);
            let body = if *deflate {
                let mut e = flate2::write::DeflateEncoder::new(Vec::new(), Default::default());
                e.write_all(data).unwrap();
                e.finish().unwrap()
            } else {
                data.to_vec()
            };
            let method: u16 = if *deflate { 8 } else { 0 };
            let offset = out.len() as u32;
            out.extend_from_slice(&LOCAL_SIG.to_le_bytes());
            out.extend_from_slice(&20u16.to_le_bytes());
            out.extend_from_slice(&0x0808u16.to_le_bytes());
            out.extend_from_slice(&method.to_le_bytes());
            out.extend_from_slice(&[0; 16]); // time, date, crc, sizes: in the descriptor
            out.extend_from_slice(&(name.len() as u16).to_le_bytes());
            out.extend_from_slice(&0u16.to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&body);
            for v in [0x0807_4b50, crc.sum(), body.len() as u32, data.len() as u32] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            central.extend_from_slice(&CENTRAL_SIG.to_le_bytes());
            central.extend_from_slice(&[20, 0, 20, 0, 0x08, 0x08]);
            central.extend_from_slice(&method.to_le_bytes());
            central.extend_from_slice(&[0; 4]);
            for v in [crc.sum(), body.len() as u32, data.len() as u32] {
                central.extend_from_slice(&v.to_le_bytes());
            }
            central.extend_from_slice(&(name.len() as u16).to_le_bytes());
            central.extend_from_slice(&[0; 12]);
            central.extend_from_slice(&offset.to_le_bytes());
            central.extend_from_slice(name.as_bytes());
        }
        let cd_offset = out.len() as u32;
        out.extend_from_slice(&central);
        out.extend_from_slice(&EOCD_SIG.to_le_bytes());
        out.extend_from_slice(&[0; 4]);
        out.extend_from_slice(&(files.len() as u16).to_le_bytes());
        out.extend_from_slice(&(files.len() as u16).to_le_bytes());
        out.extend_from_slice(&(central.len() as u32).to_le_bytes());
        out.extend_from_slice(&cd_offset.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out
    }

    #[test]
    fn stored_and_deflated_entries_read_back() {
        let big = vec![7u8; 5000];
        let z = zip(&[("a.txt", b"hello", false), ("dir/b.bin", &big, true)]);
        let a = Archive::open(&z).unwrap();
        assert_eq!(&*a.read("a.txt", 100).unwrap().unwrap(), b"hello");
        assert!(matches!(
            a.read("a.txt", 100).unwrap(),
            Some(Cow::Borrowed(_))
        ));
        assert_eq!(&*a.read("dir/b.bin", 5000).unwrap().unwrap(), &big[..]);
        assert!(a.read("c", 10).unwrap().is_none());
        // A bound smaller than the entry is an error, not a truncation.
        assert!(matches!(
            a.read("dir/b.bin", 4999),
            Err(SceneError::Corrupt(_))
        ));
        // From a file, without reading the whole archive.
        let mut cur = std::io::Cursor::new(&z);
        let b = read_entry(&mut cur, z.len() as u64, "dir/b.bin", 5000).unwrap();
        assert_eq!(b.unwrap(), big);
        assert!(
            read_entry(&mut cur, z.len() as u64, "x", 5)
                .unwrap()
                .is_none()
        );
    }

    #[test]
    fn a_comment_after_the_end_record_is_allowed() {
        let mut z = zip(&[("a", b"xyz", false)]);
        let n = z.len();
        z[n - 2..].copy_from_slice(&5u16.to_le_bytes());
        z.extend_from_slice(b"hello");
        assert_eq!(
            &*Archive::open(&z).unwrap().read("a", 3).unwrap().unwrap(),
            b"xyz"
        );
    }

    #[test]
    fn damaged_archives_are_typed_errors() {
        let z = zip(&[("a", b"some data here", false), ("b", &[1; 300], true)]);
        // Every truncation: no end record.
        for cut in 0..z.len() {
            assert!(
                matches!(Archive::open(&z[..cut]), Err(SceneError::Corrupt(_))),
                "{cut}"
            );
        }
        // A flipped data byte: the CRC.
        let mut bad = z.clone();
        bad[31] ^= 1;
        let a = Archive::open(&bad).unwrap();
        assert!(matches!(a.read("a", 100), Err(SceneError::Checksum(_))));
        // An entry whose offset points past its data.
        let cd = u32_at(&z, z.len() - 6) as usize;
        let mut bad = z.clone();
        bad[cd + 42..cd + 46].copy_from_slice(&1_000u32.to_le_bytes());
        assert!(matches!(Archive::open(&bad), Err(SceneError::Corrupt(_))));
        // ZIP64 markers and an unknown method.
        let mut bad = z.clone();
        bad[cd + 20..cd + 24].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            Archive::open(&bad),
            Err(SceneError::Unsupported(_))
        ));
        let mut bad = z.clone();
        bad[cd + 10] = 12;
        let a = Archive::open(&bad).unwrap();
        assert!(matches!(a.read("a", 100), Err(SceneError::Unsupported(_))));
    }

    #[test]
    fn inflation_is_bounded_by_the_archive_size() {
        // 20 MB of zeros deflate to about 20 KB: past 2× the archive + 1 MiB.
        let zeros = vec![0u8; 20 << 20];
        let z = zip(&[("bomb", &zeros, true)]);
        assert!(z.len() < 100_000);
        let a = Archive::open(&z).unwrap();
        let e = a.read("bomb", u64::MAX).unwrap_err();
        assert!(e.to_string().contains("compression bomb"), "{e}");
    }

    #[test]
    fn unsafe_names_are_refused() {
        for name in ["../evil", "/abs", "a/../b", "a//b", "c:\\x", "./a", ""] {
            assert!(!is_safe_name(name), "{name}");
        }
        for name in ["meta.json", "textures/means_l.webp", "a..b"] {
            assert!(is_safe_name(name), "{name}");
        }
        let z = zip(&[("../evil", b"x", false)]);
        let e = Archive::open(&z).err().unwrap();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
    }
}
