//! `splatmark bench quality --quick` end to end on the shared donut scene: the defaults a user
//! gets embed a 32-bit message, and views the finetuning never saw (other azimuths and
//! elevations) detect it at the bench's false-positive rate (1e-6) while the unmarked scene does
//! not. A few minutes on one core; skipped, loudly, when `../shared/data/scenes` is missing.

use std::path::PathBuf;
use std::process::Command;

fn scenes_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
    if dir.join("donut").is_dir() {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED: {} is missing (the shared data folder); the quick quality bench needs donut",
            dir.display()
        );
        None
    }
}

fn row<'a>(run: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    run["eval"]["rows"]
        .as_array()
        .expect("rows")
        .iter()
        .find(|r| r["name"] == name)
        .unwrap_or_else(|| panic!("no {name} row in {run}"))
}

#[test]
fn the_quick_bench_detects_the_defaults_watermark_on_unseen_views() {
    let Some(scenes) = scenes_dir() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("quick.json");
    let md = dir.path().join("quick.md");
    let res = Command::new(env!("CARGO_BIN_EXE_splatmark"))
        .args(["bench", "quality", "--quick", "--scenes"])
        .arg(&scenes)
        .arg("--out")
        .arg(&out)
        .arg("--markdown")
        .arg(&md)
        .arg("--assets")
        .arg(dir.path().join("assets"))
        .output()
        .unwrap();
    assert!(
        res.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&res.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let run = &report["runs"][0];
    assert_eq!(run["scene"], "donut");
    assert_eq!(run["bits"], 32);
    // Which decoder the bits were written for: the shipped one.
    let (dec, _, sidecar) = splatmark::decoder::artifact::shipped_bytes(32).unwrap();
    assert_eq!(
        run["decoder"],
        splatmark::decoder::artifact::digest_of(dec, sidecar)
    );
    let eval = &run["eval"];
    assert_eq!(eval["fpr"], 1e-6);
    assert!(eval["views"].as_u64().unwrap() >= 4);
    // Invisible: the watermarked scene's unseen views against the original's.
    let psnr = eval["psnr"].as_f64().unwrap();
    assert!(psnr >= 36.0, "PSNR {psnr} dB on unseen views");
    // Detected from the unseen views together, at FPR 1e-6, and most bits right in each.
    let clean = row(run, "clean");
    assert_eq!(clean["detected"], true, "{clean}");
    assert!(clean["p_value"].as_f64().unwrap() < 1e-6, "{clean}");
    assert!(clean["bit_accuracy"].as_f64().unwrap() >= 0.8, "{clean}");
    // Through a real JPEG at quality 50 too.
    let jpeg = row(run, "jpeg");
    assert_eq!(jpeg["detected"], true, "{jpeg}");
    // The unmarked original is not accused.
    let unmarked = row(run, "unmarked");
    assert_eq!(unmarked["detected"], false, "{unmarked}");
    assert_eq!(unmarked["detection_rate_per_view"], 0.0, "{unmarked}");
    // Each model attack is read over two draws (the quick bench's), the targets on their mean.
    let remove = row(run, "remove_20");
    let draws = remove["draws"].as_array().expect("draws");
    assert_eq!(draws.len(), 2, "{remove}");
    let mean = draws.iter().map(|d| d.as_f64().unwrap()).sum::<f64>() / 2.0;
    assert!((remove["bit_accuracy"].as_f64().unwrap() - mean).abs() < 1e-12);
    // And view by view, in the order of the views: their mean is the row's accuracy.
    let by_view: Vec<f64> = remove["view_accuracy"]
        .as_array()
        .expect("view_accuracy")
        .iter()
        .map(|a| a.as_f64().unwrap())
        .collect();
    assert_eq!(by_view.len() as u64, eval["views"].as_u64().unwrap());
    let mean = by_view.iter().sum::<f64>() / by_view.len() as f64;
    assert!((remove["bit_accuracy"].as_f64().unwrap() - mean).abs() < 1e-12);
    // The markdown table names the scene and says which targets were missed, and gives each
    // model attack's worst draw and weakest view.
    let table = std::fs::read_to_string(&md).unwrap();
    assert!(table.starts_with("| scene |") && table.contains("donut"));
    assert!(
        table.contains("remove_20") && table.contains("(worst ") && table.contains("weakest view "),
        "{table}"
    );
    // The embedding it judged is kept for a second look: the watermarked scene, its report
    // (the message, the decoder) and one line per finetuning step.
    let kept = dir.path().join("assets/donut-32-seed0");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(kept.with_extension("report.json")).unwrap())
            .unwrap();
    assert_eq!(report["decoder"], run["decoder"]);
    assert_eq!(report["bits"], 32);
    assert_eq!(report["message_hex"].as_str().unwrap().len(), 8);
    let g = splatmark::scene::read_scene(
        kept.with_extension("ply"),
        &splatmark::scene::Limits::default(),
    )
    .unwrap();
    assert_eq!(g.len() as u64, report["output_gaussians"].as_u64().unwrap());
    let steps = std::fs::read_to_string(kept.with_extension("steps.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(steps.lines().last().unwrap()).unwrap();
    assert_eq!(steps.lines().count() as u64, run["steps"].as_u64().unwrap());
    assert_eq!(last["step"], run["steps"]);
}
