// Fully fused small MLPs (tiny-cuda-nn style), forward, inference and backward.
// Rust side: nerf_gpu::mlp::FusedMlp. CPU twin: nerf_mlp::Mlp (crates/mlp): layer i computes
// y = act(x·Wᵀ + b), W `out × fan_in` row-major then b, layer by layer in one flat parameter buffer;
// activation derivatives are taken from the saved outputs.
//
// Limits: every width (input, hidden, output) ≤ MAXW = 64, any number of layers, no skips.
//
// Buffers ([n] = counters[1] samples, row-major like the CPU):
//   input [n][input_dim], output [n][output_dim], d_output [n][output_dim], d_input [n][input_dim],
//   params/grads: the CPU layout (grads are ACCUMULATED, +=),
//   layers: one MlpLayer (8 × u32) per linear layer (static, made by FusedMlp::new),
//   tape: tiled. Tile t holds samples t0 = t·T .. t0 + m (m = min(T, n − t0)) and starts at float
//     t0·fps (fps = tape floats per sample = 2·Σ widths). Inside the tile, layer l's activated output
//     A_l is [w_l][m] at + m·a_pre_l and its pre-activation gradient D_l = dL/dz_l is [w_l][m] at
//     + m·d_pre_l. Feature-major inside a tile matches the workgroup tiles, so tape traffic is
//     contiguous; the tile of m < T samples at the end packs into exactly n·fps floats.
//
// Kernels (workgroups of WG = 64 invocations, one tile of T = 32 samples per workgroup):
//   mlp_forward  : input tile → workgroup memory act_t [feature][sample] (row stride AS = 40, so
//                  the 8×4 invocation grid reads/writes without bank conflicts). Per layer every
//                  invocation computes an 8-feature × 4-sample register block (8 named vec4
//                  accumulators, 4 workgroup + 8 weight loads per 32 FMAs); the weights are read
//                  straight from `params` (a warp reads 4 distinct, L1-resident addresses per load:
//                  measured 3× faster on the H100 than staging each layer's W in workgroup memory per
//                  tile, which cost occupancy and a latency-bound copy). Barrier, activation written
//                  back in place. Mode bit 0 also stores every A_l to the tape (coalesced copies).
//   mlp_backward : D_last = d_output ⊙ act'(A_last); for l = last..1: dH = D_l·W_l (same register
//                  blocking), D_{l−1} = dH ⊙ act'(A_{l−1}) in place; every D_l goes to the tape. Mode
//                  bit 1 also writes d_input = D_0·W_0.
//   mlp_wgrad    : weight gradients as a split-K reduction (tiny-cuda-nn also leaves dW to a separate
//                  split-K GEMM): dispatch [G, n_layers]; workgroup (g, l) sums dW_l = Σ_s D_l[s]ᵀ·H[s]
//                  (H = input for l = 0, else A_{l−1}) and db_l = Σ_s D_l[s] over its contiguous range of
//                  tiles in registers (8 o × 8 k per invocation, tiles staged in workgroup memory with
//                  row stride 33), then ONE atomic add per weight per workgroup. With G ≈ capacity/1024
//                  that is ≈ n_params/1024 atomics per sample (≈ 6 for the 32→64→64→3 colour net,
//                  ≈ 3 for the 32→64→16 density net).
// Per sample and step (fwd + bwd) the field's two nets cost ≈ 19 kFLOP forward, ≈ 38 kFLOP backward,
// ≈ 2 KB of tape traffic. Rows/columns beyond a narrow layer's width are computed on clamped indices
// and dropped (uniform control flow, no divergence).
//
// f32 atomics: this file declares grads as atomic<u32> with a compare-and-swap loop (valid on every
// adapter); FusedMlp swaps the block between the GRAD_ATOMIC markers for atomic<f32> + atomicAdd when
// the adapter has SHADER_FLOAT32_ATOMIC.

const T: u32 = 32u;      // samples per tile
const WG: u32 = 64u;     // invocations per workgroup
const MAXW: u32 = 64u;   // widest layer
const AS: u32 = 40u;     // row stride of act_t
const GS: u32 = 33u;     // row stride of the wgrad tiles
const NO_DERIV: u32 = 0xffffffffu;  // bwd_store: no activation derivative (d_input)

