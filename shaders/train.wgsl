// Training-step glue on the device: the photometric loss and its gradient, and the adaptive batch
// size (rays per step from a target number of samples per step). CPU twins:
// nerf_render::photometric_loss_grad and nerf_train's batch sizing (Trainer::step).

struct LossParams {
    capacity_rays: u32,
    huber_delta: f32,  // > 0: instant-ngp's Huber loss (residuals clamped to ±δ in the gradient); 0: MSE
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> lp: LossParams;
@group(0) @binding(1) var<storage, read> counters: array<u32>;       // [0] = n_rays
@group(0) @binding(2) var<storage, read> pred: array<f32>;           // 3·n_rays
@group(0) @binding(3) var<storage, read> target_rgb: array<f32>;     // 3·n_rays
@group(0) @binding(4) var<storage, read_write> d_pred: array<f32>;   // 3·n_rays
@group(0) @binding(5) var<storage, read_write> ray_sq_err: array<f32>; // n_rays: Σ_c (pred − target)²

// MSE over all 3·n_rays values: L = Σ e² / (3 n), dL/dpred = 2 e / (3 n); with a Huber δ,
// dL/dpred = 2 clamp(e, −δ, δ) / (3 n). The per-ray squared errors are kept so the host can read
// the MSE every N steps without a reduction kernel.
@compute @workgroup_size(64)
fn mse_loss(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    let n = min(counters[0], lp.capacity_rays);
    if (r >= n) {
        return;
    }
    let scale = 2.0 / f32(3u * n);
    var sq = 0.0;
    for (var c = 0u; c < 3u; c = c + 1u) {
        let e = pred[3u * r + c] - target_rgb[3u * r + c];
        var g = e;
        if (lp.huber_delta > 0.0) {
            g = clamp(e, -lp.huber_delta, lp.huber_delta);
        }
        d_pred[3u * r + c] = scale * g;
        sq = sq + e * e;
    }
    ray_sq_err[r] = sq;
}

struct BatchParams {
    target_samples: u32,
    min_rays: u32,
    max_rays: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> bp: BatchParams;
@group(0) @binding(1) var<storage, read_write> batch_counters: array<u32>;  // [0] n_rays, [1] n_samples
@group(0) @binding(2) var<storage, read_write> samples_per_ray: array<f32>; // [0] running mean (0 = none yet)

// After a step: running mean of samples per ray (0.9 / 0.1 EMA, the first step sets it), then the
// next step's ray count = clamp(target / mean, min_rays, max_rays). One invocation.
@compute @workgroup_size(1)
fn next_batch() {
    let n_rays = max(batch_counters[0], 1u);
    let spr = f32(batch_counters[1]) / f32(n_rays);
    var m = samples_per_ray[0];
    if (m > 0.0) {
        m = 0.9 * m + 0.1 * spr;
    } else {
        m = spr;
    }
    samples_per_ray[0] = m;
    let want = f32(bp.target_samples) / max(m, 1e-6);
    batch_counters[0] = u32(clamp(want, f32(bp.min_rays), f32(bp.max_rays)));
}

@group(0) @binding(3) var<storage, read_write> seen: array<u32>;            // [lo, hi] samples so far

// Adds this stage's n_samples (counters[1]) to the 64-bit running total. One invocation.
@compute @workgroup_size(1)
fn count_samples() {
    let n = batch_counters[1];
    let lo = seen[0] + n;
    if (lo < seen[0]) {
        seen[1] = seen[1] + 1u;
    }
    seen[0] = lo;
}

// counters[0] from the running mean alone (after rendering or a resume reused the counters);
// leaves counters[0] as it is while no step has set the mean. One invocation.
@compute @workgroup_size(1)
fn batch_from_mean() {
    let m = samples_per_ray[0];
    if (m > 0.0) {
        let want = f32(bp.target_samples) / m;
        batch_counters[0] = u32(clamp(want, f32(bp.min_rays), f32(bp.max_rays)));
    }
}

struct ChunkParams {
    offset: u32,
    size: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> cp: ChunkParams;
@group(0) @binding(6) var<storage, read> src_counters: array<u32>;

// counters[1] = the part of src_counters[1] items that falls in [offset, offset + size): how many
// items a chunked launch (e.g. the occupancy-grid density query) handles. One invocation.
@compute @workgroup_size(1)
fn chunk_count() {
    let m = src_counters[1];
    var c = 0u;
    if (m > cp.offset) {
        c = min(m - cp.offset, cp.size);
    }
    batch_counters[1] = c;
}
