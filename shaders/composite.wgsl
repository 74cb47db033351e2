// Volume-rendering quadrature over packed samples (forward), one invocation per ray.
// CPU twin: nerf_render::composite_forward (crates/render). Buffer layouts: crates/gpu/src/layout.rs.
//
// α_i = 1 − exp(−σ_i δ_i); T_i = Π_{j<i}(1 − α_j); w_i = T_i α_i;
// rgb = Σ w_i c_i + (1 − Σ w_i)·bg; opacity = Σ w_i; depth = Σ w_i t_i.
// Compositing stops (weights 0) once T falls below `t_threshold` (0 disables), as the CPU twin.

// The number of rays is read on the device from counters[0] (slot COUNTER_N_RAYS); params.n_rays is
// the capacity the buffers were sized for (the launch size).
struct Params {
    n_rays: u32,
    t_threshold: f32,
    has_background: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> ray_offsets: array<u32>;   // n_rays + 1
@group(0) @binding(2) var<storage, read> sigma: array<f32>;         // n
@group(0) @binding(3) var<storage, read> rgb: array<f32>;           // 3n
@group(0) @binding(4) var<storage, read> dt: array<f32>;            // n
@group(0) @binding(5) var<storage, read> t: array<f32>;             // n
@group(0) @binding(6) var<storage, read> background: array<f32>;    // 3·n_rays (ignored unless has_background)
@group(0) @binding(7) var<storage, read_write> out_rgb: array<f32>; // 3·n_rays
@group(0) @binding(8) var<storage, read_write> out_opacity: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(10) var<storage, read_write> weights: array<f32>; // n
@group(0) @binding(16) var<storage, read> counters: array<u32>;     // [0] = n_rays

@compute @workgroup_size(64)
fn composite_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= min(counters[0], params.n_rays)) {
        return;
    }
    let s0 = ray_offsets[r];
    let s1 = ray_offsets[r + 1u];
    var trans = 1.0;
    var acc = vec3<f32>(0.0);
    var opacity = 0.0;
    var depth = 0.0;
    var stopped = false;
    for (var k = s0; k < s1; k = k + 1u) {
        if (stopped || (params.t_threshold > 0.0 && trans < params.t_threshold)) {
            stopped = true;
            weights[k] = 0.0;
            continue;
        }
        let em1 = exp(-sigma[k] * dt[k]) - 1.0;   // exp(−σδ) − 1 = −α
        let w = trans * (-em1);
        weights[k] = w;
        acc = acc + w * vec3<f32>(rgb[3u * k], rgb[3u * k + 1u], rgb[3u * k + 2u]);
        opacity = opacity + w;
        depth = depth + w * t[k];
        trans = trans * (1.0 + em1);
    }
    if (params.has_background != 0u) {
        let bg = vec3<f32>(background[3u * r], background[3u * r + 1u], background[3u * r + 2u]);
        acc = acc + (1.0 - opacity) * bg;
    }
    out_rgb[3u * r] = acc.x;
    out_rgb[3u * r + 1u] = acc.y;
    out_rgb[3u * r + 2u] = acc.z;
    out_opacity[r] = opacity;
    out_depth[r] = depth;
}

// ---- backward ------------------------------------------------------------------------------
// CPU twin: nerf_render::composite_backward. With g_i = d_rgb·(c_i − bg) + d_opacity + d_depth·t_i
// (bg = 0 without background) the loss gradient is
//   dσ_k = δ_k (g_k T_{k+1} − Σ_{i>k} w_i g_i),   dc_k = d_rgb · w_k,
// using the forward's weights; samples after an early stop get zero gradient.

@group(0) @binding(11) var<storage, read> d_ray_rgb: array<f32>;      // 3·n_rays
@group(0) @binding(12) var<storage, read> d_opacity: array<f32>;      // n_rays (zeros = none)
@group(0) @binding(13) var<storage, read> d_depth: array<f32>;        // n_rays (zeros = none)
@group(0) @binding(14) var<storage, read_write> d_sigma: array<f32>;  // n
@group(0) @binding(15) var<storage, read_write> d_sample_rgb: array<f32>; // 3n

fn grad_weight(k: u32, r: u32, drgb: vec3<f32>, bg: vec3<f32>) -> f32 {
    let c = vec3<f32>(rgb[3u * k], rgb[3u * k + 1u], rgb[3u * k + 2u]);
    return dot(drgb, c - bg) + d_opacity[r] + d_depth[r] * t[k];
}

