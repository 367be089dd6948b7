//! INRIA gaussian-splatting `cameras.json` (an array of cameras).

use super::{Camera, Intrinsics, camera_from_c2w, read_limited, strip_bom};
use crate::scene::SceneError;
use glam::{DMat3, DVec3};
use std::path::Path;

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

pub(super) fn inria_from_json(json: &[u8], path: &Path) -> Result<Vec<Camera>, SceneError> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::read_cameras;
    use crate::scene::camera::tests::{
        assert_same_projection, data_path, inria_json, inside, sample_cameras, write,
    };
    use glam::{Vec2, Vec3};
    use serde_json::json;

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
}
