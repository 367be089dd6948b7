//! PlayCanvas SOG ("Spatially Ordered Gaussians"): a `meta.json` and 8-bit images, read either
//! unbundled (a directory, or its `meta.json`) or bundled (`.sog`: a ZIP of the same files at its
//! root, read with [`zip`]). Read-only: splatmark does not write SOG.
//!
//! Sources: the specification (developer.playcanvas.com/user-manual/gaussian-splatting/formats/sog
//! and …/formats/sog-v2, repository `playcanvas/developer-site`,
//! `docs/user-manual/gaussian-splatting/formats/sog.md`), PlayCanvas's reader and writer
//! (`playcanvas/splat-transform` 3.2.0, `src/lib/readers/read-sog.ts`, `read-sog-v1.ts`,
//! `src/lib/writers/write-sog.ts`, `src/lib/io/write/zip-file-system.ts`) and the engine's decoder
//! (`playcanvas/engine`, `src/scene/gsplat/gsplat-sog-data.js`). Where the spec's prose and the
//! code disagree, the code, on which the writer, both readers and the spec's snippets agree, is
//! followed: the spec's quaternion snippet labels mode 0 "omitted = x" but places the
//! reconstructed component first (w), as the code does; its centroid table gives 96 pixels for one
//! band where 64·3 = 192 is what is written and read.
//!
//! **Versions.** `meta.json` without `version` is the legacy SOGS layout (v1: `shape`/`dtype`,
//! per-property linear `mins`/`maxs`); `version: 2` uses 256-entry codebooks. Both are read.
//! The v2 page says "the current version is version 3", but neither the spec pages stored nor
//! splat-transform 3.2.0 (which reads and writes only 2 and refuses any other number) nor the
//! engine describe its encoding, so version 3 and later are refused with
//! [`SceneError::Unsupported`] naming the version rather than decoded by guess.
//!
//! **Layout.** Gaussian `i` is pixel `i` of every per-Gaussian image in row-major order (`x = i %
//! W`, `y = i / W`); `count ≤ W·H` and trailing pixels are ignored. Images should be lossless
//! WebP; the spec allows other 8-bit RGB(A) formats, so PNG is read too. Lossy WebP (a `VP8 `
//! chunk) is refused: the spec forbids it, and its noise in a position's high byte or a
//! quaternion's mode byte moves a Gaussian arbitrarily. An image without alpha reads as alpha 255.
//!
//! **Decoding** (`lerp(a, b, t) = a + (b − a)·t`, bytes `b ∈ 0..=255`):
//! - positions (`means_l`, `means_u`, RGB): per axis `q = u << 8 | l` (16 bits),
//!   `n = lerp(mins[k], maxs[k], q / 65535)`, then the inverse of the writer's
//!   `sign(v)·ln(|v| + 1)`: `sign(n)·(e^|n| − 1)`;
//! - rotation (`quats`, RGBA, "smallest three"): `mode = A − 252 ∈ 0..=3` is the index of the
//!   largest-magnitude component in PLY order `(rot_0..rot_3) = (w, x, y, z)` — our order — which
//!   the writer made positive and dropped; R, G, B are the other three in that order, each
//!   `(b / 255 − 0.5)·√2`; the dropped one is `√max(0, 1 − a² − b² − c²)`. `A < 252` is invalid
//!   (the spec reserves it): refused. v1 packs quaternions the same way (engine; splat-transform's
//!   v1 reader);
//! - scales (`scales`, RGB): v2 `codebook[b]`, v1 `lerp(mins[k], maxs[k], b / 255)`: log-scales;
//! - colour and opacity (`sh0`, RGBA): R, G, B are the DC coefficients (`codebook[b]`, v1 per
//!   channel `lerp`); in v2 A is the opacity itself, `sigmoid(logit)·255` truncated, read as
//!   `logit(A / 255)` (clamped, [`logit`]); in v1 A is `lerp(mins[3], maxs[3], A / 255)`, a logit;
//! - higher SH (`shN`, optional): v2 `shN.bands ∈ 1..=3` bands (3, 8, 15 coefficients), a
//!   palette of `shN.count ≤ 65 536` entries in `shN_centroids`, 64 entries per row, entry `n`'s
//!   coefficient `j` at pixel `((n % 64)·coeffs + j, n / 64)`, its R, G, B the three channels as
//!   indices into `shN.codebook` (the image is `64·coeffs` wide); `shN_labels` holds each
//!   Gaussian's entry as `R + (G << 8)`. v1 has no `bands`: the width (192, 512, 960) gives it, and
//!   values are `lerp(shN.mins, shN.maxs, b / 255)`;
//! - a codebook is 256 numbers; a leading `null` (what older splat-transform wrote for a −∞ scale)
//!   is patched as the engine does (`cb[1] + (cb[1] − cb[255]) / 255`); any other `null` is
//!   refused.
//!
//! **Coordinates.** The v2 spec: "SOG stores Gaussians in the same coordinate system as 3DGS PLY
//! files" (viewers rotate 180° about z to show them y-up), as for v3; splat-transform writes and
//! reads them in PLY space. So nothing is flipped. `antialias` / `model` flags are not kept.
//!
//! **Bounds.** Before any image is decoded, the count is checked against [`Limits`] and against
//! the files' size ([`MAX_EXPANSION`]), each image's dimensions against what the count allows
//! ([`max_pixels`]), `meta.json` against [`MAX_META_BYTES`]; [`read_overhead`] bounds what a read
//! holds besides the file and the scene (the service reserves it, `scene::cost`).
//!
//! Besides the tests' own encodings, real files were read (not kept in the repository): the
//! PlayCanvas engine's example assets `playcanvas-logo` (v1, 307 128 Gaussians), `playbot/4_0`
//! (v2, 8 406, SH degree 2) and the bundled `wave_0001.sog` / `monkey_0001.sog` (v2).

