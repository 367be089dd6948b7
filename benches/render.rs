//! Rasterizer benchmarks: forward and forward + backward at 800×800 on synthetic scenes of 10k,
//! 100k and 1M Gaussians, and on the real scenes in ../shared/data when present; on the GPU path
//! also a finetuning step's GPU work with everything on the device (render, backward from a
//! burn tensor, gradients summed there, one Adam step).
//!
//! Run: `cargo bench --bench render` (add `-- --quick` for fewer repetitions, and words such as
//! `-- 100k donut "ply io"` to run only the benchmarks whose names contain them). Prints a Markdown
//! table; figures are recorded in docs/BENCHMARKS.md.

use burn::tensor::{Tensor, TensorData};
use splatmark::render::gpu::{AdapterChoice, GpuRenderer, StepPlan, shared};
use splatmark::render::{RenderOptions, backward, render};
use splatmark::scene::orbit::{OrbitOptions, orbit_cameras};
use splatmark::scene::{
    Camera, Gaussians, Limits, read_scene, read_scene_bytes, synthetic, write_ply,
};
use std::time::{Duration, Instant};

fn median(mut v: Vec<Duration>) -> f64 {
    v.sort();
    v[v.len() / 2].as_secs_f64() * 1e3
}

fn camera_for(radius: f32, width: u32, height: u32) -> Camera {
    // Looking at the origin from distance 3·radius along −z, 50° vertical field of view.
    let f = height as f32 / 2.0 / (25f32.to_radians()).tan();
    let eye = glam::Vec3::new(0.3 * radius, -0.4 * radius, -3.0 * radius);
    let fwd = (-eye).normalize();
    let right = glam::Vec3::Y.cross(fwd).normalize();
    let down = fwd.cross(right);
    let c2w = glam::Mat3::from_cols(right, down, fwd);
    Camera::from_pose(
        "bench",
        width,
        height,
        f,
        f,
        width as f32 / 2.0,
        height as f32 / 2.0,
        c2w,
        eye,
    )
}

fn bench(name: &str, g: &Gaussians, cam: &Camera, reps: usize, gpu: Option<&GpuRenderer>) {
    if !selected(name) {
        return;
    }
    let opts = RenderOptions::default();
    let warm = render(g, cam, &opts).expect("render");
    let stats = warm.stats;
    let mut fwd = Vec::new();
    let mut both = Vec::new();
    let d_image = vec![[1.0f32 / (cam.width * cam.height) as f32; 3]; warm.image.len()];
    for _ in 0..reps {
        let t0 = Instant::now();
        let r = render(g, cam, &opts).expect("render");
        fwd.push(t0.elapsed());
        let t1 = Instant::now();
        let r2 = render(g, cam, &opts).expect("render");
        let grads = backward(g, &r2, &d_image).expect("backward");
        both.push(t1.elapsed());
        std::hint::black_box((r, grads));
    }
    // The GPU path: upload, every kernel, and the image read back (what a caller waits for);
    // and the same render of a scene uploaded once before.
    let gpu_ms = gpu.map_or("– | – | – | –".to_string(), |r| {
        let warm = match r.render(g, cam, &opts) {
            Ok(w) => w,
            Err(e) => return format!("{e} | – | – | –"),
        };
        let (mut fwd, mut both, mut uploaded) = (Vec::new(), Vec::new(), Vec::new());
        let up = r.upload(g, &opts).expect("gpu upload");
        for _ in 0..reps {
            let t0 = Instant::now();
            std::hint::black_box(r.render(g, cam, &opts).expect("gpu render"));
            fwd.push(t0.elapsed());
            // Another view of a scene already uploaded (a job's views, `splatmark render`).
            let t0 = Instant::now();
            std::hint::black_box(r.render_uploaded(&up, cam, &opts).expect("gpu render"));
            uploaded.push(t0.elapsed());
            let t1 = Instant::now();
            let f = r.render(g, cam, &opts).expect("gpu render");
            std::hint::black_box(r.backward(g, &f, &d_image).expect("gpu backward"));
            both.push(t1.elapsed());
        }
        format!(
            "{:.1} ({} entries) | {:.1} | {:.1} | {}",
            median(fwd),
            warm.tile_entries,
            median(uploaded),
            median(both),
            device_step(r, g, cam, &d_image, reps)
        )
    });
    println!(
        "| {name} | {} | {}×{} | {} | {} | {:.1} | {:.1} | {gpu_ms} |",
        g.len(),
        cam.width,
        cam.height,
        stats.visible,
        stats.tile_entries,
        median(fwd),
        median(both)
    );
}

