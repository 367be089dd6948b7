//! SuperSplat / PlayCanvas compressed PLY (`*.compressed.ply`).
//!
//! Layout (written by SuperSplat and `splat-transform`):
//! - element `chunk` (one per 256 Gaussians): `float min_x min_y min_z max_x max_y max_z
//!   min_scale_x min_scale_y min_scale_z max_scale_x max_scale_y max_scale_z`, optionally followed
//!   by `min_r min_g min_b max_r max_g max_b`;
//! - element `vertex`: `uint packed_position packed_rotation packed_scale packed_color`;
//! - optional element `sh`: `uchar f_rest_0 .. f_rest_{N-1}` (N = 9, 24 or 45, INRIA channel-major
//!   order).
//!
//! Decoding follows PlayCanvas exactly (`splat-transform/src/lib/readers/decompress-ply.ts` and
//! the engine's `gsplat-compressed-data.js`), in f64 as JavaScript does, rounded to f32 at the end:
//! - position: 11-10-11 bit unorms lerped between the chunk's min and max;
//! - rotation: 2 bits index of the largest component + three 10-bit components
//!   `(v/1023 − 0.5)·√2`, the largest `√max(0, 1 − a² − b² − c²)`, components in `rot_0..rot_3`
//!   (w, x, y, z) order;
//! - scale: 11-10-11 bit unorms lerped between the chunk's log-scale min and max;
//! - colour: 8-8-8-8 unorms; RGB lerped between the chunk's colour min and max when present, then
//!   `f_dc = (c − 0.5) / SH_C0`; opacity `−ln(1/a − 1)`, with PlayCanvas's ±40 for `a` = 0 or 1;
//! - SH byte `v`: `n = 0 if v = 0, 1 if v = 255, else (v + 0.5)/256`, value `(n − 0.5)·8`
//!   (the inverse of SuperSplat's `trunc((x/8 + 0.5)·256)`).

use crate::scene::format::{GaussianBuilder, Limits, RawGaussian};
use crate::scene::ply::{Header, ScalarType, for_each_row, parse_header, rest_properties};
use crate::scene::{Gaussians, SceneError, sigmoid};

/// Gaussians per chunk.
pub const CHUNK_SIZE: usize = 256;

/// `SH_C0` at the precision PlayCanvas uses (JavaScript double).
const SH_C0_F64: f64 = 0.282_094_791_773_878_14;

/// The chunk properties every SuperSplat compressed PLY declares.
pub const CHUNK_REQUIRED: [&str; 12] = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
];
const CHUNK_COLOR: [&str; 6] = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"];
/// The packed vertex properties of a SuperSplat compressed PLY.
pub const PACKED: [&str; 4] = [
    "packed_position",
    "packed_rotation",
    "packed_scale",
    "packed_color",
];

/// Whether a PLY header describes a compressed PLY: a `chunk` element and a `vertex` element with
/// `packed_position`.
pub fn is_compressed(header: &Header) -> bool {
    header.element("chunk").is_some()
        && header
            .element("vertex")
            .is_some_and(|(_, v)| v.property("packed_position").is_some())
}

/// Reads a compressed PLY file.
pub fn read(bytes: &[u8], limits: &Limits) -> Result<Gaussians, SceneError> {
    let header = parse_header(bytes)?;
    if !is_compressed(&header) {
        return Err(SceneError::UnknownFormat(
            "not a compressed PLY (needs a 'chunk' element and 'packed_position')".into(),
        ));
    }
    read_with_header(bytes, &header, limits)
}

#[inline]
fn unorm(value: u32, bits: u32) -> f64 {
    let t = (1u32 << bits) - 1;
    (value & t) as f64 / t as f64
}

#[inline]
fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a * (1.0 - t) + b * t
}

/// 11-10-11 bit unorms.
#[inline]
fn unpack_111011(v: u32) -> [f64; 3] {
    [unorm(v >> 21, 11), unorm(v >> 11, 10), unorm(v, 11)]
}

/// 8-8-8-8 bit unorms.
#[inline]
fn unpack_8888(v: u32) -> [f64; 4] {
    [
        unorm(v >> 24, 8),
        unorm(v >> 16, 8),
        unorm(v >> 8, 8),
        unorm(v, 8),
    ]
}

