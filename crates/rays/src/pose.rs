//! Camera pose refinement (nerfstudio's camera optimizer in its `SO3xR3` mode; BARF's and
//! instant-ngp's extrinsics optimisation): the poses of real captures come from structure from
//! motion and are a little off, which a field cannot explain and fits as blur and floaters. Each
//! training view `v` gets a correction of 6 values `p_v = [τ (3), ω (3)]`, a translation and a
//! rotation vector, applied to the rays of that view:
//!
//! ```text
//! o' = o + τ_v          d' = R(ω_v) d          R(ω) = exp([ω]×)  (Rodrigues)
//! ```
//!
//! exactly nerfstudio's `CameraOptimizer.apply_to_raybundle`: the rotation turns the view's rays
//! about the camera centre, in world axes. `p_v = 0` leaves the rays unchanged. The rays stay unit
//! length, so the samples `x = o' + t d'` and their view direction `d'` are what the field sees;
//! the backward pass, given `∂L/∂o'` and `∂L/∂d'` per ray (the field's input gradients summed over
//! the ray's samples, `nerf_sampling::RaySamples::backward_to_rays`), accumulates per view
//!
//! ```text
//! ∂L/∂τ_v = Σ_rays ∂L/∂o'        ∂L/∂ω_i = ⟨∂R/∂ω_i, Σ_rays ∂L/∂d' dᵀ⟩   (Frobenius)
//! ```
//!
//! with Gallego & Yezzi's closed form of `∂R/∂ω_i` ([`so3_exp_derivatives`]). The sample distances
//! `t` are held fixed, as nerfstudio's samplers detach them.

use nerf_core::Real;

/// Values per view: a translation, then a rotation vector (nerfstudio's `SO3xR3` order).
pub const POSE_PARAMS_PER_VIEW: usize = 6;

/// A row-major 3×3 matrix.
pub type Mat3x3<T> = [[T; 3]; 3];

/// `R = exp([ω]×)` (Rodrigues' formula; its Taylor series near `ω = 0`).
pub fn so3_exp<T: Real>(w: [T; 3]) -> Mat3x3<T> {
    // R = I + a [ω]× + b [ω]×²,  a = sin θ / θ,  b = (1 − cos θ) / θ².
    let (a, b) = rodrigues_ab(w);
    let k = skew(w);
    let k2 = matmul(&k, &k);
    let mut r = [[T::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let id = if i == j { T::one() } else { T::zero() };
            r[i][j] = id + a * k[i][j] + b * k2[i][j];
        }
    }
    r
}

/// `(a, b)` of `R = I + a [ω]× + b [ω]×²`: `a = sin θ / θ`, `b = (1 − cos θ) / θ²`, the latter
/// as `2 sin²(θ/2) / θ²` (no cancellation in f32); their Taylor series near `θ = 0`.
fn rodrigues_ab<T: Real>(w: [T; 3]) -> (T, T) {
    let th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    if th2 < T::c(1e-8) {
        (T::one() - th2 / T::c(6.0), T::c(0.5) - th2 / T::c(24.0))
    } else {
        let th = th2.sqrt();
        let s = (T::c(0.5) * th).sin();
        (th.sin() / th, T::c(2.0) * s * s / th2)
    }
}

