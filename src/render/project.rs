//! Per-Gaussian projection: 3D parameters → screen-space mean, conic, opacity, colour; and its
//! exact backward pass. Forward and backward share [`project`], so they cannot disagree.

use super::{LOW_PASS, Real, sh};
use crate::scene::{Camera, Gaussians};

pub(crate) type M3<T> = [[T; 3]; 3];

/// The camera converted to the compute type.
#[derive(Clone, Debug)]
pub(crate) struct Cam<T> {
    pub w: M3<T>,
    pub t: [T; 3],
    pub center: [T; 3],
    pub fx: T,
    pub fy: T,
    pub cx: T,
    pub cy: T,
    pub lim_x: T,
    pub lim_y: T,
    pub near: T,
    pub width: usize,
    pub height: usize,
}

impl<T: Real> Cam<T> {
    pub fn new(cam: &Camera, near: f32) -> Self {
        let f = T::from_f32;
        let w = cam.rotation.map(|r| r.map(f));
        let t = cam.translation.map(f);
        // centre = −Wᵀ t
        let center = std::array::from_fn(|c| -(w[0][c] * t[0] + w[1][c] * t[1] + w[2][c] * t[2]));
        let (wf, hf) = (cam.width as f32, cam.height as f32);
        Self {
            w,
            t,
            center,
            fx: f(cam.fx),
            fy: f(cam.fy),
            cx: f(cam.cx),
            cy: f(cam.cy),
            lim_x: f(1.3 * cam.cx.max(wf - cam.cx).max(1.0) / cam.fx),
            lim_y: f(1.3 * cam.cy.max(hf - cam.cy).max(1.0) / cam.fy),
            near: f(near),
            width: cam.width as usize,
            height: cam.height as usize,
        }
    }
}

/// Everything the forward pass computes for one Gaussian, kept so the backward pass can reuse it.
#[derive(Clone, Debug)]
pub(crate) struct Projection<T> {
    /// Camera-space centre.
    pub tc: [T; 3],
    /// Screen-space centre (pixels).
    pub xy: [T; 2],
    /// 2D covariance (A, B, C) including the low-pass.
    pub cov2: [T; 3],
    /// Inverse of the 2D covariance (a, b, c): σ = ½(a dx² + c dy²) + b dx dy.
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
    /// Which colour channels were clamped at 0 (their gradient is zero).
    pub clamped: [bool; 3],
    /// Largest eigenvalue of the 2D covariance.
    pub lambda_max: T,
}

