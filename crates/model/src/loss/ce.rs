//! Class-weighted cross-entropy with an ignore label (docs/losses.md §2).

use super::{check_labels, host_tensor, select_rows, valid_rows, zero_loss};
use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::activation::log_softmax;

/// PyTorch's `CrossEntropyLoss(weight=weights, ignore_index=ignore, reduction='mean')` on logits
/// `[N, C]` (docs/losses.md §2):
///
/// `loss = Σ_{i: y_i != ignore} w[y_i] · (−log_softmax(x_i)[y_i]) / Σ_{i: y_i != ignore} w[y_i]`.
///
/// `labels` has one class index per row (`< C`) or `ignore`; `weights` has `C` entries. When no row
/// is left, or the weights of the remaining rows sum to 0, the loss is 0 (PyTorch returns NaN).
/// The same formula with `avg_factor = Σ w[labels]` is the query-classification CE of the SparseOcc
/// head (docs/losses.md §2).
pub fn cross_entropy_weighted<B: Backend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    weights: &[f64],
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&logits, labels, ignore, "cross_entropy_weighted")?;
    let [_, c] = logits.dims();
    if weights.len() != c {
        return Err(ModelError::Input(format!(
            "cross_entropy_weighted: {} class weights for {c} classes",
            weights.len()
        )));
    }
    if let Some((k, w)) = weights.iter().enumerate().find(|(_, w)| !w.is_finite()) {
        return Err(ModelError::Input(format!(
            "cross_entropy_weighted: class weight {k} is {w}"
        )));
    }
    let (rows, ys) = valid_rows(labels, ignore);
    let row_w: Vec<f64> = ys.iter().map(|&y| weights[y as usize]).collect();
    let w_sum: f64 = row_w.iter().sum();
    if rows.is_empty() || w_sum == 0.0 {
        return Ok(zero_loss(logits));
    }
    let n = rows.len();
    let x = select_rows(logits, &rows);
    let device = x.device();
    let logp = log_softmax(x, 1);
    let idx: Vec<i64> = ys.iter().map(|&y| y as i64).collect();
    let idx = Tensor::<B, 2, Int>::from_data(TensorData::new(idx, [n, 1]), &device);
    let picked = logp.gather(1, idx); // [n, 1]
    let w = host_tensor(row_w, [n, 1], &picked);
    Ok((picked * w).sum().neg().mul_scalar(1.0 / w_sum))
}

/// Unweighted cross-entropy with an ignore label: the mean of `−log_softmax(x_i)[y_i]` over the
/// rows whose label is not `ignore` (PyTorch `CrossEntropyLoss(ignore_index=ignore)`).
pub fn cross_entropy<B: Backend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    let c = logits.dims()[1];
    cross_entropy_weighted(logits, labels, &vec![1.0; c], ignore)
}
