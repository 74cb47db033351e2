enable f16;
enable wgpu_cooperative_matrix;
// Fully fused small MLPs on cooperative matrices (tensor cores): 16×16×16 f16 products with f32
// accumulation. Rust side: nerf_gpu::mlp_coop::FusedMlpCoop (same API as the plain-WGSL
// nerf_gpu::mlp::FusedMlp, shaders/mlp_fused.wgsl). CPU twin: nerf_mlp::Mlp (crates/mlp): layer l
// computes y = act(x·Wᵀ + b), W `out × fan_in` row-major then b, layer by layer in one flat f32
// parameter buffer; activation derivatives are taken from the saved outputs. Results equal the CPU's
// up to f16 rounding of the activations, the weights and the (scaled) gradients.
//
// Limits: every width ≤ 64, at most MAX_LAYERS = 16 linear layers, no skips.
//
// Widths are padded to multiples of 16 (xp = round16(input_dim), kp_l = round16(fan_in_l),
// np_l = round16(out_l)); every padding element is an exact zero.
//
// Buffers ([n] = counters[1] samples, row-major like the CPU; n ≤ the launch capacity):
//   input [n][input_dim] f32, output [n][output_dim] f32, d_output like output, d_input like input
//     (OVERWRITTEN when requested), params / grads [n_params] f32 in the CPU layout (grads are
//     ACCUMULATED, +=).
//   w16: f16 copy of the weights, per layer [np_l][kp_l] row-major at P.layers[l].w16_off (zero
//     padding), written by convert_weights at the start of every record_* call (a few thousand
//     elements).
//   tape: the caller's f32 buffer bound as array<f16>: per sample a row of P.s16 f16 values
//     (tape_floats_per_sample = s16 / 2 f32 words): for every layer l its activated output A_l
//     (np_l columns at a_off, written by the training forward) and its scaled pre-activation
//     gradient D_l = GRAD_SCALE·dL/dz_l (np_l columns at d_off, written by the backward). Padding
//     columns hold zeros. Row-major per sample, so a tile's rows are contiguous 32–128-byte runs.
//   partial [splits][ps] f32: per split s of the samples, layer l's dW block [np_l][kcp_l] at
//     p_off_l (kcp_l = kp_l + 16 with a bias: the bias gradient is the product with a column of ones).
//
// Kernels (workgroup = one subgroup of 32 invocations; coop ops only under uniform control flow,
// every coop pointer index and stride a `let` derived from the uniform — the "runtime zero"
// workaround for naga 30's SPIR-V backend, see linear_coop.wgsl):
//   convert_weights: w16 from params (one launch for all layers).
//   forward        : a workgroup owns a tile of T = 32 samples. The input tile goes to workgroup
//                    memory `tile` [32][TS] f16; per layer C = A·Wᵀ on 2 × (np/16) accumulators (A
//                    from `tile` with coopLoadT, Wᵀ blocks from w16 with coopLoad), stored with
//                    coopStoreT to the f32 staging area `stg` [32][SS]; bias + activation applied
//                    there and written back to `tile` as f16 (padding columns 0) for the next layer;
//                    with mode bit 0 also to the tape (A_l); the last layer also to `output` (f32).
//   backward       : per tile: D_last = GRAD_SCALE·d_output ⊙ act'(A_last) into `tile` (f16) and the
//                    tape; for l = last..1: dH = D_l·W_l (coop, A = `tile`, B = w16 row-major blocks)
//                    → `stg`, D_{l−1} = dH ⊙ act'(A_{l−1}) (A_{l−1} from the tape) → `tile` and the
//                    tape. Mode bit 1: d_input = D_0·W_0 / GRAD_SCALE.
//   wgrad          : split-K weight gradients on cooperative matrices: workgroup (block b, split s)
//                    owns a 32×32 block of layer l's padded [np][kcp] dW (2×2 accumulators) and
//                    sums dZᵀ·[H | 1] over its contiguous range of samples, staging 32 samples at a
//                    time in workgroup memory (zeros past n, so partial 16-row blocks are exact);
//                    H = the input (f32 → f16) for layer 0, else A_{l−1} from the tape. The sums go to
//                    `partial` with coopStoreT. One launch for all layers: [max blocks, splits, layers].
//   reduce_grads   : grads[i] += Σ_s partial[s][…] / GRAD_SCALE (one launch for all parameters).
// Sample ranges: chunk = max(64, round32(ceil(n / splits))) samples per split; splits past n exit.

