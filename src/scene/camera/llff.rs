//! LLFF `poses_bounds.npy` (camera poses as an `(N, 17)` NPY array).

use super::npy::parse_npy;
use super::{Camera, Intrinsics, camera_from_c2w, image_size, read_limited};
use crate::scene::SceneError;
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Reads LLFF's `poses_bounds.npy` (written by LLFF's `imgs2poses.py`): an `(N, 17)` float
/// array whose rows are a 3×5 row-major matrix `[R | centre | (h, w, f)]` followed by the near
/// and far depth bounds (which this reader checks for finiteness and otherwise ignores). `R`'s
/// columns are the camera's down, right and backwards axes in world space; they are reordered to
/// this crate's right, down, forward. `h`, `w`, `f` are in pixels of the images COLMAP saw; the
/// principal point is the image centre.
///
/// With `images_dir`, its image files (`.png`, `.jpg`, `.jpeg`, sorted by name, as LLFF pairs
/// them) are matched one to one with the poses: their count must equal `N`, each becomes
/// [`Camera::image`] and names its camera, and `h`, `w`, `f` are rescaled to each image's actual
/// size (so `images_8` gives 1/8 resolution cameras). Without it, cameras are named
/// `llff_000`, `llff_001`… at the pose's own resolution.
pub fn read_llff_poses(path: &Path, images_dir: Option<&Path>) -> Result<Vec<Camera>, SceneError> {
    let bytes = read_limited(path)?;
    llff_from_bytes(&bytes, path, images_dir)
}

pub(super) fn llff_from_bytes(
    bytes: &[u8],
    path: &Path,
    images_dir: Option<&Path>,
) -> Result<Vec<Camera>, SceneError> {
    let npy = parse_npy(bytes)?;
    let err = |msg: String| SceneError::Camera(format!("{}: {msg}", path.display()));
    let n = match npy.shape[..] {
        [n, 17] if n > 0 => n,
        _ => {
            return Err(err(format!(
                "LLFF poses must be an array of shape (N, 17) with N ≥ 1; found {:?}",
                npy.shape
            )));
        }
    };
    let images = match images_dir {
        Some(dir) => {
            let files = list_images(dir)?;
            if files.len() != n {
                return Err(err(format!(
                    "{n} poses but {} images in {}",
                    files.len(),
                    dir.display()
                )));
            }
            Some(files)
        }
        None => None,
    };
    let mut cams = Vec::with_capacity(n);
    for (i, row) in npy.data.chunks_exact(17).enumerate() {
        let m = |r: usize, c: usize| row[r * 5 + c];
        let col = |c: usize| DVec3::new(m(0, c), m(1, c), m(2, c));
        let (down, right, back) = (col(0), col(1), col(2));
        let centre = col(3);
        let (h, w, f) = (m(0, 4), m(1, 4), m(2, 4));
        if !(row[15].is_finite() && row[16].is_finite()) {
            return Err(err(format!("pose {i}: near/far bounds are not finite")));
        }
        let pose_dim = |v: f64, key: &str| {
            if v.is_finite() && v >= 1.0 && v <= f64::from(u32::MAX) {
                Ok(v.round() as u32)
            } else {
                Err(err(format!(
                    "pose {i}: {key} = {v} is not a valid image size"
                )))
            }
        };
        let (pw, ph) = (pose_dim(w, "w")?, pose_dim(h, "h")?);
        let c2w = DMat3::from_cols(right, down, -back);
        let (name, image, width, height, fx, fy) = match &images {
            Some(files) => {
                let file = &files[i];
                let (iw, ih) = image_size(file).map_err(&err)?;
                let (sx, sy) = (f64::from(iw) / w, f64::from(ih) / h);
                if (h * sx - f64::from(ih)).abs() > f64::max(1.0, 0.01 * f64::from(ih)) {
                    return Err(err(format!(
                        "pose {i}: image {} is {iw}×{ih}, not the pose's aspect ratio ({w}×{h})",
                        file.display()
                    )));
                }
                let name = file
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| format!("llff_{i:03}"));
                (name, Some(file.clone()), iw, ih, f * sx, f * sy)
            }
            None => (format!("llff_{i:03}"), None, pw, ph, f, f),
        };
        let intr = Intrinsics {
            width,
            height,
            fx,
            fy,
            cx: 0.5 * f64::from(width),
            cy: 0.5 * f64::from(height),
        };
        let mut cam = camera_from_c2w(name, intr, c2w, centre)?;
        cam.image = image;
        cams.push(cam);
    }
    Ok(cams)
}