#[inline(always)]
pub(crate) fn quat_to_mat<T: Real>(q: [T; 4]) -> M3<T> {
    let [w, x, y, z] = q;
    let one = T::one();
    let two = T::c(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

#[inline(always)]
fn normalized<T: Real>(q: [T; 4]) -> ([T; 4], T) {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    (q.map(|v| v / n), n)
}

#[inline(always)]
fn sigmoid<T: Real>(x: T) -> T {
    T::one() / (T::one() + (-x).exp())
}

/// Clamped camera-space coordinate used by the Jacobian (INRIA's frustum guard), and whether it
/// was clamped (then the sign of the limit).
#[inline(always)]
fn clamp_ratio<T: Real>(v: T, z: T, lim: T) -> (T, Option<T>) {
    let r = v / z;
    if r > lim {
        (lim * z, Some(T::one()))
    } else if r < -lim {
        (-lim * z, Some(-T::one()))
    } else {
        (v, None)
    }
}

/// Projects Gaussian `i`; `None` when it is behind the near plane or degenerate.
#[inline]
pub(crate) fn project<T: Real>(
    g: &Gaussians<T>,
    i: usize,
    cam: &Cam<T>,
    sh_degree: u8,
) -> Option<Projection<T>> {
    let m = g.means[i];
    let w = &cam.w;
    let tc: [T; 3] =
        std::array::from_fn(|r| w[r][0] * m[0] + w[r][1] * m[1] + w[r][2] * m[2] + cam.t[r]);
    let z = tc[2];
    if !(z > cam.near) {
        return None;
    }
    let inv_z = T::one() / z;
    let xy = [
        cam.fx * tc[0] * inv_z + cam.cx,
        cam.fy * tc[1] * inv_z + cam.cy,
    ];

    let cov = Cov3::new(g, i);
    let jac = Jacobian::new(cam, tc);
    let (ca, cb, cc) = cov2d(&jac.tm, &cov.sig);
    let lp = T::c(LOW_PASS);
    let cov2 = [ca + lp, cb, cc + lp];
    let det = cov2[0] * cov2[2] - cov2[1] * cov2[1];
    if !(det > T::zero()) {
        return None;
    }
    let inv_det = T::one() / det;
    let conic = [cov2[2] * inv_det, -cov2[1] * inv_det, cov2[0] * inv_det];
    let half = T::c(0.5);
    let mid = half * (cov2[0] + cov2[2]);
    let lambda_max = mid + (mid * mid - det).max(T::zero()).sqrt();

    let opacity = sigmoid(g.opacity_logits[i]);
    let (color, clamped) = sh_color(g, i, cam, sh_degree);
    Some(Projection {
        tc,
        xy,
        cov2,
        conic,
        opacity,
        color,
        clamped,
        lambda_max,
    })
}

/// Unit direction camera centre → Gaussian and the distance.
#[inline(always)]
fn view_dir<T: Real>(m: [T; 3], cam: &Cam<T>) -> ([T; 3], T) {
    let v = [
        m[0] - cam.center[0],
        m[1] - cam.center[1],
        m[2] - cam.center[2],
    ];
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        .sqrt()
        .max(T::c(1e-12));
    (v.map(|x| x / len), len)
}

/// Gaussian `i`'s colour along the view direction: SH of degree `deg` + 0.5, clamped at 0
/// (and which channels were clamped).
#[inline]
pub(crate) fn sh_color<T: Real>(
    g: &Gaussians<T>,
    i: usize,
    cam: &Cam<T>,
    deg: u8,
) -> ([T; 3], [bool; 3]) {
    let dc = g.sh_dc[i];
    let c0 = T::c(0.282_094_791_773_878_1);
    let mut col = [c0 * dc[0], c0 * dc[1], c0 * dc[2]];
    if deg > 0 {
        let (d, _) = view_dir(g.means[i], cam);
        let b = sh::basis(deg, d);
        let rest = g.rest_of(i);
        for k in 1..sh::basis_len(deg) {
            for (ch, c) in col.iter_mut().enumerate() {
                *c = *c + b[k] * rest[(k - 1) * 3 + ch];
            }
        }
    }
    let mut clamped = [false; 3];
    for ch in 0..3 {
        col[ch] = col[ch] + T::c(0.5);
        if col[ch] < T::zero() {
            col[ch] = T::zero();
            clamped[ch] = true;
        }
    }
    (col, clamped)
}

/// The 3D covariance Σ = M Mᵀ, M = R S, of Gaussian `i` and the pieces its gradient needs.
struct Cov3<T> {
    /// Normalised quaternion and the length it had.
    q: [T; 4],
    qn: T,
    r: M3<T>,
    /// Per-axis standard deviations.
    s: [T; 3],
    mm: M3<T>,
    sig: M3<T>,
}

impl<T: Real> Cov3<T> {
    #[inline(always)]
    fn new(g: &Gaussians<T>, i: usize) -> Self {
        let (q, qn) = normalized(g.rotations[i]);
        let r = quat_to_mat(q);
        let s = g.log_scales[i].map(|v| v.exp());
        let mm: M3<T> = std::array::from_fn(|a| std::array::from_fn(|b| r[a][b] * s[b]));
        let sig = sym_mmt(&mm);
        Self {
            q,
            qn,
            r,
            s,
            mm,
            sig,
        }
    }
}

/// T = J W for a camera-space centre, J the Jacobian of the perspective projection with x/z and
/// y/z clamped to the guarded field of view (`sx`, `sy`: the sign of the clamp, if any).
struct Jacobian<T> {
    tm: [[T; 3]; 2],
    sx: Option<T>,
    sy: Option<T>,
}

impl<T: Real> Jacobian<T> {
    #[inline(always)]
    fn new(cam: &Cam<T>, tc: [T; 3]) -> Self {
        let w = &cam.w;
        let inv_z = T::one() / tc[2];
        let (txc, sx) = clamp_ratio(tc[0], tc[2], cam.lim_x);
        let (tyc, sy) = clamp_ratio(tc[1], tc[2], cam.lim_y);
        let j00 = cam.fx * inv_z;
        let j02 = -cam.fx * txc * inv_z * inv_z;
        let j11 = cam.fy * inv_z;
        let j12 = -cam.fy * tyc * inv_z * inv_z;
        let tm = [
            std::array::from_fn(|c| j00 * w[0][c] + j02 * w[2][c]),
            std::array::from_fn(|c| j11 * w[1][c] + j12 * w[2][c]),
        ];
        Self { tm, sx, sy }
    }
}

/// M Mᵀ for a 3×3 M (symmetric result).
#[inline(always)]
fn sym_mmt<T: Real>(m: &M3<T>) -> M3<T> {
    std::array::from_fn(|a| {
        std::array::from_fn(|b| m[a][0] * m[b][0] + m[a][1] * m[b][1] + m[a][2] * m[b][2])
    })
}

/// (A, B, C) of T Σ Tᵀ for a 2×3 T and symmetric Σ.
#[inline(always)]
fn cov2d<T: Real>(tm: &[[T; 3]; 2], sig: &M3<T>) -> (T, T, T) {
    let ts: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| tm[r][0] * sig[0][c] + tm[r][1] * sig[1][c] + tm[r][2] * sig[2][c])
    });
    let dot = |a: &[T; 3], b: &[T; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    (
        dot(&ts[0], &tm[0]),
        dot(&ts[0], &tm[1]),
        dot(&ts[1], &tm[1]),
    )
}

