//! Helpers shared by the workspace's integration tests (each test file includes this with
//! `mod common;`): the in-repo scene and the hash field's registry preset scaled down to what
//! lavapipe and the CI's 2 cores run in seconds.
#![allow(dead_code)] // each test file uses a subset

use nerf::data::{load_blender, Dataset, LoadOptions, Split, ViewSelection};
use nerf::train::{SamplerConfig, TrainConfig};
use std::path::Path;

/// The in-repo scene (`scenes/lego_100`, 100×100).
pub fn load(split: Split, views: ViewSelection) -> Dataset {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100");
    load_blender(&scene, split, &LoadOptions { downscale: 1, views, ..Default::default() }).unwrap()
}

/// The hash field's registry preset scaled down: a 2^13-sample batch, a 2^15 table and a 32³
/// occupancy grid refreshed every `update_every` steps after `warmup_steps` warm-up steps.
pub fn small_hash_config(iters: u64, update_every: u64, warmup_steps: u64) -> TrainConfig {
    let registry = nerf::registry();
    let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
    nerf::field::merge_json(&mut v, &(registry.get("hash").unwrap().train_preset)());
    let mut c: TrainConfig = serde_json::from_value(v).unwrap();
    c.field = "hash".into();
    c.iters = iters;
    c.log_every = 50;
    c.target_samples_per_step = Some(1 << 13);
    c.field_config = serde_json::json!({"grid": {"log2_hashmap_size": 15}});
    c.sampler = SamplerConfig::Occupancy {
        grid: nerf::sampling::OccupancyGridConfig { resolution: 32, update_every, warmup_steps, ..Default::default() },
        step_size: 0.01,
        max_samples_per_ray: 512,
        cone_angle: 0.0,
    };
    c
}
