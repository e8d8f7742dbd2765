//! Typed errors of the dataset readers and writers. Every variant that concerns a file names it.

use std::path::{Path, PathBuf};

/// Error of an `occ-data` reader, writer or dataset operation.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A required file or folder does not exist.
    #[error("{}: not found ({what})", path.display())]
    NotFound { path: PathBuf, what: String },
    /// Any other I/O failure.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is shorter than its format requires.
    #[error("{}: truncated: expected {expected} bytes, found {actual}", path.display())]
    Truncated {
        path: PathBuf,
        expected: u64,
        actual: u64,
    },
    /// The file size does not fit the format (e.g. not a multiple of the record size, or too long).
    #[error("{}: wrong size: {detail}", path.display())]
    WrongSize { path: PathBuf, detail: String },
    /// A text file (calibration, poses) could not be parsed.
    #[error("{}:{line}: {detail}", path.display())]
    Parse {
        path: PathBuf,
        line: usize,
        detail: String,
    },
    /// A required key (e.g. `Tr` in calib.txt, `semantics` in labels.npz) is missing.
    #[error("{}: missing key `{key}`", path.display())]
    MissingKey { path: PathBuf, key: String },
    /// The content is well-formed but not what the format requires (dtype, shape, value range, ...).
    #[error("{}: {detail}", path.display())]
    Format { path: PathBuf, detail: String },
    /// An image (PNG or JPEG) could not be decoded or encoded.
    #[error("{}: image error: {detail}", path.display())]
    Image { path: PathBuf, detail: String },
    /// An in-memory argument is inconsistent (no file involved), e.g. a grid of the wrong length.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

impl DataError {
    /// Wrap an I/O error for `path`, turning "not found" into [`DataError::NotFound`].
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        if source.kind() == std::io::ErrorKind::NotFound {
            DataError::NotFound {
                path: path.to_path_buf(),
                what: "no such file or directory".into(),
            }
        } else {
            DataError::Io {
                path: path.to_path_buf(),
                source,
            }
        }
    }

    /// Shorthand for [`DataError::Format`].
    pub fn format(path: &Path, detail: impl Into<String>) -> Self {
        DataError::Format {
            path: path.to_path_buf(),
            detail: detail.into(),
        }
    }

    /// The file this error is about, if any.
    pub fn path(&self) -> Option<&Path> {
        match self {
            DataError::NotFound { path, .. }
            | DataError::Io { path, .. }
            | DataError::Truncated { path, .. }
            | DataError::WrongSize { path, .. }
            | DataError::Parse { path, .. }
            | DataError::MissingKey { path, .. }
            | DataError::Format { path, .. }
            | DataError::Image { path, .. } => Some(path),
            DataError::InvalidArgument(_) => None,
        }
    }
}
