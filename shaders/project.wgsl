// Per-Gaussian projection: the CPU reference's `render::project` and `Splat::new` in f32.
// One invocation per Gaussian: camera-space centre, EWA 2D covariance (+0.3 px² low-pass), its
// inverse (the conic), SH colour, opacity, the exact α ≥ 1/255 footprint's pixel rectangle, and
// how many 16×16 tiles that rectangle covers.

struct Camera {
    w0: vec4<f32>,
    w1: vec4<f32>,
    w2: vec4<f32>,
    t: vec4<f32>,
    center: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    lim_x: f32,
    lim_y: f32,
    near: f32,
    alpha_min: f32,
    bg: vec4<f32>,
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    n: u32,
    sh_degree: u32,
    stride: u32,
    override_colors: u32,
}

// One visible Gaussian: screen centre, depth, opacity; conic (a, b, c) and the footprint's σ
// threshold; colour.
struct Splat {
    xy: vec2<f32>,
    depth: f32,
    opacity: f32,
    conic: vec4<f32>,
    color: vec4<f32>,
}

@group(0) @binding(0) var<uniform> cam: Camera;
// Per Gaussian, `cam.stride` floats: mean (3), log-scale (3), quaternion w x y z (4), opacity
// logit (1), SH DC (3), the rest of the SH coefficients ((k − 1)·3 + channel); with colour
// overrides the three floats after those are the override colour.
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> splats: array<Splat>;
// Tile rectangle [x0, x1) × [y0, y1) of each Gaussian (zero-sized when it is not drawn).
@group(0) @binding(3) var<storage, read_write> tiles: array<vec4<u32>>;
// Tiles per Gaussian; one more entry than Gaussians (kept 0) so its exclusive scan ends with
// the total.
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

const C0: f32 = 0.28209479177387814;
const C1: f32 = 0.4886025119029199;
const C2_0: f32 = 1.0925484305920792;
const C2_1: f32 = -1.0925484305920792;
const C2_2: f32 = 0.31539156525252005;
const C2_3: f32 = -1.0925484305920792;
const C2_4: f32 = 0.5462742152960396;
const C3_0: f32 = -0.5900435899266435;
const C3_1: f32 = 2.890611442640554;
const C3_2: f32 = -0.4570457994644658;
const C3_3: f32 = 0.3731763325901154;
const C3_4: f32 = -0.4570457994644658;
const C3_5: f32 = 1.445305721320277;
const C3_6: f32 = -0.5900435899266435;

fn rest(base: u32, k: u32) -> vec3<f32> {
    let o = base + 14u + (k - 1u) * 3u;
    return vec3<f32>(params[o], params[o + 1u], params[o + 2u]);
}

