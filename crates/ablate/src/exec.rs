//! Running the planned runs: training to the budget with evaluation points, metrics, skipping.

use crate::report::write_summary;
use crate::spec::{Ablation, RunPlan};
use crate::AblateError;
use nerf_data::{load_scene, Dataset, LoadOptions, Split, ViewSelection};
use nerf_field::Registry;
use nerf_train::{evaluate, make_trainer, AlphaSplit, Checkpoint, DepthError, EvalReport, MaskedMetrics, SceneBounds, TrainConfig, TrainError, Trainer, ViewMetrics};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One evaluation point of a run's curve.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    /// Steps taken.
    pub iter: u64,
    /// Training seconds so far (evaluation excluded).
    pub seconds: f64,
    /// Mean test PSNR, dB.
    pub psnr: f64,
    /// Mean test SSIM.
    pub ssim: f64,
}

/// One line of a run's training log (`nerf train`'s `history.jsonl` keys), every `log_every` steps
/// and at the last step, where the step's loss was read back (on a GPU, only at those steps).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainLogPoint {
    /// Steps taken.
    pub step: u64,
    /// Training seconds so far (evaluation excluded).
    pub elapsed_secs: f64,
    /// The step's loss.
    pub loss: f32,
    /// PSNR of the step's photometric MSE on its training rays (their random backgrounds
    /// included), dB.
    pub train_psnr: f64,
    /// Learning rate of the step.
    pub lr: f32,
    /// Samples trained on in the step (after compaction, with `compact_samples`).
    pub samples: usize,
    /// Samples marched in the step (before compaction).
    pub marched_samples: usize,
    /// Rays in the step's batch.
    #[serde(default)]
    pub rays: usize,
    /// Rays that met at least one sample (positive opacity; nerfacc's `alive_ray_mask`).
    #[serde(default)]
    pub alive_rays: usize,
    /// PSNR of the photometric MSE over those rays alone, dB: what nerfacc's training log prints
    /// (as an MSE). `null` without such a ray.
    #[serde(default)]
    pub train_psnr_alive: Option<f64>,
}

/// What a finished run wrote to `runs/<id>/metrics.json` (stable keys, shared with `nerf train`
/// where they apply).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunMetrics {
    /// Run id.
    pub id: String,
    /// Explicit run name.
    pub name: String,
    /// Scene folder.
    pub scene: String,
    /// Seed.
    pub seed: u64,
    /// Grid point: dotted key → value.
    pub grid: serde_json::Map<String, serde_json::Value>,
    /// Field registry name.
    pub field: String,
    /// Always `"cpu"` (the trainer runs on the CPU).
    pub device: String,
    /// Steps taken.
    pub iterations: u64,
    /// Training seconds (evaluation excluded).
    pub wall_seconds: f64,
    /// Milliseconds per training step.
    pub ms_per_iter: f64,
    /// Field samples processed per training second.
    pub samples_per_sec: f64,
    /// Final mean test PSNR, dB.
    pub test_psnr: f64,
    /// Final mean test SSIM.
    pub test_ssim: f64,
    /// Number of test views.
    pub n_test_views: usize,
    /// Test image width.
    pub width: u32,
    /// Test image height.
    pub height: u32,
    /// Trainable parameters (all field instances).
    pub n_params: usize,
    /// Peak resident memory of the process during the run, MiB (`null` where unavailable).
    pub peak_memory_mib: Option<f64>,
    /// Test views rendered per second in the last evaluation (rendering alone, at the test views'
    /// resolution, on the run's device).
    #[serde(default)]
    pub render_fps: f64,
    /// Evaluation points.
    pub curve: Vec<CurvePoint>,
    /// The last evaluation's error split by ground-truth alpha (scenes with empty pixels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_split: Option<AlphaSplit>,
    /// The last evaluation's depth error against the test views' depth maps (scenes with them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_depth: Option<DepthError>,
    /// The last evaluation's scores over the pixels the test views' masks keep (scenes whose
    /// test views have masks).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_masked: Option<MaskedMetrics>,
    /// The last evaluation's metrics per test view.
    #[serde(default)]
    pub per_view: Vec<ViewMetrics>,
    /// The training log: loss, training PSNR and samples every `log_every` steps.
    #[serde(default)]
    pub train_log: Vec<TrainLogPoint>,
    /// See [`crate::config_hash`].
    pub config_hash: String,
    /// The resolved training config (as asked: see `device_note` for what the device changed).
    pub config: TrainConfig,
    /// What the GPU path changed to fit the adapter (fewer samples per step), if anything.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_note: Option<String>,
    /// Per-kernel GPU timings of the steps `config.gpu_profile` asked for (GPU runs only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_profile: Option<nerf_train::GpuProfile>,
    /// With `camera_optimizer`: the learnt corrections' mean sizes (`mean_translation`,
    /// `mean_rotation_degrees`); every view's goes to `runs/<id>/camera_corrections.json`
    /// (`nerf_train::pose::corrections_json`, as `nerf train` writes it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_corrections: Option<serde_json::Value>,
    /// The whole `camera_corrections.json` (not part of metrics.json).
    #[serde(skip)]
    pub camera_corrections_file: Option<serde_json::Value>,
}

