// Exclusive prefix sum of u32 in blocks of 256: `scan_blocks` scans each block in place and
// writes the block's total to `sums`; once `sums` is itself scanned (the same two kernels, one
// level up), `add_sums` adds each block's offset. Integer sums: the result is exact and the
// same on every device.

struct Params {
    n: u32,
    groups_x: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

var<workgroup> tmp: array<u32, 256>;

@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let block = wid.x + wid.y * p.groups_x;
    let i = block * 256u + lid;
    var v = 0u;
    if (i < p.n) {
        v = data[i];
    }
    tmp[lid] = v;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off = off * 2u) {
        var add = 0u;
        if (lid >= off) {
            add = tmp[lid - off];
        }
        workgroupBarrier();
        tmp[lid] = tmp[lid] + add;
        workgroupBarrier();
    }
    if (i < p.n) {
        data[i] = tmp[lid] - v;
    }
    if (lid == 255u && block < (p.n + 255u) / 256u) {
        sums[block] = tmp[255];
    }
}

@compute @workgroup_size(256)
fn add_sums(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let block = wid.x + wid.y * p.groups_x;
    let i = block * 256u + lid;
    if (i < p.n) {
        data[i] = data[i] + sums[block];
    }
}
