//! Scene-class affinity losses of MonoScene (`loss/ssc_loss.py`; docs/losses.md §4): `geo_scal` and
//! `sem_scal`. Both use the softmax probabilities of the voxels whose label is not `ignore` only
//! (the ignore mask is applied before every sum), and `BCE(x, 1) = min(−ln x, 100)` as PyTorch's
//! `binary_cross_entropy` with target 1.
//!
//! Degenerate denominators: the reference divides by zero (NaN) when a sum is 0; here such a term
//! is skipped instead (documented per function). With real labels this never happens except for
//! scenes without any empty / any occupied voxel.

use super::{check_labels, host_tensor, neg_log_capped, select_rows, valid_rows, zero_loss};
use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::activation::softmax;
use occ_sparse::{sum_rows, SparseConvBackend};

/// `num / den` where `den > 0`, and `1` (a BCE term of 0 with gradient 0) where `den <= 0`.
fn safe_ratio<B: Backend, const D: usize>(num: Tensor<B, D>, den: Tensor<B, D>) -> Tensor<B, D> {
    let bad = den.clone().lower_equal_elem(0.0);
    let den = den.mask_fill(bad.clone(), 1.0);
    (num / den).mask_fill(bad, 1.0)
}

/// [`geo_scal_loss_probs`] on `softmax(logits, 1)`.
pub fn geo_scal_loss<B: SparseConvBackend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    empty: u8,
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&logits, labels, ignore, "geo_scal_loss")?;
    geo_scal_loss_probs(softmax(logits, 1), labels, empty, ignore)
}

/// Geometric scene-class affinity loss on class probabilities `probs` `[N, C]` (docs/losses.md §4).
///
/// Over the rows with `label != ignore`: `p0 = probs[:, empty]`, `pn = 1 − p0`,
/// `t = (label != empty)`; `P = Σ t·pn / Σ pn`, `R = Σ t·pn / Σ t`, `S = Σ (1−t)·p0 / Σ (1−t)`;
/// `loss = −ln P − ln R − ln S`. A term whose denominator is 0 is left out (the reference gives
/// NaN); with no row left the loss is 0.
pub fn geo_scal_loss_probs<B: SparseConvBackend>(
    probs: Tensor<B, 2>,
    labels: &[u8],
    empty: u8,
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&probs, labels, ignore, "geo_scal_loss")?;
    let [_, c] = probs.dims();
    if empty as usize >= c {
        return Err(ModelError::Input(format!(
            "geo_scal_loss: empty class {empty} is not < {c}"
        )));
    }
    let (rows, ys) = valid_rows(labels, ignore);
    if rows.is_empty() {
        return Ok(zero_loss(probs));
    }
    let n = rows.len();
    let p = select_rows(probs, &rows);
    let e = empty as usize;
    let p0 = p.clone().slice([0..n, e..e + 1]); // [n, 1]
    let pn = p0.clone().neg().add_scalar(1.0);
    let t_host: Vec<f64> = ys
        .iter()
        .map(|&y| if y != empty { 1.0 } else { 0.0 })
        .collect();
    let n_occ: f64 = t_host.iter().sum();
    let n_empty = n as f64 - n_occ;
    let t = host_tensor(t_host, [n, 1], &p);
    let inter = (t.clone() * pn.clone()).sum();
    let precision = safe_ratio(inter.clone(), pn.sum());
    let mut loss = neg_log_capped(precision);
    if n_occ > 0.0 {
        loss = loss + neg_log_capped(inter.mul_scalar(1.0 / n_occ));
    }
    if n_empty > 0.0 {
        let spec = (t.neg().add_scalar(1.0) * p0)
            .sum()
            .mul_scalar(1.0 / n_empty);
        loss = loss + neg_log_capped(spec);
    }
    Ok(loss)
}

/// [`sem_scal_loss_probs`] on `softmax(logits, 1)`.
pub fn sem_scal_loss<B: SparseConvBackend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&logits, labels, ignore, "sem_scal_loss")?;
    sem_scal_loss_probs(softmax(logits, 1), labels, ignore)
}

/// Semantic scene-class affinity loss on class probabilities `probs` `[N, C]` (docs/losses.md §4).
///
/// Over the rows with `label != ignore`, for each class `i` present there, with `t = (label == i)`:
/// `P = Σ p_i·t / Σ p_i` (only if `Σ p_i > 0`), `R = Σ p_i·t / Σ t`,
/// `S = Σ (1−p_i)(1−t) / Σ (1−t)` (only if `Σ (1−t) > 0`); the class loss is the sum of the
/// `−ln` terms, and the result is their mean over the present classes (0 with no row left).
pub fn sem_scal_loss_probs<B: SparseConvBackend>(
    probs: Tensor<B, 2>,
    labels: &[u8],
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&probs, labels, ignore, "sem_scal_loss")?;
    let (rows, ys) = valid_rows(labels, ignore);
    if rows.is_empty() {
        return Ok(zero_loss(probs));
    }
    let [_, c] = probs.dims();
    let n = rows.len();
    let mut count = vec![0usize; c];
    for &y in &ys {
        count[y as usize] += 1;
    }
    let classes: Vec<usize> = (0..c).filter(|&k| count[k] > 0).collect();
    let cp = classes.len();
    let mut slot = vec![usize::MAX; c];
    for (j, &k) in classes.iter().enumerate() {
        slot[k] = j;
    }
    let p = select_rows(probs, &rows);
    let device = p.device();
    // Probabilities of the present classes only, [n, cp].
    let p = if cp == c {
        p
    } else {
        let idx: Vec<i64> = classes.iter().map(|&k| k as i64).collect();
        p.select(
            1,
            Tensor::<B, 1, Int>::from_data(TensorData::new(idx, [cp]), &device),
        )
    };
    let mut onehot = vec![0.0; n * cp];
    for (i, &y) in ys.iter().enumerate() {
        onehot[i * cp + slot[y as usize]] = 1.0;
    }
    let t = host_tensor(onehot, [n, cp], &p);
    // Column sums over the voxel axis in two levels (occ_sparse::sum_rows: burn's `sum_dim(0)`
    // loops over every voxel on one thread per class on the cubecl backends).
    let nominator = sum_rows(p.clone() * t.clone()); // [1, cp]
    let sum_p = sum_rows(p.clone());
    let precision = neg_log_capped(safe_ratio(nominator.clone(), sum_p));
    let pos: Vec<f64> = classes.iter().map(|&k| count[k] as f64).collect();
    let neg: Vec<f64> = pos.iter().map(|&x| n as f64 - x).collect();
    let recall = neg_log_capped(nominator / host_tensor(pos, [1, cp], &t));
    let spec_num = sum_rows(p.neg().add_scalar(1.0) * t.clone().neg().add_scalar(1.0));
    let specificity = neg_log_capped(safe_ratio(spec_num, host_tensor(neg, [1, cp], &t)));
    Ok((precision + recall + specificity)
        .sum()
        .mul_scalar(1.0 / cp as f64))
}
