// Multiresolution hash encoding (Instant-NGP), forward, parameter backward and the gradient
// w.r.t. the input positions (hash_input_grad).
// CPU twin: nerf_encoding::HashGrid (crates/encoding/src/hash_grid.rs); host side:
// nerf_gpu::encoding::GpuHashGrid. Same level resolutions, dense/hashed levels, spatial hash
// (x·1 ⊕ y·2654435761 ⊕ z·805459861) & (T−1), corner order (bit 0 = +x, bit 1 = +y, bit 2 = +z),
// trilinear weights and summation order as the CPU.
//
// Layouts (row-major, exactly the CPU's):
//   counters   array<u32>; counters[1] = n samples (nerf_gpu::layout::COUNTER_N_SAMPLES)
//   positions  [n][3] f32 in WORLD units; normalised as nerf-field-hash does:
//              clamp((p − aabb_min)·inv_extent, 0, 1), NaN → 0 (Rust's f32::max maps NaN to 0)
//   params     [n_params] f32 = HashGrid::params(): level l starts at levels[l].y (in floats),
//              slot-major within a level: feature j of slot s is params[off + s·F + j]
//   features   [n][L·F] f32, level-major (sample i, level l, feature j at (i·L + l)·F + j)
//   d_features [n][L·F] f32 (same layout); grads: same layout as params, ACCUMULATED
//
// Launch: workgroups (x, y) = groups_1d(capacity, WG), z = L. One invocation per (sample, level):
// a workgroup reads a single level's table (cache locality, as tiny-cuda-nn). Invocations with
// i >= n return.
//
// `Feat` holds the F features of one slot as one vector load: f32 (F = 1), vec2 (F = 2),
// vec4 (F = 4 and 8, two per slot for F = 8). The host rewrites the alias line below for F ≠ 2
// (GpuHashGrid::new). The backward entry points add with atomic<f32> (hash_backward_atomic, needs
// SHADER_FLOAT32_ATOMIC; the host strips the marked section when the adapter lacks it) or with a
// compare-and-swap loop on atomic<u32> (hash_backward_cas); hash_backward_subgroup (needs SUBGROUP
// as well; its section is stripped without it) sums each dense level's additions over the
// subgroup before the atomics.

alias Feat = vec2<f32>;

// F (features per level).
override FEATS: u32 = 2u;
// Feat vectors per slot (F / components of Feat).
override VEC_PER_SLOT: u32 = 1u;
override WG: u32 = 128u;

struct Params {
    aabb_min: vec3<f32>,
    n_levels: u32,
    inv_extent: vec3<f32>,
    // o of p = x·s_l + o: 0 (corner grids) or ½ (staggered, tiny-cuda-nn's).
    offset: f32,
    // Per level: x = resolution (cells per axis), y = offset of the level in params (floats),
    // z = 1 when dense, w = T − 1 (hash mask).
    levels: array<vec4<u32>, 64>,
    // Per level l: s_l of p = x·s_l + o, at scales[l / 4][l % 4] (the resolution for corner grids).
    scales: array<vec4<f32>, 16>,
}