const T: u32 = 32u;          // samples per tile (forward / backward) and per wgrad staging step
const TS: u32 = 72u;         // row stride (f16) of `tile`: 64 columns + 8 (16-byte aligned rows, fewer bank conflicts)
const SS: u32 = 68u;         // row stride (f32) of `stg`
const WS: u32 = 40u;         // row stride (f16) of the wgrad staging tiles (32 columns + 8)
const MAX_LAYERS: u32 = 16u;
const MIN_CHUNK: u32 = 64u;
const COUNTER_N_SAMPLES: u32 = 1u;
const GRAD_SCALE: f32 = 128.0;
const MODE_TAPE: u32 = 1u;
const MODE_DX: u32 = 2u;

struct Layer {
    fan_in: u32, out: u32, kp: u32, np: u32,
    w_off: u32, b_off: u32, has_bias: u32, act: u32,
    w16_off: u32, a_off: u32, d_off: u32, h_off: u32,   // h_off: tape column of A_{l−1} (l > 0)
    kcp: u32, p_off: u32, nbc: u32, nblk: u32,          // wgrad: column blocks (of 32) per block row, blocks of dW
}

struct Params {
    n_layers: u32, input_dim: u32, output_dim: u32, xp: u32,
    s16: u32, mode: u32, splits: u32, ps: u32,
    n_params: u32, w16_total: u32, zero: u32, _pad: u32,
    layers: array<Layer, 16>,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> counters: array<u32>;

var<workgroup> wg_n: u32;
var<workgroup> tile: array<f16, 2304>;   // T × TS
var<workgroup> stg: array<f32, 2176>;    // T × SS
var<workgroup> sd: array<f16, 1280>;     // wgrad: D columns [32 samples][WS]
var<workgroup> sh: array<f16, 1280>;     // wgrad: H columns [32 samples][WS]

fn load_n(lid: u32) -> u32 {
    if lid == 0u {
        wg_n = counters[COUNTER_N_SAMPLES];
    }
    return workgroupUniformLoad(&wg_n);
}

// Samples per wgrad split (a multiple of T; inlined in wgrad, keep the two equal).
fn split_chunk(n: u32) -> u32 {
    let per = (n + P.splits - 1u) / P.splits;
    return max(MIN_CHUNK, (per + T - 1u) / T * T);
}

// log(1 + x) accurate for small x (Goldberg's trick; WGSL has no log1p).
fn log1p_(x: f32) -> f32 {
    let u = 1.0 + x;
    if (u == 1.0) {
        return x;
    }
    return log(u) * (x / (u - 1.0));
}

// exp(x) − 1 accurate for small x.
fn expm1_(x: f32) -> f32 {
    let u = exp(x);
    if (u == 1.0) {
        return x;
    }
    let um1 = u - 1.0;
    if (um1 == -1.0) {
        return -1.0;
    }
    return um1 * (x / log(u));
}

// Activation codes: 0 none, 1 relu, 2 sigmoid, 3 tanh, 4 softplus, 5 exp (as mlp_fused.wgsl).
fn act_apply(a: u32, z: f32) -> f32 {
    switch a {
        case 1u: { return max(z, 0.0); }
        case 2u: { return 1.0 / (1.0 + exp(-z)); }
        case 3u: { return tanh(clamp(z, -15.0, 15.0)); }
        case 4u: { return max(z, 0.0) + log1p_(exp(-abs(z))); }
        case 5u: { return exp(z); }
        default: { return z; }
    }
}

// dy/dz from the output y (as nerf_mlp::Activation::derivative_from_output).
fn act_deriv(a: u32, y: f32) -> f32 {
    switch a {
        case 1u: { return select(0.0, 1.0, y > 0.0); }
        case 2u: { return y * (1.0 - y); }
        case 3u: { return 1.0 - y * y; }
        case 4u: { return -expm1_(-y); }
        case 5u: { return y; }
        default: { return 1.0; }
    }
}

// ---------------------------------------------------------------------------------------------
// convert_weights: w16[w16_off_l + j·kp_l + c] = W_l[j][c] (0 in the padding)
@group(0) @binding(2) var<storage, read> cw_params: array<f32>;
@group(0) @binding(3) var<storage, read_write> cw_w16: array<f16>;

@compute @workgroup_size(256)
fn convert_weights(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, 256u);
    if i >= P.w16_total { return; }
    var l = 0u;
    for (var k = 1u; k < P.n_layers; k++) {
        if i >= P.layers[k].w16_off { l = k; }
    }
    let L = P.layers[l];
    let e = i - L.w16_off;
    let j = e / L.kp;
    let c = e % L.kp;
    var v = 0.0;
    if j < L.out && c < L.fan_in { v = cw_params[L.w_off + j * L.fan_in + c]; }
    cw_w16[i] = f16(v);
}

