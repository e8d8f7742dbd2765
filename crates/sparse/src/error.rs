//! Typed errors of the sparse library.

use thiserror::Error;

/// Everything that can go wrong when building sparse tensors, kernel maps or running layers.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SparseError {
    /// A coordinate lies outside the spatial shape (or has a negative batch index).
    #[error("coordinate {coord:?} (row {row}) is outside the spatial shape {shape:?} / batch size {batch_size}")]
    OutOfRange {
        /// Row index in the coordinate list.
        row: usize,
        /// The offending (batch, x, y, z).
        coord: [i32; 4],
        /// Spatial shape (x, y, z).
        shape: [usize; 3],
        /// Batch size.
        batch_size: usize,
    },
    /// The same coordinate appears twice.
    #[error("duplicate coordinate {coord:?} at rows {first} and {second}")]
    Duplicate {
        /// The repeated (batch, x, y, z).
        coord: [i32; 4],
        /// First row holding it.
        first: usize,
        /// Second row holding it.
        second: usize,
    },
    /// Shapes of coordinates, features, weights or grids disagree.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// A layer's configuration is invalid (even kernel for submanifold, zero stride...).
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The weight tensor does not have the layout [Cout, kx, ky, kz, Cin] expected by the layer.
    #[error("weight layout: expected [Cout={cout}, {kernel:?}, Cin={cin}], got {got:?}")]
    WeightLayout {
        /// Expected output channels.
        cout: usize,
        /// Expected kernel size.
        kernel: [usize; 3],
        /// Expected input channels.
        cin: usize,
        /// The shape received.
        got: Vec<usize>,
    },
    /// An inverse convolution found no matching strided convolution in the tensor's history.
    #[error("inverse convolution: no strided convolution with {0} produced these coordinates")]
    NoInverseMap(String),
    /// Two tensors that must share a coordinate frame do not.
    #[error("incompatible tensors: {0}")]
    Incompatible(String),
}

/// Result alias.
pub type Result<T> = std::result::Result<T, SparseError>;
