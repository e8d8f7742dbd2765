//! The batch checks and targets SparseOcc and the dense baseline share: the full-resolution labels of a
//! batch downsampled to the prediction grid by the official SparseOcc in-network mode rule
//! ([`occ_labels::downsample_mode`]; the label conventions and both downsampling rules live in
//! `occ-labels`, docs/formats.md §2.6). SparseOcc++ takes its targets with the MonoScene rule in
//! `sparseocc_pp`.

use crate::batch::Batch;
use crate::error::ModelError;
use burn::prelude::*;
use occ_labels::downsample_mode;

pub(crate) fn check_input<B: Backend>(
    feats: &Tensor<B, 4>,
    batch: &Batch<B>,
    feat_channels: usize,
    full_dims: [usize; 3],
) -> Result<(), ModelError> {
    let c = feats.dims()[1];
    if c != feat_channels {
        return Err(ModelError::Input(format!(
            "feature map has {c} channels, the model was configured for {feat_channels}"
        )));
    }
    if batch.grid.dims != full_dims {
        return Err(ModelError::Input(format!(
            "batch grid {:?} differs from the configured full_dims {full_dims:?}",
            batch.grid.dims
        )));
    }
    Ok(())
}

/// Full-resolution targets of a batch downsampled to the prediction grid by the mode rule, one vector
/// per item.
pub(crate) fn targets_at<B: Backend>(
    batch: &Batch<B>,
    full_dims: [usize; 3],
    ratio: usize,
) -> Result<Vec<Vec<u8>>, ModelError> {
    let target = batch.target.as_ref().ok_or_else(|| {
        ModelError::Input("losses need batch.target (the full-resolution labels)".into())
    })?;
    if target.len() != batch.batch_size() {
        return Err(ModelError::Input(format!(
            "batch.target has {} items, the batch has {}",
            target.len(),
            batch.batch_size()
        )));
    }
    target
        .iter()
        .map(|t| {
            downsample_mode(t, full_dims, ratio)
                .map_err(|e| ModelError::Input(format!("downsample_mode: {e}")))
        })
        .collect()
}
