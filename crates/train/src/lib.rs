//! Training and evaluation of any radiance field behind the `RadianceField` trait.
//!
//! [`Trainer`] takes random ray batches from a [`nerf_data::Dataset`], turns them into packed
//! samples (stratified, then optionally hierarchical through a coarse instance of the same field),
//! queries the field(s), composites, takes the photometric MSE on every stage, back-propagates
//! through compositing into the field(s) and steps Adam (optionally keeping an exponential moving
//! average of the parameters that rendering then uses, `TrainConfig::ema_decay`). [`run()`] wraps it into a whole run with
//! a progress bar, a time budget, atomic checkpoints (resumable, written on Ctrl-C), evaluation on
//! held-out views and `metrics.json`. Nothing here knows which field it drives.

pub mod checkpoint;
pub mod color;
pub mod pose;
pub mod views;
pub mod config;
pub mod eval;
mod gpu;
pub mod profile;
mod rounds;
pub mod run;
pub mod trainer;

pub use checkpoint::Checkpoint;
pub use color::ColorState;
pub use views::{ViewKind, ViewState};
pub use config::{LossConfig, SamplerConfig, TrainConfig};
pub use eval::{evaluate, AlphaSplit, DepthError, EvalReport, MaskedMetrics, PassMean, ViewMetrics};
pub use profile::{GpuProfile, ProfileWindow};
pub use run::{make_trainer, run, run_progress, RunOptions, RunSummary};
pub use trainer::{ema_from_entries, ema_to_entries, seen_from_entry, seen_to_entry, SceneBounds, StepStats, Trainer, SEEN_ENTRY};

use std::path::PathBuf;

/// Parameters of every field instance of a run: per instance, `(group name, values)` in the
/// field's `export_params` order (what checkpoints hold, on either device).
pub type FieldParams = Vec<Vec<(String, Vec<f32>)>>;

/// Errors of training and evaluation.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The run's config is inconsistent.
    #[error("invalid training config: {0}")]
    Config(String),
    /// Building or loading a field failed.
    #[error(transparent)]
    Field(#[from] nerf_field::FieldError),
    /// Loading data or writing images failed.
    #[error(transparent)]
    Data(#[from] nerf_data::DataError),
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A checkpoint is unreadable or does not fit the run.
    #[error("checkpoint {path}: {message}")]
    Checkpoint {
        /// The checkpoint file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The GPU path failed (no adapter, a field without a GPU twin, a failed read-back).
    #[error("GPU: {0}")]
    Gpu(String),
    /// A buffer sized per sample is larger than the adapter's storage binding limit.
    /// [`Trainer::new_on`] fits the step's samples to the adapter instead of returning this; it
    /// comes out only where even the smallest batch does not fit.
    #[error("GPU: {message}")]
    GpuCapacity {
        /// What did not fit, and on which adapter.
        message: String,
        /// Bytes the buffer needs.
        bytes: u64,
        /// The adapter's limit in bytes.
        limit: u64,
    },
    /// The output folder holds an interrupted run (a checkpoint without `metrics.json`) and the
    /// new run neither resumes it nor may overwrite it.
    #[error(
        "{} holds an interrupted run (checkpoint at step {step}, no metrics.json): continue it with \
         --resume, start over with --overwrite, or choose another --out",
        out.display()
    )]
    OutDirInUse {
        /// The output folder.
        out: PathBuf,
        /// The step of its checkpoint.
        step: u64,
    },
    /// The loss of a step came out NaN or infinite, or the parameters did (found when saving or
    /// evaluating between two GPU loss read-backs). Nothing is saved (the last checkpoint written
    /// before it stays as it was).
    #[error(
        "training diverged by step {step}: NaN or infinite values (loss {loss}); no checkpoint was \
         written for it (the last one, if any, is kept); lower the learning rate"
    )]
    Diverged {
        /// Steps completed, the diverged one included.
        step: u64,
        /// The loss read (NaN where the parameters were found non-finite instead).
        loss: f32,
    },
    /// Training was interrupted (Ctrl-C); the state was saved.
    #[error("interrupted at step {step}; checkpoint saved to {checkpoint} (resume with --resume)")]
    Interrupted {
        /// Steps completed.
        step: u64,
        /// Where the state was written.
        checkpoint: PathBuf,
    },
}

impl TrainError {
    /// This error, raised while restoring the state read from the checkpoint `path`
    /// ([`Trainer::restore`]), as an error about that checkpoint: the state does not fit the run
    /// (a group of another length, non-finite optimiser moments, an unknown sampler entry). GPU
    /// and I/O errors are not about the file's content and pass through.
    pub fn in_checkpoint(self, path: &std::path::Path) -> TrainError {
        let message = match self {
            TrainError::Gpu(_) | TrainError::GpuCapacity { .. } | TrainError::Io { .. } | TrainError::Checkpoint { .. } => {
                return self
            }
            TrainError::Config(m) => m,
            e => e.to_string(),
        };
        TrainError::Checkpoint { path: path.to_path_buf(), message }
    }
}

#[cfg(test)]
mod tests {
    use super::TrainError;
    use std::path::Path;

    #[test]
    fn restore_errors_name_the_checkpoint() {
        let p = Path::new("run/checkpoint.bin");
        let e = TrainError::Config("Adam state: group \"g\" has non-finite or negative moments".into()).in_checkpoint(p);
        assert!(matches!(e, TrainError::Checkpoint { .. }), "{e}");
        assert_eq!(e.to_string(), "checkpoint run/checkpoint.bin: Adam state: group \"g\" has non-finite or negative moments");
        // Errors that are not about the file's content keep their own kind.
        assert!(matches!(TrainError::Gpu("lost".into()).in_checkpoint(p), TrainError::Gpu(_)));
    }
}