/// The image files of a folder (`.png`, `.jpg`, `.jpeg`, any case), sorted by file name.
fn list_images(dir: &Path) -> Result<Vec<PathBuf>, SceneError> {
    let io = |source| SceneError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let p = entry.path();
        let is_image = p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            ["png", "jpg", "jpeg"]
                .iter()
                .any(|x| e.eq_ignore_ascii_case(x))
        });
        if is_image && p.is_file() {
            files.push(p);
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::read_cameras;
    use crate::scene::camera::tests::{
        assert_same_projection, data_path, f8_header, inside, llff_rows, npy_bytes, sample_cameras,
        write, write_png,
    };
    use glam::{Vec2, Vec3};

    #[test]
    fn llff_round_trip() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cams = sample_cameras(true, true);
        let path = dir.path().join("poses_bounds.npy");
        write(
            &path,
            npy_bytes(
                &f8_header(&format!("({}, 17)", cams.len())),
                &llff_rows(&cams),
            ),
        );
        let read = read_llff_poses(&path, None).expect("read");
        assert_eq!(read.len(), cams.len());
        for (i, (a, b)) in cams.iter().zip(&read).enumerate() {
            assert_eq!(b.name, format!("llff_{i:03}"));
            assert_same_projection(a, b);
        }
        // Without an `images` folder the dispatcher gives the same; with one it pairs images.
        assert_eq!(read_cameras(&path).expect("dispatch"), read);
        let images = dir.path().join("images");
        std::fs::create_dir(&images).expect("mkdir");
        for (i, c) in cams.iter().enumerate() {
            write_png(
                &images.join(format!("img{i:02}.png")),
                c.width / 2,
                c.height / 2,
            );
        }
        write(&images.join("notes.txt"), "ignored");
        let halves = read_cameras(&path).expect("dispatch with images");
        for (i, (a, b)) in cams.iter().zip(&halves).enumerate() {
            assert_eq!(b.name, format!("img{i:02}"));
            assert_eq!(
                b.image.as_deref(),
                Some(images.join(format!("img{i:02}.png")).as_path())
            );
            assert_same_projection(&a.resized(a.width / 2, a.height / 2), b);
        }
        write_png(&images.join("extra.png"), 8, 8);
        let e = read_llff_poses(&path, Some(&images))
            .expect_err("count")
            .to_string();
        assert!(e.contains("4 poses but 5 images"), "{e}");
    }

    #[test]
    fn llff_axes_hand_computed() {
        // Camera at (0, 0, 5) looking at the origin, world +y up: down = −y, right = +x,
        // backwards = +z. A second one rolled: down = +x, right = +y, backwards = +z.
        let rows = [
            [
                0.0, 1.0, 0.0, 0.0, 80.0, -1.0, 0.0, 0.0, 0.0, 100.0, 0.0, 0.0, 1.0, 5.0, 50.0,
                1.0, 9.0,
            ],
            [
                1.0, 0.0, 0.0, 0.0, 80.0, 0.0, 1.0, 0.0, 0.0, 100.0, 0.0, 0.0, 1.0, 5.0, 50.0, 1.0,
                9.0,
            ],
        ];
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("poses_bounds.npy");
        write(&path, npy_bytes(&f8_header("(2, 17)"), rows.as_flattened()));
        let cams = read_llff_poses(&path, None).expect("read");
        let pp = Vec2::new(50.0, 40.0);
        for c in &cams {
            assert_eq!(
                (c.width, c.height, c.fx, c.fy, c.cx, c.cy),
                (100, 80, 50.0, 50.0, 50.0, 40.0)
            );
            assert!((c.project(Vec3::ZERO).expect("visible") - pp).length() < 1e-4);
            assert!((c.center() - Vec3::new(0.0, 0.0, 5.0)).length() < 1e-6);
        }
        let px = cams[0].project(Vec3::X).expect("visible");
        assert!(
            (px - Vec2::new(60.0, 40.0)).length() < 1e-4,
            "+x is right: {px}"
        );
        let py = cams[0].project(Vec3::Y).expect("visible");
        assert!(
            (py - Vec2::new(50.0, 30.0)).length() < 1e-4,
            "+y is up: {py}"
        );
        let py = cams[1].project(Vec3::Y).expect("visible");
        assert!(
            (py - Vec2::new(60.0, 40.0)).length() < 1e-4,
            "+y is right: {py}"
        );
        let px = cams[1].project(Vec3::X).expect("visible");
        assert!(
            (px - Vec2::new(50.0, 50.0)).length() < 1e-4,
            "+x is down: {px}"
        );
    }

    #[test]
    fn llff_rejects_wrong_shapes() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("poses_bounds.npy");
        for shape in ["(2, 16)", "(0, 17)", "(34,)", "(1, 2, 17)"] {
            let n: usize = shape
                .trim_matches(|c| c == '(' || c == ')')
                .split(',')
                .filter_map(|d| d.trim().parse::<usize>().ok())
                .product();
            write(&path, npy_bytes(&f8_header(shape), &vec![1.0; n]));
            let e = read_llff_poses(&path, None).expect_err(shape);
            assert!(
                matches!(&e, SceneError::Camera(m) if m.contains("(N, 17)")),
                "{shape}: {e}"
            );
        }
        // A non-rotation pose.
        let mut row = vec![0.0; 17];
        row[4] = 10.0;
        row[9] = 10.0;
        row[14] = 10.0;
        write(&path, npy_bytes(&f8_header("(1, 17)"), &row));
        let e = read_llff_poses(&path, None)
            .expect_err("zero rotation")
            .to_string();
        assert!(e.contains("orthonormal"), "{e}");
    }

    /// COLMAP `points3D.bin` positions (test-only reader).
    fn colmap_points(path: &Path) -> Vec<Vec3> {
        let b = std::fs::read(path).expect("points3D.bin");
        let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
        let f64_at = |o: usize| f64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
        let n = u64_at(0) as usize;
        let mut o = 8;
        let mut pts = Vec::with_capacity(n);
        for _ in 0..n {
            pts.push(DVec3::new(f64_at(o + 8), f64_at(o + 16), f64_at(o + 24)).as_vec3());
            o += 8 + 24 + 3 + 8;
            let track = u64_at(o) as usize;
            o += 8 + 8 * track;
        }
        assert_eq!(o, b.len(), "parsed the whole points3D.bin");
        pts
    }

    #[test]
    fn real_fern_poses() {
        let Some(path) = data_path("datasets/llff_fern/poses_bounds.npy") else {
            return;
        };
        let Some(images) = data_path("datasets/llff_fern/images_8") else {
            return;
        };
        let cams = read_llff_poses(&path, Some(&images)).expect("read fern");
        assert_eq!(cams.len(), 20);
        let full = read_llff_poses(&path, None).expect("read fern without images");
        for (c, f) in cams.iter().zip(&full) {
            assert_eq!((c.width, c.height), (504, 378));
            assert_eq!((f.width, f.height), (4032, 3024));
            assert!((c.fx - f.fx / 8.0).abs() < 1e-3 && (c.fy - f.fy / 8.0).abs() < 1e-3);
            assert_same_projection(&f.resized(504, 378), c);
        }
        assert_eq!(cams[0].name, "image000");
        // No `images` folder beside the file: the dispatcher reads the poses alone.
        assert_eq!(read_cameras(&path).expect("dispatch"), full);
        // The COLMAP points the poses came from must be in front of every camera and mostly
        // inside its image (fern is forward-facing).
        let Some(points) = data_path("datasets/llff_fern/sparse/0/points3D.bin") else {
            return;
        };
        let pts = colmap_points(&points);
        assert!(pts.len() > 1000);
        for c in &cams {
            let visible = pts
                .iter()
                .filter(|&&p| c.project(p).is_some_and(|q| inside(c, q)))
                .count();
            let frac = visible as f64 / pts.len() as f64;
            assert!(
                frac > 0.8,
                "{}: only {:.1} % of the COLMAP points project inside",
                c.name,
                100.0 * frac
            );
        }
    }
}
