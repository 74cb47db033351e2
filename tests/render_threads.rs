//! The CPU renderer with the occupancy grid renders its chunks of rays (`render_chunk_rays`
//! each, marched and composited in rounds) concurrently: the image must not depend on the number
//! of threads, and every ray, the partial last chunk's too, must get its own colour.

use nerf::data::{RayBatch, Split, ViewSelection};
use nerf::train::{SceneBounds, TrainConfig, Trainer};

mod common;
use common::load;

/// Colours, opacities and depths of `n` rays, outputs poisoned beforehand.
fn render(t: &Trainer, o: &[f32], d: &[f32], bg: &[f32]) -> Vec<f32> {
    let n = o.len() / 3;
    let (mut rgb, mut op, mut depth) = (vec![f32::NAN; 3 * n], vec![f32::NAN; n], vec![f32::NAN; n]);
    t.render_rays(o, d, bg, &mut rgb, &mut op, &mut depth).unwrap();
    rgb.extend(op);
    rgb.extend(depth);
    rgb
}

#[test]
fn cpu_occupancy_render_is_the_same_on_one_thread_and_many_and_per_ray() {
    let train = load(Split::Train, ViewSelection::First(10));
    let test = load(Split::Test, ViewSelection::First(1));
    let bounds = SceneBounds::of(&train);
    // 97 rays per chunk: the 100×100 view is 103 full chunks and one of 9.
    let config = TrainConfig { render_chunk_rays: 97, ..common::small_hash_config(60, 4, 8) };
    let mut t = Trainer::new(config.clone(), &nerf::registry(), bounds).unwrap();
    for _ in 0..config.iters {
        t.step(&train).unwrap();
    }
    let mut batch = RayBatch::default();
    test.view_rays(0, nerf::data::Background::White, config.pixel_convention, &mut batch);
    let n = batch.len();
    // The trained state, rendered by a trainer restored from it in a pool of `k` threads (a
    // trainer is not `Sync`, so each pool builds its own).
    let (fields, adam, sampler) = (t.export_fields().unwrap(), t.adam_state().unwrap(), t.sampler_state().unwrap());
    let in_pool = |k: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(k).build().unwrap();
        pool.install(|| {
            let mut r = Trainer::new(config.clone(), &nerf::registry(), bounds).unwrap();
            r.restore(config.iters, &fields, adam.clone(), &sampler).unwrap();
            render(&r, &batch.origins, &batch.dirs, &batch.background)
        })
    };
    let (many, one) = (in_pool(4), in_pool(1));
    assert_eq!(many, render(&t, &batch.origins, &batch.dirs, &batch.background), "the restored trainer renders as the trained one");
    assert!(many.iter().all(|x| x.is_finite()), "every ray written");
    assert_eq!(many, one, "the image depends on the thread count");
    let opaque = (0..n).filter(|&r| many[3 * n + r] > 0.5).count();
    assert!(opaque > n / 20, "the field learnt nothing to render: {opaque} of {n} rays opaque");
    // Rays rendered one at a time (each a call of its own) get what the whole view gave them:
    // each chunk's outputs land on its own rays.
    for r in (0..n).step_by(37).chain([n - 1]) {
        let s = 3 * r..3 * r + 3;
        let alone = render(&t, &batch.origins[s.clone()], &batch.dirs[s.clone()], &batch.background[s]);
        let whole = [many[3 * r], many[3 * r + 1], many[3 * r + 2], many[3 * n + r], many[4 * n + r]];
        for (a, w) in alone.iter().zip(whole) {
            assert!((a - w).abs() <= 1e-4 * (1.0 + w.abs()), "ray {r}: alone {alone:?}, in the view {whole:?}");
        }
    }
}
