// Shared by every kernel file (prepended by `src/render/gpu/mod.rs`): the camera uniform, the
// projected Gaussian, and the exact tiles an α ≥ 1/255 footprint touches.

// The camera and render settings (`gpu::camera_uniform` writes it).
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

// Tile columns [a, b) touched by splat `s` (pixel rectangle `rect`) within the band of pixel
// rows [y0, y1): the exact x-extent of its footprint ellipse over that band, as the CPU
// reference's `Splat::band_tiles` bins it (elongated Gaussians do not claim every tile of their
// bounding box).
fn band_tiles(s: Splat, rect: vec4<u32>, y0: u32, y1: u32, tiles_x: u32) -> vec2<u32> {
    let a = s.conic.x;
    let b = s.conic.y;
    let c = s.conic.z;
    let thr = s.conic.w;
    let det = a * c - b * b;
    let dy_max = sqrt(2.0 * a * thr / det);
    let lo_dy = max(f32(y0) + 0.5 - s.xy.y, -dy_max);
    let hi_dy = min(f32(y1) - 0.5 - s.xy.y, dy_max);
    if (!(lo_dy <= hi_dy)) {
        return vec2<u32>(0u);
    }
    let k = 2.0 * a * thr;
    let disc_lo = sqrt(max(k - det * lo_dy * lo_dy, 0.0));
    let disc_hi = sqrt(max(k - det * hi_dy * hi_dy, 0.0));
    let dx_max = sqrt(2.0 * thr * c / det);
    let dy_at_right = -b * dx_max / c;
    var r: f32;
    if (dy_at_right >= lo_dy && dy_at_right <= hi_dy) {
        r = dx_max;
    } else {
        r = max((-b * lo_dy + disc_lo) / a, (-b * hi_dy + disc_hi) / a);
    }
    var l: f32;
    if (-dy_at_right >= lo_dy && -dy_at_right <= hi_dy) {
        l = -dx_max;
    } else {
        l = min((-b * lo_dy - disc_lo) / a, (-b * hi_dy - disc_hi) / a);
    }
    let px_lo = max(ceil(s.xy.x + l - 0.5), f32(rect.x));
    let px_hi = min(floor(s.xy.x + r - 0.5), f32(rect.z) - 1.0);
    if (!(px_lo <= px_hi)) {
        return vec2<u32>(0u);
    }
    return vec2<u32>(u32(px_lo) / 16u, min(u32(px_hi) / 16u + 1u, tiles_x));
}

// Pixel rows [y0, y1) of tile row `ty` within `rect`.
fn band_rows(rect: vec4<u32>, ty: u32) -> vec2<u32> {
    return vec2<u32>(max(ty * 16u, rect.y), min((ty + 1u) * 16u, rect.w));
}
