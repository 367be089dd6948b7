//! Hostile input end to end: a corpus of crafted scene files, camera files and dispute images,
//! each wrong in its own way, against the real server; each must get a 4xx problem, store nothing,
//! and leave the process's memory where it was.

use reqwest::StatusCode;
use reqwest::multipart::{Form, Part};
use serde_json::json;

use splatmark::scene::synthetic::object_scene;

mod common;
use common::*;

/// Resident memory of this process (the server runs in it), in bytes.
fn rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: u64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(raw).unwrap();
    e.finish().unwrap()
}

/// Crafted scene files, each wrong in its own way (named for what is wrong).
fn hostile_scenes() -> Vec<(&'static str, Vec<u8>)> {
    let good = ply_bytes(&object_scene(50, 0, 1));
    let props = "property float x\nproperty float y\nproperty float z\nproperty float f_dc_0\n\
                 property float f_dc_1\nproperty float f_dc_2\nproperty float opacity\n\
                 property float scale_0\nproperty float scale_1\nproperty float scale_2\n\
                 property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n";
    let ascii = |rows: &[&str]| -> Vec<u8> {
        format!(
            "ply\nformat ascii 1.0\nelement vertex {}\n{props}end_header\n{}\n",
            rows.len(),
            rows.join("\n")
        )
        .into_bytes()
    };
    let row = "0 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0";
    let header = |h: &str| h.as_bytes().to_vec();
    let mut truncated = good.clone();
    truncated.truncate(good.len() - 7);
    let mut polyglot = good.clone();
    polyglot.extend_from_slice(b"PK\x03\x04\x14\x00\x00\x00 a zip archive riding along");
    let mut png = vec![];
    image::RgbImage::new(8, 8)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let mut png_tail = good.clone();
    png_tail.extend_from_slice(&png);
    let spz_header = |magic: &[u8], version: u32, n: u32| {
        let mut raw = magic.to_vec();
        raw.extend_from_slice(&version.to_le_bytes());
        raw.extend_from_slice(&n.to_le_bytes());
        raw.extend_from_slice(&[0, 12, 0, 0]);
        raw
    };
    let mut bad_crc = spz_bytes(100);
    let at = bad_crc.len() - 8;
    bad_crc[at] ^= 0x40;
    let mut spz_bomb = spz_header(b"NGSP", 2, 200_000);
    spz_bomb.resize(spz_bomb.len() + 200_000 * 19, 0);
    let mut short_spz = spz_header(b"NGSP", 2, 1000);
    short_spz.extend_from_slice(&[7; 100]);
    let mut nan_splat = vec![];
    for _ in 0..3 {
        nan_splat.extend_from_slice(&f32::NAN.to_le_bytes());
    }
    nan_splat.extend_from_slice(&[0u8; 20]);
    vec![
        ("empty.ply", vec![]),
        ("magic_only.ply", header("ply\n")),
        (
            "wrong_magic.ply",
            header("plx\nformat ascii 1.0\nend_header\n"),
        ),
        (
            "no_end_header.ply",
            header("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"),
        ),
        (
            "lying_count.ply",
            header(
                "ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\nend_header\n",
            ),
        ),
        (
            "negative_count.ply",
            header("ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nend_header\n"),
        ),
        ("truncated.ply", truncated),
        (
            "duplicate_property.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 2\n",
            ),
        ),
        (
            "list_property.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n1 2\n",
            ),
        ),
        (
            "duplicate_element.ply",
            header(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement vertex 1\nproperty float x\nend_header\n1\n2\n",
            ),
        ),
        (
            "nan_position.ply",
            ascii(&["nan 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0"]),
        ),
        (
            "inf_opacity.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 inf -3 -3 -3 1 0 0 0"]),
        ),
        (
            "overflowing_scale.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 0.5 100 -3 -3 1 0 0 0"]),
        ),
        (
            "zero_quaternion.ply",
            ascii(&["0 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 0 0 0 0"]),
        ),
        ("too_few_values.ply", ascii(&["0 0 0 0.1"])),
        (
            "trailing_values.ply",
            [ascii(&[row]), b"9 9 9\n".to_vec()].concat(),
        ),
        (
            "banana.ply",
            ascii(&["0 0 banana 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0"]),
        ),
        (
            "version_2.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("ascii 1.0", "ascii 2.0", 1)
                .into_bytes(),
        ),
        (
            "unknown_format.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("ascii 1.0", "binary_middle_endian 1.0", 1)
                .into_bytes(),
        ),
        (
            "unknown_type.ply",
            header("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n1\n"),
        ),
        (
            "missing_opacity.ply",
            String::from_utf8(ascii(&[row]))
                .unwrap()
                .replacen("property float opacity\n", "", 1)
                .into_bytes(),
        ),
        (
            "no_format.ply",
            header("ply\nelement vertex 1\nproperty float x\nend_header\n1\n"),
        ),
        (
            "binary_header.ply",
            b"ply\n\xff\xfe\xfd\x00\x01format\nend_header\n".to_vec(),
        ),
        ("polyglot_zip.ply", polyglot),
        ("png_tail.ply", png_tail),
        ("picture.ply", png),
        (
            "zip.ply",
            b"PK\x03\x04\x14\x00\x00\x00\x08\x00 not a scene at all".to_vec(),
        ),
        ("bad_length.splat", vec![1; 33]),
        ("nan.splat", nan_splat),
        (
            "garbage.spz",
            [&[0x1f, 0x8b, 8, 0][..], &[0xAB; 64][..]].concat(),
        ),
        ("bad_crc.spz", bad_crc),
        ("bomb.spz", gzip(&spz_bomb)),
        ("wrong_magic.spz", gzip(&spz_header(b"XXXX", 2, 1))),
        ("version_99.spz", gzip(&spz_header(b"NGSP", 99, 1))),
        ("short.spz", gzip(&short_spz)),
        (
            "zstd_garbage.spz",
            [&[0x28, 0xb5, 0x2f, 0xfd][..], &[0x55; 64][..]].concat(),
        ),
    ]
}

