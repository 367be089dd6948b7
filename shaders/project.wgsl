// Per-Gaussian projection: the CPU reference's `render::project` and `Splat::new` in f32.
// One invocation per Gaussian: camera-space centre, EWA 2D covariance (+0.3 px² low-pass), its
// inverse (the conic), SH colour, opacity, the exact α ≥ 1/255 footprint's pixel rectangle, and
// how many 16×16 tiles the footprint touches (`band_tiles`, row by row).

@group(0) @binding(0) var<uniform> cam: Camera;
// Per Gaussian, `cam.stride` floats: mean (3), log-scale (3), quaternion w x y z (4), opacity
// logit (1), SH DC (3), the rest of the SH coefficients ((k − 1)·3 + channel); with colour
// overrides the three floats after those are the override colour.
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> splats: array<Splat>;
// Pixel rectangle [x0, x1) × [y0, y1) of each Gaussian's footprint (zero when it is not drawn).
@group(0) @binding(3) var<storage, read_write> tiles: array<vec4<u32>>;
// Tiles per Gaussian; one more entry than Gaussians (kept 0) so its exclusive scan ends with
// the total.
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

// `chunk`, the Gaussians one dispatch covers: `chunk.wgsl`. `splats`, `tiles`, `counts` and
// `aux` are bound whole and indexed by the global index.

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

// Unit direction camera centre → `m` (xyz) and the distance (w), as the reference's `view_dir`.
fn view_dir(m: vec3<f32>) -> vec4<f32> {
    let v = m - cam.center.xyz;
    let len = max(sqrt(v.x * v.x + v.y * v.y + v.z * v.z), 1e-12);
    return vec4<f32>(v / len, len);
}

// Gaussian `base`'s SH colour along unit direction `d`, + 0.5, before the clamp at 0.
fn sh_unclamped(base: u32, d: vec3<f32>) -> vec3<f32> {
    var col = C0 * vec3<f32>(params[base + 11u], params[base + 12u], params[base + 13u]);
    for (var k = 1u; k < basis_len(cam.sh_degree); k = k + 1u) {
        col += basis(k, d) * rest(base, k);
    }
    return col + vec3<f32>(0.5);
}

// The camera-space coordinate `v` the Jacobian uses, with v/z clamped to ±`lim` (INRIA's
// frustum guard), and the side it was clamped at (±1; 0 when it was not).
fn clamp_ratio(v: f32, z: f32, lim: f32) -> vec2<f32> {
    let r = v / z;
    if (r > lim) {
        return vec2<f32>(lim * z, 1.0);
    }
    if (r < -lim) {
        return vec2<f32>(-lim * z, -1.0);
    }
    return vec2<f32>(v, 0.0);
}

@compute @workgroup_size(256)
fn project(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = gid.x + gid.y * nwg.x * 256u;
    if (local >= chunk.count) {
        return;
    }
    let i = chunk.first + local;
    counts[i] = 0u;
    tiles[i] = vec4<u32>(0u);
    let base = chunk.params_at + local * cam.stride;
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
    let txc = clamp_ratio(tc.x, z, cam.lim_x).x;
    let tyc = clamp_ratio(tc.y, z, cam.lim_y).x;
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
        color = max(sh_unclamped(base, view_dir(m).xyz), vec3<f32>(0.0));
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
    let sp = Splat(xy, z, o, vec4<f32>(conic, thr), vec4<f32>(color, 0.0));
    splats[i] = sp;
    let rect = vec4<u32>(rx0, ry0, rx1, ry1);
    tiles[i] = rect;
    var count = 0u;
    for (var ty = ry0 / 16u; ty <= (ry1 - 1u) / 16u; ty = ty + 1u) {
        let rows = band_rows(rect, ty);
        let span = band_tiles(sp, rect, rows.x, rows.y, cam.tiles_x);
        count = count + (span.y - span.x);
    }
    counts[i] = count;
}