use std::borrow::Cow;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::ImageDecoder;
use serde::Deserialize;

use crate::scene::format::{GaussianBuilder, Limits, RawGaussian};
use crate::scene::zip::{self, Archive, is_safe_name};
use crate::scene::{Gaussians, SceneError, logit, rest_len_for};

/// The file every SOG is described by, at the root of a bundle.
pub const META_NAME: &str = "meta.json";
/// Largest `meta.json` read (real ones take 2 to 25 KB: three codebooks of 256 numbers).
pub const MAX_META_BYTES: u64 = 256 << 10;
/// A SOG's files hold at least 1/64 byte per Gaussian (real ones 4 to 20); a file declaring
/// more Gaussians than 64 × its bytes (and more than [`COUNT_FLOOR`]) is refused unread.
pub const MAX_EXPANSION: u64 = 64;
/// Counts accepted whatever the file's size.
pub const COUNT_FLOOR: u64 = 1 << 16;
/// What writing SOG answers.
pub const READ_ONLY: &str =
    "SOG is read-only in splatmark; write ply, compressed-ply, splat or spz";
/// Largest SH palette (16-bit labels) and the largest centroid image (15 coefficients).
const MAX_PALETTE: u64 = 1 << 16;
const MAX_CENTROID_PIXELS: u64 = 64 * 15 * (MAX_PALETTE / 64);
/// Bytes a read may hold per pixel of the per-Gaussian images: up to six decoded RGBA images,
/// one decoder buffer and the decoder's own tables.
const BYTES_PER_PIXEL: u64 = 40;

/// Most pixels a per-Gaussian image may have for `count` Gaussians: writers pad to a rectangle
/// (splat-transform: sides rounded up to multiples of 4, `≤ count + 4√count + 16`).
pub fn max_pixels(count: u64) -> u64 {
    count.saturating_add(count / 4).saturating_add(1 << 16)
}

