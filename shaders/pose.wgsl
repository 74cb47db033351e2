// Camera pose refinement (nerfstudio's SO3xR3 camera optimizer) on the device. 6 values per
// training view v: a translation τ_v, then a rotation vector ω_v; a ray of view v becomes
//
//   o' = o + τ_v        d' = R(ω_v) d        R(ω) = exp([ω]×) = I + a K + b K²,  K = [ω]×
//
// with a = sin θ / θ, b = (1 − cos θ) / θ² = 2 sin²(θ/2) / θ² (no cancellation in f32).
// CPU twins: nerf_rays::pose::{pose_correct_rays, pose_correct_backward},
// nerf_sampling::RaySamples::backward_to_rays and the trainer's regulariser (crates/train/src/pose.rs).
//
// pose_correct        per ray: moves the ray, keeps d (base_dirs) and zeroes the ray's gradient sums.
// pose_rays_backward  per ray, once per stage: adds Σ_samples ∂L/∂x (→ ∂L/∂o') and
//                     Σ_samples t ∂L/∂x + ∂L/∂dir (→ ∂L/∂d'), kept as [∂L/∂o' (3), ∂L/∂d' dᵀ (9)].
// (views.wgsl)        one workgroup per view sums its rays' 12 values into view_acc (deterministic,
//                     no atomics).
// pose_view_grads     per view: turns the sums into ∂L/∂τ and ∂L/∂ω (Gallego & Yezzi's ∂R/∂ω_i),
//                     adds the regulariser's gradient and writes its value for the view.

struct PoseParams {
    n_views: u32,
    capacity_rays: u32,
    trans_penalty: f32,
    rot_penalty: f32,
}

@group(0) @binding(0) var<uniform> pp: PoseParams;
@group(0) @binding(1) var<storage, read> counters: array<u32>;          // [0] = rays of the step
@group(0) @binding(2) var<storage, read> views: array<u32>;             // n_rays
@group(0) @binding(3) var<storage, read> params: array<f32>;            // 6·n_views
@group(0) @binding(4) var<storage, read_write> origins: array<f32>;     // 3·n_rays, moved in place
@group(0) @binding(5) var<storage, read_write> dirs: array<f32>;        // 3·n_rays, turned in place
@group(0) @binding(6) var<storage, read_write> base_dirs: array<f32>;   // 3·n_rays, d before the turn
@group(0) @binding(7) var<storage, read> ray_offsets: array<u32>;       // n_rays + 1 (a stage's samples)
@group(0) @binding(8) var<storage, read> t: array<f32>;                 // n
@group(0) @binding(9) var<storage, read> d_positions: array<f32>;       // 3·n, ∂L/∂x
@group(0) @binding(10) var<storage, read> d_sample_dirs: array<f32>;    // 3·n, ∂L/∂dir
@group(0) @binding(11) var<storage, read_write> ray_grads: array<f32>;  // 12·n_rays
@group(0) @binding(12) var<storage, read_write> grads: array<f32>;      // 6·n_views, added to
@group(0) @binding(13) var<storage, read_write> reg_terms: array<f32>;  // n_views, written
@group(0) @binding(14) var<storage, read> view_acc: array<f32>;         // 12·n_views, the views' sums

fn n_rays() -> u32 {
    return min(counters[0], pp.capacity_rays);
}

fn tau(v: u32) -> vec3<f32> {
    return vec3<f32>(params[6u * v], params[6u * v + 1u], params[6u * v + 2u]);
}

fn omega(v: u32) -> vec3<f32> {
    return vec3<f32>(params[6u * v + 3u], params[6u * v + 4u], params[6u * v + 5u]);
}

// [w]× as columns (WGSL matrices are column-major): K x = w × x.
fn skew(w: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(vec3<f32>(0.0, w.z, -w.y), vec3<f32>(-w.z, 0.0, w.x), vec3<f32>(w.y, -w.x, 0.0));
}

// (a, b) of Rodrigues' formula; their Taylor series near θ = 0 (the CPU twin's threshold).
fn rodrigues_ab(w: vec3<f32>) -> vec2<f32> {
    let th2 = dot(w, w);
    if (th2 < 1e-8) {
        return vec2<f32>(1.0 - th2 / 6.0, 0.5 - th2 / 24.0);
    }
    let th = sqrt(th2);
    let s = sin(0.5 * th);
    return vec2<f32>(sin(th) / th, 2.0 * s * s / th2);
}

fn so3_exp(w: vec3<f32>) -> mat3x3<f32> {
    let ab = rodrigues_ab(w);
    let k = skew(w);
    let id = mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
    return id + ab.x * k + ab.y * (k * k);
}

