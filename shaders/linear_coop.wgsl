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
// stage K chunks in workgroup memory; see the section near the end), which replace forward,
// backward_data, backward_weight when the host selects LinearPath::CoopTiled. In that mode the
// f16 buffers have round64(capacity) rows (rows in [n, round64(n)) are zeros where written).
// LinearPath::CoopTiledWide adds forward_wide, backward_data_wide, backward_weight_wide (128×128
// blocks, 4×4 accumulators per subgroup; the last section) for the products whose block width is
// a multiple of 128, with round128(capacity) rows.

struct CP {
    n_out: u32, k_in: u32, ka: u32, act: u32,
    np: u32, kp: u32, xp: u32, hp: u32,
    w16_off: u32, h_src: u32, h_dst: u32, flags: u32,    // flags: 1 dst, 2 out2, 4 bias, 8 d_input, 16 h16, 32 act' from h16
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
@group(0) @binding(7) var<storage, read> d_h16: array<f16>;

// The previous layer's post-activation at (row, h), for act'(y): from the f32 tape, or with flag
// 32 (a net whose forward keeps no f32 tape of its hidden layers: ReLU or identity ones, whose
// act' needs only the sign) from its f16 copy in h16, this layer's input. The two differ only
// where 0 < y < 3·10⁻⁸ rounds to an f16 zero, which the next layer's product already saw as 0.
fn prev_y(row: u32, h: u32) -> f32 {
    if (P.flags & 32u) != 0u {
        return f32(d_h16[P.h_src + row * P.hp + h]);
    }
    return d_tape[row * P.t_stride + P.t_prev_off + h];
}

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
                g = v * act_grad(P.prev_act, prev_y(row, h));
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

// forward's epilogue for one entry of C (the product `acc` at row, col): bias, activation, the
// f32 tape / output and the f16 copy (zeros in the padding rows).
fn ft_put(n: u32, row: u32, col: u32, acc: f32) {
    var y = 0.0;
    if row < n && col < P.n_out {
        var z = acc;
        if (P.flags & 4u) != 0u { z += f_params[P.bias_off + col]; }
        y = act_apply(P.act, z);
        if (P.flags & 1u) != 0u { f_dst[row * P.t_stride + P.t_off + col] = y; }
        if (P.flags & 2u) != 0u { f_out[row * P.out_dim + col] = y; }
    }
    if (P.flags & 16u) != 0u && col < P.hp {
        f_h16[P.h_dst + row * P.hp + col] = f16(y);
    }
}

// forward's epilogue for the 16×16 accumulator staged at Cs[cs..], rows r0.., columns c0...
fn ft_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 256u; e += 32u) {
        ft_put(n, r0 + e / 16u, c0 + e % 16u, Cs[cs + e]);
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

// backward_data's epilogue for one entry (row, col) of dA: the input gradient (x16 block) or the
// f16 pre-activation gradient of the previous layer (h16 block; zeros in the padding rows).
fn bt_put(n: u32, row: u32, col: u32, v: f32) {
    if col >= P.kp { return; }
    if col < P.xp {
        if (P.flags & 8u) != 0u && row < n && col < P.ka {
            let o = row * P.in_dim + col;
            d_input[o] = d_input[o] + v * (1.0 / GRAD_SCALE);
        }
    } else {
        let h = col - P.xp;
        var g = 0.0;
        if row < n && h < P.k_in - P.ka {
            g = v * act_grad(P.prev_act, prev_y(row, h));
        }
        d_dh16[row * P.hp + h] = f16(g);
    }
}

// backward_data's epilogue for the 16×16 accumulator staged at Cs[cs..].
fn bt_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 256u; e += 32u) {
        bt_put(n, r0 + e / 16u, c0 + e % 16u, Cs[cs + e]);
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

// Entry (j, c) of a split's dW to the partials (inside np × kp only).
fn wt_put(base: u32, j: u32, c: u32, v: f32) {
    if j < P.np && c < P.kp {
        w_partial[base + j * P.kcp + c] = v;
    }
}

// Writes the 16×16 accumulator staged at Cs[cs..] (dW rows j0.., columns c0..) to the partials.
fn wt_epilogue(base: u32, j0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 256u; e += 32u) {
        wt_put(base, j0 + e / 16u, c0 + e % 16u, Cs[cs + e]);
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

// =============================================================================================
// Wide variants: forward_wide, backward_data_wide, backward_weight_wide (LinearPath::CoopTiledWide).
// As the *_tiled kernels (same bindings, staging helpers and per-element epilogues, same results up
// to the f32 summation order) with 128×128 blocks: a workgroup is 4 subgroups of 32 and owns a
// 128×128 block of C; subgroup sg owns its 64×64 quarter (rows (sg / 2)·64, columns (sg % 2)·64)
// as 4×4 accumulators, so each K step of 16 loads 4 A + 4 B tiles for 16 products (the 64×64
// blocks: 2 + 2 for 4), and each staged chunk feeds 4× the products for 2× the bytes. K runs in
// chunks of 32, staged as in the tiled kernels: each lane moves 8 + 8 vec4<f16> per chunk,
// prefetched into registers one chunk ahead. Epilogue: two accumulators at a time through the
// subgroup's [16][32] slice of `Cw`. The host launches these only for blocks whose width is a
// whole number of 128s (other layers keep the 64×64 kernels) and pads the f16 scratch to 128 rows.
// Workgroup memory: ua 10 240 B + ub 10 240 B + Cw 8 192 B + wg_n 4 B = 28 676 B.

const TW2: u32 = 128u;
const SB2: u32 = 136u;  // f16 row stride of [32][128] chunks (128 + 8)

var<workgroup> ua: array<f16, 5120>;  // A chunk [128][SA], or a [32][SB2] chunk (4352)
var<workgroup> ub: array<f16, 5120>;  // B chunk [128][SA] or [32][SB2]
var<workgroup> Cw: array<f32, 2048>;  // 4 subgroups × [16][32] epilogue staging

fn put_ua(o: u32, v: vec4<f16>) {
    ua[o] = v.x;
    ua[o + 1u] = v.y;
    ua[o + 2u] = v.z;
    ua[o + 3u] = v.w;
}

fn put_ub(o: u32, v: vec4<f16>) {
    ub[o] = v.x;
    ub[o + 1u] = v.y;
    ub[o + 2u] = v.z;
    ub[o + 3u] = v.w;
}

// The [16][32] block staged at Cw[cs..] (rows r0.., columns c0..) through ft_put.
fn fw_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 512u; e += 32u) {
        ft_put(n, r0 + e / 32u, c0 + e % 32u, Cw[cs + e]);
    }
}

