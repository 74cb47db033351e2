//! End to end on the in-repo scene: the paper's field (scaled down, `configs/demo.toml` minus
//! the time budget) and the hash-grid field (its registry preset) train for a fixed number of
//! steps and must beat a PSNR threshold on held-out views; a resumed run matches an uninterrupted
//! one exactly; the shared crates name no field.

use nerf::data::{load_blender, Background, Dataset, LoadOptions, Split, ViewSelection};
use nerf::train::{evaluate, SceneBounds, TrainConfig, Trainer};
use std::path::Path;

fn scene() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100")
}

fn load(split: Split, views: ViewSelection) -> Dataset {
    load_blender(&scene(), split, &LoadOptions { downscale: 1, views, ..Default::default() }).unwrap()
}

/// The README demo's config, read from the file the README points at (so this test also keeps
/// that file valid), with the wall-clock budget removed to make the run deterministic.
fn demo_config() -> TrainConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/demo.toml");
    let mut c: TrainConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    c.time_budget_secs = None;
    c
}

#[test]
fn paper_field_learns_the_small_lego_scene() {
    let train = load(Split::Train, ViewSelection::All);
    let test = load(Split::Test, ViewSelection::Every(6));
    let mut config = demo_config();
    config.iters = 150;
    let mut trainer = Trainer::new(config.clone(), &nerf::registry(), SceneBounds::of(&train)).unwrap();
    for _ in 0..config.iters {
        trainer.step(&train).unwrap();
    }
    let report = evaluate(&trainer, &test, None, |_, _| {}).unwrap();

    // Baseline: predicting the white background everywhere (9.7 dB on these views): a field
    // that has learned nothing about geometry or colour cannot beat it by much.
    let baseline: f64 = (0..test.n_views())
        .map(|i| {
            let gt = test.view_rgb(i, Background::White);
            nerf::metrics::psnr(&vec![1.0; gt.len()], &gt)
        })
        .sum::<f64>()
        / test.n_views() as f64;
    println!("test PSNR {:.2} dB (SSIM {:.3}) vs background-only {:.2} dB", report.psnr, report.ssim, baseline);
    // Threshold: this run measured 17.57 dB / SSIM 0.61 on every 6th test view after 150 steps
    // (x86-64, 2 cores; 18.6 dB / SSIM 0.67 after 200, a test 1.3× as long). Requiring 16 dB and
    // 6 dB above the background-only image (9.93 dB here), i.e. a 4x lower MSE, leaves 1.6 dB of
    // margin for seed and platform differences (summation order in the GEMM), while a broken
    // gradient, sampler or compositor stays near the baseline and fails.
    assert!(report.psnr > 16.0, "PSNR {:.2} below 16 dB (background-only: {baseline:.2})", report.psnr);
    assert!(report.psnr > baseline + 6.0, "PSNR {:.2} not 6 dB above baseline {baseline:.2}", report.psnr);
    assert!(report.ssim > 0.5, "SSIM {:.3}", report.ssim);
}

/// The config `nerf train --field hash` uses: trainer defaults ← the field's registry preset.
fn hash_config() -> TrainConfig {
    let registry = nerf::registry();
    let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
    nerf::field::merge_json(&mut v, &(registry.get("hash").unwrap().train_preset)());
    let mut c: TrainConfig = serde_json::from_value(v).unwrap();
    c.field = "hash".into();
    c
}

#[test]
fn hash_field_learns_the_small_lego_scene() {
    let train = load(Split::Train, ViewSelection::All);
    let test = load(Split::Test, ViewSelection::Every(6));
    let mut config = hash_config();
    config.iters = 200;
    let mut trainer = Trainer::new(config.clone(), &nerf::registry(), SceneBounds::of(&train)).unwrap();
    for _ in 0..config.iters {
        trainer.step(&train).unwrap();
    }
    let occupied = trainer.occupancy_grid().unwrap().occupied_fraction();
    let report = evaluate(&trainer, &test, None, |_, _| {}).unwrap();
    println!("hash: test PSNR {:.2} dB (SSIM {:.3}), occupied cells {:.3}", report.psnr, report.ssim, occupied);
    // Measured: 25.1 dB / SSIM 0.88 in this test on every 6th test view (24.8 dB on every 3rd;
    // PyTorch's MLP init: 22.2 dB / SSIM 0.82 after
    // 200 steps of `nerf train scenes/lego_100 --field hash --iters 200`). 20 dB leaves 2 dB of margin and is still far above the 9.7 dB
    // background-only image and above what the paper's field reaches in 200 steps (18 dB).
    assert!(report.psnr > 20.0, "PSNR {:.2}", report.psnr);
    assert!(report.ssim > 0.7, "SSIM {:.3}", report.ssim);
    // The error split by ground-truth alpha adds up to each view's PSNR: the two parts' MSEs
    // weighted by their pixel shares give the view's MSE, and the empty part's share of it.
    for v in &report.views {
        let a = v.alpha_split.expect("the lego views have empty pixels");
        let mse = a.empty_fraction * a.mse_empty + (1.0 - a.empty_fraction) * a.mse_object;
        assert!((nerf::metrics::mse_to_psnr(mse) - v.psnr).abs() < 1e-6, "{a:?} against {:.4} dB", v.psnr);
        assert!((a.empty_fraction * a.mse_empty / mse - a.empty_error_share).abs() < 1e-9, "{a:?}");
        assert!((0.0..=1.0).contains(&a.empty_opacity), "{a:?}");
    }
    let split = report.alpha_split.expect("a mean split");
    println!("hash: by ground-truth alpha: {}", split.summary());
    // Past warm-up the grid must have carved out empty space (the lego fills a few % of the box).
    assert!(occupied < 0.5, "occupied fraction {occupied}");
}

