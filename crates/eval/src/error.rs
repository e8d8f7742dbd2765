//! Typed errors of the evaluation. Every variant that concerns a file names it.

use std::path::PathBuf;

/// Error of an evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Prediction, ground truth and mask of one frame differ in length.
    #[error("frame {frame}: {what} has {got} voxels but the ground truth has {expected}")]
    SizeMismatch {
        /// The frame (file name or index) concerned.
        frame: String,
        /// Which array (`"prediction"`, `"mask"`).
        what: &'static str,
        /// Ground-truth voxel count.
        expected: usize,
        /// Voxel count of the other array.
        got: usize,
    },
    /// Ground-truth frames have no prediction file; the first one is named.
    #[error("{}: missing prediction (expected for ground truth {}); {count} prediction file(s) missing in total", path.display(), gt.display())]
    MissingPrediction {
        /// The first prediction file that should exist.
        path: PathBuf,
        /// The ground-truth file it is scored against.
        gt: PathBuf,
        /// Number of missing prediction files.
        count: usize,
    },
    /// No ground-truth frame was found.
    #[error("{}: no ground-truth frames found ({what})", root.display())]
    NoFrames {
        /// The ground-truth root searched.
        root: PathBuf,
        /// What was looked for.
        what: String,
    },
    /// A prediction file is malformed.
    #[error("{}: {detail}", path.display())]
    BadPrediction {
        /// The prediction file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// A ground-truth file is malformed (not a file, ids outside the dataset's label set, a grid of
    /// the wrong shape).
    #[error("{}: {detail}", path.display())]
    BadGroundTruth {
        /// The ground-truth file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The options contradict themselves or the data (e.g. a sequence listed twice).
    #[error("{0}")]
    InvalidOptions(String),
    /// Evaluators or reports of different protocols / class counts were combined.
    #[error("cannot combine evaluations: {0}")]
    Incompatible(String),
    /// A dataset reader failed (the error names the file).
    #[error(transparent)]
    Data(#[from] occ_data::DataError),
    /// Any other I/O failure.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder concerned.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
}