@compute @workgroup_size(128)
fn forward_wide(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TW2;
    let col0 = wid.z * TW2;
    if row0 >= n { return; }
    let sg = lid / 32u;
    let lane = lid % 32u;
    // Staging: chunk entry lid + 128·t (t < 8) is row lid / 8 + 16·t, columns 4·(lid % 8) + 0..3.
    let sr = lid / 8u;
    let sq = (lid % 8u) * 4u;
    var a0 = ft_a(n, row0 + sr, sq);
    var a1 = ft_a(n, row0 + sr + 16u, sq);
    var a2 = ft_a(n, row0 + sr + 32u, sq);
    var a3 = ft_a(n, row0 + sr + 48u, sq);
    var a4 = ft_a(n, row0 + sr + 64u, sq);
    var a5 = ft_a(n, row0 + sr + 80u, sq);
    var a6 = ft_a(n, row0 + sr + 96u, sq);
    var a7 = ft_a(n, row0 + sr + 112u, sq);
    var w0 = ft_w(col0 + sr, sq);
    var w1 = ft_w(col0 + sr + 16u, sq);
    var w2 = ft_w(col0 + sr + 32u, sq);
    var w3 = ft_w(col0 + sr + 48u, sq);
    var w4 = ft_w(col0 + sr + 64u, sq);
    var w5 = ft_w(col0 + sr + 80u, sq);
    var w6 = ft_w(col0 + sr + 96u, sq);
    var w7 = ft_w(col0 + sr + 112u, sq);
    // Runtime zero: every coop index / stride is a `let` (naga 30 SPIR-V quirk, see forward).
    let z = P.flags & 0u;
    let sa = z + SA;
    let ia = z + (sg / 2u) * 64u * SA;   // this subgroup's A rows in ua
    let ib = z + (sg % 2u) * 64u * SA;   // this subgroup's W rows (= C columns) in ub
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c02 = coop_mat16x16<f32, C>();
    var c03 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    var c12 = coop_mat16x16<f32, C>();
    var c13 = coop_mat16x16<f32, C>();
    var c20 = coop_mat16x16<f32, C>();
    var c21 = coop_mat16x16<f32, C>();
    var c22 = coop_mat16x16<f32, C>();
    var c23 = coop_mat16x16<f32, C>();
    var c30 = coop_mat16x16<f32, C>();
    var c31 = coop_mat16x16<f32, C>();
    var c32 = coop_mat16x16<f32, C>();
    var c33 = coop_mat16x16<f32, C>();
    for (var kb = 0u; kb < P.kp; kb += 32u) {
        workgroupBarrier(); // the previous chunk's products are done
        put_ua(sr * SA + sq, a0);
        put_ua((sr + 16u) * SA + sq, a1);
        put_ua((sr + 32u) * SA + sq, a2);
        put_ua((sr + 48u) * SA + sq, a3);
        put_ua((sr + 64u) * SA + sq, a4);
        put_ua((sr + 80u) * SA + sq, a5);
        put_ua((sr + 96u) * SA + sq, a6);
        put_ua((sr + 112u) * SA + sq, a7);
        put_ub(sr * SA + sq, w0);
        put_ub((sr + 16u) * SA + sq, w1);
        put_ub((sr + 32u) * SA + sq, w2);
        put_ub((sr + 48u) * SA + sq, w3);
        put_ub((sr + 64u) * SA + sq, w4);
        put_ub((sr + 80u) * SA + sq, w5);
        put_ub((sr + 96u) * SA + sq, w6);
        put_ub((sr + 112u) * SA + sq, w7);
        workgroupBarrier();
        // Prefetch the next chunk (zeros past kp) while this one is multiplied.
        let kn = kb + 32u + sq;
        a0 = ft_a(n, row0 + sr, kn);
        a1 = ft_a(n, row0 + sr + 16u, kn);
        a2 = ft_a(n, row0 + sr + 32u, kn);
        a3 = ft_a(n, row0 + sr + 48u, kn);
        a4 = ft_a(n, row0 + sr + 64u, kn);
        a5 = ft_a(n, row0 + sr + 80u, kn);
        a6 = ft_a(n, row0 + sr + 96u, kn);
        a7 = ft_a(n, row0 + sr + 112u, kn);
        w0 = ft_w(col0 + sr, kn);
        w1 = ft_w(col0 + sr + 16u, kn);
        w2 = ft_w(col0 + sr + 32u, kn);
        w3 = ft_w(col0 + sr + 48u, kn);
        w4 = ft_w(col0 + sr + 64u, kn);
        w5 = ft_w(col0 + sr + 80u, kn);
        w6 = ft_w(col0 + sr + 96u, kn);
        w7 = ft_w(col0 + sr + 112u, kn);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            // Wᵀ blocks: ub holds W rows [128][SA], so Wᵀ is column-major with stride SA.
            let pa0 = ia + ks;
            let pa1 = pa0 + 16u * SA;
            let pa2 = pa0 + 32u * SA;
            let pa3 = pa0 + 48u * SA;
            let pb0 = ib + ks;
            let pb1 = pb0 + 16u * SA;
            let pb2 = pb0 + 32u * SA;
            let pb3 = pb0 + 48u * SA;
            let ma0 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa0], sa);
            let ma1 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa1], sa);
            let ma2 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa2], sa);
            let ma3 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa3], sa);
            let mb0 = coopLoad<coop_mat16x16<f16, B>>(&ub[pb0], sa);
            let mb1 = coopLoad<coop_mat16x16<f16, B>>(&ub[pb1], sa);
            let mb2 = coopLoad<coop_mat16x16<f16, B>>(&ub[pb2], sa);
            let mb3 = coopLoad<coop_mat16x16<f16, B>>(&ub[pb3], sa);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c02 = coopMultiplyAdd(ma0, mb2, c02);
            c03 = coopMultiplyAdd(ma0, mb3, c03);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
            c12 = coopMultiplyAdd(ma1, mb2, c12);
            c13 = coopMultiplyAdd(ma1, mb3, c13);
            c20 = coopMultiplyAdd(ma2, mb0, c20);
            c21 = coopMultiplyAdd(ma2, mb1, c21);
            c22 = coopMultiplyAdd(ma2, mb2, c22);
            c23 = coopMultiplyAdd(ma2, mb3, c23);
            c30 = coopMultiplyAdd(ma3, mb0, c30);
            c31 = coopMultiplyAdd(ma3, mb1, c31);
            c32 = coopMultiplyAdd(ma3, mb2, c32);
            c33 = coopMultiplyAdd(ma3, mb3, c33);
        }
    }
    let st = z + 32u;
    let cs = z + sg * 512u;
    let cs16 = cs + 16u;
    let r0 = row0 + (sg / 2u) * 64u;
    let c0 = col0 + (sg % 2u) * 64u;
    workgroupBarrier();
    coopStoreT(c00, &Cw[cs], st);
    coopStoreT(c01, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 0u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c02, &Cw[cs], st);
    coopStoreT(c03, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 0u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cw[cs], st);
    coopStoreT(c11, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 16u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c12, &Cw[cs], st);
    coopStoreT(c13, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 16u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c20, &Cw[cs], st);
    coopStoreT(c21, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 32u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c22, &Cw[cs], st);
    coopStoreT(c23, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 32u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c30, &Cw[cs], st);
    coopStoreT(c31, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 48u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c32, &Cw[cs], st);
    coopStoreT(c33, &Cw[cs16], st);
    workgroupBarrier();
    fw_epilogue(n, r0 + 48u, c0 + 32u, cs, lane);
}

