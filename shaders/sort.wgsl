// One pass of a stable LSD radix sort of (key, value) pairs on a 4-bit digit of the 64-bit key
// (hi, lo): `count` histograms each block of 256 pairs into `hist[digit · blocks + block]`;
// after an exclusive scan of `hist` (digit-major, so equal digits keep block order),
// `scatter` writes each pair to its digit's offset plus its rank among the equal digits before
// it in its block (so equal digits keep their order within the block too).

struct Params {
    n: u32,
    blocks: u32,
    groups_x: u32,
    // Bit of the 64-bit key the digit starts at (0–63).
    shift: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> hi_in: array<u32>;
@group(0) @binding(2) var<storage, read> lo_in: array<u32>;
@group(0) @binding(3) var<storage, read> val_in: array<u32>;
@group(0) @binding(4) var<storage, read_write> hi_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> lo_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> val_out: array<u32>;
@group(0) @binding(7) var<storage, read_write> hist: array<u32>;

var<workgroup> counts: array<atomic<u32>, 16>;
var<workgroup> digits: array<u32, 256>;

fn digit(i: u32) -> u32 {
    if (p.shift >= 32u) {
        return (hi_in[i] >> (p.shift - 32u)) & 15u;
    }
    return (lo_in[i] >> p.shift) & 15u;
}

@compute @workgroup_size(256)
fn count(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let block = wid.x + wid.y * p.groups_x;
    if (lid < 16u) {
        atomicStore(&counts[lid], 0u);
    }
    workgroupBarrier();
    let i = block * 256u + lid;
    if (i < p.n) {
        atomicAdd(&counts[digit(i)], 1u);
    }
    workgroupBarrier();
    if (lid < 16u && block < p.blocks) {
        hist[lid * p.blocks + block] = atomicLoad(&counts[lid]);
    }
}

@compute @workgroup_size(256)
fn scatter(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let block = wid.x + wid.y * p.groups_x;
    let i = block * 256u + lid;
    var d = 16u;
    if (i < p.n) {
        d = digit(i);
    }
    digits[lid] = d;
    workgroupBarrier();
    if (i < p.n) {
        var rank = 0u;
        for (var j = 0u; j < lid; j = j + 1u) {
            rank = rank + select(0u, 1u, digits[j] == d);
        }
        let dest = hist[d * p.blocks + block] + rank;
        hi_out[dest] = hi_in[i];
        lo_out[dest] = lo_in[i];
        val_out[dest] = val_in[i];
    }
}
