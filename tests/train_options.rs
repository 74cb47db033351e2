//! Training options that must reach both devices' step: `pixel_jitter` (rays through random points
//! of their pixels; the ray generators themselves are tested in crates/data and
//! crates/gpu/tests/sampling.rs) and `loss` (the Huber loss; its gradient is tested in
//! crates/render and crates/gpu/tests/kernels.rs), `distortion_loss` (likewise). Each option,
//! switched on alone, changes what one
//! step does to the parameters, on the CPU and (where an adapter exists) on the GPU, and
//! switching it off again reproduces the default run exactly.

use nerf::data::{Dataset, Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{LossConfig, SamplerConfig, SceneBounds, TrainConfig, TrainError, Trainer};
use std::path::Path;
use std::sync::Arc;

mod common;

/// The tests of this file take turns on the device: the reproducibility check below compares two
/// GPU runs bit for bit, and the hash grid's backward sums with float atomics, whose order
/// lavapipe keeps only while no other test's kernels share its threads.
static DEVICE: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn take_device() -> std::sync::MutexGuard<'static, ()> {
    DEVICE.lock().unwrap_or_else(|e| e.into_inner())
}

fn load() -> Dataset {
    common::load(Split::Train, ViewSelection::First(10))
}

/// The hash field, small: 32-wide nets and 128 rays a step. An untrained field's step marches
/// ~300 samples per ray, ~40 k samples, which lavapipe takes seconds over at the preset's widths.
fn config() -> TrainConfig {
    TrainConfig {
        field: "hash".into(),
        field_config: serde_json::json!({"grid": {"log2_hashmap_size": 14}, "density_hidden": 32, "color_hidden": 32}),
        sampler: SamplerConfig::Occupancy {
            grid: nerf::sampling::OccupancyGridConfig { resolution: 32, update_every: 16, warmup_steps: 64, ..Default::default() },
            step_size: 0.02,
            max_samples_per_ray: 256,
            cone_angle: None,
        },
        batch_rays: 128,
        seed: 3,
        ..TrainConfig::default()
    }
}

/// The in-repo scene's first test view as a 25×25 thumbnail (what `nerf::train::run` evaluates
/// at its end).
fn load_test_view() -> Dataset {
    common::thumbnails(Split::Test, 1)
}

/// Options of a `nerf::train::run` into `out` on `device`, without progress bar or renders.
fn quiet_run(out: &Path, device: nerf::gpu::DevicePreference) -> nerf::train::RunOptions {
    nerf::train::RunOptions { progress: false, write_renders: false, device, ..nerf::train::RunOptions::new(out) }
}

/// The parameters after `steps` steps of `c` on `dev`.
fn params_after(c: &TrainConfig, train: &Dataset, dev: Option<Arc<GpuContext>>, steps: usize) -> Vec<f32> {
    let mut t = Trainer::new_on(c.clone(), &nerf::registry(), SceneBounds::of(train), dev).unwrap();
    for _ in 0..steps {
        t.step(train).unwrap();
    }
    t.export_fields().unwrap().into_iter().flatten().flat_map(|(_, v)| v).collect()
}

#[test]
fn jitter_and_huber_loss_reach_the_step_on_both_devices() {
    let _device = take_device();
    let train = load();
    let gpu = GpuContext::for_tests().map(Arc::new);
    let base = config();
    let jitter = TrainConfig { pixel_jitter: true, ..config() };
    // δ small enough that most residuals of an untrained field lie beyond it.
    let huber = TrainConfig { loss: LossConfig::Huber { delta: 0.01 }, ..config() };
    let distortion = TrainConfig { distortion_loss: Some(0.05), ..config() };
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let p0 = params_after(&base, &train, dev.clone(), 2);
        assert_eq!(p0, params_after(&base, &train, dev.clone(), 2), "{name}: a run is reproducible");
        for (what, c) in [("pixel_jitter", &jitter), ("huber loss", &huber), ("distortion loss", &distortion)] {
            let p = params_after(c, &train, dev.clone(), 2);
            assert!(p.iter().all(|x| x.is_finite()), "{name}: {what}");
            let changed = p.iter().zip(&p0).filter(|(a, b)| a != b).count();
            assert!(changed > 100, "{name}: {what} changed only {changed} parameters");
        }
    }
}

