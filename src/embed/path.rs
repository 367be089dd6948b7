//! Views along the capture path: cameras interpolated between consecutive training cameras.
//!
//! A camera file is a capture path (a video's frames, a scan's stops), and the views a dispute
//! is likeliest to render lie along it and between its stops. A watermark written through the
//! stops alone is written for those exact views: on udon (11 cameras 7.2° apart, every 4th held
//! out) the held-out cameras read 95.3 % of a 32-bit payload where the training stops read 100 %,
//! and 98.4 % with the path's cameras (docs/RESULTS.md, "Views along the capture path"). [`path_cameras`] adds `per_gap` cameras in each gap between consecutive
//! cameras — centre interpolated linearly, orientation by spherical interpolation, intrinsics
//! linearly — so the finetuning writes the message for the path, not its stops.
//!
//! A gap is skipped when its two cameras are not neighbours on a path: another resolution,
//! a turn of more than [`PathConfig::max_turn_deg`] (the orbits of the service and the CLI
//! change elevation by 25–80° from one view to the next: a camera in between may look at
//! nothing, as the turned copies of `extra_views` did on udon), or a step longer than
//! [`PathConfig::max_step`] × the median step. At most [`PathConfig::max_total`] cameras are
//! added in all, the widest gaps first (each view's target image is held in memory for the whole
//! finetuning, and a dense capture — a video's frames — needs no filling in).

use glam::{Mat3, Quat};
use serde::{Deserialize, Serialize};

use crate::scene::Camera;

/// Which gaps of a camera path get interpolated cameras, and how many.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PathConfig {
    /// Cameras added in each gap, evenly at t = k / (per_gap + 1); 0 turns the path off.
    pub per_gap: usize,
    /// A gap whose cameras' orientations differ by more than this (degrees) is skipped.
    pub max_turn_deg: f32,
    /// A gap longer than this many times the median distance between consecutive cameras is
    /// skipped.
    pub max_step: f32,
    /// Most path cameras in all: when the gaps would get more, the widest turns get theirs
    /// first (whole gaps, `per_gap` each; ties in path order).
    pub max_total: usize,
}

impl Default for PathConfig {
    fn default() -> Self {
        Self {
            per_gap: 2,
            max_turn_deg: 20.0,
            max_step: 2.5,
            max_total: 64,
        }
    }
}

impl PathConfig {
    /// Most cameras a gap may get.
    pub const MAX_PER_GAP: usize = 16;
    /// Most path cameras [`Self::max_total`] may allow.
    pub const MAX_TOTAL: usize = 1000;

    /// Checks the ranges: `per_gap` ≤ [`Self::MAX_PER_GAP`], the limits finite and positive.
    pub fn validate(&self) -> Result<(), String> {
        if self.per_gap > Self::MAX_PER_GAP {
            return Err(format!(
                "path.per_gap is {}; at most {}",
                self.per_gap,
                Self::MAX_PER_GAP
            ));
        }
        if !(self.max_turn_deg.is_finite() && self.max_turn_deg > 0.0 && self.max_turn_deg <= 180.0)
        {
            return Err(format!(
                "path.max_turn_deg must be in (0, 180], got {}",
                self.max_turn_deg
            ));
        }
        if self.max_total > Self::MAX_TOTAL {
            return Err(format!(
                "path.max_total is {}; at most {}",
                self.max_total,
                Self::MAX_TOTAL
            ));
        }
        if !(self.max_step.is_finite() && self.max_step > 0.0) {
            return Err(format!(
                "path.max_step must be finite and positive, got {}",
                self.max_step
            ));
        }
        Ok(())
    }
}