/// Screen-space gradients of one Gaussian, summed over every pixel it touched.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct ScreenGrad<T> {
    pub xy: [T; 2],
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
}

/// Parameter gradients of one Gaussian.
pub(crate) struct ParamGrad<T> {
    pub mean: [T; 3],
    pub log_scale: [T; 3],
    pub rotation: [T; 4],
    pub opacity_logit: T,
    pub dc: [T; 3],
}

/// Back-propagates ∂L/∂colour of Gaussian `i` (the colour [`sh_color`] gave, `clamped` its
/// clamp flags) to its SH coefficients: returns ∂L/∂DC and ∂L/∂mean through the view
/// direction, and writes ∂L/∂SH-rest into `rest_out` (length `g.rest_len()`).
pub(crate) fn colour_backward<T: Real>(
    g: &Gaussians<T>,
    i: usize,
    cam: &Cam<T>,
    sh_degree: u8,
    clamped: [bool; 3],
    d_colour: [T; 3],
    rest_out: &mut [T],
) -> ([T; 3], [T; 3]) {
    let zero = T::zero();
    let mut d_mean = [zero; 3];
    let dcol: [T; 3] = std::array::from_fn(|ch| if clamped[ch] { zero } else { d_colour[ch] });
    let c0 = T::c(0.282_094_791_773_878_1);
    let d_dc = dcol.map(|v| c0 * v);
    rest_out.iter_mut().for_each(|v| *v = zero);
    if sh_degree > 0 {
        let (d, len) = view_dir(g.means[i], cam);
        let b = sh::basis(sh_degree, d);
        let bg = sh::basis_grad(sh_degree, d);
        let rest = g.rest_of(i);
        let mut d_dir = [zero; 3];
        for k in 1..sh::basis_len(sh_degree) {
            let mut s = zero;
            for ch in 0..3 {
                rest_out[(k - 1) * 3 + ch] = b[k] * dcol[ch];
                s = s + rest[(k - 1) * 3 + ch] * dcol[ch];
            }
            for a in 0..3 {
                d_dir[a] = d_dir[a] + s * bg[k][a];
            }
        }
        let dd = d[0] * d_dir[0] + d[1] * d_dir[1] + d[2] * d_dir[2];
        for a in 0..3 {
            d_mean[a] = d_mean[a] + (d_dir[a] - d[a] * dd) / len;
        }
    }
    (d_dc, d_mean)
}

