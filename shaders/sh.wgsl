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

// Column j of d_sh's row at o, or 0 past the od = DEGREE² columns.
fn sh_col(o: u32, j: u32, od: u32) -> f32 {
    if (j < od) {
        return d_sh[o + j];
    }
    return 0.0;
}

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
    // gk = d_sh·constant per SH column (columns past DEGREE² read as 0), named, not an array: see
    // the no-function-memory-arrays rule in crates/gpu/tests/kernels.rs.
    let g1 = sh_col(o, 1u, od) * -0.4886025119029199;
    let g2 = sh_col(o, 2u, od) * 0.4886025119029199;
    let g3 = sh_col(o, 3u, od) * -0.4886025119029199;
    let g4 = sh_col(o, 4u, od) * 1.0925484305920792;
    let g5 = sh_col(o, 5u, od) * -1.0925484305920792;
    let g6 = sh_col(o, 6u, od) * 0.31539156525252005;
    let g7 = sh_col(o, 7u, od) * -1.0925484305920792;
    let g8 = sh_col(o, 8u, od) * 0.5462742152960396;
    let g9 = sh_col(o, 9u, od) * -0.5900435899266435;
    let g10 = sh_col(o, 10u, od) * 2.890611442640554;
    let g11 = sh_col(o, 11u, od) * -0.4570457994644658;
    let g12 = sh_col(o, 12u, od) * 0.3731763325901154;
    let g13 = sh_col(o, 13u, od) * -0.4570457994644658;
    let g14 = sh_col(o, 14u, od) * 1.445305721320277;
    let g15 = sh_col(o, 15u, od) * -0.5900435899266435;
    var dx = 0.0;
    var dy = 0.0;
    var dz = 0.0;
    if (DEGREE > 1u) {
        dy += g1;
        dz += g2;
        dx += g3;
    }
    if (DEGREE > 2u) {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        // xy
        dx += g4 * y;
        dy += g4 * x;
        // yz
        dy += g5 * z;
        dz += g5 * y;
        // 2zz − xx − yy
        dx -= g6 * 2.0 * x;
        dy -= g6 * 2.0 * y;
        dz += g6 * 4.0 * z;
        // xz
        dx += g7 * z;
        dz += g7 * x;
        // xx − yy
        dx += g8 * 2.0 * x;
        dy -= g8 * 2.0 * y;
        if (DEGREE > 3u) {
            // y(3xx − yy)
            dx += g9 * 6.0 * x * y;
            dy += g9 * 3.0 * (xx - yy);
            // xyz
            dx += g10 * y * z;
            dy += g10 * x * z;
            dz += g10 * x * y;
            // y(4zz − xx − yy)
            dx -= g11 * 2.0 * x * y;
            dy += g11 * (4.0 * zz - xx - 3.0 * yy);
            dz += g11 * 8.0 * y * z;
            // z(2zz − 3xx − 3yy)
            dx -= g12 * 6.0 * x * z;
            dy -= g12 * 6.0 * y * z;
            dz += g12 * (6.0 * zz - 3.0 * xx - 3.0 * yy);
            // x(4zz − xx − yy)
            dx += g13 * (4.0 * zz - 3.0 * xx - yy);
            dy -= g13 * 2.0 * x * y;
            dz += g13 * 8.0 * x * z;
            // z(xx − yy)
            dx += g14 * 2.0 * x * z;
            dy -= g14 * 2.0 * y * z;
            dz += g14 * (xx - yy);
            // x(xx − 3yy)
            dx += g15 * 3.0 * (xx - yy);
            dy -= g15 * 6.0 * x * y;
        }
    }
    d_dirs[3u * i] = dx;
    d_dirs[3u * i + 1u] = dy;
    d_dirs[3u * i + 2u] = dz;
}
