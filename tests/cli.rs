//! The `splatmark` binary end to end: `info` and `render` on the shared real scenes, and clear
//! failures on bad input.

use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_splatmark"))
}

fn data() -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!(
            "SKIPPED: {} is missing, real-scene CLI tests not run",
            d.display()
        );
        None
    }
}

fn json(out: &std::process::Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("stdout is JSON")
}

/// Fraction of pixels brighter than near-black, and the mean of each channel.
fn coverage(png: &Path) -> (f64, [f64; 3]) {
    let img = image::open(png).expect("readable PNG").to_rgb8();
    let n = (img.width() * img.height()) as f64;
    let lit = img.pixels().filter(|p| p.0.iter().any(|&v| v > 16)).count() as f64;
    let mut mean = [0.0; 3];
    for p in img.pixels() {
        for (m, v) in mean.iter_mut().zip(p.0) {
            *m += v as f64 / n;
        }
    }
    (lit / n, mean)
}

#[test]
fn info_reports_format_count_and_sh_degree() {
    let Some(d) = data() else { return };
    for (file, format, count, sh) in [
        ("udon/point_cloud.ply", "ply", 2153, 3),
        ("donut/fused.ply", "ply", 45_624, 0),
        ("plant/plant.splat", "splat", 113_648, 0),
    ] {
        let v = json(&bin().arg("info").arg(d.join(file)).output().unwrap());
        assert_eq!(v["format"], format, "{file}");
        assert_eq!(v["count"], count, "{file}");
        assert_eq!(v["sh_degree"], sh, "{file}");
        let min = v["bounds"]["min"].as_array().unwrap();
        let max = v["bounds"]["max"].as_array().unwrap();
        assert!(
            min.iter().zip(max).all(|(a, b)| a.as_f64() < b.as_f64()),
            "{file}"
        );
    }
}

#[test]
fn udon_renders_through_its_own_cameras() {
    let Some(d) = data() else { return };
    let out = tempfile::tempdir().unwrap();
    let status = bin()
        .args(["render"])
        .arg(d.join("udon/point_cloud.ply"))
        .arg("--cameras")
        .arg(d.join("udon/cameras.json"))
        .args(["--limit", "4", "--width", "472"])
        .arg("--out")
        .arg(out.path())
        .status()
        .unwrap();
    assert!(status.success());
    let mut pngs: Vec<_> = std::fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    pngs.sort();
    assert_eq!(pngs.len(), 4);
    for p in &pngs {
        let img = image::open(p).unwrap();
        // cameras.json is 1888×1061: --width alone keeps the aspect ratio.
        assert_eq!((img.width(), img.height()), (472, 265));
        let (lit, mean) = coverage(p);
        // The object is in view and it is the golden-brown noodle dish (red > green > blue).
        assert!(lit > 0.03, "{}: only {lit:.3} of pixels lit", p.display());
        assert!(
            mean[0] > mean[1] && mean[1] > mean[2],
            "{}: mean colour {mean:?}",
            p.display()
        );
    }
}

#[test]
fn donut_and_plant_render_through_orbit_views() {
    let Some(d) = data() else { return };
    for file in ["donut/fused.ply", "plant/plant.splat"] {
        let out = tempfile::tempdir().unwrap();
        let status = bin()
            .arg("render")
            .arg(d.join(file))
            .args(["--orbit", "3", "--width", "200", "--height", "160"])
            .arg("--out")
            .arg(out.path())
            .status()
            .unwrap();
        assert!(status.success(), "{file}");
        let pngs: Vec<_> = std::fs::read_dir(out.path())
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(pngs.len(), 3, "{file}");
        for p in &pngs {
            let (lit, _) = coverage(p);
            // Orbit views frame the object: it covers a good part of the image but not all.
            assert!(
                lit > 0.05 && lit < 0.9,
                "{file} {}: lit fraction {lit:.3}",
                p.display()
            );
        }
    }
}

