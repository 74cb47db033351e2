// Per-view sums of per-ray values: the gradients of parameters the trainer keeps per training view
// (colour correction, camera pose refinement) from their rays' shares. 12 values per ray; one
// workgroup per view strides over the batch's rays, takes those of its view and reduces in
// workgroup memory in a fixed order (deterministic, no atomics); the sums are ADDED to out.
// Host side: nerf_gpu::views::ViewSums. Users: color.wgsl's ray_grads, pose.wgsl's ray_grads.

struct ViewParams {
    n_views: u32,
    capacity_rays: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> vp: ViewParams;
@group(0) @binding(1) var<storage, read> counters: array<u32>;        // [0] = rays of the step
@group(0) @binding(2) var<storage, read> views: array<u32>;           // n_rays
@group(0) @binding(3) var<storage, read> ray_vals: array<f32>;        // 12·n_rays
@group(0) @binding(4) var<storage, read_write> sums: array<f32>;      // 12·n_views, added to

const RWG: u32 = 256u;
var<workgroup> partial: array<array<f32, 12>, RWG>;

@compute @workgroup_size(RWG)
fn view_sums(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    // Uniform across the workgroup (barriers below).
    let v = wid.x + wid.y * nwg.x;
    let n = min(counters[0], vp.capacity_rays);
    var acc: array<f32, 12>;
    for (var k = 0u; k < 12u; k = k + 1u) {
        acc[k] = 0.0;
    }
    if (v < vp.n_views) {
        for (var r = lid; r < n; r = r + RWG) {
            if (views[r] == v) {
                for (var k = 0u; k < 12u; k = k + 1u) {
                    acc[k] = acc[k] + ray_vals[12u * r + k];
                }
            }
        }
    }
    partial[lid] = acc;
    workgroupBarrier();
    for (var s = RWG / 2u; s > 0u; s = s / 2u) {
        if (lid < s) {
            for (var k = 0u; k < 12u; k = k + 1u) {
                partial[lid][k] = partial[lid][k] + partial[lid + s][k];
            }
        }
        workgroupBarrier();
    }
    if (v < vp.n_views && lid < 12u) {
        sums[12u * v + lid] = sums[12u * v + lid] + partial[0][lid];
    }
}
