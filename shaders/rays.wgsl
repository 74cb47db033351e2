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
// through the camera's lens (Cam.size.w: 1 OpenCV's radial–tangential, 2 its fisheye) the
// direction it saw at (u, v): nerf_rays::Camera::camera_dir, whose UNDISTORT_ITERATIONS (10)
// Newton steps camera_dir runs here in f32.
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
    size: vec4<u32>,   // width, height, pixel_offset, lens (0 none, 1 radial–tangential, 2 fisheye)
    k: vec4<f32>,      // k1, k2, k3, k4
    p: vec4<f32>,      // p1, p2, unused, unused
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

// nerf_rays::Camera::camera_dir: the direction, in OpenGL camera axes, of image point (u, v)
// (z = −1 without a lens or through a radial–tangential one, unit through a fisheye).
fn camera_dir(cam: Cam, u: f32, v: f32) -> vec3<f32> {
    let xd = (u - cam.intr.z) / cam.intr.x;
    let yd = (v - cam.intr.w) / cam.intr.y;
    let k = cam.k;
    if (cam.size.w == 1u) {
        // Newton on the distortion (nerf_rays::Distortion::undistort_iterate).
        var x = xd;
        var y = yd;
        for (var i = 0u; i < 10u; i = i + 1u) {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k.x + r2 * (k.y + r2 * k.z));
            let dr = k.x + r2 * (2.0 * k.y + r2 * 3.0 * k.z);
            let xy = x * y;
            let ex = x * radial + 2.0 * cam.p.x * xy + cam.p.y * (r2 + 2.0 * x * x) - xd;
            let ey = y * radial + cam.p.x * (r2 + 2.0 * y * y) + 2.0 * cam.p.y * xy - yd;
            let a = radial + 2.0 * x * x * dr + 2.0 * cam.p.x * y + 6.0 * cam.p.y * x;
            let b = 2.0 * xy * dr + 2.0 * cam.p.x * x + 2.0 * cam.p.y * y;
            let d = radial + 2.0 * y * y * dr + 6.0 * cam.p.x * y + 2.0 * cam.p.y * x;
            let det = a * d - b * b;
            if (!(abs(det) > 1e-12)) {
                break;
            }
            x = x - (d * ex - b * ey) / det;
            y = y - (a * ey - b * ex) / det;
        }
        return vec3<f32>(x, -y, -1.0);
    }
    if (cam.size.w == 2u) {
        let theta_d = sqrt(xd * xd + yd * yd);
        if (theta_d < 1e-12) {
            return vec3<f32>(0.0, 0.0, -1.0);
        }
        var theta = theta_d;
        for (var i = 0u; i < 10u; i = i + 1u) {
            let t2 = theta * theta;
            let f = theta * (1.0 + t2 * (k.x + t2 * (k.y + t2 * (k.z + t2 * k.w)))) - theta_d;
            let df = 1.0 + t2 * (3.0 * k.x + t2 * (5.0 * k.y + t2 * (7.0 * k.z + t2 * 9.0 * k.w)));
            if (!(abs(df) > 1e-12)) {
                break;
            }
            theta = theta - f / df;
        }
        let s = sin(theta) / theta_d;
        return vec3<f32>(xd * s, -yd * s, -cos(theta));
    }
    return vec3<f32>(xd, -(v - cam.intr.w) / cam.intr.y, -1.0);
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
