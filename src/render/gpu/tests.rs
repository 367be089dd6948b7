//! Parity of the GPU path with the CPU reference, on whatever adapter wgpu finds (Mesa's
//! lavapipe on the CI machines, installed by `scripts/setup.sh`): the integer kernels (scan,
//! sort) exactly, renders to ≤ 1/255 on ≥ 99.9 % of the pixels.

use super::*;
use crate::render::render;
use crate::render::{RenderOptions, TILE};
use crate::scene::{Camera, Gaussians};
use glam::{Mat3, Vec3};
use std::sync::Arc;

fn gpu() -> Arc<GpuRenderer> {
    shared(AdapterChoice::AllowSoftware).unwrap_or_else(|e| {
        panic!("no wgpu adapter ({e}); `bash scripts/setup.sh` installs Mesa's lavapipe")
    })
}

struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 32) as u32
    }
    fn range(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * (self.next() as f32 / u32::MAX as f32)
    }
}

fn upload(r: &GpuRenderer, v: &[u32]) -> wgpu::Buffer {
    let b = r.storage("test", v.len() as u64 * 4).unwrap();
    r.queue.write_buffer(&b, 0, words(v));
    b
}

fn download(
    r: &GpuRenderer,
    encoder: wgpu::CommandEncoder,
    b: &wgpu::Buffer,
    n: usize,
) -> Vec<u32> {
    let bytes = r.read(encoder, &[(b, 0, n as u64 * 4)]).unwrap();
    bytemuck::cast_slice(&bytes).to_vec()
}

#[test]
fn scan_is_an_exact_exclusive_prefix_sum_over_several_levels() {
    let r = gpu();
    let mut rng = Lcg(7);
    // 100 000 values: 391 blocks, whose sums need a second and a third level.
    let v: Vec<u32> = (0..100_000).map(|_| rng.next() % 50).collect();
    let buf = upload(&r, &v);
    let mut encoder = r.device.create_command_encoder(&Default::default());
    let mut keep = Vec::new();
    r.scan(&mut encoder, &buf, v.len() as u32, &mut keep)
        .unwrap();
    let got = download(&r, encoder, &buf, v.len());
    let mut acc = 0u32;
    for (i, (&x, &g)) in v.iter().zip(&got).enumerate() {
        assert_eq!(g, acc, "element {i}");
        acc += x;
    }
}

#[test]
fn sort_orders_pairs_as_a_stable_sort_by_tile_then_depth() {
    let r = gpu();
    let mut rng = Lcg(11);
    let n = 70_000usize;
    // Few distinct depths, so that ties are common and stability shows.
    let hi: Vec<u32> = (0..n).map(|_| rng.next() % 1000).collect();
    let lo: Vec<u32> = (0..n).map(|_| (rng.range(3.0, 3.01)).to_bits()).collect();
    let val: Vec<u32> = (0..n as u32).collect();
    let pairs = sort::Pairs {
        hi: upload(&r, &hi),
        lo: upload(&r, &lo),
        val: upload(&r, &val),
    };
    let mut encoder = r.device.create_command_encoder(&Default::default());
    let mut keep = Vec::new();
    let sorted = r
        .pipes
        .sort
        .sort(&r, &mut encoder, pairs, n as u32, 10, &mut keep)
        .unwrap();
    r.queue.submit([encoder.finish()]);
    let read = |b: &wgpu::Buffer| {
        let e = r.device.create_command_encoder(&Default::default());
        download(&r, e, b, n)
    };
    let (ghi, glo, gval) = (read(&sorted.hi), read(&sorted.lo), read(&sorted.val));
    let mut want: Vec<u32> = val.clone();
    want.sort_by_key(|&i| (hi[i as usize], lo[i as usize]));
    assert_eq!(gval, want);
    for k in 0..n {
        let i = want[k] as usize;
        assert_eq!((ghi[k], glo[k]), (hi[i], lo[i]));
    }
}

