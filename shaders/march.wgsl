// Occupancy-grid ray marching into the packed (CSR) sample layout, one invocation per ray.
// CPU twin: nerf_sampling::march (crates/sampling/src/occupancy.rs); host side:
// nerf_gpu::sampling::GpuMarcher, which records
//   march_coarse  (one bit per 4³ block of cells: any cell occupied; after clearing `coarse`)
//   march_count   (samples per ray → counts[r], r < n_rays = min(counters[0], cap_rays))
//   GpuScan       (exclusive scan of counts → raw offsets, raw[cap_rays] = total)
//   march_fill    (offsets = min(raw, L), L = the largest raw offset ≤ cap_samples: whole rays
//                  only, a ray whose samples would cross the capacity gets none, as do the rays
//                  after it; counters[1] = L; samples written at their offsets).
//
// Sampling rule (the CPU's): [near, far] clipped to the box (slab test), and to the render crop
// box when crop_c.w = 1 (crop_slab; RayMarch::cropped), gives [t0, t1); sample k
// sits at t_k = t0 + (k + u)·step (with a cone, cone > 0: t_k = S⁻¹(S(t0) + (k + u)·step), the
// warp of nerf_sampling::Stepping, and dt = clamp(t·cone, step, 1024·step)), t_k < t1, and is
// emitted when the cell holding o + t_k·d is
// occupied, at most max_samples per ray; u = rand_f32(seed, 0x4d415243, r) with jitter, else 0.5.
// The cell of a point (cell_of, the CPU's OccupancyGrid::cell_of): the finest level of the
// cascade whose box holds it (the outermost for none), then index level·res³ + x + res·(y + res·z),
// grid coordinates clamped to [0, res−1]. One level: the box's grid.
// The walk is a dense walk that skips steps proven empty: from a step in an empty cell (or in an
// empty 4³ block) it jumps to the first step at or past the time the ray leaves that cell (block)
// minus a margin (10⁻² of the level's cell and ≥ 10⁻³ of the outermost one: far above rounding),
// so every skipped step lies in the empty region and the emitted samples are exactly the dense
// walk's. The inner box of a level lies on its blocks' faces (res divisible by 16), so a cell or
// block of the level's own region never reaches into a finer level; a point rounded into the
// inner box's cells (on its face) only takes one step.
//
// Layouts: bits = u32 words, bit i of word i/32 = cell i; origins/dirs [R][3]; outputs:
// offsets [cap_rays + 1], positions [S][3], dirs [S][3], t [S], dt [S] (= step, as the CPU).

const MAX_STEP_RATIO: f32 = 1024.0;

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
    cone: f32,
    n_levels: u32,
    level_cells: u32,       // res³
    _p0: u32,
    _p1: u32,
    lv_lo: array<vec4<f32>, 8>,     // per level (finest first): lower corner, w = margin
    lv_hi: array<vec4<f32>, 8>,     // upper corner
    lv_cell: array<vec4<f32>, 8>,   // cell size
    lv_inv: array<vec4<f32>, 8>,    // res / (hi − lo)
    crop_x: vec4<f32>,              // render crop box (crop_slab): axes (xyz) and half sizes (w)
    crop_y: vec4<f32>,
    crop_z: vec4<f32>,
    crop_c: vec4<f32>,              // centre; w = 1: crop on
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

fn block_empty(m: u32, b: vec3<u32>) -> bool {
    let i = m * P.cres * P.cres * P.cres + b.x + P.cres * (b.y + P.cres * b.z);
    return ((coarse[i >> 5u] >> (i & 31u)) & 1u) == 0u;
}

// The finest level whose box holds p (the outermost when none does).
fn level_of(p: vec3<f32>) -> u32 {
    for (var m = 0u; m + 1u < P.n_levels; m = m + 1u) {
        if (all(p >= P.lv_lo[m].xyz) && all(p <= P.lv_hi[m].xyz)) {
            return m;
        }
    }
    return P.n_levels - 1u;
}

struct RaySetup {
    o: vec3<f32>,
    d: vec3<f32>,
    t0: f32,
    t1: f32,
    u: f32,
    ok: bool,
    s0: f32,            // warp(t0) (cone steps)
    kn: vec4<f32>,      // knots() (cone steps), computed once per ray
}