/// A step whose loss comes out NaN is an error (`TrainError::Diverged`), not a run that goes on
/// training and evaluating NaN parameters: on the CPU at that step, on the GPU at the next
/// loss read-back (every `log_every` steps).
#[test]
fn non_finite_parameters_stop_training_with_a_divergence_error() {
    let _device = take_device();
    let train = load();
    let gpu = GpuContext::for_tests().map(Arc::new);
    let c = TrainConfig { log_every: 3, ..config() };
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let mut t = Trainer::new_on(c.clone(), &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
        t.step(&train).unwrap();
        // A NaN in every weight of the colour network: every rendered colour is NaN.
        let mut fields = t.export_fields().unwrap();
        let (_, w) = fields[0].iter_mut().find(|(n, _)| n == "color_mlp").expect("the hash field's colour network");
        w.fill(f32::NAN);
        let (adam, sampler) = (t.adam_state().unwrap(), t.sampler_state().unwrap());
        t.restore(1, &fields, adam, &sampler).unwrap();
        let mut outcome = Vec::new();
        for _ in 0..3 {
            match t.step(&train) {
                Ok(s) => outcome.push(Ok(s.loss)),
                Err(e) => {
                    outcome.push(Err(e));
                    break;
                }
            }
        }
        // CPU: the first step after the poisoning; GPU: the read-back after step 3.
        let want_step = if dev.is_some() { 3 } else { 2 };
        match outcome.last() {
            Some(Err(TrainError::Diverged { step, loss })) => {
                assert_eq!(*step, want_step, "{name}");
                assert!(!loss.is_finite(), "{name}");
                let msg = outcome.last().unwrap().as_ref().unwrap_err().to_string();
                assert!(msg.contains("diverged") && msg.contains("learning rate"), "{name}: {msg}");
            }
            other => panic!("{name}: expected a divergence error, got {other:?}"),
        }
        assert_eq!(outcome.len() as u64, want_step - 1, "{name}: {outcome:?}");
    }
}

/// On the GPU the loss is read back only every `log_every` steps; a run that diverges between
/// two read-backs is caught when it would save a checkpoint (here the periodic one at step 2,
/// long before the read-back at the last step), and nothing is written.
#[test]
fn a_gpu_run_never_checkpoints_non_finite_parameters() {
    let _device = take_device();
    let Some(gpu) = GpuContext::for_tests() else { return };
    drop(gpu);
    let train = load();
    let test = load_test_view();
    let c = TrainConfig {
        lr: nerf::optim::LrSchedule::Constant { lr: 1e30 },
        iters: 6,
        log_every: 1000,
        checkpoint_every: 2,
        ..config()
    };
    let dir = tempfile::tempdir().unwrap();
    let opts = quiet_run(dir.path(), nerf::gpu::DevicePreference::Gpu);
    match nerf::train::run(c, &nerf::registry(), &train, &test, &opts) {
        Err(TrainError::Diverged { step, .. }) => assert!(step < 6, "caught by the read-back at step {step}, not by the save"),
        Err(e) => panic!("expected a divergence, got {e}"),
        Ok(s) => panic!("a run with a learning rate of 1e30 finished: {}", s.metrics),
    }
    // Whichever periodic checkpoint came before the divergence holds finite parameters only.
    if let Ok(ck) = nerf::train::Checkpoint::load(&dir.path().join("checkpoint.bin")) {
        assert!(ck.fields.iter().flatten().all(|(_, v)| v.iter().all(|x| x.is_finite())));
    }
    assert!(!dir.path().join("metrics.json").exists());
}

