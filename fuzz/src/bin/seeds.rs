//! `seeds DIR`: writes the seed corpora, one folder per target (`DIR/<target>/`), from
//! splatmark's own writers and small hand-made files — every format and variant a target reads.
use std::io::Write;
use std::path::Path;

use splatmark::scene::synthetic::{Rng, object_scene};

fn put(dir: &Path, target: &str, name: &str, bytes: &[u8]) {
    let d = dir.join(target);
    std::fs::create_dir_all(&d).unwrap();
    std::fs::write(d.join(name), bytes).unwrap();
}

/// The scene target's input: a byte that picks the file name's extension (0 none, 1 ply, 2
/// splat, 3 spz), then the file.
fn scene(pick: u8, file: &[u8]) -> Vec<u8> {
    let mut v = vec![pick];
    v.extend_from_slice(file);
    v
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(raw).unwrap();
    e.finish().unwrap()
}

fn scenes(dir: &Path) {
    let g = object_scene(6, 1, 3);
    let mut ply = Vec::new();
    splatmark::scene::format::write_ply(&g, &mut ply).unwrap();
    put(dir, "scene", "inria_le.ply", &scene(1, &ply));
    put(dir, "scene", "inria_le_nohint.ply", &scene(0, &ply));
    // The same properties, fewer of them, as ASCII and big-endian.
    let props = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let rows: [[f32; 14]; 2] = [
        [
            0.0, 0.1, 0.2, 0.5, -0.2, 0.1, 1.0, -3.0, -3.2, -3.1, 1.0, 0.0, 0.0, 0.0,
        ],
        [
            0.3, -0.1, 0.0, -0.4, 0.6, 0.0, -0.5, -2.5, -2.9, -3.3, 0.7, 0.1, 0.7, 0.0,
        ],
    ];
    let header = |format: &str| {
        let mut h = format!("ply\nformat {format} 1.0\ncomment seed\nelement vertex 2\n");
        for p in props {
            h += &format!("property float {p}\n");
        }
        h + "end_header\n"
    };
    let mut ascii = header("ascii").into_bytes();
    for r in rows {
        let line: Vec<String> = r.iter().map(|v| v.to_string()).collect();
        ascii.extend_from_slice((line.join(" ") + "\n").as_bytes());
    }
    put(dir, "scene", "ascii.ply", &scene(1, &ascii));
    let mut be = header("binary_big_endian").into_bytes();
    for r in rows {
        for v in r {
            be.extend_from_slice(&v.to_be_bytes());
        }
    }
    put(dir, "scene", "big_endian.ply", &scene(1, &be));
    // SuperSplat compressed PLY: one chunk, 4 points.
    let mut h = String::from("ply\nformat binary_little_endian 1.0\nelement chunk 1\n");
    for p in splatmark::scene::compressed_ply::CHUNK_REQUIRED {
        h += &format!("property float {p}\n");
    }
    h += "element vertex 4\n";
    for p in splatmark::scene::compressed_ply::PACKED {
        h += &format!("property uint {p}\n");
    }
    h += "end_header\n";
    let mut cply = h.into_bytes();
    for v in [
        -1.0f32, -1.0, -1.0, 1.0, 1.0, 1.0, -5.0, -5.0, -5.0, -3.0, -3.0, -3.0,
    ] {
        cply.extend_from_slice(&v.to_le_bytes());
    }
    let mut rng = Rng::new(7);
    for _ in 0..16 {
        cply.extend_from_slice(&(rng.next_u64() as u32).to_le_bytes());
    }
    put(dir, "scene", "compressed.ply", &scene(1, &cply));
    // antimatter15 .splat: 32 bytes per point.
    let mut splat = Vec::new();
    for k in 0..3 {
        for v in [0.1 * k as f32, -0.2, 0.3, 0.02, 0.03, 0.04] {
            splat.extend_from_slice(&v.to_le_bytes());
        }
        splat.extend_from_slice(&[200, 100, 50, 180, 255, 128, 128, 128]);
    }
    put(dir, "scene", "points.splat", &scene(2, &splat));
    // Niantic .spz version 2 and 3 (gzip), 3 points, SH degree 0 and 1.
    for (version, degree) in [(2u32, 0u8), (3, 1)] {
        let n = 3usize;
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&version.to_le_bytes());
        raw.extend_from_slice(&(n as u32).to_le_bytes());
        raw.extend_from_slice(&[degree, 12, 0, 0]);
        let rot = if version >= 3 { 4 } else { 3 };
        let sh = if degree == 1 { 9 } else { 0 };
        for per_point in [9, 1, 3, 3, rot, sh] {
            raw.extend((0..n * per_point).map(|_| rng.next_u64() as u8));
        }
        put(
            dir,
            "scene",
            &format!("v{version}.spz"),
            &scene(3, &gzip(&raw)),
        );
    }
}