/// An upper bound of what reading a SOG of `file_bytes` declaring `count` Gaussians holds besides
/// the file and the decoded scene: the decoded images, the centroids, what deflated entries
/// inflate to ([`zip::INFLATE_RATIO`]) and `meta.json` parsed (at most 16 bytes a number of at
/// least 2 characters, its vectors grown twice over).
pub fn read_overhead(count: u64, file_bytes: u64) -> u64 {
    max_pixels(count)
        .saturating_mul(BYTES_PER_PIXEL)
        .saturating_add(MAX_CENTROID_PIXELS * 8)
        .saturating_add(file_bytes.saturating_mul(zip::INFLATE_RATIO))
        .saturating_add(zip::INFLATE_FLOOR + 32 * MAX_META_BYTES)
}

// ---- meta.json --------------------------------------------------------------------------------

#[derive(Deserialize)]
struct Files {
    files: Vec<String>,
}

#[derive(Deserialize)]
struct Ranged<T> {
    mins: T,
    maxs: T,
    files: Vec<String>,
}

#[derive(Deserialize)]
struct Codebooked {
    codebook: Vec<Option<f64>>,
    files: Vec<String>,
}

#[derive(Deserialize)]
struct ShNV2 {
    count: u64,
    bands: u64,
    codebook: Vec<Option<f64>>,
    files: Vec<String>,
}

#[derive(Deserialize)]
struct MetaV2 {
    count: u64,
    means: Ranged<[f64; 3]>,
    scales: Codebooked,
    quats: Files,
    sh0: Codebooked,
    #[serde(rename = "shN")]
    sh_n: Option<ShNV2>,
}

#[derive(Deserialize)]
struct MeansV1 {
    shape: Vec<u64>,
    mins: [f64; 3],
    maxs: [f64; 3],
    files: Vec<String>,
}

#[derive(Deserialize)]
struct MetaV1 {
    means: MeansV1,
    scales: Ranged<[f64; 3]>,
    quats: Files,
    sh0: Ranged<[f64; 4]>,
    #[serde(rename = "shN")]
    sh_n: Option<Ranged<f64>>,
}

/// How bytes become values: a codebook, or a linear range.
#[derive(Clone, Debug)]
enum Dequant {
    Codebook(Vec<f32>),
    Lerp(f64, f64),
}

impl Dequant {
    fn codebook(raw: Vec<Option<f64>>, what: &str) -> Result<Self, SceneError> {
        if raw.len() != 256 {
            return Err(SceneError::Header(format!(
                "meta.json: {what}.codebook has {} entries, not 256",
                raw.len()
            )));
        }
        let mut cb = raw;
        if cb[0].is_none()
            && let (Some(a), Some(z)) = (cb[1], cb[255])
        {
            cb[0] = Some(a + (a - z) / 255.0);
        }
        cb.into_iter()
            .enumerate()
            .map(|(k, v)| match v {
                Some(v) => Ok(v as f32),
                None => Err(SceneError::Header(format!(
                    "meta.json: {what}.codebook[{k}] is null"
                ))),
            })
            .collect::<Result<_, _>>()
            .map(Dequant::Codebook)
    }

    fn get(&self, b: u8) -> f32 {
        match self {
            Dequant::Codebook(cb) => cb[usize::from(b)],
            Dequant::Lerp(a, z) => (a + (z - a) * f64::from(b) / 255.0) as f32,
        }
    }
}

/// What `meta.json` declares, checked and made version-independent.
struct Plan {
    count: u64,
    means: ([f64; 3], [f64; 3], [String; 2]),
    scales: ([Dequant; 3], String),
    quats: String,
    colours: [Dequant; 3],
    /// v1: the opacity logit's range; v2: `None` (alpha is the opacity).
    opacity: Option<Dequant>,
    sh0: String,
    sh: Option<ShPlan>,
}

struct ShPlan {
    /// v2: from `meta.json`; v1: from the centroid image's width.
    bands: Option<u8>,
    /// v2: the palette's size; v1: the centroid image's slots.
    palette: Option<u64>,
    values: Dequant,
    centroids: String,
    labels: String,
}

