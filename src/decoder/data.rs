//! Training and evaluation images for the decoder: discovery, the held-out split, decoding into
//! memory and random crops.
//!
//! # Split
//!
//! Every `.png` / `.jpg` / `.jpeg` file under the image folder (recursively, extension
//! case-insensitive) is named by its path **relative to that folder**, with `/` separators (e.g.
//! `kodak/kodim05.png`). An image is **held out** when the 64-bit FNV-1a hash of that name is
//! `≡ 0 (mod 10)` ([`is_held_out`]), about 10 % of the images. The rule depends on the name only,
//! so it is stable under adding or removing other images, across machines and across runs, and
//! `decoder train` and `decoder eval` agree on it without sharing any state. On the shared data
//! set (Kodak + CBSD68 + skimage, 99 images) it holds out 10 of them (`held_out_names` of the
//! tests lists them).
//!
//! # Crops
//!
//! Training batches are random `crop × crop` windows ([`ImageSet::sample_batch`]): an image drawn
//! uniformly, a scale `s` drawn uniformly in `[min_scale, 1]` (so a crop sees a window of
//! `crop / s` source pixels, resampled to `crop`: more content per crop, and content at roughly
//! the scale of the evaluation images, which are downscaled to a short side of 256), a uniform
//! position, and a horizontal flip with probability ½. Resampling averages four bilinear taps
//! spread over the source footprint of each output pixel, a cheap anti-aliasing filter that is
//! adequate down to s = 0.25.

use std::path::{Path, PathBuf};

use crate::attack::diff::EotRng;

/// Why images could not be listed or loaded.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The folder could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An image could not be decoded.
    #[error("cannot decode {path}: {source}")]
    Decode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    /// No image in the requested part of the split.
    #[error("no {what} images under {dir}")]
    Empty { what: &'static str, dir: PathBuf },
    /// An image is smaller than the crop.
    #[error("{name} is {width}×{height}, smaller than the {crop}-pixel crop")]
    TooSmall {
        name: String,
        width: usize,
        height: usize,
        crop: usize,
    },
}

/// 64-bit FNV-1a hash.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Whether the image named `relative_name` (path relative to the image folder, `/`-separated)
/// belongs to the held-out split: FNV-1a-64 of the name ≡ 0 (mod 10).
pub fn is_held_out(relative_name: &str) -> bool {
    fnv1a64(relative_name.as_bytes()).is_multiple_of(10)
}

/// Which part of the split to load.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Images with `!is_held_out(name)`.
    Train,
    /// Images with `is_held_out(name)`.
    HeldOut,
    /// Every image.
    All,
}

impl Split {
    fn keeps(self, name: &str) -> bool {
        match self {
            Split::Train => !is_held_out(name),
            Split::HeldOut => is_held_out(name),
            Split::All => true,
        }
    }

    fn label(self) -> &'static str {
        match self {
            Split::Train => "training",
            Split::HeldOut => "held-out",
            Split::All => "",
        }
    }
}