fn camera(w: u32, h: u32, f: f32) -> Camera {
    Camera::from_pose(
        "front",
        w,
        h,
        f,
        f,
        w as f32 / 2.0,
        h as f32 / 2.0,
        Mat3::IDENTITY,
        Vec3::ZERO,
    )
}

/// `n` random anisotropic Gaussians in front of a camera at the origin, in the box
/// `[−s, s]² × [2, 6]`.
fn scene(seed: u64, n: usize, sh_degree: u8, s: f32, log_scale: (f32, f32)) -> Gaussians {
    let mut rng = Lcg(seed);
    let mut g = Gaussians::with_capacity(n, sh_degree);
    for _ in 0..n {
        g.means
            .push([rng.range(-s, s), rng.range(-s, s), rng.range(2.0, 6.0)]);
        g.log_scales.push([
            rng.range(log_scale.0, log_scale.1),
            rng.range(log_scale.0, log_scale.1),
            rng.range(log_scale.0, log_scale.1),
        ]);
        g.rotations.push([
            rng.range(0.3, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        ]);
        g.opacity_logits.push(rng.range(-3.0, 4.0));
        g.sh_dc.push([
            rng.range(-1.5, 1.5),
            rng.range(-1.5, 1.5),
            rng.range(-1.5, 1.5),
        ]);
        for _ in 0..g.rest_len() {
            g.sh_rest.push(rng.range(-0.4, 0.4));
        }
    }
    g
}

/// Renders on both paths; asserts ≤ 1/255 on ≥ 99.9 % of the values of the image and of the
/// final transmittance; returns the largest difference.
fn assert_parity(g: &Gaussians, cam: &Camera, opts: &RenderOptions) -> f32 {
    let cpu = render(g, cam, opts).unwrap();
    let renderer = gpu();
    let gpu = renderer.render(g, cam, opts).unwrap();
    assert_eq!((gpu.width, gpu.height), (cpu.width, cpu.height));
    // Binning is the reference's: the exact tiles each footprint touches (rounding may move
    // a tile at the very edge of a footprint, where α is below 1/255 anyway).
    let (a, b) = (cpu.stats.tile_entries, gpu.tile_entries);
    assert!(
        a.abs_diff(b) * 1000 <= a.max(1),
        "tile entries: CPU {a}, GPU {b}"
    );
    let tol = 1.0 / 255.0;
    let mut worst = 0f32;
    let mut over = 0usize;
    for (a, b) in cpu.image.iter().zip(&gpu.image) {
        for c in 0..3 {
            let d = (a[c] - b[c]).abs();
            worst = worst.max(d);
            over += usize::from(!(d <= tol));
        }
    }
    // The reference keeps T tile-major.
    let tiles_x = (cam.width as usize).div_ceil(TILE);
    for (p, &t) in renderer.read_final_t(&gpu).unwrap().iter().enumerate() {
        let (x, y) = (p % cam.width as usize, p / cam.width as usize);
        let k = ((y / TILE) * tiles_x + x / TILE) * TILE * TILE + (y % TILE) * TILE + x % TILE;
        let d = (cpu.state.final_t[k] - t).abs();
        worst = worst.max(d);
        over += usize::from(!(d <= tol));
    }
    let values = cpu.image.len() * 4;
    assert!(
        (over as f64) <= values as f64 * 1e-3,
        "{over} of {values} values differ by more than 1/255 (largest {worst})"
    );
    worst
}

#[test]
fn renders_match_the_cpu_reference_at_every_sh_degree() {
    for deg in 0..=3u8 {
        let g = scene(100 + u64::from(deg), 3000, deg, 1.5, (-4.0, -2.0));
        // Not a multiple of 16: partial tiles on the right and bottom edges.
        let cam = camera(120, 88, 100.0);
        let worst = assert_parity(&g, &cam, &RenderOptions::default());
        assert!(worst < 1e-3, "SH degree {deg}: largest difference {worst}");
    }
}

#[test]
fn background_colour_overrides_and_a_lower_sh_degree_match_the_reference() {
    let g = scene(5, 2000, 3, 1.5, (-4.0, -2.0));
    let cam = camera(96, 96, 90.0);
    let colors: Arc<[[f32; 3]]> = (0..g.len())
        .map(|i| [(i % 7) as f32 / 7.0, 0.5, 1.2 - (i % 3) as f32 * 0.4])
        .collect();
    for opts in [
        RenderOptions {
            background: [0.2, 0.5, 1.0],
            ..Default::default()
        },
        RenderOptions {
            colors: Some(colors),
            background: [1.0; 3],
            ..Default::default()
        },
        RenderOptions {
            sh_degree: Some(1),
            ..Default::default()
        },
    ] {
        let worst = assert_parity(&g, &cam, &opts);
        assert!(worst < 1e-3, "{opts:?}: largest difference {worst}");
    }
}

#[test]
fn edge_cases_match_the_reference() {
    let cam = camera(80, 64, 70.0);
    // Behind the camera and behind the near plane: culled on both paths.
    let mut behind = scene(1, 300, 0, 1.0, (-3.0, -2.0));
    for (k, m) in behind.means.iter_mut().enumerate() {
        m[2] = if k % 2 == 0 { -m[2] } else { 0.005 };
    }
    // Huge footprints covering the whole screen, and sub-pixel ones.
    let huge = scene(2, 20, 0, 0.5, (0.5, 1.5));
    let tiny = scene(3, 2000, 0, 1.0, (-9.0, -7.0));
    // One corner only: most tiles are empty.
    let mut corner = scene(4, 400, 0, 0.2, (-4.0, -3.0));
    for m in &mut corner.means {
        m[0] -= 1.2;
        m[1] -= 1.0;
    }
    // 3 000 Gaussians over a few tiles: far more than one 256-splat batch per tile, and pixels
    // that saturate (T below 1e-4) long before the list ends.
    let dense = scene(6, 3000, 0, 0.08, (-3.5, -2.5));
    for (name, g) in [
        ("behind", behind),
        ("huge", huge),
        ("tiny", tiny),
        ("corner", corner),
        ("dense", dense),
    ] {
        let worst = assert_parity(&g, &cam, &RenderOptions::default());
        assert!(worst < 2e-3, "{name}: largest difference {worst}");
    }
    // An empty scene is the background.
    let empty = Gaussians::with_capacity(0, 0);
    let opts = RenderOptions {
        background: [0.25, 0.5, 0.75],
        ..Default::default()
    };
    let out = gpu().render(&empty, &cam, &opts).unwrap();
    assert!(out.image.iter().all(|p| *p == [0.25, 0.5, 0.75]));
    let final_t = gpu().read_final_t(&out).unwrap();
    assert_eq!(final_t.len(), 80 * 64);
    assert!(final_t.iter().all(|&t| t == 1.0));
}

#[test]
fn bad_input_is_the_references_typed_error() {
    let g = scene(1, 10, 0, 1.0, (-3.0, -2.0));
    let mut cam = camera(32, 32, 30.0);
    cam.fx = -1.0;
    match gpu().render(&g, &cam, &RenderOptions::default()) {
        Err(GpuError::Render(RenderError::BadCamera { .. })) => {}
        other => panic!("expected a bad-camera error, got {other:?}"),
    }
}

#[test]
fn the_shared_scenes_render_as_on_the_cpu() {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
    // donut (SH 0, dense), plant (.splat, 114 k Gaussians), udon (SH 3, through its cameras).
    for file in [
        "donut/fused.ply",
        "plant/plant.splat",
        "udon/point_cloud.ply",
    ] {
        let path = dir.join(file);
        if !path.is_file() {
            eprintln!(
                "SKIPPED: {} is missing (the shared data folder)",
                path.display()
            );
            continue;
        }
        let g = crate::scene::read_scene(&path, &crate::scene::Limits::default()).unwrap();
        let cams = if file.starts_with("udon") {
            let cams = crate::scene::camera::read_cameras(&dir.join("udon/cameras.json")).unwrap();
            crate::scene::camera::resize_all(cams, Some(160), None)
                .into_iter()
                .take(3)
                .collect()
        } else {
            let orbit = crate::scene::orbit::OrbitOptions {
                count: 3,
                width: 128,
                height: 128,
                ..Default::default()
            };
            crate::scene::orbit::orbit_cameras(&g, &orbit).unwrap()
        };
        for cam in &cams {
            assert_parity(&g, cam, &RenderOptions::default());
        }
    }
}

/// Largest |GPU − CPU| of each gradient kind, relative to the largest |CPU| of that kind.
fn gradient_gaps(
    g: &Gaussians,
    cam: &Camera,
    opts: &RenderOptions,
    seed: u64,
) -> Vec<(&'static str, f32)> {
    let cpu_fwd = render(g, cam, opts).unwrap();
    let r = gpu();
    let gpu_fwd = r.render(g, cam, opts).unwrap();
    let mut rng = Lcg(seed);
    let d_image: Vec<[f32; 3]> = (0..cpu_fwd.image.len())
        .map(|_| {
            [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            ]
        })
        .collect();
    let a = crate::render::backward(g, &cpu_fwd, &d_image).unwrap();
    let b = r.backward(g, &gpu_fwd, &d_image).unwrap();
    let flat3 = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<_>>();
    let flat4 = |v: &[[f32; 4]]| v.iter().flatten().copied().collect::<Vec<_>>();
    let flat2 = |v: &[[f32; 2]]| v.iter().flatten().copied().collect::<Vec<_>>();
    let kinds: Vec<(&str, Vec<f32>, Vec<f32>)> = vec![
        ("means", flat3(&a.params.means), flat3(&b.params.means)),
        (
            "log_scales",
            flat3(&a.params.log_scales),
            flat3(&b.params.log_scales),
        ),
        (
            "rotations",
            flat4(&a.params.rotations),
            flat4(&b.params.rotations),
        ),
        (
            "opacity_logits",
            a.params.opacity_logits.clone(),
            b.params.opacity_logits.clone(),
        ),
        ("sh_dc", flat3(&a.params.sh_dc), flat3(&b.params.sh_dc)),
        (
            "sh_rest",
            a.params.sh_rest.clone(),
            b.params.sh_rest.clone(),
        ),
        ("colors", flat3(&a.colors), flat3(&b.colors)),
        (
            "blend_weights",
            a.blend_weights.clone(),
            b.blend_weights.clone(),
        ),
        ("screen_xy", flat2(&a.screen_xy), flat2(&b.screen_xy)),
    ];
    kinds
        .into_iter()
        .map(|(name, x, y)| {
            assert_eq!(x.len(), y.len(), "{name}");
            let scale = x.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
            let gap = x
                .iter()
                .zip(&y)
                .fold(0f32, |m, (p, q)| m.max((p - q).abs()));
            (name, gap / scale)
        })
        .collect()
}

#[test]
fn gradients_match_the_cpu_reference() {
    let colors: Arc<[[f32; 3]]> = (0..1500)
        .map(|i| [(i % 5) as f32 / 5.0, 0.3, 0.9])
        .collect();
    let cases = [
        (
            "SH0",
            scene(21, 1500, 0, 1.2, (-4.0, -2.5)),
            RenderOptions::default(),
        ),
        (
            "SH3 on a background",
            scene(22, 1500, 3, 1.2, (-4.0, -2.5)),
            RenderOptions {
                background: [0.3, 0.6, 0.9],
                ..Default::default()
            },
        ),
        (
            "colour override",
            scene(23, 1500, 1, 1.2, (-4.0, -2.5)),
            RenderOptions {
                colors: Some(colors),
                ..Default::default()
            },
        ),
        // Dense: many batches per tile, saturated pixels; wide: clamped Jacobians at the edges.
        (
            "dense",
            scene(24, 3000, 0, 0.1, (-3.5, -2.5)),
            RenderOptions::default(),
        ),
        (
            "wide",
            scene(25, 800, 2, 4.0, (-3.0, -1.5)),
            RenderOptions::default(),
        ),
    ];
    let cam = camera(72, 56, 60.0);
    for (name, g, opts) in cases {
        for (kind, gap) in gradient_gaps(&g, &cam, &opts, 9) {
            eprintln!("{name}: {kind} {gap:.2e}");
            assert!(
                gap < 1e-3,
                "{name}: {kind} differs by {gap:.2e} of its largest value"
            );
        }
    }
}

#[test]
fn the_gpu_backward_is_deterministic() {
    let g = scene(31, 2000, 3, 1.0, (-4.0, -2.5));
    let cam = camera(64, 64, 60.0);
    let r = gpu();
    let d_image = vec![[0.01f32, -0.02, 0.03]; 64 * 64];
    let run = || {
        let f = r.render(&g, &cam, &RenderOptions::default()).unwrap();
        r.backward(&g, &f, &d_image).unwrap()
    };
    let (a, b) = (run(), run());
    assert_eq!(a.params.means, b.params.means);
    assert_eq!(a.params.sh_rest, b.params.sh_rest);
    assert_eq!(a.blend_weights, b.blend_weights);
    // A gradient of the wrong size is the reference's typed error.
    let f = r.render(&g, &cam, &RenderOptions::default()).unwrap();
    match r.backward(&g, &f, &d_image[1..]) {
        Err(GpuError::Render(RenderError::GradientSize { .. })) => {}
        other => panic!(
            "expected a gradient-size error, got {:?}",
            other.map(|_| ())
        ),
    }
}

#[test]
fn one_upload_renders_every_view_and_back_propagates_as_fresh_uploads_do() {
    let g = scene(37, 1500, 3, 1.0, (-4.0, -2.5));
    let r = gpu();
    let opts = RenderOptions::default();
    let up = r.upload(&g, &opts).unwrap();
    assert_eq!(up.len(), g.len());
    let d_image = vec![[0.01f32, -0.02, 0.03]; 48 * 40];
    for (w, h, f) in [(48, 40, 50.0), (48, 40, 80.0), (64, 64, 60.0)] {
        let cam = camera(w, h, f);
        let fresh = r.render(&g, &cam, &opts).unwrap();
        let shared = r.render_uploaded(&up, &cam, &opts).unwrap();
        assert_eq!(shared.image, fresh.image, "{w}×{h}, f {f}");
        assert_eq!(
            r.read_final_t(&shared).unwrap(),
            r.read_final_t(&fresh).unwrap()
        );
        // Kept on the device, the same render: read back, as a burn tensor, back-propagated.
        let resident = r.render_resident(&up, &cam, &opts).unwrap();
        assert!(resident.image.is_empty());
        assert_eq!(r.read_image(&resident).unwrap(), fresh.image);
        if (w, h) == (48, 40) {
            let a = r.backward(&g, &fresh, &d_image).unwrap();
            let b = r.backward(&g, &shared, &d_image).unwrap();
            assert_eq!(a.params.means, b.params.means);
            assert_eq!(a.params.sh_rest, b.params.sh_rest);
            assert_eq!(a.blend_weights, b.blend_weights);
        }
    }
    // Another SH degree is a render option: the same upload serves it.
    let sh1 = RenderOptions {
        sh_degree: Some(1),
        ..RenderOptions::default()
    };
    let cam = camera(48, 40, 50.0);
    assert_eq!(
        r.render_uploaded(&up, &cam, &sh1).unwrap().image,
        r.render(&g, &cam, &sh1).unwrap().image
    );
    // The colour override is the upload's: a render that asks for one of an upload without
    // (or the reverse) is a typed error, not a render of other colours.
    let colours = RenderOptions {
        colors: Some(vec![[0.2, 0.5, 0.9]; g.len()].into()),
        ..RenderOptions::default()
    };
    for (upload, render_with) in [(&opts, &colours), (&colours, &opts)] {
        let up = r.upload(&g, upload).unwrap();
        match r.render_uploaded(&up, &cam, render_with) {
            Err(GpuError::Render(RenderError::BadScene(why))) => {
                assert!(why.contains("colour override"), "{why}")
            }
            other => panic!("expected a scene error, got {:?}", other.map(|_| ())),
        }
    }
    let up = r.upload(&g, &colours).unwrap();
    assert_eq!(
        r.render_uploaded(&up, &cam, &colours).unwrap().image,
        r.render(&g, &cam, &colours).unwrap().image
    );
}

#[test]
fn chunk_slices_start_aligned_fit_one_binding_and_cover_every_gaussian() {
    for (align, floats, limit) in [
        (256u64, 59u64, 1u64 << 27),
        (16, 62, 4096),
        (4, 14, 1000),
        (64, 17, 300),
    ] {
        let bytes = floats * 4;
        let per = chunk::most_per_chunk(limit, align, bytes) as u32;
        assert!(per > 0);
        let n = per * 5 + 7;
        let mut first = 0u32;
        while first < n {
            let count = per.min(n - first);
            let s = chunk::slice(first, count, bytes, align);
            assert_eq!(s.offset % align, 0);
            assert!(s.size <= limit, "{s:?} over {limit}");
            assert_eq!(s.size % 4, 0);
            assert_eq!(s.offset + u64::from(s.at) * 4, u64::from(first) * bytes);
            assert_eq!(s.offset + s.size, u64::from(first + count) * bytes);
            first += count;
        }
    }
}

/// Every float of `a` and `b`, bit for bit.
fn assert_same_bits(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}");
    for (k, (x, y)) in a.iter().zip(b).enumerate() {
        assert_eq!(x.to_bits(), y.to_bits(), "{what}[{k}]: {x} against {y}");
    }
}