fn files<const N: usize>(f: Vec<String>, what: &str) -> Result<[String; N], SceneError> {
    if let Some(bad) = f.iter().find(|n| !is_safe_name(n)) {
        return Err(SceneError::Corrupt(format!(
            "meta.json: {what} names {bad:?}, which is not a relative path beside meta.json"
        )));
    }
    let n = f.len();
    f.try_into().map_err(|_| {
        SceneError::Header(format!("meta.json: {what}.files lists {n} files, not {N}"))
    })
}

fn header(e: serde_json::Error) -> SceneError {
    SceneError::Header(format!("meta.json: {e}"))
}

/// Only `version`: every other field is skipped unparsed.
#[derive(Deserialize)]
struct Version {
    version: Option<serde_json::Value>,
}

impl Plan {
    fn parse(bytes: &[u8]) -> Result<Self, SceneError> {
        let v: Version = serde_json::from_slice(bytes).map_err(header)?;
        match &v.version {
            None => Self::v1(serde_json::from_slice(bytes).map_err(header)?),
            Some(n) if n.as_u64() == Some(2) => {
                Self::v2(serde_json::from_slice(bytes).map_err(header)?)
            }
            Some(n) if n.is_u64() => Err(SceneError::Unsupported(format!(
                "SOG version {n}: versions 1 (legacy, no \"version\") and 2 are read; convert it \
                 to .ply first (e.g. `splat-transform scene.sog scene.ply`)"
            ))),
            Some(n) => Err(SceneError::Header(format!(
                "meta.json: \"version\" is {n}, not an integer"
            ))),
        }
    }

    fn v2(m: MetaV2) -> Result<Self, SceneError> {
        let scales = Dequant::codebook(m.scales.codebook, "scales")?;
        let colours = Dequant::codebook(m.sh0.codebook, "sh0")?;
        let sh = match m.sh_n {
            Some(s) if s.bands > 0 => {
                if s.bands > 3 {
                    return Err(SceneError::UnsupportedShDegree(s.bands as usize));
                }
                if s.count == 0 || s.count > MAX_PALETTE {
                    return Err(SceneError::Header(format!(
                        "meta.json: shN.count is {}, not 1 to {MAX_PALETTE}",
                        s.count
                    )));
                }
                let [centroids, labels] = files(s.files, "shN")?;
                Some(ShPlan {
                    bands: Some(s.bands as u8),
                    palette: Some(s.count),
                    values: Dequant::codebook(s.codebook, "shN")?,
                    centroids,
                    labels,
                })
            }
            _ => None,
        };
        Ok(Self {
            count: m.count,
            means: (m.means.mins, m.means.maxs, files(m.means.files, "means")?),
            scales: (
                [scales.clone(), scales.clone(), scales],
                one(m.scales.files, "scales")?,
            ),
            quats: one(m.quats.files, "quats")?,
            colours: [colours.clone(), colours.clone(), colours],
            opacity: None,
            sh0: one(m.sh0.files, "sh0")?,
            sh,
        })
    }

    fn v1(m: MetaV1) -> Result<Self, SceneError> {
        let count =
            *m.means.shape.first().ok_or_else(|| {
                SceneError::Header("meta.json (legacy): means.shape is empty".into())
            })?;
        let lerp = |r: &Ranged<[f64; 3]>| [0, 1, 2].map(|k| Dequant::Lerp(r.mins[k], r.maxs[k]));
        let sh0 = &m.sh0;
        let sh = match m.sh_n {
            Some(s) => {
                let [centroids, labels] = files(s.files, "shN")?;
                Some(ShPlan {
                    bands: None,
                    palette: None,
                    values: Dequant::Lerp(s.mins, s.maxs),
                    centroids,
                    labels,
                })
            }
            None => None,
        };
        Ok(Self {
            count,
            means: (m.means.mins, m.means.maxs, files(m.means.files, "means")?),
            scales: (lerp(&m.scales), one(m.scales.files, "scales")?),
            quats: one(m.quats.files, "quats")?,
            colours: [0, 1, 2].map(|c| Dequant::Lerp(sh0.mins[c], sh0.maxs[c])),
            opacity: Some(Dequant::Lerp(sh0.mins[3], sh0.maxs[3])),
            sh0: one(m.sh0.files, "sh0")?,
            sh,
        })
    }

