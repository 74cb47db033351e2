// Occupancy-grid ray marching into the packed (CSR) sample layout, one invocation per ray.
// CPU twin: nerf_sampling::march (crates/sampling/src/occupancy.rs); host side:
// nerf_gpu::sampling::GpuMarcher, which records
//   march_coarse  (one bit per 4³ block of cells: any cell occupied; after clearing `coarse`)
//   march_count   (samples per ray → counts[r], r < n_rays = min(counters[0], cap_rays))
//   GpuScan       (exclusive scan of counts → raw offsets, raw[cap_rays] = total)
//   march_fill    (offsets = min(raw, cap_samples); counters[1] = min(total, cap_samples);
//                  samples written at their offsets).
//
// Sampling rule (the CPU's): [near, far] clipped to the box (slab test) gives [t0, t1); sample k
// sits at t_k = t0 + (k + u)·step, t_k < t1, and is emitted when the cell holding o + t_k·d is
// occupied (cell index x + res·(y + res·z), grid coordinates clamped to [0, res−1]), at most
// max_samples per ray; u = rand_f32(seed, 0x4d415243, r) with jitter, else 0.5.
// The walk is a dense walk that skips steps proven empty: from a step in an empty cell (or in an
// empty 4³ block) it jumps to the first step at or past the time the ray leaves that cell (block)
// minus a margin (10⁻² cell, far above rounding), so every skipped step lies in the empty region
// and the emitted samples are exactly the dense walk's.
//
// Layouts: bits = u32 words, bit i of word i/32 = cell i; origins/dirs [R][3]; outputs:
// offsets [cap_rays + 1], positions [S][3], dirs [S][3], t [S], dt [S] (= step, as the CPU).

const WG: u32 = 64u;
const CBLOCK: u32 = 4u;
const BIG: f32 = 3.0e38;

struct MarchParams {
    aabb_min: vec3<f32>,
    step: f32,
    aabb_max: vec3<f32>,
    near: f32,
    cell: vec3<f32>,
    far: f32,
    inv_cell: vec3<f32>,
    margin: f32,
    res: u32,
    cres: u32,
    max_samples: u32,
    cap_rays: u32,
    cap_samples: u32,
    seed: u32,
    jitter: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> P: MarchParams;
@group(0) @binding(1) var<storage, read_write> counters: array<u32>;
@group(0) @binding(2) var<storage, read> bits: array<u32>;
@group(0) @binding(3) var<storage, read> coarse: array<u32>;
@group(0) @binding(4) var<storage, read> origins: array<f32>;
@group(0) @binding(5) var<storage, read> dirs: array<f32>;
@group(0) @binding(6) var<storage, read_write> counts: array<u32>;
@group(0) @binding(7) var<storage, read> raw_offsets: array<u32>;
@group(0) @binding(8) var<storage, read_write> out_offsets: array<u32>;
@group(0) @binding(9) var<storage, read_write> out_positions: array<f32>;
@group(0) @binding(10) var<storage, read_write> out_dirs: array<f32>;
@group(0) @binding(11) var<storage, read_write> out_t: array<f32>;
@group(0) @binding(12) var<storage, read_write> out_dt: array<f32>;
@group(0) @binding(13) var<storage, read_write> coarse_build: array<atomic<u32>>;

fn occupied(idx: u32) -> bool {
    return ((bits[idx >> 5u] >> (idx & 31u)) & 1u) != 0u;
}

fn block_empty(b: vec3<u32>) -> bool {
    let i = b.x + P.cres * (b.y + P.cres * b.z);
    return ((coarse[i >> 5u] >> (i & 31u)) & 1u) == 0u;
}

struct RaySetup {
    o: vec3<f32>,
    d: vec3<f32>,
    t0: f32,
    t1: f32,
    u: f32,
    ok: bool,
}

fn setup(r: u32) -> RaySetup {
    var s: RaySetup;
    s.o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    s.d = vec3<f32>(dirs[3u * r], dirs[3u * r + 1u], dirs[3u * r + 2u]);
    var a0 = -BIG;
    var a1 = BIG;
    var hit = true;
    for (var a = 0u; a < 3u; a = a + 1u) {
        let o = s.o[a];
        let d = s.d[a];
        if (d == 0.0) {
            if (!(o >= P.aabb_min[a] && o <= P.aabb_max[a])) {
                hit = false;
            }
        } else {
            let inv = 1.0 / d;
            let x = (P.aabb_min[a] - o) * inv;
            let y = (P.aabb_max[a] - o) * inv;
            a0 = max(a0, min(x, y));
            a1 = min(a1, max(x, y));
        }
    }
    s.t0 = max(P.near, a0);
    s.t1 = min(P.far, a1);
    s.u = 0.5;
    if (P.jitter != 0u) {
        s.u = rand_f32(P.seed, 0x4d415243u, r);
    }
    s.ok = hit && P.far > P.near && s.t1 > s.t0 && abs(s.t0) < 1.0e38 && abs(s.t1) < 1.0e38;
    return s;
}

fn t_at(s: RaySetup, k: u32) -> f32 {
    return s.t0 + (f32(k) + s.u) * P.step;
}

// Marches one ray; writes samples base.. when `write`; returns the number of samples (≤ max_n).
fn march_ray(s: RaySetup, max_n: u32, base: u32, write: bool) -> u32 {
    if (max_n == 0u) {
        return 0u;
    }
    let fres = f32(P.res);
    let hi_cell = vec3<f32>(fres - 1.0);
    // Per axis: face-crossing time = face·fa + fb, safety margin in t (0 where d = 0).
    var fa = vec3<f32>(0.0);
    var fb = vec3<f32>(BIG);
    var mt = vec3<f32>(0.0);
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (s.d[a] != 0.0) {
            let inv = 1.0 / s.d[a];
            fa[a] = P.cell[a] * inv;
            fb[a] = (P.aabb_min[a] - s.o[a]) * inv;
            mt[a] = P.margin * abs(inv);
        }
    }
    var k = 0u;
    var count = 0u;
    var t = t_at(s, 0u);
    loop {
        if (t >= s.t1 || count >= max_n) {
            break;
        }
        let p = s.o + t * s.d;
        let g = clamp((p - P.aabb_min) * P.inv_cell, vec3<f32>(0.0), hi_cell);
        let c = vec3<u32>(g);
        let idx = c.x + P.res * (c.y + P.res * c.z);
        if (occupied(idx)) {
            if (write) {
                let j = base + count;
                out_t[j] = t;
                out_dt[j] = P.step;
                for (var a = 0u; a < 3u; a = a + 1u) {
                    out_positions[3u * j + a] = p[a];
                    out_dirs[3u * j + a] = s.d[a];
                }
            }
            count = count + 1u;
            k = k + 1u;
            t = t_at(s, k);
            continue;
        }
        // An empty cell: the region to skip is its 4³ block when that is empty, else the cell.
        let b = c / CBLOCK;
        var lo = vec3<f32>(c);
        var hi = lo + vec3<f32>(1.0);
        if (block_empty(b)) {
            lo = vec3<f32>(b * CBLOCK);
            hi = min(lo + vec3<f32>(f32(CBLOCK)), vec3<f32>(fres));
        }
        var ts = s.t1;
        for (var a = 0u; a < 3u; a = a + 1u) {
            if (s.d[a] != 0.0) {
                let face = select(lo[a], hi[a], s.d[a] > 0.0);
                ts = min(ts, face * fa[a] + fb[a] - mt[a]);
            }
        }
        // First step k' > k with t_k' ≥ ts: all steps in between lie in the empty region.
        var kn = k + 1u;
        if (t_at(s, kn) < ts) {
            let est = (ts - s.t0) / P.step - s.u;
            kn = max(kn, u32(max(est, 0.0)));
            loop {
                if (kn <= k + 1u || t_at(s, kn - 1u) < ts) {
                    break;
                }
                kn = kn - 1u;
            }
            loop {
                if (t_at(s, kn) >= ts) {
                    break;
                }
                kn = kn + 1u;
            }
        }
        k = kn;
        t = t_at(s, k);
    }
    return count;
}

