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
// backward_weight, reduce_grads (same roles as in linear.wgsl), and the workgroup-tiled
// forward_tiled, backward_data_tiled, backward_weight_tiled (4 subgroups share a 64×64 block and
// stage K chunks in workgroup memory; see the section at the end), which replace forward,
// backward_data, backward_weight when the host selects LinearPath::CoopTiled. In that mode the
// f16 buffers have round64(capacity) rows (rows in [n, round64(n)) are zeros where written).

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

// =============================================================================================
// Workgroup-tiled variants: forward_tiled, backward_data_tiled, backward_weight_tiled.
// Same bindings (plus binding 8 in forward_tiled, see there), same epilogues and same results (up
// to the f32 summation order) as forward, backward_data, backward_weight. A workgroup is 4
// subgroups of 32 (128 invocations; subgroup sg = lid / 32, which needs a subgroup size of 32:
// the host checks it) and owns a 64×64 block of C; subgroup sg owns its 32×32 quarter
// (rows (sg / 2)·32, columns (sg % 2)·32) as 2×2 accumulators. K runs in chunks of 32: each
// chunk of A (64×32) and B (32×64) is staged ONCE into workgroup memory (`ta`, `tb`, rows padded
// by 8 f16 = 16 bytes so the 16-byte row reads of a tensor-core load hit distinct banks) by all
// 128 lanes with coalesced 8-byte loads (the f16 buffers bound a second time as
// array<vec4<f16>>: consecutive lanes read consecutive vec4s), zeros past n rows / past np, kp
// columns; the next chunk is prefetched into registers while the subgroups multiply the current
// one from workgroup memory (register double buffering: 2 barriers per chunk, no second copy of
// the staging arrays). Epilogue: each subgroup stores one 16×16 accumulator at a time into its
// quarter of `Cs` (4 × 256 f32) and its 32 lanes apply the unchanged epilogue to it.
// Workgroup memory per entry point: ta 5120 B + tb 5120 B + Cs 4096 B + wg_n 4 B = 14 340 B.
// Rows: the f16 activations / dz16 written by the tiled epilogues are padded to 64 rows (the
// host allocates round64(capacity) rows in tiled mode); rows in [n, round64(n)) are zeros.

const TW: u32 = 64u;   // output block edge
const SA: u32 = 40u;   // f16 row stride of [64][32] chunks (32 + 8)
const SB: u32 = 72u;   // f16 row stride of [32][64] chunks (64 + 8)

var<workgroup> ta: array<f16, 2560>;  // A chunk [64][SA] (backward_weight: dZ chunk [32][SB])
var<workgroup> tb: array<f16, 2560>;  // B chunk [64][SA] (Wᵀ of forward) or [32][SB]

fn put_ta(o: u32, v: vec4<f16>) {
    ta[o] = v.x;
    ta[o + 1u] = v.y;
    ta[o + 2u] = v.z;
    ta[o + 3u] = v.w;
}

fn put_tb(o: u32, v: vec4<f16>) {
    tb[o] = v.x;
    tb[o + 1u] = v.y;
    tb[o + 2u] = v.z;
    tb[o + 3u] = v.w;
}

// ---------------------------------------------------------------------------------------------
// forward_tiled: as forward. Binding 8 is h16 again (as vec4s, for the staging loads; read_write
// like binding 3 so that wgpu accepts the same buffer twice in one dispatch).
@group(0) @binding(2) var<storage, read> ft_x16: array<vec4<f16>>;
@group(0) @binding(4) var<storage, read> ft_w16: array<vec4<f16>>;
@group(0) @binding(8) var<storage, read_write> ft_h16: array<vec4<f16>>;

// Columns c..c+3 of row `row` of A = [x16 block, h16 block]; zeros past n and past kp.
fn ft_a(n: u32, row: u32, c: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if row < n {
        if c < P.xp {
            v = ft_x16[(row * P.xp + c) >> 2u];
        } else if c < P.kp {
            v = ft_h16[(P.h_src + row * P.hp + (c - P.xp)) >> 2u];
        }
    }
    return v;
}

