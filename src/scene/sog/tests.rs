//! SOG scenes encoded here from the spec, independently of the reader (quantised, packed,
//! written as lossless WebP, zipped), then read back.

use super::*;
use crate::scene::format::{Format, detect_format, read_scene_bytes_detect, read_scene_path};
use crate::scene::synthetic::object_scene;
use crate::scene::zip::tests::zip;
use crate::scene::{cost, sigmoid};
use serde_json::json;

/// 256 evenly spaced values over the range of `values`.
struct Book {
    lo: f64,
    step: f64,
}

impl Book {
    fn new(values: impl Iterator<Item = f32>) -> Self {
        let (lo, hi) = values.fold((f64::MAX, f64::MIN), |(a, b), v| {
            (a.min(v.into()), b.max(v.into()))
        });
        Self {
            lo,
            step: ((hi - lo) / 255.0).max(1e-9),
        }
    }
    fn index(&self, v: f32) -> u8 {
        ((f64::from(v) - self.lo) / self.step)
            .round()
            .clamp(0.0, 255.0) as u8
    }
    fn codebook(&self) -> Vec<f64> {
        (0..256).map(|k| self.lo + self.step * k as f64).collect()
    }
}

/// An encoded SOG: `meta.json` and its images.
struct Encoded {
    meta: serde_json::Value,
    files: Vec<(String, Vec<u8>)>,
    /// The codebooks' (or ranges') steps: scales, DC, SH rest.
    steps: [f64; 3],
}

impl Encoded {
    fn meta_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(&self.meta).unwrap()
    }
    /// The bundle, `meta.json` last and one image deflated, as splat-transform writes it.
    fn bundle(&self) -> Vec<u8> {
        let meta = self.meta_bytes();
        let mut entries: Vec<(&str, &[u8], bool)> = self
            .files
            .iter()
            .enumerate()
            .map(|(k, (n, d))| (n.as_str(), &d[..], k == 1))
            .collect();
        entries.push(("meta.json", &meta, false));
        zip(&entries)
    }
    fn set_file(&mut self, name: &str, bytes: Vec<u8>) {
        self.files.iter_mut().find(|(n, _)| n == name).unwrap().1 = bytes;
    }
}

fn webp(data: &[u8], w: u32, h: u32, channels: usize) -> Vec<u8> {
    let mut out = Vec::new();
    let ct = match channels {
        3 => image::ExtendedColorType::Rgb8,
        _ => image::ExtendedColorType::Rgba8,
    };
    image::codecs::webp::WebPEncoder::new_lossless(&mut out)
        .encode(data, w, h, ct)
        .unwrap();
    out
}

/// splat-transform's texture size: sides multiples of 4.
fn dims(n: usize) -> (u32, u32) {
    let w = (((n as f64).sqrt() / 4.0).ceil() as u32 * 4).max(4);
    let h = (((n as f64 / f64::from(w)) / 4.0).ceil() as u32 * 4).max(4);
    (w, h)
}

fn log_t(v: f32) -> f64 {
    let v = f64::from(v);
    v.signum() * (v.abs() + 1.0).ln()
}

/// Smallest three: the largest-magnitude component of `(w, x, y, z)` made positive and dropped.
fn pack_quat(q: [f32; 4]) -> [u8; 4] {
    let m = (0..4)
        .max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs()))
        .unwrap();
    let s = if q[m] < 0.0 { -1.0 } else { 1.0 };
    let mut out = [0, 0, 0, 252 + m as u8];
    let kept = (0..4).filter(|&k| k != m);
    for (slot, k) in kept.enumerate() {
        let v = f64::from(q[k] * s) * std::f64::consts::SQRT_2;
        out[slot] = (255.0 * (v * 0.5 + 0.5)).round().clamp(0.0, 255.0) as u8;
    }
    out
}

