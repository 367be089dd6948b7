//! `splatmark embed`, `verify` and `eval` end to end on a small synthetic scene with the shipped
//! 32-bit decoder: the files a user gets, their consistency, and clear failures on bad input.
//! (How well the watermark survives is measured in docs/RESULTS.md, not asserted here.)

use std::path::Path;
use std::process::Command;

use splatmark::scene::synthetic::object_scene;
use splatmark::scene::{Limits, read_scene, write_ply};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_splatmark"));
    c.env("XDG_RUNTIME_DIR", std::env::temp_dir());
    c
}

fn ok_json(out: &std::process::Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("stdout is JSON")
}

fn scene(dir: &Path) -> std::path::PathBuf {
    let p = dir.join("object.ply");
    let g = object_scene(1500, 1, 4);
    write_ply(&g, std::fs::File::create(&p).unwrap()).unwrap();
    p
}

const VIEWS: [&str; 6] = ["--orbit", "8", "--width", "64", "--height", "64"];

#[test]
fn embed_writes_scene_attribution_and_report_that_agree() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let out = dir.path().join("marked.ply");
    let attr = dir.path().join("attr.jsonl");
    let report = dir.path().join("report.json");
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--bits", "32", "--message", "c0ffee42", "--steps", "3"])
            .arg("--out")
            .arg(&out)
            .arg("--attribution")
            .arg(&attr)
            .arg("--report")
            .arg(&report)
            .output()
            .unwrap(),
    );
    assert_eq!(v["message_hex"], "c0ffee42");
    assert_eq!(v["bits"], 32);
    assert_eq!(v["views"], 7, "8 orbit views, every 8th held out");
    assert_eq!(
        v["analysis_views"], 7,
        "fewer than analysis_views: every one read"
    );
    let n_out = v["output_gaussians"].as_u64().unwrap() as usize;
    let carriers = v["carriers"].as_u64().unwrap() as usize;
    assert!(carriers > 0);
    // The report file is the JSON printed.
    let file: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(file, v);
    // The scene has the reported count; one attribution record per Gaussian, roles agree.
    let g = read_scene(&out, &Limits::default()).unwrap();
    assert_eq!(g.len(), n_out);
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(&attr)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), n_out);
    let n_carrier = lines.iter().filter(|r| r["role"] == "carrier").count();
    assert_eq!(n_carrier, carriers);
    let share: f64 = lines
        .iter()
        .map(|r| r["wm_grad_share"].as_f64().unwrap())
        .sum();
    assert!((share - 1.0).abs() < 1e-3, "{share}");

    // eval and verify run on what embed wrote.
    let e = ok_json(
        &bin()
            .arg("eval")
            .arg(&input)
            .arg(&out)
            .args(VIEWS)
            .args(["--message", "c0ffee42", "--json"])
            .output()
            .unwrap(),
    );
    assert_eq!(e["views"], 1);
    let names: Vec<&str> = e["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["name"].as_str().unwrap())
        .collect();
    for want in [
        "clean",
        "unmarked",
        "noise",
        "rotation",
        "scaling",
        "blur",
        "crop",
        "crop_on_asset",
        "jpeg",
        "combined",
        "combined_on_asset",
        "noise_0.1",
        "remove_20",
        "clone_20",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    assert!(e["psnr"].as_f64().unwrap() > 10.0);

    // Each model attack is drawn several times (seeds --seed, --seed + 1, …) and its row reads
    // their mean; one draw at seed 6 is the second of three from seed 5.
    let model_eval = |seed: &str, draws: &str| {
        ok_json(
            &bin()
                .arg("eval")
                .arg(&input)
                .arg(&out)
                .args(VIEWS)
                .args([
                    "--message",
                    "c0ffee42",
                    "--seed",
                    seed,
                    "--model-draws",
                    draws,
                ])
                .output()
                .unwrap(),
        )
    };
    let rows_of = |e: &serde_json::Value| -> Vec<serde_json::Value> {
        e["rows"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| r["kind"] == "model")
            .cloned()
            .collect()
    };
    let three = rows_of(&model_eval("5", "3"));
    let one = rows_of(&model_eval("6", "1"));
    assert_eq!(
        three.len(),
        4,
        "noise_0.1, noise_0.1_scaled, remove_20, clone_20"
    );
    for (r3, r1) in three.iter().zip(&one) {
        assert_eq!(r3["name"], r1["name"]);
        let d: Vec<f64> = r3["draws"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(d.len(), 3, "{r3}");
        let mean = d.iter().sum::<f64>() / 3.0;
        assert!(
            (r3["bit_accuracy"].as_f64().unwrap() - mean).abs() < 1e-12,
            "{r3}"
        );
        assert_eq!(r1["draws"].as_array().unwrap().len(), 1);
        assert_eq!(r1["bit_accuracy"].as_f64().unwrap(), d[1], "{r3} {r1}");
    }
    let none = bin()
        .arg("eval")
        .arg(&input)
        .arg(&out)
        .args(VIEWS)
        .args(["--message", "c0ffee42", "--model-draws", "0"])
        .output()
        .unwrap();
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("--model-draws"));

    let renders = dir.path().join("renders");
    assert!(
        bin()
            .arg("render")
            .arg(&out)
            .args(VIEWS)
            .args(["--limit", "2", "--out"])
            .arg(&renders)
            .status()
            .unwrap()
            .success()
    );
    let mut pngs: Vec<_> = std::fs::read_dir(&renders)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    pngs.sort();
    let r = ok_json(
        &bin()
            .arg("verify")
            .args(&pngs)
            .args(["--message", "c0ffee42"])
            .output()
            .unwrap(),
    );
    assert_eq!(r["bits"], 32);
    let acc = r["bit_accuracy"].as_f64().unwrap();
    let p = r["p_value"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&acc) && (0.0..=1.0).contains(&p));
    let decided = r["matches"].as_u64().unwrap() >= r["threshold"].as_u64().unwrap();
    assert_eq!(r["detected"], decided);
}