/// The outcome of one run of an ablation.
#[derive(Clone, Debug)]
pub struct RunOutcome {
    /// The plan.
    pub plan: RunPlan,
    /// True when the run's finished `metrics.json` (same config hash) was reused.
    pub skipped: bool,
    /// Its metrics.
    pub metrics: RunMetrics,
}

/// Everything an ablation produced.
#[derive(Clone, Debug)]
pub struct AblationReport {
    /// Output folder.
    pub out_dir: PathBuf,
    /// Every run, in plan order.
    pub runs: Vec<RunOutcome>,
    /// `results.csv`.
    pub results_csv: PathBuf,
    /// `results.md`.
    pub results_md: PathBuf,
    /// `psnr_vs_time.png`.
    pub psnr_vs_time: PathBuf,
    /// `psnr_vs_iter.png`.
    pub psnr_vs_iter: PathBuf,
    /// Runs whose loss turned NaN or infinite (`TrainError::Diverged`): `(run id, step)`. They
    /// are left out of `runs`, the tables and the plots, and listed at the end of `results.md`;
    /// the other runs go on (a learning-rate sweep is expected to diverge at its high end).
    pub diverged: Vec<(String, u64)>,
}

/// Options of [`run_ablation`].
#[derive(Clone, Debug)]
pub struct AblateOptions {
    /// Output folder (`runs/<id>/…` and the summary files).
    pub out_dir: PathBuf,
    /// Print one line per run start/finish to stderr.
    pub verbose: bool,
    /// Device of every run (`auto` / `cpu` / `gpu`, as `nerf train --device`). A finished run is
    /// reused only when it ran on the same kind of device.
    pub device: nerf_gpu::DevicePreference,
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> AblateError + '_ {
    move |source| AblateError::Io { path: path.to_path_buf(), error: source }
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AblateError> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(io_err(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Loads a finished run's metrics when they exist and carry `hash`.
fn load_finished(path: &Path, hash: &str) -> Option<RunMetrics> {
    let text = std::fs::read_to_string(path).ok()?;
    let m: RunMetrics = serde_json::from_str(&text).ok()?;
    (m.config_hash == hash).then_some(m)
}

/// Resets the kernel's peak-RSS counter of this process (Linux; errors ignored).
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Peak resident set size (VmHWM) in MiB, where the OS reports it.
fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

fn log_point(s: &nerf_train::StepStats, step: u64, elapsed_secs: f64) -> TrainLogPoint {
    TrainLogPoint {
        step,
        elapsed_secs,
        loss: s.loss,
        train_psnr: nerf_metrics::mse_to_psnr(s.mse as f64),
        lr: s.lr,
        samples: s.n_samples,
        marched_samples: s.n_marched,
        rays: s.n_rays,
        alive_rays: s.alive_rays,
        train_psnr_alive: s.psnr_alive(),
    }
}

/// Trains one planned run to its budget, evaluating at the schedule's points and at the end.
///
/// With `checkpoint`, the trained fields are written there (atomically) after the final
/// evaluation, in `nerf train`'s checkpoint format. With `progress`, each training-log point and
/// each evaluation is printed to stderr as it happens, after that prefix.
#[allow(clippy::too_many_arguments)]
pub fn train_run(
    ablation: &Ablation,
    plan: &RunPlan,
    registry: &Registry,
    train: &Dataset,
    test: &Dataset,
    device: nerf_gpu::DevicePreference,
    checkpoint: Option<&Path>,
    progress: Option<&str>,
) -> Result<RunMetrics, AblateError> {
    let terr = |source| AblateError::Train { id: plan.id.clone(), error: source };
    let sched = &ablation.spec.eval;
    let cfg = &plan.config;
    reset_peak_rss();
    let trainer = make_trainer(cfg, registry, SceneBounds::of(train), device).map_err(terr);
    let mut trainer = trainer?;
    let budget = cfg.time_budget_secs.unwrap_or(f64::INFINITY);
    let mut elapsed = 0.0f64;
    let mut next_secs = sched.every_seconds.unwrap_or(f64::INFINITY);
    let mut curve: Vec<CurvePoint> = Vec::new();
    let render_fps = std::cell::Cell::new(0.0f64);
    let last_report = std::cell::RefCell::new(None::<EvalReport>);
    let eval_point = |t: &Trainer, elapsed: f64, curve: &mut Vec<CurvePoint>| {
        let r = evaluate(t, test, None, |_, _| {}).map_err(terr)?;
        if r.psnr.is_nan() {
            // NaN parameters between two GPU loss read-backs: the run diverged.
            return Err(terr(TrainError::Diverged { step: t.step_count(), loss: f32::NAN }));
        }
        curve.push(CurvePoint { iter: t.step_count(), seconds: elapsed, psnr: r.psnr, ssim: r.ssim });
        if let Some(prefix) = progress {
            eprintln!("{prefix}: step {}, {elapsed:.1} s: test PSNR {:.2} dB, SSIM {:.4}", t.step_count(), r.psnr, r.ssim);
        }
        if r.render_seconds > 0.0 {
            render_fps.set(r.views.len() as f64 / r.render_seconds);
        }
        *last_report.borrow_mut() = Some(r);
        Ok::<_, AblateError>(())
    };
    // The clock runs over segments between evaluations (excluded). GPU steps are queued, so a
    // segment ends with `finish()` (wait for the device) before the clock is read.
    let mut seg_base = 0.0f64;
    let mut seg = Instant::now();
    let mut profile = None;
    let mut train_log: Vec<TrainLogPoint> = Vec::new();
    let mut last_point = None;
    while trainer.step_count() < cfg.iters && elapsed < budget {
        trainer.set_progress(nerf_train::run_progress(trainer.step_count(), cfg.iters, elapsed, budget));
        let stats = trainer.step(train).map_err(terr)?;
        if let Some(p) = trainer.take_gpu_profile(false) {
            eprintln!("[{}] {}", plan.id, p.table(25));
            profile = Some(p);
        }
        elapsed = seg_base + seg.elapsed().as_secs_f64();
        let done = trainer.step_count();
        if stats.loss.is_finite() {
            let point = log_point(&stats, done, elapsed);
            if done % cfg.log_every.max(1) == 0 {
                if let Some(prefix) = progress {
                    let alive = point
                        .train_psnr_alive
                        .map(|p| format!(" ({p:.2} dB over the {} of {} rays with opacity > 0)", point.alive_rays, point.rays))
                        .unwrap_or_default();
                    eprintln!(
                        "{prefix}: step {done}, {elapsed:.1} s: loss {:.3e}, training PSNR {:.2} dB{alive}",
                        point.loss, point.train_psnr
                    );
                }
                train_log.push(point);
            }
            last_point = Some(point);
        }
        let by_iter = sched.every_iters.is_some_and(|k| done % k == 0);
        let by_time = elapsed >= next_secs;
        if by_time {
            while next_secs <= elapsed {
                next_secs += sched.every_seconds.unwrap_or(f64::INFINITY);
            }
        }
        if by_iter || by_time {
            trainer.finish().map_err(terr)?;
            elapsed = seg_base + seg.elapsed().as_secs_f64();
            eval_point(&trainer, elapsed, &mut curve)?;
            seg_base = elapsed;
            seg = Instant::now();
        }
    }
    trainer.finish().map_err(terr)?;
    if let Some(p) = trainer.take_gpu_profile(true) {
        eprintln!("[{}] {}", plan.id, p.table(25));
        profile = Some(p);
    }
    if curve.last().map(|p| p.iter) != Some(trainer.step_count()) {
        elapsed = elapsed.max(seg_base + seg.elapsed().as_secs_f64());
        eval_point(&trainer, elapsed, &mut curve)?;
    }
    if let Some(p) = last_point.filter(|p| train_log.last().map(|q| q.step) != Some(p.step)) {
        train_log.push(p);
    }
    let last = *curve.last().expect("at least the final evaluation");
    let corrections = trainer.pose_params().map_err(terr)?.map(|p| nerf_train::pose::corrections_json(&p, &train.cameras, &train.view_names()));
    let iters = trainer.step_count();
    let samples = trainer.samples_seen().map_err(terr)?;
    let report = last_report.into_inner().expect("at least the final evaluation");
    if let Some(path) = checkpoint {
        let dir = path.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        Checkpoint {
            step: iters,
            elapsed_secs: elapsed,
            samples_seen: samples,
            config: cfg.clone(),
            fields: trainer.export_fields().map_err(terr)?,
            adam: trainer.adam_state().map_err(terr)?,
            sampler: trainer.sampler_state().map_err(terr)?,
            render_only: false,
        }
        .save(path)
        .map_err(terr)?;
    }
    Ok(RunMetrics {
        id: plan.id.clone(),
        name: plan.name.clone(),
        scene: plan.scene.display().to_string(),
        seed: plan.seed,
        grid: plan.grid.iter().cloned().collect(),
        field: cfg.field.clone(),
        device: match trainer.adapter() {
            Some(a) => format!("gpu: {a}"),
            None => "cpu".into(),
        },
        iterations: iters,
        wall_seconds: elapsed,
        ms_per_iter: if iters > 0 { 1e3 * elapsed / iters as f64 } else { 0.0 },
        samples_per_sec: if elapsed > 0.0 { samples as f64 / elapsed } else { 0.0 },
        test_psnr: last.psnr,
        test_ssim: last.ssim,
        n_test_views: test.n_views(),
        width: test.width,
        height: test.height,
        n_params: trainer.n_params(),
        peak_memory_mib: peak_rss_mib(),
        render_fps: render_fps.get(),
        curve,
        alpha_split: report.alpha_split,
        test_depth: report.depth,
        test_masked: report.masked,
        per_view: report.views,
        train_log,
        config_hash: plan.config_hash.clone(),
        config: cfg.clone(),
        device_note: trainer.device_note().map(str::to_string),
        gpu_profile: profile,
        camera_corrections: corrections
            .as_ref()
            .map(|c| serde_json::json!({ "mean_translation": c["mean_translation"], "mean_rotation_degrees": c["mean_rotation_degrees"] })),
        camera_corrections_file: corrections,
    })
}

/// Runs (or reuses) every run of the ablation, then rebuilds `results.csv`, `results.md`,
/// `psnr_vs_time.png` and `psnr_vs_iter.png` under `opts.out_dir` from all runs.
pub fn run_ablation(
    ablation: &Ablation,
    registry: &Registry,
    opts: &AblateOptions,
) -> Result<AblationReport, AblateError> {
    let plans = ablation.plan(registry)?;
    let out = &opts.out_dir;
    let s = &ablation.spec;
    // Loaded scenes by folder and ray space (a run's `ndc` picks it for forward-facing scenes).
    let mut cache: HashMap<(PathBuf, String), (Dataset, Dataset)> = HashMap::new();
    let mut outcomes = Vec::with_capacity(plans.len());
    let mut diverged = Vec::new();
    for (k, plan) in plans.into_iter().enumerate() {
        let dir = out.join("runs").join(&plan.id);
        let mpath = dir.join("metrics.json");
        let same_device = |m: &RunMetrics| match opts.device {
            nerf_gpu::DevicePreference::Cpu => m.device == "cpu",
            nerf_gpu::DevicePreference::Gpu => m.device.starts_with("gpu"),
            nerf_gpu::DevicePreference::Auto => true,
        };
        // A file that asks for checkpoints trains again a finished run that has none.
        let has_checkpoint = !s.checkpoints || dir.join("checkpoint.bin").is_file();
        if let Some(m) = load_finished(&mpath, &plan.config_hash).filter(same_device).filter(|_| has_checkpoint) {
            if opts.verbose {
                eprintln!("[{}] {} finished before: PSNR {:.2} dB (skipped)", k + 1, plan.id, m.test_psnr);
            }
            outcomes.push(RunOutcome { plan, skipped: true, metrics: m });
            continue;
        }
        // Runs whose configs load the scene alike share it (NDC, lens, box, pose normalisation,
        // depth maps).
        let load_opts = |views| LoadOptions { downscale: s.downscale, ..plan.config.load_options(views, false, plan.config.depth_loss.is_some()) };
        let key = (plan.scene.clone(), format!("{:?}", load_opts(ViewSelection::All)));
        if !cache.contains_key(&key) {
            let load = |split, views| load_scene(&plan.scene, split, &load_opts(views)).map_err(|e| AblateError::Scene { path: plan.scene.clone(), message: e.to_string() });
            let train = load(Split::Train, s.train_views.clone())?;
            let test = load(Split::Test, s.test_views.clone())?;
            cache.insert(key.clone(), (train, test));
        }
        let (train, test) = &cache[&key];
        if opts.verbose {
            eprintln!("[{}] {} ({}) starting", k + 1, plan.id, plan.config.field);
        }
        let checkpoint = s.checkpoints.then(|| dir.join("checkpoint.bin"));
        let prefix = format!("[{}] {}", k + 1, plan.id);
        let progress = opts.verbose.then_some(prefix.as_str());
        let m = match train_run(ablation, &plan, registry, train, test, opts.device, checkpoint.as_deref(), progress) {
            Err(AblateError::Train { id, error: TrainError::Diverged { step, loss } }) => {
                eprintln!("[{}] {id} diverged: loss {loss} after step {step}; left out of the results", k + 1);
                diverged.push((id, step));
                continue;
            }
            r => r?,
        };
        std::fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        let mut csv = String::from("iter,seconds,psnr,ssim\n");
        for p in &m.curve {
            csv.push_str(&format!("{},{},{},{}\n", p.iter, p.seconds, p.psnr, p.ssim));
        }
        write_atomic(&dir.join("curve.csv"), csv.as_bytes())?;
        if let Some(c) = &m.camera_corrections_file {
            let text = serde_json::to_string_pretty(c).expect("a JSON value serialises");
            write_atomic(&dir.join("camera_corrections.json"), text.as_bytes())?;
        }
        let text = serde_json::to_string_pretty(&m).expect("metrics serialise");
        write_atomic(&mpath, text.as_bytes())?;
        // Summaries are built from the metrics as read back (serde_json's float parsing need not
        // round-trip the last bit), so a re-run that reuses this file rebuilds them identically.
        let m: RunMetrics = serde_json::from_str(&text).expect("metrics parse back");
        if opts.verbose {
            eprintln!(
                "[{}] {} done: {} steps, {:.1} s, PSNR {:.2} dB, SSIM {:.4}",
                k + 1,
                plan.id,
                m.iterations,
                m.wall_seconds,
                m.test_psnr,
                m.test_ssim
            );
        }
        outcomes.push(RunOutcome { plan, skipped: false, metrics: m });
    }
    let keys: Vec<String> = s.grid.keys().cloned().collect();
    write_summary(out, &ablation.name(), &keys, outcomes, diverged)
}
