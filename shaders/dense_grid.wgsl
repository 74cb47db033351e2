// Dense trilinear grid (DVGO's voxel grids): C values on every vertex of an (R+1)³ lattice over
// the scene box, forward and parameter backward.
// CPU twin: nerf_encoding::DenseGrid (crates/encoding/src/dense_grid.rs) after the normalisation
// of nerf-field-voxel; host side: nerf_gpu::encoding::GpuDenseGrid. Same cell, corner order
// (bit 0 = +x, bit 1 = +y, bit 2 = +z), trilinear weights and summation order as the CPU.
//
// Layouts:
//   counters   array<u32>; counters[1] = n samples (nerf_gpu::layout::COUNTER_N_SAMPLES)
//   positions  [n][3] f32 in WORLD units; normalised as nerf-field-voxel does:
//              clamp((p − aabb_min)·inv_extent, 0, 1), NaN → 0 (Rust's f32::max maps NaN to 0)
//   params     [C][V] f32 = DenseGrid::params(), channel-major, V = (R+1)³: channel c of vertex
//              (x, y, z) at c·V + (z·(R+1) + y)·(R+1) + x
//   out        rows of `stride` floats: sample i's channel c at i·stride + col + c, written as
//              scale · (trilinear interpolation); the row's other columns are left untouched (a
//              field writes several grids into the columns of one buffer)
//   d_out      the same layout; grads: the params' layout, ACCUMULATED (+= scale · w · d_out)
//
// Launch: one invocation per sample (its channels looped: the cell is computed once), workgroups
// groups_1d(capacity, WG); invocations with i >= n return. The backward adds with atomic<f32>
// (dense_backward_atomic, needs SHADER_FLOAT32_ATOMIC; the host strips the marked section when
// the adapter lacks it) or with a compare-and-swap loop on atomic<u32> (dense_backward_cas).

override WG: u32 = 128u;

struct Params {
    aabb_min: vec3<f32>,
    // R (cells per axis).
    res: u32,
    inv_extent: vec3<f32>,
    // C (values per vertex).
    channels: u32,
    // Floats per row of out / d_out, and the column of channel 0.
    stride: u32,
    col: u32,
    // Factor on the interpolated values (and on their gradient).
    scale: f32,
    // V = (R+1)³.
    n_vertices: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> counters: array<u32>;
@group(0) @binding(2) var<storage, read> positions: array<f32>;
@group(0) @binding(3) var<storage, read> params: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;
@group(0) @binding(5) var<storage, read> d_out: array<f32>;
@group(0) @binding(6) var<storage, read_write> grads_cas: array<atomic<u32>>;

struct Cell {
    // Vertices of corners 0..3 (z = 0) and 4..7 (z = 1).
    s0: vec4<u32>,
    s1: vec4<u32>,
    // Their trilinear weights.
    w0: vec4<f32>,
    w1: vec4<f32>,
}

fn is_nan(v: f32) -> bool {
    // Bit test: WGSL lets compilers assume x == x for floats.
    return (bitcast<u32>(v) & 0x7fffffffu) > 0x7f800000u;
}

// Position i normalised to [0, 1]³ as nerf-field-voxel does.
fn unit_position(i: u32) -> vec3<f32> {
    let p = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    var x = (p - P.aabb_min) * P.inv_extent;
    for (var a = 0u; a < 3u; a++) {
        x[a] = select(clamp(x[a], 0.0, 1.0), 0.0, is_nan(x[a]));
    }
    return x;
}

// DenseGrid::cell: the far face x = 1 lands in the last cell with fraction 1. The weights are the
// CPU's products in the CPU's order ((x·y)·z). Written without arrays (see hash_grid.wgsl's cell).
fn cell(x: vec3<f32>) -> Cell {
    let r = P.res;
    let p = x * f32(r);
    let v = min(vec3<u32>(p), vec3<u32>(r - 1u));
    let f = p - vec3<f32>(v);
    let s = r + 1u;
    let base = v.x + s * (v.y + s * v.z);
    var c: Cell;
    c.s0 = vec4<u32>(base, base + 1u, base + s, base + 1u + s);
    c.s1 = c.s0 + vec4<u32>(s * s);
    let ax0 = 1.0 - f.x;
    let ay0 = 1.0 - f.y;
    let wxy = vec4<f32>(ax0 * ay0, f.x * ay0, ax0 * f.y, f.x * f.y);
    c.w0 = wxy * (1.0 - f.z);
    c.w1 = wxy * f.z;
    return c;
}

// Samples of this launch, bounded by what the bound buffers hold.
fn n_samples(rows_len: u32) -> u32 {
    return min(counters[1], min(arrayLength(&positions) / 3u, rows_len / P.stride));
}

@compute @workgroup_size(WG)
fn dense_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= n_samples(arrayLength(&out))) {
        return;
    }
    let c = cell(unit_position(i));
    let row = i * P.stride + P.col;
    for (var ch = 0u; ch < P.channels; ch++) {
        let o = ch * P.n_vertices;
        // The 8 reads first (independent), then the sum in corner order.
        let t0 = params[o + c.s0.x];
        let t1 = params[o + c.s0.y];
        let t2 = params[o + c.s0.z];
        let t3 = params[o + c.s0.w];
        let t4 = params[o + c.s1.x];
        let t5 = params[o + c.s1.y];
        let t6 = params[o + c.s1.z];
        let t7 = params[o + c.s1.w];
        var acc = 0.0;
        acc += c.w0.x * t0;
        acc += c.w0.y * t1;
        acc += c.w0.z * t2;
        acc += c.w0.w * t3;
        acc += c.w1.x * t4;
        acc += c.w1.y * t5;
        acc += c.w1.z * t6;
        acc += c.w1.w * t7;
        out[row + ch] = P.scale * acc;
    }
}

