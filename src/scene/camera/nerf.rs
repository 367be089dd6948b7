//! NeRF (Blender synthetic) and nerfstudio / instant-ngp `transforms.json`.

use super::{Camera, Intrinsics, camera_from_c2w, image_size, read_limited, strip_bom};
use crate::scene::SceneError;
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Intrinsics that `transforms.json` may give at the top level or per frame.
#[derive(serde::Deserialize, Default)]
struct NerfIntrinsics {
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
}

#[derive(serde::Deserialize)]
struct NerfFrame {
    file_path: String,
    /// Camera → world, OpenGL camera axes (x right, y up, z backwards); 3 or 4 rows of 4.
    transform_matrix: Vec<[f64; 4]>,
    #[serde(flatten)]
    intrinsics: NerfIntrinsics,
}

#[derive(serde::Deserialize)]
struct NerfTransforms {
    #[serde(flatten)]
    intrinsics: NerfIntrinsics,
    frames: Vec<NerfFrame>,
}

/// Reads a NeRF (Blender synthetic) or nerfstudio / instant-ngp `transforms.json`.
///
/// Intrinsics come from each frame's own `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, `camera_angle_x`,
/// `camera_angle_y` or else from the same keys at the top level: `fl_x` wins over
/// `camera_angle_x` (`fl_x = w / (2·tan(camera_angle_x / 2))`), `fl_y` defaults to `fl_x` unless
/// `camera_angle_y` is given, and the principal point defaults to the image centre.
///
/// `file_path` is relative to the JSON's folder and may lack its extension (tried as written,
/// then with `.png`, `.jpg`, `.jpeg`); the image must exist and becomes [`Camera::image`]. Its
/// header gives `w`/`h` when the JSON does not; when both are present and differ, the intrinsics
/// are rescaled to the image actually on disk (an aspect-ratio change is an error).
///
/// `transform_matrix` is camera → world in the OpenGL convention (x right, y up, z backwards);
/// the y and z axes are negated to get this crate's OpenCV convention.
pub fn read_nerf_transforms(path: &Path) -> Result<Vec<Camera>, SceneError> {
    let bytes = read_limited(path)?;
    nerf_from_json(
        strip_bom(&bytes),
        path,
        Some(path.parent().unwrap_or(Path::new(""))),
    )
}

/// `images`: the folder `file_path`s are relative to, or `None` to open no image at all (then
/// every frame must give `w` and `h`; see [`read_cameras_bytes`](super::read_cameras_bytes)).
pub(super) fn nerf_from_json(
    json: &[u8],
    path: &Path,
    images: Option<&Path>,
) -> Result<Vec<Camera>, SceneError> {
    let doc: NerfTransforms = serde_json::from_slice(json).map_err(|e| {
        SceneError::Camera(format!(
            "{}: not a NeRF transforms.json: {e}",
            path.display()
        ))
    })?;
    if doc.frames.is_empty() {
        return Err(SceneError::Camera(format!(
            "{}: 'frames' is empty",
            path.display()
        )));
    }
    doc.frames
        .iter()
        .enumerate()
        .map(|(i, frame)| nerf_frame(i, frame, &doc.intrinsics, images, path))
        .collect()
}