fn level_scale(l: u32) -> f32 {
    return P.scales[l / 4u][l % 4u];
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> counters: array<u32>;
@group(0) @binding(2) var<storage, read> positions: array<f32>;
@group(0) @binding(3) var<storage, read> table: array<Feat>;
@group(0) @binding(4) var<storage, read_write> features: array<Feat>;
@group(0) @binding(5) var<storage, read> d_features: array<f32>;
@group(0) @binding(6) var<storage, read_write> grads_cas: array<atomic<u32>>;

// The 8 corners of a sample's cell at one level: slot indices within the level, weights, and the
// position within the cell (the weights' factors; the input gradient differentiates them).
struct Cell {
    // Slots of corners 0..3 (z = 0) and 4..7 (z = 1).
    s0: vec4<u32>,
    s1: vec4<u32>,
    // Their trilinear weights.
    w0: vec4<f32>,
    w1: vec4<f32>,
    frac: vec3<f32>,
}

fn is_nan(v: f32) -> bool {
    // Bit test: WGSL lets compilers assume x == x for floats.
    return (bitcast<u32>(v) & 0x7fffffffu) > 0x7f800000u;
}

// Position i normalised to [0, 1]³ as nerf-field-hash does.
fn unit_position(i: u32) -> vec3<f32> {
    let p = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    var x = (p - P.aabb_min) * P.inv_extent;
    for (var a = 0u; a < 3u; a++) {
        x[a] = select(clamp(x[a], 0.0, 1.0), 0.0, is_nan(x[a]));
    }
    return x;
}

// Written without arrays or loops over the corners: naga emits WGSL loops as `loop { if !cond
// { break } }`, which drivers may leave rolled, and then an array indexed by the loop counter
// (here the corners' slots and weights, and naga's copies of value arrays) lives in local memory,
// and the corners' table reads wait on each other (on the H100 the plain GEMM's accumulators, an
// array indexed in loops, ran 22x slower than the same sums in named registers). The same
// integers and the same products, in the same order, as the CPU.
fn cell(x: vec3<f32>, lv: vec4<u32>, l: u32) -> Cell {
    let res = lv.x;
    // + 0 (corner grids) leaves every p ≥ 0 as it is.
    let p = x * level_scale(l) + P.offset;
    let v = min(vec3<u32>(p), vec3<u32>(res - 1u));
    let f = p - vec3<f32>(v);
    var c: Cell;
    if (lv.z != 0u) {
        let s = res + 1u;
        let base = v.x + s * (v.y + s * v.z);
        c.s0 = vec4<u32>(base, base + 1u, base + s, base + 1u + s);
        c.s1 = c.s0 + vec4<u32>(s * s);
    } else {
        let hy0 = v.y * 2654435761u;
        let hy1 = (v.y + 1u) * 2654435761u;
        let xy = vec4<u32>(v.x ^ hy0, (v.x + 1u) ^ hy0, v.x ^ hy1, (v.x + 1u) ^ hy1);
        c.s0 = (xy ^ vec4<u32>(v.z * 805459861u)) & vec4<u32>(lv.w);
        c.s1 = (xy ^ vec4<u32>((v.z + 1u) * 805459861u)) & vec4<u32>(lv.w);
    }
    let ax0 = 1.0 - f.x;
    let ay0 = 1.0 - f.y;
    let wxy = vec4<f32>(ax0 * ay0, f.x * ay0, ax0 * f.y, f.x * f.y);
    c.w0 = wxy * (1.0 - f.z);
    c.w1 = wxy * f.z;
    c.frac = f;
    return c;
}

// Samples of this step, bounded by what the bound buffers hold.
fn n_samples(out_len: u32, per_sample: u32) -> u32 {
    return min(counters[1], min(arrayLength(&positions) / 3u, out_len / per_sample));
}

@compute @workgroup_size(WG)
fn hash_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let l = gid.z;
    let nl = P.n_levels;
    if (i >= n_samples(arrayLength(&features), nl * VEC_PER_SLOT) || l >= nl) {
        return;
    }
    let lv = P.levels[l];
    let c = cell(unit_position(i), lv, l);
    let base = lv.y / (FEATS / VEC_PER_SLOT);
    let out = (i * nl + l) * VEC_PER_SLOT;
    for (var v = 0u; v < VEC_PER_SLOT; v++) {
        // The 8 reads first (independent, all in flight at once), then the sum in corner order.
        let t0 = table[base + c.s0.x * VEC_PER_SLOT + v];
        let t1 = table[base + c.s0.y * VEC_PER_SLOT + v];
        let t2 = table[base + c.s0.z * VEC_PER_SLOT + v];
        let t3 = table[base + c.s0.w * VEC_PER_SLOT + v];
        let t4 = table[base + c.s1.x * VEC_PER_SLOT + v];
        let t5 = table[base + c.s1.y * VEC_PER_SLOT + v];
        let t6 = table[base + c.s1.z * VEC_PER_SLOT + v];
        let t7 = table[base + c.s1.w * VEC_PER_SLOT + v];
        var acc = Feat(0.0);
        acc += c.w0.x * t0;
        acc += c.w0.y * t1;
        acc += c.w0.z * t2;
        acc += c.w0.w * t3;
        acc += c.w1.x * t4;
        acc += c.w1.y * t5;
        acc += c.w1.z * t6;
        acc += c.w1.w * t7;
        features[out + v] = acc;
    }
}