/// Positions, quaternions and the two means images, common to both versions.
fn encode_common(g: &Gaussians, w: u32, h: u32) -> (serde_json::Value, Vec<(String, Vec<u8>)>) {
    let px = (w * h) as usize;
    let mut mins = [f64::MAX; 3];
    let mut maxs = [f64::MIN; 3];
    for m in &g.means {
        for k in 0..3 {
            mins[k] = mins[k].min(log_t(m[k]));
            maxs[k] = maxs[k].max(log_t(m[k]));
        }
    }
    let (mut lo, mut hi, mut quats) = (vec![0u8; px * 4], vec![0u8; px * 4], vec![0u8; px * 4]);
    for (i, m) in g.means.iter().enumerate() {
        for k in 0..3 {
            let q = (65535.0 * (log_t(m[k]) - mins[k]) / (maxs[k] - mins[k])).round() as u16;
            lo[i * 4 + k] = q as u8;
            hi[i * 4 + k] = (q >> 8) as u8;
        }
        lo[i * 4 + 3] = 255;
        hi[i * 4 + 3] = 255;
        quats[i * 4..i * 4 + 4].copy_from_slice(&pack_quat(g.rotations[i]));
    }
    // Trailing pixels stay 0: quaternion mode 0 is invalid, so reading them would fail.
    let means = json!({"mins": mins, "maxs": maxs, "files": ["means_l.webp", "means_u.webp"]});
    let files = vec![
        ("means_l.webp".to_string(), webp(&lo, w, h, 4)),
        ("means_u.webp".to_string(), webp(&hi, w, h, 4)),
        ("quats.webp".to_string(), webp(&quats, w, h, 4)),
    ];
    (means, files)
}