// ---- Backward: the screen-space gradients of `shaders/backward.wgsl`'s entry slots through the
// projection, per Gaussian (the CPU reference's `project_backward`). ----

// Floats per entry slot: xy (2), conic (3), opacity (1), colour (3), blend weight (1).
const SLOT: u32 = 10u;

@group(0) @binding(5) var<storage, read> slots: array<f32>;
// ∂L/∂parameters, `cam.stride` floats per Gaussian laid out like `params` (minus the
// override colour).
@group(0) @binding(6) var<storage, read_write> grads: array<f32>;
// Per Gaussian: ∂L/∂colour (3), Σ α·T (1), ∂L/∂(x, y) of the screen centre (2).
@group(0) @binding(7) var<storage, read_write> aux: array<f32>;

// Writes ∂L/∂parameter `idx` of this dispatch's chunk, or adds it when accumulating.
fn put(idx: u32, v: f32) {
    if (chunk.accumulate != 0u) {
        grads[idx] = grads[idx] + v;
    } else {
        grads[idx] = v;
    }
}

fn basis_len(deg: u32) -> u32 {
    return (deg + 1u) * (deg + 1u);
}

// SH basis value k at unit direction d.
fn basis(k: u32, d: vec3<f32>) -> f32 {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    switch k {
        case 0u: { return C0; }
        case 1u: { return -C1 * y; }
        case 2u: { return C1 * z; }
        case 3u: { return -C1 * x; }
        case 4u: { return C2_0 * x * y; }
        case 5u: { return C2_1 * y * z; }
        case 6u: { return C2_2 * (2.0 * zz - xx - yy); }
        case 7u: { return C2_3 * x * z; }
        case 8u: { return C2_4 * (xx - yy); }
        case 9u: { return C3_0 * y * (3.0 * xx - yy); }
        case 10u: { return C3_1 * x * y * z; }
        case 11u: { return C3_2 * y * (4.0 * zz - xx - yy); }
        case 12u: { return C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy); }
        case 13u: { return C3_4 * x * (4.0 * zz - xx - yy); }
        case 14u: { return C3_5 * z * (xx - yy); }
        default: { return C3_6 * x * (xx - 3.0 * yy); }
    }
}

// ∂basis_k/∂(x, y, z), x, y, z independent.
fn basis_grad(k: u32, d: vec3<f32>) -> vec3<f32> {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    switch k {
        case 1u: { return vec3<f32>(0.0, -C1, 0.0); }
        case 2u: { return vec3<f32>(0.0, 0.0, C1); }
        case 3u: { return vec3<f32>(-C1, 0.0, 0.0); }
        case 4u: { return vec3<f32>(C2_0 * y, C2_0 * x, 0.0); }
        case 5u: { return vec3<f32>(0.0, C2_1 * z, C2_1 * y); }
        case 6u: { return vec3<f32>(-2.0 * C2_2 * x, -2.0 * C2_2 * y, 4.0 * C2_2 * z); }
        case 7u: { return vec3<f32>(C2_3 * z, 0.0, C2_3 * x); }
        case 8u: { return vec3<f32>(2.0 * C2_4 * x, -2.0 * C2_4 * y, 0.0); }
        case 9u: { return vec3<f32>(C3_0 * 6.0 * x * y, C3_0 * 3.0 * (xx - yy), 0.0); }
        case 10u: { return vec3<f32>(C3_1 * y * z, C3_1 * x * z, C3_1 * x * y); }
        case 11u: { return vec3<f32>(-2.0 * C3_2 * x * y, C3_2 * (4.0 * zz - xx - 3.0 * yy), C3_2 * 8.0 * y * z); }
        case 12u: { return vec3<f32>(-6.0 * C3_3 * x * z, -6.0 * C3_3 * y * z, C3_3 * (6.0 * zz - 3.0 * xx - 3.0 * yy)); }
        case 13u: { return vec3<f32>(C3_4 * (4.0 * zz - 3.0 * xx - yy), -2.0 * C3_4 * x * y, C3_4 * 8.0 * x * z); }
        case 14u: { return vec3<f32>(2.0 * C3_5 * x * z, -2.0 * C3_5 * y * z, C3_5 * (xx - yy)); }
        case 15u: { return vec3<f32>(C3_6 * 3.0 * (xx - yy), -C3_6 * 6.0 * x * y, 0.0); }
        default: { return vec3<f32>(0.0); }
    }
}