// The [16][32] block staged at Cw[cs..] through bt_put.
fn bw_epilogue(n: u32, r0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 512u; e += 32u) {
        bt_put(n, r0 + e / 32u, c0 + e % 32u, Cw[cs + e]);
    }
}

@compute @workgroup_size(128)
fn backward_data_wide(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                      @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let row0 = (wid.x + wid.y * nwg.x) * TW2;
    let col0 = P.c_lo + wid.z * TW2;
    if row0 >= n { return; }
    let sg = lid / 32u;
    let lane = lid % 32u;
    // A chunk [128][32] as in forward_wide; B chunk [32][128]: entry lid + 128·t is row
    // lid / 32 + 4·t, columns 4·(lid % 32) + 0..3.
    let sr = lid / 8u;
    let sq = (lid % 8u) * 4u;
    let bk = lid / 32u;
    let bq = (lid % 32u) * 4u;
    var a0 = bt_a(n, row0 + sr, sq);
    var a1 = bt_a(n, row0 + sr + 16u, sq);
    var a2 = bt_a(n, row0 + sr + 32u, sq);
    var a3 = bt_a(n, row0 + sr + 48u, sq);
    var a4 = bt_a(n, row0 + sr + 64u, sq);
    var a5 = bt_a(n, row0 + sr + 80u, sq);
    var a6 = bt_a(n, row0 + sr + 96u, sq);
    var a7 = bt_a(n, row0 + sr + 112u, sq);
    var w0 = bt_w(bk, col0 + bq);
    var w1 = bt_w(bk + 4u, col0 + bq);
    var w2 = bt_w(bk + 8u, col0 + bq);
    var w3 = bt_w(bk + 12u, col0 + bq);
    var w4 = bt_w(bk + 16u, col0 + bq);
    var w5 = bt_w(bk + 20u, col0 + bq);
    var w6 = bt_w(bk + 24u, col0 + bq);
    var w7 = bt_w(bk + 28u, col0 + bq);
    let z = P.flags & 0u;
    let sa = z + SA;
    let sb = z + SB2;
    let ia = z + (sg / 2u) * 64u * SA;
    let ib = z + (sg % 2u) * 64u;
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c02 = coop_mat16x16<f32, C>();
    var c03 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    var c12 = coop_mat16x16<f32, C>();
    var c13 = coop_mat16x16<f32, C>();
    var c20 = coop_mat16x16<f32, C>();
    var c21 = coop_mat16x16<f32, C>();
    var c22 = coop_mat16x16<f32, C>();
    var c23 = coop_mat16x16<f32, C>();
    var c30 = coop_mat16x16<f32, C>();
    var c31 = coop_mat16x16<f32, C>();
    var c32 = coop_mat16x16<f32, C>();
    var c33 = coop_mat16x16<f32, C>();
    for (var kb = 0u; kb < P.np; kb += 32u) {
        workgroupBarrier();
        put_ua(sr * SA + sq, a0);
        put_ua((sr + 16u) * SA + sq, a1);
        put_ua((sr + 32u) * SA + sq, a2);
        put_ua((sr + 48u) * SA + sq, a3);
        put_ua((sr + 64u) * SA + sq, a4);
        put_ua((sr + 80u) * SA + sq, a5);
        put_ua((sr + 96u) * SA + sq, a6);
        put_ua((sr + 112u) * SA + sq, a7);
        put_ub(bk * SB2 + bq, w0);
        put_ub((bk + 4u) * SB2 + bq, w1);
        put_ub((bk + 8u) * SB2 + bq, w2);
        put_ub((bk + 12u) * SB2 + bq, w3);
        put_ub((bk + 16u) * SB2 + bq, w4);
        put_ub((bk + 20u) * SB2 + bq, w5);
        put_ub((bk + 24u) * SB2 + bq, w6);
        put_ub((bk + 28u) * SB2 + bq, w7);
        workgroupBarrier();
        let kn = kb + 32u;
        a0 = bt_a(n, row0 + sr, kn + sq);
        a1 = bt_a(n, row0 + sr + 16u, kn + sq);
        a2 = bt_a(n, row0 + sr + 32u, kn + sq);
        a3 = bt_a(n, row0 + sr + 48u, kn + sq);
        a4 = bt_a(n, row0 + sr + 64u, kn + sq);
        a5 = bt_a(n, row0 + sr + 80u, kn + sq);
        a6 = bt_a(n, row0 + sr + 96u, kn + sq);
        a7 = bt_a(n, row0 + sr + 112u, kn + sq);
        w0 = bt_w(kn + bk, col0 + bq);
        w1 = bt_w(kn + bk + 4u, col0 + bq);
        w2 = bt_w(kn + bk + 8u, col0 + bq);
        w3 = bt_w(kn + bk + 12u, col0 + bq);
        w4 = bt_w(kn + bk + 16u, col0 + bq);
        w5 = bt_w(kn + bk + 20u, col0 + bq);
        w6 = bt_w(kn + bk + 24u, col0 + bq);
        w7 = bt_w(kn + bk + 28u, col0 + bq);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            let pa0 = ia + ks;
            let pa1 = pa0 + 16u * SA;
            let pa2 = pa0 + 32u * SA;
            let pa3 = pa0 + 48u * SA;
            let pb0 = ib + ks * SB2;
            let pb1 = pb0 + 16u;
            let pb2 = pb0 + 32u;
            let pb3 = pb0 + 48u;
            let ma0 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa0], sa);
            let ma1 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa1], sa);
            let ma2 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa2], sa);
            let ma3 = coopLoadT<coop_mat16x16<f16, A>>(&ua[pa3], sa);
            let mb0 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb0], sb);
            let mb1 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb1], sb);
            let mb2 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb2], sb);
            let mb3 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb3], sb);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c02 = coopMultiplyAdd(ma0, mb2, c02);
            c03 = coopMultiplyAdd(ma0, mb3, c03);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
            c12 = coopMultiplyAdd(ma1, mb2, c12);
            c13 = coopMultiplyAdd(ma1, mb3, c13);
            c20 = coopMultiplyAdd(ma2, mb0, c20);
            c21 = coopMultiplyAdd(ma2, mb1, c21);
            c22 = coopMultiplyAdd(ma2, mb2, c22);
            c23 = coopMultiplyAdd(ma2, mb3, c23);
            c30 = coopMultiplyAdd(ma3, mb0, c30);
            c31 = coopMultiplyAdd(ma3, mb1, c31);
            c32 = coopMultiplyAdd(ma3, mb2, c32);
            c33 = coopMultiplyAdd(ma3, mb3, c33);
        }
    }
    let st = z + 32u;
    let cs = z + sg * 512u;
    let cs16 = cs + 16u;
    let r0 = row0 + (sg / 2u) * 64u;
    let c0 = col0 + (sg % 2u) * 64u;
    workgroupBarrier();
    coopStoreT(c00, &Cw[cs], st);
    coopStoreT(c01, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 0u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c02, &Cw[cs], st);
    coopStoreT(c03, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 0u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cw[cs], st);
    coopStoreT(c11, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 16u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c12, &Cw[cs], st);
    coopStoreT(c13, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 16u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c20, &Cw[cs], st);
    coopStoreT(c21, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 32u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c22, &Cw[cs], st);
    coopStoreT(c23, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 32u, c0 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c30, &Cw[cs], st);
    coopStoreT(c31, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 48u, c0 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c32, &Cw[cs], st);
    coopStoreT(c33, &Cw[cs16], st);
    workgroupBarrier();
    bw_epilogue(n, r0 + 48u, c0 + 32u, cs, lane);
}