// One invocation per 4³ block: sets its bit when any of its cells is occupied.
@compute @workgroup_size(WG)
fn march_coarse(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let b = linear_id(gid, nwg, WG);
    let cr = P.cres;
    if (b >= cr * cr * cr) {
        return;
    }
    let b0 = vec3<u32>(b % cr, (b / cr) % cr, b / (cr * cr)) * CBLOCK;
    let b1 = min(b0 + vec3<u32>(CBLOCK), vec3<u32>(P.res));
    var any = false;
    for (var z = b0.z; z < b1.z; z = z + 1u) {
        for (var y = b0.y; y < b1.y; y = y + 1u) {
            for (var x = b0.x; x < b1.x; x = x + 1u) {
                if (occupied(x + P.res * (y + P.res * z))) {
                    any = true;
                }
            }
        }
    }
    if (any) {
        atomicOr(&coarse_build[b >> 5u], 1u << (b & 31u));
    }
}

// Pass 1: samples per ray.
@compute @workgroup_size(WG)
fn march_count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r >= min(counters[0], P.cap_rays)) {
        return;
    }
    let s = setup(r);
    var n = 0u;
    if (s.ok) {
        n = march_ray(s, P.max_samples, 0u, false);
    }
    counts[r] = n;
}

// Pass 3 (after the scan): clamped offsets, the sample count, and the samples. Launched for
// cap_rays + 1 invocations.
@compute @workgroup_size(WG)
fn march_fill(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r > P.cap_rays) {
        return;
    }
    let start = min(raw_offsets[r], P.cap_samples);
    out_offsets[r] = start;
    if (r == 0u) {
        counters[1] = min(raw_offsets[P.cap_rays], P.cap_samples);
    }
    if (r >= min(counters[0], P.cap_rays)) {
        return;
    }
    let end = min(raw_offsets[r + 1u], P.cap_samples);
    if (end <= start) {
        return;
    }
    let s = setup(r);
    march_ray(s, min(P.max_samples, end - start), start, true);
}