/// The distortion loss is part of the step's loss on both devices (loss − photometric loss =
/// λ × its mean over the rays; exactly 0 when off), and training with it does what it is for
/// (CPU): it gathers each ray's weight, so the rays' mean distortion ends lower than in a run that
/// only measures it (λ 10⁵ times smaller).
#[test]
fn the_distortion_loss_is_counted_and_gathers_the_weights() {
    let _device = take_device();
    let train = load();
    let gpu = GpuContext::for_tests().map(Arc::new);
    // Mean distortion per ray, (loss − mse)/λ, over the last 10 (or all) of `steps` steps with λ.
    let measure_on = |base: TrainConfig, dev: Option<Arc<GpuContext>>, lambda: f32, steps: usize, compact: bool| -> f64 {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let threshold = if compact { 1e-4 } else { base.transmittance_threshold };
        let c = TrainConfig { distortion_loss: Some(lambda), log_every: 1, compact_samples: compact, transmittance_threshold: threshold, ..base };
        let mut t = Trainer::new_on(c, &nerf::registry(), SceneBounds::of(&train), dev).unwrap();
        let mut tail = Vec::new();
        for i in 0..steps {
            let s = t.step(&train).unwrap();
            assert!(s.loss.is_finite() && s.loss > s.mse, "{name}: step {i}: loss {} vs photometric {}", s.loss, s.mse);
            if i + 10 >= steps {
                tail.push((s.loss - s.mse) as f64 / lambda as f64);
            }
        }
        tail.iter().sum::<f64>() / tail.len() as f64
    };
    let measure = |dev: Option<Arc<GpuContext>>, lambda: f32, steps: usize| measure_on(config(), dev, lambda, steps, false);
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let c = TrainConfig { log_every: 1, ..config() };
        let mut t = Trainer::new_on(c, &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
        let s = t.step(&train).unwrap();
        assert_eq!(s.loss, s.mse, "{name}: without the distortion loss the loss is the photometric one");
        // Four steps: an untrained field's step marches ~300 samples per ray, which lavapipe
        // takes seconds over.
        let d = measure(dev.clone(), 1.0, 4);
        assert!(d > 0.0 && d < 1.0, "{name}: mean distortion {d}");
        // On compacted samples (the hash preset's default, where the last stage holds each ray's
        // kept samples only) the loss is counted the same way.
        let d = measure_on(config(), dev, 1.0, 4, true);
        assert!(d > 0.0 && d < 1.0, "{name}, compacted: mean distortion {d}");
    }
    // The untrained field is a haze through the whole box (distortion ~0.16 per ray); measured
    // on 2 cores: 0.147 (λ 1e-4) against 0.015 (λ 10) after 200 steps of the preset's 64-wide
    // nets on 256 rays. (At this file's 32-wide nets and 128 rays the weights had barely
    // gathered after 200 steps: 0.133 against 0.113.)
    let wide = TrainConfig {
        field_config: serde_json::json!({"grid": {"log2_hashmap_size": 14}}),
        batch_rays: 256,
        ..config()
    };
    let (measured, trained) = (measure_on(wide.clone(), None, 1e-4, 200, false), measure_on(wide, None, 10.0, 200, false));
    println!("cpu: mean distortion per ray {measured:.5} (λ 1e-4) vs {trained:.5} (λ 10)");
    assert!(trained < 0.5 * measured, "{trained} vs {measured}");
}

