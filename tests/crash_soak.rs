//! The crash soak at CI scale: `scripts/crash-soak.sh` starts the real `serve`, uploads scenes,
//! enqueues watermark jobs and `kill -9`s the server at random moments (mid-upload, mid-claim,
//! mid-finetune, mid-publish), restarting it each time; then every accepted job must be done
//! exactly once, every upload answered 201 must still be there byte for byte, no 5xx answered,
//! `PRAGMA integrity_check` ok, every blob matching its SHA-256, the audit chain valid, and a
//! backup of the result must restore. The long soak (≥ 20 kills) is the same script run by hand
//! (docs/RELIABILITY.md). Needs bash, curl and python3 (scripts/setup.sh installs them).

use std::process::Command;

#[test]
fn the_service_survives_kill_9_at_random_moments_without_losing_or_doubling_anything() {
    for tool in ["bash", "curl", "python3"] {
        let found = Command::new("sh")
            .args(["-c", &format!("command -v {tool}")])
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false);
        assert!(
            found,
            "{tool} is needed by scripts/crash-soak.sh (scripts/setup.sh installs it)"
        );
    }
    let root = env!("CARGO_MANIFEST_DIR");
    let out = Command::new("bash")
        .arg(format!("{root}/scripts/crash-soak.sh"))
        .args(["--binary", env!("CARGO_BIN_EXE_splatmark")])
        .args(["--kills", "8", "--seed", "7"])
        .env("TMPDIR", std::env::temp_dir())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "crash soak failed\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    let summary = stdout
        .lines()
        .chain(stderr.lines())
        .find(|l| l.starts_with("crash-soak: OK"))
        .unwrap_or_else(|| panic!("no summary line\nstdout:\n{stdout}\nstderr:\n{stderr}"));
    assert!(summary.contains("kills=8"), "{summary}");
    assert!(summary.contains("chain=ok integrity=ok"), "{summary}");
}
