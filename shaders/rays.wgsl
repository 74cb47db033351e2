// Training rays drawn on the device from the training images (one invocation per ray).
// CPU twin: nerf_gpu::sampling::ray_batch_cpu (built on nerf_rays::Camera::ray_at and nerf_data's
// compositing rule). Host side: crates/gpu/src/sampling.rs (GpuImages, GpuRayGen, GpuRays).
//
// Ray r < n_rays = min(counters[0], capacity) picks, with the counter-based generator of
// common.wgsl (streams = the RAY_STREAM_* constants of sampling.rs):
//   view = rand_u32(seed, 0x52410001, r) % n_views
//   col  = rand_u32(seed, 0x52410002, r) % width,  row = rand_u32(seed, 0x52410003, r) % height
// or, with training masks (I.n_kept > 0), the k-th kept pixel of the dataset (views in order):
//   k = rand_below(seed, 0x52410001, r, n_kept)  (common.wgsl's multiply-high index: even over
//   the range where n_kept runs to 10⁹), view = the last v with start[v] ≤ k (binary search),
//   row·W + col = k − start[v] for a view that keeps every pixel, else list[k − start[v]].
// masks: per view (start, list) — kept pixels of the views before it, and the offset in `masks`
// of its ascending kept pixels or 0xffffffff when it keeps every pixel — then those lists
// (nerf_data::PixelMasks::pick is the CPU twin).
//   (u, v) = (col + off, row + off), off = 0.5 (pixel centres) or 0 (integer convention);
//   with jitter u = col + off − ½ + rand_f32(seed, 0x52410004, r), v likewise with 0x52410005.
// Direction: R·[(u − cx)/fx, −(v − cy)/fy, −1], normalised (OpenGL camera, as nerf_rays), or
// through the camera's lens (Cam.size.w: 1 OpenCV's radial–tangential, 2 its fisheye, 3
// Fisheye624, 4 COLMAP's FOV) the direction it saw at (u, v): nerf_rays::Camera::camera_dir,
// whose UNDISTORT_ITERATIONS (10) Newton steps (twice for Fisheye624; FOV's closed form)
// camera_dir runs here in f32.
// NDC scenes (I.ndc = 1): the ray is then warped as nerf_rays::Ndc::ray_or_miss (nerf-pytorch's
// ndc_rays, unit direction; a ray with d_z ≥ 0 becomes the miss ray (0, 0, 2) + t·(0, 0, 1)).
// Background: white, black, or (random) rand_f32(seed, 0x52410006 + c, r) per channel c.
// Target: rgb·a + (1 − a)·bg (straight alpha, as nerf_data).
//
// Layouts: cameras = array<Cam> (one per view, see Cam); pixels = one u32 per pixel, RGBA8
// (r | g<<8 | b<<16 | a<<24, value/255) when format == 1, or two u32 per pixel, RGBA16
// (r | g<<16, b | a<<16, value/65535) when format == 2; pixel (col, row) of a view is pixel
// `pixel_offset + row·width + col`. Outputs: origins, dirs (unit), target, background: [R][3] f32;
// with depth maps (I.has_depth = 1), the pixel's measured distance along its ray (0: none) in
// out_depth_target[r] (the depth map is nerf_data::Dataset::depths, laid out as the pixels).

const WG: u32 = 64u;

struct RayGenParams {
    seed: u32,
    background: u32,   // 0 white, 1 black, 2 random
    jitter: u32,       // 1: sub-pixel jitter
    pixel_offset: f32, // 0.5 (centre) or 0 (integer)
}

struct ImagesInfo {
    n_views: u32,
    format: u32,       // 1 RGBA8, 2 RGBA16
    ndc: u32,          // 1: warp rays to NDC
    ndc_near: f32,     // near plane distance n
    ndc_sx: f32,       // 2·fx / W
    ndc_sy: f32,       // 2·fy / H
    n_kept: u32,       // kept pixels of the training masks (0: no masks)
    has_depth: u32,    // 1: depth maps, one f32 per pixel laid out as `pixels`
}

