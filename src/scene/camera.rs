//! Pinhole cameras and the camera files people ship with scenes.
//!
//! Convention (OpenCV / COLMAP / INRIA): camera space has x right, y down, z forward; a world
//! point `p` maps to camera space as `R·p + t`, then to pixels as
//! `(fx·x/z + cx, fy·y/z + cy)`; pixel `(i, j)` covers `[i, i+1) × [j, j+1)`, so its centre is at
//! `(i + 0.5, j + 0.5)` (with `cx = W/2` this matches the INRIA rasterizer exactly).

use glam::{Mat3, Vec3};
use std::path::PathBuf;

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