/// A `progress` learning-rate schedule follows the fraction of the run done: by default the
/// fraction of `iters`, or what the caller sets (`run` sets the time budget's fraction when that
/// is larger). The rate reaches the optimiser on both devices: a step at progress 0.6 of a
/// schedule that drops ×0.1 at 0.5 leaves the same parameters as a step at a constant 10⁻³.
#[test]
fn a_progress_schedule_follows_the_run_on_both_devices() {
    use nerf::optim::LrSchedule;
    let _device = take_device();
    let train = load();
    let progress = TrainConfig {
        lr: LrSchedule::Progress { lr0: 1e-2, gamma: 0.1, at: vec![0.5], warmup_steps: 0 },
        iters: 4,
        ..config()
    };
    let constant = |lr| TrainConfig { lr: LrSchedule::Constant { lr }, ..progress.clone() };
    let gpu = GpuContext::for_tests().map(Arc::new);
    for dev in std::iter::once(None).chain(gpu.map(Some)) {
        let name = if dev.is_some() { "gpu" } else { "cpu" };
        let mut t = Trainer::new_on(progress.clone(), &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
        // Steps 0 and 1 are before half of the 4 iterations, 2 and 3 after.
        let lrs: Vec<f32> = (0..4).map(|_| t.step(&train).unwrap().lr).collect();
        assert_eq!(lrs, [1e-2, 1e-2, 1e-3, 1e-3], "{name}");

        let mut late = Trainer::new_on(progress.clone(), &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
        late.set_progress(0.6);
        assert_eq!(late.learning_rate(), 1e-3);
        late.step(&train).unwrap();
        let p_late: Vec<f32> = late.export_fields().unwrap().into_iter().flatten().flat_map(|(_, v)| v).collect();
        assert_eq!(p_late, params_after(&constant(1e-3), &train, dev.clone(), 1), "{name}: the rate reached the step");
        assert_ne!(p_late, params_after(&constant(1e-2), &train, dev.clone(), 1), "{name}");
    }
}

/// `run` with a time budget anneals a `progress` schedule by the clock: a run of 10⁹ iterations
/// (its step fraction stays ~0) cut by a 3-second budget logs lr0 first and the dropped rate last.
#[test]
fn a_time_budget_drives_a_progress_schedule() {
    let _device = take_device();
    let train = load();
    let test = load_test_view();
    let c = TrainConfig {
        lr: nerf::optim::LrSchedule::Progress { lr0: 1e-2, gamma: 0.1, at: vec![0.5], warmup_steps: 0 },
        iters: 1_000_000_000,
        time_budget_secs: Some(3.0),
        log_every: 1,
        checkpoint_every: 0,
        ..config()
    };
    let dir = tempfile::tempdir().unwrap();
    let opts = quiet_run(dir.path(), nerf::gpu::DevicePreference::Cpu);
    nerf::train::run(c, &nerf::registry(), &train, &test, &opts).unwrap();
    let history = std::fs::read_to_string(dir.path().join("history.jsonl")).unwrap();
    let lrs: Vec<f64> = history.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["lr"].as_f64().unwrap()).collect();
    assert!(lrs.len() >= 4, "only {} steps in 3 s", lrs.len());
    assert!((lrs[0] - 1e-2).abs() < 1e-9, "first step at lr0: {}", lrs[0]);
    assert!((lrs[lrs.len() - 1] - 1e-3).abs() < 1e-9, "last step after half the budget: {}", lrs[lrs.len() - 1]);
    assert!(lrs.windows(2).all(|w| w[1] <= w[0]), "the rate never rises again");
}

/// `eval_spp`: the evaluation renders each test view through `eval_spp` points of every pixel
/// (`PixelConvention::sample_offsets`) and scores their mean; one point is the default
/// evaluation exactly. Checked against renders made here through the same points, on the CPU and
/// (where an adapter exists) on the GPU; an `eval_spp` of 0 is refused.
#[test]
fn supersampled_evaluation_scores_the_mean_of_its_renders() {
    let _device = take_device();
    let (train, test) = (load(), load_test_view());
    let devices = [None, GpuContext::for_tests().map(Arc::new)];
    for dev in devices.iter().enumerate().filter(|(i, d)| *i == 0 || d.is_some()).map(|(_, d)| d.clone()) {
        // A few small steps at 0.05 steps along the rays: the untrained field's steps and the ten
        // renders below march whole rays (lavapipe took 36 s over this test at `config`'s 0.02);
        // any field that is not uniform tells the renders apart.
        let mut c = config();
        if let SamplerConfig::Occupancy { step_size, max_samples_per_ray, .. } = &mut c.sampler {
            (*step_size, *max_samples_per_ray) = (0.05, 64);
        }
        let mut t = Trainer::new_on(c, &nerf::registry(), SceneBounds::of(&train), dev.clone()).unwrap();
        for _ in 0..10 {
            t.step(&train).unwrap();
        }
        let one = nerf::train::evaluate(&t, &test, None, |_, _| ()).unwrap();
        let (w, h) = (test.width as usize, test.height as usize);
        let (mut rgb, mut opacity, mut depth) = (vec![0.0f32; 3 * w * h], vec![0.0f32; w * h], vec![0.0f32; w * h]);
        let mut batch = nerf::data::RayBatch::default();
        let mut render = |t: &Trainer, point: [f32; 2], rgb: &mut Vec<f32>| {
            test.view_rays_at(0, t.config().eval_background, point, &mut batch);
            t.render_rays(&batch.origins, &batch.dirs, &batch.background, rgb, &mut opacity, &mut depth).unwrap();
            batch.target.clone()
        };
        // One point: the pixel convention's, the evaluation as it always was.
        let gt = render(&t, t.config().pixel_convention.sample_offsets(1)[0], &mut rgb);
        assert_eq!(one.psnr, nerf::metrics::psnr(&rgb, &gt), "device {:?}", t.device());
        // Four points: the mean of four renders.
        t.set_eval_spp(4).unwrap();
        let four = nerf::train::evaluate(&t, &test, None, |_, _| ()).unwrap();
        let mut sum = vec![0.0f32; 3 * w * h];
        for point in t.config().pixel_convention.sample_offsets(4) {
            render(&t, point, &mut rgb);
            sum.iter_mut().zip(&rgb).for_each(|(s, x)| *s += x);
        }
        let mean: Vec<f32> = sum.iter().map(|s| s * 0.25).collect();
        assert_eq!(four.psnr, nerf::metrics::psnr(&mean, &gt), "device {:?}", t.device());
        assert_ne!(four.psnr, one.psnr, "four points must render something else than one");
        assert!(t.set_eval_spp(0).is_err());
    }
}
