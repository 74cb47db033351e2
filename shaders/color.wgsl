// Per-view affine colour correction of composited pixels (CPU twins: nerf_render's
// color_correct_forward / color_correct_backward). 12 values per view: a row-major 3×3 matrix A,
// then an offset b. With fg = rgb − (1 − α)·bg (the field's part of the pixel):
//
//   out = A fg + α·b + (1 − α)·bg
//
// Backward, g = ∂L/∂out: ∂L/∂rgb = Aᵀ g (written over g), ∂L/∂α = g·(A bg + b − bg), and the
// ray's parameter gradient (g fgᵀ, α g) into ray_grads; views.wgsl adds those per view to grads
// (one workgroup per view: deterministic, no atomics).

struct ColorParams {
    n_views: u32,
    capacity_rays: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> cp: ColorParams;
@group(0) @binding(1) var<storage, read> counters: array<u32>;        // [0] = rays of the step
@group(0) @binding(2) var<storage, read> views: array<u32>;           // n_rays
@group(0) @binding(3) var<storage, read> params: array<f32>;          // 12·n_views
@group(0) @binding(4) var<storage, read> rgb: array<f32>;             // 3·n_rays, composited
@group(0) @binding(5) var<storage, read> opacity: array<f32>;         // n_rays
@group(0) @binding(6) var<storage, read> background: array<f32>;      // 3·n_rays
@group(0) @binding(7) var<storage, read_write> out_rgb: array<f32>;   // 3·n_rays
@group(0) @binding(8) var<storage, read_write> d_ray: array<f32>;     // 3·n_rays: ∂L/∂out in, ∂L/∂rgb out
@group(0) @binding(9) var<storage, read_write> d_opacity: array<f32>; // n_rays
@group(0) @binding(10) var<storage, read_write> ray_grads: array<f32>; // 12·n_rays

fn n_rays() -> u32 {
    return min(counters[0], cp.capacity_rays);
}

// Row i of view v's matrix, and its offset.
fn row(v: u32, i: u32) -> vec3<f32> {
    return vec3<f32>(params[12u * v + 3u * i], params[12u * v + 3u * i + 1u], params[12u * v + 3u * i + 2u]);
}

fn background_at(r: u32) -> vec3<f32> {
    return vec3<f32>(background[3u * r], background[3u * r + 1u], background[3u * r + 2u]);
}

fn rgb_at(r: u32) -> vec3<f32> {
    return vec3<f32>(rgb[3u * r], rgb[3u * r + 1u], rgb[3u * r + 2u]);
}

@compute @workgroup_size(64)
fn color_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays()) {
        return;
    }
    let v = views[r];
    let a = opacity[r];
    let bg = background_at(r);
    let fg = rgb_at(r) - (1.0 - a) * bg;
    for (var i = 0u; i < 3u; i = i + 1u) {
        out_rgb[3u * r + i] = dot(row(v, i), fg) + a * params[12u * v + 9u + i] + (1.0 - a) * bg[i];
    }
}

@compute @workgroup_size(64)
fn color_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays()) {
        return;
    }
    let v = views[r];
    let a = opacity[r];
    let bg = background_at(r);
    let fg = rgb_at(r) - (1.0 - a) * bg;
    let g = vec3<f32>(d_ray[3u * r], d_ray[3u * r + 1u], d_ray[3u * r + 2u]);
    let b = vec3<f32>(params[12u * v + 9u], params[12u * v + 10u], params[12u * v + 11u]);
    let atg = row(v, 0u) * g.x + row(v, 1u) * g.y + row(v, 2u) * g.z;
    d_ray[3u * r] = atg.x;
    d_ray[3u * r + 1u] = atg.y;
    d_ray[3u * r + 2u] = atg.z;
    d_opacity[r] = dot(atg, bg) + dot(g, b - bg);
    for (var i = 0u; i < 3u; i = i + 1u) {
        for (var j = 0u; j < 3u; j = j + 1u) {
            ray_grads[12u * r + 3u * i + j] = g[i] * fg[j];
        }
        ray_grads[12u * r + 9u + i] = a * g[i];
    }
}