#[test]
fn a_reference_is_reported_and_verify_reads_it() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let out = dir.path().join("marked.ply");
    let report = dir.path().join("report.json");
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--message", "c0ffee42", "--steps", "1"])
            .arg("--out")
            .arg(&out)
            .arg("--report")
            .arg(&report)
            .output()
            .unwrap(),
    );
    assert_eq!(v["options"]["reference"], true);
    let r = v["reference_logits"].as_array().expect("reference_logits");
    assert_eq!(r.len(), 32);
    assert!(r.iter().all(|z| z.as_f64().unwrap().is_finite()));
    let renders = dir.path().join("renders");
    assert!(
        bin()
            .arg("render")
            .arg(&out)
            .args(VIEWS)
            .args(["--limit", "1", "--out"])
            .arg(&renders)
            .status()
            .unwrap()
            .success()
    );
    let png: Vec<_> = std::fs::read_dir(&renders)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    let plain = ok_json(
        &bin()
            .arg("verify")
            .args(&png)
            .args(["--message", "c0ffee42"])
            .output()
            .unwrap(),
    );
    let relative = ok_json(
        &bin()
            .arg("verify")
            .args(&png)
            .args(["--message", "c0ffee42", "--report"])
            .arg(&report)
            .output()
            .unwrap(),
    );
    assert_eq!(relative["bits"], 32);
    // eval reads the same report.
    let e = ok_json(
        &bin()
            .arg("eval")
            .arg(&input)
            .arg(&out)
            .args(VIEWS)
            .args(["--message", "c0ffee42", "--report"])
            .arg(&report)
            .output()
            .unwrap(),
    );
    assert_eq!(e["views"], 1);
    // Same images, same message: only the reference differs between the two decodings.
    assert_ne!(plain["decoded"], relative["decoded"]);
    // A report for another length is refused.
    let bad = bin()
        .arg("verify")
        .args(&png)
        .args(["--message", "c0ffee42c0ffee42", "--report"])
        .arg(&report)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    // (the report's matched head, read first, names the length it reads)
    assert!(String::from_utf8_lossy(&bad.stderr).contains("matched head for 32 bits"));
    assert_eq!(v["options"]["projection"]["matched"], true);
    assert_eq!(
        v["view_projection"]["head"].as_array().map(Vec::len),
        Some(32 * 128)
    );
    // The report names the decoder the bits were written for: one step leaves the views far
    // above the fidelity bound, so the check (at step 1 of 1) switched to the shipped coarse
    // decoder, which `verify --report` and `eval --report` above read with. Other weights —
    // here the main decoder's weights with another sidecar — are refused, not read as noise.
    let shipped = v["decoder"].as_str().expect("decoder digest");
    assert_eq!(shipped.len(), 64);
    assert_eq!(v["choice"]["coarse"], true, "{}", v["choice"]);
    let (cdec, cside) = splatmark::decoder::artifact::shipped_coarse_bytes(32).unwrap();
    assert_eq!(
        shipped,
        splatmark::decoder::artifact::digest_of(cdec, cside)
    );
    let (dec, _, sidecar) = splatmark::decoder::artifact::shipped_bytes(32).unwrap();
    let mut json: serde_json::Value = serde_json::from_slice(sidecar).unwrap();
    json["note"] = "another decoder".into();
    let other = dir.path().join("other.bpk");
    std::fs::write(&other, dec).unwrap();
    std::fs::write(other.with_extension("json"), json.to_string()).unwrap();
    let bad = bin()
        .arg("verify")
        .args(&png)
        .args(["--message", "c0ffee42", "--weights"])
        .arg(&other)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains(&format!("written for decoder {}", &shipped[..12])),
        "{err}"
    );
    // Plain decoding on request: no reference measured or reported.
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--message", "c0ffee42", "--steps", "1", "--no-reference"])
            .arg("--out")
            .arg(dir.path().join("plain.ply"))
            .output()
            .unwrap(),
    );
    assert_eq!(v["options"]["reference"], false);
    assert!(v["reference_logits"].is_null());
}

