// The Plenoxels field's own per-sample kernels (nerf_plenoxels::gpu::GpuPlenoxels), compiled with
// nerf-rs's common.wgsl prepended (nerf_gpu::shaders::with_common: linear_id). CPU twin:
// nerf_plenoxels::Plenoxels (eval, backward_t).
//
// Layouts: counters array<u32> (counters[1] = n samples); head [n][S], S = 1 + 3·B: column 0 is
// s·d (the density grid's forward at scale s), column 1 + c·B + l is s·k_{c,l} (the coefficient
// grid's); sh [n][B] (the direction's SH values); sigma [n]; rgb [n][3]; d_head as head.
// Launch: one invocation per sample (nerf_gpu::Launch); i >= n returns, and n is bounded by what
// every bound buffer holds (hardware adapters run without bounds checks).

// SH coefficients per colour channel (degree²).
override B: u32 = 4u;
override WG: u32 = 128u;
// σ = softplus(s·d + SHIFT) · INV_VOXEL.
override SHIFT: f32 = 0.0;
override INV_VOXEL: f32 = 1.0;

@group(0) @binding(0) var<storage, read> counters: array<u32>;
@group(0) @binding(1) var<storage, read> head: array<f32>;
@group(0) @binding(2) var<storage, read> sh: array<f32>;
@group(0) @binding(3) var<storage, read_write> sigma: array<f32>;
@group(0) @binding(4) var<storage, read_write> rgb: array<f32>;
@group(0) @binding(5) var<storage, read> d_sigma: array<f32>;
@group(0) @binding(6) var<storage, read> d_rgb: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_head: array<f32>;

fn stride() -> u32 {
    return 1u + 3u * B;
}

// ln(1 + e) for e = exp(−|z|) in (0, 1]: a series below 0.01, where log(1 + e) loses the digits
// of e (the field starts at alpha_init = 1e-6, i.e. e ≈ 1e-6).
fn log1p_small(e: f32) -> f32 {
    if (e < 0.01) {
        return e * (1.0 - e * (0.5 - e * (1.0 / 3.0 - 0.25 * e)));
    }
    return log(1.0 + e);
}

fn softplus(z: f32) -> f32 {
    return max(z, 0.0) + log1p_small(exp(-abs(z)));
}

fn sigmoid(z: f32) -> f32 {
    return 1.0 / (1.0 + exp(-z));
}

// z_c = Σ_l (s·k_{c,l}) · Y_l of sample i.
fn logit(i: u32, c: u32) -> f32 {
    let row = i * stride() + 1u + c * B;
    var z = 0.0;
    for (var l = 0u; l < B; l++) {
        z += head[row + l] * sh[i * B + l];
    }
    return z;
}

@compute @workgroup_size(WG)
fn plen_density(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let n = min(counters[1], min(arrayLength(&head) / stride(), arrayLength(&sigma)));
    if (i >= n) {
        return;
    }
    sigma[i] = softplus(head[i * stride()] + SHIFT) * INV_VOXEL;
}

@compute @workgroup_size(WG)
fn plen_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let n = min(min(counters[1], arrayLength(&head) / stride()), min(min(arrayLength(&sh) / B, arrayLength(&sigma)), arrayLength(&rgb) / 3u));
    if (i >= n) {
        return;
    }
    sigma[i] = softplus(head[i * stride()] + SHIFT) * INV_VOXEL;
    for (var c = 0u; c < 3u; c++) {
        rgb[3u * i + c] = sigmoid(logit(i, c));
    }
}

// d_head = [∂L/∂(s·d), ∂L/∂(s·k)]: the grids' backward multiply by s. Recomputes the forward's
// values from head and sh, which the batch's forward left in place.
@compute @workgroup_size(WG)
fn plen_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let rows = min(arrayLength(&head), arrayLength(&d_head)) / stride();
    let n = min(min(counters[1], rows), min(min(arrayLength(&sh) / B, arrayLength(&d_sigma)), arrayLength(&d_rgb) / 3u));
    if (i >= n) {
        return;
    }
    let row = i * stride();
    // softplus' = sigmoid.
    d_head[row] = d_sigma[i] * sigmoid(head[row] + SHIFT) * INV_VOXEL;
    for (var c = 0u; c < 3u; c++) {
        let r = sigmoid(logit(i, c));
        let dz = d_rgb[3u * i + c] * r * (1.0 - r);
        for (var l = 0u; l < B; l++) {
            d_head[row + 1u + c * B + l] = dz * sh[i * B + l];
        }
    }
}
