// Real spherical-harmonics encoding of view directions: forward, and the gradient w.r.t. the
// directions (sh_input_grad).
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

// ---- Gradient w.r.t. the directions (camera pose refinement) ----
// CPU twin: SphericalHarmonics::backward(dirs, d_sh, &mut [], Some(d_dirs)) (backward_chunk): the
// polynomials above differentiated as written (directions as-is: no renormalisation, no [0, 1]
// mapping), with gk = d_sh·constant and the terms added in the CPU's order.
// Layouts: dirs [n][3]; d_sh row k at d_sh[k·G.x + G.y + j], j < DEGREE² (G.x = stride ≥ G.y +
// DEGREE², G.y = offset: the SH columns of a wider row, e.g. the colour net's input gradient);
// d_dirs [n][3], OVERWRITTEN for i < n (zeros for DEGREE = 1), rows past n untouched.
// Launch: groups_1d(capacity, WG), one invocation per sample.
@group(0) @binding(3) var<uniform> G: vec4<u32>;
@group(0) @binding(4) var<storage, read> d_sh: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_dirs: array<f32>;

@compute @workgroup_size(WG)
fn sh_input_grad(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, WG);
    let od = DEGREE * DEGREE;
    let stride = G.x;
    let off = G.y;
    // Rows of d_sh whose SH columns lie within the bound buffer.
    let len = arrayLength(&d_sh);
    var rows = 0u;
    if (len >= off + od) {
        rows = (len - off - od) / stride + 1u;
    }
    let n = min(min(counters[1], rows), min(arrayLength(&dirs) / 3u, arrayLength(&d_dirs) / 3u));
    if (i >= n) {
        return;
    }
    let x = dirs[3u * i];
    let y = dirs[3u * i + 1u];
    let z = dirs[3u * i + 2u];
    let o = i * stride + off;
    var gk: array<f32, 16>;
    let k = array<f32, 16>(
        0.28209479177387814, -0.4886025119029199, 0.4886025119029199, -0.4886025119029199,
        1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
        0.5462742152960396, -0.5900435899266435, 2.890611442640554, -0.4570457994644658,
        0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
    );
    for (var j = 0u; j < od; j++) {
        gk[j] = d_sh[o + j] * k[j];
    }
    var dx = 0.0;
    var dy = 0.0;
    var dz = 0.0;
    if (DEGREE > 1u) {
        dy += gk[1];
        dz += gk[2];
        dx += gk[3];
    }
    if (DEGREE > 2u) {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        // xy
        dx += gk[4] * y;
        dy += gk[4] * x;
        // yz
        dy += gk[5] * z;
        dz += gk[5] * y;
        // 2zz − xx − yy
        dx -= gk[6] * 2.0 * x;
        dy -= gk[6] * 2.0 * y;
        dz += gk[6] * 4.0 * z;
        // xz
        dx += gk[7] * z;
        dz += gk[7] * x;
        // xx − yy
        dx += gk[8] * 2.0 * x;
        dy -= gk[8] * 2.0 * y;
        if (DEGREE > 3u) {
            // y(3xx − yy)
            dx += gk[9] * 6.0 * x * y;
            dy += gk[9] * 3.0 * (xx - yy);
            // xyz
            dx += gk[10] * y * z;
            dy += gk[10] * x * z;
            dz += gk[10] * x * y;
            // y(4zz − xx − yy)
            dx -= gk[11] * 2.0 * x * y;
            dy += gk[11] * (4.0 * zz - xx - 3.0 * yy);
            dz += gk[11] * 8.0 * y * z;
            // z(2zz − 3xx − 3yy)
            dx -= gk[12] * 6.0 * x * z;
            dy -= gk[12] * 6.0 * y * z;
            dz += gk[12] * (6.0 * zz - 3.0 * xx - 3.0 * yy);
            // x(4zz − xx − yy)
            dx += gk[13] * (4.0 * zz - 3.0 * xx - yy);
            dy -= gk[13] * 2.0 * x * y;
            dz += gk[13] * 8.0 * x * z;
            // z(xx − yy)
            dx += gk[14] * 2.0 * x * z;
            dy -= gk[14] * 2.0 * y * z;
            dz += gk[14] * (xx - yy);
            // x(xx − 3yy)
            dx += gk[15] * 3.0 * (xx - yy);
            dy -= gk[15] * 6.0 * x * y;
        }
    }
    d_dirs[3u * i] = dx;
    d_dirs[3u * i + 1u] = dy;
    d_dirs[3u * i + 2u] = dz;
}