// Camera-to-world 3×4 rows (rotation row a, then position a), intrinsics, size and lens.
struct Cam {
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    intr: vec4<f32>,   // fx, fy, cx, cy
    size: vec4<u32>,   // width, height, pixel_offset, lens (0 none, 1 radial–tangential, 2 fisheye, 3 Fisheye624, 4 FOV, 5 division, 6 EUCM)
    k: vec4<f32>,      // k1, k2, k3, k4 (FOV: ω, 0, 0, 0)
    kp: vec4<f32>,     // k5, k6, p1, p2
    s: vec4<f32>,      // s1, s2, s3, s4
}

@group(0) @binding(0) var<uniform> P: RayGenParams;
@group(0) @binding(1) var<uniform> I: ImagesInfo;
@group(0) @binding(2) var<storage, read> counters: array<u32>;
@group(0) @binding(3) var<storage, read> cams: array<Cam>;
@group(0) @binding(4) var<storage, read> pixels: array<u32>;
@group(0) @binding(5) var<storage, read_write> out_origins: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_dirs: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_target: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_background: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_view: array<u32>;
@group(0) @binding(10) var<storage, read> masks: array<u32>;         // 2·n_views table, then lists
@group(0) @binding(11) var<storage, read> depths: array<f32>;        // per pixel (has_depth)
@group(0) @binding(12) var<storage, read_write> out_depth_target: array<f32>;

// nerf_rays::Ndc::ray_or_miss: (origin, unit direction) of the NDC ray.
fn ndc_ray(o_in: vec3<f32>, d: vec3<f32>) -> array<vec3<f32>, 2> {
    if (!(d.z < 0.0)) {
        return array<vec3<f32>, 2>(vec3<f32>(0.0, 0.0, 2.0), vec3<f32>(0.0, 0.0, 1.0));
    }
    let n = I.ndc_near;
    let t = -(n + o_in.z) / d.z;
    let o = o_in + t * d;
    let on = vec3<f32>(-I.ndc_sx * o.x / o.z, -I.ndc_sy * o.y / o.z, 1.0 + 2.0 * n / o.z);
    let dn = vec3<f32>(-I.ndc_sx * (d.x / d.z - o.x / o.z), -I.ndc_sy * (d.y / d.z - o.y / o.z), -2.0 * n / o.z);
    return array<vec3<f32>, 2>(on, normalize(dn));
}

// nerf_rays::Distortion::radial: the radial factor R at ρ² and dR/d(ρ²), rational for the
// radial–tangential lens, a polynomial in θ² for the fisheyes.
fn lens_radial(cam: Cam, r2: f32) -> vec2<f32> {
    let k = cam.k;
    let k5 = cam.kp.x;
    let k6 = cam.kp.y;
    if (cam.size.w == 1u) {
        let n = 1.0 + r2 * (k.x + r2 * (k.y + r2 * k.z));
        let dn = k.x + r2 * (2.0 * k.y + r2 * 3.0 * k.z);
        let d = 1.0 + r2 * (k.w + r2 * (k5 + r2 * k6));
        let dd = k.w + r2 * (2.0 * k5 + r2 * 3.0 * k6);
        return vec2<f32>(n / d, (dn * d - n * dd) / (d * d));
    }
    let r = 1.0 + r2 * (k.x + r2 * (k.y + r2 * (k.z + r2 * (k.w + r2 * (k5 + r2 * k6)))));
    let dr = k.x + r2 * (2.0 * k.y + r2 * (3.0 * k.z + r2 * (4.0 * k.w + r2 * (5.0 * k5 + r2 * 6.0 * k6))));
    return vec2<f32>(r, dr);
}

// nerf_rays::Distortion::stage: the radial factor and/or the tangential and thin-prism terms
// on the point q, and the Jacobian (columns: ∂/∂a, ∂/∂b).
struct LensStage {
    f: vec2<f32>,
    j: mat2x2<f32>,
}

