// Stratified sampling and hierarchical (inverse-CDF, nerf-pytorch sample_pdf) sampling into the
// packed layout (GpuStratified / GpuHierarchical in crates/gpu/src/pdf.rs; CPU twins:
// nerf_sampling::stratified and nerf_sampling::hierarchical, same formulas in the same order).
// Packed layout: offsets [R+1] u32 (ray r owns offsets[r]..offsets[r+1]), positions [S][3],
// dirs [S][3], t [S], dt [S] with δ_i = t_{i+1} − t_i and the last δ = far − t_last (clamped ≥ 0).
// Rays: origins [R][3], dirs [R][3] (unit), near/far scalars from the uniform; with clip = 1 each
// ray's segment is [near, far] ∩ box, or [near, near] on a miss (`segment`, the CPU's
// nerf_sampling::segment: NDC scenes), then ∩ the render crop box when crop_c.w = 1 (CropBox::clip),
// and far below means that ray's far.
// Random numbers: stratified jitter u = rand_f32(seed, 0, r·N + k); hierarchical jitter
// ξ = rand_f32(seed, 1, r·n_fine + k), u_k = min((k + ξ)·(1/n_fine), 1).
//
// stratified:   one invocation per sample (coalesced writes); it recomputes its neighbour's t for δ.
//               n_rays = counters[0]; writes counters[1] = n_rays·N (0 samples if !(far ≥ near)).
// hier_offsets: one workgroup: out offsets = coarse offsets + n_fine·(# earlier rays with ≥ 3
//               coarse samples); counters_out = [n_rays, total].
// hierarchical: one invocation per ray, the CPU's algorithm literally (cdf walk over sorted u,
//               insertion sort, merge with the coarse t; the ray's dt slots are the scratch for the
//               fine samples). Cheap next to the 8×256 MLP that follows it (the paper's pipeline).

struct PdfParams {
    n_per_ray: u32,  // stratified: N; hierarchical: n_fine
    near: f32,
    far: f32,
    jitter: u32,     // 0: bin centres (stratified) / linspace u (hierarchical)
    seed: u32,
    clip: u32,       // 1: [near, far] ∩ box per ray
    _pad1: u32,
    _pad2: u32,
    box_min: vec4<f32>,
    box_max: vec4<f32>,
    crop_x: vec4<f32>,   // render crop box (common.wgsl's crop_slab): axes (xyz), half sizes (w)
    crop_y: vec4<f32>,
    crop_z: vec4<f32>,
    crop_c: vec4<f32>,   // centre; w = 1: crop on
}

override WG: u32 = 64u;

@group(0) @binding(0) var<uniform> prm: PdfParams;
@group(0) @binding(1) var<storage, read_write> counters: array<u32>;
@group(0) @binding(2) var<storage, read_write> counters_out: array<u32>;
@group(0) @binding(3) var<storage, read> origins: array<f32>;
@group(0) @binding(4) var<storage, read> ray_dirs: array<f32>;
@group(0) @binding(5) var<storage, read> coarse_offsets: array<u32>;
@group(0) @binding(6) var<storage, read> coarse_t: array<f32>;
@group(0) @binding(7) var<storage, read> coarse_w: array<f32>;
@group(0) @binding(8) var<storage, read_write> offsets_out: array<u32>;
@group(0) @binding(9) var<storage, read_write> positions: array<f32>;
@group(0) @binding(10) var<storage, read_write> dirs_out: array<f32>;
@group(0) @binding(11) var<storage, read_write> t_out: array<f32>;
@group(0) @binding(12) var<storage, read_write> dt_out: array<f32>;
@group(0) @binding(13) var<storage, read> counters_in: array<u32>;

var<workgroup> wg_u: array<u32, WG>;

fn write_geometry(r: u32, s: u32, t: f32) {
    for (var c = 0u; c < 3u; c++) {
        let d = ray_dirs[3u * r + c];
        positions[3u * s + c] = origins[3u * r + c] + t * d;
        dirs_out[3u * s + c] = d;
    }
}