// Columns c..c+3 of row j of W16; zeros past np and past kp.
fn ft_w(j: u32, c: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if j < P.np && c < P.kp {
        v = ft_w16[(P.w16_off + j * P.kp + c) >> 2u];
    }
    return v;
}

// forward's epilogue for the 16×16 accumulator staged at Cs[cs..], rows r0.., columns c0...
fn ft_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 256u; e += 32u) {
        let row = r0 + e / 16u;
        let col = c0 + e % 16u;
        var y = 0.0;
        let valid = row < n && col < P.n_out;
        if valid {
            var z = Cs[cs + e];
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

@compute @workgroup_size(128)
fn forward_tiled(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TW;
    let col0 = wid.z * TW;
    if row0 >= n { return; }
    let sg = lid / 32u;
    let lane = lid % 32u;
    // Staging: chunk entry lid + 128·t (t < 4) is row lid / 8 + 16·t, columns 4·(lid % 8) + 0..3.
    let sr = lid / 8u;
    let sq = (lid % 8u) * 4u;
    var a0 = ft_a(n, row0 + sr, sq);
    var a1 = ft_a(n, row0 + sr + 16u, sq);
    var a2 = ft_a(n, row0 + sr + 32u, sq);
    var a3 = ft_a(n, row0 + sr + 48u, sq);
    var w0 = ft_w(col0 + sr, sq);
    var w1 = ft_w(col0 + sr + 16u, sq);
    var w2 = ft_w(col0 + sr + 32u, sq);
    var w3 = ft_w(col0 + sr + 48u, sq);
    // Runtime zero: every coop index / stride is a `let` (naga 30 SPIR-V quirk, see forward).
    let z = P.flags & 0u;
    let sa = z + SA;
    let ia = z + (sg / 2u) * 32u * SA;   // this subgroup's A rows in ta
    let ib = z + (sg % 2u) * 32u * SA;   // this subgroup's W rows (= C columns) in tb
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var kb = 0u; kb < P.kp; kb += 32u) {
        workgroupBarrier(); // the previous chunk's products are done
        put_ta(sr * SA + sq, a0);
        put_ta((sr + 16u) * SA + sq, a1);
        put_ta((sr + 32u) * SA + sq, a2);
        put_ta((sr + 48u) * SA + sq, a3);
        put_tb(sr * SA + sq, w0);
        put_tb((sr + 16u) * SA + sq, w1);
        put_tb((sr + 32u) * SA + sq, w2);
        put_tb((sr + 48u) * SA + sq, w3);
        workgroupBarrier();
        // Prefetch the next chunk (zeros past kp) while this one is multiplied.
        let kn = kb + 32u + sq;
        a0 = ft_a(n, row0 + sr, kn);
        a1 = ft_a(n, row0 + sr + 16u, kn);
        a2 = ft_a(n, row0 + sr + 32u, kn);
        a3 = ft_a(n, row0 + sr + 48u, kn);
        w0 = ft_w(col0 + sr, kn);
        w1 = ft_w(col0 + sr + 16u, kn);
        w2 = ft_w(col0 + sr + 32u, kn);
        w3 = ft_w(col0 + sr + 48u, kn);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            // Wᵀ blocks: tb holds W rows [64][SA], so Wᵀ is column-major with stride SA.
            let pa0 = ia + ks;
            let pa1 = pa0 + 16u * SA;
            let pb0 = ib + ks;
            let pb1 = pb0 + 16u * SA;
            let ma0 = coopLoadT<coop_mat16x16<f16, A>>(&ta[pa0], sa);
            let ma1 = coopLoadT<coop_mat16x16<f16, A>>(&ta[pa1], sa);
            let mb0 = coopLoad<coop_mat16x16<f16, B>>(&tb[pb0], sa);
            let mb1 = coopLoad<coop_mat16x16<f16, B>>(&tb[pb1], sa);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
        }
    }
    let st = z + 16u;
    let cs = z + sg * 256u;
    let r0 = row0 + (sg / 2u) * 32u;
    let c0 = col0 + (sg % 2u) * 32u;
    coopStoreT(c00, &Cs[cs], st);
    workgroupBarrier();
    ft_epilogue(n, r0, c0, cs, lane);
    workgroupBarrier();
    coopStoreT(c01, &Cs[cs], st);
    workgroupBarrier();
    ft_epilogue(n, r0, c0 + 16u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cs[cs], st);
    workgroupBarrier();
    ft_epilogue(n, r0 + 16u, c0, cs, lane);
    workgroupBarrier();
    coopStoreT(c11, &Cs[cs], st);
    workgroupBarrier();
    ft_epilogue(n, r0 + 16u, c0 + 16u, cs, lane);
}

