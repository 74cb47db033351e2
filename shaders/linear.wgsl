// Tiled linear layers for wide MLPs (plain WGSL, f32). Host side: nerf_gpu::linear::GpuMlp.
// CPU twin: nerf_mlp::Mlp (forward / infer / backward), layer by layer.
//
// One linear layer: Y[n][N] = act(A[n][K] · Wᵀ + b), W `N × K` row-major at params[w_off], b at
// params[bias_off]. The layer input A is the concatenation [xa (ka columns), hidden (K − ka columns)]
// read from two sources without a copy: `xa` (the network input, row stride a_stride) and a
// block of `work` (row stride b_stride, column offset b_off). ka = 0 for a plain hidden layer,
// ka = K for layer 0, 0 < ka < K for a skip layer (nerf_mlp's "[input, h_{i−1}]").
// n = counters[1] (samples of the step); launches cover a host-known capacity.
//
// Entry points (one 64×64 output tile per workgroup of 256, 16-deep K steps through workgroup
// memory, 4×4 outputs per invocation, bias + activation fused in the epilogue):
//   forward:        Y → work[row·dst_stride + dst_off + col] (flag 1) and/or out2[row·out_stride + col] (flag 2)
//   backward_data:  dA = dZ[n][N] · W; columns < ka are added to d_input[row·ka + col] (flag 8),
//                   hidden columns h give dZ_prev[row·dst_stride + h] = dA · act'_prev(y_prev) with
//                   y_prev = tape[row·b_stride + b_off + h] (dZ of the previous layer, fused).
//   backward_weight: partial[s][N][KC] = Σ_{rows of split s} dZ[r][j] · [A[r], 1][c] (KC = K + has_bias:
//                   the bias gradient is the column of ones), splits of `chunk` rows over n.
//   reduce_grads:   grads += Σ_s partial[s] (deterministic: no atomics), mapped back to the W/b layout.
//   output_grad:    dZ_last[r][j] = d_output[r][j] · act'(y[r][j]) with y from the tape.

struct Params {
    n_out: u32,      // N: fan-out of the layer
    k_in: u32,       // K: fan-in (incl. the skip input)
    ka: u32,         // leading input columns read from `xa`
    act: u32,        // activation of this layer (0 none, 1 relu, 2 sigmoid, 3 tanh, 4 softplus, 5 exp)
    a_stride: u32,   // row stride of xa
    b_stride: u32,   // row stride of the hidden source (work / tape)
    b_off: u32,      // column offset of the hidden source
    dst_stride: u32, // row stride of the destination
    dst_off: u32,    // column offset of the destination
    out_stride: u32, // row stride of out2 (forward) / of d_output (output_grad)
    flags: u32,      // 1 write work, 2 write out2, 4 bias, 8 accumulate d_input
    w_off: u32,      // offset of W in params / grads
    bias_off: u32,   // offset of b in params / grads
    chunk: u32,      // rows per split (backward_weight / reduce_grads)
    c_lo: u32,       // first column computed by backward_data
    prev_act: u32,   // activation of the previous layer (backward_data epilogue)
}

const TILE: u32 = 64u;
const BK: u32 = 16u;
const LDS: u32 = 65u; // padded row of the shared tiles (no bank conflicts on the transposed stores)
const COUNTER_N_SAMPLES: u32 = 1u;

fn act_apply(a: u32, z: f32) -> f32 {
    switch a {
        case 1u: { return max(z, 0.0); }
        case 2u: { return 1.0 / (1.0 + exp(-z)); }
        case 3u: { return tanh(z); }
        case 4u: { return max(z, 0.0) + log(1.0 + exp(-abs(z))); }
        case 5u: { return exp(z); }
        default: { return z; }
    }
}

