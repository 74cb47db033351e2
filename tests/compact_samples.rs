//! Training on compacted samples (`compact_samples`, instant-ngp): a step that trains only on the
//! samples compositing reaches is the step that trains on every marched sample — same loss, same
//! parameter update up to summation order — on fewer samples, on the CPU and (where an adapter
//! exists) on the GPU, whose compacted step gives the same loss whether the density pass keeps
//! the density net's activations or the net runs again. The pieces are tested against each other in crates/sampling/tests/compact.rs
//! (CPU twins) and crates/gpu/tests/compact.rs (kernels).

mod common;

use nerf::data::{Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{SceneBounds, StepStats, TrainConfig, Trainer};
use std::sync::Arc;

fn flat(t: &Trainer) -> Vec<f32> {
    t.export_fields().unwrap().into_iter().flatten().flat_map(|(_, v)| v).collect()
}

#[test]
fn a_compacted_step_is_the_full_step_on_fewer_samples() {
    let train = common::load(Split::Train, ViewSelection::First(20));
    let gpu = GpuContext::for_tests().map(Arc::new);
    // A fixed ray batch, so that both runs of the compared step draw the same rays.
    let mut base = common::small_hash_config(1000, 16, 32);
    base.target_samples_per_step = None;
    base.batch_rays = 256;
    if let nerf::train::SamplerConfig::Occupancy { max_samples_per_ray, .. } = &mut base.sampler {
        *max_samples_per_ray = 128; // the GPU buffers fit lavapipe's bindings
    }
    base.log_every = 1;
    base.ema_decay = None;
    // An early stop at 10 % transmittance, so that after a short training many rays stop early
    // (the equivalence holds for any threshold).
    base.transmittance_threshold = 0.1;
    // Train (on the CPU: checkpoints are device independent) until surfaces stop rays early,
    // then take the same step both ways on each device.
    let mut t = Trainer::new(base.clone(), &nerf::registry(), SceneBounds::of(&train)).unwrap();
    for _ in 0..150 {
        t.step(&train).unwrap();
    }
    let (fields, adam, sampler) = (t.export_fields().unwrap(), t.adam_state().unwrap(), t.sampler_state().unwrap());
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let before = flat(&t);
        let step_with = |compact: bool, keep_activations: bool| -> (StepStats, Vec<f32>) {
            let mut c = TrainConfig { compact_samples: compact, ..base.clone() };
            c.field_config["gpu_keep_density_activations"] = keep_activations.into();
            let mut u = Trainer::new_on(c, &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
            u.restore(t.step_count(), &fields, adam.clone(), &sampler).unwrap();
            let s = u.step(&train).unwrap();
            (s, flat(&u))
        };
        let step = |compact: bool| step_with(compact, true);
        let (full, p_full) = step(false);
        let (comp, p_comp) = step(true);
        if dev.is_some() {
            // The GPU twin's density pass keeps the density net's activations for the compacted
            // batch by default; running the net again gives the same loss to the last bit and the
            // same update up to the order in which the hash table's gradient atomics land (on
            // lavapipe, which runs them in order, to the last bit as well).
            let (again, p_again) = step_with(true, false);
            assert_eq!(again.loss.to_bits(), comp.loss.to_bits(), "{name}: loss with the density net run again");
            let moved: f64 = p_comp.iter().zip(&before).map(|(a, b)| (a - b).abs() as f64).sum();
            let apart: f64 = p_again.iter().zip(&p_comp).map(|(a, b)| (a - b).abs() as f64).sum();
            assert!(apart <= 1e-4 * moved, "{name}: the density net run again moves the parameters elsewhere ({apart} of {moved})");
        }
        assert!(full.loss.is_finite() && comp.loss.is_finite(), "{name}: losses read back");
        assert!(
            (full.loss - comp.loss).abs() <= 1e-5 * full.loss.abs().max(1e-6),
            "{name}: the compacted batch composites to other colours (loss {} vs {})",
            comp.loss,
            full.loss
        );
        assert!(
            comp.n_samples * 10 < full.n_samples * 9 && comp.n_samples > 0,
            "{name}: compaction kept {} of {} samples",
            comp.n_samples,
            full.n_samples
        );
        // The alive rays (those that met a sample) are the same either way: compaction keeps every
        // ray's first sample. Their MSE is the part of the batch's that they carry.
        assert_eq!((full.n_rays, comp.n_rays), (256, 256), "{name}: rays read back");
        assert_eq!(full.alive_rays, comp.alive_rays, "{name}: alive rays");
        assert!(full.alive_rays > 0 && full.alive_rays < full.n_rays, "{name}: {} alive rays of {}", full.alive_rays, full.n_rays);
        for s in [&full, &comp] {
            let (all, alive) = (s.mse as f64 * s.n_rays as f64, s.mse_alive as f64 * s.alive_rays as f64);
            assert!(alive.is_finite() && alive > 0.0 && alive <= all * (1.0 + 1e-5), "{name}: alive rays' squared error {alive} of {all}");
        }
        assert!((full.mse_alive - comp.mse_alive).abs() <= 1e-5 * full.mse_alive, "{name}: {} vs {}", full.mse_alive, comp.mse_alive);
        // The density pass saw exactly the samples the full step trained on.
        assert_eq!((full.n_marched, comp.n_marched), (full.n_samples, full.n_samples), "{name}: marched samples");
        // The update: what the step moved, and how far apart the two results are.
        let moved: f64 = p_full.iter().zip(&before).map(|(a, b)| (a - b).abs() as f64).sum();
        let apart: f64 = p_full.iter().zip(&p_comp).map(|(a, b)| (a - b).abs() as f64).sum();
        assert!(moved > 0.0 && p_comp.iter().all(|x| x.is_finite()), "{name}");
        assert!(apart <= 1e-2 * moved, "{name}: updates differ by {apart} (the step moved {moved})");
    }
}

#[test]
fn compact_samples_needs_the_occupancy_sampler_and_a_threshold() {
    let train = common::load(Split::Train, ViewSelection::First(2));
    let mut c = common::small_hash_config(10, 16, 32);
    c.compact_samples = true;
    c.transmittance_threshold = 0.0;
    let e = Trainer::new(c, &nerf::registry(), SceneBounds::of(&train)).err().expect("refused");
    assert!(e.to_string().contains("transmittance_threshold"), "{e}");
    let c = TrainConfig { compact_samples: true, transmittance_threshold: 1e-4, ..TrainConfig::default() };
    let e = Trainer::new(c, &nerf::registry(), SceneBounds::of(&train)).err().expect("refused");
    assert!(e.to_string().contains("occupancy"), "{e}");
}