#[test]
fn chunked_projection_renders_and_back_propagates_bit_for_bit_as_one_dispatch() {
    let whole = gpu();
    let chunked = GpuRenderer::new(AdapterChoice::AllowSoftware)
        .unwrap()
        .with_gaussians_per_dispatch(333);
    let limits = chunked.device.limits();
    eprintln!(
        "storage binding ≤ {} B from offsets aligned to {} B; buffers ≤ {} B",
        limits.max_storage_buffer_binding_size,
        limits.min_storage_buffer_offset_alignment,
        limits.max_buffer_size
    );
    // 333, 333, 333 and 1 Gaussians a dispatch: chunks that start off every alignment.
    assert_eq!(chunked.per_chunk(59).unwrap(), 333);
    let colors: Arc<[[f32; 3]]> = (0..1000)
        .map(|i| [(i % 5) as f32 / 5.0, 0.3, 0.9])
        .collect();
    let cases = [
        (
            "SH3",
            scene(41, 1000, 3, 1.2, (-4.0, -2.5)),
            RenderOptions::default(),
        ),
        (
            "SH0",
            scene(42, 1000, 0, 1.2, (-4.0, -2.5)),
            RenderOptions::default(),
        ),
        // Parameters 3 floats a Gaussian longer than their gradients: two slicings.
        (
            "colour override",
            scene(43, 1000, 1, 1.2, (-4.0, -2.5)),
            RenderOptions {
                colors: Some(colors),
                ..Default::default()
            },
        ),
    ];
    let cam = camera(72, 56, 60.0);
    let mut rng = Lcg(17);
    let d_image: Vec<[f32; 3]> = (0..72 * 56)
        .map(|_| {
            [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            ]
        })
        .collect();
    for (name, g, opts) in cases {
        let a = whole.render(&g, &cam, &opts).unwrap();
        let b = chunked.render(&g, &cam, &opts).unwrap();
        assert!(a.tile_entries > 1000, "{name}: {} entries", a.tile_entries);
        assert_eq!(a.tile_entries, b.tile_entries, "{name}");
        let flat3 = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<_>>();
        let flat4 = |v: &[[f32; 4]]| v.iter().flatten().copied().collect::<Vec<_>>();
        let flat2 = |v: &[[f32; 2]]| v.iter().flatten().copied().collect::<Vec<_>>();
        assert_same_bits(name, &flat3(&a.image), &flat3(&b.image));
        assert_same_bits(
            name,
            &whole.read_final_t(&a).unwrap(),
            &chunked.read_final_t(&b).unwrap(),
        );
        let ga = whole.backward(&g, &a, &d_image).unwrap();
        let gb = chunked.backward(&g, &b, &d_image).unwrap();
        let (pa, pb) = (&ga.params, &gb.params);
        assert!(pa.means.iter().flatten().any(|v| *v != 0.0), "{name}");
        for (kind, x, y) in [
            ("means", flat3(&pa.means), flat3(&pb.means)),
            ("log_scales", flat3(&pa.log_scales), flat3(&pb.log_scales)),
            ("rotations", flat4(&pa.rotations), flat4(&pb.rotations)),
            (
                "opacity_logits",
                pa.opacity_logits.clone(),
                pb.opacity_logits.clone(),
            ),
            ("sh_dc", flat3(&pa.sh_dc), flat3(&pb.sh_dc)),
            ("sh_rest", pa.sh_rest.clone(), pb.sh_rest.clone()),
            ("colors", flat3(&ga.colors), flat3(&gb.colors)),
            (
                "blend_weights",
                ga.blend_weights.clone(),
                gb.blend_weights.clone(),
            ),
            ("screen_xy", flat2(&ga.screen_xy), flat2(&gb.screen_xy)),
        ] {
            assert_same_bits(&format!("{name}: {kind}"), &x, &y);
        }
    }
}

