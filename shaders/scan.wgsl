// Exclusive prefix sums of u32 (multi-level, any length up to 2^30). Host side: nerf_gpu::sampling::GpuScan.
// CPU twin: the obvious running sum (out[i] = Σ_{j<i} in[j]; out[len] = total).
//
// One workgroup scans a block of 1024 values (256 invocations × 4) in workgroup memory
// (coalesced loads, Hillis–Steele over the 256 per-invocation sums) and writes the block's total
// to `sums` (the next level), which is scanned the same way in place (`scan_inplace`); `scan_add`
// then adds each block's scanned offset back, level by level.
//
// Level 0 (`scan_block`): values i < n_input (n_input = len, or min(len, counters[slot]) when
// `dynamic_n` is set) are read from `scan_in`, values n_input ≤ i < n are 0; n = len + 1, so
// scan_out[len] receives the total.

const WG: u32 = 256u;
const BLOCK: u32 = 1024u;

struct ScanParams {
    n: u32,          // values scanned at this level
    n_input: u32,    // values read (the rest are 0)
    dynamic_n: u32,  // 1: n_input = min(n_input, counters[slot])
    has_sums: u32,   // 1: write block totals to scan_sums
    slot: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> SP: ScanParams;
@group(0) @binding(1) var<storage, read> scan_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> scan_out: array<u32>;
@group(0) @binding(3) var<storage, read_write> scan_sums: array<u32>;
@group(0) @binding(4) var<storage, read> scan_counters: array<u32>;
@group(0) @binding(5) var<storage, read_write> scan_data: array<u32>;

var<workgroup> sh: array<u32, 1024>;
var<workgroup> part: array<u32, 256>;

fn block_id(wid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wid.x + wid.y * nwg.x;
}

// Scans sh[0..1024) in place (exclusive) and returns the block total. All invocations call it.
fn scan_shared(t: u32) -> u32 {
    let a = sh[4u * t];
    let b = sh[4u * t + 1u];
    let c = sh[4u * t + 2u];
    let d = sh[4u * t + 3u];
    let local = a + b + c + d;
    part[t] = local;
    for (var off = 1u; off < WG; off = off << 1u) {
        workgroupBarrier();
        var v = part[t];
        if (t >= off) {
            v = v + part[t - off];
        }
        workgroupBarrier();
        part[t] = v;
    }
    workgroupBarrier();
    let excl = part[t] - local;
    sh[4u * t] = excl;
    sh[4u * t + 1u] = excl + a;
    sh[4u * t + 2u] = excl + a + b;
    sh[4u * t + 3u] = excl + a + b + c;
    let total = part[WG - 1u];
    workgroupBarrier();
    return total;
}

@compute @workgroup_size(WG)
fn scan_block(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let blk = block_id(wid, nwg);
    let base = blk * BLOCK;
    if (base >= SP.n) {
        return;
    }
    var n_in = SP.n_input;
    if (SP.dynamic_n != 0u) {
        n_in = min(n_in, scan_counters[SP.slot]);
    }
    for (var k = 0u; k < 4u; k = k + 1u) {
        let i = base + k * WG + t;
        var x = 0u;
        if (i < n_in) {
            x = scan_in[i];
        }
        sh[k * WG + t] = x;
    }
    workgroupBarrier();
    let total = scan_shared(t);
    for (var k = 0u; k < 4u; k = k + 1u) {
        let i = base + k * WG + t;
        if (i < SP.n) {
            scan_out[i] = sh[k * WG + t];
        }
    }
    if (t == 0u && SP.has_sums != 0u) {
        scan_sums[blk] = total;
    }
}

@compute @workgroup_size(WG)
fn scan_inplace(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let blk = block_id(wid, nwg);
    let base = blk * BLOCK;
    if (base >= SP.n) {
        return;
    }
    for (var k = 0u; k < 4u; k = k + 1u) {
        let i = base + k * WG + t;
        var x = 0u;
        if (i < SP.n) {
            x = scan_data[i];
        }
        sh[k * WG + t] = x;
    }
    workgroupBarrier();
    let total = scan_shared(t);
    for (var k = 0u; k < 4u; k = k + 1u) {
        let i = base + k * WG + t;
        if (i < SP.n) {
            scan_data[i] = sh[k * WG + t];
        }
    }
    if (t == 0u && SP.has_sums != 0u) {
        scan_sums[blk] = total;
    }
}

// scan_data[i] += scan_sums[i / BLOCK] for i < n (blocks ≥ 1 only; block 0 adds 0).
@compute @workgroup_size(WG)
fn scan_add(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    if (i >= SP.n || i < BLOCK) {
        return;
    }
    scan_data[i] = scan_data[i] + scan_sums[i / BLOCK];
}