// ---------------------------------------------------------------------------------------------
// backward_data_tiled: as backward_data (columns [c_lo, kp) in 64-column blocks).
@group(0) @binding(2) var<storage, read> bt_dz16: array<vec4<f16>>;
@group(0) @binding(3) var<storage, read> bt_w16: array<vec4<f16>>;

// Columns c..c+3 of row `row` of dz16; zeros past n and past np.
fn bt_a(n: u32, row: u32, c: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if row < n && c < P.np {
        v = bt_dz16[(row * P.np + c) >> 2u];
    }
    return v;
}

// Columns c..c+3 of row k of W16; zeros past np and past kp.
fn bt_w(k: u32, c: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if k < P.np && c < P.kp {
        v = bt_w16[(P.w16_off + k * P.kp + c) >> 2u];
    }
    return v;
}

// backward_data's epilogue for the 16×16 accumulator staged at Cs[cs..].
fn bt_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    let hidden = P.k_in - P.ka;
    for (var e = lane; e < 256u; e += 32u) {
        let row = r0 + e / 16u;
        let col = c0 + e % 16u;
        if col >= P.kp { continue; }
        let v = Cs[cs + e];
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

@compute @workgroup_size(128)
fn backward_data_tiled(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                       @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TW;
    let col0 = P.c_lo + wid.z * TW;
    if row0 >= n { return; }
    let sg = lid / 32u;
    let lane = lid % 32u;
    // A chunk [64][32] as in forward_tiled; B chunk [32][64]: entry lid + 128·t is row
    // lid / 16 + 8·t, columns 4·(lid % 16) + 0..3.
    let sr = lid / 8u;
    let sq = (lid % 8u) * 4u;
    let bk = lid / 16u;
    let bq = (lid % 16u) * 4u;
    var a0 = bt_a(n, row0 + sr, sq);
    var a1 = bt_a(n, row0 + sr + 16u, sq);
    var a2 = bt_a(n, row0 + sr + 32u, sq);
    var a3 = bt_a(n, row0 + sr + 48u, sq);
    var w0 = bt_w(bk, col0 + bq);
    var w1 = bt_w(bk + 8u, col0 + bq);
    var w2 = bt_w(bk + 16u, col0 + bq);
    var w3 = bt_w(bk + 24u, col0 + bq);
    let z = P.flags & 0u;
    let sa = z + SA;
    let sb = z + SB;
    let ia = z + (sg / 2u) * 32u * SA;
    let ib = z + (sg % 2u) * 32u;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var kb = 0u; kb < P.np; kb += 32u) {
        workgroupBarrier();
        put_ta(sr * SA + sq, a0);
        put_ta((sr + 16u) * SA + sq, a1);
        put_ta((sr + 32u) * SA + sq, a2);
        put_ta((sr + 48u) * SA + sq, a3);
        put_tb(bk * SB + bq, w0);
        put_tb((bk + 8u) * SB + bq, w1);
        put_tb((bk + 16u) * SB + bq, w2);
        put_tb((bk + 24u) * SB + bq, w3);
        workgroupBarrier();
        let kn = kb + 32u;
        a0 = bt_a(n, row0 + sr, kn + sq);
        a1 = bt_a(n, row0 + sr + 16u, kn + sq);
        a2 = bt_a(n, row0 + sr + 32u, kn + sq);
        a3 = bt_a(n, row0 + sr + 48u, kn + sq);
        w0 = bt_w(kn + bk, col0 + bq);
        w1 = bt_w(kn + bk + 8u, col0 + bq);
        w2 = bt_w(kn + bk + 16u, col0 + bq);
        w3 = bt_w(kn + bk + 24u, col0 + bq);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            let pa0 = ia + ks;
            let pa1 = pa0 + 16u * SA;
            let pb0 = ib + ks * SB;
            let pb1 = pb0 + 16u;
            let ma0 = coopLoadT<coop_mat16x16<f16, A>>(&ta[pa0], sa);
            let ma1 = coopLoadT<coop_mat16x16<f16, A>>(&ta[pa1], sa);
            let mb0 = coopLoadT<coop_mat16x16<f16, B>>(&tb[pb0], sb);
            let mb1 = coopLoadT<coop_mat16x16<f16, B>>(&tb[pb1], sb);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
        }
    }
    let st = z + 16u;
    let cs = z + sg * 256u;
    let r0 = row0 + (sg / 2u) * 32u;
    let c0 = col0 + (sg % 2u) * 32u;
    coopStoreT(c00, &Cs[cs], st);
    workgroupBarrier();
    bt_epilogue(n, r0, c0, cs, lane);
    workgroupBarrier();
    coopStoreT(c01, &Cs[cs], st);
    workgroupBarrier();
    bt_epilogue(n, r0, c0 + 16u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cs[cs], st);
    workgroupBarrier();
    bt_epilogue(n, r0 + 16u, c0, cs, lane);
    workgroupBarrier();
    coopStoreT(c11, &Cs[cs], st);
    workgroupBarrier();
    bt_epilogue(n, r0 + 16u, c0 + 16u, cs, lane);
}

