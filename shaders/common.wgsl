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

// Slab test of the ray o + t·d against the box [lo, hi] (CPU twin: nerf_sampling's slab):
// (t_enter, t_exit, hit) with t_enter/t_exit starting at ∓3e38; a zero direction component keeps
// the ray only when o lies between that slab's planes (hit = 0 otherwise). An empty result has
// t_exit ≤ t_enter.
fn slab(o: vec3<f32>, d: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec3<f32> {
    var t0 = -3.0e38;
    var t1 = 3.0e38;
    var hit = 1.0;
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (d[a] == 0.0) {
            if (!(o[a] >= lo[a] && o[a] <= hi[a])) {
                hit = 0.0;
            }
        } else {
            let inv = 1.0 / d[a];
            let x = (lo[a] - o[a]) * inv;
            let y = (hi[a] - o[a]) * inv;
            t0 = max(t0, min(x, y));
            t1 = min(t1, max(x, y));
        }
    }
    return vec3<f32>(t0, t1, hit);
}
