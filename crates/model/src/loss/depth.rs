//! Depth supervision of the LSS view transformer (docs/losses.md §6, SparseOcc
//! `image2bev/ViewTransformerLSSVoxel.py`): per-patch minimum lidar depth, metric depth → bin index,
//! and the BCE between the predicted depth distribution and the one-hot bin.

use super::{host_tensor, neg_log_capped, select_rows, zero_loss};
use crate::error::ModelError;
use burn::prelude::*;

/// How a metric depth `d` becomes a bin index, with `k = floor((d − (d_min − step/2)) / step)`
/// (docs/losses.md §6).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DepthBinRule {
    /// Bin `k`, valid for `0 <= k < D`: the bin whose center `d_min + k·step` is nearest to `d`
    /// (bin `k` covers `[d_min + (k − ½)·step, d_min + (k + ½)·step)`). This is the rule the LSS
    /// lifting implies (depth candidates `arange(d_min, d_max, step)`); the default here.
    #[default]
    NearestCenter,
    /// The SparseOcc code exactly: `k` is kept if `0 <= k < D + 1` (else set to 0), one-hot with
    /// `D + 1` columns, column 0 dropped. The effective bin is therefore `k − 1`, valid for
    /// `1 <= k <= D`: bin `b` covers `[d_min + (b + ½)·step, d_min + (b + 3/2)·step)`, half a step
    /// beyond its LSS depth candidate, and depths in `[d_min − ½·step, d_min + ½·step)` get no
    /// supervision.
    SparseOccOfficial,
}

/// Depth bins `arange(d_min, d_max, step)` (the LSS `dbound = [d_min, d_max, step]`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthBins {
    /// Depth of bin 0's candidate, metres.
    pub d_min_m: f64,
    /// Bin width, metres.
    pub step_m: f64,
    /// Number of bins D.
    pub num_bins: usize,
}

impl DepthBins {
    /// Bins from an LSS `dbound = [d_min, d_max, step]`; `D = ceil((d_max − d_min) / step)`, the
    /// length of `arange(d_min, d_max, step)` (SemanticKITTI `[2, 58, 0.5]` → 112).
    pub fn from_dbound(dbound: [f64; 3]) -> Result<Self, ModelError> {
        let [lo, hi, step] = dbound;
        if !(lo.is_finite() && hi.is_finite() && step.is_finite() && step > 0.0 && hi > lo) {
            return Err(ModelError::Config(format!(
                "depth bins: dbound {dbound:?} needs finite d_min < d_max and step > 0"
            )));
        }
        let num_bins = ((hi - lo) / step - 1e-9).ceil() as usize;
        Ok(Self {
            d_min_m: lo,
            step_m: step,
            num_bins,
        })
    }

    /// Depth candidate of bin `k`: `d_min + k·step`.
    pub fn center_m(&self, k: usize) -> f64 {
        self.d_min_m + k as f64 * self.step_m
    }

    /// Bin index of one metric depth under `rule`; `None` for depths `<= 0` (no lidar return),
    /// non-finite depths and depths outside the bins.
    pub fn bin_index(&self, depth_m: f64, rule: DepthBinRule) -> Option<usize> {
        if !(depth_m.is_finite() && depth_m > 0.0) {
            return None;
        }
        let k = ((depth_m - (self.d_min_m - self.step_m / 2.0)) / self.step_m).floor();
        let d = self.num_bins as f64;
        match rule {
            DepthBinRule::NearestCenter => (k >= 0.0 && k < d).then_some(k as usize),
            DepthBinRule::SparseOccOfficial => (k >= 1.0 && k < d + 1.0).then(|| k as usize - 1),
        }
    }

    /// [`Self::bin_index`] for every depth.
    pub fn bin_indices(&self, depths_m: &[f32], rule: DepthBinRule) -> Vec<Option<usize>> {
        depths_m
            .iter()
            .map(|&d| self.bin_index(d as f64, rule))
            .collect()
    }
}