#[test]
fn shared_crates_name_no_field() {
    // The trainer, samplers, compositing and CLI drive fields only through the trait and the
    // registry: no dependency on a field crate and no field type named in their sources.
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for krate in ["train", "sampling", "render", "cli", "data", "rays", "metrics"] {
        let dir = root.join("crates").join(krate);
        let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).unwrap();
        assert!(!manifest.contains("nerf-field-"), "crates/{krate}/Cargo.toml depends on a field crate");
        for entry in std::fs::read_dir(dir.join("src")).unwrap() {
            let path = entry.unwrap().path();
            let src = std::fs::read_to_string(&path).unwrap();
            for name in ["field_freq", "field_hash", "field_voxel", "FreqNerf", "HashNerf", "VoxelNerf"] {
                assert!(!src.contains(name), "{} names `{name}`", path.display());
            }
        }
    }
}

#[test]
fn resumed_training_matches_uninterrupted_training() {
    let mut config = demo_config();
    config.batch_rays = 64;
    config.field_config = serde_json::json!({"width": 16, "depth": 2, "skips": [], "view_width": 8});
    check_resume(config);
    // The hash field with its occupancy grid (updated every 2 steps, so the grid state and the
    // adaptive batch size must survive the checkpoint too).
    let mut config = hash_config();
    config.field_config = serde_json::json!({"grid": {"log2_hashmap_size": 12, "n_levels": 4}});
    config.target_samples_per_step = Some(2048);
    config.batch_rays = 64;
    config.sampler = nerf::train::SamplerConfig::Occupancy {
        grid: nerf::sampling::OccupancyGridConfig { resolution: 16, update_every: 2, warmup_steps: 2, ..Default::default() },
        step_size: 0.02,
        max_samples_per_ray: 256,
        cone_angle: None,
    };
    check_resume(config);
}

fn check_resume(config: TrainConfig) {
    let train = load(Split::Train, ViewSelection::First(4));
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);

    let mut straight = Trainer::new(config.clone(), &registry, bounds).unwrap();
    for _ in 0..6 {
        straight.step(&train).unwrap();
    }

    let mut first = Trainer::new(config.clone(), &registry, bounds).unwrap();
    for _ in 0..3 {
        first.step(&train).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("checkpoint.bin");
    nerf::train::Checkpoint {
        step: first.step_count(),
        elapsed_secs: 0.0,
        samples_seen: 0,
        config: config.clone(),
        fields: first.export_fields().unwrap(),
        adam: first.adam_state().unwrap(),
        sampler: first.sampler_state().unwrap(),
        render_only: false,
    }
    .save(&path)
    .unwrap();
    drop(first);
    let ck = nerf::train::Checkpoint::load(&path).unwrap();
    let mut resumed = Trainer::new(config, &registry, bounds).unwrap();
    resumed.restore(ck.step, &ck.fields, ck.adam, &ck.sampler).unwrap();
    for _ in 0..3 {
        resumed.step(&train).unwrap();
    }
    assert_eq!(resumed.step_count(), 6);
    // Compare without printing millions of numbers on failure.
    let (a, b) = (resumed.export_fields().unwrap(), straight.export_fields().unwrap());
    for (fa, fb) in a.iter().zip(&b) {
        for ((na, va), (_, vb)) in fa.iter().zip(fb) {
            let diff = va.iter().zip(vb).position(|(x, y)| x.to_bits() != y.to_bits());
            assert_eq!(diff, None, "resume must be bit-exact: group {na} differs first at {diff:?}");
        }
    }
    assert_eq!(a.len(), b.len());
}
