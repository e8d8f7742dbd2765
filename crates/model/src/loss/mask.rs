//! Mask losses of the SparseOcc transformer head (docs/losses.md §5, Mask2Former `sigmoid_ce_loss` and
//! `dice_loss`): mask logits `[Q, P]` (Q matched queries, P sampled points) against binary (or soft)
//! targets `[Q, P]` in `[0, 1]`.

use super::zero_loss;
use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::activation::log_sigmoid;

fn check_shapes<B: Backend>(
    logits: &Tensor<B, 2>,
    targets: &Tensor<B, 2>,
    what: &str,
) -> Result<(), ModelError> {
    if logits.dims() != targets.dims() {
        return Err(ModelError::Input(format!(
            "{what}: logits {:?} and targets {:?} differ in shape",
            logits.dims(),
            targets.dims()
        )));
    }
    Ok(())
}

/// Per-mask binary cross-entropy with logits `[Q]`: the mean over the P points of
/// `−t·ln σ(x) − (1−t)·ln σ(−x)` (PyTorch `binary_cross_entropy_with_logits`, computed with the
/// stable `log_sigmoid`). Zeros when `P = 0`.
pub fn mask_bce_per_mask<B: Backend>(
    logits: Tensor<B, 2>,
    targets: Tensor<B, 2>,
) -> Result<Tensor<B, 1>, ModelError> {
    check_shapes(&logits, &targets, "mask_bce")?;
    let [q, p] = logits.dims();
    if p == 0 {
        return Ok(Tensor::zeros([q], (&logits.device(), logits.dtype())));
    }
    let pos = log_sigmoid(logits.clone()) * targets.clone();
    let neg = log_sigmoid(logits.neg()) * targets.neg().add_scalar(1.0);
    Ok((pos + neg)
        .neg()
        .sum_dim(1)
        .mul_scalar(1.0 / p as f64)
        .reshape([q]))
}

/// Mask BCE `[1]`: the mean of [`mask_bce_per_mask`] over the Q masks (Mask2Former
/// `loss.mean(1).sum() / num_masks` with `num_masks = Q`). 0 when `Q = 0` or `P = 0`.
pub fn mask_bce<B: Backend>(
    logits: Tensor<B, 2>,
    targets: Tensor<B, 2>,
) -> Result<Tensor<B, 1>, ModelError> {
    let [q, p] = logits.dims();
    if q == 0 || p == 0 {
        check_shapes(&logits, &targets, "mask_bce")?;
        return Ok(zero_loss(logits));
    }
    Ok(mask_bce_per_mask(logits, targets)?.mean())
}

/// Per-mask naive dice loss `[Q]` with eps 1: with `s = σ(x)`,
/// `1 − (2·Σ s·t + 1) / (Σ s + Σ t + 1)` over the P points of each mask.
///
/// `σ` is computed as `exp(log_sigmoid(x))`: burn 0.21's `sigmoid` evaluates in f32 even on f64
/// backends, which would limit f64 checks to ~1e-7.
pub fn dice_per_mask<B: Backend>(
    logits: Tensor<B, 2>,
    targets: Tensor<B, 2>,
) -> Result<Tensor<B, 1>, ModelError> {
    check_shapes(&logits, &targets, "dice_loss")?;
    let [q, _] = logits.dims();
    let s = log_sigmoid(logits).exp();
    let num = (s.clone() * targets.clone())
        .sum_dim(1)
        .mul_scalar(2.0)
        .add_scalar(1.0);
    let den = (s.sum_dim(1) + targets.sum_dim(1)).add_scalar(1.0);
    Ok((num / den).neg().add_scalar(1.0).reshape([q]))
}

/// Dice loss `[1]`: the mean of [`dice_per_mask`] over the Q masks (0 when `Q = 0`).
pub fn dice_loss<B: Backend>(
    logits: Tensor<B, 2>,
    targets: Tensor<B, 2>,
) -> Result<Tensor<B, 1>, ModelError> {
    if logits.dims()[0] == 0 {
        check_shapes(&logits, &targets, "dice_loss")?;
        return Ok(zero_loss(logits));
    }
    Ok(dice_per_mask(logits, targets)?.mean())
}
