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
//                  accumulators, 4 workgroup + 8 weight loads per 32 FMAs; where a layer's rows of
//                  W start on 16-byte boundaries, as in the hash field's nets, 16 workgroup + 8
//                  vec4 weight loads per 128 FMAs through `params4`, the same buffer viewed as
//                  vec4, summed in the same order); the weights are read
//                  straight from `params` (a warp reads 4 distinct, L1-resident addresses per load:
//                  measured 3× faster on the H100 than staging each layer's W in workgroup memory per
//                  tile, which cost occupancy and a latency-bound copy). Barrier, activation written
//                  back in place. Mode bit 0 also stores every A_l to the tape (coalesced copies).
//                  The last layer computes only its first P.out_rows outputs (the density pass of
//                  a field reads σ alone: one register block instead of two).
//                  Mode bit 2 stores the A_l as one row per sample instead ([n][fps/2]: the density
//                  pass of a compacted step keeps them for mlp_tape_gather).
//   mlp_backward : D_last = d_output ⊙ act'(A_last); for l = last..1: dH = D_l·W_l (same register
//                  blocking), D_{l−1} = dH ⊙ act'(A_{l−1}) in place; every D_l goes to the tape. Mode
//                  bit 1 also writes d_input = D_0·W_0, its first P.dx_cols columns only (the
//                  hash field's colour net needs no gradient for its SH inputs). Where a layer's
//                  out and w_off are multiples of 4, the weights come from Wᵀ (`wt`, written by
//                  mlp_transpose just before) as vec4s over four consecutive o, in the same order.
//   mlp_transpose: wt = Wᵀ per layer from `params` (a few thousand floats, one launch).
//   mlp_wgrad    : weight gradients as a split-K reduction (tiny-cuda-nn also leaves dW to a separate
//                  split-K GEMM): dispatch [G, n_layers], workgroups of 256; workgroup (g, l) sums
//                  dW_l = Σ_s D_l[s]ᵀ·H[s] (H = input for l = 0, else A_{l−1}) and db_l = Σ_s D_l[s] over
//                  its contiguous range of tiles. Each tile's D and H blocks are contiguous in the tape
//                  (input: contiguous [s][k] rows) and are prefetched into registers one tile ahead,
//                  then stored transposed to workgroup memory [sample][feature] (row stride 68
//                  floats) so the product reads vec4s. Each invocation holds an 8 o × 8 k register
//                  block (16 vec4 accumulators, 4 vec4 loads per 64 FMAs) for a run of the tile's
//                  samples; the layer's blocks (nb = ⌈out/8⌉·⌈fan_in/8⌉, rounded up to a power of
//                  two bw ≥ 8) are spread over the 256 invocations as 256/bw sample splits, so a
//                  narrow layer keeps every invocation on blocks inside its width (a 32-wide input
//                  layer: 8 splits of 4 samples; the 3-wide colour output: 32 splits of 1). The
//                  splits are summed in workgroup memory, then each weight's sum is STORED in the
//                  workgroup's row of `partials` ([G][n_params], G ≈ capacity/1024: n_params/256
//                  bytes per sample written and read back). H100, 2^18 samples, when these were one
//                  atomic add per weight and workgroup and the blocks a fixed 8 × 8 grid: 0.68 ms
//                  (density) / 1.07 ms (colour), was 1.21 / 2.01 ms with one 8 × 8 block per
//                  64-invocation workgroup staged without prefetch.
//   mlp_wgrad_sum: grads += the rows of `partials` of the workgroups that had tiles, summed in
//                  order, one invocation per parameter.
//   mlp_tape_gather: the tape's activation half and the output of a compacted batch from the rows
//                  of mode bit 2 (a copy: no forward runs again for the kept samples).
// Per sample and step (fwd + bwd) the field's two nets cost ≈ 19 kFLOP forward, ≈ 38 kFLOP backward,
// ≈ 2 KB of tape traffic. Register blocks wholly past a narrow layer's width are skipped (the
// block count is uniform over the workgroup); inside the last block, rows/columns beyond the width
// are computed on clamped indices and dropped (uniform control flow, no divergence).
//
// No atomics: the weight gradients are summed in a fixed order (tiles and sample splits inside a
// workgroup, then the workgroups' rows in order), so they are the same bits on every run and run
// as fast on adapters without SHADER_FLOAT32_ATOMIC, where a compare-and-swap loop on the same
// few thousand addresses from every workgroup would be the alternative.

const T: u32 = 32u;      // samples per tile
const WG: u32 = 64u;     // invocations per workgroup
const MAXW: u32 = 64u;   // widest layer
const AS: u32 = 40u;     // row stride of act_t
const DT: u32 = 17u;     // row stride of the wgrad tiles in vec4 (68 floats)
const NO_DERIV: u32 = 0xffffffffu;  // bwd_store: no activation derivative (d_input)