fn cameras(dir: &Path) {
    let inria = r#"[{"id": 0, "img_name": "a", "width": 64, "height": 48,
 "position": [0.0, 0.0, -3.0], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
 "fx": 60.0, "fy": 60.0},
 {"id": 1, "img_name": "b", "width": 64, "height": 48,
 "position": [3.0, 0.0, 0.0], "rotation": [[0, 0, -1], [0, 1, 0], [1, 0, 0]],
 "fx": 60.0, "fy": 61.5}]"#;
    put(dir, "cameras", "cameras.json", inria.as_bytes());
    let nerf = r#"{"camera_angle_x": 0.69, "w": 64, "h": 64, "frames": [
 {"file_path": "./train/r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]},
 {"file_path": "./train/r_1", "w": 32, "h": 32, "transform_matrix": [[0, 0, 1, 4], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]}]}"#;
    put(dir, "cameras", "transforms.json", nerf.as_bytes());
    // LLFF poses_bounds.npy: (2, 17) little-endian f64 — a 3 × 5 pose (rotation, position,
    // [h, w, focal]) and the near/far bounds per view.
    let mut body = Vec::new();
    for k in 0..2 {
        let pose = [
            1.0,
            0.0,
            0.0,
            0.1 * k as f64,
            378.0,
            0.0,
            1.0,
            0.0,
            0.0,
            504.0,
            0.0,
            0.0,
            1.0,
            2.0,
            407.0,
            1.5,
            20.0,
        ];
        for v in pose {
            body.extend_from_slice(&f64::to_le_bytes(v));
        }
    }
    let mut dict = String::from("{'descr': '<f8', 'fortran_order': False, 'shape': (2, 17), }");
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    npy.extend_from_slice(dict.as_bytes());
    npy.extend_from_slice(&body);
    put(dir, "cameras", "poses_bounds.npy", &npy);
}

fn images(dir: &Path) {
    let img = image::RgbImage::from_fn(64, 64, |x, y| {
        image::Rgb([(x * 4) as u8, (y * 4) as u8, 90])
    });
    for (name, format) in [
        ("64.png", image::ImageFormat::Png),
        ("64.jpg", image::ImageFormat::Jpeg),
    ] {
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        put(dir, "image", name, out.get_ref());
    }
}

fn texts(dir: &Path) {
    let jobs = [
        ("empty.json", "{}"),
        ("steps.json", r#"{"steps": 10, "holdout_every": 4}"#),
        (
            "orbit.json",
            r#"{"orbit": {"count": 8, "width": 128, "height": 128}, "use_cameras": false}"#,
        ),
        ("size.json", r#"{"width": 256, "use_cameras": true}"#),
        (
            "embed.json",
            r#"{"embed": {"finetune": {"steps": 5, "extra_steps": 2}, "extra_views": 4}}"#,
        ),
    ];
    for (name, s) in jobs {
        put(dir, "job_options", name, s.as_bytes());
    }
    let queries = [
        (
            "audit",
            "since=2026-12-01T16:00:00Z&until=2026-12-02T00:00:00.123Z&limit=10&cursor=5",
        ),
        (
            "audit_filter",
            "action=job.enqueue&actor=k1&asset_id=6f1c2a3b-0000-4000-8000-000000000001",
        ),
        ("attribution", "role=carrier&cursor=3&limit=100"),
    ];
    for (name, s) in queries {
        put(dir, "query", name, s.as_bytes());
    }
    for (name, s) in [
        ("time", "2026-12-01T16:00:00Z"),
        ("time_ms", "2024-02-29T23:59:59.1Z"),
        ("hex32", "deadbeef"),
        ("hex64", "0xDEADBEEFcafebabe"),
        ("hex48", " 0123456789ab "),
    ] {
        put(dir, "text", name, s.as_bytes());
    }
}

fn main() {
    let dir = std::env::args().nth(1).unwrap_or_else(|| "corpus".into());
    let dir = Path::new(&dir);
    scenes(dir);
    cameras(dir);
    images(dir);
    texts(dir);
    println!("seed corpora written to {}", dir.display());
}
