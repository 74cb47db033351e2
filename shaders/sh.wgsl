// Real spherical-harmonics encoding of view directions, forward only.
// CPU twin: nerf_encoding::SphericalHarmonics (crates/encoding/src/sh.rs): HashNeRF's SHEncoder
// order, signs, constants and polynomials (directions used as-is, no renormalisation).
// Host side: nerf_gpu::encoding::GpuSphericalHarmonics.
//
// Layouts: counters array<u32> (counters[1] = n samples); dirs [n][3] f32; out [n][DEGREE²] f32.
// Launch: groups_1d(capacity, WG), one invocation per sample; i >= n returns.

// Number of bands (1..=4): DEGREE² outputs per sample.
override DEGREE: u32 = 4u;
override WG: u32 = 128u;

@group(0) @binding(0) var<storage, read> counters: array<u32>;
@group(0) @binding(1) var<storage, read> dirs: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(WG)
fn sh_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let od = DEGREE * DEGREE;
    let n = min(counters[1], min(arrayLength(&dirs) / 3u, arrayLength(&out) / od));
    if (i >= n) {
        return;
    }
    let x = dirs[3u * i];
    let y = dirs[3u * i + 1u];
    let z = dirs[3u * i + 2u];
    let o = i * od;
    out[o] = 0.28209479177387814;
    if (DEGREE > 1u) {
        out[o + 1u] = -0.4886025119029199 * y;
        out[o + 2u] = 0.4886025119029199 * z;
        out[o + 3u] = -0.4886025119029199 * x;
    }
    if (DEGREE > 2u) {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        out[o + 4u] = 1.0925484305920792 * x * y;
        out[o + 5u] = -1.0925484305920792 * y * z;
        out[o + 6u] = 0.31539156525252005 * (2.0 * zz - xx - yy);
        out[o + 7u] = -1.0925484305920792 * x * z;
        out[o + 8u] = 0.5462742152960396 * (xx - yy);
        if (DEGREE > 3u) {
            out[o + 9u] = -0.5900435899266435 * y * (3.0 * xx - yy);
            out[o + 10u] = 2.890611442640554 * x * y * z;
            out[o + 11u] = -0.4570457994644658 * y * (4.0 * zz - xx - yy);
            out[o + 12u] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            out[o + 13u] = -0.4570457994644658 * x * (4.0 * zz - xx - yy);
            out[o + 14u] = 1.445305721320277 * z * (xx - yy);
            out[o + 15u] = -0.5900435899266435 * x * (xx - 3.0 * yy);
        }
    }
}