#[test]
fn the_gpu_path_renders_the_same_pngs_as_the_cpu_reference() {
    let Some(d) = data() else { return };
    // udon has SH degree 3: view-dependent colour on both paths.
    let render = |device: &str, out: &Path| {
        let res = bin()
            .arg("render")
            .arg(d.join("udon/point_cloud.ply"))
            .arg("--cameras")
            .arg(d.join("udon/cameras.json"))
            .args(["--limit", "2", "--width", "236", "--device", device])
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        let msg = String::from_utf8_lossy(&res.stderr).to_string();
        assert!(res.status.success(), "{device}: {msg}");
        msg
    };
    let (cpu, gpu) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    assert!(render("cpu", cpu.path()).contains("rendering on cpu"));
    // `bash scripts/setup.sh` installs Mesa's lavapipe, so wgpu finds an adapter here.
    assert!(render("wgpu", gpu.path()).contains("rendering on wgpu"));
    let mut names: Vec<_> = std::fs::read_dir(cpu.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    names.sort();
    assert_eq!(names.len(), 2);
    for name in names {
        let a = image::open(cpu.path().join(&name)).unwrap().to_rgb8();
        let b = image::open(gpu.path().join(&name)).unwrap().to_rgb8();
        assert_eq!(a.dimensions(), b.dimensions());
        let values = a.as_raw().len();
        let off = a
            .as_raw()
            .iter()
            .zip(b.as_raw())
            .filter(|(x, y)| x.abs_diff(**y) > 1)
            .count();
        assert!(
            off * 1000 <= values,
            "{name:?}: {off} of {values} values differ by > 1"
        );
    }
    let bad = bin()
        .arg("render")
        .arg(d.join("udon/point_cloud.ply"))
        .args(["--device", "tpu", "--out", "/nonexistent"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("expected cpu, wgpu or auto"));
}

#[test]
fn bad_input_fails_with_a_clear_message_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("truncated.ply");
    std::fs::write(
        &bad,
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nend_header\n\0\0\0\0",
    )
    .unwrap();
    let out_dir = dir.path().join("out");
    let out = bin()
        .arg("render")
        .arg(&bad)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let msg = String::from_utf8_lossy(&out.stderr);
    assert!(msg.contains("truncated"), "{msg}");
    assert!(!out_dir.exists(), "nothing is written for a bad scene");

    let unknown = dir.path().join("notes.txt");
    std::fs::write(&unknown, b"hello, this is not a scene").unwrap();
    let out = bin().arg("info").arg(&unknown).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown scene format"));
}

#[test]
fn an_image_the_jpeg_decoder_panics_on_is_a_clear_error() {
    // A fuzz finding: zune-jpeg asserts in its upsampler on this progressive JPEG.
    let jpeg = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/regressions/image/zune_jpeg_progressive_upsample_panic.jpg");
    let out = bin()
        .args(["decode", "--bits", "32"])
        .arg(&jpeg)
        .output()
        .unwrap();
    let msg = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{msg}");
    assert!(
        msg.contains("the image decoder failed on this file (malformed data)"),
        "{msg}"
    );
    assert!(!msg.contains("panicked"), "{msg}");
}

#[test]
fn convert_writes_an_inria_ply_that_reads_back_exactly() {
    let Some(d) = data() else { return };
    let out = tempfile::tempdir().unwrap();
    for (file, count) in [
        ("udon/point_cloud.ply", 2153),
        ("plant/plant.splat", 113_648),
    ] {
        let ply = out.path().join("converted.ply");
        let status = bin()
            .arg("convert")
            .arg(d.join(file))
            .arg("--out")
            .arg(&ply)
            .status()
            .unwrap();
        assert!(status.success(), "{file}");
        let limits = splatmark::scene::Limits::default();
        let original = splatmark::scene::read_scene(d.join(file), &limits).unwrap();
        let converted = splatmark::scene::read_scene(&ply, &limits).unwrap();
        assert_eq!(converted.len(), count);
        assert!(
            original == converted,
            "{file}: converted scene differs from the original"
        );
        let v = json(&bin().arg("info").arg(&ply).output().unwrap());
        assert_eq!(v["format"], "ply");
    }
}

#[test]
fn convert_writes_the_format_its_output_names() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("object.ply");
    let g = splatmark::scene::synthetic::object_scene(600, 1, 9);
    splatmark::scene::write_ply(&g, std::fs::File::create(&input).unwrap()).unwrap();
    for (name, format, degree) in [
        ("o.compressed.ply", "compressed_ply", 1),
        ("o.splat", "splat", 0),
        ("o.spz", "spz", 1),
        ("o.ply", "ply", 1),
    ] {
        let out = dir.path().join(name);
        let o = bin()
            .arg("convert")
            .arg(&input)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let v = json(&bin().arg("info").arg(&out).output().unwrap());
        assert_eq!(v["format"], format, "{name}: {v}");
        assert_eq!(v["count"], 600, "{name}: {v}");
        assert_eq!(v["sh_degree"], degree, "{name}: {v}");
    }
    let bad = dir.path().join("o.ksplat");
    let o = bin()
        .arg("convert")
        .arg(&input)
        .arg("--out")
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains(".ply, .compressed.ply, .splat or .spz"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!bad.exists());
}

