// Backward pass, the CPU reference's `render::backward` on the GPU:
// - `raster_backward`: one 16×16 workgroup per tile walks the tile's entries back to front,
//   each pixel rebuilding its transmittance from the forward pass's final T, and writes each
//   entry's screen-space gradient (∂L/∂xy, ∂L/∂conic, ∂L/∂opacity, ∂L/∂colour, Σ α·T),
//   summed over the tile's pixels in a fixed order, to the entry's slot in emission order;
// - `project_backward` (in `project.wgsl`): one invocation per Gaussian sums its entries' slots
//   in order (its tiles, row-major) and carries the sum through the projection to ∂L/∂(mean,
//   log-scale, quaternion, opacity logit, SH).
// No float atomics: the result is the same on every run. Workgroup memory stays under the 16 KiB
// every adapter offers: splats are loaded 128 at a time.

// Floats per entry slot: xy (2), conic (3), opacity (1), colour (3), blend weight (1).
const SLOT: u32 = 10u;

@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read> splats: array<Splat>;
@group(0) @binding(2) var<storage, read> vals: array<u32>;
@group(0) @binding(3) var<storage, read> owner: array<u32>;
@group(0) @binding(4) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(5) var<storage, read> final_t: array<f32>;
@group(0) @binding(6) var<storage, read> n_contrib: array<u32>;
// ∂L/∂pixel, row-major RGB.
@group(0) @binding(7) var<storage, read> d_image: array<f32>;
@group(1) @binding(0) var<storage, read_write> entry_grads: array<f32>;

const BATCH: u32 = 128u;

var<workgroup> s_xy: array<vec2<f32>, BATCH>;
var<workgroup> s_conic: array<vec4<f32>, BATCH>;
var<workgroup> s_color: array<vec4<f32>, BATCH>;
var<workgroup> s_opacity: array<f32, BATCH>;
var<workgroup> red: array<array<f32, 256>, 10>;
var<workgroup> max_contrib: atomic<u32>;
var<workgroup> walk: u32;

@compute @workgroup_size(16, 16)
fn raster_backward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid3: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let tile = wid.y * cam.tiles_x + wid.x;
    let px = wid.x * 16u + lid3.x;
    let py = wid.y * 16u + lid3.y;
    let inside = px < cam.width && py < cam.height;
    let range = ranges[tile];
    var ft = 1.0;
    var ncon = 0u;
    var dpix = vec3<f32>(0.0);
    if (inside) {
        let p = py * cam.width + px;
        ft = final_t[p];
        ncon = n_contrib[p];
        dpix = vec3<f32>(d_image[p * 3u], d_image[p * 3u + 1u], d_image[p * 3u + 2u]);
    }
    let bg_dot = dot(cam.bg.xyz, dpix);
    var trans = ft;
    var acc = vec3<f32>(0.0);
    var last_alpha = 0.0;
    var last_color = vec3<f32>(0.0);
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;

    if (lid == 0u) {
        atomicStore(&max_contrib, 0u);
    }
    workgroupBarrier();
    atomicMax(&max_contrib, ncon);
    workgroupBarrier();
    if (lid == 0u) {
        walk = min(atomicLoad(&max_contrib), range.y - range.x);
    }
    let n = workgroupUniformLoad(&walk);
    let batches = (n + BATCH - 1u) / BATCH;
    for (var bi = 0u; bi < batches; bi = bi + 1u) {
        let start = (batches - 1u - bi) * BATCH;
        let count = min(BATCH, n - start);
        workgroupBarrier();
        if (lid < count) {
            let s = splats[owner[vals[range.x + start + lid]]];
            s_xy[lid] = s.xy;
            s_conic[lid] = s.conic;
            s_color[lid] = s.color;
            s_opacity[lid] = s.opacity;
        }
        workgroupBarrier();
        for (var jj = 0u; jj < count; jj = jj + 1u) {
            let j = count - 1u - jj;
            var g_xy = vec2<f32>(0.0);
            var g_conic = vec3<f32>(0.0);
            var g_opacity = 0.0;
            var g_color = vec3<f32>(0.0);
            var g_w = 0.0;
            if (start + j < ncon) {
                let con = s_conic[j];
                let dx = fx - s_xy[j].x;
                let dy = fy - s_xy[j].y;
                let sigma = dx * (0.5 * con.x * dx + con.y * dy) + 0.5 * con.z * dy * dy;
                let gauss = exp(-sigma);
                let o = s_opacity[j];
                let og = o * gauss;
                let alpha = min(og, 0.99);
                if (sigma <= con.w && alpha >= cam.alpha_min) {
                    let t_p = trans / (1.0 - alpha);
                    trans = t_p;
                    let w = alpha * t_p;
                    g_w = w;
                    acc = last_alpha * last_color + (1.0 - last_alpha) * acc;
                    let col = s_color[j].xyz;
                    last_color = col;
                    g_color = w * dpix;
                    var d_alpha = dot(col - acc, dpix);
                    d_alpha = d_alpha * t_p - ft / (1.0 - alpha) * bg_dot;
                    last_alpha = alpha;
                    if (og < 0.99) {
                        g_opacity = gauss * d_alpha;
                        let d_g = o * d_alpha * gauss;
                        g_xy = d_g * vec2<f32>(con.x * dx + con.y * dy, con.y * dx + con.z * dy);
                        g_conic = vec3<f32>(-d_g * 0.5 * dx * dx, -d_g * dx * dy, -d_g * 0.5 * dy * dy);
                    }
                }
            }
            // Sum over the 256 pixels in a fixed order with three barriers: each pixel
            // parks its values; 160 threads sum one (value, pixel row) each; 10 threads sum
            // the 16 row sums and write the entry's slot.
            red[0][lid] = g_xy.x;
            red[1][lid] = g_xy.y;
            red[2][lid] = g_conic.x;
            red[3][lid] = g_conic.y;
            red[4][lid] = g_conic.z;
            red[5][lid] = g_opacity;
            red[6][lid] = g_color.x;
            red[7][lid] = g_color.y;
            red[8][lid] = g_color.z;
            red[9][lid] = g_w;
            workgroupBarrier();
            if (lid < 160u) {
                let f = lid / 16u;
                let row = (lid % 16u) * 16u;
                var sum = 0.0;
                for (var k = 0u; k < 16u; k = k + 1u) {
                    sum = sum + red[f][row + k];
                }
                red[f][row] = sum;
            }
            workgroupBarrier();
            if (lid < SLOT) {
                var sum = 0.0;
                for (var row = 0u; row < 256u; row = row + 16u) {
                    sum = sum + red[lid][row];
                }
                entry_grads[vals[range.x + start + j] * SLOT + lid] = sum;
            }
            // The next entry's values must not land before the sum is read.
            workgroupBarrier();
        }
    }
}
