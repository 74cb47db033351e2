// Shared helpers prepended to every kernel family (nerf_gpu::shaders::with_common).
// Counter-based random numbers (PCG hash; Rust twin: nerf_gpu::rng) and the 1-D launch index.

fn pcg_hash(x: u32) -> u32 {
    let state = x * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// A random u32 for (seed, stream, index): independent streams, no state.
fn rand_u32(seed: u32, stream: u32, i: u32) -> u32 {
    return pcg_hash(seed ^ pcg_hash(stream ^ pcg_hash(i)));
}

// Uniform in [0, 1): the top 24 bits of rand_u32.
fn rand_f32(seed: u32, stream: u32, i: u32) -> f32 {
    return f32(rand_u32(seed, stream, i) >> 8u) * (1.0 / 16777216.0);
}

// Linear invocation index of a launch made with nerf_gpu::kernel::groups_1d.
fn linear_id(gid: vec3<u32>, nwg: vec3<u32>, wg: u32) -> u32 {
    return gid.x + gid.y * nwg.x * wg;
}
