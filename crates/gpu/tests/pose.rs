//! Camera pose refinement's kernels (`shaders/pose.wgsl`) against their CPU twins
//! (`nerf_rays::pose`, `nerf_sampling::RaySamples::backward_to_rays`) on random batches: fresh
//! seeds, gradients added to non-zero values, a view with no ray, a view with no rotation yet,
//! rays without samples, two stages, batches larger than one reduction workgroup.

use nerf_gpu::pose::{GpuPoseCorrection, PARAMS_PER_VIEW};
use nerf_gpu::GpuContext;
use nerf_rays::pose::{pose_correct_backward, pose_correct_rays, pose_regulariser};
use nerf_sampling::RaySamples;
use rand::Rng as _;

struct Batch {
    views: Vec<u32>,
    params: Vec<f32>,
    origins: Vec<f32>,
    dirs: Vec<f32>,
}

/// `n` rays over `n_views` views (the last gets no ray when there are several); corrections of
/// up to 0.1 units and 3°, view 0 without rotation.
fn batch(n: usize, n_views: usize, seed: u64) -> Batch {
    let mut g = nerf_core::rng(seed, 0);
    let views = (0..n).map(|_| g.gen_range(0..n_views.max(2) as u32 - 1)).collect();
    let origins = (0..3 * n).map(|_| g.gen_range(-3.0..3.0)).collect();
    let mut dirs: Vec<f32> = (0..3 * n).map(|_| g.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_exact_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
        d.iter_mut().for_each(|x| *x /= l);
    }
    let mut params: Vec<f32> = (0..PARAMS_PER_VIEW * n_views)
        .map(|i| if i % 6 < 3 { g.gen_range(-0.1..0.1) } else { g.gen_range(-0.05..0.05) })
        .collect();
    params[3..6].fill(0.0);
    Batch { views, params, origins, dirs }
}

/// One stage: 0..8 samples per ray, `t` in [2, 6), random input gradients.
fn stage(n: usize, seed: u64) -> RaySamples {
    let mut g = nerf_core::rng(seed, 1);
    let mut s = RaySamples { n_rays: n, ray_offsets: vec![0], ..Default::default() };
    for _ in 0..n {
        let k = if g.gen::<f32>() < 0.2 { 0 } else { g.gen_range(1..8) };
        for _ in 0..k {
            s.t.push(g.gen_range(2.0..6.0));
        }
        s.ray_offsets.push(s.t.len() as u32);
    }
    s
}

