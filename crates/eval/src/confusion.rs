//! Square confusion matrix with `u64` counts, indexed `conf[pred][gt]` (rows = prediction,
//! columns = ground truth, as in semantic-kitti-api `np_ioueval.py`).

use serde::{Deserialize, Serialize};

/// `n × n` confusion matrix, `counts[pred * n + gt]`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ConfusionMatrix {
    n: usize,
    counts: Vec<u64>,
}

impl ConfusionMatrix {
    /// All-zero `n × n` matrix.
    pub fn new(n: usize) -> Self {
        Self {
            n,
            counts: vec![0; n * n],
        }
    }

    /// Build from rows `rows[pred][gt]`; `None` if the rows are not square.
    pub fn from_rows(rows: &[Vec<u64>]) -> Option<Self> {
        let n = rows.len();
        if rows.iter().any(|r| r.len() != n) {
            return None;
        }
        Some(Self {
            n,
            counts: rows.iter().flatten().copied().collect(),
        })
    }

    /// Rows `[pred][gt]`.
    pub fn to_rows(&self) -> Vec<Vec<u64>> {
        if self.n == 0 {
            return Vec::new();
        }
        self.counts.chunks(self.n).map(|r| r.to_vec()).collect()
    }

    /// Number of classes.
    pub fn num_classes(&self) -> usize {
        self.n
    }

    /// `conf[pred][gt]`; 0 outside the matrix.
    pub fn get(&self, pred: usize, gt: usize) -> u64 {
        if pred < self.n && gt < self.n {
            self.counts[pred * self.n + gt]
        } else {
            0
        }
    }

    /// Add `count` to `conf[pred][gt]`. Returns false (and adds nothing) outside the matrix.
    pub fn add(&mut self, pred: usize, gt: usize, count: u64) -> bool {
        if pred < self.n && gt < self.n {
            self.counts[pred * self.n + gt] += count;
            true
        } else {
            false
        }
    }

    /// Element-wise sum; `false` (nothing added) if the sizes differ.
    pub fn merge(&mut self, other: &ConfusionMatrix) -> bool {
        if other.n != self.n {
            return false;
        }
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        true
    }

    /// Sum of row `pred` (all voxels predicted as `pred`).
    pub fn row_sum(&self, pred: usize) -> u64 {
        (0..self.n).map(|g| self.get(pred, g)).sum()
    }

    /// Sum of column `gt` (all voxels labelled `gt`).
    pub fn col_sum(&self, gt: usize) -> u64 {
        (0..self.n).map(|p| self.get(p, gt)).sum()
    }

    /// Sum of all counts.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// The sum of all counts, `None` when it does not fit a `u64` (then every row, column and
    /// total that the metrics take would wrap).
    pub fn checked_total(&self) -> Option<u64> {
        self.counts.iter().try_fold(0u64, |t, &c| t.checked_add(c))
    }

    /// Raw counts in row-major `[pred][gt]` order.
    pub fn counts(&self) -> &[u64] {
        &self.counts
    }
}