// d_features of (sample i, level l), or false when they are all zero (nothing to add).
// Features 0..3 in g0, 4..7 in g1 (F ≤ 8), zeros past F; FEATS is a pipeline constant, so the
// branches on it fold away.
struct Grad {
    g0: vec4<f32>,
    g1: vec4<f32>,
    any: bool,
}

fn load_grad(i: u32, l: u32) -> Grad {
    var r: Grad;
    r.g0 = vec4<f32>(0.0);
    r.g1 = vec4<f32>(0.0);
    let o = (i * P.n_levels + l) * FEATS;
    r.g0.x = d_features[o];
    if (FEATS > 1u) {
        r.g0.y = d_features[o + 1u];
    }
    if (FEATS > 2u) {
        r.g0.z = d_features[o + 2u];
        r.g0.w = d_features[o + 3u];
    }
    if (FEATS > 4u) {
        r.g1 = vec4<f32>(d_features[o + 4u], d_features[o + 5u], d_features[o + 6u], d_features[o + 7u]);
    }
    r.any = any(r.g0 != vec4<f32>(0.0)) || any(r.g1 != vec4<f32>(0.0));
    return r;
}

// Feature j of g (the opt-in subgroup path, which loops over j).
fn grad_at(g: Grad, j: u32) -> f32 {
    return select(g.g0, g.g1, j >= 4u)[j & 3u];
}

// Slot and weight of corner k (the opt-in subgroup path, which loops over the corners).
fn corner_slot(c: Cell, k: u32) -> u32 {
    return select(c.s0, c.s1, k >= 4u)[k & 3u];
}

fn corner_weight(c: Cell, k: u32) -> f32 {
    return select(c.w0, c.w1, k >= 4u)[k & 3u];
}