/// Minimum non-zero depth in each `ds × ds` patch of a depth map `[h, w]` (row-major), 0 where a
/// patch has no non-zero depth (docs/losses.md §6 step 1; SparseOcc replaces zeros by 1e5 before the min,
/// which the bin rules then reject, the same as 0 here). Returns `[h/ds, w/ds]` row-major; `h` and
/// `w` must be multiples of `ds`.
pub fn downsample_depth_min(
    depth_m: &[f32],
    h: usize,
    w: usize,
    ds: usize,
) -> Result<Vec<f32>, ModelError> {
    if ds == 0 || !h.is_multiple_of(ds) || !w.is_multiple_of(ds) || depth_m.len() != h * w {
        return Err(ModelError::Input(format!(
            "downsample_depth_min: {} depths for {h}x{w} with patch {ds} (need h, w multiples of ds)",
            depth_m.len()
        )));
    }
    let (ho, wo) = (h / ds, w / ds);
    let mut out = vec![0.0f32; ho * wo];
    for (r, row) in depth_m.chunks_exact(w).enumerate() {
        for (col, &d) in row.iter().enumerate() {
            if d > 0.0 && d.is_finite() {
                let o = &mut out[(r / ds) * wo + col / ds];
                if *o == 0.0 || d < *o {
                    *o = d;
                }
            }
        }
    }
    Ok(out)
}

/// Depth BCE (docs/losses.md §6 step 3): `probs` `[N, D]` is the predicted (softmaxed) depth distribution
/// per pixel, `bins[i]` the target bin of pixel `i` (`None` = no supervision). Over the foreground
/// rows (a valid bin), `Σ_rows Σ_d BCE(p_d, onehot_d) / max(1, #fg)` with
/// `BCE(p, t) = −t·ln p − (1−t)·ln(1−p)` and the logs capped at −100 as in PyTorch.
pub fn depth_bce<B: Backend>(
    probs: Tensor<B, 2>,
    bins: &[Option<usize>],
) -> Result<Tensor<B, 1>, ModelError> {
    let [n, d] = probs.dims();
    if bins.len() != n {
        return Err(ModelError::Input(format!(
            "depth_bce: {} bin targets for {n} prediction rows",
            bins.len()
        )));
    }
    let mut rows = Vec::new();
    let mut targets = Vec::new();
    for (i, b) in bins.iter().enumerate() {
        if let Some(b) = *b {
            if b >= d {
                return Err(ModelError::Input(format!(
                    "depth_bce: bin {b} at row {i} is not < {d}"
                )));
            }
            rows.push(i as i64);
            targets.push(b);
        }
    }
    if rows.is_empty() {
        return Ok(zero_loss(probs));
    }
    let nf = rows.len();
    let p = select_rows(probs, &rows);
    let mut onehot = vec![0.0; nf * d];
    for (i, &b) in targets.iter().enumerate() {
        onehot[i * d + b] = 1.0;
    }
    let t = host_tensor(onehot, [nf, d], &p);
    let pos = neg_log_capped(p.clone()) * t.clone();
    let neg = neg_log_capped(p.neg().add_scalar(1.0)) * t.neg().add_scalar(1.0);
    Ok((pos + neg).sum().mul_scalar(1.0 / nf as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kitti_dbound_has_112_bins_and_rules_differ_by_one() {
        let b = DepthBins::from_dbound([2.0, 58.0, 0.5]).unwrap();
        assert_eq!(b.num_bins, 112);
        let near = DepthBinRule::NearestCenter;
        let so = DepthBinRule::SparseOccOfficial;
        // Exactly on a candidate depth: nearest bin is that candidate.
        assert_eq!(b.bin_index(2.0, near), Some(0));
        assert_eq!(b.bin_index(2.0, so), None);
        assert_eq!(b.bin_index(2.3, near), Some(1));
        assert_eq!(b.bin_index(2.3, so), Some(0));
        assert_eq!(b.bin_index(1.74, near), None);
        assert_eq!(b.bin_index(1.75, near), Some(0));
        assert_eq!(b.bin_index(57.74, near), Some(111));
        assert_eq!(b.bin_index(57.76, near), None);
        assert_eq!(b.bin_index(58.24, so), Some(111));
        assert_eq!(b.bin_index(58.26, so), None);
        assert_eq!(b.bin_index(0.0, near), None);
        assert_eq!(b.bin_index(f64::NAN, so), None);
    }

    #[test]
    fn patch_min_ignores_zeros() {
        // 2 x 6 map, patches of 2: [[0,5],[0,0]] -> 5, [[3,0],[4,2]] -> 2, [[0,0],[7,1]] -> 1
        let d = [0.0, 5.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0, 2.0, 7.0, 1.0];
        let out = downsample_depth_min(&d, 2, 6, 2).unwrap();
        assert_eq!(out, vec![5.0, 2.0, 1.0]);
        assert!(downsample_depth_min(&d, 3, 4, 2).is_err());
        assert!(downsample_depth_min(&d, 2, 6, 4).is_err());
    }
}
