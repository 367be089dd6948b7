//! Real spherical harmonics up to degree 3, as the INRIA 3D-GS reference evaluates them, with the
//! basis gradient for back-propagating into the viewing direction.

use super::Real;

const C0: f64 = 0.282_094_791_773_878_1;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Number of basis functions used for a degree.
pub const fn basis_len(degree: u8) -> usize {
    let d = degree as usize + 1;
    d * d
}

/// The SH basis at unit direction `(x, y, z)` for degrees up to `degree`; entries beyond
/// `basis_len(degree)` are zero.
pub fn basis<T: Real>(degree: u8, d: [T; 3]) -> [T; 16] {
    let [x, y, z] = d;
    let c = T::c;
    let mut b = [T::zero(); 16];
    b[0] = c(C0);
    if degree >= 1 {
        b[1] = -c(C1) * y;
        b[2] = c(C1) * z;
        b[3] = -c(C1) * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = c(C2[0]) * x * y;
        b[5] = c(C2[1]) * y * z;
        b[6] = c(C2[2]) * (c(2.0) * zz - xx - yy);
        b[7] = c(C2[3]) * x * z;
        b[8] = c(C2[4]) * (xx - yy);
        if degree >= 3 {
            b[9] = c(C3[0]) * y * (c(3.0) * xx - yy);
            b[10] = c(C3[1]) * x * y * z;
            b[11] = c(C3[2]) * y * (c(4.0) * zz - xx - yy);
            b[12] = c(C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy);
            b[13] = c(C3[4]) * x * (c(4.0) * zz - xx - yy);
            b[14] = c(C3[5]) * z * (xx - yy);
            b[15] = c(C3[6]) * x * (xx - c(3.0) * yy);
        }
    }
    b
}

/// ∂basis_k/∂(x, y, z) at `d` (treating x, y, z as independent; the caller projects onto the
/// tangent plane of the unit sphere).
pub fn basis_grad<T: Real>(degree: u8, d: [T; 3]) -> [[T; 3]; 16] {
    let [x, y, z] = d;
    let c = T::c;
    let o = T::zero();
    let mut g = [[o; 3]; 16];
    if degree >= 1 {
        g[1] = [o, -c(C1), o];
        g[2] = [o, o, c(C1)];
        g[3] = [-c(C1), o, o];
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let two = c(2.0);
        g[4] = [c(C2[0]) * y, c(C2[0]) * x, o];
        g[5] = [o, c(C2[1]) * z, c(C2[1]) * y];
        g[6] = [
            -two * c(C2[2]) * x,
            -two * c(C2[2]) * y,
            c(4.0) * c(C2[2]) * z,
        ];
        g[7] = [c(C2[3]) * z, o, c(C2[3]) * x];
        g[8] = [two * c(C2[4]) * x, -two * c(C2[4]) * y, o];
        if degree >= 3 {
            let three = c(3.0);
            let four = c(4.0);
            g[9] = [c(C3[0]) * c(6.0) * x * y, c(C3[0]) * three * (xx - yy), o];
            g[10] = [c(C3[1]) * y * z, c(C3[1]) * x * z, c(C3[1]) * x * y];
            g[11] = [
                -two * c(C3[2]) * x * y,
                c(C3[2]) * (four * zz - xx - three * yy),
                c(C3[2]) * c(8.0) * y * z,
            ];
            g[12] = [
                -c(6.0) * c(C3[3]) * x * z,
                -c(6.0) * c(C3[3]) * y * z,
                c(C3[3]) * (c(6.0) * zz - three * xx - three * yy),
            ];
            g[13] = [
                c(C3[4]) * (four * zz - three * xx - yy),
                -two * c(C3[4]) * x * y,
                c(C3[4]) * c(8.0) * x * z,
            ];
            g[14] = [
                two * c(C3[5]) * x * z,
                -two * c(C3[5]) * y * z,
                c(C3[5]) * (xx - yy),
            ];
            g[15] = [c(C3[6]) * three * (xx - yy), -c(C3[6]) * c(6.0) * x * y, o];
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_gradient_matches_finite_differences() {
        let d = [0.3f64, -0.5, 0.81];
        let g = basis_grad(3, d);
        let h = 1e-6;
        for axis in 0..3 {
            let mut p = d;
            let mut m = d;
            p[axis] += h;
            m[axis] -= h;
            let (bp, bm) = (basis(3, p), basis(3, m));
            for k in 0..16 {
                let fd = (bp[k] - bm[k]) / (2.0 * h);
                assert!(
                    (fd - g[k][axis]).abs() < 1e-7,
                    "k={k} axis={axis} fd={fd} an={}",
                    g[k][axis]
                );
            }
        }
    }

    #[test]
    fn degree_zero_is_constant_and_higher_entries_are_zero() {
        let b = basis(0, [0.0f32, 0.0, 1.0]);
        assert!((b[0] - 0.282_094_8).abs() < 1e-7);
        assert!(b[1..].iter().all(|&v| v == 0.0));
        let b1 = basis(1, [0.0f32, 0.0, 1.0]);
        assert!((b1[2] - 0.488_602_5).abs() < 1e-6);
        assert!(b1[4..].iter().all(|&v| v == 0.0));
    }
}
