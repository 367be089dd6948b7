//! Pinhole cameras and the camera files people ship with scenes.
//!
//! Convention (OpenCV / COLMAP / INRIA): camera space has x right, y down, z forward; a world
//! point `p` maps to camera space as `R·p + t`, then to pixels as
//! `(fx·x/z + cx, fy·y/z + cy)`; pixel `(i, j)` covers `[i, i+1) × [j, j+1)`, so its centre is at
//! `(i + 0.5, j + 0.5)` (with `cx = W/2` this matches the INRIA rasterizer exactly).

mod inria;
mod llff;
mod nerf;
mod npy;

pub use inria::read_inria_cameras;
pub use llff::read_llff_poses;
pub use nerf::read_nerf_transforms;

use crate::scene::SceneError;
use glam::{DMat3, DVec3, Mat3, Vec2, Vec3};
use std::io::Read;
use std::path::{Path, PathBuf};

use inria::inria_from_json;
use llff::llff_from_bytes;
use nerf::nerf_from_json;
use npy::NPY_MAGIC;

/// A pinhole camera: intrinsics in pixels and the world → camera rigid transform.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Camera {
    /// A name for output files and reports (image name, frame index…).
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// World → camera rotation, row-major (`rotation[r][c]`).
    pub rotation: [[f32; 3]; 3],
    /// World → camera translation.
    pub translation: [f32; 3],
    /// The ground-truth image of this view, when the camera file names one.
    pub image: Option<PathBuf>,
}

impl Camera {
    /// World → camera rotation as a glam matrix.
    pub fn rotation_mat(&self) -> Mat3 {
        let r = self.rotation;
        Mat3::from_cols(
            Vec3::new(r[0][0], r[1][0], r[2][0]),
            Vec3::new(r[0][1], r[1][1], r[2][1]),
            Vec3::new(r[0][2], r[1][2], r[2][2]),
        )
    }

    pub fn translation_vec(&self) -> Vec3 {
        Vec3::from(self.translation)
    }

    /// Builds a camera from a camera → world rotation (columns are the camera axes in world
    /// space, OpenCV convention) and the camera centre in world space.
    #[allow(clippy::too_many_arguments)]
    pub fn from_pose(
        name: impl Into<String>,
        width: u32,
        height: u32,
        fx: f32,
        fy: f32,
        cx: f32,
        cy: f32,
        cam_to_world: Mat3,
        center: Vec3,
    ) -> Self {
        let r = cam_to_world.transpose();
        let t = -(r * center);
        let rows = [r.row(0), r.row(1), r.row(2)];
        Self {
            name: name.into(),
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            rotation: rows.map(|v| v.to_array()),
            translation: t.to_array(),
            image: None,
        }
    }

    /// Camera centre in world space.
    pub fn center(&self) -> Vec3 {
        -(self.rotation_mat().transpose() * self.translation_vec())
    }

    /// World point → camera space.
    pub fn to_camera(&self, p: Vec3) -> Vec3 {
        self.rotation_mat() * p + self.translation_vec()
    }

    /// Horizontal and vertical field of view in radians.
    pub fn fov(&self) -> (f32, f32) {
        (
            2.0 * (self.width as f32 / (2.0 * self.fx)).atan(),
            2.0 * (self.height as f32 / (2.0 * self.fy)).atan(),
        )
    }

    /// The same view at another resolution (intrinsics scaled accordingly).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Self {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            ..self.clone()
        }
    }
}

impl Camera {
    /// World point → pixel coordinates (pixel centres at `i + 0.5`), or `None` when the point is
    /// not in front of the camera (`z ≤ 0` in camera space).
    pub fn project(&self, p: Vec3) -> Option<Vec2> {
        let c = self.to_camera(p);
        if c.z <= 0.0 || !c.z.is_finite() {
            return None;
        }
        Some(Vec2::new(
            self.fx * c.x / c.z + self.cx,
            self.fy * c.y / c.z + self.cy,
        ))
    }

