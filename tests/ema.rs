//! The parameters' exponential moving average (`TrainConfig::ema_decay`, instant-ngp's `Ema`):
//! the trainer keeps the debiased average of every step's parameters, renders with it (and only
//! rendering does), checkpoints carry it, and the GPU path keeps the same average as the CPU
//! (step by step here; tests/gpu_train.rs scores a whole GPU training of the hash preset, which
//! keeps the average, against the CPU's). GPU tests print a notice and return where no adapter exists.

use nerf::data::{Dataset, RayBatch, Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{Checkpoint, FieldParams, SceneBounds, TrainConfig, Trainer};
use std::sync::Arc;

mod common;
use common::load;

/// The hash field's preset scaled down (the grid refreshed every 4 steps after 8), with the
/// average on.
fn small_hash_config(iters: u64, ema: Option<f32>) -> TrainConfig {
    TrainConfig { ema_decay: ema, ..common::small_hash_config(iters, 4, 8) }
}

/// Renders the first view of `test` (colours, then opacities), outputs poisoned beforehand (the
/// tests pass [`common::thumbnails`]).
fn render(t: &Trainer, test: &Dataset) -> Vec<f32> {
    let mut batch = RayBatch::default();
    test.view_rays(0, t.config().eval_background, t.config().pixel_convention, &mut batch);
    let n = batch.len();
    let (mut rgb, mut op, mut depth) = (vec![f32::NAN; 3 * n], vec![f32::NAN; n], vec![f32::NAN; n]);
    t.render_rays(&batch.origins, &batch.dirs, &batch.background, &mut rgb, &mut op, &mut depth).unwrap();
    rgb.extend(op);
    assert!(rgb.iter().all(|x| x.is_finite()));
    rgb
}

fn mean_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len() as f32
}

/// The debiased average of the parameter history written out as a weighted sum, in f64:
/// `Σ_k (1−d)·d^(t−k)·p_k / (1 − d^t)` per group (`"<prefix>/<group>"` names, as the trainer's).
fn direct_average(decay: f64, history: &[FieldParams]) -> Vec<(String, Vec<f64>)> {
    let t = history.len() as i32;
    let prefixes: &[&str] = if history[0].len() == 1 { &["field"] } else { &["coarse", "fine"] };
    let mut out: Vec<(String, Vec<f64>)> = history[0]
        .iter()
        .zip(prefixes)
        .flat_map(|(groups, p)| groups.iter().map(move |(n, v)| (format!("{p}/{n}"), vec![0.0; v.len()])))
        .collect();
    for (k, params) in history.iter().enumerate() {
        let w = (1.0 - decay) * decay.powi(t - 1 - k as i32) / (1.0 - decay.powi(t));
        let flat = params.iter().flatten();
        for ((_, acc), (_, v)) in out.iter_mut().zip(flat) {
            for (a, &x) in acc.iter_mut().zip(v) {
                *a += w * x as f64;
            }
        }
    }
    out
}

/// Largest |a − b| over the groups of an EMA state against the direct average.
fn max_error(state: &nerf::optim::EmaState, direct: &[(String, Vec<f64>)]) -> f64 {
    assert_eq!(state.groups.len(), direct.len());
    let mut worst = 0.0f64;
    for (name, want) in direct {
        let (_, got) = state.groups.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("no EMA of {name}"));
        assert_eq!(got.len(), want.len(), "{name}");
        for (&g, &w) in got.iter().zip(want) {
            worst = worst.max(if g.is_finite() { (g as f64 - w).abs() } else { f64::INFINITY });
        }
    }
    worst
}

/// The average as field parameters (what a field would hold if the average were its weights).
fn ema_as_fields(state: &nerf::optim::EmaState, like: &FieldParams) -> FieldParams {
    let prefixes: &[&str] = if like.len() == 1 { &["field"] } else { &["coarse", "fine"] };
    like.iter()
        .zip(prefixes)
        .map(|(groups, p)| {
            groups
                .iter()
                .map(|(n, _)| {
                    let full = format!("{p}/{n}");
                    (n.clone(), state.groups.iter().find(|(g, _)| *g == full).unwrap().1.clone())
                })
                .collect()
        })
        .collect()
}

