//! `splatmark fit` end to end on a NeRF-synthetic folder written here: renders of a synthetic
//! object (RGBA PNGs, `transforms_train.json`, `transforms_test.json`) are fitted from random
//! points, the output is an INRIA PLY that reads back, the report measures the test views, and
//! a finished fit resumed from its checkpoint writes the same scene.

use splatmark::render::{RenderOptions, render};
use splatmark::scene::orbit::{OrbitOptions, orbit_cameras};
use splatmark::scene::synthetic::object_scene;
use splatmark::scene::{Camera, Limits, read_scene};
use std::path::Path;
use std::process::Command;

/// Camera → world in NeRF's OpenGL convention (x right, y up, z backwards).
fn nerf_matrix(c: &Camera) -> [[f32; 4]; 4] {
    let r = c.rotation; // world → camera, rows are the camera axes in world space
    let centre = c.center();
    let mut m = [[0.0; 4]; 4];
    for row in 0..3 {
        m[row][0] = r[0][row];
        m[row][1] = -r[1][row];
        m[row][2] = -r[2][row];
        m[row][3] = centre[row];
    }
    m[3][3] = 1.0;
    m
}

/// Writes `split` views of the object as a NeRF-synthetic split (transparent background).
fn write_split(dir: &Path, split: &str, cams: &[Camera]) {
    let truth = object_scene(300, 1, 9);
    std::fs::create_dir_all(dir.join(split)).unwrap();
    let mut frames = Vec::new();
    for (i, cam) in cams.iter().enumerate() {
        // Alpha = 1 − T: render on black for the colour and on white for the transmittance.
        let on = |bg: f32| {
            let o = RenderOptions {
                background: [bg; 3],
                ..RenderOptions::default()
            };
            render(&truth, cam, &o).unwrap().image
        };
        let (black, white) = (on(0.0), on(1.0));
        let mut img = image::RgbaImage::new(cam.width, cam.height);
        for (k, p) in img.pixels_mut().enumerate() {
            let t = (white[k][0] - black[k][0]).clamp(0.0, 1.0);
            let a = 1.0 - t;
            let c = |v: f32| {
                let straight = if a > 1e-3 { v / a } else { 0.0 };
                (straight.clamp(0.0, 1.0) * 255.0).round() as u8
            };
            *p = image::Rgba([
                c(black[k][0]),
                c(black[k][1]),
                c(black[k][2]),
                (a * 255.0).round() as u8,
            ]);
        }
        img.save(dir.join(split).join(format!("r_{i}.png")))
            .unwrap();
        frames.push(serde_json::json!({
            "file_path": format!("./{split}/r_{i}"),
            "transform_matrix": nerf_matrix(cam),
        }));
    }
    let fov_x = cams[0].fov().0;
    let doc = serde_json::json!({ "camera_angle_x": fov_x, "frames": frames });
    std::fs::write(
        dir.join(format!("transforms_{split}.json")),
        serde_json::to_vec_pretty(&doc).unwrap(),
    )
    .unwrap();
}

fn dataset(dir: &Path) {
    let truth = object_scene(300, 1, 9);
    let cams = |count: usize, elevations: Vec<f32>, offset: f32| {
        orbit_cameras(
            &truth,
            &OrbitOptions {
                count,
                elevations_deg: elevations,
                width: 96,
                height: 96,
                azimuth_offset_deg: offset,
                ..OrbitOptions::default()
            },
        )
        .unwrap()
    };
    write_split(dir, "train", &cams(24, vec![-20.0, 10.0, 35.0], 0.0));
    write_split(dir, "test", &cams(4, vec![20.0], 7.0));
}

fn fit(dir: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_splatmark"))
        .arg("fit")
        .arg(dir)
        .arg("--out")
        .arg(out)
        .args([
            "--iterations",
            "400",
            "--max-side",
            "64",
            "--sh-degree",
            "1",
        ])
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn fit_turns_a_posed_image_folder_into_a_scene_that_renders_its_test_views() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("object");
    dataset(&data);
    let out = tmp.path().join("fitted.ply");
    let cfg = tmp.path().join("fit.json");
    // A short schedule: densify from step 100, reset opacities every 200.
    std::fs::write(
        &cfg,
        r#"{"init_points": 3000, "sh_up_every": 200,
            "densify": {"from": 100, "every": 50, "opacity_reset_every": 200}}"#,
    )
    .unwrap();
    let cfg_arg = cfg.to_str().unwrap();
    let res = fit(&data, &out, &["--config", cfg_arg, "--eval-every", "200"]);
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "stderr: {stderr}");
    assert!(stderr.contains("test views PSNR"), "{stderr}");
    let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    assert_eq!(report["kind"], "blender");
    assert_eq!(
        (
            report["train_views"].as_u64(),
            report["test_views"].as_u64()
        ),
        (Some(24), Some(4))
    );
    assert_eq!(
        (report["width"].as_u64(), report["height"].as_u64()),
        (Some(64), Some(64))
    );
    let psnr = report["test"]["psnr"].as_f64().unwrap();
    assert!(psnr > 22.0, "test PSNR {psnr}: {report}");
    let g = read_scene(&out, &Limits::default()).unwrap();
    assert_eq!(g.len() as u64, report["gaussians"].as_u64().unwrap());
    assert_eq!(g.sh_degree, 1);

    // Resuming the finished fit runs no step and writes the same scene.
    let first = std::fs::read(&out).unwrap();
    let res = fit(&data, &out, &["--config", cfg_arg, "--resume"]);
    assert!(
        res.status.success(),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let again: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    assert_eq!(again["steps_run"], 0);
    assert_eq!(std::fs::read(&out).unwrap(), first);

    // Resuming under another configuration is refused, and nothing is written.
    let res = fit(
        &data,
        &out,
        &["--config", cfg_arg, "--resume", "--seed", "7"],
    );
    assert!(!res.status.success());
    assert!(String::from_utf8_lossy(&res.stderr).contains("another configuration"));
    assert_eq!(std::fs::read(&out).unwrap(), first);
}

#[test]
fn a_folder_that_is_not_a_dataset_is_a_clear_error_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("x.ply");
    let res = fit(tmp.path(), &out, &[]);
    assert!(!res.status.success());
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(stderr.contains("transforms_train.json"), "{stderr}");
    assert!(!out.exists());
}