    /// Checks that the camera is usable: non-zero size, positive finite focal lengths, finite
    /// principal point and translation, and a proper rotation (orthonormal within 1e-3,
    /// determinant +1).
    pub fn validate(&self) -> Result<(), SceneError> {
        let name = &self.name;
        if self.width == 0 || self.height == 0 {
            return Err(SceneError::Camera(format!(
                "camera '{name}': image size {}×{} is empty",
                self.width, self.height
            )));
        }
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(SceneError::Camera(format!(
                "camera '{name}': focal lengths must be positive and finite (fx = {}, fy = {})",
                self.fx, self.fy
            )));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(SceneError::Camera(format!(
                "camera '{name}': principal point ({}, {}) is not finite",
                self.cx, self.cy
            )));
        }
        if !self.translation.iter().all(|v| v.is_finite()) {
            return Err(SceneError::Camera(format!(
                "camera '{name}': translation is not finite"
            )));
        }
        let r = self.rotation;
        let m = DMat3::from_cols_array_2d(&r.map(|row| row.map(f64::from))).transpose();
        check_rotation(name, m)
    }
}

// ---------------------------------------------------------------------------------------------
// Camera files
// ---------------------------------------------------------------------------------------------

/// Largest camera file (JSON or NPY) the readers accept, in bytes. Real ones are kilobytes to a
/// few megabytes; the cap keeps a mistaken or hostile path from being read into memory.
pub const MAX_CAMERA_FILE_BYTES: u64 = 256 << 20;

/// Resizes `cams` to `width` × `height`; a missing side follows each camera's aspect ratio,
/// `(None, None)` keeps them as they are.
pub fn resize_all(cams: Vec<Camera>, width: Option<u32>, height: Option<u32>) -> Vec<Camera> {
    if width.is_none() && height.is_none() {
        return cams;
    }
    cams.into_iter()
        .map(|c| {
            let w = width.unwrap_or_else(|| {
                let h = height.unwrap_or(c.height);
                (f64::from(c.width) * f64::from(h) / f64::from(c.height)).round() as u32
            });
            let h = height.unwrap_or_else(|| {
                (f64::from(c.height) * f64::from(w) / f64::from(c.width)).round() as u32
            });
            c.resized(w.max(1), h.max(1))
        })
        .collect()
}

/// Reads whichever camera file `path` is, deciding by content (and name):
///
/// - NPY data (`\x93NUMPY` magic, usually `poses_bounds.npy`): LLFF poses, see
///   [`read_llff_poses`]; an `images` folder beside the file, when there is one, supplies the
///   images and their resolution.
/// - a JSON array: INRIA `cameras.json`, see [`read_inria_cameras`].
/// - a JSON object: NeRF / nerfstudio `transforms.json`, see [`read_nerf_transforms`].
///
/// A directory is searched for `cameras.json`, `transforms.json`, `transforms_train.json` and
/// `poses_bounds.npy`, in that order.
///
/// This follows the paths the file names (images beside it, or wherever a `file_path` points): it
/// is for the user's own files (the CLI). A file from someone else (an upload) is read with
/// [`read_cameras_bytes`], which opens nothing.
pub fn read_cameras(path: &Path) -> Result<Vec<Camera>, SceneError> {
    if path.is_dir() {
        const CANDIDATES: [&str; 4] = [
            "cameras.json",
            "transforms.json",
            "transforms_train.json",
            "poses_bounds.npy",
        ];
        return match CANDIDATES
            .iter()
            .map(|n| path.join(n))
            .find(|p| p.is_file())
        {
            Some(file) => read_cameras(&file),
            None => Err(SceneError::Camera(format!(
                "{} is a directory without a camera file (looked for {})",
                path.display(),
                CANDIDATES.join(", ")
            ))),
        };
    }
    let bytes = read_limited(path)?;
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if is_npy || bytes.starts_with(NPY_MAGIC) {
        let images = path
            .parent()
            .map(|d| d.join("images"))
            .filter(|d| d.is_dir());
        return llff_from_bytes(&bytes, path, images.as_deref());
    }
    let json = strip_bom(&bytes);
    match json.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'[') => inria_from_json(json, path),
        Some(b'{') => nerf_from_json(json, path, Some(path.parent().unwrap_or(Path::new("")))),
        _ => Err(not_a_camera_file(path)),
    }
}

fn not_a_camera_file(path: &Path) -> SceneError {
    SceneError::Camera(format!(
        "{}: not a recognised camera file (expected an INRIA cameras.json array, a NeRF \
         transforms.json object or an LLFF poses_bounds.npy)",
        path.display()
    ))
}

/// The kind of camera file [`read_cameras_bytes`] found.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CameraFormat {
    /// INRIA gaussian-splatting `cameras.json`.
    Inria,
    /// NeRF / nerfstudio `transforms.json`.
    Nerf,
    /// LLFF `poses_bounds.npy`.
    Llff,
}