// dy/dz from the output y (nerf_mlp::Activation::derivative_from_output).
fn act_grad(a: u32, y: f32) -> f32 {
    switch a {
        case 1u: { return select(0.0, 1.0, y > 0.0); }
        case 2u: { return y * (1.0 - y); }
        case 3u: { return 1.0 - y * y; }
        case 4u: { return 1.0 - exp(-y); }
        case 5u: { return y; }
        default: { return 1.0; }
    }
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> counters: array<u32>;

var<workgroup> As: array<f32, 1040>; // [BK][LDS]
var<workgroup> Bs: array<f32, 1040>; // [BK][LDS]
var<workgroup> wg_n: u32;

fn load_n(lid: u32) -> u32 {
    if lid == 0u {
        wg_n = counters[COUNTER_N_SAMPLES];
    }
    return workgroupUniformLoad(&wg_n);
}

// ---------------------------------------------------------------------------------------------
// forward
@group(0) @binding(2) var<storage, read> f_xa: array<f32>;
@group(0) @binding(3) var<storage, read_write> f_work: array<f32>;
@group(0) @binding(4) var<storage, read> f_params: array<f32>;
@group(0) @binding(5) var<storage, read_write> f_out: array<f32>;

fn f_a(row: u32, k: u32) -> f32 {
    if k < P.ka {
        return f_xa[row * P.a_stride + k];
    }
    return f_work[row * P.b_stride + P.b_off + (k - P.ka)];
}

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TILE;
    let col0 = wid.z * TILE;
    if row0 >= n { return; }
    let N = P.n_out;
    let K = P.k_in;
    let tx = lid % 16u;
    let ty = lid / 16u;
    // Four vec4 rows of accumulators in registers (an array indexed in loops, as before, stayed
    // in local memory on the H100's compiler: the plain trunk ran 44× slower than on tensor cores).
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var k0 = 0u; k0 < K; k0 += BK) {
        for (var q = 0u; q < 4u; q++) {
            let e = lid + 256u * q;
            let r = e / BK;
            let kk = e % BK;
            let k = k0 + kk;
            let row = row0 + r;
            var va = 0.0;
            if row < n && k < K { va = f_a(row, k); }
            As[kk * LDS + r] = va;
            let j = col0 + r;
            var vb = 0.0;
            if j < N && k < K { vb = f_params[P.w_off + j * K + k]; }
            Bs[kk * LDS + r] = vb;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let o = kk * LDS;
            let a = vec4<f32>(As[o + ty], As[o + ty + 16u], As[o + ty + 32u], As[o + ty + 48u]);
            let b = vec4<f32>(Bs[o + tx], Bs[o + tx + 16u], Bs[o + tx + 32u], Bs[o + tx + 48u]);
            acc0 = fma(vec4<f32>(a.x), b, acc0);
            acc1 = fma(vec4<f32>(a.y), b, acc1);
            acc2 = fma(vec4<f32>(a.z), b, acc2);
            acc3 = fma(vec4<f32>(a.w), b, acc3);
        }
        workgroupBarrier();
    }
    // acc[i][j]: row ty + 16i, column tx + 16j of the tile (read once per output).
    var acc = array<vec4<f32>, 4>(acc0, acc1, acc2, acc3);
    for (var j = 0u; j < 4u; j++) {
        let col = col0 + tx + 16u * j;
        if col >= N { continue; }
        var bias = 0.0;
        if (P.flags & 4u) != 0u { bias = f_params[P.bias_off + col]; }
        for (var i = 0u; i < 4u; i++) {
            let row = row0 + ty + 16u * i;
            if row >= n { continue; }
            let y = act_apply(P.act, acc[i][j] + bias);
            if (P.flags & 1u) != 0u { f_work[row * P.dst_stride + P.dst_off + col] = y; }
            if (P.flags & 2u) != 0u { f_out[row * P.out_stride + col] = y; }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// backward_data: dA = dZ · W over columns [c_lo, K)
@group(0) @binding(2) var<storage, read> d_dz: array<f32>;
@group(0) @binding(3) var<storage, read> d_params: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_dh: array<f32>;
@group(0) @binding(5) var<storage, read> d_tape: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_input: array<f32>;

@compute @workgroup_size(256)
fn backward_data(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TILE;
    let col0 = P.c_lo + wid.z * TILE;
    if row0 >= n { return; }
    let N = P.n_out; // reduction dimension here
    let K = P.k_in;  // output columns
    let tx = lid % 16u;
    let ty = lid / 16u;
    // Four vec4 rows of accumulators in registers (an array indexed in loops, as before, stayed
    // in local memory on the H100's compiler: the plain trunk ran 44× slower than on tensor cores).
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var k0 = 0u; k0 < N; k0 += BK) {
        for (var q = 0u; q < 4u; q++) {
            let e = lid + 256u * q;
            // dZ tile: 64 rows × 16 (coalesced along the 16)
            let r = e / BK;
            let kk = e % BK;
            let row = row0 + r;
            var va = 0.0;
            if row < n && k0 + kk < N { va = d_dz[row * N + k0 + kk]; }
            As[kk * LDS + r] = va;
            // W tile: 16 rows (outputs j) × 64 input columns (coalesced along the 64)
            let kb = e / TILE;
            let c = e % TILE;
            let col = col0 + c;
            var vb = 0.0;
            if k0 + kb < N && col < K { vb = d_params[P.w_off + (k0 + kb) * K + col]; }
            Bs[kb * LDS + c] = vb;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let o = kk * LDS;
            let a = vec4<f32>(As[o + ty], As[o + ty + 16u], As[o + ty + 32u], As[o + ty + 48u]);
            let b = vec4<f32>(Bs[o + tx], Bs[o + tx + 16u], Bs[o + tx + 32u], Bs[o + tx + 48u]);
            acc0 = fma(vec4<f32>(a.x), b, acc0);
            acc1 = fma(vec4<f32>(a.y), b, acc1);
            acc2 = fma(vec4<f32>(a.z), b, acc2);
            acc3 = fma(vec4<f32>(a.w), b, acc3);
        }
        workgroupBarrier();
    }
    // acc[i][j]: row ty + 16i, column tx + 16j of the tile (read once per output).
    var acc = array<vec4<f32>, 4>(acc0, acc1, acc2, acc3);
    for (var j = 0u; j < 4u; j++) {
        let col = col0 + tx + 16u * j;
        if col >= K { continue; }
        for (var i = 0u; i < 4u; i++) {
            let row = row0 + ty + 16u * i;
            if row >= n { continue; }
            if col < P.ka {
                if (P.flags & 8u) != 0u {
                    let o = row * P.ka + col;
                    d_input[o] = d_input[o] + acc[i][j];
                }
            } else {
                let h = col - P.ka;
                let y = d_tape[row * P.b_stride + P.b_off + h];
                d_dh[row * P.dst_stride + h] = acc[i][j] * act_grad(P.prev_act, y);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// backward_weight: partial[s][j][c] = Σ_r dZ[r][j] · [A[r], 1][c]
@group(0) @binding(2) var<storage, read> w_dz: array<f32>;
@group(0) @binding(3) var<storage, read> w_xa: array<f32>;
@group(0) @binding(4) var<storage, read> w_tape: array<f32>;
@group(0) @binding(5) var<storage, read_write> w_partial: array<f32>;

fn w_a(row: u32, c: u32) -> f32 {
    if c < P.ka {
        return w_xa[row * P.a_stride + c];
    }
    if c < P.k_in {
        return w_tape[row * P.b_stride + P.b_off + (c - P.ka)];
    }
    return 1.0; // the bias column
}

@compute @workgroup_size(256)
fn backward_weight(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let N = P.n_out;
    let KC = P.k_in + select(0u, 1u, (P.flags & 4u) != 0u);
    let c0 = wid.x * TILE;
    let j0 = wid.y * TILE;
    let s = wid.z;
    let r_begin = s * P.chunk;
    if r_begin >= n { return; }
    let r_end = min(r_begin + P.chunk, n);
    let tx = lid % 16u;
    let ty = lid / 16u;
    // Four vec4 rows of accumulators in registers (an array indexed in loops, as before, stayed
    // in local memory on the H100's compiler: the plain trunk ran 44× slower than on tensor cores).
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var r0 = r_begin; r0 < r_end; r0 += BK) {
        for (var q = 0u; q < 4u; q++) {
            let e = lid + 256u * q;
            let kk = e / TILE;
            let m = e % TILE;
            let r = r0 + kk;
            let j = j0 + m;
            var va = 0.0;
            if r < r_end && j < N { va = w_dz[r * N + j]; }
            As[kk * LDS + m] = va;
            let c = c0 + m;
            var vb = 0.0;
            if r < r_end && c < KC { vb = w_a(r, c); }
            Bs[kk * LDS + m] = vb;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let o = kk * LDS;
            let a = vec4<f32>(As[o + ty], As[o + ty + 16u], As[o + ty + 32u], As[o + ty + 48u]);
            let b = vec4<f32>(Bs[o + tx], Bs[o + tx + 16u], Bs[o + tx + 32u], Bs[o + tx + 48u]);
            acc0 = fma(vec4<f32>(a.x), b, acc0);
            acc1 = fma(vec4<f32>(a.y), b, acc1);
            acc2 = fma(vec4<f32>(a.z), b, acc2);
            acc3 = fma(vec4<f32>(a.w), b, acc3);
        }
        workgroupBarrier();
    }
    // acc[i][j]: row ty + 16i, column tx + 16j of the tile (read once per output).
    var acc = array<vec4<f32>, 4>(acc0, acc1, acc2, acc3);
    let base = s * N * KC;
    for (var i = 0u; i < 4u; i++) {
        let j = j0 + ty + 16u * i;
        if j >= N { continue; }
        for (var jj = 0u; jj < 4u; jj++) {
            let c = c0 + tx + 16u * jj;
            if c < KC { w_partial[base + j * KC + c] = acc[i][jj]; }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// reduce_grads: grads[W/b] += Σ_{s < ceil(n / chunk)} partial[s]
@group(0) @binding(2) var<storage, read> r_partial: array<f32>;
@group(0) @binding(3) var<storage, read_write> r_grads: array<f32>;

@compute @workgroup_size(256)
fn reduce_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = counters[COUNTER_N_SAMPLES];
    let K = P.k_in;
    let KC = K + select(0u, 1u, (P.flags & 4u) != 0u);
    let total = P.n_out * KC;
    let i = linear_id(gid, nwg, 256u);
    if i >= total { return; }
    let splits = (n + P.chunk - 1u) / P.chunk;
    var sum = 0.0;
    for (var s = 0u; s < splits; s++) {
        sum += r_partial[s * total + i];
    }
    let j = i / KC;
    let c = i % KC;
    var o = P.bias_off + j;
    if c < K { o = P.w_off + j * K + c; }
    r_grads[o] = r_grads[o] + sum;
}

// ---------------------------------------------------------------------------------------------
// output_grad: dZ_last = d_output ⊙ act'(y_last)
@group(0) @binding(2) var<storage, read> o_dout: array<f32>;
@group(0) @binding(3) var<storage, read> o_tape: array<f32>;
@group(0) @binding(4) var<storage, read_write> o_dz: array<f32>;

@compute @workgroup_size(256)
fn output_grad(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = counters[COUNTER_N_SAMPLES];
    let N = P.n_out;
    let i = linear_id(gid, nwg, 256u);
    if i >= n * N { return; }
    let row = i / N;
    let col = i % N;
    let y = o_tape[row * P.b_stride + P.b_off + col];
    o_dz[i] = o_dout[row * P.out_stride + col] * act_grad(P.act, y);
}