#[test]
fn a_render_becomes_a_burn_tensor_on_the_device_as_it_reads_back() {
    let g = scene(41, 800, 1, 1.0, (-4.0, -2.5));
    let r = gpu();
    let cam = camera(40, 24, 40.0);
    let f = r.render(&g, &cam, &RenderOptions::default()).unwrap();
    let t = r.image_tensor(&f).unwrap();
    assert_eq!(t.dims(), [1, 3, 24, 40]);
    let got: Vec<f32> = t.try_into_vec_as::<f32>().unwrap();
    let n = 24 * 40;
    for (p, px) in f.image.iter().enumerate() {
        for c in 0..3 {
            assert_eq!(got[c * n + p], px[c], "pixel {p}, channel {c}");
        }
    }
}

#[test]
fn a_burn_gradient_back_propagates_on_the_device_as_from_the_host() {
    use burn::tensor::{Tensor, TensorData};
    let g = scene(43, 900, 2, 1.0, (-4.0, -2.5));
    let r = gpu();
    let (w, h) = (40usize, 24usize);
    let cam = camera(w as u32, h as u32, 40.0);
    let f = r.render(&g, &cam, &RenderOptions::default()).unwrap();
    let d_host: Vec<[f32; 3]> = (0..w * h)
        .map(|i| [(i % 7) as f32 - 3.0, 0.5, (i % 3) as f32 * 0.25])
        .collect();
    // The same gradient as a burn tensor [1, 3, H, W] on the renderer's device.
    let planar: Vec<f32> = (0..3)
        .flat_map(|c| d_host.iter().map(move |p| p[c]))
        .collect();
    let device = r.burn_device().unwrap();
    let d = Tensor::<4>::from_data(TensorData::new(planar, [1, 3, h, w]), &device);
    let a = r.backward(&g, &f, &d_host).unwrap();
    let b = r.backward_tensor(&g, &f, d).unwrap();
    assert_eq!(a.params.means, b.params.means);
    assert_eq!(a.params.sh_dc, b.params.sh_dc);
    assert_eq!(a.params.sh_rest, b.params.sh_rest);
    assert_eq!(a.blend_weights, b.blend_weights);
    // A tensor of another size is the typed error of a wrong gradient.
    let small = Tensor::<4>::zeros([1, 3, h, w - 1], &device);
    assert!(matches!(
        r.backward_tensor(&g, &f, small),
        Err(GpuError::Render(RenderError::GradientSize { .. }))
    ));
}

