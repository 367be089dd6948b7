//! `splatmark bench paper --quick` end to end on the shared lego dataset: the scene is fitted
//! from the posed images into the cache (and reused by the next run), watermarked through
//! training cameras, evaluated on the dataset's test cameras, and the tables put our rows
//! beside the paper's. A few minutes on two cores; skipped, loudly, when
//! `../shared/data/datasets` is missing.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn datasets_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/datasets");
    if dir
        .join("nerf_synthetic_lego/transforms_train.json")
        .is_file()
    {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED: {} is missing (the shared data folder); the quick paper bench needs lego",
            dir.display()
        );
        None
    }
}

fn bench(datasets: &Path, cache: &Path, out: &Path, md: &Path) -> Output {
    let res = Command::new(env!("CARGO_BIN_EXE_splatmark"))
        .args(["bench", "paper", "--quick", "--datasets"])
        .arg(datasets)
        .arg("--cache")
        .arg(cache)
        .arg("--out")
        .arg(out)
        .arg("--markdown")
        .arg(md)
        .output()
        .unwrap();
    assert!(
        res.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&res.stderr)
    );
    res
}

#[test]
fn the_quick_paper_bench_fits_lego_and_evaluates_on_its_test_views() {
    let Some(datasets) = datasets_dir() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let (out, md) = (dir.path().join("paper.json"), dir.path().join("paper.md"));
    let first = bench(&datasets, &cache, &out, &md);
    assert!(String::from_utf8_lossy(&first.stderr).contains("lego: fitting 300 steps"));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let fit = &report["fits"][0];
    assert_eq!(fit["name"], "lego");
    assert_eq!(
        (fit["train_views"].as_u64(), fit["test_views"].as_u64()),
        (Some(100), Some(25))
    );
    assert_eq!(fit["width"], 128);
    // 300 steps from random points: a rough but recognisable lego on its test views.
    assert!(fit["test"]["psnr"].as_f64().unwrap() > 18.0, "{fit}");

    let run = &report["runs"][0];
    assert_eq!(
        (run["dataset"].as_str(), run["bits"].as_u64()),
        (Some("lego"), Some(32))
    );
    assert_eq!(
        (run["train_views"].as_u64(), run["test_views"].as_u64()),
        (Some(12), Some(4))
    );
    let eval = &run["eval"];
    // The test views are dataset cameras the embedding never rendered; the watermark is
    // invisible there and carries more than chance.
    assert!(eval["psnr"].as_f64().unwrap() > 30.0, "{eval}");
    let clean = eval["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["name"] == "clean")
        .unwrap();
    assert!(clean["bit_accuracy"].as_f64().unwrap() > 0.65, "{clean}");
    let tables = std::fs::read_to_string(&md).unwrap();
    for needle in [
        "Table 1",
        "Table 2",
        "Table 3",
        "| paper (Ours) | 98.46 |",
        "| splatmark, lego |",
    ] {
        assert!(tables.contains(needle), "{needle} missing from\n{tables}");
    }

    // A second run reuses the fitted scene and the finished embedding (an interrupted
    // protocol resumes where it stopped): the same figures, nothing fitted or embedded again.
    let second = bench(&datasets, &cache, &out, &md);
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(stderr.contains("lego: reusing the fit"), "{stderr}");
    assert!(!stderr.contains("fitting 300 steps"), "{stderr}");
    assert!(stderr.contains("reusing the finished run"), "{stderr}");
    assert!(!stderr.contains("embedding over"), "{stderr}");
    let again: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(again["runs"], report["runs"]);
}