    /// The SH degree, as far as `meta.json` tells (v1's comes from an image: 3 is the bound).
    fn sh_degree_bound(&self) -> u8 {
        self.sh.as_ref().map_or(0, |s| s.bands.unwrap_or(3))
    }

    /// Checks the count against the limits and against `file_bytes`, the files' size.
    fn check_count(&self, limits: &Limits, file_bytes: u64) -> Result<usize, SceneError> {
        let n = limits.check_count(self.count)?;
        self.plausible(file_bytes)?;
        Ok(n)
    }

    /// Refuses more Gaussians than [`MAX_EXPANSION`] per byte of the files.
    fn plausible(&self, file_bytes: u64) -> Result<(), SceneError> {
        if self.count > file_bytes.saturating_mul(MAX_EXPANSION).max(COUNT_FLOOR) {
            return Err(SceneError::Corrupt(format!(
                "meta.json declares {} Gaussians in {file_bytes} bytes of files: more than \
                 {MAX_EXPANSION} per byte, which no real SOG holds",
                self.count
            )));
        }
        Ok(())
    }
}

/// The first file of a property that names one (a first file is all these read).
fn one(f: Vec<String>, what: &str) -> Result<String, SceneError> {
    let [name] = files::<1>(f.into_iter().take(1).collect(), what)?;
    Ok(name)
}

// ---- images -----------------------------------------------------------------------------------

/// A decoded image: 3 (RGB) or 4 (RGBA) bytes per pixel.
struct Texture {
    width: u32,
    height: u32,
    channels: usize,
    data: Vec<u8>,
}

impl Texture {
    fn pixels(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// Pixel `i` as RGBA (alpha 255 when the image has none).
    fn px(&self, i: usize) -> [u8; 4] {
        let p = &self.data[i * self.channels..];
        [
            p[0],
            p[1],
            p[2],
            if self.channels == 4 { p[3] } else { 255 },
        ]
    }
}

/// What a WebP's chunks say that the decoder would accept silently: lossy or animated.
fn webp_refusal(bytes: &[u8]) -> Option<&'static str> {
    let mut pos = 12usize;
    while let Some(head) = bytes.get(pos..pos.saturating_add(8)) {
        match &head[..4] {
            b"VP8 " => {
                return Some(
                    "lossy WebP (the spec asks for lossless: lossy coding corrupts the quantised \
                     values)",
                );
            }
            b"ANIM" | b"ANMF" => return Some("an animated WebP"),
            _ => {}
        }
        let size = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
        pos = pos
            .saturating_add(8)
            .saturating_add(size)
            .saturating_add(size & 1);
    }
    None
}

/// Decodes image `name` (WebP or PNG, 8-bit RGB or RGBA), after checking its dimensions against
/// `max_pixels`.
fn decode_texture(name: &str, bytes: &[u8], max_pixels: u64) -> Result<Texture, SceneError> {
    let bad = |e: image::ImageError| SceneError::Corrupt(format!("{name}: {e}"));
    if bytes.len() >= 12 && &bytes[..4] == b"RIFF" && &bytes[8..12] == b"WEBP" {
        if let Some(why) = webp_refusal(bytes) {
            return Err(SceneError::Unsupported(format!("{name} is {why}")));
        }
        let d = image::codecs::webp::WebPDecoder::new(Cursor::new(bytes)).map_err(bad)?;
        read_image(name, d, max_pixels)
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        let d = image::codecs::png::PngDecoder::new(Cursor::new(bytes)).map_err(bad)?;
        read_image(name, d, max_pixels)
    } else {
        let shown: Vec<String> = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
        Err(SceneError::Unsupported(format!(
            "{name} is not a WebP or PNG image (first bytes: {})",
            shown.join(" ")
        )))
    }
}