fn nerf_frame(
    index: usize,
    frame: &NerfFrame,
    top: &NerfIntrinsics,
    base: Option<&Path>,
    json_path: &Path,
) -> Result<Camera, SceneError> {
    // Without an image folder the frame's path is not echoed either: the message is the same
    // whatever the path names.
    let err = |msg: String| match base {
        Some(_) => SceneError::Camera(format!(
            "{}: frame {index} ('{}'): {msg}",
            json_path.display(),
            frame.file_path
        )),
        None => SceneError::Camera(format!("{}: frame {index}: {msg}", json_path.display())),
    };
    let (image, img_size) = match base {
        Some(base) => {
            let image = resolve_image(base, &frame.file_path).map_err(&err)?;
            let size = image_size(&image).map_err(&err)?;
            (Some(image), Some(size))
        }
        None => (None, None),
    };

    let own = &frame.intrinsics;
    let pick = |f: fn(&NerfIntrinsics) -> Option<f64>| f(own).or_else(|| f(top));
    let no_size = || {
        err(
            "no image size: give w and h (the images a camera file names are not opened \
             when it is uploaded)"
                .to_string(),
        )
    };
    let w = match (pick(|k| k.w), img_size) {
        (Some(w), _) => positive_dim(w, "w").map_err(&err)?,
        (None, Some((img_w, _))) => img_w,
        (None, None) => return Err(no_size()),
    };
    let h = match (pick(|k| k.h), img_size) {
        (Some(h), _) => positive_dim(h, "h").map_err(&err)?,
        (None, Some((_, img_h))) => img_h,
        (None, None) => return Err(no_size()),
    };
    let (wf, hf) = (f64::from(w), f64::from(h));
    let focal_from_angle = |angle: f64, size: f64, key: &str| {
        if angle.is_finite() && angle > 0.0 && angle < std::f64::consts::PI {
            Ok(0.5 * size / (0.5 * angle).tan())
        } else {
            Err(err(format!("{key} = {angle} is not an angle in (0, π)")))
        }
    };
    let fx = match (pick(|k| k.fl_x), pick(|k| k.camera_angle_x)) {
        (Some(f), _) => f,
        (None, Some(a)) => focal_from_angle(a, wf, "camera_angle_x")?,
        (None, None) => {
            return Err(err(
                "no focal length: give fl_x or camera_angle_x".to_string()
            ));
        }
    };
    let fy = match (pick(|k| k.fl_y), pick(|k| k.camera_angle_y)) {
        (Some(f), _) => f,
        (None, Some(a)) => focal_from_angle(a, hf, "camera_angle_y")?,
        (None, None) => fx,
    };
    let intr = Intrinsics {
        width: w,
        height: h,
        fx,
        fy,
        cx: pick(|k| k.cx).unwrap_or(0.5 * wf),
        cy: pick(|k| k.cy).unwrap_or(0.5 * hf),
    };

    let m = &frame.transform_matrix;
    if !(m.len() == 3 || m.len() == 4) {
        return Err(err(format!(
            "transform_matrix has {} rows (3 or 4 expected)",
            m.len()
        )));
    }
    // OpenGL camera axes (right, up, back) → OpenCV (right, down, forward).
    let gl = DMat3::from_cols(
        DVec3::new(m[0][0], m[1][0], m[2][0]),
        DVec3::new(m[0][1], m[1][1], m[2][1]),
        DVec3::new(m[0][2], m[1][2], m[2][2]),
    );
    let c2w = DMat3::from_cols(gl.x_axis, -gl.y_axis, -gl.z_axis);
    let centre = DVec3::new(m[0][3], m[1][3], m[2][3]);
    let name = image
        .as_deref()
        .unwrap_or(Path::new(&frame.file_path))
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| format!("frame_{index:03}"));
    let mut cam = camera_from_c2w(name, intr, c2w, centre)?;
    if let Some((img_w, img_h)) = img_size
        && (cam.width, cam.height) != (img_w, img_h)
    {
        cam = rescale_to_image(&cam, img_w, img_h).map_err(&err)?;
    }
    cam.image = image;
    Ok(cam)
}

/// Finds the image a `transforms.json` frame names: as written, then with `.png`, `.jpg`, `.jpeg`.
fn resolve_image(base: &Path, file_path: &str) -> Result<PathBuf, String> {
    let rel = Path::new(file_path);
    let rel = rel.strip_prefix(".").unwrap_or(rel);
    let plain = base.join(rel);
    let mut tried = Vec::new();
    for suffix in ["", ".png", ".jpg", ".jpeg"] {
        let mut candidate = plain.clone().into_os_string();
        candidate.push(suffix);
        let candidate = PathBuf::from(candidate);
        if candidate.is_file() {
            return Ok(candidate);
        }
        tried.push(candidate.display().to_string());
    }
    Err(format!("image not found (tried {})", tried.join(", ")))
}

/// A JSON image dimension: a positive whole number that fits in u32.
fn positive_dim(v: f64, key: &str) -> Result<u32, String> {
    if v.is_finite() && v >= 1.0 && v <= f64::from(u32::MAX) && v.fract() == 0.0 {
        Ok(v as u32)
    } else {
        Err(format!(
            "{key} = {v} is not a positive whole number of pixels"
        ))
    }
}