impl CameraFormat {
    /// The stored name (`assets.cameras_format`): `inria`, `nerf` or `llff`.
    pub fn as_str(self) -> &'static str {
        match self {
            CameraFormat::Inria => "inria",
            CameraFormat::Nerf => "nerf",
            CameraFormat::Llff => "llff",
        }
    }
}

/// Reads a camera file that came without its folder — an upload, or the blob stored from one —
/// from its bytes alone, deciding by content as [`read_cameras`] does. It never opens another
/// file, so what a hostile file names on the server can neither be read nor probed:
///
/// - a NeRF `transforms.json` must give each frame's image size, `w` and `h` (per frame or at
///   the top level): the images its `file_path`s name are not opened, the paths only name the
///   cameras (by their file stem) and [`Camera::image`] stays empty;
/// - LLFF poses keep their own resolution (no `images` folder is looked for);
/// - INRIA `cameras.json` needs nothing else.
///
/// Errors name the file `label` (e.g. the name the client gave), never a path on the server.
pub fn read_cameras_bytes(
    bytes: &[u8],
    label: &str,
) -> Result<(CameraFormat, Vec<Camera>), SceneError> {
    let path = Path::new(label);
    if bytes.len() as u64 > MAX_CAMERA_FILE_BYTES {
        return Err(SceneError::Camera(format!(
            "{label}: more than the {MAX_CAMERA_FILE_BYTES}-byte limit for camera files"
        )));
    }
    if bytes.starts_with(NPY_MAGIC) {
        return Ok((CameraFormat::Llff, llff_from_bytes(bytes, path, None)?));
    }
    let json = strip_bom(bytes);
    match json.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'[') => Ok((CameraFormat::Inria, inria_from_json(json, path)?)),
        Some(b'{') => Ok((CameraFormat::Nerf, nerf_from_json(json, path, None)?)),
        _ => Err(not_a_camera_file(path)),
    }
}

// ----- shared helpers ----------------------------------------------------------------------------

/// Intrinsics in f64 while a camera is assembled.
struct Intrinsics {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// Builds and validates a camera from a camera → world rotation (columns: OpenCV camera axes in
/// world space) and the camera centre, computing the world → camera transform in f64.
fn camera_from_c2w(
    name: String,
    k: Intrinsics,
    c2w: DMat3,
    centre: DVec3,
) -> Result<Camera, SceneError> {
    if !(c2w.is_finite() && centre.is_finite()) {
        return Err(SceneError::Camera(format!(
            "camera '{name}': pose is not finite"
        )));
    }
    check_rotation(&name, c2w)?;
    let r = c2w.transpose();
    let t = -(r * centre);
    let cam = Camera {
        name,
        width: k.width,
        height: k.height,
        fx: k.fx as f32,
        fy: k.fy as f32,
        cx: k.cx as f32,
        cy: k.cy as f32,
        rotation: [r.row(0), r.row(1), r.row(2)].map(|v| v.as_vec3().to_array()),
        translation: t.as_vec3().to_array(),
        image: None,
    };
    cam.validate()?;
    Ok(cam)
}

/// A proper rotation: orthonormal within 1e-3 and determinant +1 (not a reflection).
fn check_rotation(name: &str, m: DMat3) -> Result<(), SceneError> {
    if !m.is_finite() {
        return Err(SceneError::Camera(format!(
            "camera '{name}': rotation is not finite"
        )));
    }
    let e = m.transpose() * m - DMat3::IDENTITY;
    let dev = e.to_cols_array().iter().fold(0.0f64, |a, v| a.max(v.abs()));
    if dev > 1e-3 {
        return Err(SceneError::Camera(format!(
            "camera '{name}': rotation is not orthonormal (max |RᵀR − I| = {dev:.2e})"
        )));
    }
    if m.determinant() < 0.0 {
        return Err(SceneError::Camera(format!(
            "camera '{name}': rotation is a reflection (determinant −1); wrong axis convention?"
        )));
    }
    Ok(())
}

/// Reads a whole camera file, refusing ones larger than [`MAX_CAMERA_FILE_BYTES`].
fn read_limited(path: &Path) -> Result<Vec<u8>, SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    if len > MAX_CAMERA_FILE_BYTES {
        return Err(SceneError::Camera(format!(
            "{}: {len} bytes is more than the {MAX_CAMERA_FILE_BYTES}-byte limit for camera files",
            path.display()
        )));
    }
    let mut bytes = Vec::new();
    file.take(MAX_CAMERA_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_CAMERA_FILE_BYTES {
        return Err(SceneError::Camera(format!(
            "{}: more than the {MAX_CAMERA_FILE_BYTES}-byte limit for camera files",
            path.display()
        )));
    }
    Ok(bytes)
}

/// JSON text without a leading UTF-8 byte-order mark.
fn strip_bom(bytes: &[u8]) -> &[u8] {
    bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes)
}