/// The cameras `cfg.per_gap` interpolates in each gap of `cameras` (consecutive pairs, in the
/// order given) that passes the gap rules of [`PathConfig`]; the training cameras themselves
/// are not included. Named `"{a}~{b}#{k}"`.
pub fn path_cameras(cameras: &[Camera], cfg: &PathConfig) -> Vec<Camera> {
    if cfg.per_gap == 0 || cameras.len() < 2 {
        return Vec::new();
    }
    let steps: Vec<f32> = cameras
        .windows(2)
        .map(|w| w[0].center().distance(w[1].center()))
        .collect();
    let mut sorted = steps.clone();
    sorted.sort_by(f32::total_cmp);
    let median = sorted[sorted.len() / 2];
    // The gaps of the path (index, turn in degrees).
    let mut gaps: Vec<(usize, f32)> = cameras
        .windows(2)
        .zip(&steps)
        .enumerate()
        .filter_map(|(i, (w, &step))| {
            let (a, b) = (&w[0], &w[1]);
            let turn = orientation(a).angle_between(orientation(b)).to_degrees();
            (a.width == b.width
                && a.height == b.height
                && turn <= cfg.max_turn_deg
                && step <= cfg.max_step * median)
                .then_some((i, turn))
        })
        .collect();
    let keep = cfg.max_total / cfg.per_gap;
    if gaps.len() > keep {
        // The widest turns first; the sort is stable, so ties keep the path's order.
        gaps.sort_by(|x, y| y.1.total_cmp(&x.1));
        gaps.truncate(keep);
        gaps.sort_by_key(|g| g.0);
    }
    let mut out = Vec::new();
    for (i, _) in gaps {
        let (a, b) = (&cameras[i], &cameras[i + 1]);
        let (qa, qb) = (orientation(a), orientation(b));
        let (ca, cb) = (a.center(), b.center());
        let lerp = |x: f32, y: f32, t: f32| x + (y - x) * t;
        for k in 1..=cfg.per_gap {
            let t = k as f32 / (cfg.per_gap + 1) as f32;
            out.push(Camera::from_pose(
                format!("{}~{}#{k}", a.name, b.name),
                a.width,
                a.height,
                lerp(a.fx, b.fx, t),
                lerp(a.fy, b.fy, t),
                lerp(a.cx, b.cx, t),
                lerp(a.cy, b.cy, t),
                Mat3::from_quat(qa.slerp(qb, t)),
                ca.lerp(cb, t),
            ));
        }
    }
    out
}

