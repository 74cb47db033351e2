//! A whole training run: budget, progress, checkpoints, resume, Ctrl-C, evaluation, metrics.json.

use crate::checkpoint::Checkpoint;
use crate::config::TrainConfig;
use crate::eval::{evaluate, EvalReport};
use crate::trainer::{SceneBounds, Trainer};
use crate::TrainError;
use indicatif::{ProgressBar, ProgressStyle};
use nerf_data::Dataset;
use nerf_field::Registry;
use serde_json::json;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// How a run is carried out (as opposed to what is trained, which is [`TrainConfig`]).
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Output folder: `checkpoint.bin`, `history.jsonl`, `renders/`, `metrics.json` (and, for a
    /// nerfstudio capture, nerfstudio's `dataparser_transforms.json`).
    pub out_dir: PathBuf,
    /// Continue from `<out_dir>/checkpoint.bin` when it exists.
    pub resume: bool,
    /// Start over in an `out_dir` that holds an interrupted run (a checkpoint without
    /// `metrics.json`), replacing it. Without it (and without `resume`) such a folder is an error,
    /// so re-running a command after Ctrl-C does not throw the interrupted run away. A finished
    /// run (one with `metrics.json`) is always replaced.
    pub overwrite: bool,
    /// Show a progress bar on stderr.
    pub progress: bool,
    /// Set (e.g. by a Ctrl-C handler) to stop after the current step and save a checkpoint.
    pub stop: Arc<AtomicBool>,
    /// Write the rendered test views as PNG.
    pub write_renders: bool,
    /// Scene name recorded in metrics.json.
    pub scene: String,
    /// Where the step runs: `auto` (the GPU when an adapter exists and the field has a GPU twin,
    /// else the CPU), `cpu`, or `gpu` (an error without an adapter). `NERF_DEVICE` overrides it.
    pub device: nerf_gpu::DevicePreference,
}

impl RunOptions {
    /// Defaults: no resume, progress bar, renders written, a fresh stop flag.
    pub fn new(out_dir: impl Into<PathBuf>) -> Self {
        Self {
            out_dir: out_dir.into(),
            resume: false,
            overwrite: false,
            progress: true,
            stop: Arc::new(AtomicBool::new(false)),
            write_renders: true,
            scene: String::new(),
            device: nerf_gpu::DevicePreference::Auto,
        }
    }
}

/// The outcome of [`run`].
#[derive(Clone, Debug)]
pub struct RunSummary {
    /// What was written to `metrics.json`.
    pub metrics: serde_json::Value,
    /// Evaluation on the test views.
    pub eval: EvalReport,
    /// Steps taken in total (including resumed ones).
    pub iterations: u64,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |e| TrainError::Io { path: path.to_path_buf(), source: e }
}