@compute @workgroup_size(64)
fn composite_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= min(counters[0], params.n_rays)) {
        return;
    }
    let s0 = ray_offsets[r];
    let s1 = ray_offsets[r + 1u];
    let drgb = vec3<f32>(d_ray_rgb[3u * r], d_ray_rgb[3u * r + 1u], d_ray_rgb[3u * r + 2u]);
    var bg = vec3<f32>(0.0);
    if (params.has_background != 0u) {
        bg = vec3<f32>(background[3u * r], background[3u * r + 1u], background[3u * r + 2u]);
    }
    // Total Σ w_i g_i, then one forward sweep with the running prefix.
    var total = 0.0;
    for (var k = s0; k < s1; k = k + 1u) {
        total = total + weights[k] * grad_weight(k, r, drgb, bg);
    }
    var trans = 1.0;
    var prefix = 0.0;
    var stopped = false;
    for (var k = s0; k < s1; k = k + 1u) {
        if (stopped || (params.t_threshold > 0.0 && trans < params.t_threshold)) {
            stopped = true;
            d_sigma[k] = 0.0;
            d_sample_rgb[3u * k] = 0.0;
            d_sample_rgb[3u * k + 1u] = 0.0;
            d_sample_rgb[3u * k + 2u] = 0.0;
            continue;
        }
        let g = grad_weight(k, r, drgb, bg);
        let w = weights[k];
        prefix = prefix + w * g;
        trans = trans * exp(-sigma[k] * dt[k]);   // T_{k+1}
        d_sigma[k] = dt[k] * (g * trans - (total - prefix));
        d_sample_rgb[3u * k] = drgb.x * w;
        d_sample_rgb[3u * k + 1u] = drgb.y * w;
        d_sample_rgb[3u * k + 2u] = drgb.z * w;
    }
}

// ---- distortion loss (mip-NeRF 360) -------------------------------------------------------
// CPU twin: nerf_render::distortion_loss_grad. Per ray, with s_i = scale·t_i, ℓ_i = scale·δ_i
// and the forward's weights, L = λ/N · (Σ_{i,j} w_i w_j |s_i − s_j| + ⅓ Σ w_i² ℓ_i), N the rays
// of the step (counters[0]). Writes L per ray and ADDS ∂L/∂σ_k = δ_k (g_k T_{k+1} − Σ_{i>k} g_i w_i)
// to d_sigma, g_k = ∂L/∂w_k = λ/N (2 (s_k (2 W_{<k} − W) − 2 S_{<k} + S) + ⅔ ℓ_k w_k),
// T_{k+1} = 1 − W_{≤k}; samples past an early stop get nothing.

struct DistortionParams {
    scale: f32,
    lambda: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(17) var<uniform> dparams: DistortionParams;
@group(0) @binding(18) var<storage, read_write> ray_loss: array<f32>;   // n_rays

@compute @workgroup_size(64)
fn distortion_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n_rays = min(counters[0], params.n_rays);
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays) {
        return;
    }
    let s0 = ray_offsets[r];
    let s1 = ray_offsets[r + 1u];
    let weight = dparams.lambda / f32(max(n_rays, 1u));
    let sc = dparams.scale;
    // The samples compositing reached, and W = Σ w, S = Σ w s over them.
    var trans = 1.0;
    var m = s0;
    var w_all = 0.0;
    var s_all = 0.0;
    for (var k = s0; k < s1; k = k + 1u) {
        if (params.t_threshold > 0.0 && trans < params.t_threshold) {
            break;
        }
        trans = trans * exp(-sigma[k] * dt[k]);
        w_all = w_all + weights[k];
        s_all = s_all + weights[k] * sc * t[k];
        m = k + 1u;
    }
    var w_after = 0.0;
    var s_after = 0.0;
    var suffix = 0.0;
    var loss = 0.0;
    for (var k = m; k > s0; k = k - 1u) {
        let i = k - 1u;
        let w = weights[i];
        let s = sc * t[i];
        let len = sc * dt[i];
        let w_before = w_all - w_after - w;
        let s_before = s_all - s_after - w * s;
        loss = loss + 2.0 * w * (s * w_before - s_before) + len * w * w / 3.0;
        let g = weight * (2.0 * (s * (2.0 * w_before - w_all) - 2.0 * s_before + s_all) + 2.0 * len * w / 3.0);
        let t_next = 1.0 - (w_before + w);
        d_sigma[i] = d_sigma[i] + dt[i] * (g * t_next - suffix);
        suffix = suffix + g * w;
        w_after = w_after + w;
        s_after = s_after + w * s;
    }
    ray_loss[r] = weight * loss;
}

// Depth supervision (CPU twin: nerf_render::depth_loss_grad): per ray with a measured distance
// (depth_target[r] > 0), loss λ/N·|D̂ − D| into depth_ray_loss[r] and d_depth[r] = λ/N·sign(D̂ − D),
// where D̂ = out_depth[r] is the forward's expected depth and N = n_rays; 0 and 0 without one.

struct DepthParams {
    lambda: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(19) var<uniform> depth_params: DepthParams;
@group(0) @binding(20) var<storage, read> depth_target: array<f32>;   // n_rays
@group(0) @binding(21) var<storage, read_write> d_depth_out: array<f32>;   // n_rays
@group(0) @binding(22) var<storage, read_write> depth_ray_loss: array<f32>; // n_rays

@compute @workgroup_size(64)
fn depth_loss(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n_rays = min(counters[0], params.n_rays);
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays) {
        return;
    }
    let measured = depth_target[r];
    if (measured > 0.0) {
        let scale = depth_params.lambda / f32(max(n_rays, 1u));
        let e = out_depth[r] - measured;
        depth_ray_loss[r] = scale * abs(e);
        d_depth_out[r] = scale * sign(e);
    } else {
        depth_ray_loss[r] = 0.0;
        d_depth_out[r] = 0.0;
    }
}