/// A finetuning step's GPU work for one view with everything on the device (what a GPU job
/// runs): render from the live parameters (image kept there), ∂L/∂image from a burn tensor
/// into the backward, the gradients summed on the device, one Adam step of every parameter —
/// nothing read back but the render's entry count (the Adam step waits for the device).
fn device_step(
    r: &GpuRenderer,
    g: &Gaussians,
    cam: &Camera,
    d_image: &[[f32; 3]],
    reps: usize,
) -> String {
    let n = g.len();
    let plan = StepPlan {
        rates: vec![[1e-4, 2.5e-3, 1.25e-4, 2.5e-2, 1e-3, 5e-3]; n],
        carrier: vec![true; n],
        bounded: vec![true; n],
    };
    let (device, mut params) = match (r.burn_device(), r.upload_params(g, g, &plan)) {
        (Ok(d), Ok(p)) => (d, p),
        (Err(e), _) | (_, Err(e)) => return e.to_string(),
    };
    let (w, h) = (cam.width as usize, cam.height as usize);
    let planar: Vec<f32> = (0..3)
        .flat_map(|c| d_image.iter().map(move |p| p[c]))
        .collect();
    let d = Tensor::<4>::from_data(TensorData::new(planar, [1, 3, h, w]), &device);
    let opts = RenderOptions::default();
    let mut times = Vec::new();
    for _ in 0..reps {
        let t0 = Instant::now();
        let step = (|| {
            let f = r.render_resident(params.scene(), cam, &opts)?;
            let sum = r.backward_tensors_summed_on_device(g, &[(&f, d.clone())])?;
            r.adam_step(&mut params, &sum, &sum, true, 1.0)
        })();
        if let Err(e) = step {
            return e.to_string();
        }
        times.push(t0.elapsed());
    }
    format!("{:.1}", median(times))
}

/// Benchmarks whose name contains one of the non-flag arguments (all when there are none).
fn selected(name: &str) -> bool {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    filters.is_empty() || filters.iter().any(|f| name.contains(f.as_str()))
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let reps = if quick { 3 } else { 9 };
    // `-- --no-gpu` leaves the wgpu column out.
    let gpu = if std::env::args().any(|a| a == "--no-gpu") {
        None
    } else {
        match shared(AdapterChoice::AllowSoftware) {
            Ok(r) => Some(r),
            Err(e) => {
                eprintln!("no wgpu adapter ({e}): the wgpu column is left empty");
                None
            }
        }
    };
    println!(
        "threads: {}, reps: {reps} (median), wgpu adapter: {}\n\n| scene | Gaussians | image | visible | tile entries | forward ms | forward+backward ms | wgpu forward ms | wgpu forward, scene uploaded ms | wgpu forward+backward ms | wgpu step on the device ms |\n|---|---|---|---|---|---|---|---|---|---|---|",
        rayon::current_num_threads(),
        gpu.as_ref().map_or("none".to_string(), |r| format!(
            "{} ({:?}, {:?})",
            r.adapter().name,
            r.adapter().device_type,
            r.adapter().backend
        ))
    );
    let gpu = gpu.as_deref();
    for n in [10_000, 100_000, 1_000_000] {
        let g = synthetic::object_scene(n, 3, 42);
        bench(
            &format!("synthetic SH3 {}k", n / 1000),
            &g,
            &camera_for(1.0, 800, 800),
            reps,
            gpu,
        );
    }
    // SPLATMARK_SCENES: the scenes folder when the binary runs away from its checkout
    // (scripts/gpu-bench.sh on a GPU machine).
    let data = std::env::var_os("SPLATMARK_SCENES")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes")
        });
    for (name, file) in [
        ("donut (real, SH0)", "donut/fused.ply"),
        ("plant (real, SH0)", "plant/plant.splat"),
    ] {
        let path = data.join(file);
        if !path.exists() {
            eprintln!("SKIPPED {name}: {} not found", path.display());
            continue;
        }
        let g = read_scene(&path, &Limits::default()).expect("scene");
        let opts = OrbitOptions {
            count: 1,
            elevations_deg: vec![20.0],
            ..OrbitOptions::default()
        };
        let cam = orbit_cameras(&g, &opts).expect("orbit").remove(0);
        bench(name, &g, &cam, reps, gpu);
    }

    // Scene I/O: INRIA binary PLY of 1M SH3 Gaussians (236 MB), in memory.
    if !selected("ply io") {
        return;
    }
    let g = synthetic::object_scene(1_000_000, 3, 7);
    let mut bytes = Vec::new();
    let t = Instant::now();
    write_ply(&g, &mut bytes).expect("write");
    let write_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut reads = Vec::new();
    for _ in 0..reps.min(5) {
        let t = Instant::now();
        let back = read_scene_bytes(&bytes, Some("ply"), &Limits::default()).expect("read");
        reads.push(t.elapsed());
        assert_eq!(back.len(), g.len());
    }
    println!(
        "\nINRIA PLY, 1M Gaussians SH3 ({} MB): write {write_ms:.0} ms, read {:.0} ms (median)",
        bytes.len() >> 20,
        median(reads)
    );
}
