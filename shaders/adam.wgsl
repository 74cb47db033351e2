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
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Group {
    offset: u32,       // first parameter index
    len: u32,
    start: u32,        // first launch index
    weight_decay: f32,
    lr_scale: f32,
    _pad0: u32,
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

@compute @workgroup_size(WG)
fn adam_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= prm.total) {
        return;
    }
    // Few groups (a handful per field): a linear scan is cheaper than anything clever.
    var g = 0u;
    loop {
        if (g + 1u >= prm.n_groups || i < groups[g + 1u].start) {
            break;
        }
        g += 1u;
    }
    let grp = groups[g];
    let k = grp.offset + (i - grp.start);
    let p = params[k];
    let gi = grads[k] + grp.weight_decay * p;
    let mi = prm.beta1 * m1[k] + prm.one_minus_beta1 * gi;
    let vi = prm.beta2 * m2[k] + prm.one_minus_beta2 * gi * gi;
    m1[k] = mi;
    m2[k] = vi;
    params[k] = p - (prm.step_size * grp.lr_scale) * mi / (sqrt(vi) * prm.inv_sqrt_bc2 + prm.eps);
    grads[k] = 0.0;
}
