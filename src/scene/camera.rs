//! Pinhole cameras and the camera files people ship with scenes.
//!
//! Convention (OpenCV / COLMAP / INRIA): camera space has x right, y down, z forward; a world
//! point `p` maps to camera space as `R·p + t`, then to pixels as
//! `(fx·x/z + cx, fy·y/z + cy)`; pixel `(i, j)` covers `[i, i+1) × [j, j+1)`, so its centre is at
//! `(i + 0.5, j + 0.5)` (with `cx = W/2` this matches the INRIA rasterizer exactly).

use crate::scene::SceneError;
use glam::{DMat3, DVec3, Mat3, Vec2, Vec3};
use std::io::Read;
use std::path::{Path, PathBuf};

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

// ----- INRIA cameras.json --------------------------------------------------------------------

/// One entry of INRIA's `cameras.json` (written by `utils/camera_utils.py::camera_to_JSON`).
#[derive(serde::Deserialize)]
struct InriaCamera {
    img_name: String,
    width: u32,
    height: u32,
    /// Camera centre in world space.
    position: [f64; 3],
    /// Camera → world rotation, row-major: INRIA writes the rows of `inv([Rᵀ_c2w | T])[:3, :3]`,
    /// i.e. of the camera → world rotation, so its columns are the camera axes in world space.
    rotation: [[f64; 3]; 3],
    fx: f64,
    fy: f64,
}

/// Reads INRIA gaussian-splatting's `cameras.json`: an array of
/// `{id, img_name, width, height, position, rotation, fx, fy}` where `position` is the camera
/// centre and `rotation` the camera → world rotation (rows as written by numpy; columns are the
/// camera's x right, y down, z forward axes in world space). The principal point is the image
/// centre (INRIA's rasterizer has no other). `Camera::image` is left empty: the file names the
/// image but not its folder.
pub fn read_inria_cameras(path: &Path) -> Result<Vec<Camera>, SceneError> {
    let bytes = read_limited(path)?;
    inria_from_json(strip_bom(&bytes), path)
}

fn inria_from_json(json: &[u8], path: &Path) -> Result<Vec<Camera>, SceneError> {
    let entries: Vec<InriaCamera> = serde_json::from_slice(json).map_err(|e| {
        SceneError::Camera(format!(
            "{}: not an INRIA cameras.json: {e}",
            path.display()
        ))
    })?;
    if entries.is_empty() {
        return Err(SceneError::Camera(format!(
            "{}: the camera list is empty",
            path.display()
        )));
    }
    entries
        .into_iter()
        .map(|e| {
            let intr = Intrinsics {
                width: e.width,
                height: e.height,
                fx: e.fx,
                fy: e.fy,
                cx: 0.5 * f64::from(e.width),
                cy: 0.5 * f64::from(e.height),
            };
            let c2w = DMat3::from_cols_array_2d(&e.rotation).transpose();
            camera_from_c2w(e.img_name, intr, c2w, DVec3::from_array(e.position))
        })
        .collect()
}

