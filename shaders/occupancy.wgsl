// Occupancy-grid update on the device (GpuOccupancyGrid in crates/gpu/src/occupancy.rs; CPU twin:
// nerf_sampling::OccupancyGrid::update / recompute). Layouts:
//   density  [n] f32, n = levels·res³, cell idx = level·res³ + x + res·(y + res·z) (level 0 the
//            finest of the cascade; one level: the box), +∞ = never sampled;
//   bits     [⌈n/32⌉] u32, bit (i mod 32) of word i/32 = cell i occupied;
//   tmp      [n] u32: max of this update's new σ per cell, encoded bitcast<u32>(σ)+1 (σ ≥ 0 finite,
//            so the u32 order is the float order and atomicMax needs no float atomics), 0 = not chosen;
//   occupied [n] u32: the indices of the occupied cells, ascending (deterministic compaction);
//   stats    [4] u32: 0 = n_occupied, 1 = m (cells chosen by the last `choose`), 2 = bits of the
//            threshold, 3 = bits of the mean σ·step_size;
//   partials [⌈n/WG⌉] f32 per-workgroup density sums; block_counts / block_offsets [⌈n_words/WG⌉] u32.
// Stages (one update per submission):
//   choose:      m = n (warm-up: every cell in order) or ⌊n/4⌋ uniform + ⌊n_occ/4⌋ occupied cells
//                (with replacement, u = rand_u32 % count: modulo bias < count/2³² ≈ 5e-4 at 128³);
//                one jittered point per chosen cell (jitter rand_f32(seed, 2+axis, j), clamped to
//                the cell of its level as the CPU) → positions [m][3], cells [m]; counters_out[1] = m.
//   (the caller evaluates σ at the positions)
//   scatter_max: tmp[cell] = max(tmp[cell], enc(sanitise(σ))) (NaN/negative → 0, +∞ → f32 max),
//                except for cells no training camera sees (seen [⌈n/32⌉] u32 bits; all set unless
//                marked), which are never refreshed (their density stays 0).
//   ema:         chosen cells: d = finite(d) ? max(decay·d, t) : t; tmp reset; workgroup sums of d
//                over the finest level's cells (the others add 0).
//   reduce:      one workgroup: Kahan sum of the partials → mean = (Σ/mean_cells)·step_size,
//                thr = min(threshold, mean) (an infinite mean gives threshold, as on the CPU).
//   bits:        one invocation per 32-cell word: bit = d·step_size > thr; workgroup popcounts.
//   scan_blocks: one workgroup: exclusive scan of the block counts → block offsets, n_occupied.
//   compact:     writes the occupied cell indices (word-level workgroup scan + block offset).

struct OccParams {
    aabb_min_x: f32,
    aabb_min_y: f32,
    aabb_min_z: f32,
    res: u32,
    cell_x: f32,
    cell_y: f32,
    cell_z: f32,
    n_cells: u32,
    decay: f32,
    threshold: f32,
    n_words: u32,
    n_blocks: u32,      // ⌈n_words / WG⌉
    n_partials: u32,    // ⌈n_cells / WG⌉
    seed: u32,          // per update (written by record_choose)
    warm: u32,          // per update (written by record_choose): 1 = choose every cell
    step_size: f32,     // per update (written by record_apply)
    level_cells: u32,   // res³
    mean_cells: u32,    // the mean's divisor: level 0's cells a camera sees (all unless marked)
    _p1: u32,
    _p2: u32,
    lv_lo: array<vec4<f32>, 8>,    // per level: the box's lower corner
    lv_cell: array<vec4<f32>, 8>,  // per level: the cell size
}

override WG: u32 = 256u;
const F32_MAX: f32 = 3.40282347e38;

@group(0) @binding(0) var<uniform> prm: OccParams;
@group(0) @binding(1) var<storage, read_write> density: array<f32>;
@group(0) @binding(2) var<storage, read_write> bits: array<u32>;
@group(0) @binding(3) var<storage, read_write> tmp: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> occupied: array<u32>;
@group(0) @binding(5) var<storage, read_write> stats: array<u32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;
@group(0) @binding(7) var<storage, read_write> blocks: array<u32>;
@group(0) @binding(8) var<storage, read_write> positions: array<f32>;
@group(0) @binding(9) var<storage, read_write> cells: array<u32>;
@group(0) @binding(10) var<storage, read_write> counters_out: array<u32>;
@group(0) @binding(11) var<storage, read> sigma: array<f32>;
@group(0) @binding(12) var<storage, read> seen: array<u32>;

var<workgroup> wg_f: array<f32, WG>;
var<workgroup> wg_u: array<u32, WG>;

fn chosen_count() -> u32 {
    if (prm.warm != 0u) {
        return prm.n_cells;
    }
    return prm.n_cells / 4u + stats[0] / 4u;
}

