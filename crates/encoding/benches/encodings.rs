//! Criterion benches of the Instant-NGP encodings on the CPU: hash grid forward (f32 and f16 storage)
//! and backward (parameter gradient), and the spherical-harmonics forward.
//!
//! Run with `cargo bench -p nerf-encoding -- --quick`. Points are uniform in the unit cube (the
//! worst case for the hashed levels' cache behaviour; real samples cluster near surfaces).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nerf_encoding::{Encoding, HashGrid, HashGridConfig, Precision, ShConfig, SphericalHarmonics};
use rand::Rng as _;
use std::hint::black_box;

const SIZES: [usize; 2] = [1 << 16, 1 << 18];

fn points(n: usize, seed: u64) -> Vec<f32> {
    let mut r = nerf_core::rng(seed, 0);
    (0..3 * n).map(|_| r.gen::<f32>()).collect()
}

fn hash_grid(c: &mut Criterion) {
    let mut rng = nerf_core::rng(1, 0);
    let g32: HashGrid = HashGrid::new(&HashGridConfig::default(), &mut rng);
    let g16: HashGrid = HashGrid::new(
        &HashGridConfig {
            storage: Precision::F16,
            ..HashGridConfig::default()
        },
        &mut nerf_core::rng(1, 0),
    );
    let od = Encoding::<f32>::output_dim(&g32);

    let mut group = c.benchmark_group("hash_grid_forward");
    group.sample_size(10);
    for n in SIZES {
        let x = points(n, 2);
        let mut y = vec![0.0f32; n * od];
        group.throughput(Throughput::Elements(n as u64));
        for (name, g) in [("f32", &g32), ("f16", &g16)] {
            group.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
                b.iter(|| g.forward(black_box(&x), black_box(&mut y)))
            });
        }
    }
    group.finish();

    let mut group = c.benchmark_group("hash_grid_backward");
    group.sample_size(10);
    let mut d_params = vec![0.0f32; Encoding::<f32>::n_params(&g32)];
    for n in SIZES {
        let x = points(n, 3);
        let mut r = nerf_core::rng(4, 0);
        let d_out: Vec<f32> = (0..n * od).map(|_| r.gen::<f32>() - 0.5).collect();
        group.throughput(Throughput::Elements(n as u64));
        group.bench_with_input(BenchmarkId::new("d_params", n), &n, |b, _| {
            b.iter(|| g32.backward(black_box(&x), black_box(&d_out), &mut d_params, None))
        });
    }
    group.finish();
}

fn spherical_harmonics(c: &mut Criterion) {
    let sh = SphericalHarmonics::new(&ShConfig::default());
    let mut group = c.benchmark_group("sh_forward");
    group.sample_size(10);
    let n = 1 << 18;
    let mut r = nerf_core::rng(5, 0);
    let d: Vec<f32> = (0..n)
        .flat_map(|_| {
            let v: [f32; 3] = std::array::from_fn(|_| r.gen::<f32>() * 2.0 - 1.0);
            let s = 1.0 / (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-6);
            v.map(|c| c * s)
        })
        .collect();
    let mut y = vec![0.0f32; 16 * n];
    group.throughput(Throughput::Elements(n as u64));
    group.bench_with_input(BenchmarkId::new("degree4", n), &n, |b, _| {
        b.iter(|| sh.forward(black_box(&d), black_box(&mut y)))
    });
    group.finish();
}

criterion_group!(benches, hash_grid, spherical_harmonics);
criterion_main!(benches);