// ---------------------------------------------------------------------------------------------
// forward: per tile of 32 samples, every layer on cooperative matrices, activations in `tile`.
@group(0) @binding(2) var<storage, read> f_input: array<f32>;
@group(0) @binding(3) var<storage, read> f_params: array<f32>;
@group(0) @binding(4) var<storage, read> f_w16: array<f16>;
@group(0) @binding(5) var<storage, read_write> f_output: array<f32>;
@group(0) @binding(6) var<storage, read_write> f_tape: array<f16>;

@compute @workgroup_size(32)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * T;
    if row0 >= n { return; }
    let din = P.input_dim;
    let xp = P.xp;
    let write_tape = (P.mode & MODE_TAPE) != 0u;
    // The input tile as f16, zeros past n and in the padding columns.
    for (var e = lid; e < T * xp; e += 32u) {
        let r = e / xp;
        let c = e % xp;
        var v = 0.0;
        if row0 + r < n && c < din { v = f_input[(row0 + r) * din + c]; }
        tile[r * TS + c] = f16(v);
    }
    workgroupBarrier();
    // Runtime zero: naga 30's SPIR-V backend fails ("not cached") on literal strides / indices in
    // coop ops; every index and stride below is a `let` derived from the uniform.
    let z = P.zero & 0u;
    let ts = z + TS;
    let ss = z + SS;
    let t_lo = z;            // rows 0..15 of `tile`
    let t_hi = z + 16u * TS; // rows 16..31
    let s_lo = z;
    let s_hi = z + 16u * SS;
    let nl = P.n_layers;
    for (var l = 0u; l < nl; l++) {
        let L = P.layers[l];
        let kp = L.kp;
        let np = L.np;
        let wbase = L.w16_off;
        for (var cb = 0u; cb < np; cb += 16u) {
            var c0 = coop_mat16x16<f32, C>();
            var c1 = coop_mat16x16<f32, C>();
            let wcol = wbase + cb * kp;
            for (var kb = 0u; kb < kp; kb += 16u) {
                // Wᵀ block: W is row-major [np][kp], so Wᵀ is column-major with stride kp.
                let ia0 = t_lo + kb;
                let ia1 = t_hi + kb;
                let ib = wcol + kb;
                let a0 = coopLoadT<coop_mat16x16<f16, A>>(&tile[ia0], ts);
                let a1 = coopLoadT<coop_mat16x16<f16, A>>(&tile[ia1], ts);
                let b = coopLoad<coop_mat16x16<f16, B>>(&f_w16[ib], kp);
                c0 = coopMultiplyAdd(a0, b, c0);
                c1 = coopMultiplyAdd(a1, b, c1);
            }
            let is0 = s_lo + cb;
            let is1 = s_hi + cb;
            coopStoreT(c0, &stg[is0], ss);
            coopStoreT(c1, &stg[is1], ss);
        }
        workgroupBarrier();
        // Epilogue: bias + activation; f16 back to `tile` (zeros in the padding), tape, output.
        let last = l + 1u == nl;
        let out = L.out;
        for (var e = lid; e < T * np; e += 32u) {
            let r = e / np;
            let c = e % np;
            let row = row0 + r;
            var y = 0.0;
            if c < out {
                var zv = stg[r * SS + c];
                if L.has_bias != 0u { zv += f_params[L.b_off + c]; }
                y = act_apply(L.act, zv);
            }
            tile[r * TS + c] = f16(y);
            if row < n {
                if write_tape { f_tape[row * P.s16 + L.a_off + c] = f16(y); }
                if last && c < out { f_output[row * out + c] = y; }
            }
        }
        workgroupBarrier();
    }
}

// ---------------------------------------------------------------------------------------------
// backward: per tile, D_l = GRAD_SCALE·dL/dz_l for every layer (to the tape), d_input on request.
@group(0) @binding(2) var<storage, read> b_d_output: array<f32>;
@group(0) @binding(4) var<storage, read> b_w16: array<f16>;
@group(0) @binding(6) var<storage, read_write> b_tape: array<f16>;
@group(0) @binding(7) var<storage, read_write> b_d_input: array<f32>;