#[test]
fn bad_messages_and_sizes_fail_clearly_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let out = dir.path().join("marked.ply");
    for (args, needle) in [
        (
            vec!["--bits", "32", "--message", "abc"],
            "32 bits need 8 hex digits",
        ),
        (
            vec!["--bits", "32", "--message", "zzzzzzzz"],
            "not hexadecimal",
        ),
        (vec!["--bits", "40"], "--bits must be 32, 48 or 64"),
        (vec!["--budget", "150%"], "(0, 100]"),
    ] {
        let o = bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(&args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!out.exists(), "{args:?} left a file");
    }
}

#[test]
fn a_partial_config_file_sets_what_it_names_and_keeps_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let cfg = dir.path().join("cfg.json");
    std::fs::write(
        &cfg,
        r#"{"finetune": {"steps": 2, "weights": {"wm": 0.25}}, "no_group_mask": true}"#,
    )
    .unwrap();
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--message", "0123abcd", "--config"])
            .arg(&cfg)
            .arg("--out")
            .arg(dir.path().join("m.ply"))
            .output()
            .unwrap(),
    );
    let o = &v["options"];
    assert_eq!(o["finetune"]["steps"], 2);
    assert_eq!(o["finetune"]["weights"]["wm"], 0.25);
    let rec = o["finetune"]["weights"]["rec"].as_f64().unwrap();
    assert!(
        (rec - 0.8).abs() < 1e-6,
        "unnamed fields keep defaults: {rec}"
    );
    // Unnamed fields keep the default recipe (coupled, colour only, 4 views per step,
    // relative to the asset) …
    assert_eq!(o["finetune"]["views_per_step"], 4);
    assert_eq!(o["finetune"]["coupled"], true);
    assert_eq!(o["finetune"]["lr"]["means"], 0.0);
    assert_eq!(o["reference"], true);
    assert_eq!(o["no_group_mask"], true);
    assert_eq!(v["mask_wm"], serde_json::json!([1.0, 1.0, 1.0, 1.0, 1.0]));

    std::fs::write(&cfg, r#"{"finetune": {"steps": "many"}}"#).unwrap();
    let o = bin()
        .arg("embed")
        .arg(&input)
        .args(VIEWS)
        .arg("--config")
        .arg(&cfg)
        .arg("--out")
        .arg(dir.path().join("n.ply"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("is not valid embedding options"));
    assert!(!dir.path().join("n.ply").exists());

    // … and --paper starts from the paper's recipe instead.
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--message", "0123abcd", "--steps", "1", "--paper"])
            .arg("--out")
            .arg(dir.path().join("p.ply"))
            .output()
            .unwrap(),
    );
    let o = &v["options"];
    assert_eq!(o["finetune"]["coupled"], false);
    assert_eq!(o["finetune"]["views_per_step"], 2);
    assert!(o["finetune"]["lr"]["opacity"].as_f64().unwrap() > 0.0);
    assert_eq!(o["reference"], false);
}

