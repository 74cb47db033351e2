//! MLP benchmarks: the NeRF paper's trunk (input 63, 8×256 ReLU, skip, 257 outputs) forward and
//! forward+backward at n = 4096 and 16384 samples, and a plain 256×256 layer GEMM.
//! Prints samples/s and GFLOP/s (from `flops_per_sample`) measured by criterion's own timing loop.

use std::cell::Cell;
use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nerf_mlp::{matmul, MatMut, MatRef, Mlp, MlpConfig, MlpTape, Parallelism};
use rand::Rng as _;

/// Runs `f` under criterion with a custom timer, then prints the throughput over everything it measured.
fn timed(
    g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    id: BenchmarkId,
    label: &str,
    n: usize,
    flops_per_iter: f64,
    mut f: impl FnMut(),
) {
    let total = Cell::new((Duration::ZERO, 0u64));
    g.bench_function(id, |b| {
        b.iter_custom(|iters| {
            let t = Instant::now();
            for _ in 0..iters {
                f();
            }
            let d = t.elapsed();
            let (d0, i0) = total.get();
            total.set((d0 + d, i0 + iters));
            d
        })
    });
    let (d, iters) = total.get();
    let secs = d.as_secs_f64() / iters.max(1) as f64;
    println!(
        "RESULT {label:<28} n={n:<6} {:>9.3} ms/iter  {:>12.0} samples/s  {:>7.1} GFLOP/s",
        secs * 1e3,
        n as f64 / secs,
        flops_per_iter / secs * 1e-9
    );
}

fn trunk(c: &mut Criterion) {
    let mut rng = nerf_core::rng(0, 0);
    let mut mlp = Mlp::<f32>::new(MlpConfig::nerf_trunk(63, 257), &mut rng);
    let fps = mlp.flops_per_sample() as f64;
    let mut g = c.benchmark_group("nerf_trunk");
    g.sample_size(10);
    for n in [4096usize, 16384] {
        let x: Vec<f32> = (0..n * 63).map(|_| rng.gen::<f32>() * 2.0 - 1.0).collect();
        let d_out: Vec<f32> = (0..n * 257).map(|_| rng.gen::<f32>() - 0.5).collect();
        let mut d_in = vec![0.0f32; n * 63];
        let mut tape = MlpTape::default();
        g.throughput(Throughput::Elements(n as u64));
        timed(
            &mut g,
            BenchmarkId::new("forward", n),
            "trunk forward",
            n,
            fps * n as f64,
            || {
                black_box(mlp.forward(n, &x, &mut tape));
            },
        );
        // Backward costs two products per layer (dW and dX; the first layer's dX is the d_input one),
        // so forward+backward ≈ 3× the forward FLOPs.
        timed(
            &mut g,
            BenchmarkId::new("forward_backward", n),
            "trunk forward+backward",
            n,
            3.0 * fps * n as f64,
            || {
                mlp.forward(n, &x, &mut tape);
                mlp.backward(n, &x, &mut tape, &d_out, Some(&mut d_in));
                black_box(&d_in);
            },
        );
    }
    g.finish();
}

fn layer_gemm(c: &mut Criterion) {
    let mut rng = nerf_core::rng(1, 0);
    let mut g = c.benchmark_group("gemm_256x256_layer");
    g.sample_size(10);
    let w: Vec<f32> = (0..256 * 256).map(|_| rng.gen::<f32>() - 0.5).collect();
    for n in [4096usize, 16384] {
        let x: Vec<f32> = (0..n * 256).map(|_| rng.gen::<f32>() - 0.5).collect();
        let mut y = vec![0.0f32; n * 256];
        g.throughput(Throughput::Elements(n as u64));
        let flops = 2.0 * 256.0 * 256.0 * n as f64;
        timed(
            &mut g,
            BenchmarkId::new("x_wt", n),
            "gemm X·Wᵀ 256×256",
            n,
            flops,
            || {
                matmul(
                    MatMut::row_major(&mut y, n, 256),
                    false,
                    MatRef::row_major(&x, n, 256),
                    MatRef::row_major(&w, 256, 256).t(),
                    Parallelism::Rayon(0),
                );
                black_box(&y);
            },
        );
        let mut dw = vec![0.0f32; 256 * 256];
        timed(
            &mut g,
            BenchmarkId::new("dzt_x", n),
            "gemm dW += dZᵀ·X 256×256",
            n,
            flops,
            || {
                matmul(
                    MatMut::row_major(&mut dw, 256, 256),
                    true,
                    MatRef::row_major(&y, n, 256).t(),
                    MatRef::row_major(&x, n, 256),
                    Parallelism::Rayon(0),
                );
                black_box(&dw);
            },
        );
        timed(
            &mut g,
            BenchmarkId::new("x_wt_single_thread", n),
            "gemm X·Wᵀ 1 thread",
            n,
            flops,
            || {
                matmul(
                    MatMut::row_major(&mut y, n, 256),
                    false,
                    MatRef::row_major(&x, n, 256),
                    MatRef::row_major(&w, 256, 256).t(),
                    Parallelism::None,
                );
                black_box(&y);
            },
        );
    }
    g.finish();
}

criterion_group!(benches, trunk, layer_gemm);
criterion_main!(benches);
