//! Training losses of the occupancy models (docs/losses.md), as differentiable burn graphs.
//!
//! - [`ce`]: class-weighted cross-entropy with an ignore label (PyTorch `CrossEntropyLoss(weight,
//!   ignore_index=255, reduction='mean')`).
//! - [`lovasz`]: Lovasz-softmax (Berman et al. 2018), `classes='present'`, `per_image=False`.
//! - [`scal`]: MonoScene's `geo_scal_loss` and `sem_scal_loss`.
//! - [`mask`]: binary cross-entropy with logits and the naive dice loss for mask predictions
//!   (SparseOcc transformer head, docs/losses.md §5).
//! - [`depth`]: the LSS depth-distribution BCE and the metric-depth → bin-index conversion.
//!
//! Conventions shared by the voxel losses: predictions are rows `[N, C]` (one row per voxel, class 0 =
//! empty), labels are a host slice `&[u8]` with one class index per row and `ignore` (255) for
//! unlabelled voxels. Labels stay on the host because every loss needs host-side bookkeeping anyway
//! (present classes, counts, sort orders for Lovasz); ground-truth grids are `u8` in this project
//! (docs/formats.md §1). The result of every loss is a one-element tensor `[1]` that is part of the autodiff
//! graph of the prediction, also when nothing is left to supervise (then it is `0 * sum(pred)`).
//!
//! Precision note (burn 0.21): the autodiff backward of `div_scalar` multiplies by `1 / rhs`
//! computed in f32, and `activation::sigmoid` evaluates in f32 even on f64 backends. These losses
//! therefore use `mul_scalar(1.0 / x)` and `exp(log_sigmoid(x))`, which keeps f64 gradients exact.
//!
//! The paper's occupancy loss (Eq. `loss_occ`, Sec. 4) is
//! `L_occ = L_ce + L_lovasz + L_geo_scal + L_sem_scal`, see [`occ_loss`].

pub mod ce;
pub mod depth;
pub mod keys;
pub mod lovasz;
pub mod mask;
pub mod scal;

pub use ce::{cross_entropy, cross_entropy_weighted};
pub use depth::{depth_bce, downsample_depth_min, DepthBinRule, DepthBins};
pub use keys::{LossKey, MaskTerm, OccTerm};
pub use lovasz::{lovasz_grad, lovasz_softmax};
pub use mask::{dice_loss, dice_per_mask, mask_bce, mask_bce_per_mask};
pub use scal::{geo_scal_loss, geo_scal_loss_probs, sem_scal_loss, sem_scal_loss_probs};

use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::activation::softmax;
use occ_labels::{EMPTY, IGNORE, SEMANTIC_KITTI_CLASS_FREQUENCIES};

/// MonoScene cross-entropy class weights `1 / ln(f + 0.001)` from
/// [`SEMANTIC_KITTI_CLASS_FREQUENCIES`] (docs/losses.md §2; `0.0446` for empty … `0.0786` for traffic-sign).
pub fn monoscene_class_weights() -> [f64; 20] {
    SEMANTIC_KITTI_CLASS_FREQUENCIES.map(|f| 1.0 / (f + 0.001).ln())
}

/// SparseOcc class weights `(1 / ln f) / (1 / ln f_empty)` from
/// [`SEMANTIC_KITTI_CLASS_FREQUENCIES`] (docs/losses.md §2; `1.0` for empty … `1.7621` for traffic-sign).
/// Used by the coarse voxel CE of the SparseOcc head.
pub fn sparseocc_class_weights() -> [f64; 20] {
    let f0 = SEMANTIC_KITTI_CLASS_FREQUENCIES[0].ln();
    SEMANTIC_KITTI_CLASS_FREQUENCIES.map(|f| f0 / f.ln())
}

/// Weight of the "no object" class of the SparseOcc mask-classification CE (docs/losses.md §2).
pub const NO_OBJECT_WEIGHT: f64 = 0.1;