/// "Smallest three" 2+10+10+10 quaternion, returned as `(rot_0, rot_1, rot_2, rot_3)`.
#[inline]
fn unpack_rot(v: u32) -> [f64; 4] {
    let norm = 1.0 / (std::f64::consts::SQRT_2 * 0.5);
    let a = (unorm(v >> 20, 10) - 0.5) * norm;
    let b = (unorm(v >> 10, 10) - 0.5) * norm;
    let c = (unorm(v, 10) - 0.5) * norm;
    let m = (1.0 - (a * a + b * b + c * c)).max(0.0).sqrt();
    match v >> 30 {
        0 => [m, a, b, c],
        1 => [a, m, b, c],
        2 => [a, b, m, c],
        _ => [a, b, c, m],
    }
}

/// PlayCanvas's opacity decode, finite at both ends.
#[inline]
fn opacity_logit(a: f64) -> f64 {
    if a <= 0.0 {
        -40.0
    } else if a >= 1.0 {
        40.0
    } else {
        -(1.0 / a - 1.0).ln()
    }
}

/// SuperSplat's SH byte decode.
#[inline]
fn sh_value(v: u8) -> f32 {
    let n = match v {
        0 => 0.0,
        255 => 1.0,
        _ => (v as f64 + 0.5) / 256.0,
    };
    ((n - 0.5) * 8.0) as f32
}

fn require_type(
    element: &crate::scene::ply::Element,
    idx: usize,
    ok: &[ScalarType],
) -> Result<(), SceneError> {
    let p = &element.properties[idx];
    if ok.contains(&p.ty) {
        Ok(())
    } else {
        Err(SceneError::Header(format!(
            "property '{}' of element '{}' has type {:?}, expected {:?}",
            p.name, element.name, p.ty, ok
        )))
    }
}

