//! The per-view colour correction's kernels (`shaders/color.wgsl`) against their CPU twins in
//! `nerf_render` on random inputs: poisoned outputs, gradients added to non-zero values, views
//! with no ray, and batches larger than one reduction workgroup.

use nerf_gpu::color::{GpuColorCorrection, PARAMS_PER_VIEW};
use nerf_gpu::GpuContext;
use nerf_render::{color_correct_backward, color_correct_forward, identity_color_correction};
use rand::Rng as _;

struct Batch {
    views: Vec<u32>,
    params: Vec<f32>,
    rgb: Vec<f32>,
    opacity: Vec<f32>,
    background: Vec<f32>,
    d_out: Vec<f32>,
}

/// `n` rays over `n_views` views of which the last gets no ray; pixels composited from a random
/// foreground and opacity so that `rgb − (1 − α)·bg` is a plausible field colour.
fn batch(n: usize, n_views: usize, seed: u64) -> Batch {
    let mut g = nerf_core::rng(seed, 0);
    let mut b = Batch { views: vec![], params: vec![], rgb: vec![], opacity: vec![], background: vec![], d_out: vec![] };
    for _ in 0..n {
        let a: f32 = if g.gen::<f32>() < 0.2 { 0.0 } else { g.gen() };
        let bg: [f32; 3] = [g.gen(), g.gen(), g.gen()];
        for c in 0..3 {
            b.rgb.push(a * g.gen::<f32>() + (1.0 - a) * bg[c]);
        }
        b.opacity.push(a);
        b.background.extend(bg);
        b.views.push(g.gen_range(0..n_views.max(2) as u32 - 1));
        b.d_out.extend([g.gen::<f32>() - 0.5, g.gen::<f32>() - 0.5, g.gen::<f32>() - 0.5]);
    }
    b.params = identity_color_correction(n_views).iter().map(|&x| x + 0.4 * (g.gen::<f32>() - 0.5)).collect();
    b
}

#[test]
fn color_correction_matches_its_cpu_twin() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    // (rays, views, capacity): one ray; a batch spanning several reduction strides; rays fewer
    // than the capacity; one view.
    for (seed, (n, n_views, cap)) in [(1, 1, 3), (1000, 7, 1000), (300, 40, 512), (50, 1, 64)].into_iter().enumerate() {
        let seed = seed as u64 + 10;
        let b = batch(n, n_views, seed);
        let cc = GpuColorCorrection::new(&ctx, n_views, cap).unwrap();
        assert_eq!(cc.len(), PARAMS_PER_VIEW * n_views);
        // Identity at creation.
        assert_eq!(cc.read_params(&ctx).unwrap(), identity_color_correction(n_views));
        cc.set_params(&ctx, &b.params).unwrap();
        let out = cc.forward(&ctx, &b.views, &b.rgb, &b.opacity, &b.background).unwrap();
        let mut want = vec![0.0; 3 * n];
        color_correct_forward(Some(&b.views), &b.params, &b.rgb, &b.opacity, &b.background, &mut want);
        for (k, (x, y)) in out.iter().zip(&want).enumerate() {
            // Three products and sums in the same order; FMA contraction at most.
            assert!((x - y).abs() <= 1e-6, "seed {seed} forward [{k}]: {x} vs {y}");
        }
        let start: Vec<f32> = (0..cc.len()).map(|i| 0.01 * i as f32).collect();
        let (d_rgb, d_op, grads) = cc.backward(&ctx, &b.views, &b.rgb, &b.opacity, &b.background, &b.d_out, &start).unwrap();
        let (mut w_rgb, mut w_op, mut w_grads) = (vec![0.0; 3 * n], vec![0.0; n], start.clone());
        color_correct_backward(Some(&b.views), &b.params, &b.rgb, &b.opacity, &b.background, &b.d_out, &mut w_rgb, &mut w_op, &mut w_grads);
        for (k, (x, y)) in d_rgb.iter().zip(&w_rgb).enumerate() {
            assert!((x - y).abs() <= 1e-6, "seed {seed} d_rgb[{k}]: {x} vs {y}");
        }
        for (k, (x, y)) in d_op.iter().zip(&w_op).enumerate() {
            assert!((x - y).abs() <= 2e-6, "seed {seed} d_opacity[{k}]: {x} vs {y}");
        }
        // Sums over a view's rays in another order: relative to the sum of magnitudes.
        let mut scale = vec![0f32; cc.len()];
        for r in 0..n {
            for s in &mut scale[PARAMS_PER_VIEW * b.views[r] as usize..][..PARAMS_PER_VIEW] {
                *s += 1.0;
            }
        }
        for (k, (x, y)) in grads.iter().zip(&w_grads).enumerate() {
            assert!((x - y).abs() <= 1e-6 * (1.0 + scale[k]), "seed {seed} grads[{k}]: {x} vs {y}");
        }
        if n_views > 1 {
            // The view no ray came from keeps exactly what it had.
            let last = PARAMS_PER_VIEW * (n_views - 1);
            assert_eq!(&grads[last..], &start[last..], "seed {seed}: a view without rays changed");
        }
    }
}

#[test]
fn color_correction_refuses_a_wrong_parameter_count() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let cc = GpuColorCorrection::new(&ctx, 3, 8).unwrap();
    let e = cc.set_params(&ctx, &[1.0; 24]).unwrap_err().to_string();
    assert!(e.contains("24") && e.contains("3 views"), "{e}");
    assert!(GpuColorCorrection::new(&ctx, 0, 8).is_err());
}
