// Glue between the parts of a field of the form "density network → (σ, features) → colour network
// on [features, direction encoding]" — the Instant-NGP field (crates/field-hash), the paper's
// field (crates/field-freq) and the voxel field (crates/field-voxel, whose "density network" is
// its two grids). One invocation per sample, n = counters[1]. CPU twins: the fields'
// forward_t / backward_t / query_t (each GPU field is compared with its CPU field in its crate).
//
//   x = dout[k·dd]  (the density network's first output)
//   σ = exp(min(x + b, 80))        (act = 0, Instant-NGP; backward: exp(min(x + b, 15)), truncated
//                                   exp; b = bias, 0 by default, nerfacc's example: −1)
//   σ = max(x, 0)                  (act = 1, the paper)
//   σ = s·softplus(x + b)          (act = 2, DVGO; s = scale; backward: s·sigmoid(x + b))
//   colour input = [dout[feat_start .. dd], dir_enc[0 .. dir_dim]]
//   backward: d_dout[j] = d_color_in[j − feat_start] for j ≥ feat_start, else 0; d_dout[0] += dσ·σ'(x)

struct GlueParams {
    dd: u32,
    dir_dim: u32,
    capacity: u32,
    feat_start: u32,
    act: u32,
    bias: f32,
    scale: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> gp: GlueParams;
@group(0) @binding(1) var<storage, read> counters: array<u32>;
@group(0) @binding(2) var<storage, read> dout: array<f32>;             // n·dd
@group(0) @binding(3) var<storage, read> dir_enc: array<f32>;          // n·dir_dim
@group(0) @binding(4) var<storage, read_write> sigma: array<f32>;      // n
@group(0) @binding(5) var<storage, read_write> color_in: array<f32>;   // n·(dd − feat_start + dir_dim)
@group(0) @binding(6) var<storage, read> d_color_in: array<f32>;       // n·(dd − feat_start + dir_dim)
@group(0) @binding(7) var<storage, read> d_sigma: array<f32>;          // n
@group(0) @binding(8) var<storage, read_write> d_dout: array<f32>;     // n·dd

fn n_samples() -> u32 {
    return min(counters[1], gp.capacity);
}

// ln(1 + e) for e in [0, 1]: the series where 1 + e would lose e's digits (and where log's
// absolute error bound, 2^-21 near 1 in Vulkan, would swamp a small result), else log.
fn log1p_small(e: f32) -> f32 {
    if (e < 0.01) {
        return e * (1.0 - e * (0.5 - e * (1.0 / 3.0 - 0.25 * e)));
    }
    return log(1.0 + e);
}

// softplus(z) = max(z, 0) + ln(1 + exp(−|z|)), the CPU's form.
fn softplus(z: f32) -> f32 {
    return max(z, 0.0) + log1p_small(exp(-abs(z)));
}

fn activate(x: f32) -> f32 {
    if (gp.act == 0u) {
        return exp(min(x + gp.bias, 80.0));
    }
    if (gp.act == 2u) {
        return gp.scale * softplus(x + gp.bias);
    }
    return max(x, 0.0);
}

fn activation_grad(x: f32) -> f32 {
    if (gp.act == 0u) {
        return exp(min(x + gp.bias, 15.0));
    }
    if (gp.act == 2u) {
        return gp.scale / (1.0 + exp(-(x + gp.bias)));
    }
    return select(0.0, 1.0, x > 0.0);
}

// Each workgroup owns 64 consecutive samples, whose rows are contiguous in every buffer: its 64
// invocations walk the block's colour-input elements (and, in the backward, its d_dout elements)
// one after another, so neighbouring invocations touch neighbouring addresses. One invocation
// per sample looping over its own row (as before) made each load and store of a subgroup touch
// 32 rows a row apart: 3.3 ms for the paper field's 196k × 283 colour inputs on the H100.
@compute @workgroup_size(64)
fn assemble(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let k = linear_id(gid, nwg, 64u);
    let n = n_samples();
    let k0 = k - lid;
    if (k0 >= n) {
        return;
    }
    if (k < n) {
        sigma[k] = activate(dout[k * gp.dd]);
    }
    let nf = gp.dd - gp.feat_start;
    let w = nf + gp.dir_dim;
    let total = min(64u, n - k0) * w;
    for (var e = lid; e < total; e = e + 64u) {
        let kk = k0 + e / w;
        let j = e % w;
        var v: f32;
        if (j < nf) {
            v = dout[kk * gp.dd + gp.feat_start + j];
        } else {
            v = dir_enc[kk * gp.dir_dim + (j - nf)];
        }
        color_in[k0 * w + e] = v;
    }
}

@compute @workgroup_size(64)
fn density_only(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let k = linear_id(gid, nwg, 64u);
    if (k >= n_samples()) {
        return;
    }
    sigma[k] = activate(dout[k * gp.dd]);
}

// Coalesced as `assemble`: the workgroup's invocations walk its 64 samples' d_dout elements.
@compute @workgroup_size(64)
fn backward_glue(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let k = linear_id(gid, nwg, 64u);
    let n = n_samples();
    let k0 = k - lid;
    if (k0 >= n) {
        return;
    }
    let w = gp.dd - gp.feat_start + gp.dir_dim;
    let total = min(64u, n - k0) * gp.dd;
    for (var e = lid; e < total; e = e + 64u) {
        let kk = k0 + e / gp.dd;
        let j = e % gp.dd;
        var g = 0.0;
        if (j >= gp.feat_start) {
            g = d_color_in[kk * w + (j - gp.feat_start)];
        }
        if (j == 0u) {
            g = g + d_sigma[kk] * activation_grad(dout[kk * gp.dd]);
        }
        d_dout[k0 * gp.dd + e] = g;
    }
}
