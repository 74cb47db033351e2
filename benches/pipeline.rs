//! Pipeline benchmarks of the facade: the frequency encoding forward/backward and one full
//! training iteration of each field — the paper's (coarse + fine), the hash grid (also with
//! camera pose refinement) and the voxel grid (occupancy marching, after its warm-up) — on the
//! in-repo scene, side by side in one group, as samples/s.
//! Per-component benches live beside their crates: `cargo bench -p nerf-mlp` (MLP at width 256,
//! GFLOP/s), `-p nerf-render` (compositing), `-p nerf-encoding` (hash grid, SH),
//! `-p nerf-sampling` (marching).
//!
//! `train_step_gpu`: the same for the fields' GPU twins on the first adapter, each iteration
//! waiting for the device so the time is the step's, not its submission's. Skipped without an
//! adapter. On a software adapter (lavapipe) it always takes the small sizes below: its numbers
//! are only a smoke test there, and the full-size warm-up alone (300 hash steps) runs longer than
//! 20 minutes on 2 cores.
//!
//! `occupancy_mark_seen`: marking the grid cells no training camera sees, over the in-repo
//! scene's cameras in a box four times as large.
//!
//! `view_rays`: one view's rays for pinhole cameras and through two lenses (the Newton steps
//! that invert a lens, per ray).
//!
//! `NERF_BENCH_SMALL=1` shrinks every size for a quick CI-sized run.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nerf::data::{load_blender, LoadOptions, Split, ViewSelection};
use nerf::encoding::{Encoding, FrequencyEncoding, FrequencyEncodingConfig};
use nerf::train::{SamplerConfig, SceneBounds, TrainConfig, Trainer};
use rand::Rng as _;
use std::hint::black_box;

fn small() -> bool {
    std::env::var_os("NERF_BENCH_SMALL").is_some()
}

fn encoding(c: &mut Criterion) {
    let n = if small() { 1 << 12 } else { 1 << 16 };
    let enc = FrequencyEncoding::new(3, &FrequencyEncodingConfig { n_frequencies: 10, include_input: true });
    let mut rng = nerf::core::rng(0, 0);
    let x: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.5..1.5)).collect();
    let d_out: Vec<f32> = (0..63 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let mut out = vec![0.0f32; 63 * n];
    let mut d_in = vec![0.0f32; 3 * n];
    let mut g = c.benchmark_group("frequency_encoding_L10");
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function(BenchmarkId::new("forward", n), |b| b.iter(|| enc.forward(black_box(&x), &mut out)));
    g.bench_function(BenchmarkId::new("backward", n), |b| {
        b.iter(|| Encoding::<f32>::backward(&enc, black_box(&x), &d_out, &mut [], Some(&mut d_in)))
    });
    g.finish();
}

