//! Posed image sets a 3D-GS scene is fitted to: NeRF-synthetic folders (`transforms_train.json`,
//! `transforms_test.json`, RGBA images over a background) and LLFF folders (`poses_bounds.npy`,
//! `images_N/`, COLMAP's `sparse/0/points3D.bin`), split into training and test views the way
//! INRIA's 3D-GS splits them.

use super::FitError;
use crate::scene::Camera;
use crate::scene::camera::{read_llff_poses, read_nerf_transforms};
use crate::scene::colmap::read_points3d;
use glam::Vec3;
use image::imageops::FilterType;
use rayon::prelude::*;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// One posed image: the camera (at the image's resolution) and its pixels, RGB in [0, 1] with
/// any alpha composited over the dataset's background.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    pub image: Vec<[f32; 3]>,
}

/// Which convention the folder follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DatasetKind {
    /// NeRF synthetic (Blender): `transforms_{train,test}.json`.
    Blender,
    /// LLFF: `poses_bounds.npy`, every `hold`-th image held out for testing.
    Llff,
}

/// Where the Gaussians start.
#[derive(Clone, Debug)]
pub enum Init {
    /// `count` points uniform in the box (INRIA's start for synthetic scenes, which have no
    /// structure-from-motion points).
    RandomBox { min: [f32; 3], max: [f32; 3] },
    /// The structure-from-motion points with their colours.
    Points {
        xyz: Vec<[f32; 3]>,
        rgb: Vec<[f32; 3]>,
    },
}

/// A dataset ready to fit.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub kind: DatasetKind,
    pub train: Vec<View>,
    pub test: Vec<View>,
    /// The colour behind the scene, in training and evaluation.
    pub background: [f32; 3],
    pub init: Init,
    /// INRIA's `cameras_extent`: 1.1 × the largest distance of a training camera from their mean
    /// centre; learning rates and densification thresholds scale with it.
    pub extent: f32,
    /// SHA-256 over the camera files, the images read and the options that shaped them: a
    /// checkpoint only resumes on the dataset it was made from.
    pub fingerprint: String,
}

/// How to read a dataset.
#[derive(Clone, Debug, Default)]
pub struct DataOptions {
    /// Resize every image so that its longer side is at most this many pixels.
    pub max_side: Option<u32>,
    /// Override the dataset's background (white for Blender, black for LLFF).
    pub background: Option<[f32; 3]>,
    /// LLFF image folder (default: the first of `images_8`, `images_4`, `images_2`, `images`).
    pub images: Option<String>,
    /// LLFF: every `hold`-th view (index % hold == 0) is a test view (default 8, INRIA's
    /// `llffhold`).
    pub llff_hold: Option<usize>,
}

/// INRIA's random start box for synthetic scenes: [−1.3, 1.3]³.
const BLENDER_BOX: f32 = 1.3;

impl Dataset {
    /// Reads the dataset in `dir` (kind from the files it holds).
    pub fn open(dir: &Path, opts: &DataOptions) -> Result<Self, FitError> {
        if dir.join("transforms_train.json").is_file() {
            open_blender(dir, opts)
        } else if dir.join("poses_bounds.npy").is_file() {
            open_llff(dir, opts)
        } else {
            Err(FitError::Data(format!(
                "{} holds neither transforms_train.json (NeRF synthetic) nor poses_bounds.npy \
                 (LLFF)",
                dir.display()
            )))
        }
    }

    /// A dataset made in memory (tests, benchmarks): `extent` and the fingerprint computed as
    /// for files.
    pub fn from_views(
        kind: DatasetKind,
        train: Vec<View>,
        test: Vec<View>,
        background: [f32; 3],
        init: Init,
    ) -> Result<Self, FitError> {
        if train.is_empty() {
            return Err(FitError::Data("no training views".into()));
        }
        let mut h = Sha256::new();
        for v in train.iter().chain(&test) {
            h.update(serde_json::to_vec(&v.camera).unwrap_or_default());
            for p in &v.image {
                for c in p {
                    h.update(c.to_le_bytes());
                }
            }
        }
        h.update(format!("{kind:?} {background:?}"));
        let extent = cameras_extent(&train);
        Ok(Self {
            kind,
            train,
            test,
            background,
            init,
            extent,
            fingerprint: hex::encode(h.finalize()),
        })
    }

