//! tiny-cuda-nn's sparse Adam on the hash table (`adam.sparse_groups`): the trainer refuses a name
//! that matches no parameter group, and on either device a run keeps per-entry step counts for the
//! table — entries the batch did not reach are skipped — which checkpoints carry across devices.
//! GPU parts print a notice and return where no adapter exists.

use nerf::data::{Dataset, Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{SceneBounds, TrainConfig, TrainError, Trainer};
use std::sync::Arc;

mod common;

fn load() -> Dataset {
    common::load(Split::Train, ViewSelection::First(10))
}

/// The hash preset scaled down (as tests/gpu_train.rs, a smaller batch and table), the table
/// updated sparsely.
fn config(iters: u64) -> TrainConfig {
    let mut c = common::small_hash_config(iters, 4, 8);
    c.log_every = 100;
    c.target_samples_per_step = Some(1 << 12);
    c.field_config = serde_json::json!({"grid": {"log2_hashmap_size": 14}});
    c.adam.sparse_groups = vec!["hash_grid".into()];
    c
}

#[test]
fn an_unknown_sparse_group_is_refused() {
    let mut c = config(1);
    c.adam.sparse_groups = vec!["hash_table".into()];
    let train = load();
    let e = Trainer::new(c, &nerf::registry(), SceneBounds::of(&train)).err().expect("refused");
    let TrainError::Config(msg) = e else { panic!("{e}") };
    assert!(msg.contains("hash_table") && msg.contains("field/hash_grid"), "{msg}");
}

#[test]
fn table_entries_count_their_own_steps_on_either_device() {
    let train = load();
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let steps = 12u64;
    let gpu = GpuContext::for_tests().map(Arc::new);
    let mut states = Vec::new();
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let mut t = Trainer::new_on(config(steps), &registry, bounds, dev).unwrap();
        let init = t.export_fields().unwrap();
        for _ in 0..steps {
            t.step(&train).unwrap();
        }
        let st = t.adam_state().unwrap();
        assert_eq!(st.steps.len(), 1, "{}: only the table is sparse", t.device());
        let (name, counts) = &st.steps[0];
        assert_eq!(name, "field/hash_grid");
        assert!(counts.iter().all(|&k| k as u64 <= steps));
        // Coarse levels are reached every step, most fine-level entries never in 12 small batches.
        assert!(counts.iter().any(|&k| k as u64 == steps), "{}", t.device());
        assert!(counts.iter().any(|&k| k > 0 && (k as u64) < steps), "{}", t.device());
        let untouched = counts.iter().filter(|&&k| k == 0).count();
        assert!(untouched > 0, "{}", t.device());
        // Entries never reached keep their initial values.
        let now = t.export_fields().unwrap();
        let (_, p0) = init[0].iter().find(|(n, _)| n == "hash_grid").unwrap();
        let (_, p1) = now[0].iter().find(|(n, _)| n == "hash_grid").unwrap();
        for (i, &k) in counts.iter().enumerate() {
            assert_eq!(k == 0, p0[i] == p1[i], "{}: entry {i} (count {k})", t.device());
        }
        states.push((t.device().to_string(), st, now, t.sampler_state().unwrap()));
    }
    // A GPU checkpoint continues on the CPU with the same counts.
    if let Some((dev, st, fields, sampler)) = states.iter().find(|(d, ..)| d == "gpu") {
        let mut cpu = Trainer::new(config(steps + 1), &registry, bounds).unwrap();
        cpu.restore(steps, fields, st.clone(), sampler).unwrap();
        assert_eq!(cpu.adam_state().unwrap().steps, st.steps, "from {dev}");
        cpu.step(&train).unwrap();
        let after = cpu.adam_state().unwrap();
        let grew = after.steps[0].1.iter().zip(&st.steps[0].1).filter(|(a, b)| a > b).count();
        assert!(grew > 0 && after.steps[0].1.iter().zip(&st.steps[0].1).all(|(a, b)| a == b || *a == b + 1));
    }
}
