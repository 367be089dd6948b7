//! Every committed fuzz input — the seed corpora (`fuzz/corpus/<target>/`) and the inputs of
//! past findings (`fuzz/regressions/<target>/`) — through the fuzz targets' own checks, without
//! AFL: a finding saved there is a regression test from then on (docs/RELIABILITY.md).

#[path = "../fuzz/src/lib.rs"]
mod targets;

use std::path::Path;

#[test]
fn every_committed_fuzz_input_passes_its_targets_checks() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut ran = 0;
    for target in targets::TARGETS {
        let mut per_target = 0;
        for folder in ["corpus", "regressions"] {
            let dir = root.join(folder).join(target);
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            let mut files: Vec<_> = entries.map(|e| e.unwrap().path()).collect();
            files.sort();
            for f in files {
                let data = std::fs::read(&f).unwrap();
                let outcome = std::panic::catch_unwind(|| targets::run(target, &data));
                assert!(
                    matches!(outcome, Ok(true)),
                    "{target}: {} fails the target's checks",
                    f.display()
                );
                per_target += 1;
            }
        }
        assert!(
            per_target > 0,
            "no committed input for fuzz target {target}"
        );
        ran += per_target;
    }
    println!("{ran} committed fuzz inputs replayed");
}
