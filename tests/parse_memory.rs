//! The service reserves what reading an upload costs before it reads it
//! (`scene::cost::Declared::read_bytes`, from the header alone). This checks that reservation
//! against what the readers really allocate, with a counting allocator, for every format: if a
//! reader came to allocate more than its reservation, the parse budget would no longer bound
//! the server's memory.
//!
//! The allocator counts every thread of the process: this binary holds only these tests, and
//! they run one at a time ([`SERIAL`]).

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};

use splatmark::scene::cost::{PROBE_BYTES, declared};
use splatmark::scene::synthetic::{Rng, object_scene};
use splatmark::scene::{Limits, read_scene_bytes, write_ply};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(now, Ordering::SeqCst);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::SeqCst)
                    + (new_size - layout.size());
                // A moving realloc holds both blocks for a moment.
                PEAK.fetch_max(now + layout.size(), Ordering::SeqCst);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::SeqCst);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Bytes allocated at the peak of `f`, above what was live when it started.
fn peak_of<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let base = LIVE.load(Ordering::SeqCst);
    PEAK.store(base, Ordering::SeqCst);
    let r = f();
    (r, PEAK.load(Ordering::SeqCst) - base)
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(raw).unwrap();
    e.finish().unwrap()
}

/// A file of every format the service takes, with `n` Gaussians each.
fn files(n: usize) -> Vec<(&'static str, Vec<u8>)> {
    let mut rng = Rng::new(3);
    let mut out = Vec::new();
    for (name, degree) in [("ply, SH degree 3", 3u8), ("ply, SH degree 0", 0)] {
        let mut ply = Vec::new();
        write_ply(&object_scene(n, degree, 1), &mut ply).unwrap();
        out.push((name, ply));
    }
    let props = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let mut ascii = format!("ply\nformat ascii 1.0\nelement vertex {n}\n");
    for p in props {
        ascii += &format!("property float {p}\n");
    }
    ascii += "end_header\n";
    for i in 0..n {
        let t = i as f32 / n as f32;
        ascii += &format!("{t} {} 0.5 0.1 0.2 0.3 1.5 -4 -4.5 -5 1 0 0 0\n", 1.0 - t);
    }
    out.push(("ascii ply", ascii.into_bytes()));
    // SuperSplat compressed PLY: a chunk per 256 points, SH degree 1.
    let chunks = n.div_ceil(256);
    let mut h = format!("ply\nformat binary_little_endian 1.0\nelement chunk {chunks}\n");
    for p in splatmark::scene::compressed_ply::CHUNK_REQUIRED {
        h += &format!("property float {p}\n");
    }
    h += &format!("element vertex {n}\n");
    for p in splatmark::scene::compressed_ply::PACKED {
        h += &format!("property uint {p}\n");
    }
    h += &format!("element sh {n}\n");
    for k in 0..9 {
        h += &format!("property uchar f_rest_{k}\n");
    }
    h += "end_header\n";
    let mut cply = h.into_bytes();
    for _ in 0..chunks {
        for v in [
            -1.0f32, -1.0, -1.0, 1.0, 1.0, 1.0, -5.0, -5.0, -5.0, -3.0, -3.0, -3.0,
        ] {
            cply.extend_from_slice(&v.to_le_bytes());
        }
    }
    for _ in 0..4 * n {
        cply.extend_from_slice(&(rng.next_u64() as u32).to_le_bytes());
    }
    cply.extend((0..9 * n).map(|_| rng.next_u64() as u8));
    out.push(("compressed ply, SH degree 1", cply));
    let mut splat = Vec::with_capacity(32 * n);
    for i in 0..n {
        for v in [i as f32 * 1e-4, -0.2, 0.3, 0.02, 0.03, 0.04] {
            splat.extend_from_slice(&v.to_le_bytes());
        }
        splat.extend_from_slice(&[200, 100, 50, 180, 255, 128, 128, 128]);
    }
    out.push(("splat", splat));
    for (name, version, degree) in [
        ("spz v2 (gzip), SH degree 3", 2u32, 3u8),
        ("spz v3 (gzip), SH degree 0", 3, 0),
    ] {
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&version.to_le_bytes());
        raw.extend_from_slice(&(n as u32).to_le_bytes());
        raw.extend_from_slice(&[degree, 12, 0, 0]);
        let rot = if version >= 3 { 4 } else { 3 };
        let sh = splatmark::scene::rest_len_for(degree);
        for (k, per_point) in [9, 1, 3, 3, rot, sh].into_iter().enumerate() {
            // Version 3's rotations pack "smallest three" in 4 bytes: all zero is the identity.
            let zero = k == 4 && version >= 3;
            raw.extend((0..n * per_point).map(|_| if zero { 0 } else { rng.next_u64() as u8 }));
        }
        out.push((name, gzip(&raw)));
    }
    out
}