@compute @workgroup_size(WG)
fn choose(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let j = linear_id(gid, nwg, WG);
    let m = chosen_count();
    if (j == 0u) {
        counters_out[1] = m;
        stats[1] = m;
    }
    if (j >= m) {
        return;
    }
    var idx = j;
    if (prm.warm == 0u) {
        let n_uniform = prm.n_cells / 4u;
        if (j < n_uniform) {
            idx = rand_u32(prm.seed, 0u, j) % prm.n_cells;
        } else {
            idx = occupied[rand_u32(prm.seed, 1u, j) % stats[0]];
        }
    }
    cells[j] = idx;
    let r = prm.res;
    let lv = idx / prm.level_cells;
    let li = idx % prm.level_cells;
    let ijk = vec3<f32>(f32(li % r), f32((li / r) % r), f32(li / (r * r)));
    let mn = prm.lv_lo[lv].xyz;
    let h = prm.lv_cell[lv].xyz;
    let jit = vec3<f32>(rand_f32(prm.seed, 2u, j), rand_f32(prm.seed, 3u, j), rand_f32(prm.seed, 4u, j));
    let lo = mn + ijk * h;
    let hi = mn + (ijk + 1.0) * h;
    let p = clamp(lo + jit * h, lo, hi);
    positions[3u * j] = p.x;
    positions[3u * j + 1u] = p.y;
    positions[3u * j + 2u] = p.z;
}

@compute @workgroup_size(WG)
fn scatter_max(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let j = linear_id(gid, nwg, WG);
    if (j >= stats[1]) {
        return;
    }
    let c = cells[j];
    if (((seen[c >> 5u] >> (c & 31u)) & 1u) == 0u) {
        return;
    }
    let s0 = sigma[j];
    var s = 0.0;
    if (s0 > 0.0) {
        s = min(s0, F32_MAX);
    }
    atomicMax(&tmp[c], bitcast<u32>(s) + 1u);
}

@compute @workgroup_size(WG)
fn ema(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
       @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let c = linear_id(gid, nwg, WG);
    var d = 0.0;
    if (c < prm.n_cells) {
        d = density[c];
        let code = atomicLoad(&tmp[c]);
        if (code != 0u) {
            let t = bitcast<f32>(code - 1u);
            if (d <= F32_MAX) {
                d = max(d * prm.decay, t);
            } else {
                d = t;
            }
            density[c] = d;
            atomicStore(&tmp[c], 0u);
        }
    }
    if (c >= prm.level_cells) {
        d = 0.0;
    }
    wg_f[lid] = d;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (lid < s) {
            wg_f[lid] = wg_f[lid] + wg_f[lid + s];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        partials[wid.x + wid.y * nwg.x] = wg_f[0];
    }
}

@compute @workgroup_size(WG)
fn reduce(@builtin(local_invocation_index) lid: u32) {
    // Each invocation: Kahan sum over a strided subset of the partials; then a tree over the
    // invocations (sum and compensation separately).
    var s = 0.0;
    var comp = 0.0;
    for (var i = lid; i < prm.n_partials; i += WG) {
        let y = partials[i] - comp;
        let t = s + y;
        comp = (t - s) - y;
        s = t;
    }
    wg_f[lid] = s;
    workgroupBarrier();
    for (var k = WG / 2u; k > 0u; k = k / 2u) {
        if (lid < k) {
            wg_f[lid] = wg_f[lid] + wg_f[lid + k];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        let mean = (wg_f[0] / f32(prm.mean_cells)) * prm.step_size;
        stats[2] = bitcast<u32>(min(prm.threshold, mean));
        stats[3] = bitcast<u32>(mean);
    }
}

@compute @workgroup_size(WG)
fn build_bits(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let w = linear_id(gid, nwg, WG);
    var count = 0u;
    if (w < prm.n_words) {
        let thr = bitcast<f32>(stats[2]);
        let lo = 32u * w;
        let hi = min(lo + 32u, prm.n_cells);
        var word = 0u;
        for (var c = lo; c < hi; c++) {
            if (density[c] * prm.step_size > thr) {
                word |= 1u << (c - lo);
            }
        }
        bits[w] = word;
        count = countOneBits(word);
    }
    wg_u[lid] = count;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (lid < s) {
            wg_u[lid] = wg_u[lid] + wg_u[lid + s];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        blocks[wid.x + wid.y * nwg.x] = wg_u[0];
    }
}

// Inclusive Hillis–Steele scan of wg_u (all invocations must call it).
fn wg_inclusive_scan(lid: u32) {
    for (var s = 1u; s < WG; s = s * 2u) {
        workgroupBarrier();
        var add = 0u;
        if (lid >= s) {
            add = wg_u[lid - s];
        }
        workgroupBarrier();
        wg_u[lid] = wg_u[lid] + add;
    }
    workgroupBarrier();
}

@compute @workgroup_size(WG)
fn scan_blocks(@builtin(local_invocation_index) lid: u32) {
    var carry = 0u;
    let n = prm.n_blocks;
    for (var base = 0u; base < n; base += WG) {
        let i = base + lid;
        var v = 0u;
        if (i < n) {
            v = blocks[i];
        }
        workgroupBarrier();
        wg_u[lid] = v;
        wg_inclusive_scan(lid);
        if (i < n) {
            blocks[i] = carry + wg_u[lid] - v;
        }
        carry += wg_u[WG - 1u];
    }
    if (lid == 0u) {
        stats[0] = carry;
    }
}

@compute @workgroup_size(WG)
fn compact(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let w = linear_id(gid, nwg, WG);
    var word = 0u;
    if (w < prm.n_words) {
        word = bits[w];
    }
    let count = countOneBits(word);
    wg_u[lid] = count;
    wg_inclusive_scan(lid);
    var pos = blocks[wid.x + wid.y * nwg.x] + wg_u[lid] - count;
    while (word != 0u) {
        let b = firstTrailingBit(word);
        occupied[pos] = 32u * w + b;
        pos += 1u;
        word &= word - 1u;
    }
}