/// Reads a compressed PLY whose header has already been parsed.
pub fn read_with_header(
    bytes: &[u8],
    header: &Header,
    limits: &Limits,
) -> Result<Gaussians, SceneError> {
    let (vi, vertex) = header
        .element("vertex")
        .ok_or_else(|| SceneError::Header("no 'vertex' element".into()))?;
    let (ci, chunk) = header
        .element("chunk")
        .ok_or_else(|| SceneError::Header("no 'chunk' element".into()))?;
    let n = limits.check_count(vertex.count)?;

    let packed: Vec<usize> = PACKED
        .iter()
        .map(|p| vertex.require(p))
        .collect::<Result<_, _>>()?;
    for &p in &packed {
        require_type(vertex, p, &[ScalarType::UInt, ScalarType::Int])?;
    }
    let mut chunk_props: Vec<usize> = CHUNK_REQUIRED
        .iter()
        .map(|p| chunk.require(p))
        .collect::<Result<_, _>>()?;
    let has_color = chunk.property("min_r").is_some();
    if has_color {
        for p in CHUNK_COLOR {
            chunk_props.push(chunk.require(p)?);
        }
    }
    for &p in &chunk_props {
        require_type(chunk, p, &[ScalarType::Float, ScalarType::Double])?;
    }
    let chunks_needed = n.div_ceil(CHUNK_SIZE);
    if chunk.count != chunks_needed as u64 {
        return Err(SceneError::Corrupt(format!(
            "{} chunks declared for {n} Gaussians, expected {chunks_needed} (one per {CHUNK_SIZE})",
            chunk.count
        )));
    }

    let sh = match header.element("sh") {
        Some((si, sh)) => {
            let (idx, degree) = rest_properties(sh)?;
            if degree == 0 {
                return Err(SceneError::ShRestCount(0));
            }
            for &p in &idx {
                require_type(sh, p, &[ScalarType::UChar])?;
            }
            if sh.count != vertex.count {
                return Err(SceneError::Corrupt(format!(
                    "'sh' element has {} rows but there are {} vertices",
                    sh.count, vertex.count
                )));
            }
            Some((si, idx, degree))
        }
        None => None,
    };
    let degree = sh.as_ref().map_or(0, |s| s.2);

    // Chunk bounds. for_each_row checks the data is present before the first callback, and the
    // chunk count is tied to the (limited) Gaussian count above.
    let mut chunks: Vec<[f64; 18]> = Vec::new();
    for_each_row(bytes, header, ci, &chunk_props, |i, v| {
        let mut c = [0.0f64; 18];
        c[..v.len()].copy_from_slice(v);
        if c.iter().any(|x| !x.is_finite()) {
            return Err(SceneError::Corrupt(format!(
                "chunk {i} has a NaN or infinite bound"
            )));
        }
        if chunks.is_empty() {
            chunks.reserve_exact(chunks_needed);
        }
        chunks.push(c);
        Ok(())
    })?;

    let mut words: Vec<[u32; 4]> = Vec::new();
    for_each_row(bytes, header, vi, &packed, |_, v| {
        if words.is_empty() {
            words.reserve_exact(n);
        }
        // Values came from (u)int properties; reinterpret as the 32 bits PlayCanvas reads.
        words.push([
            v[0] as i64 as u32,
            v[1] as i64 as u32,
            v[2] as i64 as u32,
            v[3] as i64 as u32,
        ]);
        Ok(())
    })?;

    let rest_len = Gaussians::<f32>::rest_len_for(degree);
    let mut sh_bytes: Vec<u8> = Vec::new();
    if let Some((si, idx, _)) = &sh {
        // Our [k][c] slot k*3+c comes from file property f_rest_{c*per_channel+k}.
        let per_channel = idx.len() / 3;
        let wanted: Vec<usize> = (0..per_channel)
            .flat_map(|k| (0..3).map(move |c| idx[c * per_channel + k]))
            .collect();
        for_each_row(bytes, header, *si, &wanted, |_, v| {
            if sh_bytes.is_empty() {
                sh_bytes.reserve_exact(n * rest_len);
            }
            sh_bytes.extend(v.iter().map(|&x| x as u8));
            Ok(())
        })?;
    }

    let mut builder = GaussianBuilder::new(n, degree);
    let mut rest = vec![0f32; rest_len];
    for (i, w) in words.iter().enumerate() {
        let c = chunks
            .get(i / CHUNK_SIZE)
            .ok_or_else(|| SceneError::Corrupt("missing chunk".into()))?;
        let p = unpack_111011(w[0]);
        let r = unpack_rot(w[1]);
        let s = unpack_111011(w[2]);
        let col = unpack_8888(w[3]);
        let rgb = if has_color {
            [
                lerp(c[12], c[15], col[0]),
                lerp(c[13], c[16], col[1]),
                lerp(c[14], c[17], col[2]),
            ]
        } else {
            [col[0], col[1], col[2]]
        };
        if let Some(src) = sh_bytes.get(i * rest_len..(i + 1) * rest_len) {
            for (d, &b) in rest.iter_mut().zip(src) {
                *d = sh_value(b);
            }
        }
        builder.push(RawGaussian {
            mean: [
                lerp(c[0], c[3], p[0]) as f32,
                lerp(c[1], c[4], p[1]) as f32,
                lerp(c[2], c[5], p[2]) as f32,
            ],
            log_scale: [
                lerp(c[6], c[9], s[0]) as f32,
                lerp(c[7], c[10], s[1]) as f32,
                lerp(c[8], c[11], s[2]) as f32,
            ],
            rotation: r.map(|x| x as f32),
            opacity: opacity_logit(col[3]) as f32,
            dc: rgb.map(|x| ((x - 0.5) / SH_C0_F64) as f32),
            rest: &rest,
        })?;
    }
    Ok(builder.finish())
}