// Ray r's segment: (near, far), or with prm.clip = 1 [near, far] ∩ box (common.wgsl's slab, as
// the occupancy marcher's), then with crop_c.w = 1 ∩ the crop box; [near, near] when empty.
fn segment(r: u32) -> vec2<f32> {
    var seg = vec2<f32>(prm.near, prm.far);
    if (prm.clip == 0u && prm.crop_c.w == 0.0) {
        return seg;
    }
    let o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    let d = vec3<f32>(ray_dirs[3u * r], ray_dirs[3u * r + 1u], ray_dirs[3u * r + 2u]);
    if (prm.clip != 0u) {
        let box = slab(o, d, prm.box_min.xyz, prm.box_max.xyz);
        if (box.z == 0.0) {
            return vec2<f32>(prm.near, prm.near);
        }
        let a = max(prm.near, box.x);
        let b = min(prm.far, box.y);
        if (!(b > a)) {
            return vec2<f32>(prm.near, prm.near);
        }
        seg = vec2<f32>(a, b);
    }
    if (prm.crop_c.w != 0.0) {
        // The render crop box (CPU twin: nerf_sampling::CropBox::clip).
        let c = crop_slab(o, d, prm.crop_x, prm.crop_y, prm.crop_z, prm.crop_c.xyz);
        let a = max(seg.x, c.x);
        let b = min(seg.y, c.y);
        if (c.z == 0.0 || !(b > a)) {
            return vec2<f32>(prm.near, prm.near);
        }
        seg = vec2<f32>(a, b);
    }
    return seg;
}

// t of stratified sample k of a ray with segment starting at a (the CPU's expression, clamped
// to its bin).
fn strat_t(r: u32, k: u32, a: f32, step: f32) -> f32 {
    var u = 0.5;
    if (prm.jitter != 0u) {
        u = rand_f32(prm.seed, 0u, r * prm.n_per_ray + k);
    }
    return min(a + (f32(k) + u) * step, a + f32(k + 1u) * step);
}

@compute @workgroup_size(WG)
fn stratified(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let n_rays = counters[0];
    var n = prm.n_per_ray;
    if (!(prm.far >= prm.near)) {
        n = 0u;
    }
    if (i <= n_rays) {
        offsets_out[i] = i * n;
    }
    if (i == 0u) {
        counters[1] = n_rays * n;
    }
    if (n == 0u || i >= n_rays * n) {
        return;
    }
    let r = i / n;
    let k = i - r * n;
    let seg = segment(r);
    let step = (seg.y - seg.x) / f32(n);
    let t = strat_t(r, k, seg.x, step);
    var next = seg.y;
    if (k + 1u < n) {
        next = strat_t(r, k + 1u, seg.x, step);
    }
    t_out[i] = t;
    dt_out[i] = max(next - t, 0.0);
    write_geometry(r, i, t);
}

// Inclusive Hillis–Steele scan of wg_u (all invocations call it).
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
fn hier_offsets(@builtin(local_invocation_index) lid: u32) {
    let n_rays = counters_in[0];
    var carry = 0u;
    for (var base = 0u; base <= n_rays; base += WG) {
        let r = base + lid;
        var flag = 0u;
        if (r < n_rays && prm.n_per_ray > 0u && coarse_offsets[r + 1u] - coarse_offsets[r] >= 3u) {
            flag = 1u;
        }
        workgroupBarrier();
        wg_u[lid] = flag;
        wg_inclusive_scan(lid);
        if (r <= n_rays) {
            offsets_out[r] = coarse_offsets[r] + prm.n_per_ray * (carry + wg_u[lid] - flag);
        }
        carry += wg_u[WG - 1u];
    }
    if (lid == 0u) {
        counters_out[0] = n_rays;
        counters_out[1] = coarse_offsets[n_rays] + prm.n_per_ray * carry;
    }
}