fn lens_stage(cam: Cam, q: vec2<f32>, radial: bool, tangential: bool) -> LensStage {
    var out = LensStage(q, mat2x2<f32>(1.0, 0.0, 0.0, 1.0));
    let a = q.x;
    let b = q.y;
    let r2 = a * a + b * b;
    if (radial) {
        let rd = lens_radial(cam, r2);
        out.f = q * rd.x;
        let ab = 2.0 * a * b * rd.y;
        out.j = mat2x2<f32>(rd.x + 2.0 * a * a * rd.y, ab, ab, rd.x + 2.0 * b * b * rd.y);
    }
    if (tangential) {
        let p1 = cam.kp.z;
        let p2 = cam.kp.w;
        let s = cam.s;
        let ab = a * b;
        out.f = out.f + vec2<f32>(
            2.0 * p1 * ab + p2 * (r2 + 2.0 * a * a) + r2 * (s.x + r2 * s.y),
            p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * ab + r2 * (s.z + r2 * s.w),
        );
        let sx = 2.0 * (s.x + 2.0 * s.y * r2);
        let sy = 2.0 * (s.z + 2.0 * s.w * r2);
        out.j = out.j + mat2x2<f32>(
            2.0 * p1 * b + 6.0 * p2 * a + a * sx, 2.0 * p1 * a + 2.0 * p2 * b + a * sy,
            2.0 * p1 * a + 2.0 * p2 * b + b * sx, 6.0 * p1 * b + 2.0 * p2 * a + b * sy,
        );
    }
    return out;
}

// nerf_rays::Distortion::newton: the point the stage takes to `goal`, by 10 Newton steps
// from `goal` itself.
fn lens_newton(cam: Cam, goal: vec2<f32>, radial: bool, tangential: bool) -> vec2<f32> {
    var q = goal;
    for (var i = 0u; i < 10u; i = i + 1u) {
        let st = lens_stage(cam, q, radial, tangential);
        let e = st.f - goal;
        let det = determinant(st.j);
        if (!(abs(det) > 1e-12)) {
            break;
        }
        // J⁻¹·e with J = [[a, b], [c, d]] (columns (a, c), (b, d)).
        let ja = st.j[0][0];
        let jc = st.j[0][1];
        let jb = st.j[1][0];
        let jd = st.j[1][1];
        q = q - vec2<f32>(jd * e.x - jb * e.y, ja * e.y - jc * e.x) / det;
    }
    return q;
}

// nerf_rays::Camera::camera_dir: the direction, in OpenGL camera axes, of image point (u, v)
// (z = −1 without a lens or through a radial–tangential one, unit through a fisheye).
fn camera_dir(cam: Cam, u: f32, v: f32) -> vec3<f32> {
    let xd = (u - cam.intr.z) / cam.intr.x;
    let yd = (v - cam.intr.w) / cam.intr.y;
    let lens = cam.size.w;
    if (lens == 0u) {
        return vec3<f32>(xd, -yd, -1.0);
    }
    if (lens == 4u) {
        // COLMAP's FOV lens, inverted in closed form: ρ = tan(ρ_d·ω) / (2·tan(ω/2)).
        let omega = cam.k.x;
        let rho_d = sqrt(xd * xd + yd * yd);
        var s = 1.0;
        if (omega != 0.0) {
            let c = 2.0 * tan(0.5 * omega);
            if (rho_d < 1e-12) {
                s = omega / c;
            } else {
                s = tan(rho_d * omega) / (c * rho_d);
            }
        }
        return vec3<f32>(xd * s, -yd * s, -1.0);
    }
    if (lens == 6u) {
        // COLMAP's EUCM lens, inverted in closed form: the unit direction of (x_d, y_d, m_z),
        // m_z = (1 − β·α²·r²) / (α·√(1 − (2α − 1)·β·r²) + 1 − α) (past 90° off the axis too).
        let a = cam.k.x;
        let b = cam.k.y;
        let r2 = xd * xd + yd * yd;
        let mz = (1.0 - b * a * a * r2) / (a * sqrt(max(1.0 - (2.0 * a - 1.0) * b * r2, 0.0)) + 1.0 - a);
        let n = normalize(vec3<f32>(xd, yd, mz));
        return vec3<f32>(n.x, -n.y, -n.z);
    }
    if (lens == 5u) {
        // COLMAP's division lens, inverted in closed form: p = p_d / (1 + k1·ρ_d²).
        let s = 1.0 / (1.0 + cam.k.x * (xd * xd + yd * yd));
        return vec3<f32>(xd * s, -yd * s, -1.0);
    }
    let tangential = any(cam.kp.zw != vec2<f32>(0.0)) || any(cam.s != vec4<f32>(0.0));
    var q: vec2<f32>;
    if (lens == 3u && tangential) {
        // Fisheye624: its tangential terms act on the radially distorted point.
        q = lens_newton(cam, lens_newton(cam, vec2<f32>(xd, yd), false, true), true, false);
    } else {
        q = lens_newton(cam, vec2<f32>(xd, yd), true, tangential);
    }
    if (lens == 1u) {
        return vec3<f32>(q.x, -q.y, -1.0);
    }
    // A fisheye's equidistant point: θ = |q| off the axis.
    let theta = length(q);
    var s = 1.0;
    if (theta >= 1e-12) {
        s = sin(theta) / theta;
    }
    return vec3<f32>(q.x * s, -q.y * s, -cos(theta));
}

