//! End to end: the voxel field trains on the in-repo scene with exactly the machinery of the hash
//! field (its registry preset over the trainer's defaults), built through a registry that holds
//! only this crate's entry — no shared crate knows the field exists.

use nerf_data::{load_blender, Background, Dataset, LoadOptions, Split, ViewSelection};
use nerf_field::Registry;
use nerf_train::{evaluate, SceneBounds, TrainConfig, Trainer};
use std::path::{Path, PathBuf};

fn scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100")
}

fn load(split: Split, views: ViewSelection) -> Dataset {
    load_blender(&scene(), split, &LoadOptions { downscale: 1, views, ..Default::default() }).unwrap()
}

/// Trainer defaults ← the field's registry preset, as `nerf train --field voxel` would build it.
fn voxel_config(registry: &Registry) -> TrainConfig {
    let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
    nerf_field::merge_json(&mut v, &(registry.get("voxel").unwrap().train_preset)());
    let mut c: TrainConfig = serde_json::from_value(v).unwrap();
    c.field = "voxel".into();
    c
}

#[test]
fn voxel_field_learns_the_small_lego_scene() {
    let mut registry = Registry::new();
    registry.register(nerf_field_voxel::registry_entry());
    let train = load(Split::Train, ViewSelection::All);
    let test = load(Split::Test, ViewSelection::Every(3));
    let mut config = voxel_config(&registry);
    config.iters = 200;
    // A 64-wide colour MLP (default 128) keeps the test under ~30 s of training on 2 cores; with
    // the default width it reaches the same PSNR (19.15 dB) in ~38 s.
    config.field_config = serde_json::json!({"hidden": 64});
    let t0 = std::time::Instant::now();
    let mut trainer = Trainer::new(config.clone(), &registry, SceneBounds::of(&train)).unwrap();
    for _ in 0..config.iters {
        trainer.step(&train).unwrap();
    }
    let train_s = t0.elapsed().as_secs_f64();
    let report = evaluate(&trainer, &test, None, |_, _| {}).unwrap();
    let baseline: f64 = (0..test.n_views())
        .map(|i| {
            let gt = test.view_rgb(i, Background::White);
            nerf_metrics::psnr(&vec![1.0; gt.len()], &gt)
        })
        .sum::<f64>()
        / test.n_views() as f64;
    println!(
        "voxel: test PSNR {:.2} dB (SSIM {:.3}) vs background-only {baseline:.2} dB; training {train_s:.1} s",
        report.psnr, report.ssim
    );
    // Measured: 19.19 dB / SSIM 0.691 after 200 steps (x86-64, 2 cores; training 27 s). 17 dB
    // leaves 2 dB of margin for platform differences and is 7 dB above the background-only image
    // (9.7 dB): a broken gradient, sampler hook-up or density activation stays near the baseline
    // (with grid_lr_scale 10 the field has not left its empty init after 200 steps: 9.8 dB).
    assert!(report.psnr > 17.0, "PSNR {:.2} (background-only {baseline:.2})", report.psnr);
    assert!(report.psnr > baseline + 6.0, "PSNR {:.2} not 6 dB above baseline {baseline:.2}", report.psnr);
    assert!(report.ssim > 0.6, "SSIM {:.3}", report.ssim);
    // The field reports through the trait as the registry's "voxel".
    assert_eq!(trainer.fields()[0].kind(), "voxel");
}