@compute @workgroup_size(256)
fn project_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = gid.x + gid.y * nwg.x * 256u;
    if (local >= chunk.count) {
        return;
    }
    let i = chunk.first + local;
    let gs = cam.stride - select(0u, 3u, cam.override_colors != 0u);
    let out = chunk.grads_at + local * gs;
    if (chunk.accumulate == 0u) {
        for (var k = 0u; k < gs; k = k + 1u) {
            grads[out + k] = 0.0;
        }
    }
    for (var k = 0u; k < 6u; k = k + 1u) {
        aux[i * 6u + k] = 0.0;
    }
    let o0 = counts[i];
    let o1 = counts[i + 1u];
    if (o0 == o1) {
        return;
    }
    // Sum of the entries' slots, in entry order.
    var g_xy = vec2<f32>(0.0);
    var g_conic = vec3<f32>(0.0);
    var g_opacity = 0.0;
    var g_color = vec3<f32>(0.0);
    var g_w = 0.0;
    for (var e = o0; e < o1; e = e + 1u) {
        let s = e * SLOT;
        g_xy += vec2<f32>(slots[s], slots[s + 1u]);
        g_conic += vec3<f32>(slots[s + 2u], slots[s + 3u], slots[s + 4u]);
        g_opacity += slots[s + 5u];
        g_color += vec3<f32>(slots[s + 6u], slots[s + 7u], slots[s + 8u]);
        g_w += slots[s + 9u];
    }
    aux[i * 6u] = g_color.x;
    aux[i * 6u + 1u] = g_color.y;
    aux[i * 6u + 2u] = g_color.z;
    aux[i * 6u + 3u] = g_w;
    aux[i * 6u + 4u] = g_xy.x;
    aux[i * 6u + 5u] = g_xy.y;

    let base = chunk.params_at + local * cam.stride;
    let m = vec3<f32>(params[base], params[base + 1u], params[base + 2u]);
    var w: array<vec3<f32>, 3>;
    w[0] = cam.w0.xyz;
    w[1] = cam.w1.xyz;
    w[2] = cam.w2.xyz;
    let tc = vec3<f32>(
        w[0].x * m.x + w[0].y * m.y + w[0].z * m.z + cam.t.x,
        w[1].x * m.x + w[1].y * m.y + w[1].z * m.z + cam.t.y,
        w[2].x * m.x + w[2].y * m.y + w[2].z * m.z + cam.t.z,
    );
    let z = tc.z;
    let inv_z = 1.0 / z;

    // Colour → SH (an override colour depends on no parameter).
    var dcol = g_color;
    if (cam.override_colors != 0u) {
        dcol = vec3<f32>(0.0);
    }
    let deg = cam.sh_degree;
    let vd = view_dir(m);
    let d = vd.xyz;
    let len = vd.w;
    if (cam.override_colors == 0u) {
        // A channel clamped at 0 passes no gradient.
        dcol = select(dcol, vec3<f32>(0.0), sh_unclamped(base, d) < vec3<f32>(0.0));
    }
    put(out + 11u, C0 * dcol.x);
    put(out + 12u, C0 * dcol.y);
    put(out + 13u, C0 * dcol.z);
    var d_mean = vec3<f32>(0.0);
    if (deg > 0u) {
        var d_dir = vec3<f32>(0.0);
        for (var k = 1u; k < basis_len(deg); k = k + 1u) {
            let b = basis(k, d);
            let o = out + 14u + (k - 1u) * 3u;
            put(o, b * dcol.x);
            put(o + 1u, b * dcol.y);
            put(o + 2u, b * dcol.z);
            d_dir += dot(rest(base, k), dcol) * basis_grad(k, d);
        }
        let dd = dot(d, d_dir);
        d_mean += (d_dir - d * dd) / len;
    }

    // Opacity through the sigmoid.
    let op = 1.0 / (1.0 + exp(-params[base + 10u]));
    put(out + 10u, g_opacity * op * (1.0 - op));

    // The 3D covariance chain again.
    var q = vec4<f32>(params[base + 6u], params[base + 7u], params[base + 8u], params[base + 9u]);
    let qn = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    q = q / qn;
    let qw = q.x;
    let qx = q.y;
    let qy = q.z;
    let qz = q.w;
    var r: array<vec3<f32>, 3>;
    r[0] = vec3<f32>(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy));
    r[1] = vec3<f32>(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx));
    r[2] = vec3<f32>(2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
    let s = exp(vec3<f32>(params[base + 3u], params[base + 4u], params[base + 5u]));
    var mm: array<vec3<f32>, 3>;
    for (var a = 0u; a < 3u; a = a + 1u) {
        mm[a] = r[a] * s;
    }
    var sig: array<vec3<f32>, 3>;
    for (var a = 0u; a < 3u; a = a + 1u) {
        sig[a] = vec3<f32>(dot(mm[a], mm[0]), dot(mm[a], mm[1]), dot(mm[a], mm[2]));
    }

    // Jacobian with the frustum guard, and which side (if any) clamped.
    let cx = clamp_ratio(tc.x, z, cam.lim_x);
    let cy = clamp_ratio(tc.y, z, cam.lim_y);
    let txc = cx.x;
    let sgx = cx.y;
    let tyc = cy.x;
    let sgy = cy.y;
    let j00 = cam.fx * inv_z;
    let j02 = -cam.fx * txc * inv_z * inv_z;
    let j11 = cam.fy * inv_z;
    let j12 = -cam.fy * tyc * inv_z * inv_z;
    var tm: array<vec3<f32>, 2>;
    tm[0] = j00 * w[0] + j02 * w[2];
    tm[1] = j11 * w[1] + j12 * w[2];
    let ts0 = vec3<f32>(dot(tm[0], sig[0]), dot(tm[0], sig[1]), dot(tm[0], sig[2]));
    let ts1 = vec3<f32>(dot(tm[1], sig[0]), dot(tm[1], sig[1]), dot(tm[1], sig[2]));
    let ca = dot(ts0, tm[0]) + 0.3;
    let cb = dot(ts0, tm[1]);
    let cc = dot(ts1, tm[1]) + 0.3;

    // Conic → 2D covariance.
    let det = ca * cc - cb * cb;
    let id2 = 1.0 / (det * det);
    let ga = g_conic.x;
    let gb = g_conic.y;
    let gc = g_conic.z;
    let d_ca = (-cc * cc * ga + cb * cc * gb - cb * cb * gc) * id2;
    let d_cb = (2.0 * cb * cc * ga - (ca * cc + cb * cb) * gb + 2.0 * ca * cb * gc) * id2;
    let d_cc = (-cb * cb * ga + ca * cb * gb - ca * ca * gc) * id2;
    // dΣ = Tᵀ G2 T, dT = 2 G2 T Σ.
    var g2t: array<vec3<f32>, 2>;
    g2t[0] = d_ca * tm[0] + (0.5 * d_cb) * tm[1];
    g2t[1] = (0.5 * d_cb) * tm[0] + d_cc * tm[1];
    var d_sig: array<vec3<f32>, 3>;
    for (var a = 0u; a < 3u; a = a + 1u) {
        d_sig[a] = tm[0][a] * g2t[0] + tm[1][a] * g2t[1];
    }
    var d_tm: array<vec3<f32>, 2>;
    for (var rr = 0u; rr < 2u; rr = rr + 1u) {
        d_tm[rr] = 2.0 * (g2t[rr].x * sig[0] + g2t[rr].y * sig[1] + g2t[rr].z * sig[2]);
    }
    let dj00 = dot(d_tm[0], w[0]);
    let dj02 = dot(d_tm[0], w[2]);
    let dj11 = dot(d_tm[1], w[1]);
    let dj12 = dot(d_tm[1], w[2]);
    let iz2 = inv_z * inv_z;
    var d_t = vec3<f32>(0.0);
    d_t.z = d_t.z - cam.fx * iz2 * dj00 - cam.fy * iz2 * dj11;
    if (sgx == 0.0) {
        d_t.x = d_t.x - cam.fx * iz2 * dj02;
        d_t.z = d_t.z + 2.0 * cam.fx * tc.x * iz2 * inv_z * dj02;
    } else {
        d_t.z = d_t.z + cam.fx * sgx * cam.lim_x * iz2 * dj02;
    }
    if (sgy == 0.0) {
        d_t.y = d_t.y - cam.fy * iz2 * dj12;
        d_t.z = d_t.z + 2.0 * cam.fy * tc.y * iz2 * inv_z * dj12;
    } else {
        d_t.z = d_t.z + cam.fy * sgy * cam.lim_y * iz2 * dj12;
    }
    // Screen-space mean.
    d_t.x = d_t.x + cam.fx * inv_z * g_xy.x;
    d_t.y = d_t.y + cam.fy * inv_z * g_xy.y;
    d_t.z = d_t.z - (cam.fx * tc.x * g_xy.x + cam.fy * tc.y * g_xy.y) * iz2;
    // Camera space → world.
    d_mean += w[0] * d_t.x + w[1] * d_t.y + w[2] * d_t.z;
    put(out, d_mean.x);
    put(out + 1u, d_mean.y);
    put(out + 2u, d_mean.z);

    // Σ = M Mᵀ → dM = 2 dΣ M; M = R S.
    var d_m: array<vec3<f32>, 3>;
    for (var a = 0u; a < 3u; a = a + 1u) {
        d_m[a] = 2.0 * (d_sig[a].x * mm[0] + d_sig[a].y * mm[1] + d_sig[a].z * mm[2]);
    }
    for (var c = 0u; c < 3u; c = c + 1u) {
        put(out + 3u + c, (r[0][c] * d_m[0][c] + r[1][c] * d_m[1][c] + r[2][c] * d_m[2][c]) * s[c]);
    }
    var gr: array<vec3<f32>, 3>;
    for (var a = 0u; a < 3u; a = a + 1u) {
        gr[a] = d_m[a] * s;
    }
    let dq = vec4<f32>(
        2.0 * (-qz * gr[0][1] + qy * gr[0][2] + qz * gr[1][0] - qx * gr[1][2] - qy * gr[2][0] + qx * gr[2][1]),
        2.0 * (qy * gr[0][1] + qz * gr[0][2] + qy * gr[1][0] - 2.0 * qx * gr[1][1] - qw * gr[1][2] + qz * gr[2][0] + qw * gr[2][1] - 2.0 * qx * gr[2][2]),
        2.0 * (-2.0 * qy * gr[0][0] + qx * gr[0][1] + qw * gr[0][2] + qx * gr[1][0] + qz * gr[1][2] - qw * gr[2][0] + qz * gr[2][1] - 2.0 * qy * gr[2][2]),
        2.0 * (-2.0 * qz * gr[0][0] - qw * gr[0][1] + qx * gr[0][2] + qw * gr[1][0] - 2.0 * qz * gr[1][1] + qy * gr[1][2] + qx * gr[2][0] + qy * gr[2][1]),
    );
    let qd = dot(q, dq);
    let d_rot = (dq - q * qd) / qn;
    put(out + 6u, d_rot.x);
    put(out + 7u, d_rot.y);
    put(out + 8u, d_rot.z);
    put(out + 9u, d_rot.w);
}