fn add_cas(idx: u32, v: f32) {
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
fn hash_backward_cas(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let l = gid.z;
    if (i >= n_samples(arrayLength(&d_features), P.n_levels * FEATS) || l >= P.n_levels) {
        return;
    }
    let g = load_grad(i, l);
    if (!g.any) {
        return;
    }
    let lv = P.levels[l];
    let c = cell(unit_position(i), lv, l);
    add_corner_cas(lv.y + c.s0.x * FEATS, c.w0.x, g);
    add_corner_cas(lv.y + c.s0.y * FEATS, c.w0.y, g);
    add_corner_cas(lv.y + c.s0.z * FEATS, c.w0.z, g);
    add_corner_cas(lv.y + c.s0.w * FEATS, c.w0.w, g);
    add_corner_cas(lv.y + c.s1.x * FEATS, c.w1.x, g);
    add_corner_cas(lv.y + c.s1.y * FEATS, c.w1.y, g);
    add_corner_cas(lv.y + c.s1.z * FEATS, c.w1.z, g);
    add_corner_cas(lv.y + c.s1.w * FEATS, c.w1.w, g);
}

fn add_cas_nonzero(idx: u32, d: f32) {
    if (d != 0.0) {
        add_cas(idx, d);
    }
}

// w·g added to the F features at `o` with compare-and-swap (none for zeros).
fn add_corner_cas(o: u32, w: f32, g: Grad) {
    add_cas_nonzero(o, w * g.g0.x);
    if (FEATS > 1u) {
        add_cas_nonzero(o + 1u, w * g.g0.y);
    }
    if (FEATS > 2u) {
        add_cas_nonzero(o + 2u, w * g.g0.z);
        add_cas_nonzero(o + 3u, w * g.g0.w);
    }
    if (FEATS > 4u) {
        add_cas_nonzero(o + 4u, w * g.g1.x);
        add_cas_nonzero(o + 5u, w * g.g1.y);
        add_cas_nonzero(o + 6u, w * g.g1.z);
        add_cas_nonzero(o + 7u, w * g.g1.w);
    }
}

// ---- Gradient w.r.t. the WORLD positions (camera pose refinement) ----
// CPU twin: HashGrid::backward(xn, d_features, _, Some(d_input)) (input_grad_chunk) followed by
// the chain rule through nerf-field-hash's normalisation (backward_inputs_t):
//   per level l (in order), skipped when d_features of (i, l) are all zero:
//     s_k   = Σ_j g_j · table[corner k][j]                 (j in order, from 0)
//     dw[a] = Σ_k s_k · ∂w_k/∂frac[a] (the other two axes' factors; k in order)
//     acc[a] += dw[a] · res_l
//   d_positions[3i + a] = acc[a] · inv_extent[a] where 0 < xn[a] < 1, else 0 (a coordinate on or
//   outside the box's faces, or NaN, is taken as clamped).
// Reads the f32 table (params, as array<f32> at binding 10), never the f16 mirror. One invocation
// per sample (levels looped, no atomics); OVERWRITES the 3 floats of samples i < n, leaves the
// rows past n untouched. Launch: groups_1d(capacity, WG), z = 1.
@group(0) @binding(10) var<storage, read> table_f32: array<f32>;
@group(0) @binding(11) var<storage, read_write> d_positions: array<f32>;

@compute @workgroup_size(WG)
fn hash_input_grad(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let nl = P.n_levels;
    let n = min(n_samples(arrayLength(&d_positions), 3u), arrayLength(&d_features) / (nl * FEATS));
    if (i >= n) {
        return;
    }
    let x = unit_position(i);
    var acc = vec3<f32>(0.0);
    for (var l = 0u; l < nl; l++) {
        let g = load_grad(i, l);
        if (!g.any) {
            continue;
        }
        let lv = P.levels[l];
        let c = cell(x, lv, l);
        let s0 = vec4<f32>(
            corner_dot(lv.y + c.s0.x * FEATS, g),
            corner_dot(lv.y + c.s0.y * FEATS, g),
            corner_dot(lv.y + c.s0.z * FEATS, g),
            corner_dot(lv.y + c.s0.w * FEATS, g),
        );
        let s1 = vec4<f32>(
            corner_dot(lv.y + c.s1.x * FEATS, g),
            corner_dot(lv.y + c.s1.y * FEATS, g),
            corner_dot(lv.y + c.s1.z * FEATS, g),
            corner_dot(lv.y + c.s1.w * FEATS, g),
        );
        // Corner k = (bx, by, bz): its weight's factors a·[b] = (1 − frac, frac)[b] and their
        // derivatives (−1, 1)[b], in corner order.
        let f = c.frac;
        let x0 = 1.0 - f.x;
        let y0 = 1.0 - f.y;
        let z0 = 1.0 - f.z;
        var dw = vec3<f32>(0.0);
        dw_add(&dw, s0.x, x0, y0, z0, -1.0, -1.0, -1.0);
        dw_add(&dw, s0.y, f.x, y0, z0, 1.0, -1.0, -1.0);
        dw_add(&dw, s0.z, x0, f.y, z0, -1.0, 1.0, -1.0);
        dw_add(&dw, s0.w, f.x, f.y, z0, 1.0, 1.0, -1.0);
        dw_add(&dw, s1.x, x0, y0, f.z, -1.0, -1.0, 1.0);
        dw_add(&dw, s1.y, f.x, y0, f.z, 1.0, -1.0, 1.0);
        dw_add(&dw, s1.z, x0, f.y, f.z, -1.0, 1.0, 1.0);
        dw_add(&dw, s1.w, f.x, f.y, f.z, 1.0, 1.0, 1.0);
        acc += dw * level_scale(l);
    }
    for (var a = 0u; a < 3u; a++) {
        let inside = x[a] > 0.0 && x[a] < 1.0;
        d_positions[3u * i + a] = select(0.0, acc[a] * P.inv_extent[a], inside);
    }
}

// s_k = Σ_j g_j · table[o + j], j in order from 0.
fn corner_dot(o: u32, g: Grad) -> f32 {
    var sk = 0.0;
    sk += g.g0.x * table_f32[o];
    if (FEATS > 1u) {
        sk += g.g0.y * table_f32[o + 1u];
    }
    if (FEATS > 2u) {
        sk += g.g0.z * table_f32[o + 2u];
        sk += g.g0.w * table_f32[o + 3u];
    }
    if (FEATS > 4u) {
        sk += g.g1.x * table_f32[o + 4u];
        sk += g.g1.y * table_f32[o + 5u];
        sk += g.g1.z * table_f32[o + 6u];
        sk += g.g1.w * table_f32[o + 7u];
    }
    return sk;
}

// Corner k's terms of ∂(Σ_k s_k w_k)/∂frac: its weight's factors (ax, ay, az) with one of them
// replaced by its derivative (sx, sy, sz = ±1), multiplied in the CPU's order.
fn dw_add(dw: ptr<function, vec3<f32>>, s: f32, ax: f32, ay: f32, az: f32, sx: f32, sy: f32, sz: f32) {
    (*dw).x += s * sx * ay * az;
    (*dw).y += s * ax * sy * az;
    (*dw).z += s * ax * ay * sz;
}

//#begin f32-atomics
@group(0) @binding(7) var<storage, read_write> grads_f32: array<atomic<f32>>;

@compute @workgroup_size(WG)
fn hash_backward_atomic(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let l = gid.z;
    if (i >= n_samples(arrayLength(&d_features), P.n_levels * FEATS) || l >= P.n_levels) {
        return;
    }
    add_sample_atomic(i, l, P.levels[l]);
}

// Sample i's gradient at level l, one atomic add per corner and feature (none for zeros).
fn add_sample_atomic(i: u32, l: u32, lv: vec4<u32>) {
    let g = load_grad(i, l);
    if (!g.any) {
        return;
    }
    let c = cell(unit_position(i), lv, l);
    add_corner_atomic(lv.y + c.s0.x * FEATS, c.w0.x, g);
    add_corner_atomic(lv.y + c.s0.y * FEATS, c.w0.y, g);
    add_corner_atomic(lv.y + c.s0.z * FEATS, c.w0.z, g);
    add_corner_atomic(lv.y + c.s0.w * FEATS, c.w0.w, g);
    add_corner_atomic(lv.y + c.s1.x * FEATS, c.w1.x, g);
    add_corner_atomic(lv.y + c.s1.y * FEATS, c.w1.y, g);
    add_corner_atomic(lv.y + c.s1.z * FEATS, c.w1.z, g);
    add_corner_atomic(lv.y + c.s1.w * FEATS, c.w1.w, g);
}

fn add_atomic_nonzero(idx: u32, d: f32) {
    if (d != 0.0) {
        atomicAdd(&grads_f32[idx], d);
    }
}

// w·g added to the F features at `o` (none for zeros).
fn add_corner_atomic(o: u32, w: f32, g: Grad) {
    add_atomic_nonzero(o, w * g.g0.x);
    if (FEATS > 1u) {
        add_atomic_nonzero(o + 1u, w * g.g0.y);
    }
    if (FEATS > 2u) {
        add_atomic_nonzero(o + 2u, w * g.g0.z);
        add_atomic_nonzero(o + 3u, w * g.g0.w);
    }
    if (FEATS > 4u) {
        add_atomic_nonzero(o + 4u, w * g.g1.x);
        add_atomic_nonzero(o + 5u, w * g.g1.y);
        add_atomic_nonzero(o + 6u, w * g.g1.z);
        add_atomic_nonzero(o + 7u, w * g.g1.w);
    }
}

//#begin subgroups
// hash_backward_atomic with the additions of a dense level summed over the subgroup first. Dense
// levels are the coarse ones, where the consecutive samples of a subgroup (a stretch of one or two
// rays) share cells, so every lane adding to the same few slots is what makes their atomics
// contend. Per corner, up to SG_ROUNDS rounds: the subgroup's smallest pending slot, the sum of the
// lanes on it (subgroupAdd), one atomic add by the first of those lanes; a slot held by one lane
// alone ends the rounds, and the lanes still pending then add their own. Hashed levels (scattered
// slots) run hash_backward_atomic's code.
// The same terms are added, in another order (as between any two runs of the atomics).
const SG_ROUNDS: u32 = 4u;

@compute @workgroup_size(WG)
fn hash_backward_subgroup(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(subgroup_invocation_id) sid: u32,
) {
    let i = linear_id(gid, nwg, WG);
    let l = gid.z;
    if (l >= P.n_levels) {
        return;
    }
    let lv = P.levels[l];
    let live = i < n_samples(arrayLength(&d_features), P.n_levels * FEATS);
    if (lv.z == 0u) {
        if (live) {
            add_sample_atomic(i, l, lv);
        }
        return;
    }
    // Every lane takes part in the subgroup operations (uniform control flow): a lane past the
    // count, or without gradient, with nothing pending.
    var g: Grad;
    var c: Cell;
    if (live) {
        g = load_grad(i, l);
        if (g.any) {
            c = cell(unit_position(i), lv, l);
        }
    }
    let has_grad = live && g.any;
    for (var k = 0u; k < 8u; k++) {
        let slot = corner_slot(c, k);
        let wk = corner_weight(c, k);
        var pending = has_grad;
        for (var r = 0u; r < SG_ROUNDS; r++) {
            let lead = subgroupMin(select(0xffffffffu, slot, pending));
            if (lead == 0xffffffffu) {
                break;
            }
            let mine = pending && slot == lead;
            let writer = subgroupMin(select(0xffffffffu, sid, mine));
            // A slot that no other lane shares: the lanes add their own from here on (scattered
            // samples would otherwise pay every round for nothing).
            if (subgroupAdd(select(0u, 1u, mine)) == 1u) {
                break;
            }
            for (var j = 0u; j < FEATS; j++) {
                let s = subgroupAdd(select(0.0, wk * grad_at(g, j), mine));
                if (sid == writer && s != 0.0) {
                    atomicAdd(&grads_f32[lv.y + lead * FEATS + j], s);
                }
            }
            pending = pending && !mine;
        }
        if (pending) {
            add_corner_atomic(lv.y + slot * FEATS, wk, g);
        }
    }
}
//#end subgroups
//#end f32-atomics

//#begin f16-mirror
// An f16 mirror of the table (HashGridConfig::storage = "f16", F = 2 only; the host strips this
// section for other F): one u32 per slot holding its two features as pack2x16float, written from
// the f32 master by hash_mirror_f16 (round to nearest; CPU twin: HashGrid::sync_storage) and read
// by hash_forward_f16, which is hash_forward with half the bytes per lookup. The backward and the
// optimiser use the f32 master.
@group(0) @binding(8) var<storage, read> table16: array<u32>;
@group(0) @binding(9) var<storage, read_write> mirror: array<u32>;

@compute @workgroup_size(WG)
fn hash_mirror_f16(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= arrayLength(&mirror)) {
        return;
    }
    mirror[i] = pack2x16float(vec2<f32>(table[i]));
}