/// The compressed PLY bytes of `g`, as `splat-transform`'s `CompressedChunk.pack` and
/// `writeCompressedPly` write them, without their Morton sort (the Gaussians keep their order,
/// so attribution records still name them), always with chunk colour bounds. Lossy: positions
/// and scales at 11/10/11 bits and colours at 8 bits within each chunk's bounds, rotations at
/// 3 × 10 bits, opacity at 8 bits, higher SH at 8 bits in [−4, 4].
pub fn encode(g: &Gaussians) -> Vec<u8> {
    let n = g.len();
    let nchunks = n.div_ceil(CHUNK_SIZE);
    let rest_len = g.rest_len();
    let mut h = String::from("ply\nformat binary_little_endian 1.0\ncomment splatmark\n");
    h += &format!("element chunk {nchunks}\n");
    for p in CHUNK_REQUIRED.iter().chain(CHUNK_COLOR.iter()) {
        h += &format!("property float {p}\n");
    }
    h += &format!("element vertex {n}\n");
    for p in PACKED {
        h += &format!("property uint {p}\n");
    }
    if rest_len > 0 {
        h += &format!("element sh {n}\n");
        for j in 0..rest_len {
            h += &format!("property uchar f_rest_{j}\n");
        }
    }
    h += "end_header\n";

    let pack_unorm = |v: f64, bits: u32| -> u32 {
        let t = ((1u32 << bits) - 1) as f64;
        (v * t + 0.5).floor().clamp(0.0, t) as u32
    };
    let normalize = |x: f64, min: f64, max: f64| {
        if x <= min {
            0.0
        } else if x >= max {
            1.0
        } else if max - min < 0.00001 {
            0.0
        } else {
            (x - min) / (max - min)
        }
    };
    let mut chunk_data: Vec<f32> = Vec::new();
    let mut words: Vec<u32> = Vec::new();
    for ch in 0..nchunks {
        let idx: Vec<usize> = (0..CHUNK_SIZE)
            .map(|j| (ch * CHUNK_SIZE + j).min(n - 1))
            .collect();
        let col = |i: usize, c: usize| g.sh_dc[i][c] as f64 * SH_C0_F64 + 0.5;
        let minmax = |f: &dyn Fn(usize) -> f64| {
            idx.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &i| {
                    (lo.min(f(i)), hi.max(f(i)))
                })
        };
        let mut b = [(0.0, 0.0); 9];
        for a in 0..3 {
            b[a] = minmax(&|i| g.means[i][a] as f64);
            b[3 + a] = minmax(&|i| g.log_scales[i][a] as f64);
            b[6 + a] = minmax(&|i| col(i, a));
        }
        // Stored as f32, so decode with the f32 bounds.
        let b: Vec<(f64, f64)> = b
            .iter()
            .map(|&(lo, hi)| (lo as f32 as f64, hi as f32 as f64))
            .collect();
        // Per attribute (position, scale, colour): its three minima, then its three maxima.
        for attr in b.chunks_exact(3) {
            chunk_data.extend(attr.iter().map(|&(lo, _)| lo as f32));
            chunk_data.extend(attr.iter().map(|&(_, hi)| hi as f32));
        }
        for &i in idx.iter().take(n - ch * CHUNK_SIZE) {
            let p111011 = |v: [f64; 3]| {
                (pack_unorm(v[0], 11) << 21) | (pack_unorm(v[1], 10) << 11) | pack_unorm(v[2], 11)
            };
            let nz = |a: usize, v: f64| normalize(v, b[a].0, b[a].1);
            words.push(p111011([
                nz(0, g.means[i][0] as f64),
                nz(1, g.means[i][1] as f64),
                nz(2, g.means[i][2] as f64),
            ]));
            // Rotation: largest |component| index, made positive, three 10-bit others.
            let q = g.rotations[i].map(|x| x as f64);
            let largest = (0..4).fold(
                0,
                |best, k| if q[k].abs() > q[best].abs() { k } else { best },
            );
            let sign = if q[largest] < 0.0 { -1.0 } else { 1.0 };
            let mut word = largest as u32;
            for (k, &qk) in q.iter().enumerate() {
                if k != largest {
                    word = (word << 10)
                        | pack_unorm(qk * sign * std::f64::consts::SQRT_2 * 0.5 + 0.5, 10);
                }
            }
            words.push(word);
            words.push(p111011([
                nz(3, g.log_scales[i][0] as f64),
                nz(4, g.log_scales[i][1] as f64),
                nz(5, g.log_scales[i][2] as f64),
            ]));
            words.push(
                (pack_unorm(nz(6, col(i, 0)), 8) << 24)
                    | (pack_unorm(nz(7, col(i, 1)), 8) << 16)
                    | (pack_unorm(nz(8, col(i, 2)), 8) << 8)
                    | pack_unorm(sigmoid(g.opacity_logits[i]) as f64, 8),
            );
        }
    }
    let mut out = h.into_bytes();
    chunk_data
        .iter()
        .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
    words
        .iter()
        .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
    let per_channel = rest_len / 3;
    for i in 0..n {
        for j in 0..rest_len {
            // File index j = c*per_channel + k.
            let (c, k) = (j / per_channel, j % per_channel);
            let nv = g.rest_of(i)[k * 3 + c] as f64 / 8.0 + 0.5;
            out.push((nv * 256.0).trunc().clamp(0.0, 255.0) as u8);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::format::read_scene_bytes;
    use crate::scene::ply::tests::synthetic;

    fn read(bytes: &[u8]) -> Result<Gaussians, SceneError> {
        read_scene_bytes(bytes, None, &Limits::default())
    }

    #[test]
    fn decode_synthetic_within_quantisation() {
        for (n, degree) in [(1usize, 0u8), (300, 1), (600, 3), (256, 2)] {
            let g = synthetic(n, degree, 17 + n as u64);
            let bytes = encode(&g);
            assert_eq!(
                crate::scene::format::detect_format(&bytes, None).unwrap(),
                crate::scene::Format::CompressedPly
            );
            let d = read(&bytes).unwrap();
            d.validate().unwrap();
            assert_eq!((d.len(), d.sh_degree), (n, degree));
            for i in 0..n {
                for a in 0..3 {
                    // positions in [-3, 3): 10 bits over ≤ 6 → ≤ 0.003
                    assert!((d.means[i][a] - g.means[i][a]).abs() < 4e-3, "pos {i} {a}");
                    // log-scales in [-6, -1): 10 bits over ≤ 5 → ≤ 0.0025
                    assert!(
                        (d.log_scales[i][a] - g.log_scales[i][a]).abs() < 3e-3,
                        "scale {i} {a}"
                    );
                    // colour 8 bits over ≤ 0.85 → dc error ≤ 0.0017/SH_C0
                    assert!((d.sh_dc[i][a] - g.sh_dc[i][a]).abs() < 7e-3, "dc {i} {a}");
                }
                let dot: f32 = (0..4).map(|k| d.rotations[i][k] * g.rotations[i][k]).sum();
                assert!(dot.abs() > 0.9995, "rotation {i}: {dot}");
                assert!(
                    (sigmoid(d.opacity_logits[i]) - sigmoid(g.opacity_logits[i])).abs()
                        < 0.5 / 255.0 + 1e-4
                );
                for (a, b) in d.rest_of(i).iter().zip(g.rest_of(i)) {
                    assert!(
                        (a - b).abs() <= 8.0 / 256.0 * 0.5 + 1e-5,
                        "sh {i}: {a} vs {b}"
                    );
                }
            }
        }
    }

    #[test]
    fn known_values_decode_exactly() {
        // The formulas themselves on hand-picked words.
        assert_eq!(unpack_111011(0xffff_ffff), [1.0, 1.0, 1.0]);
        assert_eq!(unpack_111011(0), [0.0, 0.0, 0.0]);
        assert_eq!(unpack_111011(1023 << 11), [0.0, 1.0, 0.0]);
        // Identity rotation: largest = rot_0 (index 0), others at mid-range 511.5 → 512 ≈ 0.
        let r = unpack_rot((512 << 20) | (512 << 10) | 512);
        assert!((r[0] - 1.0).abs() < 1e-5 && r[1].abs() < 2e-3);
        let r = unpack_rot((3 << 30) | (512 << 20) | (512 << 10) | 512);
        assert!((r[3] - 1.0).abs() < 1e-5);
        assert_eq!(sh_value(0), -4.0);
        assert_eq!(sh_value(255), 4.0);
        assert_eq!(sh_value(128), ((128.5 / 256.0 - 0.5) * 8.0) as f32);
        assert_eq!(opacity_logit(0.0), -40.0);
        assert_eq!(opacity_logit(1.0), 40.0);
        assert!((opacity_logit(0.5)).abs() < 1e-12);
    }

    #[test]
    fn chunk_without_colour_bounds() {
        let t = "ply\nformat binary_little_endian 1.0\nelement chunk 1\n".to_string()
            + &CHUNK_REQUIRED
                .iter()
                .map(|p| format!("property float {p}\n"))
                .collect::<String>()
            + "element vertex 1\n"
            + &PACKED
                .iter()
                .map(|p| format!("property uint {p}\n"))
                .collect::<String>()
            + "end_header\n";
        let mut b = t.into_bytes();
        for v in [
            0.0f32, 0.0, 0.0, 2.0, 2.0, 2.0, -5.0, -5.0, -5.0, -1.0, -1.0, -1.0,
        ] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let color: u32 = (255 << 24) | (128 << 16) | 255; // r = 1, g = 128/255, b = 0, a = 1
        for w in [0xffff_ffffu32, (512 << 20) | (512 << 10) | 512, 0, color] {
            b.extend_from_slice(&w.to_le_bytes());
        }
        let g = read(&b).unwrap();
        assert_eq!(g.means[0], [2.0, 2.0, 2.0]);
        assert_eq!(g.log_scales[0], [-5.0, -5.0, -5.0]);
        assert_eq!(g.sh_dc[0][0], (0.5 / SH_C0_F64) as f32);
        assert_eq!(g.sh_dc[0][2], (-0.5 / SH_C0_F64) as f32);
        assert_eq!(g.opacity_logits[0], 40.0);
        assert_eq!(g.sh_degree, 0);
    }

    #[test]
    fn errors() {
        let g = synthetic(300, 1, 3);
        let good = encode(&g);
        let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
        let header_end = text(&good).find("end_header\n").unwrap() + 11;
        let with_header = |h: String| {
            let mut b = h.into_bytes();
            b.extend_from_slice(&good[header_end..]);
            b
        };
        let head = text(&good[..header_end]);

        // Truncated.
        let e = read(&good[..good.len() - 1]).unwrap_err();
        assert!(matches!(e, SceneError::Truncated { .. }), "{e}");
        // Wrong chunk count.
        let e = read(&with_header(
            head.replace("element chunk 2", "element chunk 3"),
        ))
        .unwrap_err();
        assert!(
            matches!(e, SceneError::Corrupt(_) | SceneError::Truncated { .. }),
            "{e}"
        );
        let e = read(&with_header(
            head.replace("element chunk 2", "element chunk 1"),
        ))
        .unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Packed word of the wrong type.
        let e = read(&with_header(head.replace(
            "property uint packed_scale",
            "property float packed_scale",
        )))
        .unwrap_err();
        assert!(matches!(e, SceneError::Header(_)), "{e}");
        // Missing chunk bound.
        let e = read(&with_header(head.replace("property float min_x\n", ""))).unwrap_err();
        assert!(
            matches!(&e, SceneError::MissingProperty(p) if p.starts_with("min_x")),
            "{e}"
        );
        // Wrong SH count.
        let e = read(&with_header(head.replace("property uchar f_rest_8\n", ""))).unwrap_err();
        assert!(matches!(e, SceneError::ShRestCount(8)), "{e}");
        // SH rows don't match the vertices.
        let e = read(&with_header(
            head.replace("element sh 300", "element sh 299"),
        ))
        .unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Too many Gaussians.
        let limits = Limits {
            max_gaussians: 299,
            ..Limits::default()
        };
        let e = read_scene_bytes(&good, None, &limits).unwrap_err();
        assert!(
            matches!(
                e,
                SceneError::TooManyGaussians {
                    count: 300,
                    max: 299
                }
            ),
            "{e}"
        );
        // NaN chunk bound.
        let mut bad = good.clone();
        bad[header_end..header_end + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        let e = read(&bad).unwrap_err();
        assert!(matches!(e, SceneError::Corrupt(_)), "{e}");
        // Never panics on corruptions.
        let mut rng = crate::scene::ply::tests::Rng(77);
        for _ in 0..2000 {
            let mut f = good.clone();
            let at = (rng.next_u64() as usize) % f.len();
            f[at] = rng.next_u64() as u8;
            let _ = read(&f);
        }
        for cut in (0..good.len()).step_by(7) {
            let _ = read(&good[..cut]);
        }
    }
}