// ---------------------------------------------------------------------------------------------
// backward_weight_tiled: as backward_weight, launched over [round64(kp)/64, round64(np)/64, splits]:
// the 64×64 blocks cover the [x16, h16] columns only; the bias column (kp) is Σ_r dZ[r][j], summed
// in f32 from the staged dZ chunks by the workgroups of column block 0 (the product with the ones
// column of backward_weight, exactly, up to summation order), so that no block is spent on it.
// Chunks run over the split's rows [r_begin, r_end) in steps of 32 (zeros past n).
@group(0) @binding(2) var<storage, read> wt_dz16: array<vec4<f16>>;
@group(0) @binding(3) var<storage, read> wt_x16: array<vec4<f16>>;
@group(0) @binding(4) var<storage, read> wt_h16: array<vec4<f16>>;

// Columns j..j+3 of row `row` of dz16; zeros at rows ≥ lim and past np.
fn wt_d(row: u32, lim: u32, j: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if row < lim && j < P.np {
        v = wt_dz16[(row * P.np + j) >> 2u];
    }
    return v;
}

// Columns c..c+3 of row `row` of [x16, h16]; zeros at rows ≥ lim and past kp.
fn wt_b(row: u32, lim: u32, c: u32) -> vec4<f16> {
    var v = vec4<f16>();
    if row < lim {
        if c < P.xp {
            v = wt_x16[(row * P.xp + c) >> 2u];
        } else if c < P.kp {
            v = wt_h16[(P.h_src + row * P.hp + (c - P.xp)) >> 2u];
        }
    }
    return v;
}

// Writes the 16×16 accumulator staged at Cs[cs..] (dW rows j0.., columns c0..) to the partials.
fn wt_epilogue(base: u32, j0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 256u; e += 32u) {
        let j = j0 + e / 16u;
        let c = c0 + e % 16u;
        if j < P.np && c < P.kp {
            w_partial[base + j * P.kcp + c] = Cs[cs + e];
        }
    }
}