// The cone steps' knots (nerf_sampling::Stepping::knots): t_a, t_b, S(t_b), ln(1 + cone)/step.
fn knots() -> vec4<f32> {
    let ta = P.step / P.cone;
    let rate = log(1.0 + P.cone) / P.step;
    return vec4<f32>(ta, MAX_STEP_RATIO * ta, ta + log(MAX_STEP_RATIO) / rate, rate);
}

// The warped distance S(t) of cone steps with knots kn (CPU twin: Stepping::warp).
fn warp(kn: vec4<f32>, t: f32) -> f32 {
    if (t <= kn.x) {
        return t;
    } else if (t <= kn.y) {
        return kn.x + log(t / kn.x) / kn.w;
    }
    return kn.z + (t - kn.y) / MAX_STEP_RATIO;
}

// S⁻¹(s) (CPU twin: Stepping::unwarp).
fn unwarp(kn: vec4<f32>, s: f32) -> f32 {
    if (s <= kn.x) {
        return s;
    } else if (s <= kn.z) {
        return kn.x * exp((s - kn.x) * kn.w);
    }
    return kn.y + (s - kn.z) * MAX_STEP_RATIO;
}

// The interval a sample at t stands for (CPU twin: Stepping::dt).
fn step_dt(t: f32) -> f32 {
    if (P.cone > 0.0) {
        return clamp(t * P.cone, P.step, MAX_STEP_RATIO * P.step);
    }
    return P.step;
}

fn setup(r: u32) -> RaySetup {
    var s: RaySetup;
    s.o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    s.d = vec3<f32>(dirs[3u * r], dirs[3u * r + 1u], dirs[3u * r + 2u]);
    let box = slab(s.o, s.d, P.aabb_min, P.aabb_max);
    let hit = box.z != 0.0;
    var hit_crop = true;
    s.t0 = max(P.near, box.x);
    s.t1 = min(P.far, box.y);
    if (P.crop_c.w != 0.0) {
        // The render crop box (CPU twin: RayMarch::cropped).
        let c = crop_slab(s.o, s.d, P.crop_x, P.crop_y, P.crop_z, P.crop_c.xyz);
        hit_crop = c.z != 0.0;
        s.t0 = max(s.t0, c.x);
        s.t1 = min(s.t1, c.y);
    }
    s.u = 0.5;
    if (P.jitter != 0u) {
        s.u = rand_f32(P.seed, 0x4d415243u, r);
    }
    s.ok = hit && hit_crop && P.far > P.near && s.t1 > s.t0 && abs(s.t0) < 1.0e38 && abs(s.t1) < 1.0e38;
    s.s0 = s.t0;
    s.kn = vec4<f32>(0.0);
    if (P.cone > 0.0) {
        s.kn = knots();
        s.s0 = warp(s.kn, s.t0);
    }
    return s;
}

fn t_at(s: RaySetup, k: u32) -> f32 {
    if (P.cone > 0.0) {
        return unwarp(s.kn, s.s0 + (f32(k) + s.u) * P.step);
    }
    return s.t0 + (f32(k) + s.u) * P.step;
}

// Marches one ray; writes samples base.. when `write`; returns the number of samples (≤ max_n).
fn march_ray(s: RaySetup, max_n: u32, base: u32, write: bool) -> u32 {
    return march_from(s, 0u, max_n, base, write).x;
}

