// Binning and compositing, the CPU reference's `render::forward` on the GPU:
// - `emit`: each drawn Gaussian writes a (tile, depth) key and its index for every tile of its
//   rectangle, at its offset from the scan of the per-Gaussian tile counts (in scene order, so
//   the stable sort keeps equal depths in scene order, as the reference does);
// - `ranges`: after the sort, each tile's [start, end) in the sorted list;
// - `raster`: one 16×16 workgroup per tile composites its Gaussians front to back:
//   α = min(0.99, o·e^(−σ)), skipped outside the α ≥ 1/255 footprint and below 1/255, stop
//   before T would fall below 1e-4, then the background behind what is left of T.

@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read> splats: array<Splat>;
@group(0) @binding(2) var<storage, read> tiles: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_hi: array<u32>;
@group(0) @binding(5) var<storage, read_write> keys_lo: array<u32>;
// The sort's values: each pair's position in emission order (its "entry"), so per-entry
// results can be written back where each Gaussian's entries lie together.
@group(0) @binding(6) var<storage, read_write> vals: array<u32>;
// [start, end) per tile.
@group(0) @binding(7) var<storage, read_write> ranges: array<vec2<u32>>;
// The Gaussian of each entry.
@group(0) @binding(8) var<storage, read_write> owner: array<u32>;

@compute @workgroup_size(256)
fn emit(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if (i >= cam.n) {
        return;
    }
    var o = offsets[i];
    if (o == offsets[i + 1u]) {
        return;
    }
    let rect = tiles[i];
    let s = splats[i];
    let depth = bitcast<u32>(s.depth);
    for (var ty = rect.y / 16u; ty <= (rect.w - 1u) / 16u; ty = ty + 1u) {
        let rows = band_rows(rect, ty);
        let span = band_tiles(s, rect, rows.x, rows.y, cam.tiles_x);
        for (var tx = span.x; tx < span.y; tx = tx + 1u) {
            keys_hi[o] = ty * cam.tiles_x + tx;
            keys_lo[o] = depth;
            vals[o] = o;
            owner[o] = i;
            o = o + 1u;
        }
    }
}

// `offsets[cam.n]` is the number of (tile, Gaussian) pairs.
@compute @workgroup_size(256)
fn tile_ranges(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let k = gid.x + gid.y * nwg.x * 256u;
    let total = offsets[cam.n];
    if (k >= total) {
        return;
    }
    let t = keys_hi[k];
    if (k == 0u || keys_hi[k - 1u] != t) {
        ranges[t].x = k;
    }
    if (k + 1u == total || keys_hi[k + 1u] != t) {
        ranges[t].y = k + 1u;
    }
}

@group(1) @binding(0) var<storage, read_write> image: array<f32>;
@group(1) @binding(1) var<storage, read_write> final_t: array<f32>;
// Per pixel: how many of its tile's entries were walked up to its last contributor.
@group(1) @binding(2) var<storage, read_write> n_contrib: array<u32>;

var<workgroup> s_xy: array<vec2<f32>, 256>;
var<workgroup> s_conic: array<vec4<f32>, 256>;
var<workgroup> s_color: array<vec4<f32>, 256>;
var<workgroup> s_opacity: array<f32, 256>;
var<workgroup> n_done: atomic<u32>;
var<workgroup> all_done: u32;

@compute @workgroup_size(16, 16)
fn raster(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid3: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let tile = wid.y * cam.tiles_x + wid.x;
    let px = wid.x * 16u + lid3.x;
    let py = wid.y * 16u + lid3.y;
    let inside = px < cam.width && py < cam.height;
    let range = ranges[tile];
    var trans = 1.0;
    var color = vec3<f32>(0.0);
    var done = !inside;
    var contrib = 0u;
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;
    let n = range.y - range.x;
    let batches = (n + 255u) / 256u;
    if (lid == 0u) {
        atomicStore(&n_done, 0u);
    }
    workgroupBarrier();
    if (done) {
        atomicAdd(&n_done, 1u);
    }
    for (var b = 0u; b < batches; b = b + 1u) {
        // Stop when every pixel of the tile is done.
        workgroupBarrier();
        if (lid == 0u) {
            all_done = atomicLoad(&n_done);
        }
        if (workgroupUniformLoad(&all_done) == 256u) {
            break;
        }
        let k = range.x + b * 256u + lid;
        if (k < range.y) {
            let s = splats[owner[vals[k]]];
            s_xy[lid] = s.xy;
            s_conic[lid] = s.conic;
            s_color[lid] = s.color;
            s_opacity[lid] = s.opacity;
        }
        workgroupBarrier();
        let count = min(256u, n - b * 256u);
        for (var j = 0u; j < count; j = j + 1u) {
            if (done) {
                break;
            }
            let con = s_conic[j];
            let dx = fx - s_xy[j].x;
            let dy = fy - s_xy[j].y;
            let sigma = dx * (0.5 * con.x * dx + con.y * dy) + 0.5 * con.z * dy * dy;
            if (sigma > con.w) {
                continue;
            }
            let alpha = min(0.99, s_opacity[j] * exp(-sigma));
            if (alpha < cam.alpha_min) {
                continue;
            }
            let test_t = trans * (1.0 - alpha);
            if (test_t < 1e-4) {
                done = true;
                atomicAdd(&n_done, 1u);
                break;
            }
            color = color + s_color[j].xyz * (alpha * trans);
            trans = test_t;
            contrib = b * 256u + j + 1u;
        }
    }
    if (inside) {
        let p = py * cam.width + px;
        let c = color + trans * cam.bg.xyz;
        image[p * 3u] = c.x;
        image[p * 3u + 1u] = c.y;
        image[p * 3u + 2u] = c.z;
        final_t[p] = trans;
        n_contrib[p] = contrib;
    }
}