struct MlpParams {
    n_layers: u32,
    input_dim: u32,
    output_dim: u32,
    fps: u32,     // tape floats per sample
    mode: u32,    // bit 0: forward stores the tape; bit 1: backward writes d_input; bit 2: forward stores rows
    out_rows: u32,  // forward: outputs computed and written (≤ output_dim; the rest left as they were)
    dx_cols: u32,   // backward: d_input columns computed and written (≤ input_dim; likewise)
    n_params: u32,  // parameters of the net (row length of `partials`)
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
// `params` again, as vec4 (the same buffer; the forward reads 16-byte aligned weight rows with it).
@group(0) @binding(10) var<storage, read> params4: array<vec4<f32>>;
// Wᵀ: per layer [fan_in][out] at the layer's w_off, written by mlp_transpose from `params` before
// each backward, read by mlp_backward as vec4 (wt4, the same buffer).
@group(0) @binding(11) var<storage, read_write> wt: array<f32>;
@group(0) @binding(12) var<storage, read> wt4: array<vec4<f32>>;

// dL/dparams in the CPU layout, ACCUMULATED (+=); only mlp_wgrad_sum writes it.
@group(0) @binding(9) var<storage, read_write> grads: array<f32>;
// mlp_wgrad's sums per workgroup, [G][n_params] (G = arrayLength / n_params, the x extent of the
// mlp_wgrad launch): row g holds workgroup g's sums over its tiles (the workgroups of layer l fill
// that layer's slice); mlp_wgrad_sum adds the rows of the workgroups that had tiles, in order.
@group(0) @binding(13) var<storage, read_write> partials: array<f32>;
// mlp_tape_gather: the row of the density pass's samples each kept sample came from.
@group(0) @binding(14) var<storage, read> rows: array<u32>;

var<workgroup> act_t: array<f32, 2560>;   // MAXW × AS
var<workgroup> b_t: array<f32, 64>;       // MAXW
var<workgroup> d_t: array<vec4<f32>, 544>;  // T × DT vec4: mlp_wgrad's D tile [sample][feature]
var<workgroup> h_t: array<vec4<f32>, 544>;  // T × DT vec4: mlp_wgrad's H tile [sample][feature]

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

// Column group of the invocation's 4 samples in act_t (row r: samples sg, sg + 8, sg + 16, sg + 24).
fn act4(r: u32) -> vec4<f32> {
    return vec4<f32>(act_t[r], act_t[r + 8u], act_t[r + 16u], act_t[r + 24u]);
}

// c += w[j]·a_j for j = 0..3 in that order (four consecutive weights of one row against the 4
// samples of four inputs; the same sums, in the same order, as four steps of the scalar loop).
fn acc4(c: ptr<function, vec4<f32>>, w: vec4<f32>, a0: vec4<f32>, a1: vec4<f32>, a2: vec4<f32>, a3: vec4<f32>) {
    *c += w.x * a0;
    *c += w.y * a1;
    *c += w.z * a2;
    *c += w.w * a3;
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
        // The last layer computes only the outputs asked for (the density pass needs σ alone).
        let out = select(L.out, min(L.out, P.out_rows), l + 1u == nl);
        if (tid < out) {
            var b = 0.0;
            if (L.has_bias != 0u) {
                b = params[L.b_off + tid];
            }
            b_t[tid] = b;
        }
        workgroupBarrier();
        // 8 named vec4 accumulators (not an array: dynamically indexed arrays may live in local memory).
        // For the same reason the loops below are spelled out per block count (1, 2, 4, 8) and per
        // load width (vec4, scalar) instead of indexing the accumulators; so are the backward's.
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
        // Only the blocks that hold a row < out are computed: 8i < out is uniform over the workgroup
        // (fg < 8), so a narrow layer (the density net's 16 outputs, the colour net's 3) runs a
        // loop over 1, 2 or 4 blocks instead of 8.
        let nb = (out + 7u) / 8u;
        // Rows of W that start on a 16-byte boundary (fan_in and w_off multiples of 4: the hash
        // field's nets) are read 4 weights at a time through the vec4 view of `params`: a quarter
        // of the weight loads for the same FMAs.
        if ((L.fan_in % 4u) == 0u && (L.w_off % 4u) == 0u) {
            if (nb > 4u) {
                for (var k = 0u; k < L.fan_in; k += 4u) {
                    let r = k * AS + sg;
                    let a0 = act4(r);
                    let a1 = act4(r + AS);
                    let a2 = act4(r + 2u * AS);
                    let a3 = act4(r + 3u * AS);
                    acc4(&c0, params4[(r0 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c1, params4[(r1 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c2, params4[(r2 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c3, params4[(r3 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c4, params4[(r4 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c5, params4[(r5 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c6, params4[(r6 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c7, params4[(r7 + k) / 4u], a0, a1, a2, a3);
                }
            } else if (nb > 2u) {
                for (var k = 0u; k < L.fan_in; k += 4u) {
                    let r = k * AS + sg;
                    let a0 = act4(r);
                    let a1 = act4(r + AS);
                    let a2 = act4(r + 2u * AS);
                    let a3 = act4(r + 3u * AS);
                    acc4(&c0, params4[(r0 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c1, params4[(r1 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c2, params4[(r2 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c3, params4[(r3 + k) / 4u], a0, a1, a2, a3);
                }
            } else if (nb > 1u) {
                for (var k = 0u; k < L.fan_in; k += 4u) {
                    let r = k * AS + sg;
                    let a0 = act4(r);
                    let a1 = act4(r + AS);
                    let a2 = act4(r + 2u * AS);
                    let a3 = act4(r + 3u * AS);
                    acc4(&c0, params4[(r0 + k) / 4u], a0, a1, a2, a3);
                    acc4(&c1, params4[(r1 + k) / 4u], a0, a1, a2, a3);
                }
            } else {
                for (var k = 0u; k < L.fan_in; k += 4u) {
                    let r = k * AS + sg;
                    let a0 = act4(r);
                    let a1 = act4(r + AS);
                    let a2 = act4(r + 2u * AS);
                    let a3 = act4(r + 3u * AS);
                    acc4(&c0, params4[(r0 + k) / 4u], a0, a1, a2, a3);
                }
            }
        } else {
            if (nb > 4u) {
                for (var k = 0u; k < L.fan_in; k++) {
                    let a = act4(k * AS + sg);
                    c0 += params[r0 + k] * a;
                    c1 += params[r1 + k] * a;
                    c2 += params[r2 + k] * a;
                    c3 += params[r3 + k] * a;
                    c4 += params[r4 + k] * a;
                    c5 += params[r5 + k] * a;
                    c6 += params[r6 + k] * a;
                    c7 += params[r7 + k] * a;
                }
            } else if (nb > 2u) {
                for (var k = 0u; k < L.fan_in; k++) {
                    let a = act4(k * AS + sg);
                    c0 += params[r0 + k] * a;
                    c1 += params[r1 + k] * a;
                    c2 += params[r2 + k] * a;
                    c3 += params[r3 + k] * a;
                }
            } else if (nb > 1u) {
                for (var k = 0u; k < L.fan_in; k++) {
                    let a = act4(k * AS + sg);
                    c0 += params[r0 + k] * a;
                    c1 += params[r1 + k] * a;
                }
            } else {
                for (var k = 0u; k < L.fan_in; k++) {
                    let a = act4(k * AS + sg);
                    c0 += params[r0 + k] * a;
                }
            }
        }
        workgroupBarrier();
        fwd_store(fg, sg, out, L.act, c0);
        fwd_store(fg + 8u, sg, out, L.act, c1);
        fwd_store(fg + 16u, sg, out, L.act, c2);
        fwd_store(fg + 24u, sg, out, L.act, c3);
        fwd_store(fg + 32u, sg, out, L.act, c4);
        fwd_store(fg + 40u, sg, out, L.act, c5);
        fwd_store(fg + 48u, sg, out, L.act, c6);
        fwd_store(fg + 56u, sg, out, L.act, c7);
        workgroupBarrier();
        if ((P.mode & 1u) != 0u) {
            let dst = base + m * L.a_pre;
            for (var o = fg; o < out; o += 8u) {
                for (var s = sg; s < m; s += 8u) {
                    tape[dst + o * m + s] = act_t[o * AS + s];
                }
            }
        }
        if ((P.mode & 4u) != 0u) {
            // Rows instead: each sample's activations A_0 … A_last as one row of fps/2 floats
            // (the density pass of a compacted step; mlp_tape_gather tiles the kept samples' rows).
            let fa = P.fps / 2u;
            for (var s = fg; s < m; s += 8u) {
                let dst = (t0 + s) * fa + L.a_pre;
                for (var o = sg; o < out; o += 8u) {
                    tape[dst + o] = act_t[o * AS + s];
                }
            }
        }
        if (l + 1u == nl) {
            let dout = L.out;
            for (var s = fg; s < m; s += 8u) {
                for (var o = sg; o < out; o += 8u) {
                    output[(t0 + s) * dout + o] = act_t[o * AS + s];
                }
            }
        }
    }
}

// The training forward's tape (its activation half) and output of the kept samples of a compacted
// step, gathered from the rows a forward with mode bit 2 stored for the density pass's samples
// (`input`: [marched][fa], fa = fps/2 = Σ widths) instead of computed again: one invocation per
// kept sample s (n = counters[1]), source row rows[s]. Inside a tile the activations come first,
// A_l's feature j of the tile's sample i at m·(a_pre_l + j) + i, so feature f of the row goes to
// t0·fps + m·f + i (consecutive samples write consecutive floats); the last layer's features are
// also the output row. Copies only: the result is the same bits as mlp_forward on the gathered
// inputs with the same parameters.
@compute @workgroup_size(64)
fn mlp_tape_gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let s = linear_id(gid, nwg, 64u);
    let n = counters[1];
    if (s >= n) {
        return;
    }
    let fa = P.fps / 2u;
    let t0 = s - s % T;
    let m = min(T, n - t0);
    let src = rows[s] * fa;
    let dst = t0 * P.fps + (s - t0);
    let last = layers[P.n_layers - 1u].a_pre;
    for (var f = 0u; f < fa; f++) {
        let v = input[src + f];
        tape[dst + f * m] = v;
        if (f >= last) {
            output[s * P.output_dim + (f - last)] = v;
        }
    }
}

// wt = Wᵀ per layer: dispatch [ceil(MAXW² / 64), n_layers]; invocation i of layer l copies W[o][k]
// (i = o·fan_in + k) to wt[w_off + k·out + o].
@compute @workgroup_size(64)
fn mlp_transpose(@builtin(global_invocation_id) gid: vec3<u32>) {
    let L = layers[gid.y];
    let i = gid.x;
    if (i >= L.out * L.fan_in) {
        return;
    }
    let o = i / L.fan_in;
    let k = i % L.fan_in;
    wt[L.w_off + k * L.out + o] = params[L.w_off + i];
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
        // d_input (l = 0) computes only the columns asked for (the colour net's SH columns have no
        // use for their gradient).
        let fan = select(L.fan_in, min(L.fan_in, P.dx_cols), l == 0u);
        // Columns fg + 8i of W (clamped to the layer: columns ≥ fan are computed and dropped).
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
        // Only the column blocks that hold a column < fan (uniform, as in the forward): the
        // 32-wide first layers run 4 blocks instead of 8.
        let nb = (fan + 7u) / 8u;
        // Where the rows of Wᵀ (mlp_transpose) start on 16-byte boundaries (out and w_off
        // multiples of 4), column k's weights for four consecutive o are one vec4 load, summed in
        // the same order as the scalar loop.
        if ((L.out % 4u) == 0u && (L.w_off % 4u) == 0u) {
            let q0 = L.w_off + k0 * L.out;
            let q1 = L.w_off + k1 * L.out;
            let q2 = L.w_off + k2 * L.out;
            let q3 = L.w_off + k3 * L.out;
            let q4 = L.w_off + k4 * L.out;
            let q5 = L.w_off + k5 * L.out;
            let q6 = L.w_off + k6 * L.out;
            let q7 = L.w_off + k7 * L.out;
            if (nb > 4u) {
                for (var o = 0u; o < L.out; o += 4u) {
                    let r = o * AS + sg;
                    let d0 = act4(r);
                    let d1 = act4(r + AS);
                    let d2 = act4(r + 2u * AS);
                    let d3 = act4(r + 3u * AS);
                    acc4(&c0, wt4[(q0 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c1, wt4[(q1 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c2, wt4[(q2 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c3, wt4[(q3 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c4, wt4[(q4 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c5, wt4[(q5 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c6, wt4[(q6 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c7, wt4[(q7 + o) / 4u], d0, d1, d2, d3);
                }
            } else if (nb > 2u) {
                for (var o = 0u; o < L.out; o += 4u) {
                    let r = o * AS + sg;
                    let d0 = act4(r);
                    let d1 = act4(r + AS);
                    let d2 = act4(r + 2u * AS);
                    let d3 = act4(r + 3u * AS);
                    acc4(&c0, wt4[(q0 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c1, wt4[(q1 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c2, wt4[(q2 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c3, wt4[(q3 + o) / 4u], d0, d1, d2, d3);
                }
            } else if (nb > 1u) {
                for (var o = 0u; o < L.out; o += 4u) {
                    let r = o * AS + sg;
                    let d0 = act4(r);
                    let d1 = act4(r + AS);
                    let d2 = act4(r + 2u * AS);
                    let d3 = act4(r + 3u * AS);
                    acc4(&c0, wt4[(q0 + o) / 4u], d0, d1, d2, d3);
                    acc4(&c1, wt4[(q1 + o) / 4u], d0, d1, d2, d3);
                }
            } else {
                for (var o = 0u; o < L.out; o += 4u) {
                    let r = o * AS + sg;
                    let d0 = act4(r);
                    let d1 = act4(r + AS);
                    let d2 = act4(r + 2u * AS);
                    let d3 = act4(r + 3u * AS);
                    acc4(&c0, wt4[(q0 + o) / 4u], d0, d1, d2, d3);
                }
            }
        } else {
            if (nb > 4u) {
                for (var o = 0u; o < L.out; o++) {
                    let d = act4(o * AS + sg);
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
            } else if (nb > 2u) {
                for (var o = 0u; o < L.out; o++) {
                    let d = act4(o * AS + sg);
                    let wr = L.w_off + o * L.fan_in;
                    c0 += params[wr + k0] * d;
                    c1 += params[wr + k1] * d;
                    c2 += params[wr + k2] * d;
                    c3 += params[wr + k3] * d;
                }
            } else if (nb > 1u) {
                for (var o = 0u; o < L.out; o++) {
                    let d = act4(o * AS + sg);
                    let wr = L.w_off + o * L.fan_in;
                    c0 += params[wr + k0] * d;
                    c1 += params[wr + k1] * d;
                }
            } else {
                for (var o = 0u; o < L.out; o++) {
                    let d = act4(o * AS + sg);
                    let wr = L.w_off + o * L.fan_in;
                    c0 += params[wr + k0] * d;
                }
            }
        }
        workgroupBarrier();
        var a = NO_DERIV;
        var src = 0u;
        if (l > 0u) {
            let lp = layers[l - 1u];
            a = lp.act;
            src = base + m * lp.a_pre;
        }
        bwd_store(fg, sg, fan, m, src, a, c0);
        bwd_store(fg + 8u, sg, fan, m, src, a, c1);
        bwd_store(fg + 16u, sg, fan, m, src, a, c2);
        bwd_store(fg + 24u, sg, fan, m, src, a, c3);
        bwd_store(fg + 32u, sg, fan, m, src, a, c4);
        bwd_store(fg + 40u, sg, fan, m, src, a, c5);
        bwd_store(fg + 48u, sg, fan, m, src, a, c6);
        bwd_store(fg + 56u, sg, fan, m, src, a, c7);
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
                for (var k = sg; k < fan; k += 8u) {
                    d_input[(t0 + s) * din + k] = act_t[k * AS + s];
                }
            }
        }
    }
}

// Weight-gradient tile loads: element e (< len) of the tile's contiguous D / H block, 0 past it.
fn wg_tape(off: u32, len: u32, e: u32) -> f32 {
    if (e < len) {
        return tape[off + e];
    }
    return 0.0;
}

fn wg_input(off: u32, len: u32, e: u32) -> f32 {
    if (e < len) {
        return input[off + e];
    }
    return 0.0;
}

// Elements e, e + 256, e + 512, e + 768 of a block (wg_tape / wg_input four times).
fn wg_tape4(off: u32, len: u32, e: u32) -> vec4<f32> {
    return vec4<f32>(wg_tape(off, len, e), wg_tape(off, len, e + 256u), wg_tape(off, len, e + 512u), wg_tape(off, len, e + 768u));
}

fn wg_input4(off: u32, len: u32, e: u32) -> vec4<f32> {
    return vec4<f32>(wg_input(off, len, e), wg_input(off, len, e + 256u), wg_input(off, len, e + 512u), wg_input(off, len, e + 768u));
}

// One tile's prefetch for mlp_wgrad: elements tid + 256r (r = 0..7) of its D block (out·m floats,
// [o][s]) in d0 (r < 4) and d1, and of its H block (tape: fan_in·m floats [k][s]; input: m·din
// floats [s][k]) in h0, h1. Named vectors, not an array indexed in a loop: naga emits loops that
// drivers may leave rolled, and such an array then lives in local memory.
struct WgTile {
    d0: vec4<f32>,
    d1: vec4<f32>,
    h0: vec4<f32>,
    h1: vec4<f32>,
}

// The tile of m samples from sample t0; dims = (out, fan_in, din), pre = (the layer's d_pre, the
// previous layer's a_pre).
fn wg_fetch(t0: u32, m: u32, dims: vec3<u32>, pre: vec2<u32>, from_input: bool, tid: u32) -> WgTile {
    let base = t0 * P.fps;
    var f: WgTile;
    f.d0 = wg_tape4(base + m * pre.x, dims.x * m, tid);
    f.d1 = wg_tape4(base + m * pre.x, dims.x * m, tid + 1024u);
    if (from_input) {
        f.h0 = wg_input4(t0 * dims.z, m * dims.z, tid);
        f.h1 = wg_input4(t0 * dims.z, m * dims.z, tid + 1024u);
    } else {
        f.h0 = wg_tape4(base + m * pre.y, dims.y * m, tid);
        f.h1 = wg_tape4(base + m * pre.y, dims.y * m, tid + 1024u);
    }
    return f;
}

// Element e of a tile's D block (vd, [o][s]: feature e / m, sample e % m) and of its H block
// (vh: from the tape [k][s] like D, or from the input rows [s][k]: sample e / din, feature
// e % din) into workgroup memory, transposed to [sample][feature]. dims = (m, out, fan_in, din);
// sh and pow2: the shifts and power-of-two flags of m and din (div_mod).
fn wg_put_pair(e: u32, dims: vec4<u32>, sh: vec4<u32>, pow2: vec2<bool>, from_input: bool, vd: f32, vh: f32) {
    let m = dims.x;
    let q = div_mod(e, m, sh.x, pow2.x);
    if (e < dims.y * m) {
        wg_put_d(q.y, q.x, vd);
    }
    if (from_input) {
        if (e < m * dims.w) {
            let qi = div_mod(e, dims.w, sh.y, pow2.y);
            wg_put_h(qi.x, qi.y, vh);
        }
    } else if (e < dims.z * m) {
        wg_put_h(q.y, q.x, vh);
    }
}

// Row o of this invocation's 8 × 8 block: dW[o][tk·8 + j] for j < 8 (lo: j < 4, hi: j ≥ 4), into
// workgroup g's row of `partials`.
fn wgrad_flush(L: MlpLayer, g: u32, o: u32, tk: u32, lo: vec4<f32>, hi: vec4<f32>) {
    if (o < L.out) {
        let row = g * P.n_params + L.w_off + o * L.fan_in;
        for (var j = 0u; j < 4u; j++) {
            let k = tk * 8u + j;
            if (k < L.fan_in) {
                partials[row + k] = lo[j];
            }
            if (k + 4u < L.fan_in) {
                partials[row + k + 4u] = hi[j];
            }
        }
    }
}

// Split reduction: splits 1..ns − 1 park one row (two vec4) of their block b in d_t (at most
// (256 − bw)·2 ≤ 496 of its 544 vec4).
fn wgrad_park(sp: u32, b: u32, bw: u32, lo: vec4<f32>, hi: vec4<f32>) {
    if (sp > 0u) {
        let r = ((sp - 1u) * bw + b) * 2u;
        d_t[r] = lo;
        d_t[r + 1u] = hi;
    }
}

// Sum of the parked vec4 c (0: lo, 1: hi) of splits 1..ns − 1 for block b (split 0 holds the rest).
fn wgrad_gather(b: u32, bw: u32, ns: u32, c: u32) -> vec4<f32> {
    var acc = d_t[b * 2u + c];
    for (var j = 1u; j + 1u < ns; j++) {
        acc += d_t[(j * bw + b) * 2u + c];
    }
    return acc;
}

// Tiles per mlp_wgrad workgroup when `groups` share `n_tiles` (workgroup g takes tiles
// g·per .. g·per + per − 1); mlp_wgrad_sum derives from it which rows of `partials` were written.
fn wgrad_tiles_per_group(n_tiles: u32, groups: u32) -> u32 {
    return (n_tiles + groups - 1u) / groups;
}

// (e / d, e % d); a shift and a mask where d = 2^sh (`pow2`, uniform), else an integer division.
fn div_mod(e: u32, d: u32, sh: u32, pow2: bool) -> vec2<u32> {
    if (pow2) {
        return vec2<u32>(e >> sh, e & (d - 1u));
    }
    return vec2<u32>(e / d, e % d);
}

// Scalar element (row, col) of a [row][DT·4] vec4 workgroup tile.
fn wg_put_d(row: u32, col: u32, v: f32) {
    d_t[row * DT + col / 4u][col % 4u] = v;
}

fn wg_put_h(row: u32, col: u32, v: f32) {
    h_t[row * DT + col / 4u][col % 4u] = v;
}

@compute @workgroup_size(256)
fn mlp_wgrad(
    @builtin(local_invocation_index) tid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let n = counters[1];
    let l = wid.y;
    let L = layers[l];
    let n_tiles = (n + T - 1u) / T;
    let per = wgrad_tiles_per_group(n_tiles, nwg.x);
    let first = wid.x * per;
    let last = min(first + per, n_tiles);
    if (first >= last) {
        return;
    }
    let out = L.out;
    let fan_in = L.fan_in;
    // The layer's 8 o × 8 k blocks of dW (nb ≤ 64), rounded up to a power of two bw ≥ 8: invocation
    // tid holds block b = tid % bw (rows o = 8·to + i, columns k = 8·tk + j) for sample split
    // sp = tid / bw, one of ns = 256 / bw (4..32) contiguous runs of T / ns samples. A narrow layer
    // thus keeps every invocation on blocks inside its width: no block lies wholly past `out` or
    // `fan_in`, whereas a fixed 8 × 8 grid of blocks left half of a 32-wide input layer and 7/8 of
    // the colour net's 3-wide output layer idle or computing columns that are dropped.
    let nbk = (fan_in + 7u) / 8u;
    let nb = ((out + 7u) / 8u) * nbk;
    var bw = 8u;
    while (bw < nb) {
        bw *= 2u;
    }
    let ns = 256u / bw;
    let run = T / ns;
    let sp = tid / bw;
    let b = tid % bw;
    let to = b / nbk;
    let tk = b % nbk;
    let busy = b < nb;
    let from_input = l == 0u;
    let din = P.input_dim;
    let din_sh = countTrailingZeros(din);
    let din_pow2 = (din & (din - 1u)) == 0u;
    var h_pre = 0u;
    if (!from_input) {
        h_pre = layers[l - 1u].a_pre;
    }
    // Register prefetch of the next tile (wg_fetch).
    let fetch_dims = vec3<u32>(out, fan_in, din);
    let fetch_pre = vec2<u32>(L.d_pre, h_pre);
    var pf = wg_fetch(first * T, min(T, n - first * T), fetch_dims, fetch_pre, from_input, tid);
    // a{i}{h}: dW[8to + i][8tk + 4h .. 8tk + 4h + 3] (named: registers, not local memory).
    var a00 = vec4<f32>(0.0);
    var a01 = vec4<f32>(0.0);
    var a10 = vec4<f32>(0.0);
    var a11 = vec4<f32>(0.0);
    var a20 = vec4<f32>(0.0);
    var a21 = vec4<f32>(0.0);
    var a30 = vec4<f32>(0.0);
    var a31 = vec4<f32>(0.0);
    var a40 = vec4<f32>(0.0);
    var a41 = vec4<f32>(0.0);
    var a50 = vec4<f32>(0.0);
    var a51 = vec4<f32>(0.0);
    var a60 = vec4<f32>(0.0);
    var a61 = vec4<f32>(0.0);
    var a70 = vec4<f32>(0.0);
    var a71 = vec4<f32>(0.0);
    var bacc = 0.0;
    for (var t = first; t < last; t++) {
        let t0 = t * T;
        let m = min(T, n - t0);
        // Prefetched registers → workgroup memory, transposed to [sample][feature]. Element e of
        // a [feature][m] block is (e % m, e / m): shifts for a full tile (m = T), a division only
        // in the last, partial one (likewise for the input's [m][din] rows when din is 2^k).
        let sh = vec4<u32>(countTrailingZeros(m), din_sh, 0u, 0u);
        let pow2 = vec2<bool>((m & (m - 1u)) == 0u, din_pow2);
        let dims = vec4<u32>(m, out, fan_in, din);
        wg_put_pair(tid, dims, sh, pow2, from_input, pf.d0.x, pf.h0.x);
        wg_put_pair(tid + 256u, dims, sh, pow2, from_input, pf.d0.y, pf.h0.y);
        wg_put_pair(tid + 512u, dims, sh, pow2, from_input, pf.d0.z, pf.h0.z);
        wg_put_pair(tid + 768u, dims, sh, pow2, from_input, pf.d0.w, pf.h0.w);
        wg_put_pair(tid + 1024u, dims, sh, pow2, from_input, pf.d1.x, pf.h1.x);
        wg_put_pair(tid + 1280u, dims, sh, pow2, from_input, pf.d1.y, pf.h1.y);
        wg_put_pair(tid + 1536u, dims, sh, pow2, from_input, pf.d1.z, pf.h1.z);
        wg_put_pair(tid + 1792u, dims, sh, pow2, from_input, pf.d1.w, pf.h1.w);
        workgroupBarrier();
        // Prefetch tile t + 1 while this one is reduced.
        if (t + 1u < last) {
            pf = wg_fetch(t0 + T, min(T, n - t0 - T), fetch_dims, fetch_pre, from_input, tid);
        }
        // Inside the last block of a row or column, entries past `out` / `fan_in` are computed on
        // stale workgroup memory and dropped at the flush.
        if (busy) {
            let s_end = min(sp * run + run, m);
            for (var s = sp * run; s < s_end; s++) {
                let d0 = d_t[s * DT + to * 2u];
                let d1 = d_t[s * DT + to * 2u + 1u];
                let h0 = h_t[s * DT + tk * 2u];
                let h1 = h_t[s * DT + tk * 2u + 1u];
                a00 += d0.x * h0;
                a01 += d0.x * h1;
                a10 += d0.y * h0;
                a11 += d0.y * h1;
                a20 += d0.z * h0;
                a21 += d0.z * h1;
                a30 += d0.w * h0;
                a31 += d0.w * h1;
                a40 += d1.x * h0;
                a41 += d1.x * h1;
                a50 += d1.y * h0;
                a51 += d1.y * h1;
                a60 += d1.z * h0;
                a61 += d1.z * h1;
                a70 += d1.w * h0;
                a71 += d1.w * h1;
            }
        }
        if (L.has_bias != 0u && tid < out) {
            for (var s = 0u; s < m; s++) {
                bacc += d_t[s * DT + tid / 4u][tid % 4u];
            }
        }
        workgroupBarrier();
    }
    // Sum the sample splits in workgroup memory, one block row at a time (split 0 adds splits
    // 1..ns − 1 in order).
    wgrad_park(sp, b, bw, a00, a01);
    workgroupBarrier();
    if (sp == 0u) { a00 += wgrad_gather(b, bw, ns, 0u); a01 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a10, a11);
    workgroupBarrier();
    if (sp == 0u) { a10 += wgrad_gather(b, bw, ns, 0u); a11 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a20, a21);
    workgroupBarrier();
    if (sp == 0u) { a20 += wgrad_gather(b, bw, ns, 0u); a21 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a30, a31);
    workgroupBarrier();
    if (sp == 0u) { a30 += wgrad_gather(b, bw, ns, 0u); a31 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a40, a41);
    workgroupBarrier();
    if (sp == 0u) { a40 += wgrad_gather(b, bw, ns, 0u); a41 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a50, a51);
    workgroupBarrier();
    if (sp == 0u) { a50 += wgrad_gather(b, bw, ns, 0u); a51 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a60, a61);
    workgroupBarrier();
    if (sp == 0u) { a60 += wgrad_gather(b, bw, ns, 0u); a61 += wgrad_gather(b, bw, ns, 1u); }
    workgroupBarrier();
    wgrad_park(sp, b, bw, a70, a71);
    workgroupBarrier();
    if (sp == 0u && busy) {
        a70 += wgrad_gather(b, bw, ns, 0u);
        a71 += wgrad_gather(b, bw, ns, 1u);
        let o = to * 8u;
        wgrad_flush(L, wid.x, o, tk, a00, a01);
        wgrad_flush(L, wid.x, o + 1u, tk, a10, a11);
        wgrad_flush(L, wid.x, o + 2u, tk, a20, a21);
        wgrad_flush(L, wid.x, o + 3u, tk, a30, a31);
        wgrad_flush(L, wid.x, o + 4u, tk, a40, a41);
        wgrad_flush(L, wid.x, o + 5u, tk, a50, a51);
        wgrad_flush(L, wid.x, o + 6u, tk, a60, a61);
        wgrad_flush(L, wid.x, o + 7u, tk, a70, a71);
    }
    if (L.has_bias != 0u && tid < out) {
        partials[wid.x * P.n_params + L.b_off + tid] = bacc;
    }
}

// grads[p] += Σ_g partials[g][p] over the mlp_wgrad workgroups that had tiles (the same split of
// the tiles as there). Each workgroup sums 32 parameters: its 8 lanes of 32 invocations each add
// every 8th row (g ≡ lane mod 8), in order of g, and then the 8 lane sums are added in lane
// order. No atomics, a fixed order: the weight gradients of a given batch are the same bits on
// every run. (One invocation per parameter summing all rows, as before, left the H100 with a
// few thousand invocations walking a few hundred dependent loads each: 0.21 ms per net.)
const WSUM_P: u32 = 32u;
const WSUM_LANES: u32 = 8u;
var<workgroup> wsum: array<f32, 256>; // [lane][parameter]

@compute @workgroup_size(256)
fn mlp_wgrad_sum(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let pl = lid % WSUM_P;
    let lane = lid / WSUM_P;
    let p = wid.x * WSUM_P + pl;
    let np = P.n_params;
    let n_tiles = (counters[1] + T - 1u) / T;
    let groups = arrayLength(&partials) / np;
    var used = 0u;
    if (n_tiles > 0u) {
        let per = wgrad_tiles_per_group(n_tiles, groups);
        used = (n_tiles + per - 1u) / per;
    }
    var acc = 0.0;
    if (p < np) {
        for (var g = lane; g < used; g += WSUM_LANES) {
            acc += partials[g * np + p];
        }
    }
    wsum[lid] = acc;
    workgroupBarrier();
    if (lane == 0u && p < np && used > 0u) {
        var total = wsum[pl];
        for (var l = 1u; l < WSUM_LANES; l++) {
            total += wsum[l * WSUM_P + pl];
        }
        grads[p] += total;
    }
}