@compute @workgroup_size(32)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * T;
    if row0 >= n { return; }
    let nl = P.n_layers;
    let s16 = P.s16;
    let write_dx = (P.mode & MODE_DX) != 0u;
    // D of the output layer (f16 in `tile`, zeros past n and in the padding).
    {
        let L = P.layers[nl - 1u];
        let np = L.np;
        let out = L.out;
        for (var e = lid; e < T * np; e += 32u) {
            let r = e / np;
            let c = e % np;
            let row = row0 + r;
            var v = 0.0;
            if row < n && c < out {
                let y = f32(b_tape[row * s16 + L.a_off + c]);
                v = GRAD_SCALE * b_d_output[row * out + c] * act_deriv(L.act, y);
            }
            let h = f16(v);
            tile[r * TS + c] = h;
            if row < n { b_tape[row * s16 + L.d_off + c] = h; }
        }
    }
    workgroupBarrier();
    let z = P.zero & 0u;
    let ts = z + TS;
    let ss = z + SS;
    let t_lo = z;
    let t_hi = z + 16u * TS;
    let s_lo = z;
    let s_hi = z + 16u * SS;
    for (var li = 0u; li < nl; li++) {
        let l = nl - 1u - li;
        if l == 0u && !write_dx { break; }
        let L = P.layers[l];
        let kp = L.kp;
        let np = L.np;
        let wbase = L.w16_off;
        // dH = D · W: A = D (rows × np) from `tile`, B = W blocks (row-major [np][kp]).
        for (var kb = 0u; kb < kp; kb += 16u) {
            var c0 = coop_mat16x16<f32, C>();
            var c1 = coop_mat16x16<f32, C>();
            for (var ob = 0u; ob < np; ob += 16u) {
                let ia0 = t_lo + ob;
                let ia1 = t_hi + ob;
                let ib = wbase + ob * kp + kb;
                let a0 = coopLoadT<coop_mat16x16<f16, A>>(&tile[ia0], ts);
                let a1 = coopLoadT<coop_mat16x16<f16, A>>(&tile[ia1], ts);
                let b = coopLoadT<coop_mat16x16<f16, B>>(&b_w16[ib], kp);
                c0 = coopMultiplyAdd(a0, b, c0);
                c1 = coopMultiplyAdd(a1, b, c1);
            }
            let is0 = s_lo + kb;
            let is1 = s_hi + kb;
            coopStoreT(c0, &stg[is0], ss);
            coopStoreT(c1, &stg[is1], ss);
        }
        workgroupBarrier();
        if l > 0u {
            // D_{l−1} = dH ⊙ act'(A_{l−1}) → `tile` and the tape.
            let Lp = P.layers[l - 1u];
            let pout = Lp.out;
            for (var e = lid; e < T * kp; e += 32u) {
                let r = e / kp;
                let c = e % kp;
                let row = row0 + r;
                var g = 0.0;
                if row < n && c < pout {
                    let y = f32(b_tape[row * s16 + Lp.a_off + c]);
                    g = stg[r * SS + c] * act_deriv(Lp.act, y);
                }
                let h = f16(g);
                tile[r * TS + c] = h;
                if row < n { b_tape[row * s16 + Lp.d_off + c] = h; }
            }
        } else {
            let din = P.input_dim;
            for (var e = lid; e < T * din; e += 32u) {
                let r = e / din;
                let c = e % din;
                let row = row0 + r;
                if row < n { b_d_input[row * din + c] = stg[r * SS + c] * (1.0 / GRAD_SCALE); }
            }
        }
        workgroupBarrier();
    }
}

// ---------------------------------------------------------------------------------------------
// wgrad: partial[s][p_off + j·kcp + c] = Σ_{samples of split s} D[row][j] · [H | 1][row][c]
@group(0) @binding(2) var<storage, read> w_input: array<f32>;
@group(0) @binding(6) var<storage, read> w_tape: array<f16>;
@group(0) @binding(8) var<storage, read_write> w_partial: array<f32>;

