enable f16;
enable wgpu_cooperative_matrix;
// Linear layers on cooperative matrices (tensor cores): 16×16×16 f16 products, f32 accumulation.
// Host side: nerf_gpu::linear::GpuMlp with use_coop; CPU twin nerf_mlp::Mlp (same results up to
// f16 rounding of the activations, weights and scaled gradients).
//
// Every workgroup is one subgroup of 32 and owns a 32×32 block of C (2×2 accumulators); operands
// come from f16 copies padded to multiples of 16 (zeros in the padding):
//   x16 [rows][xp]        the network input (xp = round16(input_dim)), written by convert_input
//   h16 [layer][rows][hp] hidden post-activations (hp = round16(hidden_dim)), written by forward
//   w16 per layer [np][kp] W with its columns laid out as [input block (xp), hidden block (hp)]
//   dz16 [rows][np]       dL/dz of a layer, scaled by GRAD_SCALE (f16 would flush small gradients)
// Rows are padded to a multiple of 32; rows in [n, round32(n)) are written as zeros so the
// weight-gradient product may run over whole 16-row blocks. The f32 tape / outputs / grads have
// the CPU layout (see linear.wgsl). n = counters[1].
// Entry points: convert_input, convert_weights, forward, output_grad, backward_data,
// backward_weight, reduce_grads (same roles as in linear.wgsl).

struct CP {
    n_out: u32, k_in: u32, ka: u32, act: u32,
    np: u32, kp: u32, xp: u32, hp: u32,
    w16_off: u32, h_src: u32, h_dst: u32, flags: u32,    // flags: 1 dst, 2 out2, 4 bias, 8 d_input, 16 h16
    t_stride: u32, t_off: u32, t_prev_off: u32, out_dim: u32,
    w_off: u32, bias_off: u32, chunk: u32, c_lo: u32,
    prev_act: u32, kcp: u32, in_dim: u32, _pad: u32,
}

const COUNTER_N_SAMPLES: u32 = 1u;
const GRAD_SCALE: f32 = 128.0;

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

@group(0) @binding(0) var<uniform> P: CP;
@group(0) @binding(1) var<storage, read> counters: array<u32>;

var<workgroup> wg_n: u32;
var<workgroup> Cs: array<f32, 1024>; // 32×32 staging of the accumulators

fn load_n(lid: u32) -> u32 {
    if lid == 0u {
        wg_n = counters[COUNTER_N_SAMPLES];
    }
    return workgroupUniformLoad(&wg_n);
}

fn round32(x: u32) -> u32 { return (x + 31u) & ~31u; }

// ---------------------------------------------------------------------------------------------
// convert_input: x16[row][c] for row < round32(n), c < xp
@group(0) @binding(2) var<storage, read> ci_input: array<f32>;
@group(0) @binding(3) var<storage, read_write> ci_x16: array<f16>;

@compute @workgroup_size(256)
fn convert_input(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = counters[COUNTER_N_SAMPLES];
    let i = linear_id(gid, nwg, 256u);
    let row = i / P.xp;
    let c = i % P.xp;
    if row >= round32(n) { return; }
    var v = 0.0;
    if row < n && c < P.in_dim { v = ci_input[row * P.in_dim + c]; }
    ci_x16[i] = f16(v);
}

// ---------------------------------------------------------------------------------------------
// convert_weights: w16[w16_off + j·kp + c] from W (f32, N × K), zero padding
@group(0) @binding(2) var<storage, read> cw_params: array<f32>;
@group(0) @binding(3) var<storage, read_write> cw_w16: array<f16>;

@compute @workgroup_size(256)
fn convert_weights(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, 256u);
    if i >= P.np * P.kp { return; }
    let j = i / P.kp;
    let c = i % P.kp;
    var src = 0xffffffffu;
    if c < P.xp {
        if c < P.ka { src = c; }
    } else if c - P.xp < P.k_in - P.ka {
        src = P.ka + (c - P.xp);
    }
    var v = 0.0;
    if j < P.n_out && src != 0xffffffffu { v = cw_params[P.w_off + j * P.k_in + src]; }
    cw_w16[P.w16_off + i] = f16(v);
}