/// A camera's camera → world rotation as a unit quaternion.
fn orientation(c: &Camera) -> Quat {
    Quat::from_mat3(&c.rotation_mat().transpose()).normalize()
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    /// A camera at `center` looking at the origin (up −y, OpenCV axes).
    fn looking_at_origin(name: &str, center: Vec3, width: u32) -> Camera {
        let z = (-center).normalize();
        let x = Vec3::Y.cross(z).normalize();
        let y = z.cross(x);
        Camera::from_pose(
            name,
            width,
            64,
            80.0,
            80.0,
            width as f32 / 2.0,
            32.0,
            Mat3::from_cols(x, y, z),
            center,
        )
    }

    /// Cameras on a circle of radius 4 at `degrees` of azimuth.
    fn arc(degrees: &[f32]) -> Vec<Camera> {
        degrees
            .iter()
            .map(|&d| {
                let r = d.to_radians();
                looking_at_origin(
                    &format!("c{d}"),
                    Vec3::new(4.0 * r.sin(), 0.0, -4.0 * r.cos()),
                    64,
                )
            })
            .collect()
    }

    #[test]
    fn a_path_camera_sits_between_its_neighbours_and_still_looks_at_the_subject() {
        let cams = arc(&[0.0, 9.0]);
        let path = path_cameras(&cams, &PathConfig::default());
        assert_eq!(path.len(), 2);
        assert_eq!(path[0].name, "c0~c9#1");
        for (k, c) in path.iter().enumerate() {
            let t = (k + 1) as f32 / 3.0;
            let want = cams[0].center().lerp(cams[1].center(), t);
            assert!(c.center().distance(want) < 1e-4, "{:?}", c.center());
            // The origin stays on the optical axis: the orientation is interpolated with the
            // position (both cameras look at it, so every camera between does, up to the
            // chord's small departure from the arc).
            let p = c.project(Vec3::ZERO).expect("in front");
            assert!(
                (p.x - 32.0).abs() < 0.5 && (p.y - 32.0).abs() < 0.5,
                "{p:?}"
            );
        }
        // The endpoints are the cameras themselves.
        let ends = PathConfig {
            per_gap: 1,
            ..PathConfig::default()
        };
        let mid = &path_cameras(&cams, &ends)[0];
        let turn = orientation(mid).angle_between(orientation(&cams[0]));
        assert!(
            (turn.to_degrees() - 4.5).abs() < 0.01,
            "{}",
            turn.to_degrees()
        );
    }

    #[test]
    fn gaps_that_are_not_neighbours_on_a_path_are_skipped() {
        // 9° steps, then a 30° turn (an orbit's step), then 9° again.
        let cams = arc(&[0.0, 9.0, 39.0, 48.0]);
        let path = path_cameras(&cams, &PathConfig::default());
        let names: Vec<&str> = path.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["c0~c9#1", "c0~c9#2", "c39~c48#1", "c39~c48#2"]);
        // Another resolution ends the path too.
        let mut odd = arc(&[0.0, 9.0, 18.0]);
        odd[2] = odd[2].resized(128, 128);
        assert_eq!(path_cameras(&odd, &PathConfig::default()).len(), 2);
        // A long jump that turns little (a dolly far along the axis) is skipped by its length.
        let dolly = [
            looking_at_origin("near", Vec3::new(0.0, 0.0, -4.0), 64),
            looking_at_origin("mid", Vec3::new(0.0, 0.0, -5.0), 64),
            looking_at_origin("far", Vec3::new(0.0, 0.0, -6.0), 64),
            looking_at_origin("away", Vec3::new(0.0, 0.0, -30.0), 64),
        ];
        let names: Vec<String> = path_cameras(&dolly, &PathConfig::default())
            .into_iter()
            .map(|c| c.name)
            .collect();
        assert_eq!(
            names,
            ["near~mid#1", "near~mid#2", "mid~far#1", "mid~far#2"]
        );
    }

    #[test]
    fn the_orbits_of_the_service_and_the_cli_get_no_path_views() {
        // Their spiral steps 7.5° of azimuth and 25–80° of elevation from one view to the
        // next: no gap is a path's, so an orbit job embeds exactly as before.
        use crate::scene::orbit::{OrbitOptions, orbit_cameras};
        use crate::scene::synthetic::object_scene;
        let g = object_scene(200, 0, 7);
        for count in [24, 48] {
            let cams = orbit_cameras(
                &g,
                &OrbitOptions {
                    count,
                    ..OrbitOptions::default()
                },
            )
            .expect("orbit");
            let train: Vec<Camera> = cams
                .iter()
                .enumerate()
                .filter(|(i, _)| i % 8 != 0)
                .map(|(_, c)| c.clone())
                .collect();
            assert!(path_cameras(&cams, &PathConfig::default()).is_empty());
            assert!(path_cameras(&train, &PathConfig::default()).is_empty());
        }
    }

    #[test]
    fn a_dense_path_gets_at_most_max_total_cameras_in_its_widest_gaps() {
        // 40 cameras 1° apart but for three gaps of 2°.
        let mut deg = vec![0.0f32];
        for k in 1..40 {
            let step = if [10, 20, 30].contains(&k) { 2.0 } else { 1.0 };
            deg.push(deg[k - 1] + step);
        }
        let cams = arc(&deg);
        // 39 gaps would get 78 cameras; the default cap keeps 64 (32 gaps).
        assert_eq!(path_cameras(&cams, &PathConfig::default()).len(), 64);
        // A cap of 6 fills the three wide gaps, in the path's order.
        let cfg = PathConfig {
            max_total: 6,
            ..PathConfig::default()
        };
        let names: Vec<String> = path_cameras(&cams, &cfg)
            .into_iter()
            .map(|c| c.name)
            .collect();
        let gap = |k: usize| {
            let (x, y) = (deg[k - 1], deg[k]);
            [format!("c{x}~c{y}#1"), format!("c{x}~c{y}#2")]
        };
        let want: Vec<String> = [10, 20, 30].into_iter().flat_map(gap).collect();
        assert_eq!(names, want);
    }

    #[test]
    fn off_or_short_paths_add_nothing_and_bad_settings_are_refused() {
        let off = PathConfig {
            per_gap: 0,
            ..PathConfig::default()
        };
        assert!(path_cameras(&arc(&[0.0, 5.0]), &off).is_empty());
        assert!(path_cameras(&arc(&[0.0]), &PathConfig::default()).is_empty());
        assert!(PathConfig::default().validate().is_ok());
        for bad in [
            PathConfig {
                per_gap: 17,
                ..PathConfig::default()
            },
            PathConfig {
                max_turn_deg: f32::NAN,
                ..PathConfig::default()
            },
            PathConfig {
                max_turn_deg: 0.0,
                ..PathConfig::default()
            },
            PathConfig {
                max_step: -1.0,
                ..PathConfig::default()
            },
            PathConfig {
                max_total: 1001,
                ..PathConfig::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
