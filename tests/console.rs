//! The web console in a real browser: headless Chromium, driven through chromedriver, against a
//! real server — sign in, upload a scene, run a short watermark job to the end, open the
//! attribution viewer and pick a Gaussian, verify rendered images, read the audit log and check
//! its chain. Screenshots of each page are written to `CARGO_TARGET_TMPDIR/console-screenshots/`.
//! Skips loudly when Chromium or chromedriver is missing (`scripts/setup.sh` installs both).

mod common;
#[path = "common/webdriver.rs"]
mod webdriver;

use std::time::Duration;

use common::{TestApp, ply_bytes};
use reqwest::StatusCode;
use serde_json::Value;
use splatmark::render::{RenderOptions, render, to_rgb8};
use splatmark::scene::orbit::{OrbitOptions, orbit_cameras};
use splatmark::scene::read_scene_bytes;
use splatmark::scene::synthetic::object_scene;
use webdriver::Browser;

/// The job's options: the toy round trip's (`common::small_job`), as a user pastes them.
const OPTIONS: &str = r#"{"orbit": {"count": 8, "width": 128, "height": 128}, "holdout_every": 0,
 "embed": {"finetune": {"steps": 40, "extra_steps": 300, "coupled": true, "wm_lr_scale": 5.0,
 "views_per_step": 4, "target_psnr": 0.0}}}"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_owner_watermarks_looks_verifies_and_audits_in_the_console() {
    let Some((chromium, driver)) = webdriver::browser() else {
        eprintln!(
            "SKIPPED: the console browser test needs chromium and chromedriver \
             (scripts/setup.sh installs them)"
        );
        return;
    };
    let shots = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("console-screenshots");
    let t = TestApp::start().await;
    let scene_file = t.dir.path().join("toy.ply");
    std::fs::write(&scene_file, ply_bytes(&object_scene(600, 0, 5))).unwrap();
    let b = Browser::start(&chromium, &driver).await;
    let wait = Duration::from_secs(20);

    // The page itself needs no key, and carries the console's own policy.
    let page = t.client.get(t.url("/")).send().await.unwrap();
    assert_eq!(page.status(), StatusCode::OK);
    let csp = page.headers()["content-security-policy"].to_str().unwrap();
    assert!(
        csp.contains("script-src 'self'") && !csp.contains("unsafe"),
        "{csp}"
    );

    // Sign in: a wrong key is refused and not kept; the admin key is.
    b.goto(&t.url("/")).await;
    let key = b.find("#api-key", wait).await;
    b.type_into(&key, "not-a-key").await;
    b.click(&b.find("#signin", wait).await).await;
    b.find("[role=alert]", wait).await;
    assert_eq!(
        b.script("return sessionStorage.getItem('splatmark.api_key')")
            .await,
        Value::Null
    );
    b.script("document.getElementById('api-key').value = ''")
        .await;
    b.type_into(&key, &t.admin).await;
    b.click(&b.find("#signin", wait).await).await;

    // Upload with progress, then open the asset.
    let input = b.find("#upload-scene", wait).await;
    b.type_into(&input, scene_file.to_str().unwrap()).await;
    b.click(&b.find("#upload", wait).await).await;
    let link = b.find("#uploaded-link", wait).await;
    assert_eq!(
        b.script("return document.getElementById('upload-progress').value")
            .await,
        serde_json::json!(100)
    );
    b.screenshot(&shots, "1-uploaded").await;
    b.click(&link).await;

    // Start a job and watch it to the end.
    b.click(&b.find("#wm-advanced", wait).await).await;
    b.type_into(&b.find("#wm-options", wait).await, OPTIONS)
        .await;
    b.click(&b.find("#wm-start", wait).await).await;
    b.find("#job-status", wait).await;
    b.wait(
        "const s = document.getElementById('job-status'); \
         return s !== null && s.dataset.state !== undefined && s.dataset.state !== 'queued'",
        Duration::from_secs(60),
    )
    .await;
    b.screenshot(&shots, "2-job-running").await;
    b.wait(
        "const s = document.getElementById('job-status'); \
         return s !== null && ['done', 'failed', 'dead', 'cancelled'].includes(s.dataset.state)",
        Duration::from_secs(600),
    )
    .await;
    let status = b.text(&b.find("#job-status", wait).await).await;
    assert!(status.starts_with("done"), "{status}");
    b.screenshot(&shots, "3-job-done").await;
    let result = b.find("#job-result-link", wait).await;
    let marked_id = b.text(&result).await;
    b.click(&result).await;

    // The attribution viewer: the roles picture, then the "why" of the Gaussian at its centre.
    b.click(&b.find("#layer-roles", wait).await).await;
    b.wait(
        "const i = document.getElementById('attr-image'); \
         return i !== null && i.dataset.layer === 'roles' && i.dataset.ready === '1' \
         && i.complete && i.naturalWidth === 384",
        Duration::from_secs(60),
    )
    .await;
    // The picture shows the roles' colours: some pixels red (carriers).
    let red = b
        .script(
            "const i = document.getElementById('attr-image'); const c = document.createElement('canvas'); \
             c.width = i.naturalWidth; c.height = i.naturalHeight; const g = c.getContext('2d'); \
             g.drawImage(i, 0, 0); const d = g.getImageData(0, 0, c.width, c.height).data; let n = 0; \
             for (let k = 0; k < d.length; k += 4) if (d[k] > 120 && d[k + 2] < 60) n++; return n;",
        )
        .await;
    assert!(red.as_u64().unwrap() > 50, "carrier pixels: {red}");
    b.click(&b.find("#attr-image", wait).await).await;
    let why = b.find("#why-title", Duration::from_secs(60)).await;
    let title = b.text(&why).await;
    assert!(title.starts_with("Gaussian "), "{title}");
    b.screenshot(&shots, "4-attribution").await;

    // Back on the original's page, its jobs list the finished job and link its result.
    b.click(&b.find("#parent-link", wait).await).await;
    b.find(&format!("#jobs-table a[href='#/asset/{marked_id}']"), wait)
        .await;
    assert_eq!(
        b.script("return document.querySelector('#jobs-table td[data-state]').dataset.state")
            .await,
        serde_json::json!("done")
    );
    b.screenshot(&shots, "4b-jobs").await;

    // Verify four renders of the watermarked scene through the verification page.
    let r = t
        .get(&t.admin, &format!("/v1/assets/{marked_id}/file"))
        .await;
    assert_eq!(r.status(), StatusCode::OK);
    let g = read_scene_bytes(&r.bytes().await.unwrap(), None, &Default::default()).unwrap();
    let cams = orbit_cameras(
        &g,
        &OrbitOptions {
            count: 8,
            width: 128,
            height: 128,
            ..OrbitOptions::default()
        },
    )
    .unwrap();
    let mut paths = Vec::new();
    for (k, cam) in cams.iter().take(4).enumerate() {
        let img = render(&g, cam, &RenderOptions::default()).unwrap();
        let p = t.dir.path().join(format!("view{k}.png"));
        to_rgb8(img.width, img.height, &img.image).save(&p).unwrap();
        paths.push(p.to_str().unwrap().to_string());
    }
    b.goto(&t.url("/#/verify")).await;
    b.type_into(&b.find("#verify-images", wait).await, &paths.join("\n"))
        .await;
    b.click(&b.find("#verify", wait).await).await;
    let verdict = b.find("#verdict", Duration::from_secs(60)).await;
    assert_eq!(b.text(&verdict).await, "Detected");
    let explained = b.text(&b.find("#verdict-explained", wait).await).await;
    assert!(explained.contains("p-value"), "{explained}");
    b.screenshot(&shots, "5-verified").await;

    // The audit page shows the verification's decision and a chain that holds.
    b.goto(&t.url("/#/audit")).await;
    b.find("#audit-table tr[data-action=verify]", wait).await;
    b.click(&b.find("#audit-verify", wait).await).await;
    b.wait(
        "const c = document.getElementById('audit-chain'); \
         return c !== null && c.innerText.startsWith('The chain holds')",
        wait,
    )
    .await;
    b.screenshot(&shots, "6-audit").await;
    b.close().await;
    eprintln!("console screenshots: {}", shots.display());
}