/// Version 2: codebooks; the SH palette holds every Gaussian's own coefficients.
fn encode_v2(g: &Gaussians) -> Encoded {
    let n = g.len();
    let (w, h) = dims(n);
    let px = (w * h) as usize;
    let (means, mut files) = encode_common(g, w, h);
    let sb = Book::new(g.log_scales.iter().flatten().copied());
    let cb = Book::new(g.sh_dc.iter().flatten().copied());
    let (mut scales, mut sh0) = (vec![0u8; px * 3], vec![0u8; px * 4]);
    for i in 0..n {
        for k in 0..3 {
            scales[i * 3 + k] = sb.index(g.log_scales[i][k]);
            sh0[i * 4 + k] = cb.index(g.sh_dc[i][k]);
        }
        sh0[i * 4 + 3] = (sigmoid(g.opacity_logits[i]) * 255.0).round() as u8;
    }
    files.push(("scales.webp".into(), webp(&scales, w, h, 3)));
    files.push(("sh0.webp".into(), webp(&sh0, w, h, 4)));
    let mut meta = json!({
        "version": 2, "count": n, "antialias": false, "means": means,
        "scales": {"codebook": sb.codebook(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": cb.codebook(), "files": ["sh0.webp"]},
    });
    let rb = Book::new(g.sh_rest.iter().copied());
    if g.sh_degree > 0 {
        let coeffs = g.rest_len() / 3;
        let (cw, ch) = (64 * coeffs as u32, n.div_ceil(64) as u32);
        let mut centroids = vec![0u8; (cw * ch) as usize * 4];
        let mut labels = vec![0u8; px * 4];
        for i in 0..n {
            let base = (i / 64) * cw as usize + (i % 64) * coeffs;
            for j in 0..coeffs {
                for c in 0..3 {
                    centroids[(base + j) * 4 + c] = rb.index(g.rest_of(i)[j * 3 + c]);
                }
                centroids[(base + j) * 4 + 3] = 255;
            }
            labels[i * 4] = i as u8;
            labels[i * 4 + 1] = (i >> 8) as u8;
        }
        files.push(("shN_centroids.webp".into(), webp(&centroids, cw, ch, 4)));
        files.push(("shN_labels.webp".into(), webp(&labels, w, h, 4)));
        meta["shN"] = json!({"count": n, "bands": g.sh_degree, "codebook": rb.codebook(),
            "files": ["shN_centroids.webp", "shN_labels.webp"]});
    }
    Encoded {
        meta,
        files,
        steps: [sb.step, cb.step, rb.step],
    }
}

/// Version 1 (legacy SOGS): per-axis ranges, the opacity a logit, SH bands from the width.
fn encode_v1(g: &Gaussians) -> Encoded {
    let n = g.len();
    let side = ((n as f64).sqrt().ceil() as u32).max(1);
    let (w, h) = (side, side);
    let px = (w * h) as usize;
    let (mut means, mut files) = encode_common(g, w, h);
    means["shape"] = json!([n, 3]);
    let axis = |f: &dyn Fn(usize) -> f32| Book::new((0..n).map(f));
    let sb: Vec<Book> = (0..3).map(|k| axis(&|i| g.log_scales[i][k])).collect();
    let cb: Vec<Book> = (0..3)
        .map(|k| axis(&|i| g.sh_dc[i][k]))
        .chain([axis(&|i| g.opacity_logits[i])])
        .collect();
    let (mut scales, mut sh0) = (vec![0u8; px * 4], vec![0u8; px * 4]);
    for i in 0..n {
        for k in 0..3 {
            scales[i * 4 + k] = sb[k].index(g.log_scales[i][k]);
            sh0[i * 4 + k] = cb[k].index(g.sh_dc[i][k]);
        }
        scales[i * 4 + 3] = 255;
        sh0[i * 4 + 3] = cb[3].index(g.opacity_logits[i]);
    }
    files.push(("scales.webp".into(), webp(&scales, w, h, 4)));
    files.push(("sh0.webp".into(), webp(&sh0, w, h, 4)));
    let range = |b: &[Book]| -> (Vec<f64>, Vec<f64>) {
        b.iter().map(|b| (b.lo, b.lo + 255.0 * b.step)).unzip()
    };
    let ((smin, smax), (cmin, cmax)) = (range(&sb), range(&cb));
    let meta = json!({
        "means": means,
        "scales": {"shape": [n, 3], "dtype": "float32", "mins": smin, "maxs": smax,
            "files": ["scales.webp"]},
        "quats": {"shape": [n, 4], "dtype": "uint8", "encoding": "quaternion_packed",
            "files": ["quats.webp"]},
        "sh0": {"shape": [n, 1, 4], "dtype": "float32", "mins": cmin, "maxs": cmax,
            "files": ["sh0.webp"]},
    });
    let step = |b: &[Book]| b.iter().map(|b| b.step).fold(0.0, f64::max);
    Encoded {
        meta,
        files,
        steps: [step(&sb), step(&cb[..3]), 0.0],
    }
}

/// Checks `back` against `g` within the quantisation `e` implies.
fn check(g: &Gaussians, back: &Gaussians, e: &Encoded) {
    assert_eq!((back.len(), back.sh_degree), (g.len(), g.sh_degree));
    let (mins, maxs) = (&e.meta["means"]["mins"], &e.meta["means"]["maxs"]);
    for i in 0..g.len() {
        for k in 0..3 {
            let (lo, hi) = (mins[k].as_f64().unwrap(), maxs[k].as_f64().unwrap());
            // Half a 16-bit step in the log domain, through e^|n|'s slope at the range's edge.
            let step = (hi - lo) / 65535.0;
            let tol = 0.5 * step * lo.abs().max(hi.abs()).exp() + 1e-6;
            let d = f64::from((back.means[i][k] - g.means[i][k]).abs());
            assert!(d <= tol, "Gaussian {i} axis {k}: off by {d} > {tol}");
            let d = f64::from((back.log_scales[i][k] - g.log_scales[i][k]).abs());
            assert!(d <= e.steps[0] / 2.0 + 1e-5, "scale {i}.{k}: {d}");
            let d = f64::from((back.sh_dc[i][k] - g.sh_dc[i][k]).abs());
            assert!(d <= e.steps[1] / 2.0 + 1e-5, "dc {i}.{k}: {d}");
        }
        let (q, r) = (g.rotations[i], back.rotations[i]);
        let dot: f32 = (0..4).map(|k| q[k] * r[k]).sum();
        let s = dot.signum();
        for k in 0..4 {
            assert!(
                (q[k] - s * r[k]).abs() < 0.01,
                "rotation {i}: {q:?} vs {r:?}"
            );
        }
        let (p, pb) = (
            sigmoid(g.opacity_logits[i]),
            sigmoid(back.opacity_logits[i]),
        );
        if e.meta.get("version").is_some() {
            assert!(
                (p - pb).abs() <= 0.5 / 255.0 + 1e-5,
                "opacity {i}: {p} vs {pb}"
            );
        } else {
            let step = e.meta["sh0"]["maxs"][3].as_f64().unwrap()
                - e.meta["sh0"]["mins"][3].as_f64().unwrap();
            let d = f64::from((g.opacity_logits[i] - back.opacity_logits[i]).abs());
            assert!(d <= step / 510.0 + 1e-5, "opacity logit {i}: {d}");
        }
        for (a, b) in g.rest_of(i).iter().zip(back.rest_of(i)) {
            assert!(
                f64::from((a - b).abs()) <= e.steps[2] / 2.0 + 1e-5,
                "rest {i}"
            );
        }
    }
}

fn limits() -> Limits {
    Limits::default()
}

#[test]
fn bundled_v2_with_sh_reads_back_within_its_quantisation() {
    let g = object_scene(300, 3, 7);
    let e = encode_v2(&g);
    let bytes = e.bundle();
    for hint in [None, Some("sog"), Some("scene.ply")] {
        assert_eq!(
            detect_format(&bytes, hint).unwrap(),
            Format::Sog,
            "{hint:?}"
        );
    }
    let (format, back) = read_scene_bytes_detect(&bytes, None, &limits()).unwrap();
    assert_eq!(format, Format::Sog);
    back.validate().unwrap();
    check(&g, &back, &e);
    assert_eq!(declared(&bytes).unwrap(), (300, 3));
}

#[test]
fn unbundled_directory_and_meta_file_read_like_the_bundle() {
    let g = object_scene(150, 0, 3);
    let e = encode_v2(&g);
    assert!(e.meta.get("shN").is_none());
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("meta.json"), e.meta_bytes()).unwrap();
    for (name, data) in &e.files {
        std::fs::write(dir.path().join(name), data).unwrap();
    }
    let bundled = read(&e.bundle(), &limits()).unwrap();
    check(&g, &bundled, &e);
    for path in [dir.path().to_path_buf(), dir.path().join("meta.json")] {
        let (format, g2) = read_scene_path(&path, &limits()).unwrap();
        assert_eq!(format, Format::Sog);
        assert_eq!(g2, bundled, "{}", path.display());
    }
    // The per-file size limit applies to each file, the missing image is named.
    let small = Limits {
        max_file_bytes: Some(64),
        ..limits()
    };
    assert!(matches!(
        read_scene_path(dir.path(), &small),
        Err(SceneError::FileTooLarge { .. })
    ));
    std::fs::remove_file(dir.path().join("sh0.webp")).unwrap();
    let err = read_scene_path(dir.path(), &limits()).unwrap_err();
    assert!(
        matches!(&err, SceneError::MissingFile { name, .. } if name == "sh0.webp"),
        "{err}"
    );
}

#[test]
fn legacy_v1_meta_reads_with_ranges_and_sh_from_the_palette_width() {
    let g = object_scene(200, 0, 5);
    let e = encode_v1(&g);
    let back = read(&e.bundle(), &limits()).unwrap();
    check(&g, &back, &e);
    // With SH: a 960-wide palette is 3 bands; v1 values lerp over one range.
    let g3 = object_scene(200, 3, 6);
    let mut e = encode_v1(&g3);
    let v2 = encode_v2(&g3);
    let rb = Book::new(g3.sh_rest.iter().copied());
    for name in ["shN_centroids.webp", "shN_labels.webp"] {
        let data = v2.files.iter().find(|(n, _)| n == name).unwrap().1.clone();
        e.files.push((name.into(), data));
    }
    // v2's labels are laid out for its own width; v1 is square: re-encode them.
    let side = (200f64).sqrt().ceil() as u32;
    let mut labels = vec![0u8; (side * side) as usize * 4];
    for i in 0..200usize {
        labels[i * 4] = i as u8;
    }
    e.set_file("shN_labels.webp", webp(&labels, side, side, 4));
    e.meta["shN"] = json!({"mins": rb.lo, "maxs": rb.lo + 255.0 * rb.step,
        "files": ["shN_centroids.webp", "shN_labels.webp"]});
    e.steps[2] = rb.step;
    let back = read(&e.bundle(), &limits()).unwrap();
    check(&g3, &back, &e);
}

#[test]
fn damaged_bundles_are_typed_errors() {
    let g = object_scene(120, 1, 9);
    let e = encode_v2(&g);
    let bytes = e.bundle();
    for cut in (0..bytes.len()).step_by(41) {
        let err = read(&bytes[..cut], &limits()).unwrap_err();
        assert!(matches!(err, SceneError::Corrupt(_)), "{cut}: {err}");
        // Without the .sog hint a damaged archive is not recognised; with it, it is reported.
        if cut >= 4 {
            let r = read_scene_bytes_detect(&bytes[..cut], None, &limits());
            assert!(matches!(r, Err(SceneError::UnknownFormat(_))), "{cut}");
            let r = read_scene_bytes_detect(&bytes[..cut], Some("sog"), &limits());
            assert!(matches!(r, Err(SceneError::Corrupt(_))), "{cut}");
        }
    }
    // A missing image, named.
    let meta = e.meta_bytes();
    let mut entries: Vec<(&str, &[u8], bool)> = e
        .files
        .iter()
        .filter(|(n, _)| n != "quats.webp")
        .map(|(n, d)| (n.as_str(), &d[..], false))
        .collect();
    entries.push(("meta.json", &meta, false));
    let err = read(&zip(&entries), &limits()).unwrap_err();
    assert!(
        matches!(&err, SceneError::MissingFile { name, .. } if name == "quats.webp"),
        "{err}"
    );
    // No meta.json: not a SOG.
    let err = read_scene_bytes_detect(&zip(&entries[..2]), None, &limits()).unwrap_err();
    assert!(matches!(err, SceneError::UnknownFormat(_)), "{err}");
}

/// Reads `e` with `edit` applied to its meta.json.
fn read_edited(e: &Encoded, edit: impl FnOnce(&mut serde_json::Value)) -> SceneError {
    let mut e2 = Encoded {
        meta: e.meta.clone(),
        files: e.files.clone(),
        steps: e.steps,
    };
    edit(&mut e2.meta);
    read(&e2.bundle(), &limits()).unwrap_err()
}

#[test]
fn meta_json_that_does_not_fit_its_images_is_refused() {
    let g = object_scene(100, 2, 4);
    let e = encode_v2(&g);
    let (w, h) = dims(100);
    // More Gaussians than pixels.
    let err = read_edited(&e, |m| m["count"] = json!(w * h + 1));
    assert!(
        matches!(&err, SceneError::Corrupt(m) if m.contains("fewer than")),
        "{err}"
    );
    // Versions other than 1 and 2.
    for v in [3, 7] {
        let err = read_edited(&e, |m| m["version"] = json!(v));
        let want = format!("SOG version {v}");
        assert!(
            matches!(&err, SceneError::Unsupported(m) if m.contains(&want)),
            "{err}"
        );
    }
    let err = read_edited(&e, |m| m["version"] = json!(2.5));
    assert!(matches!(err, SceneError::Header(_)), "{err}");
    // Names that leave the directory.
    let err = read_edited(&e, |m| m["quats"]["files"] = json!(["../quats.webp"]));
    assert!(matches!(err, SceneError::Corrupt(_)), "{err}");
    // Codebooks: 256 entries; a leading null is patched, another is refused.
    let err = read_edited(&e, |m| {
        m["scales"]["codebook"].as_array_mut().unwrap().pop();
    });
    assert!(matches!(err, SceneError::Header(_)), "{err}");
    let err = read_edited(&e, |m| m["sh0"]["codebook"][9] = json!(null));
    assert!(matches!(err, SceneError::Header(_)), "{err}");
    let mut patched = e.meta.clone();
    patched["scales"]["codebook"][0] = json!(null);
    let e2 = Encoded {
        meta: patched,
        files: e.files.clone(),
        steps: e.steps,
    };
    assert!(read(&e2.bundle(), &limits()).is_ok());
    // A palette smaller than the labels, a count no file of this size holds, too many.
    let err = read_edited(&e, |m| m["shN"]["count"] = json!(50));
    assert!(
        matches!(&err, SceneError::Corrupt(m) if m.contains("palette")),
        "{err}"
    );
    let err = read_edited(&e, |m| m["count"] = json!(5_000_000));
    assert!(
        matches!(&err, SceneError::Corrupt(m) if m.contains("per byte")),
        "{err}"
    );
    let err = read_edited(&e, |m| m["count"] = json!(20_000_000));
    assert!(matches!(err, SceneError::TooManyGaussians { .. }), "{err}");
}

#[test]
fn images_the_spec_forbids_are_refused() {
    let g = object_scene(60, 0, 2);
    let mut e = encode_v2(&g);
    // A lossy WebP ("VP8 " chunk) is refused before it is decoded.
    let mut lossy = b"RIFF\x20\0\0\0WEBPVP8 \x14\0\0\0".to_vec();
    lossy.extend_from_slice(&[0; 20]);
    e.set_file("quats.webp", lossy);
    let err = read(&e.bundle(), &limits()).unwrap_err();
    assert!(
        matches!(&err, SceneError::Unsupported(m) if m.contains("lossy")),
        "{err}"
    );
    e.set_file("quats.webp", b"GIF89a......".to_vec());
    let err = read(&e.bundle(), &limits()).unwrap_err();
    assert!(matches!(err, SceneError::Unsupported(_)), "{err}");
    // A quaternion mode byte below 252 in a counted pixel.
    let (w, h) = dims(60);
    let mut q = vec![128u8; (w * h) as usize * 4];
    q.chunks_exact_mut(4).for_each(|p| p[3] = 255);
    q[7 * 4 + 3] = 17;
    e.set_file("quats.webp", webp(&q, w, h, 4));
    let err = read(&e.bundle(), &limits()).unwrap_err();
    assert!(
        matches!(&err, SceneError::Corrupt(m) if m.contains("Gaussian 7")),
        "{err}"
    );
    // A PNG is read like a WebP.
    q[7 * 4 + 3] = 255;
    let mut png = Vec::new();
    image::RgbaImage::from_raw(w, h, q)
        .unwrap()
        .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    e.set_file("quats.webp", png);
    assert_eq!(read(&e.bundle(), &limits()).unwrap().len(), 60);
}

#[test]
fn the_service_learns_the_count_from_the_archive_end() {
    let g = object_scene(80, 3, 1);
    let e = encode_v2(&g);
    // Past PROBE_BYTES: a stored padding entry first, so meta.json is only in the directory.
    let pad = vec![0x5a; cost::PROBE_BYTES + 1000];
    let meta = e.meta_bytes();
    let mut entries: Vec<(&str, &[u8], bool)> = vec![("padding.bin", &pad, false)];
    entries.extend(e.files.iter().map(|(n, d)| (n.as_str(), &d[..], false)));
    entries.push(("meta.json", &meta, false));
    let bytes = zip(&entries);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("upload.bin");
    std::fs::write(&path, &bytes).unwrap();
    let d = cost::declared_file(&path, None).unwrap();
    assert_eq!((d.format, d.count, d.rest_len), (Format::Sog, 80, 45));
    assert!(d.read_bytes(bytes.len() as u64) > bytes.len() as u64 + 80 * (56 + 180));
    // From the first bytes alone it cannot be told; a whole small bundle can.
    let prefix = &bytes[..cost::PROBE_BYTES];
    assert!(cost::declared(prefix, bytes.len() as u64, Some("sog")).is_err());
    let small = e.bundle();
    let d = cost::declared(&small, small.len() as u64, None).unwrap();
    assert_eq!((d.format, d.count), (Format::Sog, 80));
    // A ZIP without meta.json is not a scene.
    let other = zip(&[("readme.txt", &pad, false)]);
    std::fs::write(&path, &other).unwrap();
    assert!(matches!(
        cost::declared_file(&path, None),
        Err(SceneError::UnknownFormat(_))
    ));
}
