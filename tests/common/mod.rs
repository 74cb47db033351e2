//! Helpers shared by the workspace's integration tests (each test file includes this with
//! `mod common;`): the in-repo scene, the hash field's registry preset scaled down to what
//! lavapipe and the CI's 2 cores run in seconds, and a PSNR over a subset of pixels.
#![allow(dead_code)] // each test file uses a subset

use nerf::data::{load_blender, Dataset, LoadOptions, Split, ViewSelection};
use nerf::train::{SamplerConfig, TrainConfig};
use std::path::Path;

/// The in-repo scene (`scenes/lego_100`, 100×100).
pub fn load(split: Split, views: ViewSelection) -> Dataset {
    load_downscaled(split, views, 1)
}

fn load_downscaled(split: Split, views: ViewSelection, downscale: u32) -> Dataset {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100");
    load_blender(&scene, split, &LoadOptions { downscale, views, ..Default::default() }).unwrap()
}

/// The in-repo scene's first `n` views of `split` at a quarter of its resolution (25×25): for
/// tests that compare renders or need a run's evaluation to happen, not to score it. A 100×100
/// view of a field whose occupancy grid is still warming up marches every ray through the whole
/// box; on lavapipe that render took ~50 s, this one ~3 s.
pub fn thumbnails(split: Split, n: usize) -> Dataset {
    load_downscaled(split, ViewSelection::First(n), 4)
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
        cone_angle: None,
    };
    c
}

/// [`small_hash_config`] lightened for tests that take hundreds of GPU steps: 2^12 samples per
/// step, 32-wide MLPs and a 2^14 table. On lavapipe the fused MLP kernels are most of a step
/// (`gpu_profile`, another test running beside it: 2^13 samples and 64-wide nets take 1.46 s a
/// step, 1.30 s of it the MLP kernels and 87 ms Adam over the 2^15 table; this config 0.44 s).
/// The GPU kernels at the preset's widths are checked against the CPU in crates/gpu and
/// crates/field-hash; these tests check what a training run does with them.
pub fn light_hash_config(iters: u64) -> TrainConfig {
    let mut c = small_hash_config(iters, 16, 64);
    c.target_samples_per_step = Some(1 << 12);
    c.field_config = serde_json::json!({"grid": {"log2_hashmap_size": 14}, "density_hidden": 32, "color_hidden": 32});
    c
}

/// PSNR over every `stride`th pixel of the views of `ds` (white background), rendered by `t`.
pub fn sparse_psnr(t: &nerf::train::Trainer, ds: &Dataset, stride: usize) -> f64 {
    let mut rays = nerf::data::RayBatch::default();
    let (mut o, mut d, mut target) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..ds.n_views() {
        ds.view_rays(i, nerf::data::Background::White, t.config().pixel_convention, &mut rays);
        for r in (0..rays.len()).step_by(stride) {
            o.extend_from_slice(&rays.origins[3 * r..3 * r + 3]);
            d.extend_from_slice(&rays.dirs[3 * r..3 * r + 3]);
            target.extend_from_slice(&rays.target[3 * r..3 * r + 3]);
        }
    }
    let n = o.len() / 3;
    let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * n], vec![0.0; n], vec![0.0; n]);
    t.render_rays(&o, &d, &vec![1.0; 3 * n], &mut rgb, &mut opacity, &mut depth).unwrap();
    let mse = rgb.iter().zip(&target).map(|(a, b)| ((a - b) as f64).powi(2)).sum::<f64>() / rgb.len() as f64;
    -10.0 * mse.log10()
}

/// A field's render of every view of `ds` on white: per view its rays and the rendered
/// `(rgb, opacity, depth)`.
pub struct ViewRender {
    /// The view's rays (`Dataset::view_rays`).
    pub rays: nerf::data::RayBatch,
    /// `3·n` composited colour.
    pub rgb: Vec<f32>,
    /// `n` opacities.
    pub opacity: Vec<f32>,
    /// `n` expected depths.
    pub depth: Vec<f32>,
}