/// `∂R/∂ω_i` for `i = 0, 1, 2` at `ω` (Gallego & Yezzi 2015, "A compact formula for the
/// derivative of a 3-D rotation in exponential coordinates"):
/// `∂R/∂ω_i = (ω_i [ω]× + [ω × (I − R) e_i]×) R / θ²`, and near `θ = 0` the derivative of the
/// second-order series `I + [ω]× + [ω]×²/2`.
pub fn so3_exp_derivatives<T: Real>(w: [T; 3]) -> [Mat3x3<T>; 3] {
    let th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    let mut out = [[[T::zero(); 3]; 3]; 3];
    if th2 < T::c(1e-12) {
        let k = skew(w);
        for (i, d) in out.iter_mut().enumerate() {
            let mut e = [T::zero(); 3];
            e[i] = T::one();
            let ei = skew(e);
            let (a, b) = (matmul(&ei, &k), matmul(&k, &ei));
            for r in 0..3 {
                for c in 0..3 {
                    d[r][c] = ei[r][c] + T::c(0.5) * (a[r][c] + b[r][c]);
                }
            }
        }
        return out;
    }
    let r = so3_exp(w);
    let k = skew(w);
    let (a, b) = rodrigues_ab(w);
    for (i, d) in out.iter_mut().enumerate() {
        // (I − R) e_i = −(a [ω]× e_i + b [ω]×² e_i), without the cancellation of I − R in f32.
        let mut e = [T::zero(); 3];
        e[i] = T::one();
        let ke = cross(w, e);
        let kke = cross(w, ke);
        let col = [0, 1, 2].map(|c| -(a * ke[c] + b * kke[c]));
        let v = cross(w, col);
        let s = skew(v);
        let mut m = [[T::zero(); 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                m[a][b] = (w[i] * k[a][b] + s[a][b]) / th2;
            }
        }
        *d = matmul(&m, &r);
    }
    out
}

fn skew<T: Real>(w: [T; 3]) -> Mat3x3<T> {
    let z = T::zero();
    [[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]]
}

