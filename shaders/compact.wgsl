// Compaction of packed samples to those compositing reaches (training on compacted samples, as
// instant-ngp): after an inference pass (σ of every marched sample), each ray keeps its leading
// samples up to the one before which the transmittance falls below `t_threshold`; the training
// forward and backward then run on the kept samples only. One invocation per ray.
// CPU twins: nerf_render::composited_counts (the counts) and nerf_sampling::RaySamples::compact_into
// (the copy, with the same clipping at the output capacity). Host side: nerf_gpu::compact::GpuCompactor,
// which records
//   compact_count  (counts[r] for r < n_rays = min(src_counters[0], cap_rays))
//   GpuScan        (exclusive scan of the counts → raw offsets, raw[cap_rays] = total)
//   compact_fill   (out offsets = min(raw, cap_out); out_counters = [n_rays, min(total, cap_out)];
//                   positions, dirs, t, dt of the kept samples copied to their new places,
//                   and each kept sample's row in the source batch: out_rows).
// A field that kept per-sample values of its density pass (the hash field's encodings) gathers
// them for the kept samples with compact_gather (nerf_gpu::compact::GpuRowGather; CPU twin: a
// gather by nerf_sampling::compacted_rows).
//
// The stop rule is composite.wgsl's, with the same arithmetic (T ← T·(1 + (exp(−σδ) − 1)),
// checked before each sample), so a count ends exactly where the GPU's compositing stops.

const WG: u32 = 64u;

struct CompactParams {
    cap_rays: u32,
    cap_out: u32,
    t_threshold: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> P: CompactParams;
@group(0) @binding(1) var<storage, read> src_counters: array<u32>;     // [0] = n_rays
@group(0) @binding(2) var<storage, read> src_offsets: array<u32>;      // cap_rays + 1
@group(0) @binding(3) var<storage, read> sigma: array<f32>;            // [S]
@group(0) @binding(4) var<storage, read> src_dt: array<f32>;           // [S]
@group(0) @binding(5) var<storage, read_write> counts: array<u32>;     // [cap_rays]
@group(0) @binding(6) var<storage, read> raw_offsets: array<u32>;      // [cap_rays + 1]
@group(0) @binding(7) var<storage, read> src_positions: array<f32>;    // [S][3]
@group(0) @binding(8) var<storage, read> src_dirs: array<f32>;         // [S][3]
@group(0) @binding(9) var<storage, read> src_t: array<f32>;            // [S]
@group(0) @binding(10) var<storage, read_write> out_counters: array<u32>;
@group(0) @binding(11) var<storage, read_write> out_offsets: array<u32>;   // cap_rays + 1
@group(0) @binding(12) var<storage, read_write> out_positions: array<f32>; // [cap_out][3]
@group(0) @binding(13) var<storage, read_write> out_dirs: array<f32>;
@group(0) @binding(14) var<storage, read_write> out_t: array<f32>;
@group(0) @binding(15) var<storage, read_write> out_dt: array<f32>;
@group(0) @binding(16) var<storage, read_write> out_rows: array<u32>;      // [cap_out]
// compact_gather: rows of ROW_FLOATS f32 from gather_src (indexed by out_rows) to gather_dst;
// copy_rows: the out_counters[1] rows from row C.src_row of gather_src to row C.dst_row of gather_dst.
@group(0) @binding(17) var<storage, read> gather_src: array<f32>;          // [S][ROW_FLOATS]
@group(0) @binding(18) var<storage, read_write> gather_dst: array<f32>;    // [cap_out][ROW_FLOATS]

override ROW_FLOATS: u32 = 1u;

struct RowCopyParams {
    src_row: u32,
    dst_row: u32,
    _pad0: u32,
    _pad1: u32,
}
@group(0) @binding(19) var<uniform> C: RowCopyParams;

fn n_rays() -> u32 {
    return min(src_counters[0], P.cap_rays);
}

// Pass 1: samples each ray keeps.
@compute @workgroup_size(WG)
fn compact_count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r >= n_rays()) {
        return;
    }
    let s0 = src_offsets[r];
    let s1 = src_offsets[r + 1u];
    var trans = 1.0;
    var k = s0;
    loop {
        if (k >= s1 || (P.t_threshold > 0.0 && trans < P.t_threshold)) {
            break;
        }
        let em1 = exp(-sigma[k] * src_dt[k]) - 1.0;
        trans = trans * (1.0 + em1);
        k = k + 1u;
    }
    counts[r] = k - s0;
}

// Pass 3 (after the scan): clipped offsets, the counters, the kept samples. Launched for
// cap_rays + 1 invocations.
@compute @workgroup_size(WG)
fn compact_fill(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    if (r > P.cap_rays) {
        return;
    }
    let start = min(raw_offsets[r], P.cap_out);
    out_offsets[r] = start;
    let n = n_rays();
    if (r == 0u) {
        out_counters[0] = src_counters[0];
        out_counters[1] = min(raw_offsets[P.cap_rays], P.cap_out);
    }
    if (r >= n) {
        return;
    }
    let end = min(raw_offsets[r + 1u], P.cap_out);
    let first = src_offsets[r];
    for (var j = 0u; start + j < end; j = j + 1u) {
        let a = first + j;
        let b = start + j;
        out_positions[3u * b] = src_positions[3u * a];
        out_positions[3u * b + 1u] = src_positions[3u * a + 1u];
        out_positions[3u * b + 2u] = src_positions[3u * a + 2u];
        out_dirs[3u * b] = src_dirs[3u * a];
        out_dirs[3u * b + 1u] = src_dirs[3u * a + 1u];
        out_dirs[3u * b + 2u] = src_dirs[3u * a + 2u];
        out_t[b] = src_t[a];
        out_dt[b] = src_dt[a];
        out_rows[b] = a;
    }
}

// Gathers the rows of the out_counters[1] kept samples: gather_dst[b][j] = gather_src[out_rows[b]][j].
// One invocation per float (consecutive invocations copy consecutive floats of a row).
@compute @workgroup_size(WG)
fn compact_gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let b = i / ROW_FLOATS;
    if (b >= out_counters[1]) {
        return;
    }
    let j = i - b * ROW_FLOATS;
    gather_dst[i] = gather_src[out_rows[b] * ROW_FLOATS + j];
}

// Copies the out_counters[1] rows of a chunk between buffers at row offsets: gather_dst[C.dst_row
// + b][j] = gather_src[C.src_row + b][j] (CPU twin: a slice copy). What a buffer copy of the
// chunk's whole capacity did, for the rows the batch has: a chunked density pass whose later
// chunks are empty or partly filled moves only their samples. One invocation per float.
@compute @workgroup_size(WG)
fn copy_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let b = i / ROW_FLOATS;
    if (b >= out_counters[1]) {
        return;
    }
    let j = i - b * ROW_FLOATS;
    gather_dst[(C.dst_row + b) * ROW_FLOATS + j] = gather_src[(C.src_row + b) * ROW_FLOATS + j];
}