// ---------------------------------------------------------------------------------------------
// forward: Y = act(A · Wᵀ + b), A = [x16 block, h16 block]
@group(0) @binding(2) var<storage, read> f_x16: array<f16>;
@group(0) @binding(3) var<storage, read_write> f_h16: array<f16>;
@group(0) @binding(4) var<storage, read> f_w16: array<f16>;
@group(0) @binding(5) var<storage, read> f_params: array<f32>;
@group(0) @binding(6) var<storage, read_write> f_dst: array<f32>;
@group(0) @binding(7) var<storage, read_write> f_out: array<f32>;

@compute @workgroup_size(32)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * 32u;
    let col0 = wid.z * 32u;
    if row0 >= n { return; }
    let has_c1 = col0 + 16u < P.np;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    // Two K loops (input block, hidden block): coop ops must not sit under non-uniform `if`s.
    // Wᵀ blocks: W is row-major [np][kp], so Wᵀ is column-major with stride kp.
    for (var kb = 0u; kb < P.xp; kb += 16u) {
        let a0 = coopLoadT<coop_mat16x16<f16, A>>(&f_x16[row0 * P.xp + kb], P.xp);
        let a1 = coopLoadT<coop_mat16x16<f16, A>>(&f_x16[(row0 + 16u) * P.xp + kb], P.xp);
        let b0 = coopLoad<coop_mat16x16<f16, B>>(&f_w16[P.w16_off + col0 * P.kp + kb], P.kp);
        c00 = coopMultiplyAdd(a0, b0, c00);
        c10 = coopMultiplyAdd(a1, b0, c10);
        if has_c1 {
            let b1 = coopLoad<coop_mat16x16<f16, B>>(&f_w16[P.w16_off + (col0 + 16u) * P.kp + kb], P.kp);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c11 = coopMultiplyAdd(a1, b1, c11);
        }
    }
    for (var h = 0u; h < P.kp - P.xp; h += 16u) {
        let a0 = coopLoadT<coop_mat16x16<f16, A>>(&f_h16[P.h_src + row0 * P.hp + h], P.hp);
        let a1 = coopLoadT<coop_mat16x16<f16, A>>(&f_h16[P.h_src + (row0 + 16u) * P.hp + h], P.hp);
        let b0 = coopLoad<coop_mat16x16<f16, B>>(&f_w16[P.w16_off + col0 * P.kp + P.xp + h], P.kp);
        c00 = coopMultiplyAdd(a0, b0, c00);
        c10 = coopMultiplyAdd(a1, b0, c10);
        if has_c1 {
            let b1 = coopLoad<coop_mat16x16<f16, B>>(&f_w16[P.w16_off + (col0 + 16u) * P.kp + P.xp + h], P.kp);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c11 = coopMultiplyAdd(a1, b1, c11);
        }
    }
    // Runtime zero: naga 30's SPIR-V backend fails ("not cached") on literal strides / indices here.
    // (the stride must be a `let`: an inline stride expression is never emitted).
    let z = P.flags & 0u;
    let st = z + 32u;
    let i01 = z + 16u;
    let i10 = z + 512u;
    let i11 = z + 528u;
    coopStoreT(c00, &Cs[z], st);
    coopStoreT(c01, &Cs[i01], st);
    coopStoreT(c10, &Cs[i10], st);
    coopStoreT(c11, &Cs[i11], st);
    workgroupBarrier();
    for (var e = lid; e < 1024u; e += 32u) {
        let row = row0 + e / 32u;
        let col = col0 + e % 32u;
        var y = 0.0;
        let valid = row < n && col < P.n_out;
        if valid {
            var z = Cs[e];
            if (P.flags & 4u) != 0u { z += f_params[P.bias_off + col]; }
            y = act_apply(P.act, z);
            if (P.flags & 1u) != 0u { f_dst[row * P.t_stride + P.t_off + col] = y; }
            if (P.flags & 2u) != 0u { f_out[row * P.out_dim + col] = y; }
        }
        if (P.flags & 16u) != 0u && col < P.hp {
            f_h16[P.h_dst + row * P.hp + col] = f16(y);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// output_grad: dz16[row][col] = GRAD_SCALE · d_output ⊙ act'(y)
@group(0) @binding(2) var<storage, read> o_dout: array<f32>;
@group(0) @binding(3) var<storage, read> o_tape: array<f32>;
@group(0) @binding(4) var<storage, read_write> o_dz16: array<f16>;

@compute @workgroup_size(256)
fn output_grad(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = counters[COUNTER_N_SAMPLES];
    let i = linear_id(gid, nwg, 256u);
    let row = i / P.np;
    let col = i % P.np;
    if row >= round32(n) { return; }
    var v = 0.0;
    if row < n && col < P.n_out {
        let y = o_tape[row * P.t_stride + P.t_off + col];
        v = GRAD_SCALE * o_dout[row * P.out_dim + col] * act_grad(P.act, y);
    }
    o_dz16[i] = f16(v);
}

// ---------------------------------------------------------------------------------------------
// backward_data: dA = dz16 · W16 over padded columns [c_lo, kp)
@group(0) @binding(2) var<storage, read> d_dz16: array<f16>;
@group(0) @binding(3) var<storage, read> d_w16: array<f16>;
@group(0) @binding(4) var<storage, read_write> d_dh16: array<f16>;
@group(0) @binding(5) var<storage, read> d_tape: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_input: array<f32>;

@compute @workgroup_size(32)
fn backward_data(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * 32u;
    let col0 = P.c_lo + wid.z * 32u;
    if row0 >= n { return; }
    let has_c1 = col0 + 16u < P.kp;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var kb = 0u; kb < P.np; kb += 16u) {
        let a0 = coopLoadT<coop_mat16x16<f16, A>>(&d_dz16[row0 * P.np + kb], P.np);
        let a1 = coopLoadT<coop_mat16x16<f16, A>>(&d_dz16[(row0 + 16u) * P.np + kb], P.np);
        let b0 = coopLoadT<coop_mat16x16<f16, B>>(&d_w16[P.w16_off + kb * P.kp + col0], P.kp);
        c00 = coopMultiplyAdd(a0, b0, c00);
        c10 = coopMultiplyAdd(a1, b0, c10);
        if has_c1 {
            let b1 = coopLoadT<coop_mat16x16<f16, B>>(&d_w16[P.w16_off + kb * P.kp + col0 + 16u], P.kp);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c11 = coopMultiplyAdd(a1, b1, c11);
        }
    }
    // Runtime zero: naga 30's SPIR-V backend fails ("not cached") on literal strides / indices here.
    // (the stride must be a `let`: an inline stride expression is never emitted).
    let z = P.flags & 0u;
    let st = z + 32u;
    let i01 = z + 16u;
    let i10 = z + 512u;
    let i11 = z + 528u;
    coopStoreT(c00, &Cs[z], st);
    coopStoreT(c01, &Cs[i01], st);
    coopStoreT(c10, &Cs[i10], st);
    coopStoreT(c11, &Cs[i11], st);
    workgroupBarrier();
    let hidden = P.k_in - P.ka;
    for (var e = lid; e < 1024u; e += 32u) {
        let row = row0 + e / 32u;
        let col = col0 + e % 32u;
        if col >= P.kp { continue; }
        let v = Cs[e];
        if col < P.xp {
            if (P.flags & 8u) != 0u && row < n && col < P.ka {
                let o = row * P.in_dim + col;
                d_input[o] = d_input[o] + v * (1.0 / GRAD_SCALE);
            }
        } else {
            let h = col - P.xp;
            var g = 0.0;
            if row < n && h < hidden {
                g = v * act_grad(P.prev_act, d_tape[row * P.t_stride + P.t_prev_off + h]);
            }
            d_dh16[row * P.hp + h] = f16(g);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// backward_weight: partial[s][j][c] = Σ_{r in split s} dz16[r][j] · [x16, h16, ones][r][c]
@group(0) @binding(2) var<storage, read> w_dz16: array<f16>;
@group(0) @binding(3) var<storage, read> w_x16: array<f16>;
@group(0) @binding(4) var<storage, read> w_h16: array<f16>;
@group(0) @binding(5) var<storage, read> w_ones: array<f16>;
@group(0) @binding(6) var<storage, read_write> w_partial: array<f32>;

@compute @workgroup_size(32)
fn backward_weight(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let c0 = wid.x * 32u;
    let j0 = wid.y * 32u;
    let s = wid.z;
    let r_begin = s * P.chunk;
    let n16 = (n + 15u) & ~15u;
    if r_begin >= n16 { return; }
    let r_end = min(r_begin + P.chunk, n16);
    let has_j1 = j0 + 16u < P.np;
    let c1 = c0 + 16u;
    let has_c1 = c1 < P.kcp;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var r = r_begin; r < r_end; r += 16u) {
        // dZᵀ blocks: dz16 is row-major [rows][np], so dZᵀ is column-major with stride np.
        let a0 = coopLoad<coop_mat16x16<f16, A>>(&w_dz16[r * P.np + j0], P.np);
        var a1 = coop_mat16x16<f16, A>();
        if has_j1 { a1 = coopLoad<coop_mat16x16<f16, A>>(&w_dz16[r * P.np + j0 + 16u], P.np); }
        // [x16 | h16 | ones] blocks (each 16-column block lies in one of them).
        var b0 = coop_mat16x16<f16, B>();
        if c0 < P.xp {
            b0 = coopLoadT<coop_mat16x16<f16, B>>(&w_x16[r * P.xp + c0], P.xp);
        } else if c0 < P.kp {
            b0 = coopLoadT<coop_mat16x16<f16, B>>(&w_h16[P.h_src + r * P.hp + (c0 - P.xp)], P.hp);
        } else if c0 < P.kcp {
            b0 = coopLoadT<coop_mat16x16<f16, B>>(&w_ones[P.flags & 0u], (P.flags & 0u) + 16u); // the bias column of ones
        }
        var b1 = coop_mat16x16<f16, B>();
        if c1 < P.xp {
            b1 = coopLoadT<coop_mat16x16<f16, B>>(&w_x16[r * P.xp + c1], P.xp);
        } else if c1 < P.kp {
            b1 = coopLoadT<coop_mat16x16<f16, B>>(&w_h16[P.h_src + r * P.hp + (c1 - P.xp)], P.hp);
        } else if c1 < P.kcp {
            b1 = coopLoadT<coop_mat16x16<f16, B>>(&w_ones[P.flags & 0u], (P.flags & 0u) + 16u); // the bias column of ones
        }
        c00 = coopMultiplyAdd(a0, b0, c00);
        c01 = coopMultiplyAdd(a0, b1, c01);
        c10 = coopMultiplyAdd(a1, b0, c10);
        c11 = coopMultiplyAdd(a1, b1, c11);
    }
    let base = s * P.np * P.kcp;
    let kcp = P.kcp + (P.flags & 0u); // a `let` stride (see forward)
    let i00 = base + j0 * kcp + c0;
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
// reduce_grads: grads[W/b] += Σ_s partial[s] / GRAD_SCALE over the real (unpadded) entries
@group(0) @binding(2) var<storage, read> r_partial: array<f32>;
@group(0) @binding(3) var<storage, read_write> r_grads: array<f32>;

@compute @workgroup_size(256)
fn reduce_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = counters[COUNTER_N_SAMPLES];
    let has_bias = (P.flags & 4u) != 0u;
    let KC = P.k_in + select(0u, 1u, has_bias);
    let i = linear_id(gid, nwg, 256u);
    if i >= P.n_out * KC { return; }
    let j = i / KC;
    let c = i % KC;
    var cp = P.kp;              // the bias column
    var o = P.bias_off + j;
    if c < P.ka {
        cp = c;
        o = P.w_off + j * P.k_in + c;
    } else if c < P.k_in {
        cp = P.xp + (c - P.ka);
        o = P.w_off + j * P.k_in + c;
    }
    let n16 = (n + 15u) & ~15u;
    let splits = (n16 + P.chunk - 1u) / P.chunk;
    let stride = P.np * P.kcp;
    var sum = 0.0;
    for (var s = 0u; s < splits; s++) {
        sum += r_partial[s * stride + j * P.kcp + cp];
    }
    r_grads[o] = r_grads[o] + sum * (1.0 / GRAD_SCALE);
}