/// Alone in its test binary, so that the resident memory it measures is the server's and no other
/// test's; with the allocator settings `splatmark serve` runs under.
#[test]
fn a_hostile_corpus_gets_4xx_problems_stores_nothing_and_keeps_memory_flat() {
    splatmark::alloc::tune();
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
        .block_on(hostile_corpus());
}

async fn hostile_corpus() {
    let mut t = TestApp::start().await;
    let k = t.keys().await;
    // Warm up (decoders, allocator arenas) with one good upload and one verification.
    let r = t
        .upload(&k.owner, "ok.ply", ply_bytes(&object_scene(300, 0, 1)))
        .await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let kept = t.stored_blobs();
    let good_view = image::RgbImage::from_pixel(64, 64, image::Rgb([90, 120, 200]));
    t.verify(&k.verifier, &[good_view], None).await;
    let before_rss = rss_bytes();
    let before_5xx = responses_of_class(&t, "5xx").await;

    let scenes = hostile_scenes();
    assert!(scenes.len() >= 30, "{}", scenes.len());
    for (name, bytes) in scenes {
        let r = t.upload(&k.owner, name, bytes).await;
        let status = r.status();
        assert!(status.is_client_error(), "{name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("{name}: {status} {}", p["detail"]);
    }
    // Cameras that lie, next to a good scene.
    let scene = ply_bytes(&object_scene(50, 0, 1));
    let identity = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]);
    let nan_matrix = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]])
        .to_string()
        .replacen("4", "1e999", 1);
    let cameras: Vec<(&str, Vec<u8>)> = vec![
        ("transforms.json", b"{not json".to_vec()),
        ("transforms.json", br#"{"fl_x": 100, "w": 64, "h": 64, "frames": []}"#.to_vec()),
        (
            "transforms.json",
            format!(r#"{{"fl_x": 100, "w": 64, "h": 64, "frames": [{{"file_path": "a", "transform_matrix": {nan_matrix}}}]}}"#)
                .into_bytes(),
        ),
        (
            "transforms.json",
            json!({"fl_x": -5, "w": 64, "h": 64, "frames": [{"file_path": "a", "transform_matrix": identity}]})
                .to_string()
                .into_bytes(),
        ),
        ("cameras.json", br#"[{"id": 0, "width": 64}]"#.to_vec()),
        ("poses_bounds.npy", b"\x93NUMPY\x01\x00garbage".to_vec()),
    ];
    for (name, bytes) in cameras {
        let form = Form::new()
            .part("scene", Part::bytes(scene.clone()).file_name("s.ply"))
            .part("cameras", Part::bytes(bytes).file_name(name));
        let r = t
            .client
            .post(t.url("/v1/assets"))
            .bearer_auth(&k.owner)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = r.status();
        assert!(status.is_client_error(), "cameras {name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("cameras {name}: {status} {}", p["detail"]);
    }
    // Images for a dispute that are not what they claim.
    let mut png = vec![];
    image::RgbImage::from_pixel(64, 64, image::Rgb([1, 2, 3]))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let mut huge = png.clone();
    // The IHDR says 100 000 × 100 000 (its CRC no longer matches either).
    huge[16..20].copy_from_slice(&100_000u32.to_be_bytes());
    huge[20..24].copy_from_slice(&100_000u32.to_be_bytes());
    let mut jpeg = vec![];
    image::RgbImage::from_pixel(64, 64, image::Rgb([9, 9, 9]))
        .write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let mut tiny = vec![];
    image::RgbImage::new(8, 8)
        .write_to(
            &mut std::io::Cursor::new(&mut tiny),
            image::ImageFormat::Png,
        )
        .unwrap();
    let images: Vec<(&str, Vec<u8>)> = vec![
        ("truncated.png", png[..png.len() / 2].to_vec()),
        ("huge.png", huge),
        ("truncated.jpg", jpeg[..jpeg.len() / 2].to_vec()),
        ("garbage.png", vec![0x42; 500]),
        ("tiny.png", tiny),
        ("scene.png", scene.clone()),
        // A progressive JPEG on which the JPEG decoder panics (found by fuzz/).
        (
            "decoder_panic.jpg",
            std::fs::read(
                std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("fuzz/regressions/image/zune_jpeg_progressive_upsample_panic.jpg"),
            )
            .unwrap(),
        ),
    ];
    for (name, bytes) in images {
        let form = Form::new().part("image", Part::bytes(bytes).file_name(name));
        let r = t
            .client
            .post(t.url("/v1/verify"))
            .bearer_auth(&k.verifier)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = r.status();
        assert!(status.is_client_error(), "image {name}: {status}");
        let p = assert_problem(r, status).await;
        eprintln!("image {name}: {status} {}", p["detail"]);
    }

    // No 5xx, nothing stored beyond the warm-up's upload, no upload audited but that one.
    assert_eq!(responses_of_class(&t, "5xx").await, before_5xx);
    assert_eq!(t.stored_blobs(), kept);
    assert_eq!(t.audited(&k.auditor, "asset.upload").await, 1);
    // Memory: the whole corpus leaves the process within 64 MB of where it started.
    if let (Some(a), Some(b)) = (before_rss, rss_bytes()) {
        let grown = b.saturating_sub(a);
        eprintln!("RSS {} MB → {} MB", a >> 20, b >> 20);
        assert!(grown < 64 << 20, "RSS grew by {} MB", grown >> 20);
    } else {
        eprintln!("SKIPPED the RSS check: no /proc/self/status");
    }
    t.stop().await;
}