// ----- NeRF / nerfstudio transforms.json ------------------------------------------------------

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
/// every frame must give `w` and `h`; see [`read_cameras_bytes`]).
fn nerf_from_json(
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

/// Width and height from an image file's header (PNG or JPEG, detected by content).
fn image_size(path: &Path) -> Result<(u32, u32), String> {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| format!("cannot open image {}: {e}", path.display()))?
        .into_dimensions()
        .map_err(|e| format!("cannot read the size of image {}: {e}", path.display()))
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

// ----- LLFF poses_bounds.npy ---------------------------------------------------------------

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

fn llff_from_bytes(
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

// ----- NPY -------------------------------------------------------------------------------------

const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// A parsed NPY array of floats (C order), widened to f64.
#[derive(Debug)]
struct Npy {
    shape: Vec<usize>,
    data: Vec<f64>,
}

/// Strict NPY parser: format versions 1.0, 2.0 and 3.0; header dict with exactly `descr`
/// (`'<f8'` or `'<f4'`), `fortran_order` (`False`) and `shape`; the data must be exactly the
/// size the shape implies. Sizes are computed with checked arithmetic and compared with the
/// bytes present before anything is allocated.
fn parse_npy(bytes: &[u8]) -> Result<Npy, SceneError> {
    let header_err = |msg: &str| SceneError::Header(format!("NPY: {msg}"));
    if !bytes.starts_with(NPY_MAGIC) {
        return Err(header_err("missing the \\x93NUMPY magic: not an NPY file"));
    }
    let (major, minor) = match bytes.get(6..8) {
        Some(&[a, b]) => (a, b),
        _ => return Err(header_err("file ends inside the preamble")),
    };
    let len_bytes = match (major, minor) {
        (1, 0) => 2,
        (2, 0) | (3, 0) => 4,
        _ => {
            return Err(SceneError::Unsupported(format!(
                "NPY format version {major}.{minor}"
            )));
        }
    };
    let prefix = 8 + len_bytes;
    let header_len = match bytes.get(8..prefix) {
        Some(&[a, b]) => u64::from(u16::from_le_bytes([a, b])),
        Some(&[a, b, c, d]) => u64::from(u32::from_le_bytes([a, b, c, d])),
        _ => return Err(header_err("file ends inside the preamble")),
    };
    let actual = bytes.len() as u64;
    let data_start = (prefix as u64)
        .checked_add(header_len)
        .ok_or_else(|| SceneError::Overflow("NPY header length".into()))?;
    if data_start > actual {
        return Err(SceneError::Truncated {
            expected: data_start,
            actual,
        });
    }
    // data_start ≤ bytes.len(), so it fits in usize.
    let data_start = data_start as usize;
    let header = std::str::from_utf8(&bytes[prefix..data_start])
        .map_err(|_| header_err("header is not text"))?;
    let dict = parse_npy_header(header)?;

    let item = match dict.descr.as_str() {
        "<f8" => 8u64,
        "<f4" => 4u64,
        other => {
            return Err(SceneError::Unsupported(format!(
                "NPY dtype '{other}' (only little-endian float64 '<f8' and float32 '<f4' are)"
            )));
        }
    };
    if dict.fortran_order {
        return Err(SceneError::Unsupported("NPY array in Fortran order".into()));
    }
    let overflow = || SceneError::Overflow(format!("NPY shape {:?}", dict.shape));
    let count = dict
        .shape
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d))
        .ok_or_else(overflow)?;
    let data_bytes = count.checked_mul(item).ok_or_else(overflow)?;
    let expected = (data_start as u64)
        .checked_add(data_bytes)
        .ok_or_else(overflow)?;
    if expected > actual {
        return Err(SceneError::Truncated { expected, actual });
    }
    if expected < actual {
        return Err(SceneError::Corrupt(format!(
            "NPY: {} bytes after the array data that the shape {:?} does not account for",
            actual - expected,
            dict.shape
        )));
    }
    // The data fits in the file, so every size below fits in usize.
    let shape = dict.shape.iter().map(|&d| d as usize).collect();
    let raw = &bytes[data_start..];
    let data = if item == 8 {
        raw.chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect()
    } else {
        raw.chunks_exact(4)
            .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
            .collect()
    };
    Ok(Npy { shape, data })
}

/// The three keys of an NPY header dict.
#[derive(Debug, PartialEq)]
struct NpyHeader {
    descr: String,
    fortran_order: bool,
    shape: Vec<u64>,
}