/// Renders every view of `ds` with `t` ([`ViewRender`] per view, in order).
pub fn render_views(t: &nerf::train::Trainer, ds: &Dataset) -> Vec<ViewRender> {
    (0..ds.n_views())
        .map(|i| {
            let mut rays = nerf::data::RayBatch::default();
            ds.view_rays(i, nerf::data::Background::White, t.config().pixel_convention, &mut rays);
            let m = rays.len();
            let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * m], vec![0.0; m], vec![0.0; m]);
            t.render_rays(&rays.origins, &rays.dirs, &rays.background, &mut rgb, &mut opacity, &mut depth).unwrap();
            ViewRender { rays, rgb, opacity, depth }
        })
        .collect()
}

/// A trainer of `config` on `device` (`None`: the CPU) after `config.iters` steps on `data`,
/// finished (its averaged weights in place).
pub fn train_on(config: &nerf::train::TrainConfig, data: &Dataset, device: Option<std::sync::Arc<nerf::gpu::GpuContext>>) -> nerf::train::Trainer {
    let on_gpu = device.is_some();
    let mut t = nerf::train::Trainer::new_on(config.clone(), &nerf::registry(), nerf::train::SceneBounds::of(data), device).unwrap();
    assert_eq!(t.device() != "cpu", on_gpu, "the trainer runs where it was asked to");
    for _ in 0..config.iters {
        t.step(data).unwrap();
    }
    t.finish().unwrap();
    t
}

/// The light hash preset ([`light_hash_config`]) trained for `iters` steps on `data` on the CPU
/// and, where an adapter exists, on the GPU: their PSNRs on `test` (every `stride`th pixel) must
/// lie within 1 dB. Returns them (`None` without an adapter).
pub fn gpu_matches_cpu(iters: u64, data: &Dataset, test: &Dataset, stride: usize) -> Option<(f64, f64)> {
    let ctx = std::sync::Arc::new(nerf::gpu::GpuContext::for_tests()?);
    let short = light_hash_config(iters);
    let cpu = sparse_psnr(&train_on(&short, data, None), test, stride);
    let gpu = sparse_psnr(&train_on(&short, data, Some(ctx)), test, stride);
    println!("{iters} steps: cpu {cpu:.2} dB, gpu {gpu:.2} dB");
    assert!((gpu - cpu).abs() < 1.0, "cpu {cpu:.2} dB, gpu {gpu:.2} dB");
    Some((cpu, gpu))
}

/// `config` trained on each of `runs` on the CPU: their PSNRs on every pixel of `test`, each
/// printed with its name and time.
pub fn psnr_of_each(config: &TrainConfig, runs: &[(&str, &Dataset)], test: &Dataset) -> Vec<f64> {
    runs.iter()
        .map(|(name, data)| {
            let t0 = std::time::Instant::now();
            let p = sparse_psnr(&train_on(config, data, None), test, 1);
            println!("cpu, {name}: {p:.2} dB on the held-out views ({:.1} s)", t0.elapsed().as_secs_f64());
            p
        })
        .collect()
}

/// The half-extent of the textured room of `tests/panorama.rs` and `tests/lens.rs`: its walls,
/// floor and ceiling are the faces of this cube.
pub const ROOM: f32 = 1.2;

/// The room's colour where the ray `(o, d)` from inside it meets a wall: smooth stripes that
/// differ from wall to wall.
pub fn room(o: nerf::rays::glam::Vec3, d: nerf::rays::glam::Vec3) -> [f32; 3] {
    let t = (0..3).map(|a| if d[a] > 0.0 { (ROOM - o[a]) / d[a] } else { (-ROOM - o[a]) / d[a] }).fold(f32::INFINITY, f32::min);
    let p = o + t * d;
    [0.5 + 0.4 * (3.0 * p.x + p.y).sin(), 0.5 + 0.4 * (2.5 * p.y - p.z + 1.0).sin(), 0.5 + 0.4 * (3.5 * p.z + 0.5 * p.x).sin()]
}

/// The row-major 4×4 camera-to-world matrix of a camera at `c` turned by `yaw` about the vertical
/// (+y) and tilted by `pitch` (about its x axis).
pub fn yaw_pitch_pose(c: nerf::rays::glam::Vec3, yaw: f32, pitch: f32) -> [[f32; 4]; 4] {
    let r = nerf::rays::glam::Mat3::from_rotation_y(yaw) * nerf::rays::glam::Mat3::from_rotation_x(pitch);
    let mut m = [[0.0; 4]; 4];
    for row in 0..3 {
        for col in 0..3 {
            m[row][col] = r.col(col)[row];
        }
        m[row][3] = c[row];
    }
    m[3][3] = 1.0;
    m
}