/// `(relative name, path)` of every `.png` / `.jpg` / `.jpeg` under `dir`, recursively, sorted by
/// name. Hidden entries (name starting with `.`) are skipped.
pub fn list_images(dir: &Path) -> Result<Vec<(String, PathBuf)>, DataError> {
    fn walk(
        root: &Path,
        dir: &Path,
        out: &mut Vec<(String, PathBuf)>,
        depth: usize,
    ) -> Result<(), DataError> {
        let io = |source| DataError::Io {
            path: dir.to_path_buf(),
            source,
        };
        if depth > 32 {
            return Ok(());
        }
        for entry in std::fs::read_dir(dir).map_err(io)? {
            let entry = entry.map_err(io)?;
            let path = entry.path();
            let name = entry.file_name();
            if name.to_string_lossy().starts_with('.') {
                continue;
            }
            let kind = entry.file_type().map_err(io)?;
            let kind_is_dir = kind.is_dir() || (kind.is_symlink() && path.is_dir());
            if kind_is_dir {
                walk(root, &path, out, depth + 1)?;
            } else {
                let ext = path
                    .extension()
                    .and_then(|e| e.to_str())
                    .map(str::to_ascii_lowercase);
                if matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
                    let rel = path.strip_prefix(root).unwrap_or(&path);
                    let rel: Vec<String> = rel
                        .components()
                        .map(|c| c.as_os_str().to_string_lossy().into_owned())
                        .collect();
                    out.push((rel.join("/"), path));
                }
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out, 0)?;
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// An RGB image in memory: planar f32 in [0, 1], `data[c·H·W + y·W + x]`.
#[derive(Debug, Clone)]
pub struct Image {
    /// Name relative to the image folder.
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Image {
    /// From an 8-bit RGB image.
    pub fn from_rgb8(name: impl Into<String>, img: &image::RgbImage) -> Self {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let mut data = vec![0.0f32; 3 * w * h];
        for (i, p) in img.pixels().enumerate() {
            for c in 0..3 {
                data[c * w * h + i] = f32::from(p.0[c]) / 255.0;
            }
        }
        Self {
            name: name.into(),
            width: w,
            height: h,
            data,
        }
    }

    /// Decodes an image file (any colour type, converted to RGB).
    pub fn open(name: impl Into<String>, path: &Path) -> Result<Self, DataError> {
        let img = crate::image_file::open(path).map_err(|source| DataError::Decode {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self::from_rgb8(name, &img.to_rgb8()))
    }

    /// Bilinear sample of channel `c` at continuous pixel coordinates (pixel centres at
    /// integers), edges clamped.
    fn bilinear(&self, c: usize, x: f32, y: f32) -> f32 {
        let (w, h) = (self.width, self.height);
        let x = x.clamp(0.0, (w - 1) as f32);
        let y = y.clamp(0.0, (h - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let plane = &self.data[c * w * h..(c + 1) * w * h];
        let top = plane[y0 * w + x0] * (1.0 - fx) + plane[y0 * w + x1] * fx;
        let bottom = plane[y1 * w + x0] * (1.0 - fx) + plane[y1 * w + x1] * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// Writes a `crop × crop` planar window into `out` (length `3·crop²`): source window of side
    /// `crop / scale` at (`left`, `top`) (source pixels), resampled, optionally mirrored.
    fn write_crop(
        &self,
        out: &mut [f32],
        crop: usize,
        scale: f32,
        left: f32,
        top: f32,
        flip: bool,
    ) {
        let step = 1.0 / scale;
        // Four taps at ±¼ of the footprint of an output pixel (only when shrinking).
        let spread = if step > 1.0 { 0.25 * step } else { 0.0 };
        for c in 0..3 {
            for y in 0..crop {
                let sy = top + (y as f32 + 0.5) * step - 0.5;
                for x in 0..crop {
                    let xx = if flip { crop - 1 - x } else { x };
                    let sx = left + (xx as f32 + 0.5) * step - 0.5;
                    let v = if spread > 0.0 {
                        0.25 * (self.bilinear(c, sx - spread, sy - spread)
                            + self.bilinear(c, sx + spread, sy - spread)
                            + self.bilinear(c, sx - spread, sy + spread)
                            + self.bilinear(c, sx + spread, sy + spread))
                    } else {
                        self.bilinear(c, sx, sy)
                    };
                    out[c * crop * crop + y * crop + x] = v;
                }
            }
        }
    }

    /// Resized so that the short side is `short` (triangle filter), then centre-cropped to
    /// `short × short`, as 8-bit RGB (the evaluation geometry).
    pub fn square_rgb8(&self, short: u32) -> image::RgbImage {
        let rgb = self.to_rgb8();
        square_rgb8(&rgb, short)
    }

    /// Back to 8-bit RGB (rounded).
    pub fn to_rgb8(&self) -> image::RgbImage {
        let (w, h) = (self.width, self.height);
        image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
            let i = y as usize * w + x as usize;
            image::Rgb(std::array::from_fn(|c| {
                (self.data[c * w * h + i] * 255.0).round().clamp(0.0, 255.0) as u8
            }))
        })
    }
}

/// `img` resized so that its short side is `short` (triangle filter), then centre-cropped to
/// `short × short`.
pub fn square_rgb8(img: &image::RgbImage, short: u32) -> image::RgbImage {
    let (w, h) = img.dimensions();
    let s = f64::from(short) / f64::from(w.min(h));
    let (nw, nh) = (
        ((f64::from(w) * s).round() as u32).max(short),
        ((f64::from(h) * s).round() as u32).max(short),
    );
    let resized = if (nw, nh) == (w, h) {
        img.clone()
    } else {
        image::imageops::resize(img, nw, nh, image::imageops::FilterType::Triangle)
    };
    let (left, top) = ((nw - short) / 2, (nh - short) / 2);
    image::imageops::crop_imm(&resized, left, top, short, short).to_image()
}

/// Images decoded into memory.
#[derive(Debug, Clone, Default)]
pub struct ImageSet {
    pub images: Vec<Image>,
}

impl ImageSet {
    /// Loads the `split` part of the images under `dir` (sorted by name).
    pub fn load(dir: &Path, split: Split) -> Result<Self, DataError> {
        let images: Vec<Image> = list_images(dir)?
            .into_iter()
            .filter(|(name, _)| split.keeps(name))
            .map(|(name, path)| Image::open(name, &path))
            .collect::<Result<_, _>>()?;
        if images.is_empty() {
            return Err(DataError::Empty {
                what: split.label(),
                dir: dir.to_path_buf(),
            });
        }
        Ok(Self { images })
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.images.len()
    }

    /// Whether there are no images.
    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }

    /// Fails if an image is smaller than `crop` on a side.
    pub fn check_crop(&self, crop: usize) -> Result<(), DataError> {
        match self
            .images
            .iter()
            .find(|i| i.width < crop || i.height < crop)
        {
            Some(i) => Err(DataError::TooSmall {
                name: i.name.clone(),
                width: i.width,
                height: i.height,
                crop,
            }),
            None => Ok(()),
        }
    }

    /// `batch` random crops (see the module docs), planar `[batch, 3, crop, crop]` flattened.
    ///
    /// # Panics
    /// If the set is empty or an image is smaller than `crop` ([`check_crop`](Self::check_crop)).
    pub fn sample_batch(
        &self,
        rng: &mut EotRng,
        batch: usize,
        crop: usize,
        min_scale: f32,
        flip: bool,
    ) -> Vec<f32> {
        assert!(!self.images.is_empty(), "no images to sample from");
        let per = 3 * crop * crop;
        let mut out = vec![0.0f32; batch * per];
        for chunk in out.chunks_exact_mut(per) {
            let img = &self.images[rng.range_int(0, self.images.len() as u64 - 1) as usize];
            assert!(
                img.width >= crop && img.height >= crop,
                "{} is smaller than the crop",
                img.name
            );
            // The window must fit: scale ≥ crop / short side.
            let short = img.width.min(img.height) as f32;
            let lo = min_scale.clamp(crop as f32 / short, 1.0);
            let scale = rng.range(f64::from(lo), 1.0) as f32;
            let side = crop as f32 / scale;
            let left = rng.range(0.0, f64::from((img.width as f32 - side).max(0.0))) as f32;
            let top = rng.range(0.0, f64::from((img.height as f32 - side).max(0.0))) as f32;
            let mirror = flip && rng.uniform() < 0.5;
            img.write_crop(chunk, crop, scale, left, top, mirror);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_is_deterministic_and_about_ten_percent() {
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
        let names: Vec<String> = (0..5000)
            .map(|i| format!("set{}/img{i:05}.png", i % 7))
            .collect();
        let held: Vec<bool> = names.iter().map(|n| is_held_out(n)).collect();
        let again: Vec<bool> = names.iter().map(|n| is_held_out(n)).collect();
        assert_eq!(held, again);
        let frac = held.iter().filter(|&&h| h).count() as f64 / names.len() as f64;
        assert!((0.085..0.115).contains(&frac), "held-out fraction {frac}");
    }

    fn write_png(path: &Path, w: u32, h: u32, seed: u8) {
        let img = image::RgbImage::from_fn(w, h, |x, y| {
            image::Rgb([
                (x as u8).wrapping_mul(3).wrapping_add(seed),
                (y as u8).wrapping_mul(5),
                seed,
            ])
        });
        img.save(path).unwrap();
    }

    #[test]
    fn listing_is_recursive_sorted_and_split_consistent() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("b/c")).unwrap();
        for (i, name) in ["z.png", "b/a.PNG", "b/c/x.jpg", "a.png"]
            .iter()
            .enumerate()
        {
            write_png(&dir.path().join(name), 40, 30, i as u8);
        }
        std::fs::write(dir.path().join("notes.txt"), "x").unwrap();
        std::fs::write(dir.path().join(".hidden.png"), "x").unwrap();
        let names: Vec<String> = list_images(dir.path())
            .unwrap()
            .into_iter()
            .map(|(n, _)| n)
            .collect();
        assert_eq!(names, ["a.png", "b/a.PNG", "b/c/x.jpg", "z.png"]);
        let all = ImageSet::load(dir.path(), Split::All).unwrap();
        assert_eq!(all.len(), 4);
        assert_eq!((all.images[0].width, all.images[0].height), (40, 30));
        // Train ∪ held-out = all, disjoint.
        let train = names.iter().filter(|n| !is_held_out(n)).count();
        match ImageSet::load(dir.path(), Split::Train) {
            Ok(s) => assert_eq!(s.len(), train),
            Err(DataError::Empty { .. }) => assert_eq!(train, 0),
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn crops_have_the_right_shape_range_and_reproduce() {
        let img = Image::from_rgb8(
            "g",
            &image::RgbImage::from_fn(100, 80, |x, y| {
                image::Rgb([(x * 2) as u8, (y * 3) as u8, 128])
            }),
        );
        let set = ImageSet { images: vec![img] };
        set.check_crop(64).unwrap();
        assert!(set.check_crop(81).is_err());
        let a = set.sample_batch(&mut EotRng::new(3), 4, 32, 0.5, true);
        let b = set.sample_batch(&mut EotRng::new(3), 4, 32, 0.5, true);
        assert_eq!(a, b);
        assert_eq!(a.len(), 4 * 3 * 32 * 32);
        assert!(a.iter().all(|v| (0.0..=1.0).contains(v)));
        // Scale 1, no flip: an exact copy of a window (integer offsets come out of the RNG as
        // fractions, so compare the blue channel, constant 128/255).
        let c = set.sample_batch(&mut EotRng::new(4), 1, 16, 1.0, false);
        assert!(
            c[2 * 256..]
                .iter()
                .all(|v| (v - 128.0 / 255.0).abs() < 1e-6)
        );
    }

    #[test]
    fn square_geometry() {
        let img = image::RgbImage::from_pixel(300, 200, image::Rgb([10, 20, 30]));
        let sq = square_rgb8(&img, 128);
        assert_eq!(sq.dimensions(), (128, 128));
        assert_eq!(sq.get_pixel(64, 64).0, [10, 20, 30]);
    }

    /// Which of the shared images are held out (printed; checks ≈ 10 % when the data exists).
    #[test]
    fn held_out_names() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/images");
        if !dir.is_dir() {
            eprintln!("SKIPPED: {} is missing", dir.display());
            return;
        }
        let names = list_images(&dir).unwrap();
        let held: Vec<&str> = names
            .iter()
            .map(|(n, _)| n.as_str())
            .filter(|n| is_held_out(n))
            .collect();
        eprintln!("{} of {} held out: {held:?}", held.len(), names.len());
        let frac = held.len() as f64 / names.len() as f64;
        assert!((0.04..0.2).contains(&frac), "held-out fraction {frac}");
    }
}
