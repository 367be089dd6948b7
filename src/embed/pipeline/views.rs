//! Which cameras an embedding reads: the training/held-out split, the spread subset the
//! analysis phases read, and the training views at several resolutions.

use super::EmbedError;
use crate::scene::Camera;

/// The indices of at most `m` of `cameras` spread over them (`m` = 0 or ≥ the count: all, in
/// order): farthest-point sampling on the cameras' centres and viewing directions from the
/// first camera, returned sorted — deterministic, even over the positions (an orbit's higher,
/// smaller rings keep fewer views than the wide ones), every region of the rig kept.
pub fn spread_views(cameras: &[Camera], m: usize) -> Vec<usize> {
    let n = cameras.len();
    if m == 0 || m >= n {
        return (0..n).collect();
    }
    let centres: Vec<glam::Vec3> = cameras.iter().map(Camera::center).collect();
    let mean = centres.iter().copied().sum::<glam::Vec3>() / n as f32;
    let radius = centres
        .iter()
        .map(|c| c.distance(mean))
        .fold(0.0f32, f32::max)
        .max(1e-6);
    // A camera as a point: its centre relative to the rig (unit radius) and where it looks.
    let points: Vec<[f32; 6]> = cameras
        .iter()
        .zip(&centres)
        .map(|(c, &p)| {
            let q = (p - mean) / radius;
            let d = c.rotation_mat().row(2);
            [q.x, q.y, q.z, d.x, d.y, d.z]
        })
        .collect();
    let dist = |a: &[f32; 6], b: &[f32; 6]| -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
    };
    let mut chosen = vec![0usize];
    let mut nearest: Vec<f32> = points.iter().map(|p| dist(p, &points[0])).collect();
    while chosen.len() < m {
        let (next, _) =
            nearest.iter().enumerate().fold(
                (0, f32::MIN),
                |best, (i, &d)| if d > best.1 { (i, d) } else { best },
            );
        chosen.push(next);
        for (k, p) in points.iter().enumerate() {
            nearest[k] = nearest[k].min(dist(p, &points[next]));
        }
    }
    chosen.sort_unstable();
    chosen
}

/// Checks [`EmbedOptions::view_scales`] without cameras: at least one factor, each in
/// [0.125, 8].
pub fn check_view_scales(scales: &[f32]) -> Result<(), String> {
    if scales.is_empty() {
        return Err("view_scales needs at least one factor".into());
    }
    match scales.iter().find(|s| !(0.125..=8.0).contains(*s)) {
        Some(s) => Err(format!("view_scales: {s} is outside [0.125, 8]")),
        None => Ok(()),
    }
}

/// The training cameras at every factor of `scales` (in that order, each camera's resolution
/// multiplied, intrinsics scaled with it).
pub fn scaled_views(cameras: &[Camera], scales: &[f32]) -> Result<Vec<Camera>, EmbedError> {
    check_view_scales(scales).map_err(EmbedError::Invalid)?;
    let mut out = Vec::with_capacity(cameras.len() * scales.len());
    for &s in scales {
        for c in cameras {
            let w = (c.width as f32 * s).round() as u32;
            let h = (c.height as f32 * s).round() as u32;
            if w > 8192 || h > 8192 {
                return Err(EmbedError::Invalid(format!(
                    "view_scales: {s} makes a {}×{} view {w}×{h} (at most 8192 px a side)",
                    c.width, c.height
                )));
            }
            if w < 16 || h < 16 {
                return Err(EmbedError::Invalid(format!(
                    "view_scales: {s} makes a {}×{} view {w}×{h} (at least 16 px a side)",
                    c.width, c.height
                )));
            }
            out.push(if s == 1.0 { c.clone() } else { c.resized(w, h) });
        }
    }
    Ok(out)
}

/// Splits views into training and held-out sets: every `every`-th view (k % every == every − 1,
/// INRIA's "llffhold" rule shifted so view 0 trains) is held out; `every` = 0 holds out none.
pub fn split_views(cameras: &[Camera], every: usize) -> (Vec<Camera>, Vec<Camera>) {
    let mut train = Vec::new();
    let mut held = Vec::new();
    for (k, c) in cameras.iter().enumerate() {
        if every > 0 && k % every == every - 1 {
            held.push(c.clone());
        } else {
            train.push(c.clone());
        }
    }
    (train, held)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::orbit::{OrbitOptions, orbit_cameras};
    use crate::scene::synthetic::object_scene;

    #[test]
    fn view_scales_multiply_each_camera_and_bad_factors_are_named() {
        let g = object_scene(50, 0, 1);
        let cams = orbit_cameras(
            &g,
            &OrbitOptions {
                count: 3,
                width: 64,
                height: 48,
                ..OrbitOptions::default()
            },
        )
        .unwrap();
        let v = scaled_views(&cams, &[1.0, 2.0]).unwrap();
        assert_eq!(v.len(), 6);
        assert_eq!(v[0], cams[0]);
        assert_eq!((v[3].width, v[3].height), (128, 96));
        assert!((v[3].fx - 2.0 * cams[0].fx).abs() < 1e-4);
        assert_eq!(v[3].center(), cams[0].center());
        for (bad, needle) in [
            (&[][..], "at least one"),
            (&[9.0][..], "outside"),
            (&[0.25][..], "at least 16"),
        ] {
            let e = scaled_views(&cams, bad).unwrap_err().to_string();
            assert!(e.contains(needle), "{bad:?}: {e}");
        }
    }

    #[test]
    fn spread_views_keep_every_band_of_an_orbit_and_every_azimuth_region() {
        let g = object_scene(50, 0, 1);
        let o = OrbitOptions {
            count: 48,
            width: 32,
            height: 32,
            ..OrbitOptions::default()
        };
        let bands = o.elevations_deg.len();
        let (train, _) = split_views(&orbit_cameras(&g, &o).unwrap(), 8);
        assert_eq!(train.len(), 42);
        let pick = spread_views(&train, 24);
        assert_eq!(pick.len(), 24);
        assert!(
            pick.windows(2).all(|w| w[0] < w[1]),
            "sorted, distinct: {pick:?}"
        );
        assert_eq!(pick, spread_views(&train, 24), "deterministic");
        // Every band of elevations keeps views (the sampling is even over the sphere of
        // positions, so the 60° ring, half the others' circumference, keeps fewer).
        let elevation = |c: &Camera| c.rotation_mat().row(2).y;
        let mut levels: Vec<f32> = train.iter().map(elevation).collect();
        levels.sort_by(f32::total_cmp);
        levels.dedup_by(|a, b| (*a - *b).abs() < 1e-3);
        assert_eq!(levels.len(), bands);
        for l in levels {
            let n = pick
                .iter()
                .filter(|&&i| (elevation(&train[i]) - l).abs() < 1e-3)
                .count();
            assert!(n >= 3, "{n} views at band {l}: {pick:?}");
        }
        // No half of the orbit is left out: every 90° of azimuth holds picked views.
        let azimuth = |c: &Camera| {
            let p = c.center();
            p.z.atan2(p.x).to_degrees().rem_euclid(360.0)
        };
        for q in 0..4 {
            let lo = q as f32 * 90.0;
            assert!(
                pick.iter()
                    .any(|&i| (lo..lo + 90.0).contains(&azimuth(&train[i]))),
                "no view in [{lo}, {}): {pick:?}",
                lo + 90.0
            );
        }
        assert_eq!(spread_views(&train, 0), (0..42).collect::<Vec<_>>());
        assert_eq!(spread_views(&train, 100), (0..42).collect::<Vec<_>>());
    }
}