fn sh_color(base: u32, m: vec3<f32>) -> vec3<f32> {
    var col = C0 * vec3<f32>(params[base + 11u], params[base + 12u], params[base + 13u]);
    let deg = cam.sh_degree;
    if (deg > 0u) {
        let v = m - cam.center.xyz;
        let len = max(sqrt(v.x * v.x + v.y * v.y + v.z * v.z), 1e-12);
        let d = v / len;
        let x = d.x;
        let y = d.y;
        let z = d.z;
        col += (-C1 * y) * rest(base, 1u);
        col += (C1 * z) * rest(base, 2u);
        col += (-C1 * x) * rest(base, 3u);
        if (deg > 1u) {
            let xx = x * x;
            let yy = y * y;
            let zz = z * z;
            col += (C2_0 * x * y) * rest(base, 4u);
            col += (C2_1 * y * z) * rest(base, 5u);
            col += (C2_2 * (2.0 * zz - xx - yy)) * rest(base, 6u);
            col += (C2_3 * x * z) * rest(base, 7u);
            col += (C2_4 * (xx - yy)) * rest(base, 8u);
            if (deg > 2u) {
                col += (C3_0 * y * (3.0 * xx - yy)) * rest(base, 9u);
                col += (C3_1 * x * y * z) * rest(base, 10u);
                col += (C3_2 * y * (4.0 * zz - xx - yy)) * rest(base, 11u);
                col += (C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * rest(base, 12u);
                col += (C3_4 * x * (4.0 * zz - xx - yy)) * rest(base, 13u);
                col += (C3_5 * z * (xx - yy)) * rest(base, 14u);
                col += (C3_6 * x * (xx - 3.0 * yy)) * rest(base, 15u);
            }
        }
    }
    return max(col + vec3<f32>(0.5), vec3<f32>(0.0));
}

fn clamp_ratio(v: f32, z: f32, lim: f32) -> f32 {
    let r = v / z;
    if (r > lim) {
        return lim * z;
    }
    if (r < -lim) {
        return -lim * z;
    }
    return v;
}

@compute @workgroup_size(256)
fn project(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if (i >= cam.n) {
        return;
    }
    counts[i] = 0u;
    tiles[i] = vec4<u32>(0u);
    let base = i * cam.stride;
    let m = vec3<f32>(params[base], params[base + 1u], params[base + 2u]);
    let tc = vec3<f32>(
        cam.w0.x * m.x + cam.w0.y * m.y + cam.w0.z * m.z + cam.t.x,
        cam.w1.x * m.x + cam.w1.y * m.y + cam.w1.z * m.z + cam.t.y,
        cam.w2.x * m.x + cam.w2.y * m.y + cam.w2.z * m.z + cam.t.z,
    );
    let z = tc.z;
    if (!(z > cam.near)) {
        return;
    }
    let inv_z = 1.0 / z;
    let xy = vec2<f32>(cam.fx * tc.x * inv_z + cam.cx, cam.fy * tc.y * inv_z + cam.cy);

    // Σ = M Mᵀ, M = R S.
    var q = vec4<f32>(params[base + 6u], params[base + 7u], params[base + 8u], params[base + 9u]);
    q = q / sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    let qw = q.x;
    let qx = q.y;
    let qy = q.z;
    let qz = q.w;
    let r0 = vec3<f32>(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy));
    let r1 = vec3<f32>(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx));
    let r2 = vec3<f32>(2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
    let s = exp(vec3<f32>(params[base + 3u], params[base + 4u], params[base + 5u]));
    let m0 = r0 * s;
    let m1 = r1 * s;
    let m2 = r2 * s;
    let s00 = dot(m0, m0);
    let s01 = dot(m0, m1);
    let s02 = dot(m0, m2);
    let s11 = dot(m1, m1);
    let s12 = dot(m1, m2);
    let s22 = dot(m2, m2);

    // T = J W with the frustum guard.
    let txc = clamp_ratio(tc.x, z, cam.lim_x);
    let tyc = clamp_ratio(tc.y, z, cam.lim_y);
    let j00 = cam.fx * inv_z;
    let j02 = -cam.fx * txc * inv_z * inv_z;
    let j11 = cam.fy * inv_z;
    let j12 = -cam.fy * tyc * inv_z * inv_z;
    let t0 = j00 * cam.w0.xyz + j02 * cam.w2.xyz;
    let t1 = j11 * cam.w1.xyz + j12 * cam.w2.xyz;
    let ts0 = vec3<f32>(
        t0.x * s00 + t0.y * s01 + t0.z * s02,
        t0.x * s01 + t0.y * s11 + t0.z * s12,
        t0.x * s02 + t0.y * s12 + t0.z * s22,
    );
    let ts1 = vec3<f32>(
        t1.x * s00 + t1.y * s01 + t1.z * s02,
        t1.x * s01 + t1.y * s11 + t1.z * s12,
        t1.x * s02 + t1.y * s12 + t1.z * s22,
    );
    let ca = dot(ts0, t0) + 0.3;
    let cb = dot(ts0, t1);
    let cc = dot(ts1, t1) + 0.3;
    let det = ca * cc - cb * cb;
    if (!(det > 0.0)) {
        return;
    }
    let inv_det = 1.0 / det;
    let conic = vec3<f32>(cc * inv_det, -cb * inv_det, ca * inv_det);
    let mid = 0.5 * (ca + cc);
    let lambda_max = mid + sqrt(max(mid * mid - det, 0.0));

    let o = 1.0 / (1.0 + exp(-params[base + 10u]));
    if (!(o >= cam.alpha_min)) {
        return;
    }
    var color: vec3<f32>;
    if (cam.override_colors != 0u) {
        let c = base + cam.stride - 3u;
        color = vec3<f32>(params[c], params[c + 1u], params[c + 2u]);
    } else {
        color = sh_color(base, m);
    }
    // o·e^(−σ) ≥ 1/255 ⇔ σ ≤ ln(255·o), with the reference's margin.
    let thr = log(o / cam.alpha_min) + 0.01;
    let r = sqrt(2.0 * thr * lambda_max);
    let x0 = ceil(xy.x - r - 0.5);
    let x1 = floor(xy.x + r - 0.5);
    let y0 = ceil(xy.y - r - 0.5);
    let y1 = floor(xy.y + r - 0.5);
    let w = f32(cam.width);
    let h = f32(cam.height);
    if (!(x1 >= 0.0 && y1 >= 0.0 && x0 < w && y0 < h)) {
        return;
    }
    let rx0 = u32(min(max(x0, 0.0), w));
    let ry0 = u32(min(max(y0, 0.0), h));
    let rx1 = u32(min(max(x1 + 1.0, 0.0), w));
    let ry1 = u32(min(max(y1 + 1.0, 0.0), h));
    if (rx0 >= rx1 || ry0 >= ry1) {
        return;
    }
    splats[i] = Splat(xy, z, o, vec4<f32>(conic, thr), vec4<f32>(color, 0.0));
    let tx0 = rx0 / 16u;
    let tx1 = (rx1 - 1u) / 16u + 1u;
    let ty0 = ry0 / 16u;
    let ty1 = (ry1 - 1u) / 16u + 1u;
    tiles[i] = vec4<u32>(tx0, ty0, tx1, ty1);
    counts[i] = (tx1 - tx0) * (ty1 - ty0);
}