@compute @workgroup_size(64)
fn pose_correct(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays()) {
        return;
    }
    let v = min(views[r], pp.n_views - 1u);
    let d = vec3<f32>(dirs[3u * r], dirs[3u * r + 1u], dirs[3u * r + 2u]);
    let rot = so3_exp(omega(v));
    let nd = rot * d;
    let tv = tau(v);
    for (var a = 0u; a < 3u; a = a + 1u) {
        origins[3u * r + a] = origins[3u * r + a] + tv[a];
        base_dirs[3u * r + a] = d[a];
        dirs[3u * r + a] = nd[a];
    }
    for (var k = 0u; k < 12u; k = k + 1u) {
        ray_grads[12u * r + k] = 0.0;
    }
}

@compute @workgroup_size(64)
fn pose_rays_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = linear_id(gid, nwg, 64u);
    if (r >= n_rays()) {
        return;
    }
    var go = vec3<f32>(0.0);
    var gd = vec3<f32>(0.0);
    for (var k = ray_offsets[r]; k < ray_offsets[r + 1u]; k = k + 1u) {
        let gx = vec3<f32>(d_positions[3u * k], d_positions[3u * k + 1u], d_positions[3u * k + 2u]);
        let gdir = vec3<f32>(d_sample_dirs[3u * k], d_sample_dirs[3u * k + 1u], d_sample_dirs[3u * k + 2u]);
        go = go + gx;
        gd = gd + t[k] * gx + gdir;
    }
    let d = vec3<f32>(base_dirs[3u * r], base_dirs[3u * r + 1u], base_dirs[3u * r + 2u]);
    for (var i = 0u; i < 3u; i = i + 1u) {
        ray_grads[12u * r + i] = ray_grads[12u * r + i] + go[i];
        for (var j = 0u; j < 3u; j = j + 1u) {
            ray_grads[12u * r + 3u + 3u * i + j] = ray_grads[12u * r + 3u + 3u * i + j] + gd[i] * d[j];
        }
    }
}

@compute @workgroup_size(64)
fn pose_view_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let v = linear_id(gid, nwg, 64u);
    if (v >= pp.n_views) {
        return;
    }
    var a: array<f32, 12>;
    for (var k = 0u; k < 12u; k = k + 1u) {
        a[k] = view_acc[12u * v + k];
    }
    var g: array<f32, 6>;
    for (var i = 0u; i < 3u; i = i + 1u) {
        g[i] = a[i];
        g[3u + i] = 0.0;
    }
    // G = Σ ∂L/∂d' dᵀ (row-major in a[3..12]); ∂L/∂ω_i = ⟨∂R/∂ω_i, G⟩.
    var any_rot = false;
    for (var k = 3u; k < 12u; k = k + 1u) {
        any_rot = any_rot || a[k] != 0.0;
    }
    let w = omega(v);
    if (any_rot) {
        let th2 = dot(w, w);
        let k = skew(w);
        for (var i = 0u; i < 3u; i = i + 1u) {
            var e = vec3<f32>(0.0);
            e[i] = 1.0;
            let ei = skew(e);
            var dr: mat3x3<f32>;
            if (th2 < 1e-12) {
                // The derivative of I + K + K²/2 at ω.
                dr = ei + 0.5 * (ei * k + k * ei);
            } else {
                // Gallego & Yezzi: (ω_i K + [ω × (I − R) e_i]×) R / θ², with
                // (I − R) e_i = −(a K e_i + b K² e_i) (no cancellation).
                let ab = rodrigues_ab(w);
                let ke = cross(w, e);
                let col = -(ab.x * ke + ab.y * cross(w, ke));
                dr = (w[i] * k + skew(cross(w, col))) * (1.0 / th2) * so3_exp(w);
            }
            var s = 0.0;
            for (var row = 0u; row < 3u; row = row + 1u) {
                for (var c = 0u; c < 3u; c = c + 1u) {
                    // dr[c][row] is row `row`, column `c` (column-major).
                    s = s + dr[c][row] * a[3u + 3u * row + c];
                }
            }
            g[3u + i] = s;
        }
    }
    // nerfstudio's regulariser: trans_penalty · mean_v ‖τ_v‖ + rot_penalty · mean_v ‖ω_v‖.
    let nv = f32(pp.n_views);
    let tv = tau(v);
    let nt = length(tv);
    let nr = length(w);
    if (nt > 0.0) {
        for (var i = 0u; i < 3u; i = i + 1u) {
            g[i] = g[i] + pp.trans_penalty * tv[i] / (nt * nv);
        }
    }
    if (nr > 0.0) {
        for (var i = 0u; i < 3u; i = i + 1u) {
            g[3u + i] = g[3u + i] + pp.rot_penalty * w[i] / (nr * nv);
        }
    }
    for (var i = 0u; i < 6u; i = i + 1u) {
        grads[6u * v + i] = grads[6u * v + i] + g[i];
    }
    reg_terms[v] = (pp.trans_penalty * nt + pp.rot_penalty * nr) / nv;
}
