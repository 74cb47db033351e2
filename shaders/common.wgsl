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

// A random index below n for (seed, stream, index): floor(rand_u32 · n / 2³²) (Lemire's
// multiply-high), whose uneven share — ⌈2³²/n⌉ or ⌊2³²/n⌋ draws per index — is spread over the
// range, where `rand_u32 % n` gives every index below 2³² mod n the extra draw (a share 1/7 larger
// for the first sixth of 600 M kept pixels). The 64-bit product's high word from 16-bit halves.
fn rand_below(seed: u32, stream: u32, i: u32, n: u32) -> u32 {
    let a = rand_u32(seed, stream, i);
    let a0 = a & 0xffffu;
    let a1 = a >> 16u;
    let b0 = n & 0xffffu;
    let b1 = n >> 16u;
    let p00 = a0 * b0;
    let p01 = a0 * b1;
    let p10 = a1 * b0;
    let mid = (p00 >> 16u) + (p01 & 0xffffu) + (p10 & 0xffffu);
    return a1 * b1 + (p01 >> 16u) + (p10 >> 16u) + (mid >> 16u);
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

// Slab test against an oriented crop box (CPU twin: nerf_sampling::CropBox::slab): the ray in the
// box's frame — rows ax, ay, az (xyz: the box's axes; w: half its size along each), centre c —
// against [−half, half]. Same result layout as slab.
fn crop_slab(o: vec3<f32>, d: vec3<f32>, ax: vec4<f32>, ay: vec4<f32>, az: vec4<f32>, c: vec3<f32>) -> vec3<f32> {
    let q = o - c;
    let ob = vec3<f32>(ax.x * q.x + ax.y * q.y + ax.z * q.z, ay.x * q.x + ay.y * q.y + ay.z * q.z, az.x * q.x + az.y * q.y + az.z * q.z);
    let db = vec3<f32>(ax.x * d.x + ax.y * d.y + ax.z * d.z, ay.x * d.x + ay.y * d.y + ay.z * d.z, az.x * d.x + az.y * d.y + az.z * d.z);
    let h = vec3<f32>(ax.w, ay.w, az.w);
    return slab(ob, db, -h, h);
}
