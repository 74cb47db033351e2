//! The ablation runner: a grid of training runs — fields and any training-config key — on the
//! same scenes, seeds and budget, evaluated on the same test views at points along the way, with
//! a CSV, a markdown table and PNG plots of PSNR against wall time and iteration.
//!
//! # File format (TOML)
//! ```toml
//! name = "fields"                      # optional; default: the file stem
//! scenes = ["../../scenes/lego_100"]   # Blender or LLFF folders, relative to the file's folder (absolute allowed)
//! downscale = 1                        # default 1
//! train_views = "all"                  # all | every:K | first:N (default all)
//! test_views = "every:3"               # default every:8
//! seeds = [0]                          # default [0]; every run is repeated per seed
//! [budget]                             # required, the same for every run; at least one of the two
//! iters = 300
//! seconds = 60.0
//! [eval]                               # optional evaluation points (excluded from the training clock);
//! every_seconds = 15.0                 # and/or every_iters = 100; the final evaluation always happens
//! [base]                               # TrainConfig patch for every run (any key)
//! log_every = 50
//! [[runs]]                             # at least one: a name + a TrainConfig JSON patch
//! name = "hash"
//! config = { field = "hash" }
//! [[runs]]
//! name = "freq"
//! config = { field = "freq", batch_rays = 512 }
//! [grid]                               # optional cartesian sweep on top of every run
//! "field_config.grid.n_levels" = [8, 16]
//! "field_config.grid.log2_hashmap_size" = [15, 19]
//! ```
//! LLFF scenes load in NDC unless a run sets `ndc = false` (a grid key too: `ndc = [true, false]`).
//! Unknown keys are rejected. A run's config is `TrainConfig::default()` ← the field's registry
//! `train_preset` ← `[base]` ← the run's `config` ← the grid point (merged as JSON with
//! [`nerf_field::merge_json`]), then `iters` = `budget.iters` (or `u64::MAX`),
//! `time_budget_secs` = `budget.seconds`, `seed`, `downscale` and `test_views` from the file.
//! Grid keys are dotted paths that must exist in the resolved config (keys under `field_config`
//! are checked against the field's default config); they are swept in sorted order, the last key
//! varying fastest. The run list is runs × grid points × scenes × seeds; a run's id is
//! `<run name>[__<key>=<value>…]__<scene folder name>__s<seed>` (the key's last path segment
//! unless two grid keys share it), with characters outside `[A-Za-z0-9._=-]` replaced by `-`.
//!
//! # Outputs (under the output folder)
//! - `runs/<id>/curve.csv` (`iter,seconds,psnr,ssim`) and `runs/<id>/metrics.json`
//!   ([`RunMetrics`]: the keys of `nerf train`'s metrics.json where they apply, plus `n_params`,
//!   `peak_memory_mib`, `curve`, `config_hash`, and `train_log`: the lines of `nerf train`'s
//!   `history.jsonl` every `log_every` steps);
//! - `results.csv`, `results.md`, `psnr_vs_time.png`, `psnr_vs_iter.png`, rebuilt from all runs on
//!   every invocation.
//!
//! A run whose `metrics.json` exists with the same [`config_hash`] (FNV-1a over the canonical JSON
//! of the resolved config, the scene path, the training views and the evaluation schedule) is
//! reused, not re-run; `metrics.json` is written atomically, so an interrupted run never counts as
//! finished.

mod exec;
mod report;
mod spec;

pub use exec::{run_ablation, train_run, AblateOptions, AblationReport, CurvePoint, RunMetrics, RunOutcome, TrainLogPoint};
pub use report::{ensure_font, plot_curves, read_png_rgb, results_csv, results_md, FONT_CANDIDATES};
pub use spec::{
    canonical_json, config_hash, fnv1a64, safe_name, value_label, Ablation, AblationSpec, Budget, EvalSchedule,
    RunPlan, RunSpec,
};

use std::path::PathBuf;

/// Errors of the ablation runner; each names the file (or run) and the problem.
#[derive(Debug, thiserror::Error)]
pub enum AblateError {
    /// The ablation file cannot be read.
    #[error("{path}: cannot read the ablation file: {error}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// The ablation file is not valid TOML or has unknown / mistyped keys.
    #[error("{path}: malformed ablation file: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message (names the key and line).
        message: String,
    },
    /// The ablation file parses but describes no valid ablation.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A scene could not be loaded.
    #[error("scene {path}: {message}")]
    Scene {
        /// The scene folder.
        path: PathBuf,
        /// The loader's message.
        message: String,
    },
    /// Training or evaluating a run failed.
    #[error("run {id}: {error}")]
    Train {
        /// The run id.
        id: String,
        /// The trainer's error.
        error: nerf_train::TrainError,
    },
    /// An output file could not be written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// A plot could not be drawn.
    #[error("{path}: cannot draw the plot: {message}")]
    Plot {
        /// The PNG file.
        path: PathBuf,
        /// plotters' message.
        message: String,
    },
}