// The [16][32] block staged at Cw[cs..] (dW rows j0.., columns c0..) through wt_put.
fn ww_epilogue(base: u32, j0: u32, c0: u32, cs: u32, lane: u32) {
    for (var e = lane; e < 512u; e += 32u) {
        wt_put(base, j0 + e / 32u, c0 + e % 32u, Cw[cs + e]);
    }
}

// As backward_weight_tiled, launched over [kp / 128, np / 128, splits]; the bias column is summed
// by the workgroups of column block 0, one lane per dZ column (128 lanes, 128 columns).
@compute @workgroup_size(128)
fn backward_weight_wide(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = load_n(lid);
    let c0 = wid.x * TW2;
    let j0 = wid.y * TW2;
    let s = wid.z;
    let r_begin = s * P.chunk;
    let n16 = (n + 15u) & ~15u;
    if r_begin >= n16 { return; }
    let r_end = min(r_begin + P.chunk, n16);
    let lim = min(r_end, n);
    let sg = lid / 32u;
    let lane = lid % 32u;
    // Both chunks are [32 rows][128 columns]: entry lid + 128·t is row lid / 32 + 4·t, columns
    // 4·(lid % 32) + 0..3.
    let bk = lid / 32u;
    let bq = (lid % 32u) * 4u;
    var d0 = wt_d(r_begin + bk, lim, j0 + bq);
    var d1 = wt_d(r_begin + bk + 4u, lim, j0 + bq);
    var d2 = wt_d(r_begin + bk + 8u, lim, j0 + bq);
    var d3 = wt_d(r_begin + bk + 12u, lim, j0 + bq);
    var d4 = wt_d(r_begin + bk + 16u, lim, j0 + bq);
    var d5 = wt_d(r_begin + bk + 20u, lim, j0 + bq);
    var d6 = wt_d(r_begin + bk + 24u, lim, j0 + bq);
    var d7 = wt_d(r_begin + bk + 28u, lim, j0 + bq);
    var b0 = wt_b(r_begin + bk, lim, c0 + bq);
    var b1 = wt_b(r_begin + bk + 4u, lim, c0 + bq);
    var b2 = wt_b(r_begin + bk + 8u, lim, c0 + bq);
    var b3 = wt_b(r_begin + bk + 12u, lim, c0 + bq);
    var b4 = wt_b(r_begin + bk + 16u, lim, c0 + bq);
    var b5 = wt_b(r_begin + bk + 20u, lim, c0 + bq);
    var b6 = wt_b(r_begin + bk + 24u, lim, c0 + bq);
    var b7 = wt_b(r_begin + bk + 28u, lim, c0 + bq);
    let with_bias = c0 == 0u && (P.flags & 4u) != 0u;
    var bsum = 0.0;
    let z = P.flags & 0u;
    let sb = z + SB2;
    let ia = z + (sg / 2u) * 64u;   // this subgroup's dW rows (dZ columns) in ua
    let ib = z + (sg % 2u) * 64u;   // this subgroup's dW columns in ub
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c02 = coop_mat16x16<f32, C>();
    var c03 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    var c12 = coop_mat16x16<f32, C>();
    var c13 = coop_mat16x16<f32, C>();
    var c20 = coop_mat16x16<f32, C>();
    var c21 = coop_mat16x16<f32, C>();
    var c22 = coop_mat16x16<f32, C>();
    var c23 = coop_mat16x16<f32, C>();
    var c30 = coop_mat16x16<f32, C>();
    var c31 = coop_mat16x16<f32, C>();
    var c32 = coop_mat16x16<f32, C>();
    var c33 = coop_mat16x16<f32, C>();
    for (var r = r_begin; r < r_end; r += 32u) {
        workgroupBarrier();
        put_ua(bk * SB2 + bq, d0);
        put_ua((bk + 4u) * SB2 + bq, d1);
        put_ua((bk + 8u) * SB2 + bq, d2);
        put_ua((bk + 12u) * SB2 + bq, d3);
        put_ua((bk + 16u) * SB2 + bq, d4);
        put_ua((bk + 20u) * SB2 + bq, d5);
        put_ua((bk + 24u) * SB2 + bq, d6);
        put_ua((bk + 28u) * SB2 + bq, d7);
        put_ub(bk * SB2 + bq, b0);
        put_ub((bk + 4u) * SB2 + bq, b1);
        put_ub((bk + 8u) * SB2 + bq, b2);
        put_ub((bk + 12u) * SB2 + bq, b3);
        put_ub((bk + 16u) * SB2 + bq, b4);
        put_ub((bk + 20u) * SB2 + bq, b5);
        put_ub((bk + 24u) * SB2 + bq, b6);
        put_ub((bk + 28u) * SB2 + bq, b7);
        workgroupBarrier();
        let rn = r + 32u + bk;
        d0 = wt_d(rn, lim, j0 + bq);
        d1 = wt_d(rn + 4u, lim, j0 + bq);
        d2 = wt_d(rn + 8u, lim, j0 + bq);
        d3 = wt_d(rn + 12u, lim, j0 + bq);
        d4 = wt_d(rn + 16u, lim, j0 + bq);
        d5 = wt_d(rn + 20u, lim, j0 + bq);
        d6 = wt_d(rn + 24u, lim, j0 + bq);
        d7 = wt_d(rn + 28u, lim, j0 + bq);
        b0 = wt_b(rn, lim, c0 + bq);
        b1 = wt_b(rn + 4u, lim, c0 + bq);
        b2 = wt_b(rn + 8u, lim, c0 + bq);
        b3 = wt_b(rn + 12u, lim, c0 + bq);
        b4 = wt_b(rn + 16u, lim, c0 + bq);
        b5 = wt_b(rn + 20u, lim, c0 + bq);
        b6 = wt_b(rn + 24u, lim, c0 + bq);
        b7 = wt_b(rn + 28u, lim, c0 + bq);
        for (var ks = 0u; ks < 32u; ks += 16u) {
            // dZᵀ blocks: ua holds dZ rows [32][SB2], so dZᵀ is column-major with stride SB2.
            let pa0 = ia + ks * SB2;
            let pa1 = pa0 + 16u;
            let pa2 = pa0 + 32u;
            let pa3 = pa0 + 48u;
            let pb0 = ib + ks * SB2;
            let pb1 = pb0 + 16u;
            let pb2 = pb0 + 32u;
            let pb3 = pb0 + 48u;
            let ma0 = coopLoad<coop_mat16x16<f16, A>>(&ua[pa0], sb);
            let ma1 = coopLoad<coop_mat16x16<f16, A>>(&ua[pa1], sb);
            let ma2 = coopLoad<coop_mat16x16<f16, A>>(&ua[pa2], sb);
            let ma3 = coopLoad<coop_mat16x16<f16, A>>(&ua[pa3], sb);
            let mb0 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb0], sb);
            let mb1 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb1], sb);
            let mb2 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb2], sb);
            let mb3 = coopLoadT<coop_mat16x16<f16, B>>(&ub[pb3], sb);
            c00 = coopMultiplyAdd(ma0, mb0, c00);
            c01 = coopMultiplyAdd(ma0, mb1, c01);
            c02 = coopMultiplyAdd(ma0, mb2, c02);
            c03 = coopMultiplyAdd(ma0, mb3, c03);
            c10 = coopMultiplyAdd(ma1, mb0, c10);
            c11 = coopMultiplyAdd(ma1, mb1, c11);
            c12 = coopMultiplyAdd(ma1, mb2, c12);
            c13 = coopMultiplyAdd(ma1, mb3, c13);
            c20 = coopMultiplyAdd(ma2, mb0, c20);
            c21 = coopMultiplyAdd(ma2, mb1, c21);
            c22 = coopMultiplyAdd(ma2, mb2, c22);
            c23 = coopMultiplyAdd(ma2, mb3, c23);
            c30 = coopMultiplyAdd(ma3, mb0, c30);
            c31 = coopMultiplyAdd(ma3, mb1, c31);
            c32 = coopMultiplyAdd(ma3, mb2, c32);
            c33 = coopMultiplyAdd(ma3, mb3, c33);
        }
        if with_bias {
            for (var k = 0u; k < 32u; k++) {
                bsum += f32(ua[k * SB2 + lid]);
            }
        }
    }
    let base = s * P.np * P.kcp;
    let st = z + 32u;
    let cs = z + sg * 512u;
    let cs16 = cs + 16u;
    let j1 = j0 + (sg / 2u) * 64u;
    let c1 = c0 + (sg % 2u) * 64u;
    workgroupBarrier();
    coopStoreT(c00, &Cw[cs], st);
    coopStoreT(c01, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 0u, c1 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c02, &Cw[cs], st);
    coopStoreT(c03, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 0u, c1 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c10, &Cw[cs], st);
    coopStoreT(c11, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 16u, c1 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c12, &Cw[cs], st);
    coopStoreT(c13, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 16u, c1 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c20, &Cw[cs], st);
    coopStoreT(c21, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 32u, c1 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c22, &Cw[cs], st);
    coopStoreT(c23, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 32u, c1 + 32u, cs, lane);
    workgroupBarrier();
    coopStoreT(c30, &Cw[cs], st);
    coopStoreT(c31, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 48u, c1 + 0u, cs, lane);
    workgroupBarrier();
    coopStoreT(c32, &Cw[cs], st);
    coopStoreT(c33, &Cw[cs16], st);
    workgroupBarrier();
    ww_epilogue(base, j1 + 48u, c1 + 32u, cs, lane);
    if with_bias && j0 + lid < P.np {
        w_partial[base + (j0 + lid) * P.kcp + P.kp] = bsum;
    }
}
