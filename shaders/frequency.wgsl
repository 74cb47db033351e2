// NeRF's frequency (positional) encoding: forward, and the gradient in its input (camera pose
// refinement).
// CPU twin: nerf_encoding::FrequencyEncoding (crates/encoding/src/lib.rs), nerf-pytorch's order:
// [x, sin(2^0 x), cos(2^0 x), sin(2^1 x), cos(2^1 x), …], each block holding all D coordinates,
// no π factor; the raw input block only when include_input (SKIP = D).
// Host side: nerf_gpu::encoding::GpuFrequencyEncoding.
//
// Layouts: counters array<u32> (counters[1] = n samples); x [n][D] f32; out [n][OUT_DIM] f32.
// Launch: groups_1d(capacity·OUT_DIM, WG), one invocation per OUTPUT ELEMENT (coalesced writes, one
// sin or cos each); invocations past n·OUT_DIM return.
//
// Accuracy: 2^k·x is exact (a power of two built from its bits), and the argument is reduced to
// [−π, π] with a three-part Cody–Waite split of 2π (exact products for |k| < 2^12, i.e.
// |2^k·x| ≲ 2.5e4) before sin/cos, whose hardware versions are only accurate on [−π, π].

override D: u32 = 3u;
override N_FREQ: u32 = 10u;
// D when the input is included, else 0.
override SKIP: u32 = 3u;
override WG: u32 = 256u;
override OUT_DIM: u32 = SKIP + 2u * N_FREQ * D;

@group(0) @binding(0) var<storage, read> counters: array<u32>;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

// a − 2π·round(a / 2π), with 2π = C1 + C2 + C3 (C1: 8 significant bits, C2: 12).
fn reduce_two_pi(a: f32) -> f32 {
    let k = round(a * 0.15915494309189535);
    return ((a - k * 6.28125) - k * 0.0019354820251464844) - k * -1.7484555314695172e-07;
}

@compute @workgroup_size(WG)
fn frequency_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let id = linear_id(gid, nwg, WG);
    let n = min(counters[1], min(arrayLength(&x) / D, arrayLength(&out) / OUT_DIM));
    let s = id / OUT_DIM;
    if (s >= n) {
        return;
    }
    let e = id - s * OUT_DIM;
    if (e < SKIP) {
        out[id] = x[s * D + e];
        return;
    }
    let r = e - SKIP;
    let band = r / (2u * D);
    let within = r - band * 2u * D;
    let is_cos = within >= D;
    let j = select(within, within - D, is_cos);
    // 2^band exactly (band < 128 is checked on the host).
    let freq = bitcast<f32>((127u + band) << 23u);
    let a = reduce_two_pi(freq * x[s * D + j]);
    out[id] = select(sin(a), cos(a), is_cos);
}

// ∂L/∂x from ∂L/∂out (CPU twin: FrequencyEncoding::backward with d_input): one invocation per
// input element (sample s, coordinate j), d_x = [d_raw] + Σ_k 2^k (cos(2^k x) d_sin − sin(2^k x) d_cos).
// ∂L/∂out of sample s starts at d_out[s·grad.stride + grad.offset] (the encoding may be a slice of
// a wider row, e.g. a colour network's input gradient). Written over d_x; rows past n untouched.
struct GradLayout {
    stride: u32,
    offset: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(3) var<uniform> grad: GradLayout;
@group(0) @binding(4) var<storage, read> d_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_x: array<f32>;

@compute @workgroup_size(WG)
fn frequency_input_grad(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let id = linear_id(gid, nwg, WG);
    let n = min(counters[1], min(arrayLength(&x), arrayLength(&d_x)) / D);
    let s = id / D;
    if (s >= n) {
        return;
    }
    let j = id - s * D;
    let row = s * grad.stride + grad.offset;
    var acc = 0.0;
    if (SKIP > 0u) {
        acc = d_out[row + j];
    }
    let xj = x[s * D + j];
    for (var band = 0u; band < N_FREQ; band = band + 1u) {
        let freq = bitcast<f32>((127u + band) << 23u);
        let a = reduce_two_pi(freq * xj);
        let base = row + SKIP + band * 2u * D;
        acc = acc + freq * (cos(a) * d_out[base + j] - sin(a) * d_out[base + D + j]);
    }
    d_x[id] = acc;
}