@compute @workgroup_size(128)
fn backward_weight_tiled(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let c0 = wid.x * TW;
    let j0 = wid.y * TW;
    let s = wid.z;
    let r_begin = s * P.chunk;
    let n16 = (n + 15u) & ~15u;
    if r_begin >= n16 { return; }
    let r_end = min(r_begin + P.chunk, n16);
    let lim = min(r_end, n);
    let sg = lid / 32u;
    let lane = lid % 32u;
    // Both chunks are [32 rows][64 columns]: entry lid + 128·t is row lid / 16 + 8·t, columns
    // 4·(lid % 16) + 0..3.
    let bk = lid / 16u;
    let bq = (lid % 16u) * 4u;
    var d0 = wt_d(r_begin + bk, lim, j0 + bq);
    var d1 = wt_d(r_begin + bk + 8u, lim, j0 + bq);
    var d2 = wt_d(r_begin + bk + 16u, lim, j0 + bq);
    var d3 = wt_d(r_begin + bk + 24u, lim, j0 + bq);
    var b0 = wt_b(r_begin + bk, lim, c0 + bq);
    var b1 = wt_b(r_begin + bk + 8u, lim, c0 + bq);
    var b2 = wt_b(r_begin + bk + 16u, lim, c0 + bq);
    var b3 = wt_b(r_begin + bk + 24u, lim, c0 + bq);
    // The bias column: lane lid sums column lid % 64 over rows 16·(lid / 64) .. +16 of each chunk.
    let with_bias = c0 == 0u && (P.flags & 4u) != 0u;
    let bj = lid % 64u;
    let bh = (lid / 64u) * 16u;
    var bsum = 0.0;
    let z = P.flags & 0u;
    let sb = z + SB;
    let ia = z + (sg / 2u) * 32u;   // this subgroup's dW rows (dZ columns) in ta
    let ib = z + (sg % 2u) * 32u;   // this subgroup's dW columns in tb
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    for (var r = r_begin; r < r_end; r += 32u) {
        workgroupBarrier();
        put_ta(bk * SB + bq, d0);
        put_ta((bk + 8u) * SB + bq, d1);
        put_ta((bk + 16u) * SB + bq, d2);
        put_ta((bk + 24u) * SB + bq, d3);
        put_tb(bk * SB + bq, b0);
        put_tb((bk + 8u) * SB + bq, b1);
        put_tb((bk + 16u) * SB + bq, b2);
        put_tb((bk + 24u) * SB + bq, b3);
        workgroupBarrier();
        let rn = r + 32u + bk;
        d0 = wt_d(rn, lim, j0 + bq);
        d1 = wt_d(rn + 8u, lim, j0 + bq);
        d2 = wt_d(rn + 16u, lim, j0 + bq);
        d3 = wt_d(rn + 24u, lim, j0 + bq);
        b0 = wt_b(rn, lim, c0 + bq);
        b1 = wt_b(rn + 8u, lim, c0 + bq);
        b2 = wt_b(rn + 16u, lim, c0 + bq);
        b3 = wt_b(rn + 24u, lim, c0 + bq);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            // dZᵀ blocks: ta holds dZ rows [32][SB], so dZᵀ is column-major with stride SB.
            let pa0 = ia + ks * SB;
            let pa1 = pa0 + 16u;
            let pb0 = ib + ks * SB;
            let pb1 = pb0 + 16u;
            let ma0 = coopLoad<coop_mat16x16<f16, A>>(&ta[pa0], sb);
            let ma1 = coopLoad<coop_mat16x16<f16, A>>(&ta[pa1], sb);
            let mb0 = coopLoadT<coop_mat16x16<f16, B>>(&tb[pb0], sb);
            let mb1 = coopLoadT<coop_mat16x16<f16, B>>(&tb[pb1], sb);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
        }
        if with_bias {
            for (var k = bh; k < bh + 16u; k++) {
                bsum += f32(ta[k * SB + bj]);
            }
        }
    }
    let base = s * P.np * P.kcp;
    let st = z + 16u;
    let cs = z + sg * 256u;
    let j1 = j0 + (sg / 2u) * 32u;
    let c1 = c0 + (sg % 2u) * 32u;
    coopStoreT(c00, &Cs[cs], st);
    workgroupBarrier();
    wt_epilogue(base, j1, c1, cs, lane);
    workgroupBarrier();
    coopStoreT(c01, &Cs[cs], st);
    workgroupBarrier();
    wt_epilogue(base, j1, c1 + 16u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cs[cs], st);
    workgroupBarrier();
    wt_epilogue(base, j1 + 16u, c1, cs, lane);
    workgroupBarrier();
    coopStoreT(c11, &Cs[cs], st);
    workgroupBarrier();
    wt_epilogue(base, j1 + 16u, c1 + 16u, cs, lane);
    if with_bias {
        workgroupBarrier();
        Cs[lid] = bsum;
        workgroupBarrier();
        if lid < 64u && j0 + lid < P.np {
            w_partial[base + (j0 + lid) * P.kcp + P.kp] = Cs[lid] + Cs[lid + 64u];
        }
    }
}
