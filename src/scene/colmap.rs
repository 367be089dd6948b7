//! COLMAP's sparse point cloud (`points3D.bin` or `points3D.txt`): the points 3D-GS starts
//! from when it fits a captured scene.

use crate::scene::SceneError;
use std::path::Path;

/// Points of a COLMAP reconstruction: positions in COLMAP's world frame (the frame LLFF's
/// `poses_bounds.npy` is in) and colours as 8-bit RGB.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Points {
    pub xyz: Vec<[f32; 3]>,
    pub rgb: Vec<[u8; 3]>,
}

/// Largest file read (COLMAP clouds of real captures are tens of MB).
const MAX_BYTES: u64 = 2 << 30;

/// Reads `points3D.bin` (binary) or any other name as `points3D.txt` (text).
pub fn read_points3d(path: &Path) -> Result<Points, SceneError> {
    let err = |msg: String| SceneError::Camera(format!("{}: {msg}", path.display()));
    let meta = std::fs::metadata(path).map_err(|e| err(e.to_string()))?;
    if meta.len() > MAX_BYTES {
        return Err(err(format!(
            "{} bytes is more than a COLMAP point file may hold here ({MAX_BYTES})",
            meta.len()
        )));
    }
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    let binary = path.extension().and_then(|e| e.to_str()) == Some("bin");
    if binary {
        points_from_bin(&bytes)
    } else {
        points_from_txt(&bytes)
    }
    .map_err(err)
}

/// `points3D.bin`: u64 count, then per point u64 id, 3×f64 xyz, 3×u8 rgb, f64 error, u64 track
/// length and that many (i32 image id, i32 point2D index) pairs; little-endian.
pub fn points_from_bin(bytes: &[u8]) -> Result<Points, String> {
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8], String> {
        let s = bytes
            .get(at..at + n)
            .ok_or_else(|| format!("truncated at byte {at}: a COLMAP points3D.bin ends early"))?;
        at += n;
        Ok(s)
    };
    let u64_at = |s: &[u8]| u64::from_le_bytes(s.try_into().expect("8 bytes"));
    let f64_at = |s: &[u8]| f64::from_le_bytes(s.try_into().expect("8 bytes"));
    let count = u64_at(take(8)?);
    // Each point takes at least 43 bytes: a count beyond that is a corrupt header.
    const MIN_POINT: u64 = 8 + 24 + 3 + 8 + 8;
    if count > (bytes.len() as u64) / MIN_POINT {
        return Err(format!(
            "header says {count} points, more than {} bytes can hold",
            bytes.len()
        ));
    }
    let mut out = Points {
        xyz: Vec::with_capacity(count as usize),
        rgb: Vec::with_capacity(count as usize),
    };
    for i in 0..count {
        let rec = take(MIN_POINT as usize)?;
        let xyz = [0, 1, 2].map(|k| f64_at(&rec[8 + 8 * k..16 + 8 * k]));
        if xyz
            .iter()
            .any(|v| !v.is_finite() || v.abs() > f64::from(f32::MAX))
        {
            return Err(format!("point {i} has a non-finite position"));
        }
        let rgb = [rec[32], rec[33], rec[34]];
        let track = u64_at(&rec[43..51]);
        let track_bytes = track
            .checked_mul(8)
            .filter(|&b| b <= (bytes.len() as u64))
            .ok_or_else(|| format!("point {i}: track length {track} is past the file's end"))?;
        take(track_bytes as usize)?;
        out.xyz.push(xyz.map(|v| v as f32));
        out.rgb.push(rgb);
    }
    if at != bytes.len() {
        return Err(format!(
            "{} bytes after the last of {count} points",
            bytes.len() - at
        ));
    }
    Ok(out)
}