/// The camera rescaled to an image of another size, refusing a change of aspect ratio (more
/// than one pixel or 1 %, whichever is larger).
fn rescale_to_image(cam: &Camera, width: u32, height: u32) -> Result<Camera, String> {
    let s = f64::from(width) / f64::from(cam.width);
    let predicted_h = f64::from(cam.height) * s;
    if (predicted_h - f64::from(height)).abs() > f64::max(1.0, 0.01 * f64::from(height)) {
        return Err(format!(
            "the image is {width}×{height} but the camera is {}×{}: different aspect ratio",
            cam.width, cam.height
        ));
    }
    Ok(cam.resized(width, height))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::read_cameras;
    use crate::scene::camera::tests::{
        assert_same_projection, data_path, sample_cameras, write, write_png,
    };
    use glam::{Vec2, Vec3};
    use serde_json::json;

    /// A camera's pose as a NeRF (OpenGL camera axes) camera → world 4×4 matrix.
    fn gl_matrix(c: &Camera) -> [[f32; 4]; 4] {
        let m = c.rotation_mat().transpose();
        let (x, y, z, t) = (m.x_axis, -m.y_axis, -m.z_axis, c.center());
        [
            [x.x, y.x, z.x, t.x],
            [x.y, y.y, z.y, t.y],
            [x.z, y.z, z.z, t.z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    #[test]
    fn nerf_round_trip_explicit_intrinsics() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir(dir.path().join("images")).expect("mkdir");
        let cams = sample_cameras(false, false);
        let frames: Vec<_> = cams
            .iter()
            .map(|c| {
                write_png(
                    &dir.path().join(format!("images/{}.png", c.name)),
                    c.width,
                    c.height,
                );
                json!({
                    "file_path": format!("images/{}.png", c.name),
                    "transform_matrix": gl_matrix(c),
                    "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
                })
            })
            .collect();
        let path = dir.path().join("transforms.json");
        write(
            &path,
            json!({ "camera_model": "OPENCV", "frames": frames }).to_string(),
        );
        let read = read_nerf_transforms(&path).expect("read");
        assert_eq!(read.len(), cams.len());
        for (a, b) in cams.iter().zip(&read) {
            assert_eq!(a.name, b.name);
            assert_same_projection(a, b);
            let img = b.image.as_ref().expect("image set");
            assert_eq!(img, &dir.path().join(format!("images/{}.png", a.name)));
        }
        assert_eq!(read_cameras(&path).expect("dispatch"), read);
    }

    #[test]
    fn nerf_round_trip_camera_angle_and_image_sizes() {
        // Blender style: one top-level camera_angle_x, extension-less paths, sizes from the PNGs.
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir(dir.path().join("train")).expect("mkdir");
        let cams: Vec<Camera> = sample_cameras(true, true)
            .into_iter()
            .map(|c| Camera {
                fx: 90.0,
                fy: 90.0,
                ..c.resized(80, 60)
            })
            .map(|c| Camera {
                cx: 40.0,
                cy: 30.0,
                ..c
            })
            .collect();
        let angle_x = 2.0 * (40.0f64 / 90.0).atan();
        let frames: Vec<_> = cams
            .iter()
            .map(|c| {
                write_png(&dir.path().join(format!("train/{}.png", c.name)), 80, 60);
                json!({ "file_path": format!("./train/{}", c.name), "transform_matrix": gl_matrix(c) })
            })
            .collect();
        let path = dir.path().join("transforms_train.json");
        write(
            &path,
            json!({ "camera_angle_x": angle_x, "frames": frames }).to_string(),
        );
        let read = read_nerf_transforms(&path).expect("read");
        for (a, b) in cams.iter().zip(&read) {
            assert!(
                (b.fx - 90.0).abs() < 1e-3 && (b.fy - 90.0).abs() < 1e-3,
                "{b:?}"
            );
            assert_same_projection(a, b);
        }
    }

    #[test]
    fn nerf_json_size_differs_from_image_rescales() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_png(&dir.path().join("a.png"), 50, 40);
        let doc = json!({ "fl_x": 100.0, "w": 100, "h": 80, "frames": [{
            "file_path": "a", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,5],[0,0,0,1]] }] });
        let path = dir.path().join("transforms.json");
        write(&path, doc.to_string());
        let cam = &read_nerf_transforms(&path).expect("read")[0];
        assert_eq!(
            (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy),
            (50, 40, 50.0, 50.0, 25.0, 20.0)
        );
        write_png(&dir.path().join("a.png"), 50, 50);
        let e = read_nerf_transforms(&path).expect_err("aspect").to_string();
        assert!(e.contains("aspect"), "{e}");
    }

    #[test]
    fn nerf_opengl_to_opencv_hand_computed() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_png(&dir.path().join("a.png"), 100, 80);
        let path = dir.path().join("transforms.json");
        // Camera at (0, 0, 5) looking at the origin (OpenGL: −z forward), y up.
        let upright = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 5.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        // Same place, rolled: its right is world +y, its up world −x.
        let rolled = [
            [0.0, -1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 5.0],
        ];
        let doc = json!({ "fl_x": 50.0, "frames": [
            { "file_path": "a.png", "transform_matrix": upright },
            { "file_path": "a", "transform_matrix": rolled },
        ] });
        write(&path, doc.to_string());
        let cams = read_nerf_transforms(&path).expect("read");
        let pp = Vec2::new(50.0, 40.0);
        let up = &cams[0];
        assert!((up.project(Vec3::ZERO).expect("visible") - pp).length() < 1e-4);
        let px = up.project(Vec3::X).expect("visible");
        assert!(
            (px - Vec2::new(60.0, 40.0)).length() < 1e-4,
            "+x is right: {px}"
        );
        let py = up.project(Vec3::Y).expect("visible");
        assert!(
            (py - Vec2::new(50.0, 30.0)).length() < 1e-4,
            "+y is up: {py}"
        );
        assert!(
            up.project(Vec3::new(0.0, 0.0, 6.0)).is_none(),
            "behind the camera"
        );
        let rolled = &cams[1];
        assert!((rolled.project(Vec3::ZERO).expect("visible") - pp).length() < 1e-4);
        let py = rolled.project(Vec3::Y).expect("visible");
        assert!(
            (py - Vec2::new(60.0, 40.0)).length() < 1e-4,
            "+y is right: {py}"
        );
        let nx = rolled.project(Vec3::NEG_X).expect("visible");
        assert!(
            (nx - Vec2::new(50.0, 30.0)).length() < 1e-4,
            "−x is up: {nx}"
        );
    }

    #[test]
    fn nerf_rejects_bad_input() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_png(&dir.path().join("a.png"), 10, 10);
        let path = dir.path().join("transforms.json");
        let eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]];
        let cases = [
            (
                json!({ "fl_x": 5, "frames": [{ "file_path": "missing", "transform_matrix": eye }] }),
                "not found",
            ),
            (
                json!({ "frames": [{ "file_path": "a", "transform_matrix": eye }] }),
                "focal",
            ),
            (json!({ "fl_x": 5, "frames": [] }), "empty"),
            (
                json!({ "fl_x": 5, "frames": [{ "file_path": "a", "transform_matrix": [[1,0,0,0]] }] }),
                "rows",
            ),
            (
                json!({ "camera_angle_x": 4.0, "frames": [{ "file_path": "a", "transform_matrix": eye }] }),
                "angle",
            ),
            (
                json!({ "fl_x": 5, "w": 0, "frames": [{ "file_path": "a", "transform_matrix": eye }] }),
                "whole number",
            ),
            (json!({ "fl_x": 5 }), "frames"),
        ];
        for (doc, needle) in cases {
            write(&path, doc.to_string());
            let e = read_nerf_transforms(&path)
                .expect_err(&doc.to_string())
                .to_string();
            assert!(e.contains(needle), "{doc}: {e}");
        }
        write(&dir.path().join("bad.png"), b"not a png");
        let doc =
            json!({ "fl_x": 5, "frames": [{ "file_path": "bad.png", "transform_matrix": eye }] });
        write(&path, doc.to_string());
        let e = read_nerf_transforms(&path)
            .expect_err("bad image")
            .to_string();
        assert!(e.contains("bad.png"), "{e}");
    }

    #[test]
    fn real_lego_transforms() {
        let Some(path) = data_path("datasets/nerf_synthetic_lego/transforms_train.json") else {
            return;
        };
        let cams = read_nerf_transforms(&path).expect("read lego");
        assert_eq!(cams.len(), 100);
        let focal = 400.0 / (0.5f32 * 0.691_111_2).tan();
        let centre = Vec2::new(400.0, 400.0);
        for c in &cams {
            assert_eq!((c.width, c.height), (800, 800));
            assert!(
                (c.fx - focal).abs() < 1e-2 && (c.fy - focal).abs() < 1e-2,
                "{c:?}"
            );
            assert!(c.image.as_ref().is_some_and(|p| p.is_file()), "{}", c.name);
            // Every Blender camera looks exactly at the origin (measured: within 0.0014 px).
            let p = c.project(Vec3::ZERO).expect("origin in front");
            assert!(
                (p - centre).length() < 0.05,
                "{}: origin projects to {p}",
                c.name
            );
        }
        assert_eq!(cams[0].name, "r_0");
        assert_eq!(read_cameras(&path).expect("dispatch"), cams);
    }
}