    /// Image size of the first training view.
    pub fn size(&self) -> (u32, u32) {
        let c = &self.train[0].camera;
        (c.width, c.height)
    }
}

fn cameras_extent(views: &[View]) -> f32 {
    let centres: Vec<Vec3> = views.iter().map(|v| v.camera.center()).collect();
    let mean = centres.iter().copied().sum::<Vec3>() / centres.len().max(1) as f32;
    let diag = centres
        .iter()
        .map(|c| c.distance(mean))
        .fold(0.0f32, f32::max);
    // One camera (or cameras at one spot) would make every threshold 0.
    1.1 * diag.max(1e-3)
}

fn open_blender(dir: &Path, opts: &DataOptions) -> Result<Dataset, FitError> {
    let background = opts.background.unwrap_or([1.0; 3]);
    let train_cams = read_nerf_transforms(&dir.join("transforms_train.json"))?;
    let test_path = dir.join("transforms_test.json");
    let test_cams = if test_path.is_file() {
        read_nerf_transforms(&test_path)?
    } else {
        Vec::new()
    };
    let mut h = Sha256::new();
    hash_file(&mut h, &dir.join("transforms_train.json"))?;
    if test_path.is_file() {
        hash_file(&mut h, &test_path)?;
    }
    let train = load_views(train_cams, background, opts.max_side, &mut h)?;
    let test = load_views(test_cams, background, opts.max_side, &mut h)?;
    h.update(format!("blender {background:?} {:?}", opts.max_side));
    let extent = cameras_extent(&train);
    Ok(Dataset {
        kind: DatasetKind::Blender,
        train,
        test,
        background,
        init: Init::RandomBox {
            min: [-BLENDER_BOX; 3],
            max: [BLENDER_BOX; 3],
        },
        extent,
        fingerprint: hex::encode(h.finalize()),
    })
}

fn open_llff(dir: &Path, opts: &DataOptions) -> Result<Dataset, FitError> {
    let background = opts.background.unwrap_or([0.0; 3]);
    let hold = opts.llff_hold.unwrap_or(8);
    if hold < 2 {
        return Err(FitError::Data(format!(
            "llff_hold {hold}: at least every second view must be a training view"
        )));
    }
    let images = match &opts.images {
        Some(name) => dir.join(name),
        None => ["images_8", "images_4", "images_2", "images"]
            .iter()
            .map(|n| dir.join(n))
            .find(|p| p.is_dir())
            .ok_or_else(|| {
                FitError::Data(format!(
                    "{} has no images_N/ or images/ folder",
                    dir.display()
                ))
            })?,
    };
    let poses = dir.join("poses_bounds.npy");
    let cams = read_llff_poses(&poses, Some(&images))?;
    let points_path = ["sparse/0/points3D.bin", "sparse/0/points3D.txt"]
        .iter()
        .map(|p| dir.join(p))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            FitError::Data(format!(
                "{} has no sparse/0/points3D.bin (COLMAP's points, where the Gaussians start)",
                dir.display()
            ))
        })?;
    let points = read_points3d(&points_path)?;
    if points.xyz.is_empty() {
        return Err(FitError::Data(format!(
            "{}: no points",
            points_path.display()
        )));
    }
    let mut h = Sha256::new();
    hash_file(&mut h, &poses)?;
    hash_file(&mut h, &points_path)?;
    let (test_cams, train_cams): (Vec<_>, Vec<_>) = cams
        .into_iter()
        .enumerate()
        .partition(|(i, _)| i % hold == 0);
    let strip = |v: Vec<(usize, Camera)>| v.into_iter().map(|(_, c)| c).collect::<Vec<_>>();
    let train = load_views(strip(train_cams), background, opts.max_side, &mut h)?;
    let test = load_views(strip(test_cams), background, opts.max_side, &mut h)?;
    h.update(format!(
        "llff {background:?} {:?} {hold} {}",
        opts.max_side,
        images.display()
    ));
    let extent = cameras_extent(&train);
    Ok(Dataset {
        kind: DatasetKind::Llff,
        train,
        test,
        background,
        init: Init::Points {
            xyz: points.xyz,
            rgb: points
                .rgb
                .iter()
                .map(|c| c.map(|v| f32::from(v) / 255.0))
                .collect(),
        },
        extent,
        fingerprint: hex::encode(h.finalize()),
    })
}