#[test]
fn reading_a_scene_allocates_no_more_than_its_header_reserves() {
    let _one_at_a_time = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    for n in [1_000, 60_000] {
        for (name, bytes) in files(n) {
            let hint = name.split([' ', ',']).next();
            let d = declared(
                &bytes[..bytes.len().min(PROBE_BYTES)],
                bytes.len() as u64,
                hint,
            )
            .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(d.count, n as u64, "{name}");
            let reserved = d.read_bytes(bytes.len() as u64);
            let (g, peak) = peak_of(|| read_scene_bytes(&bytes, hint, &Limits::default()));
            let g = g.unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(g.len(), n, "{name}");
            drop(g);
            // The file's bytes are held by the caller while it is read.
            let used = bytes.len() + peak;
            eprintln!(
                "{name}, {n} Gaussians: file {} B, read peak {peak} B, reserved {reserved} B",
                bytes.len()
            );
            assert!(
                used as u64 <= reserved,
                "{name}, {n}: the read took {used} B, more than the {reserved} B reserved"
            );
            // And for a scene of some size the reservation does not waste the budget: at most
            // twice what is used.
            assert!(
                n < 10_000 || reserved <= 2 * used as u64,
                "{name}, {n}: {reserved} B reserved for {used} B used"
            );
        }
    }
}

#[test]
fn reading_cameras_allocates_no_more_than_their_reservation() {
    let _one_at_a_time = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let n = 2_000;
    let mut inria = Vec::new();
    let mut frames = Vec::new();
    for i in 0..n {
        let t = i as f64 * 0.01;
        inria.push(serde_json::json!({
            "id": i, "img_name": format!("frame{i:05}"), "width": 1888, "height": 1061,
            "position": [t.cos() * 3.0, 0.5, t.sin() * 3.0],
            "rotation": [[t.cos(), 0.0, -t.sin()], [0.0, 1.0, 0.0], [t.sin(), 0.0, t.cos()]],
            "fx": 2378.123456789, "fy": 2378.987654321
        }));
        frames.push(serde_json::json!({
            "file_path": format!("./train/r_{i}"),
            "transform_matrix": [[t.cos(), 0.0, t.sin(), 3.0 * t.sin()], [0.0, 1.0, 0.0, 0.5],
                                 [-t.sin(), 0.0, t.cos(), 3.0 * t.cos()], [0.0, 0.0, 0.0, 1.0]]
        }));
    }
    let transforms = serde_json::json!({
        "camera_angle_x": 0.6911112070083618, "w": 800, "h": 800, "frames": frames
    });
    // Hostile ones: JSON whose values are much larger in memory than in text.
    let zeros = format!("[{}0]", "0,".repeat(500_000)).into_bytes();
    let empties = format!("{{\"frames\":[{}[]]}}", "[],".repeat(300_000)).into_bytes();
    let objects = format!("{{\"frames\":[{}{{}}]}}", "{},".repeat(300_000)).into_bytes();
    // The smallest text per camera: a bare matrix and a one-letter path.
    let bare = format!(
        "{{\"camera_angle_x\":0.7,\"w\":64,\"h\":64,\"frames\":[{}]}}",
        vec![
            r#"{"file_path":"a","transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]]}"#;
            n
        ]
        .join(",")
    )
    .into_bytes();
    for (label, bytes, valid) in [
        ("transforms.json", bare, true),
        ("cameras.json", serde_json::to_vec(&inria).unwrap(), true),
        (
            "transforms.json",
            serde_json::to_vec_pretty(&transforms).unwrap(),
            true,
        ),
        ("cameras.json", zeros, false),
        ("transforms.json", empties, false),
        ("transforms.json", objects, false),
    ] {
        let reserved = splatmark::scene::cost::cameras_read_bytes(bytes.len() as u64);
        let (r, peak) = peak_of(|| splatmark::scene::camera::read_cameras_bytes(&bytes, label));
        if valid {
            let (_, cams) = r.unwrap_or_else(|e| panic!("{label}: {e}"));
            assert_eq!(cams.len(), n, "{label}");
        } else {
            assert!(r.is_err(), "{label}");
        }
        let used = bytes.len() + peak;
        eprintln!(
            "{label}: file {} B, read peak {peak} B, reserved {reserved} B",
            bytes.len()
        );
        assert!(
            used as u64 <= reserved,
            "{label}: the read took {used} B, more than the {reserved} B reserved"
        );
    }
}