/// Writes `bytes` to `path` atomically (temporary file + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(io_err(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Trains `config` on `train`, evaluates on `test`, and writes results under `opts.out_dir`.
pub fn run(
    config: TrainConfig,
    registry: &Registry,
    train: &Dataset,
    test: &Dataset,
    opts: &RunOptions,
) -> Result<RunSummary, TrainError> {
    let out = &opts.out_dir;
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    let ck_path = out.join("checkpoint.bin");
    let metrics_path = out.join("metrics.json");
    let resuming = opts.resume && ck_path.exists();
    if !resuming {
        if ck_path.exists() && !metrics_path.exists() && !opts.overwrite {
            let step = Checkpoint::read_step(&ck_path)?;
            return Err(TrainError::OutDirInUse { out: out.clone(), step });
        }
        if opts.resume {
            eprintln!("note: {} holds no checkpoint; starting a new run", out.display());
        }
        // A new run: the previous run's results no longer describe this folder (and a
        // metrics.json left beside an interrupted new run would make it look finished).
        for stale in [&metrics_path, &out.join("gpu_profile.json"), &out.join("dataparser_transforms.json"), &out.join("camera_corrections.json")] {
            match std::fs::remove_file(stale) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io_err(stale)(e)),
                _ => {}
            }
        }
    }
    // A nerfstudio capture: how its poses were normalised, in nerfstudio's own file, so points
    // and cameras of the run map back to the capture's (COLMAP's) frame.
    if let Some(n) = &train.normalization {
        let text = serde_json::to_string_pretty(&n.to_json()).expect("a JSON value serialises");
        write_atomic(&out.join("dataparser_transforms.json"), text.as_bytes())?;
    }
    let mut trainer = make_trainer(&config, registry, SceneBounds::of(train), opts.device)?;
    if config.gpu_profile.is_some() && trainer.device() == "cpu" {
        eprintln!("note: gpu_profile is ignored on the CPU path");
    }
    let mut profile: Option<crate::GpuProfile> = None;
    let profile_path = out.join("gpu_profile.json");
    let write_profile = |p: &crate::GpuProfile| -> Result<(), TrainError> {
        let text = serde_json::to_string_pretty(p).expect("profile serialises");
        write_atomic(&profile_path, text.as_bytes())
    };
    let (mut elapsed, mut samples_seen) = (0.0f64, 0u64);
    if resuming {
        let ck = Checkpoint::load(&ck_path)?;
        if ck.render_only {
            return Err(TrainError::Checkpoint {
                path: ck_path,
                message: "is a render-only copy (`nerf slim`: no optimiser state): training cannot resume from it".into(),
            });
        }
        let same = |a: &TrainConfig, b: &TrainConfig| {
            a.field == b.field && a.field_config == b.field_config && a.sampler == b.sampler && a.seed == b.seed
        };
        if !same(&ck.config, &config) {
            return Err(TrainError::Checkpoint {
                path: ck_path,
                message: "was written by a run with a different field, field config, sampler or seed".into(),
            });
        }
        if ck.config.ndc != config.ndc {
            return Err(TrainError::Checkpoint {
                path: ck_path,
                message: format!(
                    "was trained with {} rays; resume it in the same ray space ({})",
                    if ck.config.ndc { "NDC" } else { "Euclidean" },
                    if ck.config.ndc { "without --no-ndc" } else { "with --no-ndc" }
                ),
            });
        }
        trainer.restore(ck.step, &ck.fields, ck.adam, &ck.sampler).map_err(|e| e.in_checkpoint(&ck_path))?;
        elapsed = ck.elapsed_secs;
        samples_seen = ck.samples_seen;
    }
    let base_samples = samples_seen;
    let save = |t: &Trainer, elapsed: f64| -> Result<(), TrainError> {
        let fields = t.export_fields()?;
        // The GPU reads the loss back only every `log_every` steps: a time budget or Ctrl-C can
        // end a run between a divergence and its read-back. Never checkpoint (or evaluate) it.
        if fields.iter().flatten().any(|(_, v)| v.iter().any(|x| !x.is_finite())) {
            return Err(TrainError::Diverged { step: t.step_count(), loss: f32::NAN });
        }
        Checkpoint {
            step: t.step_count(),
            elapsed_secs: elapsed,
            samples_seen: base_samples + t.samples_seen()?,
            config: t.config().clone(),
            fields,
            adam: t.adam_state()?,
            sampler: t.sampler_state()?,
            render_only: false,
        }
        .save(&ck_path)
    };

    let hist_path = out.join("history.jsonl");
    let mut history = std::fs::OpenOptions::new()
        .create(true)
        .append(resuming)
        .write(true)
        .truncate(!resuming)
        .open(&hist_path)
        .map_err(io_err(&hist_path))?;

    let pb = if opts.progress { ProgressBar::new(config.iters) } else { ProgressBar::hidden() };
    pb.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} steps {per_sec} {msg}")
            .expect("valid template"),
    );
    pb.set_position(trainer.step_count());
    let budget = config.time_budget_secs.unwrap_or(f64::INFINITY);
    // Test views scored during the run (`eval_every`), and the seconds that took (not training).
    let probe = match &config.eval_every {
        Some(e) => Some((e.steps, e.renders, test.select_views(&e.views.indices(test.n_views()).map_err(|r| TrainError::Config(format!("eval_every.views: {r}")))?))),
        None => None,
    };
    let mut eval_secs = 0.0f64;
    let start = Instant::now();
    let base_elapsed = elapsed;
    // Training seconds so far: this invocation's wall clock less its evaluations.
    let train_clock = |eval_secs: f64| base_elapsed + start.elapsed().as_secs_f64() - eval_secs;
    let base_step = trainer.step_count();
    let mut last_loss = f32::NAN;
    while trainer.step_count() < config.iters && elapsed < budget {
        if opts.stop.load(Ordering::SeqCst) {
            save(&trainer, elapsed)?;
            pb.abandon_with_message("interrupted");
            return Err(TrainError::Interrupted { step: trainer.step_count(), checkpoint: ck_path });
        }
        trainer.set_progress(run_progress(trainer.step_count(), config.iters, elapsed, budget));
        let s = trainer.step(train)?;
        if let Some(p) = trainer.take_gpu_profile(false) {
            write_profile(&p)?;
            pb.suspend(|| eprintln!("{}", p.table(25)));
            profile = Some(p);
        }
        elapsed = train_clock(eval_secs);
        if s.loss.is_finite() {
            last_loss = s.loss;
        }
        pb.inc(1);
        let done = trainer.step_count();
        if (done % config.log_every.max(1) == 0 || done == config.iters) && s.loss.is_finite() {
            let psnr = nerf_metrics::mse_to_psnr(s.mse as f64);
            pb.set_message(format!("loss {:.5} psnr {:.2} lr {:.2e}", s.loss, psnr, s.lr));
            let line = json!({
                "step": done,
                "elapsed_secs": elapsed,
                "loss": s.loss,
                "train_psnr": psnr,
                "lr": s.lr,
                "samples": s.n_samples,
                "marched_samples": s.n_marched,
                "rays": s.n_rays,
                "alive_rays": s.alive_rays,
                "train_psnr_alive": s.psnr_alive(),
            });
            writeln!(history, "{line}").map_err(io_err(&hist_path))?;
        }
        if config.checkpoint_every > 0 && done % config.checkpoint_every == 0 {
            save(&trainer, elapsed)?;
        }
        // A score on a few test views (not at the last step: the whole evaluation follows).
        if let Some((every, renders, views)) = probe.as_ref().filter(|(every, _, _)| done % every == 0 && done < config.iters) {
            // Queued GPU steps are training time; the evaluation after them is not.
            trainer.finish()?;
            let t0 = Instant::now();
            let dir = renders.then(|| out.join("progress").join(format!("step_{done:06}")));
            if let Some(d) = &dir {
                std::fs::create_dir_all(d).map_err(io_err(d))?;
            }
            let r = evaluate(&trainer, views, dir.as_deref(), |_, _| {})?;
            eval_secs += t0.elapsed().as_secs_f64();
            elapsed = train_clock(eval_secs);
            if !r.psnr.is_finite() {
                // NaN parameters between two GPU loss read-backs: nothing saved.
                return Err(TrainError::Diverged { step: done, loss: f32::NAN });
            }
            pb.set_message(format!("test psnr {:.2} (step {done}, every {every})", r.psnr));
            let line = json!({"step": done, "elapsed_secs": elapsed, "test_psnr": r.psnr, "test_ssim": r.ssim, "test_views": views.n_views(), "eval_seconds": r.seconds});
            writeln!(history, "{line}").map_err(io_err(&hist_path))?;
        }
    }
    // GPU steps are queued: wait for them so the clock counts the work, not its submission.
    trainer.finish()?;
    elapsed = train_clock(eval_secs);
    if let Some(p) = trainer.take_gpu_profile(true) {
        write_profile(&p)?;
        pb.suspend(|| eprintln!("{}", p.table(25)));
        profile = Some(p);
    }
    samples_seen += trainer.samples_seen()?;
    pb.finish_with_message(format!("trained {} steps in {:.1}s", trainer.step_count(), elapsed));
    save(&trainer, elapsed)?;
    // Camera pose refinement: the corrected training poses.
    let corrections = trainer.pose_params()?.map(|p| crate::pose::corrections_json(&p, &train.cameras, &train.view_names()));
    if let Some(c) = &corrections {
        let text = serde_json::to_string_pretty(c).expect("a JSON value serialises");
        write_atomic(&out.join("camera_corrections.json"), text.as_bytes())?;
    }

    let epb = if opts.progress { ProgressBar::new(test.n_views() as u64) } else { ProgressBar::hidden() };
    epb.set_style(ProgressStyle::with_template("eval {bar:30} {pos}/{len} views").expect("valid template"));
    let renders = out.join("renders");
    let report = evaluate(&trainer, test, opts.write_renders.then_some(renders.as_path()), |i, _| {
        epb.set_position(i as u64)
    })?;
    epb.finish_and_clear();

    let steps_this_run = trainer.step_count() - base_step;
    let iters = trainer.step_count();
    let mut metrics = json!({
        "field": config.field,
        "device": trainer.device(),
        "adapter": trainer.adapter(),
        "scene": opts.scene,
        // Where the rays live: NDC for forward-facing scenes (unless `ndc = false`).
        "ray_space": if test.ndc.is_some() { "ndc" } else { "euclidean" },
        "iterations": iters,
        "wall_seconds": elapsed,
        "ms_per_iter": if iters > 0 { 1e3 * elapsed / iters as f64 } else { 0.0 },
        "samples_per_sec": if elapsed > 0.0 { samples_seen as f64 / elapsed } else { 0.0 },
        "steps_this_invocation": steps_this_run,
        "final_train_loss": last_loss,
        "test_psnr": report.psnr,
        "test_ssim": report.ssim,
        "n_test_views": report.views.len(),
        "eval_seconds": report.seconds,
        "render_fps": if report.render_seconds > 0.0 { report.views.len() as f64 / report.render_seconds } else { 0.0 },
        "width": test.width,
        "height": test.height,
        "n_params": trainer.n_params(),
        "threads": rayon::current_num_threads(),
        // As trained: the GPU path may have fitted the samples per step to the adapter.
        "config": trainer.config(),
        "device_note": trainer.device_note(),
        "alpha_split": report.alpha_split,
        "test_depth": report.depth,
        "test_masked": report.masked,
        "per_view": report.views,
    });
    if let Some(c) = &corrections {
        metrics["camera_corrections"] = json!({ "mean_translation": c["mean_translation"], "mean_rotation_degrees": c["mean_rotation_degrees"] });
    }
    if let Some(p) = &profile {
        metrics["gpu_profile"] = serde_json::to_value(p).expect("profile serialises");
    }
    let text = serde_json::to_string_pretty(&metrics).expect("metrics serialise");
    write_atomic(&metrics_path, text.as_bytes())?;
    Ok(RunSummary { metrics, eval: report, iterations: iters })
}

