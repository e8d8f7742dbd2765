//! Opt-in count of the multiply-adds of the sparse convolutions run on this thread.
//!
//! Off by default: [`add`] then reads one thread-local flag and returns. When enabled, every
//! [`crate::conv::sparse_conv3d`] adds `pairs * c_in * c_out` (its kernel map's pair count times the
//! weight's channels) and callers (a profiler) drain the count with [`take`]. The count is the
//! forward pass only; bias additions and the kernel-map build are not multiply-adds and are not
//! counted.

use std::cell::Cell;

thread_local! {
    static ON: Cell<bool> = const { Cell::new(false) };
    static MACS: Cell<u64> = const { Cell::new(0) };
}

/// Turns counting on or off for this thread (clearing the count).
pub fn enable(on: bool) {
    ON.with(|c| c.set(on));
    MACS.with(|m| m.set(0));
}

/// Whether counting is on for this thread.
pub fn enabled() -> bool {
    ON.with(Cell::get)
}

/// Adds `macs` multiply-adds when counting is on.
#[inline]
pub fn add(macs: u64) {
    if enabled() {
        MACS.with(|m| m.set(m.get().saturating_add(macs)));
    }
}

/// The multiply-adds counted since the last `take` (or `enable`), cleared.
pub fn take() -> u64 {
    MACS.with(|m| m.replace(0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conv::{ConvKind, SparseConv3dConfig};
    use crate::tensor::SparseTensor;
    use burn::backend::NdArray;
    use burn::prelude::*;

    type B = NdArray<f32>;

    /// Three voxels in a row along x and one isolated voxel, 2 input channels.
    fn sites() -> SparseTensor<B> {
        let coords = vec![[0, 0, 0, 0], [0, 1, 0, 0], [0, 2, 0, 0], [0, 5, 5, 5]];
        let feats = Tensor::<B, 2>::ones([4, 2], &Default::default());
        SparseTensor::new(coords, feats, [8, 8, 8], 1).unwrap()
    }

    #[test]
    fn submanifold_conv_counts_pairs_times_channels() {
        let conv = SparseConv3dConfig::new(2, 3, [3, 3, 3]).init::<B>(&Default::default());
        // Off: nothing is counted.
        enable(false);
        conv.forward(sites()).unwrap();
        assert_eq!(take(), 0);
        enable(true);
        conv.forward(sites()).unwrap();
        // Pairs by hand: 4 centre pairs, (0,1), (1,0), (1,2), (2,1) between the row's neighbours,
        // none for the isolated voxel: 8 pairs x 2 in x 3 out.
        assert_eq!(take(), 8 * 2 * 3);
        assert_eq!(take(), 0, "take clears the count");
        enable(false);
    }

    #[test]
    fn strided_conv_counts_one_pair_per_input() {
        // Kernel 2, stride 2: every input site falls in exactly one output cell.
        let conv = SparseConv3dConfig::new(2, 5, [2, 2, 2])
            .with_kind(ConvKind::Regular)
            .with_stride([2, 2, 2])
            .init::<B>(&Default::default());
        enable(true);
        let out = conv.forward(sites()).unwrap();
        assert_eq!(
            out.num_active(),
            3,
            "(0,0,0) and (1,0,0) share an output cell"
        );
        assert_eq!(take(), 4 * 2 * 5);
        enable(false);
    }
}