fn read_image(name: &str, d: impl ImageDecoder, max_pixels: u64) -> Result<Texture, SceneError> {
    let (width, height) = d.dimensions();
    let pixels = u64::from(width) * u64::from(height);
    if pixels > max_pixels {
        return Err(SceneError::Corrupt(format!(
            "{name} is {width}×{height} pixels, more than the {max_pixels} meta.json allows"
        )));
    }
    let channels = match d.color_type() {
        image::ColorType::Rgb8 => 3,
        image::ColorType::Rgba8 => 4,
        c => {
            return Err(SceneError::Unsupported(format!(
                "{name} has colour type {c:?} (8-bit RGB or RGBA is read)"
            )));
        }
    };
    let mut data = vec![0u8; pixels as usize * channels];
    d.read_image(&mut data)
        .map_err(|e| SceneError::Corrupt(format!("{name}: {e}")))?;
    Ok(Texture {
        width,
        height,
        channels,
        data,
    })
}

// ---- decoding ---------------------------------------------------------------------------------

fn unlog(n: f64) -> f32 {
    (n.signum() * (n.abs().exp() - 1.0)) as f32
}

/// The smallest-three quaternion of a `quats` pixel, `(w, x, y, z)`.
fn unpack_quat(p: [u8; 4], index: usize) -> Result<[f32; 4], SceneError> {
    let Some(mode) = p[3].checked_sub(252) else {
        return Err(SceneError::Corrupt(format!(
            "Gaussian {index}: quaternion mode byte {} is not 252 to 255",
            p[3]
        )));
    };
    let c = [0, 1, 2].map(|k| (f64::from(p[k]) / 255.0 - 0.5) * std::f64::consts::SQRT_2);
    let mut q = [0.0; 4];
    let mut kept = c.iter();
    for (k, v) in q.iter_mut().enumerate() {
        *v = if k == usize::from(mode) {
            (1.0 - c.iter().map(|x| x * x).sum::<f64>()).max(0.0).sqrt()
        } else {
            *kept.next().unwrap_or(&0.0)
        };
    }
    Ok(q.map(|v| v as f32))
}

/// Decodes the scene `plan` describes, its images from `load(name, max_bytes)`.
fn decode<'a>(
    plan: &Plan,
    n: usize,
    mut load: impl FnMut(&str, u64) -> Result<Cow<'a, [u8]>, SceneError>,
) -> Result<Gaussians, SceneError> {
    // A per-Gaussian image, or (false) the SH centroids.
    let mut image = |name: &str, per_gaussian: bool| -> Result<Texture, SceneError> {
        let max_px = match per_gaussian {
            true => max_pixels(plan.count),
            false => MAX_CENTROID_PIXELS,
        };
        let bytes = load(name, max_px.saturating_mul(8).saturating_add(1 << 20))?;
        let t = decode_texture(name, &bytes, max_px)?;
        if per_gaussian && t.pixels() < plan.count {
            return Err(SceneError::Corrupt(format!(
                "{name} is {}×{} pixels, fewer than meta.json's count of {}",
                t.width, t.height, plan.count
            )));
        }
        Ok(t)
    };
    let (mins, maxs, [lo, hi]) = &plan.means;
    let (lo, hi) = (image(lo, true)?, image(hi, true)?);
    let quats = image(&plan.quats, true)?;
    let scales = image(&plan.scales.1, true)?;
    let sh0 = image(&plan.sh0, true)?;
    let sh = match &plan.sh {
        Some(s) => Some(ShImages::load(s, &mut image)?),
        None => None,
    };
    let degree = sh.as_ref().map_or(0, |s| s.bands);
    let mut rest = vec![0.0f32; rest_len_for(degree)];
    let mut b = GaussianBuilder::new(n, degree);
    for i in 0..n {
        let (l, u) = (lo.px(i), hi.px(i));
        let mean = [0, 1, 2].map(|k| {
            let q = f64::from((u16::from(u[k]) << 8) | u16::from(l[k]));
            unlog(mins[k] + (maxs[k] - mins[k]) * q / 65535.0)
        });
        let s = scales.px(i);
        let c = sh0.px(i);
        let opacity = match &plan.opacity {
            Some(range) => range.get(c[3]),
            None => logit(f32::from(c[3]) / 255.0),
        };
        if let Some(sh) = &sh {
            sh.fill(i, &mut rest)?;
        }
        b.push(RawGaussian {
            mean,
            log_scale: [0, 1, 2].map(|k| plan.scales.0[k].get(s[k])),
            rotation: unpack_quat(quats.px(i), i)?,
            opacity,
            dc: [0, 1, 2].map(|k| plan.colours[k].get(c[k])),
            rest: &rest,
        })?;
    }
    Ok(b.finish())
}

