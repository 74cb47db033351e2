// Adam update over one flat f32 parameter buffer holding several parameter groups (GpuAdam in
// crates/gpu/src/optim.rs; CPU twin: nerf_optim::Adam::step, torch's formulation):
//   g = grad + wd·p;  m = β1·m + (1−β1)·g;  v = β2·v + (1−β2)·g²;
//   p −= (lr·lr_scale/(1−β1^t)) · m / (sqrt(v)·(1/sqrt(1−β2^t)) + ε);  grad = 0 (fused zeroing).
// The bias corrections are computed on the host in f64 exactly as the CPU does and written into
// the uniform each step (step_size = lr/(1−β1^t), inv_sqrt_bc2 = 1/sqrt(1−β2^t)).
// Layout: params, grads, m, v are [extent] f32, indexed by the parameter index; `groups` lists the
// groups sorted by offset with `start` = Σ of the lengths of the groups before (the launch index
// space is the concatenation of the groups, so holes between groups are never touched).
// One invocation per parameter, workgroups of WG; memory bound (4 reads, 4 writes per element).
//
// Entry `adam_step_ema` also folds the updated parameter into its exponential moving average
// (tiny-cuda-nn's Ema; CPU twin: nerf_optim::Ema::update / ema_update):
//   ema = ema_old·ema + ema_new·p_new   (ema = ema_new·p_new when ema_old == 0: the first update
// never reads the previous values), with ema_old = d·(1−d^(t−1))/(1−d^t), ema_new = (1−d)/(1−d^t)
// computed on the host in f64 (nerf_optim::Ema::coefficients). `ema` has the parameter layout;
// one more read and write per element, no extra pass.
//
// Sparse groups (Group.sparse = 1; tiny-cuda-nn's Adam on "non-matrix" parameters such as hash
// tables; CPU twin: nerf_optim::Adam with AdamConfig::sparse_groups): an entry whose gradient is
// exactly zero is left alone (parameter, moments, count); otherwise its own step count
// `counts[k]` is incremented and the bias corrections use it: step_size = lr·bias[t_k−1].x with
// bias[t−1] = (1/(1−β1^t), 1/sqrt(1−β2^t)) computed on the host in f64 (as the CPU does) up to the
// t where both are 1 in f32; larger counts use the last entry. `counts` has the parameter layout
// (u32) and is only touched for sparse groups.

struct AdamParams {
    total: u32,        // Σ group lengths (launch size)
    n_groups: u32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    eps: f32,
    step_size: f32,    // lr / (1 − β1^t)
    inv_sqrt_bc2: f32, // 1 / sqrt(1 − β2^t)
    ema_old: f32,      // EMA weight of the previous average (adam_step_ema only)
    ema_new: f32,      // EMA weight of the new parameter (adam_step_ema only)
    lr: f32,           // learning rate (sparse groups debias per entry)
}

struct Group {
    offset: u32,       // first parameter index
    len: u32,
    start: u32,        // first launch index
    weight_decay: f32,
    lr_scale: f32,
    sparse: u32,
    _pad1: u32,
    _pad2: u32,
}

override WG: u32 = 256u;

@group(0) @binding(0) var<uniform> prm: AdamParams;
@group(0) @binding(1) var<storage, read> groups: array<Group>;
@group(0) @binding(2) var<storage, read_write> params: array<f32>;
@group(0) @binding(3) var<storage, read_write> grads: array<f32>;
@group(0) @binding(4) var<storage, read_write> m1: array<f32>;
@group(0) @binding(5) var<storage, read_write> m2: array<f32>;

@group(0) @binding(6) var<storage, read_write> ema: array<f32>;
@group(0) @binding(7) var<storage, read_write> counts: array<u32>;
@group(0) @binding(8) var<storage, read> bias: array<vec2<f32>>;

/// Index of parameter of launch index `i` (the group holding `i`, then the offset inside it);
/// `wd` and `lr_scale` of that group.
struct Slot {
    k: u32,
    wd: f32,
    lr_scale: f32,
    sparse: u32,
}

fn slot(i: u32) -> Slot {
    // Few groups (a handful per field): a linear scan is cheaper than anything clever.
    var g = 0u;
    loop {
        if (g + 1u >= prm.n_groups || i < groups[g + 1u].start) {
            break;
        }
        g += 1u;
    }
    let grp = groups[g];
    return Slot(grp.offset + (i - grp.start), grp.weight_decay, grp.lr_scale, grp.sparse);
}

/// The Adam update of parameter `k`; returns the new parameter.
fn adam_update(s: Slot) -> f32 {
    let k = s.k;
    let p = params[k];
    let g = grads[k];
    var step_size = prm.step_size;
    var inv_sqrt_bc2 = prm.inv_sqrt_bc2;
    if (s.sparse != 0u) {
        if (g == 0.0) {
            return p; // its gradient is already zero
        }
        let t = counts[k] + 1u;
        counts[k] = t;
        let b = bias[min(t, arrayLength(&bias)) - 1u];
        step_size = prm.lr * b.x;
        inv_sqrt_bc2 = b.y;
    }
    let gi = g + s.wd * p;
    let mi = prm.beta1 * m1[k] + prm.one_minus_beta1 * gi;
    let vi = prm.beta2 * m2[k] + prm.one_minus_beta2 * gi * gi;
    m1[k] = mi;
    m2[k] = vi;
    let p_new = p - (step_size * s.lr_scale) * mi / (sqrt(vi) * inv_sqrt_bc2 + prm.eps);
    params[k] = p_new;
    grads[k] = 0.0;
    return p_new;
}

@compute @workgroup_size(WG)
fn adam_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= prm.total) {
        return;
    }
    adam_update(slot(i));
}

@compute @workgroup_size(WG)
fn adam_step_ema(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= prm.total) {
        return;
    }
    let s = slot(i);
    let p_new = adam_update(s);
    var e = prm.ema_new * p_new;
    if (prm.ema_old != 0.0) {
        e = prm.ema_old * ema[s.k] + e;
    }
    ema[s.k] = e;
}
