// Indirect-dispatch arguments for the kernels of a batch whose size only the device knows (the
// samples a marcher or a compaction wrote to counters[1]). Host side and CPU twin:
// nerf_gpu::dispatch (DispatchArgs, groups_for).
//
// One table per batch, written by one launch of `dispatch_args` after the count is final and
// before the kernels that read it: entry (z, k) for z = 1..=MAX_Z and k = 0..=MAX_K holds the
// workgroup counts (x, y, z) of a kernel that covers 2^k items per workgroup and launches z
// workgroups along the third dimension (the hash grid's levels): g = ceil(n / 2^k) workgroups,
// split as kernel::groups_1d splits them (x ≤ 65 535, y = ceil(g / 65 535), x = ceil(g / y)),
// except that n = 0 gives g = 0 (an empty launch; groups_1d keeps one workgroup). Entry (z, k)
// starts at word 3·((z − 1)·(MAX_K + 1) + k). n = min(counters[SLOT], cap[0]): the count never
// exceeds the capacity the buffers were made for.

override SLOT: u32 = 1u;       // counters slot holding the count (nerf_gpu::layout)
const MAX_K: u32 = 10u;        // up to 1024 items per workgroup
const MAX_Z: u32 = 32u;        // up to 32 workgroups along z
const MAX_GROUPS: u32 = 65535u;

@group(0) @binding(0) var<storage, read> counters: array<u32>;
@group(0) @binding(1) var<storage, read> cap: array<u32>;
@group(0) @binding(2) var<storage, read_write> args: array<u32>;

// ceil(a / b) without overflow for any a (b > 0).
fn ceil_div(a: u32, b: u32) -> u32 {
    return a / b + select(0u, 1u, a % b != 0u);
}

@compute @workgroup_size(64)
fn dispatch_args(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= MAX_Z * (MAX_K + 1u)) {
        return;
    }
    let k = e % (MAX_K + 1u);
    let z = e / (MAX_K + 1u) + 1u;
    let n = min(counters[SLOT], cap[0]);
    let g = ceil_div(n, 1u << k);
    var x = g;
    var y = 1u;
    if (g > MAX_GROUPS) {
        y = ceil_div(g, MAX_GROUPS);
        x = ceil_div(g, y);
    }
    args[3u * e] = x;
    args[3u * e + 1u] = y;
    args[3u * e + 2u] = z;
}