fn bin_edge(cbase: u32, i: u32) -> f32 {
    return 0.5 * (coarse_t[cbase + i] + coarse_t[cbase + i + 1u]);
}

@compute @workgroup_size(WG)
fn hierarchical(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r >= counters_in[0]) {
        return;
    }
    let cbase = coarse_offsets[r];
    let n_c = coarse_offsets[r + 1u] - cbase;
    let obase = offsets_out[r];
    let n_fine = prm.n_per_ray;
    if (n_c >= 3u && n_fine > 0u) {
        // u values into the scratch (this ray's first n_fine dt slots).
        let inv = 1.0 / f32(n_fine);
        for (var k = 0u; k < n_fine; k++) {
            var u: f32;
            if (prm.jitter != 0u) {
                u = min((f32(k) + rand_f32(prm.seed, 1u, r * n_fine + k)) * inv, 1.0);
            } else if (n_fine <= 1u) {
                u = 0.0;
            } else {
                u = f32(k) / f32(n_fine - 1u);
            }
            dt_out[obase + k] = u;
        }
        // sample_pdf (nerf-pytorch conventions), cdf built on the fly while walking sorted u.
        let nw = n_c - 2u;
        let eps = 1e-5;
        var total = 0.0;
        for (var i = 0u; i < nw; i++) {
            total += coarse_w[cbase + i + 1u] + eps;
        }
        var j = 0u;
        var c_prev = 0.0;
        var c_cur = 0.0;
        var u_last = -3.0e38;
        for (var k = 0u; k < n_fine; k++) {
            let u = dt_out[obase + k];
            if (u < u_last) {
                j = 0u;
                c_prev = 0.0;
                c_cur = 0.0;
            }
            u_last = u;
            while (j <= nw && c_cur <= u) {
                j += 1u;
                c_prev = c_cur;
                if (j <= nw) {
                    c_cur = c_prev + (coarse_w[cbase + j] + eps) / total;
                }
            }
            let below = max(j, 1u) - 1u;
            let above = min(j, nw);
            var cdf_below = c_prev;
            if (j == 0u) {
                cdf_below = 0.0;
            }
            var cdf_above = c_prev;
            if (j <= nw) {
                cdf_above = c_cur;
            }
            var denom = cdf_above - cdf_below;
            if (denom < eps) {
                denom = 1.0;
            }
            let frac = (u - cdf_below) / denom;
            let b0 = bin_edge(cbase, below);
            let b1 = bin_edge(cbase, above);
            dt_out[obase + k] = b0 + frac * (b1 - b0);
        }
        // Monotone up to the denom guard: insertion sort (linear when sorted).
        for (var k = 1u; k < n_fine; k++) {
            let x = dt_out[obase + k];
            var m = k;
            while (m > 0u && dt_out[obase + m - 1u] > x) {
                dt_out[obase + m] = dt_out[obase + m - 1u];
                m -= 1u;
            }
            dt_out[obase + m] = x;
        }
        // Merge with the coarse t (coarse first on ties).
        var a = 0u;
        var b = 0u;
        for (var x = 0u; x < n_c + n_fine; x++) {
            if (b >= n_fine || (a < n_c && coarse_t[cbase + a] <= dt_out[obase + b])) {
                t_out[obase + x] = coarse_t[cbase + a];
                a += 1u;
            } else {
                t_out[obase + x] = dt_out[obase + b];
                b += 1u;
            }
        }
    } else {
        for (var x = 0u; x < n_c; x++) {
            t_out[obase + x] = coarse_t[cbase + x];
        }
    }
    let n_out = offsets_out[r + 1u] - obase;
    let far = segment(r).y;
    for (var x = 0u; x < n_out; x++) {
        let t = t_out[obase + x];
        var next = far;
        if (x + 1u < n_out) {
            next = t_out[obase + x + 1u];
        }
        dt_out[obase + x] = max(next - t, 0.0);
        write_geometry(r, obase + x, t);
    }
}