/// [`sparseocc_class_weights`] followed by [`NO_OBJECT_WEIGHT`]: the 21 weights of the query
/// classification CE of the SparseOcc transformer head (docs/losses.md §2).
pub fn sparseocc_query_class_weights() -> [f64; 21] {
    let w = sparseocc_class_weights();
    let mut out = [NO_OBJECT_WEIGHT; 21];
    out[..20].copy_from_slice(&w);
    out
}

/// Weights of the four terms of [`occ_loss_weighted`]. All 1.0 by default (paper Eq. `loss_occ`, and
/// SparseOcc's `loss_voxel_*_weight` defaults).
#[derive(Config, Debug)]
pub struct OccLossWeights {
    /// Weighted cross-entropy.
    #[config(default = 1.0)]
    pub ce: f64,
    /// Lovasz-softmax.
    #[config(default = 1.0)]
    pub lovasz: f64,
    /// Geometric scene-class affinity loss.
    #[config(default = 1.0)]
    pub geo_scal: f64,
    /// Semantic scene-class affinity loss.
    #[config(default = 1.0)]
    pub sem_scal: f64,
}

/// The occupancy loss `L_occ = L_ce + L_lovasz + L_geo_scal + L_sem_scal` (paper Eq. `loss_occ`,
/// docs/losses.md §2-§4) with unit weights, on voxel logits `[N, C]` and labels (class 0 empty, 255 ignored).
/// Returns the terms ([`OccTerm`]: `ce`, `lovasz`, `geo_scal`, `sem_scal`; sum them for the total).
pub fn occ_loss<B: occ_sparse::SparseConvBackend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    class_weights: &[f64],
) -> Result<Vec<(OccTerm, Tensor<B, 1>)>, ModelError> {
    occ_loss_weighted(logits, labels, class_weights, &OccLossWeights::new())
}