/// The higher-SH palette and labels, checked against each other.
struct ShImages<'p> {
    plan: &'p ShPlan,
    bands: u8,
    coeffs: usize,
    palette: u64,
    centroids: Texture,
    labels: Texture,
}

impl<'p> ShImages<'p> {
    fn load(
        s: &'p ShPlan,
        image: &mut impl FnMut(&str, bool) -> Result<Texture, SceneError>,
    ) -> Result<Self, SceneError> {
        let centroids = image(&s.centroids, false)?;
        let labels = image(&s.labels, true)?;
        let width = centroids.width as usize;
        let bands = match s.bands {
            Some(b) => b,
            None => match width {
                192 => 1,
                512 => 2,
                960 => 3,
                w => {
                    return Err(SceneError::Corrupt(format!(
                        "{} is {w} pixels wide, not 192, 512 or 960 (64 palette entries of 3, 8 \
                         or 15 coefficients)",
                        s.centroids
                    )));
                }
            },
        };
        let coeffs = rest_len_for(bands) / 3;
        let slots = u64::from(centroids.height) * 64;
        let palette = s.palette.unwrap_or(slots);
        if width != 64 * coeffs || slots < palette {
            return Err(SceneError::Corrupt(format!(
                "{} is {width}×{} pixels: {palette} palette entries of {coeffs} coefficients \
                 need {}×{}",
                s.centroids,
                centroids.height,
                64 * coeffs,
                palette.div_ceil(64)
            )));
        }
        Ok(Self {
            plan: s,
            bands,
            coeffs,
            palette,
            centroids,
            labels,
        })
    }

    /// Gaussian `i`'s higher SH coefficients, `[k][c]`.
    fn fill(&self, i: usize, rest: &mut [f32]) -> Result<(), SceneError> {
        let l = self.labels.px(i);
        let label = usize::from(l[0]) | (usize::from(l[1]) << 8);
        if label as u64 >= self.palette {
            return Err(SceneError::Corrupt(format!(
                "Gaussian {i}: SH palette entry {label} is past the palette's {} entries",
                self.palette
            )));
        }
        let row = (label / 64) * self.centroids.width as usize;
        for j in 0..self.coeffs {
            let p = self.centroids.px(row + (label % 64) * self.coeffs + j);
            for c in 0..3 {
                rest[j * 3 + c] = self.plan.values.get(p[c]);
            }
        }
        Ok(())
    }
}

// ---- entry points -----------------------------------------------------------------------------

/// Whether `bytes` are a ZIP archive with `meta.json` at its root (read from its central
/// directory, so `bytes` must be the whole file).
pub fn is_bundle(bytes: &[u8]) -> bool {
    bytes.starts_with(&zip::LOCAL_MAGIC)
        && Archive::open(bytes).is_ok_and(|a| a.contains(META_NAME))
}

fn missing(name: &str, place: &str) -> SceneError {
    SceneError::MissingFile {
        name: name.to_string(),
        place: place.to_string(),
    }
}

