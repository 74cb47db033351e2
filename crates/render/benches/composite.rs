//! Compositing throughput: forward and backward over 4096 rays × 192 samples (f32), and the
//! distortion loss with its gradient over the same batch; the per-view colour correction of its
//! 4096 pixels.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nerf_render::{
    color_correct_backward, color_correct_forward, composite_backward, composite_forward, distortion_loss_grad, identity_color_correction,
    CompositeOutputs,
};
use rand::Rng;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let (n_rays, per_ray) = (4096usize, 192usize);
    let n = n_rays * per_ray;
    let mut g = nerf_core::rng(0, 0);
    let offsets: Vec<u32> = (0..=n_rays).map(|r| (r * per_ray) as u32).collect();
    let sigma: Vec<f32> = (0..n).map(|_| 0.5 * g.gen::<f32>()).collect();
    let rgb: Vec<f32> = (0..3 * n).map(|_| g.gen()).collect();
    let dt = vec![4.0 / per_ray as f32; n];
    let t: Vec<f32> = (0..n).map(|k| 2.0 + (k % per_ray) as f32 * dt[0]).collect();
    let bg: Vec<f32> = (0..3 * n_rays).map(|_| g.gen()).collect();
    let d_rgb: Vec<f32> = (0..3 * n_rays).map(|_| g.gen::<f32>() - 0.5).collect();
    let d_op: Vec<f32> = (0..n_rays).map(|_| g.gen::<f32>() - 0.5).collect();
    let d_depth: Vec<f32> = (0..n_rays).map(|_| g.gen::<f32>() - 0.5).collect();
    let mut out = CompositeOutputs::new();
    let (mut d_sigma, mut d_c) = (vec![0.0f32; n], vec![0.0f32; 3 * n]);

    let mut grp = c.benchmark_group("composite_4096x192");
    grp.throughput(Throughput::Elements(n as u64));
    grp.bench_function("forward", |b| {
        b.iter(|| {
            composite_forward(
                &offsets,
                &sigma,
                &rgb,
                &dt,
                &t,
                Some(&bg),
                0.0,
                black_box(&mut out),
            )
        })
    });
    composite_forward(&offsets, &sigma, &rgb, &dt, &t, Some(&bg), 0.0, &mut out);
    grp.bench_function("backward", |b| {
        b.iter(|| {
            composite_backward(
                &offsets,
                &sigma,
                &rgb,
                &dt,
                &t,
                Some(&bg),
                &out,
                &d_rgb,
                Some(&d_op),
                Some(&d_depth),
                black_box(&mut d_sigma),
                black_box(&mut d_c),
            )
        })
    });
    let mut ray_loss = vec![0.0f32; n_rays];
    grp.bench_function("distortion_loss_grad", |b| {
        b.iter(|| {
            distortion_loss_grad(&offsets, &sigma, &dt, &t, &out, 0.25, 1e-2 / n_rays as f32, black_box(&mut d_sigma), black_box(&mut ray_loss))
        })
    });
    grp.bench_function("forward_early_stop_1e-4", |b| {
        b.iter(|| {
            composite_forward(
                &offsets,
                &sigma,
                &rgb,
                &dt,
                &t,
                Some(&bg),
                1e-4,
                black_box(&mut out),
            )
        })
    });
    grp.finish();

    // The per-view colour correction of the same batch's pixels (100 views), per ray.
    let mut grp = c.benchmark_group("color_correction_4096_rays");
    grp.throughput(Throughput::Elements(n_rays as u64));
    let views: Vec<u32> = (0..n_rays).map(|_| g.gen_range(0..100)).collect();
    let params: Vec<f32> = identity_color_correction(100).iter().map(|&x| x + 0.1 * (g.gen::<f32>() - 0.5)).collect();
    let (mut cc_out, mut cc_d_rgb, mut cc_d_op, mut cc_grads) = (vec![0.0f32; 3 * n_rays], vec![0.0f32; 3 * n_rays], vec![0.0f32; n_rays], vec![0.0f32; params.len()]);
    grp.bench_function("forward", |b| {
        b.iter(|| color_correct_forward(Some(&views), &params, &out.rgb, &out.opacity, &bg, black_box(&mut cc_out)))
    });
    grp.bench_function("backward", |b| {
        b.iter(|| {
            color_correct_backward(
                Some(&views),
                &params,
                &out.rgb,
                &out.opacity,
                &bg,
                &d_rgb,
                black_box(&mut cc_d_rgb),
                black_box(&mut cc_d_op),
                black_box(&mut cc_grads),
            )
        })
    });
    grp.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