/// [`occ_loss`] with per-term weights (a term with weight 0 is not computed).
pub fn occ_loss_weighted<B: occ_sparse::SparseConvBackend>(
    logits: Tensor<B, 2>,
    labels: &[u8],
    class_weights: &[f64],
    weights: &OccLossWeights,
) -> Result<Vec<(OccTerm, Tensor<B, 1>)>, ModelError> {
    check_labels(&logits, labels, IGNORE, "occ_loss")?;
    let mut out = Vec::with_capacity(4);
    if weights.ce != 0.0 {
        let l = cross_entropy_weighted(logits.clone(), labels, class_weights, IGNORE)?;
        out.push((OccTerm::Ce, l.mul_scalar(weights.ce)));
    }
    let probs = softmax(logits, 1);
    if weights.lovasz != 0.0 {
        let l = lovasz_softmax(probs.clone(), labels, IGNORE)?;
        out.push((OccTerm::Lovasz, l.mul_scalar(weights.lovasz)));
    }
    if weights.geo_scal != 0.0 {
        let l = geo_scal_loss_probs(probs.clone(), labels, EMPTY, IGNORE)?;
        out.push((OccTerm::GeoScal, l.mul_scalar(weights.geo_scal)));
    }
    if weights.sem_scal != 0.0 {
        let l = sem_scal_loss_probs(probs, labels, IGNORE)?;
        out.push((OccTerm::SemScal, l.mul_scalar(weights.sem_scal)));
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Shared helpers.

/// Checks that `labels` has one entry per row of `pred` and that every label is a class index
/// `< C` or `ignore`.
pub(crate) fn check_labels<B: Backend>(
    pred: &Tensor<B, 2>,
    labels: &[u8],
    ignore: u8,
    what: &str,
) -> Result<(), ModelError> {
    let [n, c] = pred.dims();
    if labels.len() != n {
        return Err(ModelError::Input(format!(
            "{what}: {} labels for {n} prediction rows",
            labels.len()
        )));
    }
    if let Some((i, &l)) = labels
        .iter()
        .enumerate()
        .find(|(_, &l)| l != ignore && l as usize >= c)
    {
        return Err(ModelError::Input(format!(
            "{what}: label {l} at row {i} is neither a class index < {c} nor the ignore label {ignore}"
        )));
    }
    Ok(())
}

/// Rows whose label is not `ignore`, and their labels.
pub(crate) fn valid_rows(labels: &[u8], ignore: u8) -> (Vec<i64>, Vec<u8>) {
    labels
        .iter()
        .enumerate()
        .filter(|(_, &l)| l != ignore)
        .map(|(i, &l)| (i as i64, l))
        .unzip()
}

/// Keeps the rows `rows` of `x` (no copy when all rows are kept).
pub(crate) fn select_rows<B: Backend>(x: Tensor<B, 2>, rows: &[i64]) -> Tensor<B, 2> {
    if rows.len() == x.dims()[0] {
        return x;
    }
    let device = x.device();
    let idx = Tensor::<B, 1, Int>::from_data(TensorData::new(rows.to_vec(), [rows.len()]), &device);
    x.select(0, idx)
}

/// A float tensor from host values with the device and float dtype of `like`.
pub(crate) fn host_tensor<B: Backend, const D: usize, const D2: usize>(
    values: Vec<f64>,
    shape: [usize; D],
    like: &Tensor<B, D2>,
) -> Tensor<B, D> {
    Tensor::from_data(
        TensorData::new(values, shape),
        (&like.device(), like.dtype()),
    )
}

/// A zero loss `[1]` that stays connected to the graph of `pred` (gradient 0).
pub(crate) fn zero_loss<B: Backend, const D: usize>(pred: Tensor<B, D>) -> Tensor<B, 1> {
    pred.sum().mul_scalar(0.0)
}

/// Host copy of a float tensor as f64.
pub(crate) fn to_host<B: Backend, const D: usize>(
    x: Tensor<B, D>,
    what: &str,
) -> Result<Vec<f64>, ModelError> {
    x.into_data()
        .convert::<f64>()
        .to_vec::<f64>()
        .map_err(|e| ModelError::Numerical(format!("{what}: reading tensor: {e:?}")))
}

/// `min(-ln x, 100)`, the value of PyTorch's `binary_cross_entropy(x, 1)` (which clamps the log at
/// -100). Where the cap applies (`x <= e^-100`, also `x <= 0`) the gradient is 0; elsewhere it is
/// `-1/x`. No NaN is produced for `x >= 0`.
pub(crate) fn neg_log_capped<B: Backend, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    let capped = x.clone().lower_equal_elem((-100.0f64).exp());
    let safe = x.mask_fill(capped.clone(), 1.0);
    safe.log().neg().mask_fill(capped, 100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The published weight lists (MonoScene, SparseOcc) have 4 decimals. Four MonoScene entries there (classes 7, 9, 14,
    /// 18: 0.079645, 0.055749, 0.060348, 0.071649) were rounded twice (to 5, then 4 decimals), so
    /// they are 0.5e-4..0.6e-4 above the formula; the SparseOcc list is rounded once.
    #[test]
    fn class_weights_match_facts() {
        let ms = [
            0.0446, 0.0603, 0.0852, 0.0856, 0.0747, 0.0734, 0.0801, 0.0797, 0.0818, 0.0558, 0.0653,
            0.0568, 0.0683, 0.0560, 0.0604, 0.0530, 0.0688, 0.0574, 0.0717, 0.0786,
        ];
        let so = [
            1.0, 1.3523, 1.9096, 1.9181, 1.6751, 1.6457, 1.7959, 1.7851, 1.8327, 1.2495, 1.4630,
            1.2720, 1.5314, 1.2552, 1.3526, 1.1871, 1.5416, 1.2862, 1.6059, 1.7621,
        ];
        for (c, (w, r)) in monoscene_class_weights().iter().zip(ms).enumerate() {
            assert!((w - r).abs() < 0.6e-4, "MonoScene weight {c}: {w} vs {r}");
        }
        for (c, (w, r)) in sparseocc_class_weights().iter().zip(so).enumerate() {
            assert!((w - r).abs() < 0.5e-4, "SparseOcc weight {c}: {w} vs {r}");
        }
        let q = sparseocc_query_class_weights();
        assert_eq!(q[20], 0.1);
        assert_eq!(q[..20], sparseocc_class_weights());
    }
}