/// Back-propagates screen-space gradients of Gaussian `i` to its parameters; the SH-rest
/// gradient is written into `rest_out` (length `g.rest_len()`).
pub(crate) fn project_backward<T: Real>(
    g: &Gaussians<T>,
    i: usize,
    cam: &Cam<T>,
    sh_degree: u8,
    p: &Projection<T>,
    sg: &ScreenGrad<T>,
    rest_out: &mut [T],
) -> ParamGrad<T> {
    let zero = T::zero();
    let one = T::one();
    let two = T::c(2.0);
    let w = &cam.w;

    // Colour → SH coefficients and view direction.
    let (d_dc, mut d_mean) = colour_backward(g, i, cam, sh_degree, p.clamped, sg.color, rest_out);

    // Opacity through the sigmoid.
    let d_logit = sg.opacity * p.opacity * (one - p.opacity);

    // Conic (a, b, c) → 2D covariance (A, B, C).
    let [ca, cb, cc] = p.cov2;
    let det = ca * cc - cb * cb;
    let id2 = one / (det * det);
    let [ga, gb, gc] = sg.conic;
    let d_ca = (-cc * cc * ga + cb * cc * gb - cb * cb * gc) * id2;
    let d_cb = (two * cb * cc * ga - (ca * cc + cb * cb) * gb + two * ca * cb * gc) * id2;
    let d_cc = (-cb * cb * ga + ca * cb * gb - ca * ca * gc) * id2;

    // Recompute the 3D covariance chain.
    let Cov3 {
        q,
        qn,
        r,
        s,
        mm,
        sig,
    } = Cov3::new(g, i);
    let [tx, ty, z] = p.tc;
    let inv_z = one / z;
    let Jacobian { tm, sx, sy } = Jacobian::new(cam, p.tc);
    // Symmetric gradient of Σ′ (off-diagonal split between the two entries).
    let half = T::c(0.5);
    let g2 = [[d_ca, half * d_cb], [half * d_cb, d_cc]];
    // dΣ = Tᵀ G2 T
    let g2t: [[T; 3]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|c| g2[r][0] * tm[0][c] + g2[r][1] * tm[1][c]));
    let d_sig: M3<T> = std::array::from_fn(|a| {
        std::array::from_fn(|b| tm[0][a] * g2t[0][b] + tm[1][a] * g2t[1][b])
    });
    // dT = 2 G2 T Σ
    let d_tm: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            two * (g2t[r][0] * sig[0][c] + g2t[r][1] * sig[1][c] + g2t[r][2] * sig[2][c])
        })
    });
    // dJ = dT Wᵀ (only the four non-zero entries of J matter).
    let dj =
        |r: usize, k: usize| d_tm[r][0] * w[k][0] + d_tm[r][1] * w[k][1] + d_tm[r][2] * w[k][2];
    let (dj00, dj02, dj11, dj12) = (dj(0, 0), dj(0, 2), dj(1, 1), dj(1, 2));
    let iz2 = inv_z * inv_z;
    let mut d_t = [zero; 3];
    d_t[2] = d_t[2] - cam.fx * iz2 * dj00 - cam.fy * iz2 * dj11;
    match sx {
        None => {
            d_t[0] = d_t[0] - cam.fx * iz2 * dj02;
            d_t[2] = d_t[2] + two * cam.fx * tx * iz2 * inv_z * dj02;
        }
        Some(sgn) => d_t[2] = d_t[2] + cam.fx * sgn * cam.lim_x * iz2 * dj02,
    }
    match sy {
        None => {
            d_t[1] = d_t[1] - cam.fy * iz2 * dj12;
            d_t[2] = d_t[2] + two * cam.fy * ty * iz2 * inv_z * dj12;
        }
        Some(sgn) => d_t[2] = d_t[2] + cam.fy * sgn * cam.lim_y * iz2 * dj12,
    }
    // Screen-space mean.
    d_t[0] = d_t[0] + cam.fx * inv_z * sg.xy[0];
    d_t[1] = d_t[1] + cam.fy * inv_z * sg.xy[1];
    d_t[2] = d_t[2] - (cam.fx * tx * sg.xy[0] + cam.fy * ty * sg.xy[1]) * iz2;
    // Camera space → world: dμ += Wᵀ dt.
    for a in 0..3 {
        d_mean[a] = d_mean[a] + w[0][a] * d_t[0] + w[1][a] * d_t[1] + w[2][a] * d_t[2];
    }

    // Σ = M Mᵀ → dM = 2 dΣ M; M = R S.
    let d_m: M3<T> = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            two * (d_sig[a][0] * mm[0][b] + d_sig[a][1] * mm[1][b] + d_sig[a][2] * mm[2][b])
        })
    });
    let d_log_scale: [T; 3] = std::array::from_fn(|c| {
        (r[0][c] * d_m[0][c] + r[1][c] * d_m[1][c] + r[2][c] * d_m[2][c]) * s[c]
    });
    let gr: M3<T> = std::array::from_fn(|a| std::array::from_fn(|b| d_m[a][b] * s[b]));
    let [qw, qx, qy, qz] = q;
    let dq = [
        two * (-qz * gr[0][1] + qy * gr[0][2] + qz * gr[1][0] - qx * gr[1][2] - qy * gr[2][0]
            + qx * gr[2][1]),
        two * (qy * gr[0][1] + qz * gr[0][2] + qy * gr[1][0] - two * qx * gr[1][1] - qw * gr[1][2]
            + qz * gr[2][0]
            + qw * gr[2][1]
            - two * qx * gr[2][2]),
        two * (-two * qy * gr[0][0]
            + qx * gr[0][1]
            + qw * gr[0][2]
            + qx * gr[1][0]
            + qz * gr[1][2]
            - qw * gr[2][0]
            + qz * gr[2][1]
            - two * qy * gr[2][2]),
        two * (-two * qz * gr[0][0] - qw * gr[0][1] + qx * gr[0][2] + qw * gr[1][0]
            - two * qz * gr[1][1]
            + qy * gr[1][2]
            + qx * gr[2][0]
            + qy * gr[2][1]),
    ];
    // Through the normalisation q̂ = q/|q|.
    let qd = q[0] * dq[0] + q[1] * dq[1] + q[2] * dq[2] + q[3] * dq[3];
    let d_rot: [T; 4] = std::array::from_fn(|k| (dq[k] - q[k] * qd) / qn);

    ParamGrad {
        mean: d_mean,
        log_scale: d_log_scale,
        rotation: d_rot,
        opacity_logit: d_logit,
        dc: d_dc,
    }
}