fn training_iteration(c: &mut Criterion) {
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100");
    let data = load_blender(&scene, Split::Train, &LoadOptions { downscale: 1, views: ViewSelection::All, ..Default::default() })
        .expect("in-repo scene loads");
    let registry = nerf::registry();
    let mut g = c.benchmark_group("train_step");
    g.sample_size(10);

    // The paper's field with the paper's sampler (fewer rays than the paper's 1024 to keep the
    // bench short; the cost is linear in rays).
    let (rays, n_coarse, n_fine) = if small() { (64, 16, 16) } else { (256, 64, 128) };
    let config = TrainConfig {
        batch_rays: rays,
        sampler: SamplerConfig::Hierarchical { n_coarse, n_fine },
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(config, &registry, SceneBounds::of(&data)).unwrap();
    let samples = trainer.step(&data).unwrap().n_samples; // warm up buffers; samples per step are fixed
    g.throughput(Throughput::Elements(samples as u64));
    g.bench_function(BenchmarkId::new("freq", format!("{rays}rays_{n_coarse}+{n_fine}")), |b| {
        b.iter(|| black_box(trainer.step(&data).unwrap()))
    });

    // The grid fields with their registry presets, measured after the occupancy warm-up so the
    // grid has carved out empty space (samples per step then hover around the target).
    // `hash_camera_optimizer`: the hash preset with camera pose refinement (input gradients
    // through the field, per-ray sums, the per-view corrections' Adam).
    for (name, field, pose) in [("hash", "hash", false), ("hash_camera_optimizer", "hash", true), ("voxel", "voxel", false)] {
        let mut config = preset(&registry, field);
        config.camera_optimizer = pose.then(Default::default);
        if small() {
            config.field_config = match field {
                "hash" => serde_json::json!({"grid": {"log2_hashmap_size": 15}}),
                _ => serde_json::json!({"resolution": 32}),
            };
            config.target_samples_per_step = Some(1 << 13);
        }
        let target = config.target_samples_per_step.unwrap();
        let warmup = if small() { 20 } else { 300 };
        let mut trainer = Trainer::new(config, &registry, SceneBounds::of(&data)).unwrap();
        let mut seen = 0;
        for _ in 0..warmup {
            seen = trainer.step(&data).unwrap().n_samples;
        }
        g.throughput(Throughput::Elements(seen as u64));
        g.bench_function(BenchmarkId::new(name, format!("target_{target}_samples")), |b| {
            b.iter(|| black_box(trainer.step(&data).unwrap()))
        });
    }
    g.finish();
}

/// The registry preset of `field` (trainer defaults ← the field's `train_preset`).
fn preset(registry: &nerf::field::Registry, field: &str) -> TrainConfig {
    let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
    nerf::field::merge_json(&mut v, &(registry.get(field).unwrap().train_preset)());
    let mut config: TrainConfig = serde_json::from_value(v).unwrap();
    config.field = field.into();
    config
}

fn training_iteration_gpu(c: &mut Criterion) {
    use nerf::gpu::{DevicePreference, GpuContext};
    let ctx = match GpuContext::open(DevicePreference::Gpu) {
        Ok(Some(ctx)) => std::sync::Arc::new(ctx),
        _ => return eprintln!("train_step_gpu: no GPU adapter, skipped"),
    };
    eprintln!("train_step_gpu on {}", ctx.describe());
    let small = small() || ctx.is_software();
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100");
    let data = load_blender(&scene, Split::Train, &LoadOptions { downscale: 1, views: ViewSelection::All, ..Default::default() })
        .expect("in-repo scene loads");
    let registry = nerf::registry();
    let mut g = c.benchmark_group("train_step_gpu");
    g.sample_size(10);
    // Hash: Instant-NGP's 2^18 samples per step (2^13 small), after the occupancy warm-up.
    let mut hash = preset(&registry, "hash");
    hash.target_samples_per_step = Some(if small { 1 << 13 } else { 1 << 18 });
    hash.log_every = 1; // every step reads its sample count back, so the bench knows the throughput
    // Paper: 1024 rays, 64 + 128 samples (64 rays, 16 + 16 small).
    let (rays, n_coarse, n_fine) = if small { (64, 16, 16) } else { (1024, 64, 128) };
    let freq = TrainConfig { batch_rays: rays, sampler: SamplerConfig::Hierarchical { n_coarse, n_fine }, log_every: 1, ..TrainConfig::default() };
    let hash_warmup = if small { 20 } else { 300 };
    let mut runs = vec![("hash", hash.clone(), hash_warmup), ("freq", freq, 2)];
    if ctx.features.cooperative_matrix && ctx.features.shader_f16 {
        // The hash field with its fused MLPs on cooperative matrices (`gpu_mlp = "coop"`).
        let mut coop = hash;
        coop.field_config = serde_json::json!({ "gpu_mlp": "coop" });
        runs.push(("hash_coop", coop, hash_warmup));
    }
    for (name, config, warmup) in runs {
        let mut trainer = Trainer::new_on(config, &registry, SceneBounds::of(&data), Some(ctx.clone())).unwrap();
        let mut seen = 0;
        for _ in 0..warmup {
            seen = trainer.step(&data).unwrap().n_samples;
        }
        g.throughput(Throughput::Elements(seen as u64));
        g.bench_function(BenchmarkId::new(name, format!("{seen}_samples")), |b| {
            b.iter(|| {
                black_box(trainer.step(&data).unwrap());
                trainer.finish().unwrap();
            })
        });
    }
    g.finish();
}

/// Marking the occupancy-grid cells no training camera sees (done once, at a run's first step):
/// the in-repo scene's 100 cameras, a box four times the Blender cube (instant-ngp's
/// `aabb_scale` 4), one 128³ grid and the cascade of 3 the scene gets by default.
fn mark_seen(c: &mut Criterion) {
    let data = load_blender(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/lego_100").as_ref(), Split::Train, &LoadOptions::default())
        .expect("the in-repo scene");
    let frusta: Vec<_> = data.cameras.iter().map(|c| c.frustum()).collect();
    let visible = |p: [f32; 3], r: f32| frusta.iter().any(|f| f.sees_sphere(p.into(), r));
    let res = if small() { 32 } else { 128 };
    let mut g = c.benchmark_group("occupancy_mark_seen");
    g.sample_size(10);
    for cascades in [1u32, 3] {
        let cfg = nerf::sampling::OccupancyGridConfig { resolution: res, cascades: Some(cascades), ..Default::default() };
        let mut grid = nerf::sampling::OccupancyGrid::new(cfg, [-6.06; 3], [6.06; 3]);
        g.throughput(Throughput::Elements(grid.densities().len() as u64));
        g.bench_function(BenchmarkId::new(format!("cascades_{cascades}"), format!("{res}^3_100_cameras")), |b| {
            b.iter(|| grid.mark_seen(&visible))
        });
        println!("cascades {cascades}: {:.1} % of the cells seen", 100.0 * grid.seen_fraction());
    }
    g.finish();
}

/// A view's rays (`Dataset::view_rays`: directions, targets, backgrounds) for the in-repo scene's
/// pinhole cameras and for the same cameras through a radial–tangential lens, a fisheye,
/// OpenCV's rational lens with thin-prism terms and a Fisheye624, whose rays each take the
/// Newton steps that invert the lens, and COLMAP's FOV lens, inverted in closed form.
fn camera_rays(c: &mut Criterion) {
    use nerf::rays::{Distortion, LensModel, PixelConvention};
    let data = load_blender(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/lego_100").as_ref(), Split::Train, &LoadOptions::default())
        .expect("the in-repo scene");
    let lenses = [
        ("pinhole", Distortion::NONE),
        ("radial_tangential", Distortion { k1: -0.12, k2: 0.03, p1: 0.002, p2: -0.003, ..Distortion::NONE }),
        ("fisheye", Distortion { model: LensModel::Fisheye, k1: 0.05, k2: -0.01, k3: 0.002, k4: -0.0005, ..Distortion::NONE }),
        (
            "full_opencv",
            Distortion { k1: -0.12, k2: 0.03, k4: 0.05, k5: -0.01, p1: 0.002, p2: -0.003, s1: 0.003, s3: -0.002, ..Distortion::NONE },
        ),
        (
            "fisheye624",
            Distortion::from_coefficients(LensModel::Fisheye624, [0.05, -0.01, 0.002, -0.0005, 0.0001, -0.00002, 0.001, -0.002, 0.002, -0.0005, -0.001, 0.0003]),
        ),
        ("fov", Distortion::fov(0.9)),
    ];
    let mut g = c.benchmark_group("view_rays");
    g.throughput(Throughput::Elements((data.width * data.height) as u64));
    let mut batch = nerf::data::RayBatch::default();
    for (name, lens) in lenses {
        let mut d = data.clone();
        d.cameras.iter_mut().for_each(|cam| cam.distortion = lens);
        g.bench_function(BenchmarkId::new(name, "100x100"), |b| {
            b.iter(|| d.view_rays(black_box(3), nerf::data::Background::White, PixelConvention::Center, &mut batch))
        });
    }
    g.finish();
}

criterion_group!(benches, encoding, training_iteration, mark_seen, camera_rays, training_iteration_gpu);
criterion_main!(benches);