#[test]
fn embed_on_wgpu_renders_and_decodes_on_the_gpu_and_marks_as_the_cpu_does() {
    // `--device wgpu` on Mesa's lavapipe (`bash scripts/setup.sh`): the views are rendered and
    // decoded on one wgpu device; the steps follow the CPU's up to rounding.
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let run = |device: &str| {
        let out = dir.path().join(format!("marked-{device}.ply"));
        let v = ok_json(
            &bin()
                .arg("embed")
                .arg(&input)
                .args(VIEWS)
                .args(["--message", "c0ffee42", "--steps", "2", "--device", device])
                .arg("--out")
                .arg(&out)
                .output()
                .unwrap(),
        );
        assert_eq!(
            read_scene(&out, &Limits::default()).unwrap().len() as u64,
            v["output_gaussians"].as_u64().unwrap()
        );
        v
    };
    let (cpu, gpu) = (run("cpu"), run("wgpu"));
    assert_eq!(cpu["rasterizer"], "cpu");
    assert!(
        gpu["rasterizer"].as_str().unwrap().starts_with("wgpu: "),
        "{}",
        gpu["rasterizer"]
    );
    assert_eq!(cpu["carriers"], gpu["carriers"]);
    for key in ["l_wm", "psnr"] {
        let (a, b) = (
            cpu["last_step"][key].as_f64().unwrap(),
            gpu["last_step"][key].as_f64().unwrap(),
        );
        assert!((a - b).abs() <= 0.05 * a.abs(), "{key}: cpu {a}, wgpu {b}");
    }
}

#[test]
fn explain_draws_where_the_message_lives_for_each_view() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let out = dir.path().join("marked.ply");
    let attr = dir.path().join("attr.jsonl");
    let v = ok_json(
        &bin()
            .arg("embed")
            .arg(&input)
            .args(VIEWS)
            .args(["--message", "c0ffee42", "--steps", "2"])
            .arg("--out")
            .arg(&out)
            .arg("--attribution")
            .arg(&attr)
            .output()
            .unwrap(),
    );
    let pictures = dir.path().join("explain");
    let e = ok_json(
        &bin()
            .arg("explain")
            .arg(&out)
            .arg("--attribution")
            .arg(&attr)
            .arg("--original")
            .arg(&input)
            .args(VIEWS)
            .args(["--limit", "2", "--out"])
            .arg(&pictures)
            .output()
            .unwrap(),
    );
    assert_eq!(e["views"], 2);
    assert_eq!(e["carriers"], v["carriers"]);
    assert_eq!(e["gaussians"], v["output_gaussians"]);
    let index = std::fs::read_to_string(pictures.join("index.html")).unwrap();
    for kind in ["view", "roles", "heat", "diff10"] {
        let name = format!("000_orbit_000_{kind}.png");
        assert!(index.contains(&name), "{kind} missing from index.html");
        let img = image::open(pictures.join(&name)).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (64, 64));
        // Every picture shows something: the object over the black background.
        assert!(img.pixels().any(|p| p.0 != [0, 0, 0]), "{kind} is black");
    }
    // The role picture shows carriers in red.
    let roles = image::open(pictures.join("000_orbit_000_roles.png"))
        .unwrap()
        .to_rgb8();
    assert!(
        roles
            .pixels()
            .any(|p| p.0[0] > 150 && p.0[1] < 90 && p.0[2] < 90),
        "no carrier in view"
    );
    // The records of another scene are refused.
    let o = bin()
        .arg("explain")
        .arg(&input)
        .arg("--attribution")
        .arg(&attr)
        .args(VIEWS)
        .arg("--out")
        .arg(dir.path().join("wrong"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("not this scene's attribution"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn planning_and_calibration_read_a_subset_of_the_views_for_32_bit_payloads_only() {
    let dir = tempfile::tempdir().unwrap();
    let input = scene(dir.path());
    let config = dir.path().join("embed.json");
    std::fs::write(&config, r#"{"analysis_views": 3}"#).unwrap();
    for (bits, message, read) in [(32, "c0ffee42", 3), (48, "c0ffee42c0ff", 7)] {
        let v = ok_json(
            &bin()
                .arg("embed")
                .arg(&input)
                .args(VIEWS)
                .args([
                    "--bits",
                    &bits.to_string(),
                    "--message",
                    message,
                    "--steps",
                    "2",
                ])
                .arg("--config")
                .arg(&config)
                .arg("--out")
                .arg(dir.path().join(format!("marked-{bits}.ply")))
                .output()
                .unwrap(),
        );
        assert_eq!(v["views"], 7);
        assert_eq!(v["analysis_views"], read, "{bits} bits");
    }
}