fn hash_file(h: &mut Sha256, path: &Path) -> Result<(), FitError> {
    let bytes = std::fs::read(path).map_err(|e| FitError::io(path, e))?;
    h.update(&bytes);
    Ok(())
}

/// Decodes every camera's image (in parallel), composites alpha over `background`, resizes to
/// `max_side` and sizes the camera to match; the files' bytes go into `h` in camera order.
fn load_views(
    cams: Vec<Camera>,
    background: [f32; 3],
    max_side: Option<u32>,
    h: &mut Sha256,
) -> Result<Vec<View>, FitError> {
    let loaded: Vec<Result<(View, [u8; 32]), FitError>> =
        cams.into_par_iter()
            .map(|cam| {
                let path: PathBuf = cam.image.clone().ok_or_else(|| {
                    FitError::Data(format!("camera '{}' names no image", cam.name))
                })?;
                let bytes = std::fs::read(&path).map_err(|e| FitError::io(&path, e))?;
                let digest: [u8; 32] = Sha256::digest(&bytes).into();
                let img = crate::image_file::open(&path)
                    .map_err(|e| FitError::Data(format!("{}: {e}", path.display())))?;
                let (view, _) = view_from_image(cam, &img, background, max_side);
                Ok((view, digest))
            })
            .collect();
    let mut views = Vec::with_capacity(loaded.len());
    for r in loaded {
        let (v, d) = r?;
        h.update(d);
        views.push(v);
    }
    Ok(views)
}

