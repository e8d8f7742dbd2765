//! The interface every occupancy network implements, so training, inference and benchmarks treat
//! SparseOcc++, SparseOcc and the dense baseline the same way.

use crate::{Batch, ModelError, ModelOutput};
use burn::prelude::*;

/// A network from camera images to sparse voxel class logits.
pub trait OccNetwork<B: Backend> {
    /// Runs the network. When `batch.target` is set, `ModelOutput::losses` holds the training loss
    /// terms.
    fn forward_batch(&self, batch: &Batch<B>) -> Result<ModelOutput<B>, ModelError>;
    /// Number of classes (class 0 = empty).
    fn num_classes(&self) -> usize;
}
