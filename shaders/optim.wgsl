// The finetuning's optimiser on the device: the host's per-Gaussian Adam
// (`src/embed/finetune/optim.rs`), the Σ‖∂L_wm/∂θ_i‖ attribution statistic, the fidelity bound's
// offset scaling (`shrink_offsets`) and a removal's transparent copy — one invocation per
// Gaussian, in the host's order of operations, so results equal the host's up to rounding.
//
// Parameters, their gradients and Adam's moments share one layout: 14 + rest floats a Gaussian
// (mean 3, log-scale 3, quaternion 4, opacity logit 1, SH DC 3, the rest of the SH), the layout of
// `project.wgsl`'s `params` without a colour override. They are bound a chunk of Gaussians at a
// time (`src/render/gpu/chunk.rs`); with one layout every sliced binding's chunk starts at the
// same float, `chunk.params_at` (`chunk.wgsl`).

struct Step {
    // Floats a Gaussian (14 + rest).
    floats: u32,
    // Both routes' gradients summed for every Gaussian (coupled), else each Gaussian steps on
    // its own route's.
    coupled: u32,
    // `grad_norm`: over the SH coefficients only.
    colour_only: u32,
    pad: u32,
    // Adam's bias corrections 1 − β₁ᵗ, 1 − β₂ᵗ.
    bc1: f32,
    bc2: f32,
    // The watermark route's rate multiplier (its schedule at this step).
    wm_scale: f32,
    // `shrink`: the offsets' factor.
    factor: f32,
}
@group(0) @binding(0) var<uniform> args: Step;
@group(0) @binding(1) var<storage, read_write> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> m1: array<f32>;
@group(0) @binding(3) var<storage, read_write> m2: array<f32>;
@group(0) @binding(4) var<storage, read> g_wm: array<f32>;
@group(0) @binding(5) var<storage, read> g_vis: array<f32>;
// Per Gaussian (global index), its learning rates in the host's channel order: means, dc,
// rest, opacity, rotation, scale — masks applied, before the route's multiplier.
@group(0) @binding(6) var<storage, read> rates: array<f32>;
// Per Gaussian: bit 0 a carrier (steps on the watermark route), bit 1 bounded (the fidelity
// bound scales its offsets).
@group(0) @binding(7) var<storage, read> flags: array<u32>;
// Per Gaussian, Σ over steps of ‖∂L_wm/∂θ_i‖.
@group(0) @binding(9) var<storage, read_write> norms: array<f32>;
// The planned scene's parameters (the fidelity bound's origin), laid out like `params`.
@group(0) @binding(10) var<storage, read> base: array<f32>;
// Per Gaussian, how many copies of it the edited scene holds (0 removed, 1 as is, 2 cloned).
@group(0) @binding(11) var<storage, read> copies: array<u32>;

const BETA1: f32 = 0.9;
const BETA2: f32 = 0.999;
const ADAM_EPS: f32 = 1e-15;

// The index into `rates` of parameter k's channel.
fn channel(k: u32) -> u32 {
    if (k < 3u) {
        return 0u; // means
    }
    if (k < 6u) {
        return 5u; // log-scales
    }
    if (k < 10u) {
        return 4u; // quaternion
    }
    if (k == 10u) {
        return 3u; // opacity
    }
    if (k < 14u) {
        return 1u; // SH DC
    }
    return 2u; // the rest of the SH
}

fn local_index(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 256u;
}

// The quaternion of the Gaussian whose parameters start at `at`, made unit (left alone when its
// norm is 0 or not finite), in the host's order of operations.
fn normalise_quaternion(at: u32) {
    let q = vec4<f32>(params[at + 6u], params[at + 7u], params[at + 8u], params[at + 9u]);
    let n = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    if (n > 1e-12 && n < 3.4e38) {
        params[at + 6u] = q.x / n;
        params[at + 7u] = q.y / n;
        params[at + 8u] = q.z / n;
        params[at + 9u] = q.w / n;
    }
}

@compute @workgroup_size(256)
fn adam_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = local_index(gid, nwg);
    if (local >= chunk.count) {
        return;
    }
    let i = chunk.first + local;
    let at = chunk.params_at + local * args.floats;
    let carrier = (flags[i] & 1u) != 0u;
    let s = select(1.0, args.wm_scale, carrier || args.coupled != 0u);
    for (var k = 0u; k < args.floats; k = k + 1u) {
        let j = at + k;
        var gr: f32;
        if (args.coupled != 0u) {
            gr = g_wm[j] + g_vis[j];
        } else if (carrier) {
            gr = g_wm[j];
        } else {
            gr = g_vis[j];
        }
        let lr = rates[i * 6u + channel(k)] * s;
        let m = BETA1 * m1[j] + (1.0 - BETA1) * gr;
        let v = BETA2 * m2[j] + (1.0 - BETA2) * gr * gr;
        m1[j] = m;
        m2[j] = v;
        if (lr != 0.0) {
            params[j] = params[j] - lr * (m / args.bc1) / (sqrt(v / args.bc2) + ADAM_EPS);
        }
    }
    // Updated quaternions stay unit; the others bit-identical.
    if (rates[i * 6u + 4u] * s != 0.0) {
        normalise_quaternion(at);
    }
}

@compute @workgroup_size(256)
fn grad_norm(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = local_index(gid, nwg);
    if (local >= chunk.count) {
        return;
    }
    let i = chunk.first + local;
    let at = chunk.params_at + local * args.floats;
    var s = 0.0;
    let first = select(0u, 11u, args.colour_only != 0u);
    for (var k = first; k < args.floats; k = k + 1u) {
        let v = g_wm[at + k];
        s = s + v * v;
    }
    norms[i] = norms[i] + sqrt(s);
}

// x0 + f·(x − x0) where x moved (unchanged values stay bit-identical).
fn lerp_moved(j: u32) {
    let x = params[j];
    let x0 = base[j];
    if (x != x0) {
        params[j] = x0 + args.factor * (x - x0);
    }
}

@compute @workgroup_size(256)
fn shrink(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = local_index(gid, nwg);
    if (local >= chunk.count) {
        return;
    }
    let i = chunk.first + local;
    if ((flags[i] & 2u) == 0u) {
        return;
    }
    let at = chunk.params_at + local * args.floats;
    for (var k = 0u; k < args.floats; k = k + 1u) {
        if (k < 6u || k >= 10u) {
            lerp_moved(at + k);
        }
    }
    let q0 = vec4<f32>(base[at + 6u], base[at + 7u], base[at + 8u], base[at + 9u]);
    let q1 = vec4<f32>(params[at + 6u], params[at + 7u], params[at + 8u], params[at + 9u]);
    if (all(q0 == q1)) {
        return; // unchanged quaternions stay bit-identical
    }
    for (var k = 6u; k < 10u; k = k + 1u) {
        lerp_moved(at + k);
    }
    normalise_quaternion(at);
}

// A copy of the scene (already in `params`) with the Gaussians of 0 copies transparent:
// α = sigmoid(−40), far below the 1/255 a Gaussian needs to be drawn. (Clones, c > 1, are
// refused on the host: the GPU's backward stays scene-shaped.)
@compute @workgroup_size(256)
fn edit_copies(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = local_index(gid, nwg);
    if (local >= chunk.count) {
        return;
    }
    if (copies[chunk.first + local] == 0u) {
        params[chunk.params_at + local * args.floats + 10u] = -40.0;
    }
}