/// Reads a bundled SOG (`.sog`) held in memory.
pub fn read(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    let archive = Archive::open(bytes)?;
    const PLACE: &str = "the .sog archive";
    let meta = archive
        .read(META_NAME, MAX_META_BYTES)?
        .ok_or_else(|| missing(META_NAME, PLACE))?;
    let plan = Plan::parse(&meta)?;
    let n = plan.check_count(limits, bytes.len() as u64)?;
    decode(&plan, n, |name, max| {
        archive.read(name, max)?.ok_or_else(|| missing(name, PLACE))
    })
}

/// The Gaussian count and (an upper bound of) the SH degree a whole bundled SOG declares.
pub fn declared(bytes: &[u8]) -> Result<(u64, u8), SceneError> {
    let archive = Archive::open(bytes)?;
    let meta = archive
        .read(META_NAME, MAX_META_BYTES)?
        .ok_or_else(|| missing(META_NAME, "the .sog archive"))?;
    let plan = Plan::parse(&meta)?;
    plan.plausible(bytes.len() as u64)?;
    Ok((plan.count, plan.sh_degree_bound()))
}

/// Like [`declared`], from a file of `len` bytes: reads only its central directory and
/// `meta.json`. A ZIP without `meta.json` is [`SceneError::UnknownFormat`].
pub fn declared_in_file<R: std::io::Read + std::io::Seek>(
    r: &mut R,
    len: u64,
) -> Result<(u64, u8), SceneError> {
    let meta = zip::read_entry(r, len, META_NAME, MAX_META_BYTES)?.ok_or_else(|| {
        SceneError::UnknownFormat(
            "a ZIP archive without meta.json at its root (a bundled SOG holds meta.json and its \
             images)"
                .into(),
        )
    })?;
    let plan = Plan::parse(&meta)?;
    plan.plausible(len)?;
    Ok((plan.count, plan.sh_degree_bound()))
}

/// The `meta.json` an unbundled SOG at `path` is described by: `path` itself when it names a
/// `.json` file, `path/meta.json` for a directory; `None` for anything else.
pub fn meta_path(path: &Path) -> Option<PathBuf> {
    if path.is_dir() {
        return Some(path.join(META_NAME));
    }
    let ext = path.extension()?.to_str()?;
    ext.eq_ignore_ascii_case("json").then(|| path.to_path_buf())
}

/// Reads an unbundled SOG: `meta.json` at `meta` and the images it names beside it.
pub fn read_unbundled(meta: &Path, limits: &Limits) -> Result<Gaussians, SceneError> {
    let dir = meta.parent().unwrap_or(Path::new("."));
    let place = format!("directory {}", dir.display());
    let size_of = |path: &Path, name: &str| match std::fs::metadata(path) {
        Ok(m) => Ok(m.len()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(missing(name, &place)),
        Err(source) => Err(SceneError::Io {
            path: path.to_path_buf(),
            source,
        }),
    };
    let read_file = |path: &Path, max: u64| -> Result<Vec<u8>, SceneError> {
        let size = size_of(
            path,
            &path.file_name().unwrap_or_default().to_string_lossy(),
        )?;
        limits.check_file_size(size)?;
        if size > max {
            return Err(SceneError::Corrupt(format!(
                "{} is {size} bytes, more than the {max} it may hold",
                path.display()
            )));
        }
        std::fs::read(path).map_err(|source| SceneError::Io {
            path: path.to_path_buf(),
            source,
        })
    };
    let plan = Plan::parse(&read_file(meta, MAX_META_BYTES)?)?;
    let mut names: Vec<&str> = vec![&plan.means.2[0], &plan.means.2[1], &plan.quats];
    names.extend([plan.scales.1.as_str(), &plan.sh0]);
    if let Some(s) = &plan.sh {
        names.extend([s.centroids.as_str(), &s.labels]);
    }
    let mut total = size_of(meta, META_NAME)?;
    for name in names {
        total = total.saturating_add(size_of(&dir.join(name), name)?);
    }
    let n = plan.check_count(limits, total)?;
    decode(&plan, n, |name, max| {
        read_file(&dir.join(name), max).map(Cow::Owned)
    })
}

#[cfg(test)]
mod tests;