fn add_cas(idx: u32, v: f32) {
    if (v == 0.0) {
        return;
    }
    var old = atomicLoad(&grads_cas[idx]);
    loop {
        let r = atomicCompareExchangeWeak(&grads_cas[idx], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

@compute @workgroup_size(WG)
fn dense_backward_cas(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= n_samples(arrayLength(&d_out))) {
        return;
    }
    let c = cell(unit_position(i));
    let row = i * P.stride + P.col;
    for (var ch = 0u; ch < P.channels; ch++) {
        let g = d_out[row + ch];
        if (g == 0.0) {
            continue;
        }
        let gs = P.scale * g;
        let o = ch * P.n_vertices;
        add_cas(o + c.s0.x, c.w0.x * gs);
        add_cas(o + c.s0.y, c.w0.y * gs);
        add_cas(o + c.s0.z, c.w0.z * gs);
        add_cas(o + c.s0.w, c.w0.w * gs);
        add_cas(o + c.s1.x, c.w1.x * gs);
        add_cas(o + c.s1.y, c.w1.y * gs);
        add_cas(o + c.s1.z, c.w1.z * gs);
        add_cas(o + c.s1.w, c.w1.w * gs);
    }
}

//#begin f32-atomics
@group(0) @binding(7) var<storage, read_write> grads_f32: array<atomic<f32>>;

fn add_atomic(idx: u32, v: f32) {
    if (v != 0.0) {
        atomicAdd(&grads_f32[idx], v);
    }
}

@compute @workgroup_size(WG)
fn dense_backward_atomic(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= n_samples(arrayLength(&d_out))) {
        return;
    }
    let c = cell(unit_position(i));
    let row = i * P.stride + P.col;
    for (var ch = 0u; ch < P.channels; ch++) {
        let g = d_out[row + ch];
        if (g == 0.0) {
            continue;
        }
        let gs = P.scale * g;
        let o = ch * P.n_vertices;
        add_atomic(o + c.s0.x, c.w0.x * gs);
        add_atomic(o + c.s0.y, c.w0.y * gs);
        add_atomic(o + c.s0.z, c.w0.z * gs);
        add_atomic(o + c.s0.w, c.w0.w * gs);
        add_atomic(o + c.s1.x, c.w1.x * gs);
        add_atomic(o + c.s1.y, c.w1.y * gs);
        add_atomic(o + c.s1.z, c.w1.z * gs);
        add_atomic(o + c.s1.w, c.w1.w * gs);
    }
}
//#end f32-atomics