fn texel(pix: u32) -> vec4<f32> {
    if (I.format == 1u) {
        let w = pixels[pix];
        return vec4<f32>(f32(w & 255u), f32((w >> 8u) & 255u), f32((w >> 16u) & 255u), f32(w >> 24u)) / 255.0;
    }
    let a = pixels[2u * pix];
    let b = pixels[2u * pix + 1u];
    return vec4<f32>(f32(a & 65535u), f32(a >> 16u), f32(b & 65535u), f32(b >> 16u)) / 65535.0;
}

@compute @workgroup_size(WG)
fn ray_gen(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, WG);
    let n = min(counters[0], arrayLength(&out_origins) / 3u);
    if (r >= n) {
        return;
    }
    var view: u32;
    var col: u32;
    var row: u32;
    if (I.n_kept == 0u) {
        view = rand_u32(P.seed, 0x52410001u, r) % I.n_views;
        col = rand_u32(P.seed, 0x52410002u, r) % cams[view].size.x;
        row = rand_u32(P.seed, 0x52410003u, r) % cams[view].size.y;
    } else {
        let k = rand_below(P.seed, 0x52410001u, r, I.n_kept);
        // Invariant: start[lo] ≤ k < start[hi] (start[n_views] = n_kept).
        var lo = 0u;
        var hi = I.n_views;
        while (hi - lo > 1u) {
            let mid = (lo + hi) / 2u;
            if (masks[2u * mid] <= k) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        view = lo;
        var p = k - masks[2u * lo];
        let list = masks[2u * lo + 1u];
        if (list != 0xffffffffu) {
            p = masks[list + p];
        }
        col = p % cams[view].size.x;
        row = p / cams[view].size.x;
    }
    let cam = cams[view];
    let w = cam.size.x;
    var u = f32(col) + P.pixel_offset;
    var v = f32(row) + P.pixel_offset;
    if (P.jitter != 0u) {
        u = u - 0.5 + rand_f32(P.seed, 0x52410004u, r);
        v = v - 0.5 + rand_f32(P.seed, 0x52410005u, r);
    }
    let dc = camera_dir(cam, u, v);
    let dw = vec3<f32>(
        cam.r0.x * dc.x + cam.r0.y * dc.y + cam.r0.z * dc.z,
        cam.r1.x * dc.x + cam.r1.y * dc.y + cam.r1.z * dc.z,
        cam.r2.x * dc.x + cam.r2.y * dc.y + cam.r2.z * dc.z,
    );
    var dir = dw * (1.0 / sqrt(dot(dw, dw)));
    var bg = vec3<f32>(1.0);
    if (P.background == 1u) {
        bg = vec3<f32>(0.0);
    } else if (P.background == 2u) {
        bg = vec3<f32>(rand_f32(P.seed, 0x52410006u, r), rand_f32(P.seed, 0x52410007u, r), rand_f32(P.seed, 0x52410008u, r));
    }
    let px = texel(cam.size.z + row * w + col);
    let a = px.w;
    let tgt = px.xyz * a + (1.0 - a) * bg;
    var o = vec3<f32>(cam.r0.w, cam.r1.w, cam.r2.w);
    if (I.ndc != 0u) {
        let w = ndc_ray(o, dir);
        o = w[0];
        dir = w[1];
    }
    for (var c = 0u; c < 3u; c = c + 1u) {
        out_origins[3u * r + c] = o[c];
        out_dirs[3u * r + c] = dir[c];
        out_target[3u * r + c] = tgt[c];
        out_background[3u * r + c] = bg[c];
    }
    out_view[r] = view;
    if (I.has_depth != 0u) {
        out_depth_target[r] = depths[cam.size.z + row * w + col];
    }
}
