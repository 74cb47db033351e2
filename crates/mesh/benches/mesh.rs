//! Mesh extraction throughput: the isosurface of a smooth ball on a 256³ lattice (what
//! `nerf export-mesh` does after the density queries), and the lattice's node positions.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nerf_mesh::{extract_mesh, Lattice};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let l = Lattice::over_box([-1.0; 3], [1.0; 3], 256);
    let mut pts = Vec::new();
    l.points(0..l.len(), &mut pts);
    let density: Vec<f32> = pts
        .chunks_exact(3)
        .map(|p| {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            10.0 / (1.0 + ((r - 0.6) / 0.02).exp())
        })
        .collect();
    let mut grp = c.benchmark_group("mesh_256");
    grp.sample_size(10);
    grp.throughput(Throughput::Elements(l.len() as u64));
    grp.bench_function("extract_ball", |b| b.iter(|| black_box(extract_mesh(&l, &density, 5.0))));
    grp.throughput(Throughput::Elements(1 << 18));
    grp.bench_function("lattice_points_2^18", |b| b.iter(|| l.points(black_box(0..1 << 18), &mut pts)));
    grp.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