/// `points3D.txt`: `#` comments, then one point per line, `ID X Y Z R G B ERROR TRACK…`.
pub fn points_from_txt(bytes: &[u8]) -> Result<Points, String> {
    let text = std::str::from_utf8(bytes).map_err(|_| "not UTF-8 text".to_string())?;
    let mut out = Points::default();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 8 {
            return Err(format!(
                "line {}: a point needs ID X Y Z R G B ERROR",
                n + 1
            ));
        }
        let num = |s: &str| -> Result<f32, String> {
            s.parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("line {}: '{s}' is not a finite number", n + 1))
        };
        let byte = |s: &str| -> Result<u8, String> {
            s.parse::<u8>()
                .map_err(|_| format!("line {}: '{s}' is not a colour from 0 to 255", n + 1))
        };
        out.xyz.push([num(f[1])?, num(f[2])?, num(f[3])?]);
        out.rgb.push([byte(f[4])?, byte(f[5])?, byte(f[6])?]);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bin(points: &[([f64; 3], [u8; 3], u64)]) -> Vec<u8> {
        let mut b = (points.len() as u64).to_le_bytes().to_vec();
        for (i, (xyz, rgb, track)) in points.iter().enumerate() {
            b.extend((i as u64 + 1).to_le_bytes());
            for v in xyz {
                b.extend(v.to_le_bytes());
            }
            b.extend(rgb);
            b.extend(0.5f64.to_le_bytes());
            b.extend(track.to_le_bytes());
            for k in 0..*track {
                b.extend((k as i32).to_le_bytes());
                b.extend((7i32).to_le_bytes());
            }
        }
        b
    }

    #[test]
    fn binary_points_read_with_their_tracks_skipped() {
        let b = bin(&[
            ([1.0, -2.0, 3.5], [10, 20, 30], 3),
            ([0.0, 0.0, 9.0], [255, 0, 1], 0),
        ]);
        let p = points_from_bin(&b).unwrap();
        assert_eq!(p.xyz, vec![[1.0, -2.0, 3.5], [0.0, 0.0, 9.0]]);
        assert_eq!(p.rgb, vec![[10, 20, 30], [255, 0, 1]]);
    }

    #[test]
    fn corrupt_binary_files_are_errors() {
        let b = bin(&[([1.0, 2.0, 3.0], [1, 2, 3], 2)]);
        assert!(
            points_from_bin(&b[..b.len() - 1])
                .unwrap_err()
                .contains("truncated")
        );
        let mut extra = b.clone();
        extra.push(0);
        assert!(
            points_from_bin(&extra)
                .unwrap_err()
                .contains("after the last")
        );
        let mut huge = b.clone();
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(points_from_bin(&huge).unwrap_err().contains("more than"));
        let mut track = b.clone();
        track[51..59].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(
            points_from_bin(&track)
                .unwrap_err()
                .contains("track length")
        );
        let nan = bin(&[([f64::NAN, 0.0, 0.0], [0, 0, 0], 0)]);
        assert!(points_from_bin(&nan).unwrap_err().contains("non-finite"));
    }

    #[test]
    fn text_points_read_and_bad_lines_are_named() {
        let t = b"# comment\n1 1.5 2 3 4 5 6 0.1 2 3\n\n2 0 0 -1 255 255 255 0.2\n";
        let p = points_from_txt(t).unwrap();
        assert_eq!(p.xyz, vec![[1.5, 2.0, 3.0], [0.0, 0.0, -1.0]]);
        assert_eq!(p.rgb[1], [255, 255, 255]);
        assert!(points_from_txt(b"1 2 3\n").unwrap_err().contains("line 1"));
        assert!(
            points_from_txt(b"1 0 0 0 256 0 0 0\n")
                .unwrap_err()
                .contains("'256'")
        );
    }

    #[test]
    fn the_fern_cloud_reads_when_the_data_is_there() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/data/datasets/llff_fern/sparse/0/points3D.bin");
        if !path.exists() {
            eprintln!("SKIPPED: {} is missing", path.display());
            return;
        }
        let p = read_points3d(&path).unwrap();
        assert_eq!(p.xyz.len(), 10_091);
        assert_eq!(p.rgb.len(), 10_091);
    }
}