#[test]
#[allow(clippy::type_complexity)]
fn pose_correction_matches_its_cpu_twin() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    // (rays, views, capacity): one ray; more rays than a reduction workgroup; rays fewer than the
    // capacity; one view.
    for (i, (n, n_views, cap)) in [(1, 1, 3), (1000, 7, 1000), (300, 40, 512), (50, 1, 64)].into_iter().enumerate() {
        let seed = 20 + i as u64;
        let b = batch(n, n_views, seed);
        let pc = GpuPoseCorrection::new(&ctx, n_views, cap, 0.01, 0.001).unwrap();
        assert_eq!(pc.len(), PARAMS_PER_VIEW * n_views);
        assert_eq!(pc.read_params(&ctx).unwrap(), vec![0.0; pc.len()], "zero at creation");
        pc.set_params(&ctx, &b.params).unwrap();

        // Forward: the moved rays.
        let (o, d) = pc.correct(&ctx, &b.views, &b.origins, &b.dirs).unwrap();
        let (mut wo, mut wd) = (b.origins.clone(), b.dirs.clone());
        pose_correct_rays(&b.views, &b.params, &mut wo, &mut wd, &mut Vec::new());
        for (k, (x, y)) in o.iter().zip(&wo).enumerate() {
            assert!((x - y).abs() <= 1e-6, "seed {seed} origin [{k}]: {x} vs {y}");
        }
        for (k, (x, y)) in d.iter().zip(&wd).enumerate() {
            assert!((x - y).abs() <= 2e-6, "seed {seed} dir [{k}]: {x} vs {y}");
        }

        // Backward over two stages, onto gradients that are not zero.
        let mut g = nerf_core::rng(seed, 2);
        let stages: Vec<(RaySamples, Vec<f32>, Vec<f32>)> = (0..2)
            .map(|s| {
                let st = stage(n, seed * 10 + s);
                let m = st.t.len();
                let dx: Vec<f32> = (0..3 * m).map(|_| g.gen_range(-1.0..1.0)).collect();
                let dd: Vec<f32> = (0..3 * m).map(|_| g.gen_range(-1.0..1.0)).collect();
                (st, dx, dd)
            })
            .collect();
        let start: Vec<f32> = (0..pc.len()).map(|i| 0.01 * i as f32).collect();
        // Storage buffers may not be empty: a stage without samples gets one unused value.
        let pad = |x: &[f32]| if x.is_empty() { vec![0.0] } else { x.to_vec() };
        let padded: Vec<_> = stages.iter().map(|(st, dx, dd)| (pad(&st.t), pad(dx), pad(dd))).collect();
        let host: Vec<(&[u32], &[f32], &[f32], &[f32])> =
            stages.iter().zip(&padded).map(|((st, _, _), (t, dx, dd))| (&st.ray_offsets[..], &t[..], &dx[..], &dd[..])).collect();
        let (grads, reg) = pc.backward(&ctx, &b.views, &b.origins, &b.dirs, &host, &start).unwrap();

        // CPU: per-ray sums (nerf_sampling), per-view gradient in f64, then the regulariser.
        let (mut d_o, mut d_d) = (vec![0.0f32; 3 * n], vec![0.0f32; 3 * n]);
        for (st, dx, dd) in &stages {
            st.backward_to_rays(dx, dd, &mut d_o, &mut d_d);
        }
        let f64s = |x: &[f32]| x.iter().map(|&v| v as f64).collect::<Vec<f64>>();
        let mut w64 = vec![0.0f64; pc.len()];
        pose_correct_backward(&b.views, &f64s(&b.params), &f64s(&b.dirs), &f64s(&d_o), &f64s(&d_d), &mut Vec::new(), &mut w64);
        let mut want: Vec<f32> = start.iter().zip(&w64).map(|(s, w)| s + *w as f32).collect();
        let want_reg = pose_regulariser(0.01, 0.001, &b.params, &mut want);
        assert!((reg - want_reg).abs() <= 1e-6 * (1.0 + want_reg.abs()), "seed {seed} regulariser: {reg} vs {want_reg}");

        // Sums over a view's samples in another order: relative to the sum of their sizes.
        let mut scale = vec![0f32; n_views];
        for (st, dx, dd) in &stages {
            for r in 0..n {
                for k in st.ray_offsets[r] as usize..st.ray_offsets[r + 1] as usize {
                    scale[b.views[r] as usize] += (st.t[k] + 1.0) * (dx[3 * k].abs() + dx[3 * k + 1].abs() + dx[3 * k + 2].abs() + dd[3 * k..3 * k + 3].iter().map(|x| x.abs()).sum::<f32>());
                }
            }
        }
        for (k, (x, y)) in grads.iter().zip(&want).enumerate() {
            let tol = 2e-6 * (1.0 + scale[k / PARAMS_PER_VIEW]);
            assert!((x - y).abs() <= tol, "seed {seed} grads[{k}]: {x} vs {y} (tolerance {tol})");
        }
        if n_views > 1 {
            // The view no ray came from gets the regulariser's gradient alone.
            let last = PARAMS_PER_VIEW * (n_views - 1);
            let mut only_reg = start.clone();
            pose_regulariser(0.01, 0.001, &b.params, &mut only_reg);
            for k in last..pc.len() {
                assert!((grads[k] - only_reg[k]).abs() <= 1e-6, "seed {seed}: view without rays, grads[{k}] {} vs {}", grads[k], only_reg[k]);
            }
        }
    }
}

#[test]
fn pose_correction_refuses_a_wrong_parameter_count() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let pc = GpuPoseCorrection::new(&ctx, 3, 8, 0.0, 0.0).unwrap();
    let e = pc.set_params(&ctx, &[0.0; 12]).unwrap_err().to_string();
    assert!(e.contains("12") && e.contains("3 views"), "{e}");
    assert!(GpuPoseCorrection::new(&ctx, 0, 8, 0.0, 0.0).is_err());
}