/// Parses the Python dict literal of an NPY header, e.g.
/// `{'descr': '<f8', 'fortran_order': False, 'shape': (20, 17), }` (padded with spaces and a
/// newline). Exactly the keys `descr`, `fortran_order` and `shape`, each once.
fn parse_npy_header(text: &str) -> Result<NpyHeader, SceneError> {
    let err = |msg: String| SceneError::Header(format!("NPY header {text:?}: {msg}"));
    let mut p = HeaderLexer {
        s: text.trim_end().as_bytes(),
        i: 0,
    };
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    p.expect(b'{').map_err(&err)?;
    loop {
        p.skip_ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string().map_err(&err)?;
        p.expect(b':').map_err(&err)?;
        p.skip_ws();
        let dup = || err(format!("key '{key}' appears twice"));
        match key.as_str() {
            "descr" => {
                if descr.replace(p.string().map_err(&err)?).is_some() {
                    return Err(dup());
                }
            }
            "fortran_order" => {
                let v = if p.eat_word("True") {
                    true
                } else if p.eat_word("False") {
                    false
                } else {
                    return Err(err("fortran_order must be True or False".into()));
                };
                if fortran.replace(v).is_some() {
                    return Err(dup());
                }
            }
            "shape" => {
                if shape.replace(p.tuple().map_err(&err)?).is_some() {
                    return Err(dup());
                }
            }
            other => return Err(err(format!("unexpected key '{other}'"))),
        }
        p.skip_ws();
        if p.eat(b',') {
            continue;
        }
        p.expect(b'}').map_err(&err)?;
        break;
    }
    p.skip_ws();
    if p.i != p.s.len() {
        return Err(err("text after the closing brace".into()));
    }
    match (descr, fortran, shape) {
        (Some(descr), Some(fortran_order), Some(shape)) => Ok(NpyHeader {
            descr,
            fortran_order,
            shape,
        }),
        _ => Err(err(
            "needs the keys 'descr', 'fortran_order' and 'shape'".into()
        )),
    }
}

/// A cursor over the header text.
struct HeaderLexer<'a> {
    s: &'a [u8],
    i: usize,
}