/// Width and height from an image file's header (PNG or JPEG, detected by content).
fn image_size(path: &Path) -> Result<(u32, u32), String> {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| format!("cannot open image {}: {e}", path.display()))?
        .into_dimensions()
        .map_err(|e| format!("cannot read the size of image {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data");

    /// OpenCV camera → world rotation of a camera at `eye` looking at `target` with `up` up.
    fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Mat3 {
        let z = (target - eye).normalize();
        let x = z.cross(up).normalize();
        let y = z.cross(x);
        Mat3::from_cols(x, y, z)
    }

    /// A few cameras with different poses (none a symmetric rotation), all seeing the origin.
    pub(super) fn sample_cameras(square_pixels: bool, centred: bool) -> Vec<Camera> {
        let poses = [
            (Vec3::new(0.3, -0.4, 5.0), Vec3::Y),
            (Vec3::new(-4.0, 1.5, 2.0), Vec3::new(0.2, 1.0, -0.1)),
            (Vec3::new(2.5, 3.0, -3.5), Vec3::new(-0.3, 0.1, 1.0)),
            (Vec3::new(1.0, -6.0, 0.5), Vec3::X),
        ];
        poses
            .iter()
            .enumerate()
            .map(|(i, &(eye, up))| {
                let (w, h) = (64 + 16 * i as u32, 48 + 8 * i as u32);
                let fx = 70.0 + 10.0 * i as f32;
                let fy = if square_pixels { fx } else { fx * 1.05 };
                let (cx, cy) = if centred {
                    (w as f32 / 2.0, h as f32 / 2.0)
                } else {
                    (w as f32 / 2.0 + 3.25, h as f32 / 2.0 - 1.5)
                };
                let c2w = look_at(eye, Vec3::new(0.1, -0.2, 0.05), up);
                Camera::from_pose(format!("view{i}"), w, h, fx, fy, cx, cy, c2w, eye)
            })
            .collect()
    }

    fn sample_points() -> Vec<Vec3> {
        let mut pts = Vec::new();
        for x in [-1.0f32, -0.3, 0.0, 0.6, 1.1] {
            for y in [-0.8f32, 0.0, 0.9] {
                for z in [-0.7f32, 0.2, 1.0] {
                    pts.push(Vec3::new(x, y, z));
                }
            }
        }
        pts
    }

    /// Both cameras project every sample point to the same pixel within 1e-3 px.
    pub(super) fn assert_same_projection(a: &Camera, b: &Camera) {
        assert_eq!(
            (a.width, a.height),
            (b.width, b.height),
            "{} vs {}",
            a.name,
            b.name
        );
        for p in sample_points() {
            match (a.project(p), b.project(p)) {
                (Some(pa), Some(pb)) => {
                    assert!((pa - pb).length() < 1e-3, "{}: {p} → {pa} vs {pb}", a.name)
                }
                (None, None) => {}
                (pa, pb) => panic!("{}: {p} → {pa:?} vs {pb:?}", a.name),
            }
        }
    }

    pub(super) fn write(path: &Path, bytes: impl AsRef<[u8]>) {
        std::fs::write(path, bytes).expect("write test file");
    }

    pub(super) fn write_png(path: &Path, w: u32, h: u32) {
        image::RgbImage::new(w, h)
            .save(path)
            .expect("write test png");
    }

    // ----- test-only writers ------------------------------------------------------------------

    /// INRIA's `camera_to_JSON`: position = camera centre, rotation = rows of camera → world.
    pub(super) fn inria_json(cams: &[Camera]) -> String {
        let entries: Vec<_> = cams
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let c2w = c.rotation_mat().transpose();
                json!({
                    "id": i, "img_name": c.name, "width": c.width, "height": c.height,
                    "position": c.center().to_array(),
                    "rotation": [c2w.row(0).to_array(), c2w.row(1).to_array(), c2w.row(2).to_array()],
                    "fy": c.fy, "fx": c.fx,
                })
            })
            .collect();
        serde_json::to_string_pretty(&entries).expect("json")
    }

    /// An NPY v1.0 file with a C-order `<f8` array.
    pub(super) fn npy_bytes(header: &str, data: &[f64]) -> Vec<u8> {
        let mut h = header.to_string();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(h.len() as u16).to_le_bytes());
        out.extend_from_slice(h.as_bytes());
        for v in data {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    pub(super) fn f8_header(shape: &str) -> String {
        format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}")
    }

    /// LLFF rows `[down right back | centre | h w f] near far` for square-pixel cameras.
    pub(super) fn llff_rows(cams: &[Camera]) -> Vec<f64> {
        let mut out = Vec::new();
        for c in cams {
            let m = c.rotation_mat().transpose();
            let cols = [m.y_axis, m.x_axis, -m.z_axis, c.center()];
            let hwf = [c.height as f32, c.width as f32, c.fx];
            for r in 0..3 {
                for col in cols {
                    out.push(f64::from(col[r]));
                }
                out.push(f64::from(hwf[r]));
            }
            out.extend([0.5, 20.0]);
        }
        out
    }

    #[test]
    fn uploaded_cameras_never_open_the_files_they_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        // A real image on the server, of another size than the JSON says.
        let png = dir.path().join("a.png");
        write_png(&png, 50, 40);
        let identity = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]];
        let with_size = json!({ "fl_x": 100.0, "w": 100, "h": 80, "frames": [{
            "file_path": png.to_str().unwrap(), "transform_matrix": identity }] });
        // The path reader follows file_path and rescales to the PNG; the bytes reader does not.
        let path = dir.path().join("transforms.json");
        write(&path, with_size.to_string());
        assert_eq!(read_nerf_transforms(&path).expect("read")[0].width, 50);
        let (kind, cams) =
            read_cameras_bytes(with_size.to_string().as_bytes(), "t.json").expect("read");
        assert_eq!(kind, CameraFormat::Nerf);
        assert_eq!(
            (
                cams[0].width,
                cams[0].height,
                cams[0].fx,
                cams[0].image.clone()
            ),
            (100, 80, 100.0, None)
        );
        assert_eq!(cams[0].name, "a");

        // Without a size: one error, whatever the path names (an existing server file, a
        // missing one, a folder above), and no path in it.
        let without = |file_path: &str| {
            let doc = json!({ "fl_x": 100.0, "frames": [{
                "file_path": file_path, "transform_matrix": identity }] });
            read_cameras_bytes(doc.to_string().as_bytes(), "t.json")
                .expect_err("no size")
                .to_string()
        };
        let e = without(png.to_str().unwrap());
        assert!(e.contains("no image size"), "{e}");
        assert!(!e.contains("a.png") && !e.contains('/'), "{e}");
        for p in [
            "/etc/passwd",
            "../../etc/hostname",
            "missing",
            "/nonexistent/x.png",
        ] {
            assert_eq!(without(p), e, "{p}");
        }

        // INRIA and LLFF files read from bytes too; anything else is a typed error.
        let cams = sample_cameras(true, true);
        let (kind, read) =
            read_cameras_bytes(inria_json(&cams).as_bytes(), "cameras.json").expect("inria");
        assert_eq!((kind, read.len()), (CameraFormat::Inria, cams.len()));
        let npy = npy_bytes(
            &f8_header(&format!("({}, 17)", cams.len())),
            &llff_rows(&cams),
        );
        let (kind, read) = read_cameras_bytes(&npy, "poses_bounds.npy").expect("llff");
        assert_eq!((kind, read.len()), (CameraFormat::Llff, cams.len()));
        assert!(read.iter().all(|c| c.image.is_none()));
        assert!(matches!(
            read_cameras_bytes(b"hello", "x"),
            Err(SceneError::Camera(_))
        ));
    }

    // ----- real data ------------------------------------------------------------------------------

    pub(super) fn data_path(rel: &str) -> Option<PathBuf> {
        let p = Path::new(DATA).join(rel);
        if p.exists() {
            Some(p)
        } else {
            eprintln!(
                "SKIPPED: real-data test needs {} (not present)",
                p.display()
            );
            None
        }
    }

    pub(super) fn inside(c: &Camera, p: Vec2) -> bool {
        p.x >= 0.0 && p.y >= 0.0 && p.x < c.width as f32 && p.y < c.height as f32
    }
}