/// The fraction of a run done after `step` of `iters` steps and `elapsed` of `budget` seconds
/// (infinite: no budget): the larger of the two, since whichever comes first ends the run. What
/// a runner passes to [`Trainer::set_progress`] before each step.
pub fn run_progress(step: u64, iters: u64, elapsed: f64, budget: f64) -> f64 {
    let by_time = if budget.is_finite() && budget > 0.0 { elapsed / budget } else { 0.0 };
    (step as f64 / iters.max(1) as f64).max(by_time).clamp(0.0, 1.0)
}

/// A trainer on the device `pref` asks for: `cpu`; `gpu` (any adapter; an error without one, or
/// when the field has no GPU twin or the GPU path cannot take the config); `auto`: a hardware GPU
/// when one exists and the GPU path can take the run, else the CPU (with a notice on stderr).
pub fn make_trainer(
    config: &TrainConfig,
    registry: &Registry,
    bounds: SceneBounds,
    pref: nerf_gpu::DevicePreference,
) -> Result<Trainer, TrainError> {
    use nerf_gpu::{DevicePreference, GpuContext};
    let pref = pref.with_env_override().map_err(|e| TrainError::Gpu(e.to_string()))?;
    let ctx = GpuContext::open(pref).map_err(|e| TrainError::Gpu(e.to_string()))?;
    match ctx {
        None => Trainer::new(config.clone(), registry, bounds),
        // A software adapter (lavapipe) is slower than the rayon path: `auto` skips it.
        Some(ctx) if pref == DevicePreference::Auto && ctx.is_software() => Trainer::new(config.clone(), registry, bounds),
        Some(ctx) => match Trainer::new_on(config.clone(), registry, bounds, Some(std::sync::Arc::new(ctx))) {
            // `auto` falls back to the CPU when the GPU path cannot take this run (a field without
            // a GPU twin, a config its kernels do not support, a buffer larger than the adapter
            // allows); `gpu` reports it.
            Err(TrainError::Gpu(message) | TrainError::GpuCapacity { message, .. }) if pref == DevicePreference::Auto => {
                eprintln!("note: {message}; training on the CPU");
                Trainer::new(config.clone(), registry, bounds)
            }
            other => other,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::run_progress;

    #[test]
    fn progress_is_the_larger_fraction_of_steps_and_time() {
        assert_eq!(run_progress(0, 100, 0.0, f64::INFINITY), 0.0);
        assert_eq!(run_progress(25, 100, 1e9, f64::INFINITY), 0.25);
        assert_eq!(run_progress(25, 100, 30.0, 60.0), 0.5);
        assert_eq!(run_progress(90, 100, 30.0, 60.0), 0.9);
        // Past either end (a resumed run with a shorter budget): clamped.
        assert_eq!(run_progress(5, 100, 90.0, 60.0), 1.0);
        assert_eq!(run_progress(7, 0, 0.0, f64::INFINITY), 1.0);
    }
}