fn cross<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn matmul<T: Real>(a: &Mat3x3<T>, b: &Mat3x3<T>) -> Mat3x3<T> {
    let mut c = [[T::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    c
}

fn view_params<T: Real>(params: &[T], v: usize) -> ([T; 3], [T; 3]) {
    let p = &params[v * POSE_PARAMS_PER_VIEW..(v + 1) * POSE_PARAMS_PER_VIEW];
    ([p[0], p[1], p[2]], [p[3], p[4], p[5]])
}

/// Applies each ray's view correction in place: `o ← o + τ_v`, `d ← R(ω_v) d` (`origins`, `dirs`:
/// `3·n`; `view_ids`: `n`; `params`: [`POSE_PARAMS_PER_VIEW`] per view). `rotations` is scratch
/// (one matrix per view, kept between calls so a training step allocates nothing).
///
/// Panics when a ray's view has no correction.
pub fn pose_correct_rays<T: Real>(
    view_ids: &[u32],
    params: &[T],
    origins: &mut [T],
    dirs: &mut [T],
    rotations: &mut Vec<Mat3x3<T>>,
) {
    let n_views = params.len() / POSE_PARAMS_PER_VIEW;
    assert_eq!(origins.len(), 3 * view_ids.len());
    assert_eq!(dirs.len(), 3 * view_ids.len());
    rotations.clear();
    rotations.extend((0..n_views).map(|v| so3_exp(view_params(params, v).1)));
    for ((&v, o), d) in view_ids.iter().zip(origins.chunks_exact_mut(3)).zip(dirs.chunks_exact_mut(3)) {
        let v = v as usize;
        assert!(v < n_views, "pose correction: ray of view {v}, but corrections for {n_views} views");
        let (tau, _) = view_params(params, v);
        let r = &rotations[v];
        for a in 0..3 {
            o[a] += tau[a];
        }
        let d0 = [d[0], d[1], d[2]];
        for a in 0..3 {
            d[a] = r[a][0] * d0[0] + r[a][1] * d0[1] + r[a][2] * d0[2];
        }
    }
}

/// The camera whose rays are `camera`'s corrected by `p = [τ, ω]`: centre `position + τ`,
/// orientation `R(ω) · rotation` — its pixel rays are [`pose_correct_rays`]'s for the same `p`
/// (for every pixel convention and projection, as both only turn and shift the camera frame).
/// The corrected poses a run writes, and how test scenes get cameras moved on purpose.
pub fn move_camera(camera: &crate::Camera, p: &[f32; POSE_PARAMS_PER_VIEW]) -> crate::Camera {
    let r = so3_exp([p[3], p[4], p[5]]);
    let r = glam::Mat3::from_cols_array_2d(&r).transpose(); // rows → glam's columns
    crate::Camera { rotation: r * camera.rotation, position: camera.position + glam::Vec3::new(p[0], p[1], p[2]), ..*camera }
}

/// Backward of [`pose_correct_rays`]: given `∂L/∂o'` and `∂L/∂d'` (`3·n` each) and the rays'
/// directions *before* the correction (`dirs`), accumulates (`+=`) `∂L/∂p_v` into `grads`
/// ([`POSE_PARAMS_PER_VIEW`] per view). `acc` is scratch (12 values per view).
pub fn pose_correct_backward<T: Real>(
    view_ids: &[u32],
    params: &[T],
    dirs: &[T],
    d_origins: &[T],
    d_dirs: &[T],
    acc: &mut Vec<T>,
    grads: &mut [T],
) {
    let n_views = params.len() / POSE_PARAMS_PER_VIEW;
    assert_eq!(grads.len(), params.len());
    assert_eq!(dirs.len(), 3 * view_ids.len());
    assert_eq!(d_origins.len(), 3 * view_ids.len());
    assert_eq!(d_dirs.len(), 3 * view_ids.len());
    // Per view: Σ ∂L/∂o' (3), then G = Σ ∂L/∂d' dᵀ (9, row-major).
    acc.clear();
    acc.resize(12 * n_views, T::zero());
    for (k, &v) in view_ids.iter().enumerate() {
        let v = v as usize;
        assert!(v < n_views, "pose correction: ray of view {v}, but corrections for {n_views} views");
        let a = &mut acc[12 * v..12 * (v + 1)];
        for i in 0..3 {
            a[i] += d_origins[3 * k + i];
            for j in 0..3 {
                a[3 + 3 * i + j] += d_dirs[3 * k + i] * dirs[3 * k + j];
            }
        }
    }
    for v in 0..n_views {
        let a = &acc[12 * v..12 * (v + 1)];
        let g = &mut grads[v * POSE_PARAMS_PER_VIEW..(v + 1) * POSE_PARAMS_PER_VIEW];
        for i in 0..3 {
            g[i] += a[i];
        }
        if a[3..].iter().all(|x| *x == T::zero()) {
            continue;
        }
        let dr = so3_exp_derivatives(view_params(params, v).1);
        for (i, d) in dr.iter().enumerate() {
            let mut s = T::zero();
            for r in 0..3 {
                for c in 0..3 {
                    s += d[r][c] * a[3 + 3 * r + c];
                }
            }
            g[3 + i] += s;
        }
    }
}

/// nerfstudio's `camera_opt_regularizer`: `trans_penalty · mean_v ‖τ_v‖ + rot_penalty ·
/// mean_v ‖ω_v‖` over the views' corrections `params` ([`POSE_PARAMS_PER_VIEW`] per view); adds
/// its gradient to `grads` (0 where a vector is 0) and returns its value.
pub fn pose_regulariser(trans_penalty: f32, rot_penalty: f32, params: &[f32], grads: &mut [f32]) -> f32 {
    let n_views = (params.len() / POSE_PARAMS_PER_VIEW).max(1) as f32;
    let mut total = 0.0;
    for (p, g) in params.chunks_exact(POSE_PARAMS_PER_VIEW).zip(grads.chunks_exact_mut(POSE_PARAMS_PER_VIEW)) {
        for (part, weight) in [(0..3, trans_penalty), (3..6, rot_penalty)] {
            let norm = p[part.clone()].iter().map(|x| x * x).sum::<f32>().sqrt();
            total += weight * norm / n_views;
            if norm > 0.0 {
                for i in part {
                    g[i] += weight * p[i] / (norm * n_views);
                }
            }
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    fn rand_w(rng: &mut impl Rng, scale: f64) -> [f64; 3] {
        [0, 1, 2].map(|_| rng.gen_range(-scale..scale))
    }

    #[test]
    fn exp_is_a_rotation_and_turns_about_its_axis() {
        let mut rng = nerf_core::rng(7, 0);
        for scale in [1e-6, 1e-3, 0.3, 2.5] {
            let w = rand_w(&mut rng, scale);
            let r = so3_exp(w);
            let rtr = matmul(&[[r[0][0], r[1][0], r[2][0]], [r[0][1], r[1][1], r[2][1]], [r[0][2], r[1][2], r[2][2]]], &r);
            for i in 0..3 {
                for j in 0..3 {
                    let id = if i == j { 1.0 } else { 0.0 };
                    assert!((rtr[i][j] - id).abs() < 1e-12, "RᵀR ≠ I at {scale}");
                }
                // The axis is fixed.
                let rw: f64 = (0..3).map(|j| r[i][j] * w[j]).sum();
                assert!((rw - w[i]).abs() < 1e-12 * (1.0 + w[i].abs()));
            }
        }
        // A quarter turn about z takes x to y.
        let r = so3_exp([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        assert!((r[1][0] - 1.0).abs() < 1e-12 && r[0][0].abs() < 1e-12);
    }

    #[test]
    fn exp_derivatives_match_finite_differences_f64() {
        let mut rng = nerf_core::rng(8, 0);
        for scale in [0.0f64, 1e-7, 1e-3, 0.4, 2.0] {
            let w = rand_w(&mut rng, scale.max(1e-300));
            let d = so3_exp_derivatives(w);
            let h = 1e-6;
            for i in 0..3 {
                let (mut wp, mut wm) = (w, w);
                wp[i] += h;
                wm[i] -= h;
                let (rp, rm) = (so3_exp(wp), so3_exp(wm));
                for r in 0..3 {
                    for c in 0..3 {
                        let fd = (rp[r][c] - rm[r][c]) / (2.0 * h);
                        assert!((fd - d[i][r][c]).abs() < 1e-8, "scale {scale} ∂R/∂ω{i}[{r}][{c}]: {} vs fd {fd}", d[i][r][c]);
                    }
                }
            }
        }
    }

    /// In f32 the derivatives stay as accurate at the small angles refinement works with (a few
    /// hundredths of a degree) as at large ones: no `I − R` cancellation.
    #[test]
    fn exp_derivatives_in_f32_are_accurate_at_small_angles() {
        let mut rng = nerf_core::rng(10, 0);
        for scale in [3e-6f64, 1e-5, 1e-4, 1e-3, 1e-2, 0.5] {
            for _ in 0..20 {
                let w = rand_w(&mut rng, scale);
                let w32 = w.map(|x| x as f32);
                let (d64, d32) = (so3_exp_derivatives(w32.map(|x| x as f64)), so3_exp_derivatives(w32));
                for i in 0..3 {
                    for r in 0..3 {
                        for c in 0..3 {
                            let err = (d32[i][r][c] as f64 - d64[i][r][c]).abs();
                            assert!(err < 2e-6, "scale {scale} ∂R/∂ω{i}[{r}][{c}]: f32 {} vs f64 {}", d32[i][r][c], d64[i][r][c]);
                        }
                    }
                }
            }
        }
    }

    /// L = Σ a·o' + Σ b·d' over random rays of three views; the gradient of every view's six
    /// values against central differences, in f64.
    #[test]
    fn backward_matches_finite_differences_f64() {
        let mut rng = nerf_core::rng(9, 0);
        let n = 40;
        let n_views = 3;
        let view_ids: Vec<u32> = (0..n).map(|k| (k % n_views) as u32).collect();
        let origins: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-2.0..2.0)).collect();
        let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        for d in dirs.chunks_exact_mut(3) {
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d.iter_mut().for_each(|x| *x /= l);
        }
        let a: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mut params: Vec<f64> = (0..POSE_PARAMS_PER_VIEW * n_views).map(|_| rng.gen_range(-0.3..0.3)).collect();
        params[POSE_PARAMS_PER_VIEW * 2 + 3..].fill(0.0); // one view with no rotation yet
        let loss = |p: &[f64]| {
            let (mut o, mut d) = (origins.clone(), dirs.clone());
            pose_correct_rays(&view_ids, p, &mut o, &mut d, &mut Vec::new());
            o.iter().zip(&a).map(|(x, y)| x * y).sum::<f64>() + d.iter().zip(&b).map(|(x, y)| x * y).sum::<f64>()
        };
        let mut grads = vec![0.5; params.len()]; // accumulates onto what is there
        pose_correct_backward(&view_ids, &params, &dirs, &a, &b, &mut Vec::new(), &mut grads);
        let h = 1e-6;
        for i in 0..params.len() {
            let (mut pp, mut pm) = (params.clone(), params.clone());
            pp[i] += h;
            pm[i] -= h;
            let fd = (loss(&pp) - loss(&pm)) / (2.0 * h);
            assert!((grads[i] - 0.5 - fd).abs() < 1e-7 * (1.0 + fd.abs()), "∂L/∂p[{i}]: {} vs fd {fd}", grads[i] - 0.5);
            assert!(fd.abs() > 1e-3, "∂L/∂p[{i}] = {fd} is suspiciously small");
        }
    }

    #[test]
    fn zero_correction_leaves_rays_unchanged_and_keeps_them_unit() {
        let o0 = vec![1.0f32, 2.0, 3.0, -1.0, 0.5, 0.0];
        let d0 = vec![0.0f32, 0.0, -1.0, 0.6, 0.8, 0.0];
        let (mut o, mut d) = (o0.clone(), d0.clone());
        pose_correct_rays(&[0, 1], &[0.0; 12], &mut o, &mut d, &mut Vec::new());
        assert_eq!((o, d), (o0.clone(), d0.clone()));
        let (mut o, mut d) = (o0, d0);
        pose_correct_rays(&[1, 0], &[0.1, 0.2, 0.3, 0.4, -0.5, 0.6, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0], &mut o, &mut d, &mut Vec::new());
        assert_eq!(&o[..3], &[1.0, 2.0, 3.0], "view 1 has no translation");
        for (x, want) in o[3..].iter().zip([-0.9, 0.7, 0.3]) {
            assert!((x - want).abs() < 1e-6, "view 0 moves by τ");
        }
        for r in d.chunks_exact(3) {
            assert!(((r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt() - 1.0).abs() < 1e-6);
        }
        // View 1 turns −z by 0.01 rad about x; view 0 by 0.877 rad.
        assert!((d[1] - 0.01f32.sin()).abs() < 1e-6 && (d[2] + 0.01f32.cos()).abs() < 1e-6);
        assert!((d[3] * 0.6 + d[4] * 0.8 - 1.0).abs() > 0.1);
    }

    #[test]
    fn a_moved_camera_casts_the_corrected_rays() {
        let k = crate::Intrinsics::from_fov_x(16, 12, 0.7);
        let c2w = [[0.6, 0.0, 0.8, 3.0], [0.8, 0.0, -0.6, 1.0], [0.0, 1.0, 0.0, 0.5]];
        let cam = crate::Camera::from_c2w(k, &c2w).unwrap();
        let p = [0.05, -0.02, 0.01, 0.02, -0.03, 0.015];
        let moved = move_camera(&cam, &p);
        let conv = crate::PixelConvention::Center;
        for (col, row) in [(0, 0), (7, 5), (15, 11)] {
            let (r, m) = (cam.ray(col, row, conv), moved.ray(col, row, conv));
            let (mut o, mut d) = (r.origin.to_array().to_vec(), r.dir.to_array().to_vec());
            pose_correct_rays(&[0], &p, &mut o, &mut d, &mut Vec::new());
            for a in 0..3 {
                assert!((o[a] - m.origin[a]).abs() < 1e-6 && (d[a] - m.dir[a]).abs() < 1e-6, "pixel ({col}, {row}) axis {a}");
            }
            assert!((r.dir - m.dir).length() > 1e-3, "the camera turned");
        }
    }
}
