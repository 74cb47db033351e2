//! Occupancy-grid ray marching: 2^14 rays through a 128³ grid with ~5% occupied cells (constant
//! steps, and cone steps on the scattered grid), reported in emitted samples per second; and the
//! ball in a box four times as large with one grid or a cascade of three, in rays per second.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nerf_sampling::{march, OccupancyGrid, OccupancyGridConfig, RaySamples, Stepping};
use rand::Rng;

const N_RAYS: usize = 1 << 14;

/// Camera-like rays: origins on a sphere of radius 3 around the unit box, aimed at random points
/// inside it; near 0, far 6.
fn rays() -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut g = nerf_core::rng(3, 0);
    let (mut o, mut d) = (Vec::new(), Vec::new());
    for _ in 0..N_RAYS {
        let v: [f32; 3] = std::array::from_fn(|_| g.gen::<f32>() * 2.0 - 1.0);
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        let orig: [f32; 3] = std::array::from_fn(|a| 3.0 * v[a] / l);
        let target: [f32; 3] = std::array::from_fn(|_| g.gen::<f32>() * 1.6 - 0.8);
        let dir: [f32; 3] = std::array::from_fn(|a| target[a] - orig[a]);
        let dl = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        o.extend(orig);
        d.extend(dir.iter().map(|x| x / dl));
    }
    (o, d, vec![0.0; N_RAYS], vec![6.0; N_RAYS])
}

fn bench(c: &mut Criterion) {
    let (o, d, near, far) = rays();
    let step = 2.0 * 3f32.sqrt() / 1024.0; // Instant-NGP: 1024 steps along the box diagonal
    let cfg = OccupancyGridConfig::default(); // 128³
    let mut group = c.benchmark_group("march_128^3_5pct");

    // (a) an object: a ball holding ~5% of the box (r = 0.457 in [-1,1]³).
    let mut ball = OccupancyGrid::new(cfg.clone(), [-1.0; 3], [1.0; 3]);
    ball.fill_from(step, &mut |p: &[f32], s: &mut [f32]| {
        for (i, s) in s.iter_mut().enumerate() {
            let r2 = p[3 * i].powi(2) + p[3 * i + 1].powi(2) + p[3 * i + 2].powi(2);
            *s = if r2 < 0.457f32 * 0.457 { 100.0 } else { 0.0 };
        }
    });
    // (b) 5% of the cells occupied independently at random (worst case for skipping).
    let mut scattered = OccupancyGrid::new(cfg, [-1.0; 3], [1.0; 3]);
    let mut g = nerf_core::rng(4, 0);
    let dens: Vec<f32> = (0..scattered.densities().len())
        .map(|_| if g.gen::<f32>() < 0.05 { 100.0 } else { 0.0 })
        .collect();
    // The bits use the grid's default step size (box diagonal / 1024), which is `step`.
    let default_step = scattered.step_size();
    scattered.set_densities(&dens, default_step).unwrap();

    // (c) the scattered grid with instant-ngp's cone steps (1/256: growing from t = 256·step = 0.87).
    let cone = Stepping::new(step, 1.0 / 256.0);
    for (name, grid, stepping) in
        [("ball", &ball, Stepping::from(step)), ("scattered", &scattered, Stepping::from(step)), ("scattered_cone", &scattered, cone)]
    {
        let mut out = RaySamples::default();
        march(grid, &o, &d, &near, &far, stepping, 1024, None, &mut out);
        eprintln!(
            "{name}: occupied {:.2}%, {} samples for {} rays ({:.1}/ray)",
            100.0 * grid.occupied_fraction(),
            out.len(),
            N_RAYS,
            out.len() as f64 / N_RAYS as f64
        );
        group.throughput(Throughput::Elements(out.len() as u64));
        let mut rng = nerf_core::rng(5, 0);
        group.bench_function(name, |b| {
            b.iter(|| {
                march(
                    grid,
                    &o,
                    &d,
                    &near,
                    &far,
                    stepping,
                    1024,
                    Some(&mut rng),
                    &mut out,
                )
            })
        });
    }
    group.finish();

    // (d) the ball in a box four times as large ([-4, 4]³, instant-ngp's aabb_scale 4): one 128³
    // grid over the box against a cascade of 3 (the finest over [-1, 1]³), same rays and steps.
    let mut group = c.benchmark_group("march_box4_ball");
    for (name, cascades) in [("one_grid", 1u32), ("cascade_3", 3)] {
        let cfg = OccupancyGridConfig { cascades: Some(cascades), ..Default::default() };
        let mut grid = OccupancyGrid::new(cfg, [-4.0; 3], [4.0; 3]);
        grid.fill_from(step, &mut |p: &[f32], s: &mut [f32]| {
            for (i, s) in s.iter_mut().enumerate() {
                let r2 = p[3 * i].powi(2) + p[3 * i + 1].powi(2) + p[3 * i + 2].powi(2);
                *s = if r2 < 0.457f32 * 0.457 { 100.0 } else { 0.0 };
            }
        });
        let mut out = RaySamples::default();
        march(&grid, &o, &d, &near, &far, step, 1024, None, &mut out);
        eprintln!("box4 {name}: {} samples for {} rays ({:.1}/ray)", out.len(), N_RAYS, out.len() as f64 / N_RAYS as f64);
        group.throughput(Throughput::Elements(N_RAYS as u64));
        let mut rng = nerf_core::rng(5, 0);
        group.bench_function(name, |b| b.iter(|| march(&grid, &o, &d, &near, &far, step, 1024, Some(&mut rng), &mut out)));
    }
    group.finish();
}

/// Overhead of one grid update on 128³ cells with a trivial density (the field's cost excluded):
/// warm-up (all 2^21 cells) and after warm-up (a quarter of all + a quarter of the occupied).
fn bench_update(c: &mut Criterion) {
    let step = 2.0 * 3f32.sqrt() / 1024.0;
    let mut grid = OccupancyGrid::new(OccupancyGridConfig::default(), [-1.0; 3], [1.0; 3]);
    let mut density = |p: &[f32], s: &mut [f32]| {
        for (i, s) in s.iter_mut().enumerate() {
            let r2 = p[3 * i].powi(2) + p[3 * i + 1].powi(2) + p[3 * i + 2].powi(2);
            *s = if r2 < 0.457f32 * 0.457 { 100.0 } else { 0.0 };
        }
    };
    let mut rng = nerf_core::rng(6, 0);
    let mut group = c.benchmark_group("grid_update_128^3");
    group.throughput(Throughput::Elements(grid.densities().len() as u64));
    group.bench_function("warmup_all_cells", |b| {
        b.iter(|| grid.update(0, step, &mut density, &mut rng))
    });
    group.bench_function("after_warmup", |b| {
        b.iter(|| grid.update(1 << 20, step, &mut density, &mut rng))
    });
    group.finish();
}

criterion_group!(benches, bench, bench_update);
criterion_main!(benches);