#[test]
fn progress_json_reports_each_phase_step_rate_and_eta() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("object.ply");
    let g = splatmark::scene::synthetic::object_scene(300, 0, 3);
    splatmark::scene::write_ply(&g, std::fs::File::create(&input).unwrap()).unwrap();
    let o = bin()
        .args(["--progress", "json", "render"])
        .arg(&input)
        .args([
            "--orbit", "3", "--width", "32", "--height", "32", "--device", "cpu",
        ])
        .arg("--out")
        .arg(dir.path().join("r"))
        .output()
        .unwrap();
    assert!(o.status.success());
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stderr)
        .lines()
        .filter(|l| l.starts_with('{'))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let last = lines.last().expect("progress lines");
    assert_eq!(last["phase"], "render");
    assert_eq!(
        (last["step"].as_u64(), last["total"].as_u64()),
        (Some(3), Some(3))
    );
    assert_eq!(last["eta_s"], 0.0, "{last}");
    assert!(last["rate"].as_f64().unwrap() > 0.0, "{last}");
    // Not a terminal and no --progress: no progress at all.
    let quiet = bin()
        .arg("render")
        .arg(&input)
        .args([
            "--orbit", "3", "--width", "32", "--height", "32", "--device", "cpu",
        ])
        .arg("--out")
        .arg(dir.path().join("q"))
        .output()
        .unwrap();
    assert!(quiet.status.success());
    assert!(
        !String::from_utf8_lossy(&quiet.stderr).contains("000_orbit_000.png"),
        "{}",
        String::from_utf8_lossy(&quiet.stderr)
    );
}

#[test]
fn commands_that_need_one_machine_refuse_a_postgresql_database_without_its_password() {
    let dir = tempfile::tempdir().unwrap();
    let url = "postgres://app:hunter2-secret@127.0.0.1:1/splatmark";
    for args in [
        vec!["keys", "rotate-master", "--new-key-file", "new.key"],
        vec!["backup", "--out", "b"],
    ] {
        let out = bin()
            .args(&args)
            .arg("--data-dir")
            .arg(dir.path())
            .current_dir(dir.path())
            .env("SPLATMARK_MASTER_KEY", "ab".repeat(32))
            .env("SPLATMARK_DATABASE_URL", url)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(err.contains("PostgreSQL"), "{args:?}: {err}");
        assert!(!err.contains("hunter2"), "{args:?}: {err}");
        assert!(!dir.path().join("new.key").exists());
    }
}
