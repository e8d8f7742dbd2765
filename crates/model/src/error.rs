//! Model errors.

use thiserror::Error;

/// Errors from building or running a model.
#[derive(Debug, Error)]
pub enum ModelError {
    /// Sparse-library error (coordinates, kernel maps, layer shapes).
    #[error(transparent)]
    Sparse(#[from] occ_sparse::SparseError),
    /// Inputs do not match what the model was configured for.
    #[error("input: {0}")]
    Input(String),
    /// Configuration is invalid.
    #[error("config: {0}")]
    Config(String),
    /// A loss or output became NaN/inf.
    #[error("numerical: {0}")]
    Numerical(String),
}