// The walk from step k0 (0, or a step returned by an earlier call): returns (samples emitted
// (≤ max_n), the step to resume from). Resuming continues the same dense walk, so rounds of
// march_from emit exactly the samples of one march_ray.
fn march_from(s: RaySetup, k0: u32, max_n: u32, base: u32, write: bool) -> vec2<u32> {
    if (max_n == 0u) {
        return vec2<u32>(0u, k0);
    }
    let fres = f32(P.res);
    let hi_cell = vec3<f32>(fres - 1.0);
    let q = P.res / 4u;
    // 1/d once per ray (components where d = 0 are never used).
    let inv_d = 1.0 / select(s.d, vec3<f32>(1.0), s.d == vec3<f32>(0.0));
    var k = k0;
    var count = 0u;
    var t = t_at(s, k0);
    loop {
        if (t >= s.t1 || count >= max_n) {
            break;
        }
        let p = s.o + t * s.d;
        let m = level_of(p);
        let g = clamp((p - P.lv_lo[m].xyz) * P.lv_inv[m].xyz, vec3<f32>(0.0), hi_cell);
        let c = vec3<u32>(g);
        let idx = m * P.level_cells + c.x + P.res * (c.y + P.res * c.z);
        if (occupied(idx)) {
            if (write) {
                let j = base + count;
                out_t[j] = t;
                out_dt[j] = step_dt(t);
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
        // A point of a coarser level rounded into the cells of its inner box: one step.
        if (m > 0u && all(c >= vec3<u32>(q)) && all(c < vec3<u32>(3u * q))) {
            k = k + 1u;
            t = t_at(s, k);
            continue;
        }
        // An empty cell: the region to skip is its 4³ block when that is empty, else the cell.
        let b = c / CBLOCK;
        var lo = vec3<f32>(c);
        var hi = lo + vec3<f32>(1.0);
        if (block_empty(m, b)) {
            lo = vec3<f32>(b * CBLOCK);
            hi = min(lo + vec3<f32>(f32(CBLOCK)), vec3<f32>(fres));
        }
        // Face-crossing time of the level's grid face f on axis a: f·fa + fb, minus the margin.
        var ts = s.t1;
        for (var a = 0u; a < 3u; a = a + 1u) {
            if (s.d[a] != 0.0) {
                let inv = inv_d[a];
                let fa = P.lv_cell[m][a] * inv;
                let fb = (P.lv_lo[m][a] - s.o[a]) * inv;
                let face = select(lo[a], hi[a], s.d[a] > 0.0);
                ts = min(ts, face * fa + fb - P.lv_lo[m].w * abs(inv));
            }
        }
        // First step k' > k with t_k' ≥ ts: all steps in between lie in the empty region.
        var kn = k + 1u;
        if (t_at(s, kn) < ts) {
            var est = (ts - s.t0) / P.step - s.u;
            if (P.cone > 0.0) {
                est = (warp(s.kn, ts) - s.s0) / P.step - s.u;
            }
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
    return vec2<u32>(count, k);
}

// One invocation per 4³ block of each level: sets its bit when any of its cells is occupied.
@compute @workgroup_size(WG)
fn march_coarse(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let gb = linear_id(gid, nwg, WG);
    let cr = P.cres;
    if (gb >= P.n_levels * cr * cr * cr) {
        return;
    }
    let m = gb / (cr * cr * cr);
    let b = gb % (cr * cr * cr);
    let base = m * P.level_cells;
    let b0 = vec3<u32>(b % cr, (b / cr) % cr, b / (cr * cr)) * CBLOCK;
    let b1 = min(b0 + vec3<u32>(CBLOCK), vec3<u32>(P.res));
    var any = false;
    for (var z = b0.z; z < b1.z; z = z + 1u) {
        for (var y = b0.y; y < b1.y; y = y + 1u) {
            for (var x = b0.x; x < b1.x; x = x + 1u) {
                if (occupied(base + x + P.res * (y + P.res * z))) {
                    any = true;
                }
            }
        }
    }
    if (any) {
        atomicOr(&coarse_build[gb >> 5u], 1u << (gb & 31u));
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

// The end of the whole rays that fit the sample capacity: the largest raw offset ≤ cap_samples
// (the raw offsets do not decrease and raw_offsets[0] = 0), by bisection over the cap_rays + 1
// offsets (~17 reads, cached, per invocation). Training keeps whole rays only: a ray cut short
// would be trained to show its whole pixel in the part of it that was marched.
fn whole_rays_end() -> u32 {
    if (raw_offsets[P.cap_rays] <= P.cap_samples) {
        return raw_offsets[P.cap_rays];
    }
    var lo = 0u;          // raw_offsets[lo] ≤ cap_samples
    var hi = P.cap_rays;  // raw_offsets[hi] > cap_samples
    loop {
        if (hi - lo <= 1u) {
            break;
        }
        let mid = lo + (hi - lo) / 2u;
        if (raw_offsets[mid] <= P.cap_samples) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return raw_offsets[lo];
}

// Pass 3 (after the scan): clamped offsets, the sample count, and the samples. Launched for
// cap_rays + 1 invocations.
@compute @workgroup_size(WG)
fn march_fill(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r > P.cap_rays) {
        return;
    }
    let limit = whole_rays_end();
    let start = min(raw_offsets[r], limit);
    out_offsets[r] = start;
    if (r == 0u) {
        counters[1] = limit;
    }
    if (r >= min(counters[0], P.cap_rays)) {
        return;
    }
    let end = min(raw_offsets[r + 1u], limit);
    if (end <= start) {
        return;
    }
    let s = setup(r);
    march_ray(s, min(P.max_samples, end - start), start, true);
}

// ---- rendering in rounds ---------------------------------------------------------------------
// Host side: nerf_gpu::sampling::{GpuMarcher::record_round*, RoundFrame}. CPU twin: march_ray
// (nerf_sampling::march) followed by the compositing of composite.wgsl with early termination
// (nerf_render::composite_forward): the rounds emit exactly march_ray's samples, in order, and
// composite them with the same arithmetic, so the image is the same; the saving is that a ray
// leaves the alive list (and stops being marched and evaluated) once its transmittance falls
// below the threshold, instead of having every marched sample evaluated.
//
// State per frame ray r: rstate[r] (k to resume the walk from, samples emitted, done flag; rgb
// and transmittance; opacity and depth). Alive list `alive` (ray ids) of rc[0] rays. A round:
//   round_begin     w = min(rc[0], cap_window) rays of the list form the window; K =
//                   clamp(cap_samples / w, 1, kmax) steps each (so w·K ≤ cap_samples); rc[1] = w,
//                   rc[2] = K; counters[0] = w (the stage's ray count).
//   round_count     samples each window ray emits next (≤ K, ≤ max_samples − emitted) → counts;
//   GpuScan         counts → raw_offsets, total → counters[1] (the field's sample count);
//   round_fill      the samples (positions, dirs, t, dt) at their offsets; k, emitted, done.
//   (the field's inference on counters[1] samples → sigma, rgb)
//   round_composite accumulates each window ray's samples into its state (stops at the
//                   threshold); rays still alive are appended to `next` after the tail;
//   round_tail      next[j] = alive[w + j] for the rays past the window (they go first);
//   round_end       rc[0] = (rc[0] − w) + appended; rc[4] += counters[1] (samples evaluated).
// Window rays are alive on entry; a ray dies when it is done marching or its transmittance fell
// below the threshold. round_output writes the frame's rgb (+ (1 − opacity)·background), opacity
// and depth from the state.

struct RoundParams {
    n_frame: u32,       // rays of the frame
    cap_window: u32,    // most rays per round (counts/raw_offsets sizes)
    kmax: u32,          // most steps per ray and round
    has_background: u32,
    t_threshold: f32,   // transmittance below which a ray stops (0: never)
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

struct RayState {
    k: u32,
    emitted: u32,
    done: u32,
    _pad: u32,
    acc: vec4<f32>,     // rgb, transmittance
    od: vec4<f32>,      // opacity, depth
}

@group(0) @binding(14) var<uniform> R: RoundParams;
@group(0) @binding(15) var<storage, read_write> rc: array<atomic<u32>>;   // [n_alive, w, K, appended, evaluated]
@group(0) @binding(16) var<storage, read_write> rstate: array<RayState>;
@group(0) @binding(17) var<storage, read> alive: array<u32>;
@group(0) @binding(18) var<storage, read_write> next: array<u32>;
@group(0) @binding(19) var<storage, read> f_sigma: array<f32>;
@group(0) @binding(20) var<storage, read> f_rgb: array<f32>;
@group(0) @binding(21) var<storage, read> r_background: array<f32>;
@group(0) @binding(22) var<storage, read_write> r_rgb: array<f32>;
@group(0) @binding(23) var<storage, read_write> r_opacity: array<f32>;
@group(0) @binding(24) var<storage, read_write> r_depth: array<f32>;
@group(0) @binding(25) var<storage, read_write> r_alive0: array<u32>;

// Every frame ray alive, fresh state; rc = [n_frame, 0, 0, 0, 0].
@compute @workgroup_size(WG)
fn round_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r == 0u) {
        atomicStore(&rc[0], R.n_frame);
        atomicStore(&rc[1], 0u);
        atomicStore(&rc[2], 0u);
        atomicStore(&rc[3], 0u);
        atomicStore(&rc[4], 0u);
    }
    if (r >= R.n_frame) {
        return;
    }
    var st: RayState;
    st.k = 0u;
    st.emitted = 0u;
    st.done = 0u;
    st.acc = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    st.od = vec4<f32>(0.0);
    rstate[r] = st;
    r_alive0[r] = r;
}

@compute @workgroup_size(1)
fn round_begin() {
    let n_alive = atomicLoad(&rc[0]);
    let w = min(n_alive, R.cap_window);
    let kk = clamp(P.cap_samples / max(w, 1u), 1u, R.kmax);
    atomicStore(&rc[1], w);
    atomicStore(&rc[2], kk);
    atomicStore(&rc[3], 0u);
    counters[0] = w;
}

// Steps ray r may take this round.
fn round_budget(r: u32) -> u32 {
    let e = rstate[r].emitted;
    return min(atomicLoad(&rc[2]), P.max_samples - min(e, P.max_samples));
}

@compute @workgroup_size(WG)
fn round_count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= atomicLoad(&rc[1])) {
        return;
    }
    let r = alive[i];
    let s = setup(r);
    var n = 0u;
    if (s.ok) {
        n = march_from(s, rstate[r].k, round_budget(r), 0u, false).x;
    }
    counts[i] = n;
}

@compute @workgroup_size(WG)
fn round_fill(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= atomicLoad(&rc[1])) {
        return;
    }
    let r = alive[i];
    let s = setup(r);
    var st = rstate[r];
    if (!s.ok) {
        st.done = 1u;
    } else {
        let start = raw_offsets[i];
        let budget = round_budget(r);
        let got = march_from(s, st.k, budget, start, true);
        st.k = got.y;
        st.emitted = st.emitted + got.x;
        if (t_at(s, st.k) >= s.t1 || st.emitted >= P.max_samples) {
            st.done = 1u;
        }
    }
    rstate[r] = st;
}

@compute @workgroup_size(WG)
fn round_composite(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let w = atomicLoad(&rc[1]);
    if (i >= w) {
        return;
    }
    let r = alive[i];
    var st = rstate[r];
    var trans = st.acc.w;
    var acc = st.acc.xyz;
    var opacity = st.od.x;
    var depth = st.od.y;
    var stopped = false;
    for (var k = raw_offsets[i]; k < raw_offsets[i + 1u]; k = k + 1u) {
        if (R.t_threshold > 0.0 && trans < R.t_threshold) {
            stopped = true;
            break;
        }
        let em1 = exp(-f_sigma[k] * out_dt[k]) - 1.0;   // exp(−σδ) − 1 = −α
        let wk = trans * (-em1);
        acc = acc + wk * vec3<f32>(f_rgb[3u * k], f_rgb[3u * k + 1u], f_rgb[3u * k + 2u]);
        opacity = opacity + wk;
        depth = depth + wk * out_t[k];
        trans = trans * (1.0 + em1);
    }
    if (R.t_threshold > 0.0 && trans < R.t_threshold) {
        stopped = true;
    }
    st.acc = vec4<f32>(acc, trans);
    st.od = vec4<f32>(opacity, depth, 0.0, 0.0);
    if (stopped) {
        st.done = 1u;
    }
    rstate[r] = st;
    if (st.done == 0u) {
        let n_alive = atomicLoad(&rc[0]);
        next[(n_alive - w) + atomicAdd(&rc[3], 1u)] = r;
    }
}

@compute @workgroup_size(WG)
fn round_tail(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let j = linear_id(gid, nwg, WG);
    let n_alive = atomicLoad(&rc[0]);
    let w = atomicLoad(&rc[1]);
    if (j >= n_alive - w) {
        return;
    }
    next[j] = alive[w + j];
}

@compute @workgroup_size(1)
fn round_end() {
    let n_alive = atomicLoad(&rc[0]);
    let w = atomicLoad(&rc[1]);
    atomicStore(&rc[0], (n_alive - w) + atomicLoad(&rc[3]));
    atomicAdd(&rc[4], counters[1]);
}

@compute @workgroup_size(WG)
fn round_output(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r >= R.n_frame) {
        return;
    }
    let st = rstate[r];
    var rgb = st.acc.xyz;
    if (R.has_background != 0u) {
        let bg = vec3<f32>(r_background[3u * r], r_background[3u * r + 1u], r_background[3u * r + 2u]);
        rgb = rgb + (1.0 - st.od.x) * bg;
    }
    r_rgb[3u * r] = rgb.x;
    r_rgb[3u * r + 1u] = rgb.y;
    r_rgb[3u * r + 2u] = rgb.z;
    r_opacity[r] = st.od.x;
    r_depth[r] = st.od.y;
}