/// The sampler tensors without the average (what a run without `ema_decay` would store).
fn without_ema(state: &[(String, Vec<f32>)]) -> Vec<(String, Vec<f32>)> {
    state.iter().filter(|(n, _)| !n.starts_with("ema/")).cloned().collect()
}

#[test]
fn cpu_trainer_averages_every_step_and_renders_with_the_average() {
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let decay = 0.8;
    let config = small_hash_config(10, Some(decay));
    let mut t = Trainer::new(config.clone(), &registry, bounds).unwrap();
    assert_eq!(t.ema_state().unwrap().unwrap().step, 0);
    // Before any step there is no average: rendering uses the (initial) parameters.
    let plain_cfg = TrainConfig { ema_decay: None, ..config.clone() };
    let plain0 = Trainer::new(plain_cfg.clone(), &registry, bounds).unwrap();
    assert_eq!(render(&t, &test), render(&plain0, &test));
    let mut history = Vec::new();
    for step in 1..=config.iters {
        t.step(&train).unwrap();
        history.push(t.export_fields().unwrap());
        let s = t.ema_state().unwrap().unwrap();
        assert_eq!(s.step, step);
        if step == 1 {
            // The first update copies the parameters.
            assert_eq!(ema_as_fields(&s, &history[0]), history[0]);
        }
        // The recursion in f32 against the weighted sum in f64 (values are O(1e-2..1)).
        let e = max_error(&s, &direct_average(decay as f64, &history));
        assert!(e < 1e-5, "step {step}: EMA max |error| {e}");
    }
    let s = t.ema_state().unwrap().unwrap();
    let raw = t.export_fields().unwrap();
    assert_ne!(ema_as_fields(&s, &raw), raw, "the average must lag the raw parameters");

    // Rendering: the average, not the raw weights ...
    let with_ema = render(&t, &test);
    let sampler = t.sampler_state().unwrap();
    assert!(sampler.iter().any(|(n, v)| n == "ema/step" && v[..] == [10.0, 0.0]));
    let mut raw_t = Trainer::new(plain_cfg.clone(), &registry, bounds).unwrap();
    raw_t.restore(t.step_count(), &raw, t.adam_state().unwrap(), &without_ema(&sampler)).unwrap();
    let with_raw = render(&raw_t, &test);
    let d_raw = mean_abs_diff(&with_ema, &with_raw);
    assert!(d_raw > 1e-4, "EMA render equals the raw render (mean |Δ| {d_raw})");
    // ... exactly what a field whose parameters are the average renders (same grid).
    let mut ema_t = Trainer::new(plain_cfg, &registry, bounds).unwrap();
    ema_t.restore(t.step_count(), &ema_as_fields(&s, &raw), t.adam_state().unwrap(), &without_ema(&sampler)).unwrap();
    assert_eq!(with_ema, render(&ema_t, &test));
    // Training kept stepping the raw parameters: a plain run with the same seed got the same ones.
    let mut plain = Trainer::new(TrainConfig { ema_decay: None, ..config.clone() }, &registry, bounds).unwrap();
    for _ in 0..config.iters {
        plain.step(&train).unwrap();
    }
    assert_eq!(plain.export_fields().unwrap(), raw);
    // Rendering twice (cached average) and after another step (re-synced) stays consistent.
    assert_eq!(render(&t, &test), with_ema);
    t.step(&train).unwrap();
    let again = render(&t, &test);
    assert_ne!(again, with_ema);
}

/// What `nerf train` would checkpoint of `t` now.
fn checkpoint_of(t: &Trainer) -> Checkpoint {
    Checkpoint {
        step: t.step_count(),
        elapsed_secs: 0.0,
        samples_seen: 0,
        config: t.config().clone(),
        fields: t.export_fields().unwrap(),
        adam: t.adam_state().unwrap(),
        sampler: t.sampler_state().unwrap(),
        render_only: false,
    }
}

