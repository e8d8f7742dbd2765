//! Normalisation over voxel features `[N, C]`.
//!
//! SparseOcc uses BatchNorm1d over the active voxels (statistics over all sites) and GroupNorm applied
//! to each voxel's channels (docs/reference_models.md §1 and §3). Both are burn's own layers applied to the feature rows: a
//! `[N, C]` tensor is exactly the `[batch, channels]` layout they expect.

use crate::backend::SparseConvBackend;
use crate::error::Result;
use crate::rows::sum_rows;
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
}

impl<B: SparseConvBackend> SparseBatchNorm<B> {
    /// # Shapes
    /// - `[N, C]` features -> `[N, C]`
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>> {
        x.map_feats(|f| batch_norm(&self.inner, f))
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

/// burn's `BatchNorm::forward` (same statistics, running-state update and output), with the
/// training-mode batch statistics summed over the long axis in two levels ([`sum_rows`]): burn's
/// own `mean_dim` gives each channel to one thread looping over every voxel or pixel on the cubecl
/// backends (and stops at 65,532 iterations on lavapipe). Inference mode is burn's.
///
/// # Shapes
/// - x: `[N, C, ...]` -> same
pub fn batch_norm<B: SparseConvBackend, const D: usize>(
    bn: &BatchNorm<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    let device = x.device();
    if !B::ad_enabled(&device) || D < 2 {
        return bn.forward(x);
    }
    let c = x.dims()[1];
    let n = x.shape().num_elements() / c.max(1);
    if n == 0 {
        return bn.forward(x);
    }
    let mut shape = [1; D];
    shape[1] = c;
    // [N, C, ...] -> [N·..., C]: the order of the rows does not matter to the sums.
    let rows = x.clone().swap_dims(1, D - 1).reshape([n, c]);
    let inv_n = 1.0 / n as f64;
    let mean = sum_rows(rows.clone()).mul_scalar(inv_n); // [1, C]
    let var = sum_rows((rows - mean.clone()).square()).mul_scalar(inv_n); // biased, as burn's
    let momentum = bn.momentum;
    let running_mean = bn.running_mean.value_sync().to_device(&device);
    let running_var = bn.running_var.value_sync().to_device(&device);
    bn.running_mean.update(
        running_mean
            .mul_scalar(1.0 - momentum)
            .add(mean.clone().detach().mul_scalar(momentum).reshape([c]))
            .detach(),
    );
    bn.running_var.update(
        running_var
            .mul_scalar(1.0 - momentum)
            .add(var.clone().detach().mul_scalar(momentum).reshape([c]))
            .detach(),
    );
    let std = var.reshape(shape).add_scalar(bn.epsilon).sqrt();
    x.sub(mean.reshape(shape))
        .div(std)
        .mul(bn.gamma.val().reshape(shape))
        .add(bn.beta.val().reshape(shape))
}