/// The view of `cam` with image `img`: alpha composited over `background` (in the image's own
/// 8-bit values, as INRIA does), then resized with a bicubic filter so that the longer side is
/// at most `max_side`; the camera's intrinsics follow the image actually used. Returns the view
/// and whether it was resized.
pub fn view_from_image(
    cam: Camera,
    img: &image::DynamicImage,
    background: [f32; 3],
    max_side: Option<u32>,
) -> (View, bool) {
    let rgba = img.to_rgba32f();
    let (w, h) = rgba.dimensions();
    let mut rgb = image::Rgb32FImage::new(w, h);
    for (o, p) in rgb.pixels_mut().zip(rgba.pixels()) {
        let a = p[3];
        *o = image::Rgb(std::array::from_fn(|c| {
            p[c] * a + background[c] * (1.0 - a)
        }));
    }
    let side = w.max(h);
    let (rgb, resized) = match max_side {
        Some(m) if m > 0 && side > m => {
            let s = f64::from(m) / f64::from(side);
            let nw = ((f64::from(w) * s).round() as u32).max(1);
            let nh = ((f64::from(h) * s).round() as u32).max(1);
            (
                image::imageops::resize(&rgb, nw, nh, FilterType::CatmullRom),
                true,
            )
        }
        _ => (rgb, false),
    };
    let (nw, nh) = rgb.dimensions();
    let camera = if (nw, nh) == (cam.width, cam.height) {
        cam
    } else {
        cam.resized(nw, nh)
    };
    let image = rgb
        .pixels()
        .map(|p| p.0.map(|v| v.clamp(0.0, 1.0)))
        .collect();
    (View { camera, image }, resized)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(rel: &str) -> Option<PathBuf> {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/data/datasets")
            .join(rel);
        if p.exists() {
            Some(p)
        } else {
            eprintln!("SKIPPED: {} is missing", p.display());
            None
        }
    }

    #[test]
    fn alpha_is_composited_over_the_background_and_the_camera_follows_a_resize() {
        let mut img = image::RgbaImage::new(8, 4);
        img.put_pixel(0, 0, image::Rgba([255, 0, 0, 255]));
        img.put_pixel(1, 0, image::Rgba([255, 0, 0, 0]));
        let cam = Camera::from_pose(
            "c",
            8,
            4,
            10.0,
            10.0,
            4.0,
            2.0,
            glam::Mat3::IDENTITY,
            Vec3::new(0.0, 0.0, -3.0),
        );
        let dynimg = image::DynamicImage::ImageRgba8(img);
        let (v, resized) = view_from_image(cam.clone(), &dynimg, [0.0, 1.0, 0.0], None);
        assert!(!resized);
        assert_eq!(v.image[0], [1.0, 0.0, 0.0]);
        assert_eq!(v.image[1], [0.0, 1.0, 0.0]);
        let (v, resized) = view_from_image(cam, &dynimg, [1.0; 3], Some(4));
        assert!(resized);
        assert_eq!((v.camera.width, v.camera.height), (4, 2));
        assert_eq!(v.image.len(), 8);
        assert_eq!(v.camera.fx, 5.0);
        assert_eq!(v.camera.cx, 2.0);
    }

    #[test]
    fn lego_splits_into_its_training_and_test_views_on_white() {
        let Some(dir) = data("nerf_synthetic_lego") else {
            return;
        };
        let ds = Dataset::open(
            &dir,
            &DataOptions {
                max_side: Some(100),
                ..DataOptions::default()
            },
        )
        .unwrap();
        assert_eq!(ds.kind, DatasetKind::Blender);
        assert_eq!((ds.train.len(), ds.test.len()), (100, 25));
        assert_eq!(ds.size(), (100, 100));
        assert_eq!(ds.background, [1.0; 3]);
        // The corners are empty background: white after compositing.
        assert!(ds.train[0].image[0].iter().all(|&c| c > 0.99));
        // The cameras sit 4 units from the object on its upper hemisphere: 1.1 × their largest
        // distance from their mean centre.
        assert!((4.4..6.0).contains(&ds.extent), "{}", ds.extent);
    }

    #[test]
    fn fern_holds_out_every_eighth_view_and_starts_from_colmap_points() {
        let Some(dir) = data("llff_fern") else {
            return;
        };
        let ds = Dataset::open(&dir, &DataOptions::default()).unwrap();
        assert_eq!(ds.kind, DatasetKind::Llff);
        assert_eq!((ds.train.len(), ds.test.len()), (17, 3));
        assert_eq!(ds.test[1].camera.name, "image008");
        assert_eq!(ds.background, [0.0; 3]);
        match &ds.init {
            Init::Points { xyz, rgb } => assert_eq!((xyz.len(), rgb.len()), (10_091, 10_091)),
            other => panic!("{other:?}"),
        }
        // The COLMAP points lie in front of the cameras they were seen by.
        let Init::Points { xyz, .. } = &ds.init else {
            unreachable!()
        };
        let cam = &ds.train[0].camera;
        let seen = xyz
            .iter()
            .filter(|p| {
                cam.project(Vec3::from(**p)).is_some_and(|q| {
                    q.x >= 0.0 && q.y >= 0.0 && q.x < cam.width as f32 && q.y < cam.height as f32
                })
            })
            .count();
        assert!(seen > xyz.len() / 2, "{seen} of {} in view", xyz.len());
    }

    #[test]
    fn a_folder_of_neither_kind_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let err = Dataset::open(dir.path(), &DataOptions::default()).unwrap_err();
        assert!(err.to_string().contains("transforms_train.json"), "{err}");
    }
}