#[test]
fn a_steps_gradients_summed_on_the_device_are_the_sum_of_each_views() {
    use burn::tensor::{Tensor, TensorData};
    // Three views of a scene with SH (every parameter's gradient), one of them of a copy with
    // some Gaussians transparent (a removal in the EOT term), split over chunks of 300.
    let g = scene(44, 900, 2, 1.0, (-4.0, -2.5));
    let mut masked = g.clone();
    for o in masked.opacity_logits.iter_mut().step_by(3) {
        *o = -40.0;
    }
    let r = gpu();
    let chunked = GpuRenderer::new(AdapterChoice::AllowSoftware)
        .unwrap()
        .with_gaussians_per_dispatch(300);
    let device = r.burn_device().unwrap();
    let opts = RenderOptions::default();
    let views = [
        (&g, camera(40, 24, 40.0)),
        (&masked, camera(40, 24, 40.0)),
        (&g, camera(33, 29, 55.0)),
    ];
    for renderer in [&*r, &chunked] {
        let device = renderer.burn_device().unwrap_or_else(|_| device.clone());
        let mut passes = Vec::new();
        let mut sum = g.cast(|_| 0.0f32);
        for (k, (scene, cam)) in views.iter().enumerate() {
            let f = renderer.render(scene, cam, &opts).unwrap();
            let n = (cam.width * cam.height) as usize;
            let planar: Vec<f32> = (0..3 * n)
                .map(|i| ((i * (k + 3)) % 11) as f32 * 0.1 - 0.5)
                .collect();
            let shape = [1, 3, cam.height as usize, cam.width as usize];
            let d = Tensor::<4>::from_data(TensorData::new(planar, shape), &device);
            let one = renderer
                .backward_tensor(scene, &f, d.clone())
                .unwrap()
                .params;
            for (s, v) in sum.means.iter_mut().zip(&one.means) {
                (0..3).for_each(|c| s[c] += v[c]);
            }
            for (s, v) in sum.sh_dc.iter_mut().zip(&one.sh_dc) {
                (0..3).for_each(|c| s[c] += v[c]);
            }
            for (s, v) in sum.sh_rest.iter_mut().zip(&one.sh_rest) {
                *s += v;
            }
            for (s, v) in sum.rotations.iter_mut().zip(&one.rotations) {
                (0..4).for_each(|c| s[c] += v[c]);
            }
            for (s, v) in sum.log_scales.iter_mut().zip(&one.log_scales) {
                (0..3).for_each(|c| s[c] += v[c]);
            }
            for (s, v) in sum.opacity_logits.iter_mut().zip(&one.opacity_logits) {
                *s += v;
            }
            passes.push((f, d));
        }
        let refs: Vec<(&GpuRendered, Tensor<4>)> =
            passes.iter().map(|(f, d)| (f, d.clone())).collect();
        let summed = renderer.backward_tensors_summed(&g, &refs).unwrap();
        // The same additions in the same order; a compiler may fuse one into a multiply-add,
        // so allow rounding of the largest value.
        let (a, b) = (sum.flat(), summed.flat());
        let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!(
                (x - y).abs() <= 1e-6 * scale,
                "value {i}: {x} vs {y} (scale {scale})"
            );
        }
        // No passes: zero; a render of another shape: the typed error.
        let none = renderer.backward_tensors_summed(&g, &[]).unwrap();
        assert!(none.flat().iter().all(|&v| v == 0.0));
        let other = scene(45, 10, 2, 1.0, (-4.0, -2.5));
        assert!(matches!(
            renderer.backward_tensors_summed(&other, &refs),
            Err(GpuError::Render(RenderError::BadScene(_)))
        ));
    }
}