@compute @workgroup_size(32)
fn wgrad(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    // Layer wid.z, 32×32 block wid.x of its dW (launched for the largest layer: extra blocks exit),
    // split wid.y. Everything here derives from the uniform, workgroup ids and n (uniform control
    // flow for the coop ops; naga treats function-local variables as non-uniform).
    let l = wid.z;
    let L = P.layers[l];
    let blk = wid.x;
    let j0 = (blk / L.nbc) * 32u;
    let c0 = (blk % L.nbc) * 32u;
    let s = wid.y;
    // split_chunk(n) inlined: naga treats the results of user functions with arguments as
    // non-uniform.
    let per = (n + P.splits - 1u) / P.splits;
    let chunk = max(MIN_CHUNK, (per + T - 1u) / T * T);
    let r_begin = s * chunk;
    if r_begin >= n { return; }
    if l >= P.n_layers { return; }
    if blk >= L.nblk { return; }
    let r_end = min(r_begin + chunk, n);
    let has_j1 = j0 + 16u < L.np;
    let has_c1 = c0 + 16u < L.kcp;
    let s16 = P.s16;
    let din = P.input_dim;
    let z = P.zero & 0u;
    let ws = z + WS;
    let i_lo = z;               // samples 0..15 of the staging tiles, columns 0..15
    let i_c1 = z + 16u;         // columns 16..31
    let i_hi = z + 16u * WS;    // samples 16..31
    let i_hc1 = i_hi + 16u;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var r = r_begin; r < r_end; r += T) {
        // Stage 32 samples × 32 columns of D and of [H | 1]; lane = column, so a warp reads one
        // contiguous run of a tape row per step.
        let cc = lid;
        let j = j0 + cc;
        let c = c0 + cc;
        for (var rr = 0u; rr < T; rr++) {
            let row = r + rr;
            var dv = 0.0h;
            var hv = 0.0h;
            if row < r_end {
                if j < L.out { dv = w_tape[row * s16 + L.d_off + j]; }
                if c < L.fan_in {
                    if l == 0u {
                        hv = f16(w_input[row * din + c]);
                    } else {
                        hv = w_tape[row * s16 + L.h_off + c];
                    }
                } else if c == L.kp && L.has_bias != 0u {
                    hv = 1.0h;
                }
            }
            sd[rr * WS + cc] = dv;
            sh[rr * WS + cc] = hv;
        }
        workgroupBarrier();
        // dZᵀ blocks: sd is [sample][j], so dZᵀ (j × samples) is column-major with stride WS.
        {
            let a0 = coopLoad<coop_mat16x16<f16, A>>(&sd[i_lo], ws);
            let a1 = coopLoad<coop_mat16x16<f16, A>>(&sd[i_c1], ws);
            let b0 = coopLoadT<coop_mat16x16<f16, B>>(&sh[i_lo], ws);
            let b1 = coopLoadT<coop_mat16x16<f16, B>>(&sh[i_c1], ws);
            c00 = coopMultiplyAdd(a0, b0, c00);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c10 = coopMultiplyAdd(a1, b0, c10);
            c11 = coopMultiplyAdd(a1, b1, c11);
        }
        {
            let a0 = coopLoad<coop_mat16x16<f16, A>>(&sd[i_hi], ws);
            let a1 = coopLoad<coop_mat16x16<f16, A>>(&sd[i_hc1], ws);
            let b0 = coopLoadT<coop_mat16x16<f16, B>>(&sh[i_hi], ws);
            let b1 = coopLoadT<coop_mat16x16<f16, B>>(&sh[i_hc1], ws);
            c00 = coopMultiplyAdd(a0, b0, c00);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c10 = coopMultiplyAdd(a1, b0, c10);
            c11 = coopMultiplyAdd(a1, b1, c11);
        }
        workgroupBarrier();
    }
    let kcp = L.kcp + z; // a `let` stride (see forward)
    let i00 = s * P.ps + L.p_off + j0 * kcp + c0;
    let i01 = i00 + 16u;
    let i10 = i00 + 16u * kcp;
    let i11 = i10 + 16u;
    coopStoreT(c00, &w_partial[i00], kcp);
    if has_c1 { coopStoreT(c01, &w_partial[i01], kcp); }
    if has_j1 {
        coopStoreT(c10, &w_partial[i10], kcp);
        if has_c1 { coopStoreT(c11, &w_partial[i11], kcp); }
    }
}

// ---------------------------------------------------------------------------------------------
// reduce_grads: grads[i] += Σ_s partial[s][…] / GRAD_SCALE over the used splits
@group(0) @binding(8) var<storage, read> r_partial: array<f32>;
@group(0) @binding(9) var<storage, read_write> r_grads: array<f32>;

@compute @workgroup_size(256)
fn reduce_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, 256u);
    if i >= P.n_params { return; }
    let n = counters[COUNTER_N_SAMPLES];
    if n == 0u { return; }
    var l = 0u;
    for (var k = 1u; k < P.n_layers; k++) {
        if i >= P.layers[k].w_off { l = k; }
    }
    let L = P.layers[l];
    let e = i - L.w_off;
    var j = e / L.fan_in;
    var c = e % L.fan_in;
    if e >= L.out * L.fan_in {
        // The bias (b follows W): the column of ones.
        j = e - L.out * L.fan_in;
        c = L.kp;
    }
    let chunk = split_chunk(n);
    let used = (n + chunk - 1u) / chunk;
    let o = L.p_off + j * L.kcp + c;
    var sum = 0.0;
    for (var s = 0u; s < used; s++) {
        sum += r_partial[s * P.ps + o];
    }
    r_grads[i] = r_grads[i] + sum * (1.0 / GRAD_SCALE);
}