@compute @workgroup_size(WG)
fn hash_forward_f16(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let l = gid.z;
    let nl = P.n_levels;
    if (i >= n_samples(arrayLength(&features), nl) || l >= nl) {
        return;
    }
    let lv = P.levels[l];
    let c = cell(unit_position(i), lv, l);
    let base = lv.y / 2u;
    let t0 = unpack2x16float(table16[base + c.s0.x]);
    let t1 = unpack2x16float(table16[base + c.s0.y]);
    let t2 = unpack2x16float(table16[base + c.s0.z]);
    let t3 = unpack2x16float(table16[base + c.s0.w]);
    let t4 = unpack2x16float(table16[base + c.s1.x]);
    let t5 = unpack2x16float(table16[base + c.s1.y]);
    let t6 = unpack2x16float(table16[base + c.s1.z]);
    let t7 = unpack2x16float(table16[base + c.s1.w]);
    var acc = vec2<f32>(0.0);
    acc += c.w0.x * t0;
    acc += c.w0.y * t1;
    acc += c.w0.z * t2;
    acc += c.w0.w * t3;
    acc += c.w1.x * t4;
    acc += c.w1.y * t5;
    acc += c.w1.z * t6;
    acc += c.w1.w * t7;
    features[i * nl + l] = Feat(acc);
}
//#end f16-mirror