#[test]
fn checkpoints_carry_the_average() {
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let config = small_hash_config(8, Some(0.9));
    let mut t = Trainer::new(config.clone(), &registry, bounds).unwrap();
    for _ in 0..6 {
        t.step(&train).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("checkpoint.bin");
    checkpoint_of(&t).save(&path).unwrap();
    let back = Checkpoint::load(&path).unwrap();
    assert_eq!(back.config.ema_decay, Some(0.9));
    let mut resumed = Trainer::new(back.config.clone(), &registry, bounds).unwrap();
    resumed.restore(back.step, &back.fields, back.adam, &back.sampler).unwrap();
    assert_eq!(resumed.ema_state().unwrap(), t.ema_state().unwrap());
    // The same render (the average, on the same grid) ...
    let before = render(&t, &test);
    assert_eq!(render(&resumed, &test), before);
    // ... and the resumed run continues exactly as the uninterrupted one.
    for _ in 0..2 {
        t.step(&train).unwrap();
        resumed.step(&train).unwrap();
    }
    assert_eq!(resumed.ema_state().unwrap(), t.ema_state().unwrap());
    assert_eq!(render(&resumed, &test), render(&t, &test));

    // A checkpoint without an average (an older run, or one without `ema_decay`) still loads: the
    // average starts afresh, so rendering uses the raw parameters until the next step.
    let old = Checkpoint { sampler: without_ema(&back.sampler), ..Checkpoint::load(&path).unwrap() };
    let mut fresh = Trainer::new(config.clone(), &registry, bounds).unwrap();
    fresh.restore(old.step, &old.fields, old.adam.clone(), &old.sampler).unwrap();
    assert_eq!(fresh.ema_state().unwrap().unwrap().step, 0);
    let mut plain = Trainer::new(TrainConfig { ema_decay: None, ..config.clone() }, &registry, bounds).unwrap();
    plain.restore(old.step, &old.fields, old.adam.clone(), &old.sampler).unwrap();
    assert_eq!(render(&fresh, &test), render(&plain, &test));
    fresh.step(&train).unwrap();
    assert_eq!(fresh.ema_state().unwrap().unwrap().step, 1);
    // A run without `ema_decay` ignores an average in the checkpoint (renders raw).
    let mut ignoring = Trainer::new(TrainConfig { ema_decay: None, ..config.clone() }, &registry, bounds).unwrap();
    ignoring.restore(back.step, &back.fields, Checkpoint::load(&path).unwrap().adam, &back.sampler).unwrap();
    assert_eq!(ignoring.ema_state().unwrap(), None);
    assert_eq!(render(&ignoring, &test), render(&plain, &test));
    // An average that does not fit the run is rejected with the group's name.
    let mut bad = back.sampler.clone();
    let i = bad.iter().position(|(n, _)| n.starts_with("ema/field/")).unwrap();
    let name = bad[i].0.clone();
    bad[i].1.pop();
    let mut t2 = Trainer::new(config, &registry, bounds).unwrap();
    let e = t2.restore(back.step, &back.fields, old.adam, &bad).unwrap_err().to_string();
    assert!(e.contains(name.trim_start_matches("ema/")), "{e}");
}

/// A render-only copy (`Checkpoint::for_rendering`, `nerf slim`) renders exactly the image the
/// full checkpoint renders — the average, on the same occupancy grid — on the CPU and, from a GPU
/// run, on the GPU; restoring the raw parameters of the full checkpoint without the average
/// renders another image, so the copy really carries the average.
#[test]
fn a_render_only_copy_renders_what_the_full_checkpoint_renders() {
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let config = small_hash_config(8, Some(0.9));
    let check = |ctx: Option<Arc<GpuContext>>| {
        let mut t = Trainer::new_on(config.clone(), &registry, bounds, ctx.clone()).unwrap();
        for _ in 0..6 {
            t.step(&train).unwrap();
        }
        let full = checkpoint_of(&t);
        let restored = |ck: &Checkpoint| {
            let mut r = Trainer::new_on(ck.config.for_rendering(), &registry, bounds, ctx.clone()).unwrap();
            r.restore(ck.step, &ck.fields, ck.adam.clone(), &ck.sampler).unwrap();
            render(&r, &test)
        };
        let slim = full.for_rendering().unwrap();
        assert!(slim.config.ema_decay.is_none() && slim.adam.groups.is_empty());
        let image = restored(&full);
        assert_eq!(image, render(&t, &test), "the full checkpoint renders the trainer's image");
        assert_eq!(restored(&slim), image, "the render-only copy renders the same image ({})", t.device());
        let raw = Checkpoint { config: TrainConfig { ema_decay: None, ..full.config.clone() }, sampler: without_ema(&full.sampler), ..full.clone() };
        assert_ne!(restored(&raw), image, "the raw parameters render another image");
    };
    check(None);
    match device() {
        Some(ctx) => check(Some(ctx)),
        None => eprintln!("NOTICE: no GPU adapter; the render-only copy was checked on the CPU only"),
    }
}

fn device() -> Option<Arc<GpuContext>> {
    GpuContext::for_tests().map(Arc::new)
}

#[test]
fn gpu_average_matches_the_direct_sum_and_renders_the_same_on_the_cpu() {
    let Some(ctx) = device() else { return };
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let decay = 0.8;
    let config = small_hash_config(12, Some(decay));
    let mut gpu = Trainer::new_on(config.clone(), &registry, bounds, Some(ctx)).unwrap();
    assert_eq!(gpu.device(), "gpu");
    let mut history = Vec::new();
    for step in 1..=config.iters {
        gpu.step(&train).unwrap();
        history.push(gpu.export_fields().unwrap());
        let s = gpu.ema_state().unwrap().unwrap();
        assert_eq!(s.step, step);
        // Device f32 (FMA contraction) against the f64 sum of the device's own parameters.
        let e = max_error(&s, &direct_average(decay as f64, &history));
        assert!(e < 1e-5, "step {step}: GPU EMA max |error| {e}");
    }
    // Rendering with the average leaves the raw parameters in place (training goes on from them).
    let raw = gpu.export_fields().unwrap();
    let g_ema = render(&gpu, &test);
    assert_eq!(gpu.export_fields().unwrap(), raw);
    // The same average on the CPU (moved through the checkpoint tensors) renders the same image.
    let mut cpu = Trainer::new(config.clone(), &registry, bounds).unwrap();
    cpu.restore(gpu.step_count(), &raw, gpu.adam_state().unwrap(), &gpu.sampler_state().unwrap()).unwrap();
    assert_eq!(cpu.ema_state().unwrap(), gpu.ema_state().unwrap());
    let c_ema = render(&cpu, &test);
    let mut plain = Trainer::new(TrainConfig { ema_decay: None, ..config.clone() }, &registry, bounds).unwrap();
    plain.restore(gpu.step_count(), &raw, gpu.adam_state().unwrap(), &without_ema(&gpu.sampler_state().unwrap())).unwrap();
    let c_raw = render(&plain, &test);
    let (d_dev, d_raw) = (mean_abs_diff(&g_ema, &c_ema), mean_abs_diff(&g_ema, &c_raw));
    println!("GPU EMA render vs CPU EMA render: mean |Δ| {d_dev:.2e}; vs CPU raw render: {d_raw:.2e}");
    // Devices differ by summation order (tests/gpu_train.rs: mean < 1e-3); the raw weights'
    // image must be much further away, or the GPU did not render with the average.
    assert!(d_dev < 1e-3, "GPU vs CPU EMA renders: mean |Δ| {d_dev}");
    assert!(d_raw > 10.0 * d_dev.max(1e-5), "GPU EMA render vs raw render: {d_raw} (devices: {d_dev})");
    // And a CPU run's average moves to the GPU: the GPU then renders the CPU's image.
    let mut back = Trainer::new_on(config, &registry, bounds, device()).unwrap();
    back.restore(cpu.step_count(), &cpu.export_fields().unwrap(), cpu.adam_state().unwrap(), &cpu.sampler_state().unwrap())
        .unwrap();
    assert_eq!(back.ema_state().unwrap(), cpu.ema_state().unwrap());
    let d_back = mean_abs_diff(&render(&back, &test), &c_ema);
    assert!(d_back < 1e-3, "CPU average rendered on the GPU: mean |Δ| {d_back}");
}
