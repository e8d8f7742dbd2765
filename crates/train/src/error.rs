//! Training-pipeline errors.

use thiserror::Error;

/// Errors of the training and inference pipeline.
#[derive(Debug, Error)]
pub enum TrainError {
    /// Dataset problem (missing files, sizes).
    #[error("data: {0}")]
    Data(String),
    /// Reader error with the file named.
    #[error(transparent)]
    Format(#[from] occ_data::DataError),
    /// Model error.
    #[error(transparent)]
    Model(#[from] occ_model::ModelError),
    /// Configuration problem (file named).
    #[error("config: {0}")]
    Config(String),
    /// Checkpoint problem (file named).
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    /// The loss became NaN or infinite.
    #[error("loss is not finite at step {step}: {detail}")]
    NonFiniteLoss {
        /// Optimizer step.
        step: usize,
        /// Which terms.
        detail: String,
    },
    /// A data-parallel run failed: a collective operation, or the workers disagree.
    #[error("data-parallel training: {0}")]
    Parallel(String),
    /// A benchmark setting the run cannot use (a grid without a synthetic preset, or one that is
    /// not a multiple of 8 at the asked divisor).
    #[error("{0}")]
    Bench(String),
    /// Evaluation error.
    #[error(transparent)]
    Eval(#[from] occ_eval::EvalError),
    /// I/O error with the file named.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}