impl HeaderLexer<'_> {
    fn skip_ws(&mut self) {
        while self.s.get(self.i).is_some_and(|b| b.is_ascii_whitespace()) {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        self.skip_ws();
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected '{}' at byte {}", c as char, self.i))
        }
    }

    fn eat_word(&mut self, w: &str) -> bool {
        let end = self.i + w.len();
        let next_is_ident = self
            .s
            .get(end)
            .is_some_and(|b| b.is_ascii_alphanumeric() || *b == b'_');
        if self.s.get(self.i..end) == Some(w.as_bytes()) && !next_is_ident {
            self.i = end;
            true
        } else {
            false
        }
    }

    /// A single- or double-quoted string without escapes.
    fn string(&mut self) -> Result<String, String> {
        self.skip_ws();
        let quote = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a quoted string at byte {}", self.i)),
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&b| b == quote)
            .ok_or_else(|| "unterminated string".to_string())?;
        let body = &self.s[start..start + len];
        if body.contains(&b'\\') {
            return Err("escapes in strings are not supported".into());
        }
        self.i = start + len + 1;
        Ok(String::from_utf8_lossy(body).into_owned())
    }

    /// A tuple of non-negative integers: `()`, `(5,)`, `(20, 17)` (Python 2's `20L` accepted).
    fn tuple(&mut self) -> Result<Vec<u64>, String> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        let mut commas = 0;
        loop {
            self.skip_ws();
            if self.eat(b')') {
                break;
            }
            let start = self.i;
            while self.s.get(self.i).is_some_and(u8::is_ascii_digit) {
                self.i += 1;
            }
            if start == self.i {
                return Err(format!("expected a dimension at byte {start}"));
            }
            // The digits are ASCII, so this is valid UTF-8; parse fails only on overflow.
            let digits = String::from_utf8_lossy(&self.s[start..self.i]);
            let d = digits
                .parse::<u64>()
                .map_err(|_| format!("dimension {digits} does not fit in 64 bits"))?;
            dims.push(d);
            self.eat(b'L');
            self.skip_ws();
            if self.eat(b',') {
                commas += 1;
                continue;
            }
            self.expect(b')')?;
            break;
        }
        if dims.len() == 1 && commas == 0 {
            // `(5)` is an int in Python, not a tuple.
            return Err("a one-dimensional shape needs a trailing comma: (n,)".into());
        }
        Ok(dims)
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
    fn sample_cameras(square_pixels: bool, centred: bool) -> Vec<Camera> {
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
    fn assert_same_projection(a: &Camera, b: &Camera) {
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

    fn write(path: &Path, bytes: impl AsRef<[u8]>) {
        std::fs::write(path, bytes).expect("write test file");
    }

    fn write_png(path: &Path, w: u32, h: u32) {
        image::RgbImage::new(w, h)
            .save(path)
            .expect("write test png");
    }

    // ----- test-only writers ------------------------------------------------------------------

    /// INRIA's `camera_to_JSON`: position = camera centre, rotation = rows of camera → world.
    fn inria_json(cams: &[Camera]) -> String {
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

    /// An NPY v1.0 file with a C-order `<f8` array.
    fn npy_bytes(header: &str, data: &[f64]) -> Vec<u8> {
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

    fn f8_header(shape: &str) -> String {
        format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}")
    }

    /// LLFF rows `[down right back | centre | h w f] near far` for square-pixel cameras.
    fn llff_rows(cams: &[Camera]) -> Vec<f64> {
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

    // ----- INRIA --------------------------------------------------------------------------------

    #[test]
    fn inria_round_trip() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cams = sample_cameras(false, true);
        let path = dir.path().join("cameras.json");
        write(&path, inria_json(&cams));
        let read = read_inria_cameras(&path).expect("read");
        assert_eq!(read.len(), cams.len());
        for (a, b) in cams.iter().zip(&read) {
            assert_eq!(a.name, b.name);
            assert_same_projection(a, b);
        }
        let via_dispatch = read_cameras(&path).expect("dispatch");
        assert_eq!(via_dispatch, read);
        let via_dir = read_cameras(dir.path()).expect("dispatch on folder");
        assert_eq!(via_dir, read);
    }

    #[test]
    fn inria_hand_computed_pose() {
        // Camera at (0, 0, −5) looking along +z, rolled 90°: its right is world +y and its
        // down is world −x. INRIA writes the camera → world rotation's rows.
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("cameras.json");
        let doc = json!([{
            "id": 0, "img_name": "rolled", "width": 100, "height": 80,
            "position": [0.0, 0.0, -5.0],
            "rotation": [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            "fx": 50.0, "fy": 50.0
        }]);
        write(&path, doc.to_string());
        let cam = &read_inria_cameras(&path).expect("read")[0];
        assert_eq!((cam.cx, cam.cy), (50.0, 40.0));
        let o = cam.project(Vec3::ZERO).expect("origin visible");
        assert!((o - Vec2::new(50.0, 40.0)).length() < 1e-4, "{o}");
        let py = cam.project(Vec3::Y).expect("+y visible");
        assert!(
            (py - Vec2::new(60.0, 40.0)).length() < 1e-4,
            "+y world is right: {py}"
        );
        let nx = cam.project(Vec3::NEG_X).expect("−x visible");
        assert!(
            (nx - Vec2::new(50.0, 50.0)).length() < 1e-4,
            "−x world is down: {nx}"
        );
        assert!((cam.center() - Vec3::new(0.0, 0.0, -5.0)).length() < 1e-6);
    }

    #[test]
    fn inria_rejects_bad_input() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("cameras.json");
        let entry = |rot: serde_json::Value, fx: f64| {
            json!([{ "id": 0, "img_name": "a", "width": 10, "height": 10,
                     "position": [0, 0, 0], "rotation": rot, "fx": fx, "fy": 5.0 }])
            .to_string()
        };
        let cases = [
            ("[]".to_string(), "empty"),
            ("{\"frames\": 3".to_string(), "INRIA"),
            ("[{\"id\": 0}]".to_string(), "missing field"),
            (
                entry(json!([[1, 0, 0], [0, 1, 0], [0, 0, -1]]), 5.0),
                "reflection",
            ),
            (
                entry(json!([[1, 0, 0], [0, 2, 0], [0, 0, 1]]), 5.0),
                "orthonormal",
            ),
            (
                entry(json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]), -5.0),
                "focal",
            ),
        ];
        for (text, needle) in cases {
            write(&path, &text);
            let e = read_inria_cameras(&path).expect_err(&text).to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
        let missing = read_inria_cameras(&dir.path().join("nope.json")).expect_err("missing");
        assert!(matches!(missing, SceneError::Io { .. }), "{missing}");
    }

    // ----- NeRF ---------------------------------------------------------------------------------

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

    // ----- LLFF / NPY ---------------------------------------------------------------------------

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
    fn npy_accepts_variants() {
        let data: Vec<f64> = (0..6).map(f64::from).collect();
        // Version 1.0, padded to 64 bytes.
        let npy = parse_npy(&npy_bytes(&f8_header("(2, 3)"), &data)).expect("v1");
        assert_eq!((npy.shape, npy.data), (vec![2, 3], data.clone()));
        // Version 2.0, double quotes, no trailing comma, Python 2 longs, unpadded.
        let h = "{\"shape\": (2L, 3L), \"fortran_order\": False, \"descr\": \"<f8\"}\n";
        let mut v2 = b"\x93NUMPY\x02\x00".to_vec();
        v2.extend_from_slice(&(h.len() as u32).to_le_bytes());
        v2.extend_from_slice(h.as_bytes());
        for v in &data {
            v2.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(parse_npy(&v2).expect("v2").data, data);
        // Float32.
        let mut f4 = npy_bytes(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (6,), }",
            &[],
        );
        for v in &data {
            f4.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        let npy = parse_npy(&f4).expect("f4");
        assert_eq!((npy.shape, npy.data), (vec![6], data));
    }

    /// What a rejected file's error must look like.
    type ErrorCheck = fn(&SceneError) -> bool;

    #[test]
    fn npy_rejects_bad_files() {
        let row = [0.0f64; 17];
        let good = npy_bytes(&f8_header("(1, 17)"), &row);
        assert!(parse_npy(&good).is_ok());
        let header = |h: &str| npy_bytes(h, &row);
        let mut wrong_magic = good.clone();
        wrong_magic[1] = b'X';
        let mut version = good.clone();
        version[6] = 4;
        let mut long_header = good.clone();
        long_header[8..10].copy_from_slice(&u16::MAX.to_le_bytes());
        let absurd = header(&f8_header("(18446744073709551615, 17)"));
        let cases: Vec<(&str, Vec<u8>, ErrorCheck)> = vec![
            ("wrong magic", wrong_magic, |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("too short", b"\x93NUMPY\x01".to_vec(), |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("version 4.0", version, |e| {
                matches!(e, SceneError::Unsupported(_))
            }),
            ("header past end", long_header, |e| {
                matches!(e, SceneError::Truncated { .. })
            }),
            (
                "fortran order",
                header("{'descr': '<f8', 'fortran_order': True, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(m) if m.contains("Fortran")),
            ),
            (
                "int dtype",
                header("{'descr': '<i8', 'fortran_order': False, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(m) if m.contains("<i8")),
            ),
            (
                "big endian",
                header("{'descr': '>f8', 'fortran_order': False, 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Unsupported(_)),
            ),
            (
                "shape larger than data",
                header(&f8_header("(2, 17)")),
                |e| matches!(e, SceneError::Truncated { expected, actual } if expected - actual == 136),
            ),
            (
                "shape smaller than data",
                header(&f8_header("(1, 16)")),
                |e| matches!(e, SceneError::Corrupt(_)),
            ),
            ("truncated data", good[..good.len() - 3].to_vec(), |e| {
                matches!(e, SceneError::Truncated { .. })
            }),
            ("overflowing shape", absurd, |e| {
                matches!(e, SceneError::Overflow(_))
            }),
            (
                "dimension beyond u64",
                header(&f8_header("(99999999999999999999, 17)")),
                |e| matches!(e, SceneError::Header(m) if m.contains("64 bits")),
            ),
            (
                "missing key",
                header("{'descr': '<f8', 'shape': (1, 17), }"),
                |e| matches!(e, SceneError::Header(_)),
            ),
            (
                "duplicate key",
                header(
                    "{'descr': '<f8', 'descr': '<f8', 'fortran_order': False, 'shape': (1, 17)}",
                ),
                |e| matches!(e, SceneError::Header(m) if m.contains("twice")),
            ),
            (
                "unknown key",
                header("{'descr': '<f8', 'fortran_order': False, 'shape': (1, 17), 'x': 1}"),
                |e| matches!(e, SceneError::Header(_)),
            ),
            ("not a tuple", header(&f8_header("(17)")), |e| {
                matches!(e, SceneError::Header(_))
            }),
            ("negative", header(&f8_header("(-1, 17)")), |e| {
                matches!(e, SceneError::Header(_))
            }),
            (
                "garbage after dict",
                header(&format!("{} x", f8_header("(1, 17)"))),
                |e| matches!(e, SceneError::Header(_)),
            ),
            ("not a dict", header("[1, 17]"), |e| {
                matches!(e, SceneError::Header(_))
            }),
        ];
        for (what, bytes, ok) in cases {
            match parse_npy(&bytes) {
                Ok(n) => panic!("{what}: accepted {n:?}"),
                Err(e) => assert!(ok(&e), "{what}: unexpected error {e:?}"),
            }
        }
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

    // ----- real data ------------------------------------------------------------------------------

    fn data_path(rel: &str) -> Option<PathBuf> {
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

    fn inside(c: &Camera, p: Vec2) -> bool {
        p.x >= 0.0 && p.y >= 0.0 && p.x < c.width as f32 && p.y < c.height as f32
    }

    #[test]
    fn real_udon_cameras() {
        let Some(path) = data_path("scenes/udon/cameras.json") else {
            return;
        };
        let cams = read_inria_cameras(&path).expect("read udon");
        assert_eq!(cams.len(), 11);
        let text = std::fs::read_to_string(&path).expect("read udon json");
        let raw: serde_json::Value = serde_json::from_str(&text).expect("udon json");
        // A point in the middle of the udon Gaussians (x∈(−2.3, 2.0), y∈(−5.2, −1.5),
        // z∈(11.9, 14.7)).
        let target = Vec3::new(0.0, -3.3, 13.3);
        for (i, c) in cams.iter().enumerate() {
            assert_eq!((c.width, c.height), (1888, 1061));
            assert_eq!((c.cx, c.cy), (944.0, 530.5));
            // INRIA semantics: `position` is the centre, `rotation`'s columns the camera axes.
            let num = |v: &serde_json::Value| v.as_f64().expect("number") as f32;
            let pos = Vec3::from_array(std::array::from_fn(|k| num(&raw[i]["position"][k])));
            assert!((c.center() - pos).length() < 1e-4, "{}", c.name);
            let forward = Vec3::from_array(std::array::from_fn(|k| num(&raw[i]["rotation"][k][2])));
            assert!(
                (c.rotation_mat().row(2) - forward).length() < 1e-6,
                "{}",
                c.name
            );
            // The scene is in front of every camera, 10° to 26° off its optical axis.
            let cam = c.to_camera(target);
            assert!(cam.z > 0.0, "{}: scene behind the camera", c.name);
            let off_axis = cam.normalize().z.acos().to_degrees();
            assert!(
                (9.0..27.0).contains(&off_axis),
                "{}: {off_axis}° off axis",
                c.name
            );
            // Horizontally it is inside every image. Vertically only the first four views
            // (udon0009–udon0024) contain it: the later ones, looking past the cropped udon
            // object (`point_cloud4.ply` of the source repository), see it above their top edge.
            let p = c.project(target).expect("in front");
            assert!(p.x >= 0.0 && p.x < c.width as f32, "{}: {p}", c.name);
            if i < 4 {
                assert!(inside(c, p), "{}: scene centre projects to {p}", c.name);
            }
        }
        assert_eq!(read_cameras(&path).expect("dispatch"), cams);
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
