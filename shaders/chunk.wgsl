// The Gaussians one dispatch of a per-Gaussian kernel covers (`src/render/gpu/chunk.rs`; shared by
// `project.wgsl` and `optim.wgsl`): global indices [first, first + count). Per-Gaussian buffers
// (`params`, `grads`, Adam's moments) are bound a chunk at a time, from an aligned offset, so a
// scene may exceed one storage binding: Gaussian `first`'s parameters start at float `params_at`
// of the `params` binding, its gradients at float `grads_at` of the `grads` binding.
struct Chunk {
    first: u32,
    count: u32,
    params_at: u32,
    grads_at: u32,
    // `project_backward` adds its gradients to what `grads` holds (a sum over views) instead
    // of writing them.
    accumulate: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}
@group(0) @binding(8) var<uniform> chunk: Chunk;
