//! LLFF end to end: the hash field trained on fern (../shared/data, NeRF's real forward-facing
//! scene, 17 train and 3 held-out views, in NDC) learns it on the CPU, and the GPU path (lavapipe
//! in CI) trains the same scene with its 4:3 images as the CPU does. Prints a notice and returns where
//! the shared data (or, for the GPU part, an adapter) is absent.

use nerf::data::{load_scene, LoadOptions, Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{evaluate, SamplerConfig, SceneBounds, Trainer};
use std::sync::Arc;

mod common;

/// The hash preset scaled to the CI: 2^14 samples per step, a 64³ grid, 0.02 steps (~110 along
/// an NDC ray), a 2^15 table.
fn config(iters: u64) -> nerf::train::TrainConfig {
    let mut c = common::small_hash_config(iters, 16, 64);
    c.target_samples_per_step = Some(1 << 14);
    c.sampler = SamplerConfig::Occupancy {
        grid: nerf::sampling::OccupancyGridConfig { resolution: 64, update_every: 16, warmup_steps: 64, ..Default::default() },
        step_size: 0.02,
        max_samples_per_ray: 512,
        cone_angle: None,
    };
    c
}

#[test]
fn the_hash_field_learns_fern() {
    let Some(fern) = nerf::core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else {
        eprintln!("NOTICE: ../shared/data/nerf_llff_data/fern is absent; LLFF training not checked");
        return;
    };
    // images_8 box-averaged by 2: 252×189.
    let opts = |views| LoadOptions { downscale: 16, views, ..Default::default() };
    let train = load_scene(&fern, Split::Train, &opts(ViewSelection::All)).unwrap();
    let test = load_scene(&fern, Split::Test, &opts(ViewSelection::All)).unwrap();
    assert_eq!((train.n_views(), test.n_views(), train.width, train.height), (17, 3, 252, 189));
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);

    let cfg = config(300);
    let mut t = Trainer::new(cfg.clone(), &registry, bounds).unwrap();
    // Untrained, every marched sample is evaluated: a sparse score keeps this cheap.
    let untrained = common::sparse_psnr(&t, &test, 16);
    for _ in 0..cfg.iters {
        t.step(&train).unwrap();
    }
    let cpu = evaluate(&t, &test, None, |_, _| {}).unwrap();
    println!("cpu: {untrained:.2} dB untrained, {:.2} dB (SSIM {:.3}) after {} steps", cpu.psnr, cpu.ssim, cfg.iters);
    // Measured: 20.8 dB after 300 steps in NDC (PyTorch's MLP init: 20.6 dB, and 19.7 dB with
    // Euclidean rays), from 12.1 dB
    // untrained (an empty field: the white background). A wrong pose convention, warp or box
    // stays near the blur of the mean colour.
    assert!(cpu.psnr > 18.5 && cpu.psnr > untrained + 7.0, "{:.2} dB", cpu.psnr);

    // The GPU (lavapipe takes ~1 s per step here and minutes per full view): fewer, smaller
    // steps, scored on every 64th pixel of the held-out views against the CPU after the same
    // steps of the same config (same initial field).
    let Some(ctx) = GpuContext::for_tests().map(Arc::new) else { return };
    let mut cfg = config(40);
    cfg.target_samples_per_step = Some(1 << 13);
    // 32-wide nets and a 2^14 table, as `common::light_hash_config`: lavapipe spends most of a
    // step in the MLP kernels.
    cfg.field_config = common::light_hash_config(0).field_config;
    let mut c = Trainer::new(cfg.clone(), &registry, bounds).unwrap();
    let mut g = Trainer::new_on(cfg.clone(), &registry, bounds, Some(ctx)).unwrap();
    for _ in 0..cfg.iters {
        c.step(&train).unwrap();
        g.step(&train).unwrap();
    }
    g.finish().unwrap();
    let (gpu, cpu40) = (common::sparse_psnr(&g, &test, 64), common::sparse_psnr(&c, &test, 64));
    println!("gpu: {gpu:.2} dB after {} steps (every 64th pixel; cpu {cpu40:.2} dB)", cfg.iters);
    // Measured: 15.1 dB on the GPU, 15.5 dB on the CPU (12.1 dB untrained; with the preset's
    // 64-wide nets and 2^15 table 15.6 and 16.0 dB. With those and PyTorch's MLP init: 13.9 and
    // 13.7 dB, and with Euclidean rays 16.8 and 17.0 dB: NDC starts slower at this batch size and
    // overtakes by 300 steps).
    assert!((gpu - cpu40).abs() < 1.0 && gpu > untrained + 1.0, "{gpu:.2} dB vs cpu {cpu40:.2} dB (untrained {untrained:.2} dB)");
}