struct MlpParams {
    n_layers: u32,
    input_dim: u32,
    output_dim: u32,
    fps: u32,     // tape floats per sample
    mode: u32,    // bit 0: forward stores the tape; bit 1: backward writes d_input
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct MlpLayer {
    fan_in: u32,
    out: u32,
    w_off: u32,
    b_off: u32,
    act: u32,      // 0 none, 1 relu, 2 sigmoid, 3 tanh, 4 softplus, 5 exp
    a_pre: u32,    // tape floats per sample before A_l
    d_pre: u32,    // tape floats per sample before D_l
    has_bias: u32,
}

@group(0) @binding(0) var<uniform> P: MlpParams;
@group(0) @binding(1) var<storage, read> layers: array<MlpLayer>;
@group(0) @binding(2) var<storage, read> counters: array<u32>;     // [1] = n samples
@group(0) @binding(3) var<storage, read> input: array<f32>;
@group(0) @binding(4) var<storage, read> params: array<f32>;
@group(0) @binding(5) var<storage, read_write> output: array<f32>;
@group(0) @binding(6) var<storage, read_write> tape: array<f32>;
@group(0) @binding(7) var<storage, read> d_output: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_input: array<f32>;

// GRAD_ATOMIC_BEGIN
@group(0) @binding(9) var<storage, read_write> grads: array<atomic<u32>>;
fn grad_add(i: u32, v: f32) {
    var old = atomicLoad(&grads[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}
// GRAD_ATOMIC_END

var<workgroup> act_t: array<f32, 2560>;   // MAXW × AS
var<workgroup> b_t: array<f32, 64>;       // MAXW
var<workgroup> d_s: array<f32, 2112>;     // MAXW × GS
var<workgroup> h_s: array<f32, 2112>;     // MAXW × GS

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

// Row o of the forward's register block: act_t[o][sg + 8j] = act(v[j] + b[o]).
fn fwd_store(o: u32, sg: u32, out: u32, a: u32, acc: vec4<f32>) {
    if (o < out) {
        let v = acc + b_t[o];
        let r = o * AS + sg;
        act_t[r] = act_apply(a, v.x);
        act_t[r + 8u] = act_apply(a, v.y);
        act_t[r + 16u] = act_apply(a, v.z);
        act_t[r + 24u] = act_apply(a, v.w);
    }
}

// Row k of the backward's register block (dL/dh_k for the tile's samples): multiplied by
// act'(A_{l−1}) from the tape (src = tape offset of row k) unless this is d_input (a = NO_DERIV).
fn bwd_store(k: u32, sg: u32, fan_in: u32, m: u32, src: u32, a: u32, acc: vec4<f32>) {
    if (k < fan_in) {
        let r = k * AS + sg;
        for (var j = 0u; j < 4u; j++) {
            let s = sg + 8u * j;
            if (s < m) {
                var d = 1.0;
                if (a != NO_DERIV) {
                    d = act_deriv(a, tape[src + k * m + s]);
                }
                act_t[r + 8u * j] = acc[j] * d;
            }
        }
    }
}

@compute @workgroup_size(64)
fn mlp_forward(
    @builtin(local_invocation_index) tid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let n = counters[1];
    let t0 = (wid.x + wid.y * nwg.x) * T;
    if (t0 >= n) {
        return;
    }
    let m = min(T, n - t0);
    let din = P.input_dim;
    let sg = tid % 8u;
    let fg = tid / 8u;
    for (var s = fg; s < m; s += 8u) {
        for (var f = sg; f < din; f += 8u) {
            act_t[f * AS + s] = input[(t0 + s) * din + f];
        }
    }
    let base = t0 * P.fps;
    let nl = P.n_layers;
    for (var l = 0u; l < nl; l++) {
        let L = layers[l];
        if (tid < L.out) {
            var b = 0.0;
            if (L.has_bias != 0u) {
                b = params[L.b_off + tid];
            }
            b_t[tid] = b;
        }
        workgroupBarrier();
        // 8 named vec4 accumulators (not an array: dynamically indexed arrays may live in local memory).
        var c0 = vec4<f32>(0.0);
        var c1 = vec4<f32>(0.0);
        var c2 = vec4<f32>(0.0);
        var c3 = vec4<f32>(0.0);
        var c4 = vec4<f32>(0.0);
        var c5 = vec4<f32>(0.0);
        var c6 = vec4<f32>(0.0);
        var c7 = vec4<f32>(0.0);
        // Rows fg + 8i of W (clamped to the layer: rows ≥ out are computed and dropped).
        let lr = L.out - 1u;
        let r0 = L.w_off + min(fg, lr) * L.fan_in;
        let r1 = L.w_off + min(fg + 8u, lr) * L.fan_in;
        let r2 = L.w_off + min(fg + 16u, lr) * L.fan_in;
        let r3 = L.w_off + min(fg + 24u, lr) * L.fan_in;
        let r4 = L.w_off + min(fg + 32u, lr) * L.fan_in;
        let r5 = L.w_off + min(fg + 40u, lr) * L.fan_in;
        let r6 = L.w_off + min(fg + 48u, lr) * L.fan_in;
        let r7 = L.w_off + min(fg + 56u, lr) * L.fan_in;
        for (var k = 0u; k < L.fan_in; k++) {
            let r = k * AS + sg;
            let a = vec4<f32>(act_t[r], act_t[r + 8u], act_t[r + 16u], act_t[r + 24u]);
            c0 += params[r0 + k] * a;
            c1 += params[r1 + k] * a;
            c2 += params[r2 + k] * a;
            c3 += params[r3 + k] * a;
            c4 += params[r4 + k] * a;
            c5 += params[r5 + k] * a;
            c6 += params[r6 + k] * a;
            c7 += params[r7 + k] * a;
        }
        workgroupBarrier();
        fwd_store(fg, sg, L.out, L.act, c0);
        fwd_store(fg + 8u, sg, L.out, L.act, c1);
        fwd_store(fg + 16u, sg, L.out, L.act, c2);
        fwd_store(fg + 24u, sg, L.out, L.act, c3);
        fwd_store(fg + 32u, sg, L.out, L.act, c4);
        fwd_store(fg + 40u, sg, L.out, L.act, c5);
        fwd_store(fg + 48u, sg, L.out, L.act, c6);
        fwd_store(fg + 56u, sg, L.out, L.act, c7);
        workgroupBarrier();
        if ((P.mode & 1u) != 0u) {
            let dst = base + m * L.a_pre;
            for (var o = fg; o < L.out; o += 8u) {
                for (var s = sg; s < m; s += 8u) {
                    tape[dst + o * m + s] = act_t[o * AS + s];
                }
            }
        }
        if (l + 1u == nl) {
            let dout = L.out;
            for (var s = fg; s < m; s += 8u) {
                for (var o = sg; o < dout; o += 8u) {
                    output[(t0 + s) * dout + o] = act_t[o * AS + s];
                }
            }
        }
    }
}

@compute @workgroup_size(64)
fn mlp_backward(
    @builtin(local_invocation_index) tid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let n = counters[1];
    let t0 = (wid.x + wid.y * nwg.x) * T;
    if (t0 >= n) {
        return;
    }
    let m = min(T, n - t0);
    let base = t0 * P.fps;
    let nl = P.n_layers;
    let write_dx = (P.mode & 2u) != 0u;
    let sg = tid % 8u;
    let fg = tid / 8u;
    // D of the output layer.
    let lo = layers[nl - 1u];
    let dout = lo.out;
    for (var s = fg; s < m; s += 8u) {
        for (var o = sg; o < dout; o += 8u) {
            let y = tape[base + m * (lo.a_pre + o) + s];
            act_t[o * AS + s] = d_output[(t0 + s) * dout + o] * act_deriv(lo.act, y);
        }
    }
    workgroupBarrier();
    {
        let dst = base + m * lo.d_pre;
        for (var o = fg; o < dout; o += 8u) {
            for (var s = sg; s < m; s += 8u) {
                tape[dst + o * m + s] = act_t[o * AS + s];
            }
        }
    }
    for (var li = 0u; li < nl; li++) {
        let l = nl - 1u - li;
        if (l == 0u && !write_dx) {
            break;
        }
        let L = layers[l];
        // Columns fg + 8i of W (clamped to the layer: columns ≥ fan_in are computed and dropped).
        let lc = L.fan_in - 1u;
        let k0 = min(fg, lc);
        let k1 = min(fg + 8u, lc);
        let k2 = min(fg + 16u, lc);
        let k3 = min(fg + 24u, lc);
        let k4 = min(fg + 32u, lc);
        let k5 = min(fg + 40u, lc);
        let k6 = min(fg + 48u, lc);
        let k7 = min(fg + 56u, lc);
        var c0 = vec4<f32>(0.0);
        var c1 = vec4<f32>(0.0);
        var c2 = vec4<f32>(0.0);
        var c3 = vec4<f32>(0.0);
        var c4 = vec4<f32>(0.0);
        var c5 = vec4<f32>(0.0);
        var c6 = vec4<f32>(0.0);
        var c7 = vec4<f32>(0.0);
        for (var o = 0u; o < L.out; o++) {
            let r = o * AS + sg;
            let d = vec4<f32>(act_t[r], act_t[r + 8u], act_t[r + 16u], act_t[r + 24u]);
            let wr = L.w_off + o * L.fan_in;
            c0 += params[wr + k0] * d;
            c1 += params[wr + k1] * d;
            c2 += params[wr + k2] * d;
            c3 += params[wr + k3] * d;
            c4 += params[wr + k4] * d;
            c5 += params[wr + k5] * d;
            c6 += params[wr + k6] * d;
            c7 += params[wr + k7] * d;
        }
        workgroupBarrier();
        var a = NO_DERIV;
        var src = 0u;
        if (l > 0u) {
            let lp = layers[l - 1u];
            a = lp.act;
            src = base + m * lp.a_pre;
        }
        bwd_store(fg, sg, L.fan_in, m, src, a, c0);
        bwd_store(fg + 8u, sg, L.fan_in, m, src, a, c1);
        bwd_store(fg + 16u, sg, L.fan_in, m, src, a, c2);
        bwd_store(fg + 24u, sg, L.fan_in, m, src, a, c3);
        bwd_store(fg + 32u, sg, L.fan_in, m, src, a, c4);
        bwd_store(fg + 40u, sg, L.fan_in, m, src, a, c5);
        bwd_store(fg + 48u, sg, L.fan_in, m, src, a, c6);
        bwd_store(fg + 56u, sg, L.fan_in, m, src, a, c7);
        workgroupBarrier();
        if (l > 0u) {
            let lp = layers[l - 1u];
            let dst = base + m * lp.d_pre;
            for (var k = fg; k < lp.out; k += 8u) {
                for (var s = sg; s < m; s += 8u) {
                    tape[dst + k * m + s] = act_t[k * AS + s];
                }
            }
        } else {
            let din = L.fan_in;
            for (var s = fg; s < m; s += 8u) {
                for (var k = sg; k < din; k += 8u) {
                    d_input[(t0 + s) * din + k] = act_t[k * AS + s];
                }
            }
        }
    }
}

// One atomic add per weight of row o held by this invocation: columns k = tk + 8(4h + c).
fn wgrad_flush(L: MlpLayer, o: u32, tk: u32, lo: vec4<f32>, hi: vec4<f32>) {
    if (o < L.out) {
        let row = L.w_off + o * L.fan_in;
        for (var c = 0u; c < 4u; c++) {
            let k = tk + 8u * c;
            if (k < L.fan_in) {
                grad_add(row + k, lo[c]);
            }
            if (k + 32u < L.fan_in) {
                grad_add(row + k + 32u, hi[c]);
            }
        }
    }
}

@compute @workgroup_size(64)
fn mlp_wgrad(
    @builtin(local_invocation_index) tid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let n = counters[1];
    let l = wid.y;
    let L = layers[l];
    let n_tiles = (n + T - 1u) / T;
    let per = (n_tiles + nwg.x - 1u) / nwg.x;
    let first = wid.x * per;
    let last = min(first + per, n_tiles);
    if (first >= last) {
        return;
    }
    let to = tid / 8u;
    let tk = tid % 8u;
    // e{i}{h}[c] accumulates dW[o = to + 8i][k = tk + 8(4h + c)] (named: registers, not local memory).
    var e00 = vec4<f32>(0.0);
    var e01 = vec4<f32>(0.0);
    var e10 = vec4<f32>(0.0);
    var e11 = vec4<f32>(0.0);
    var e20 = vec4<f32>(0.0);
    var e21 = vec4<f32>(0.0);
    var e30 = vec4<f32>(0.0);
    var e31 = vec4<f32>(0.0);
    var e40 = vec4<f32>(0.0);
    var e41 = vec4<f32>(0.0);
    var e50 = vec4<f32>(0.0);
    var e51 = vec4<f32>(0.0);
    var e60 = vec4<f32>(0.0);
    var e61 = vec4<f32>(0.0);
    var e70 = vec4<f32>(0.0);
    var e71 = vec4<f32>(0.0);
    var bacc = 0.0;
    let din = P.input_dim;
    for (var t = first; t < last; t++) {
        let t0 = t * T;
        let m = min(T, n - t0);
        let base = t0 * P.fps;
        let dsrc = base + m * L.d_pre;
        for (var o = to; o < L.out; o += 8u) {
            for (var s = tk; s < m; s += 8u) {
                d_s[o * GS + s] = tape[dsrc + o * m + s];
            }
        }
        if (l == 0u) {
            for (var s = to; s < m; s += 8u) {
                for (var k = tk; k < din; k += 8u) {
                    h_s[k * GS + s] = input[(t0 + s) * din + k];
                }
            }
        } else {
            let hsrc = base + m * layers[l - 1u].a_pre;
            for (var k = to; k < L.fan_in; k += 8u) {
                for (var s = tk; s < m; s += 8u) {
                    h_s[k * GS + s] = tape[hsrc + k * m + s];
                }
            }
        }
        workgroupBarrier();
        for (var s = 0u; s < m; s++) {
            let h0 = vec4<f32>(h_s[tk * GS + s], h_s[(tk + 8u) * GS + s], h_s[(tk + 16u) * GS + s], h_s[(tk + 24u) * GS + s]);
            let h1 = vec4<f32>(h_s[(tk + 32u) * GS + s], h_s[(tk + 40u) * GS + s], h_s[(tk + 48u) * GS + s], h_s[(tk + 56u) * GS + s]);
            let dr = to * GS + s;
            let d0 = d_s[dr];
            let d1 = d_s[dr + 8u * GS];
            let d2 = d_s[dr + 16u * GS];
            let d3 = d_s[dr + 24u * GS];
            let d4 = d_s[dr + 32u * GS];
            let d5 = d_s[dr + 40u * GS];
            let d6 = d_s[dr + 48u * GS];
            let d7 = d_s[dr + 56u * GS];
            e00 += d0 * h0;
            e01 += d0 * h1;
            e10 += d1 * h0;
            e11 += d1 * h1;
            e20 += d2 * h0;
            e21 += d2 * h1;
            e30 += d3 * h0;
            e31 += d3 * h1;
            e40 += d4 * h0;
            e41 += d4 * h1;
            e50 += d5 * h0;
            e51 += d5 * h1;
            e60 += d6 * h0;
            e61 += d6 * h1;
            e70 += d7 * h0;
            e71 += d7 * h1;
        }
        if (tid < L.out) {
            for (var s = 0u; s < m; s++) {
                bacc += d_s[tid * GS + s];
            }
        }
        workgroupBarrier();
    }
    wgrad_flush(L, to, tk, e00, e01);
    wgrad_flush(L, to + 8u, tk, e10, e11);
    wgrad_flush(L, to + 16u, tk, e20, e21);
    wgrad_flush(L, to + 24u, tk, e30, e31);
    wgrad_flush(L, to + 32u, tk, e40, e41);
    wgrad_flush(L, to + 40u, tk, e50, e51);
    wgrad_flush(L, to + 48u, tk, e60, e61);
    wgrad_flush(L, to + 56u, tk, e70, e71);
    if (L.has_bias != 0u && tid < L.out) {
        grad_add(L.b_off + tid, bacc);
    }
}
