//! Normalisation over voxel features `[N, C]`.
//!
//! SparseOcc uses BatchNorm1d over the active voxels (statistics over all sites) and GroupNorm applied
//! to each voxel's channels (docs/reference_models.md §1 and §3). Both are burn's own layers applied to the feature rows: a
//! `[N, C]` tensor is exactly the `[batch, channels]` layout they expect.

use crate::error::Result;
use crate::tensor::SparseTensor;
use burn::nn::{BatchNorm, BatchNormConfig, GroupNorm, GroupNormConfig};
use burn::prelude::*;

/// Batch norm over active sites (statistics over the N sites).
#[derive(Module, Debug)]
pub struct SparseBatchNorm<B: Backend> {
    /// The underlying burn layer.
    pub inner: BatchNorm<B>,
}

impl<B: Backend> SparseBatchNorm<B> {
    /// New layer for `channels` features.
    pub fn new(channels: usize, device: &B::Device) -> Self {
        Self {
            inner: BatchNormConfig::new(channels).init(device),
        }
    }
    /// # Shapes
    /// - `[N, C]` features -> `[N, C]`
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>> {
        x.map_feats(|f| self.inner.forward(f))
    }
}

/// Group norm of each site's channels.
#[derive(Module, Debug)]
pub struct SparseGroupNorm<B: Backend> {
    /// The underlying burn layer.
    pub inner: GroupNorm<B>,
}

impl<B: Backend> SparseGroupNorm<B> {
    /// New layer with `groups` groups over `channels` features.
    pub fn new(groups: usize, channels: usize, device: &B::Device) -> Self {
        Self {
            inner: GroupNormConfig::new(groups, channels).init(device),
        }
    }
    /// # Shapes
    /// - `[N, C]` features -> `[N, C]`
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>> {
        x.map_feats(|f| self.inner.forward(f))
    }
}
