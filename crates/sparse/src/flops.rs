//! Opt-in count of the multiply-adds of the sparse convolutions run on this thread.
//!
//! Off by default: [`add`] then reads one thread-local flag and returns. When enabled, every
//! [`crate::conv::sparse_conv3d`] adds `pairs * c_in * c_out` (its kernel map's pair count times the
//! weight's channels) and callers (a profiler) drain the count with [`take`]. The count is the
//! forward pass only; bias additions and the kernel-map build are not multiply-adds and are not
//! counted.
//!
//! A map whose table lives only on a device (built there, without host pairs) is counted from that
//! table: the count is queued with [`add_later`] and read back at the next [`take`], which callers
//! make after synchronising, so that counting neither builds host pairs nor stalls the pass.

use std::cell::{Cell, RefCell};

/// A count read later (at [`take`]).
pub type LaterCount = Box<dyn FnOnce() -> u64>;

thread_local! {
    static ON: Cell<bool> = const { Cell::new(false) };
    static MACS: Cell<u64> = const { Cell::new(0) };
    static LATER: RefCell<Vec<LaterCount>> = const { RefCell::new(Vec::new()) };
}

/// Turns counting on or off for this thread (clearing the count).
pub fn enable(on: bool) {
    ON.with(|c| c.set(on));
    MACS.with(|m| m.set(0));
    LATER.with(|l| l.borrow_mut().clear());
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

/// Adds the multiply-adds that `count` returns when it is called, at the next [`take`] (when
/// counting is on; `count` is dropped uncalled otherwise).
pub fn add_later(count: LaterCount) {
    if enabled() {
        LATER.with(|l| l.borrow_mut().push(count));
    }
}

/// The multiply-adds counted since the last `take` (or `enable`), cleared. Reads the counts queued
/// with [`add_later`].
pub fn take() -> u64 {
    let later = LATER.with(|l| std::mem::take(&mut *l.borrow_mut()));
    let n = later.into_iter().fold(0u64, |n, f| n.saturating_add(f()));
    MACS.with(|m| m.replace(0)).saturating_add(n)
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

    #[test]
    fn later_counts_are_read_at_take_and_dropped_when_off() {
        enable(true);
        add(3);
        add_later(Box::new(|| 40));
        add_later(Box::new(|| 500));
        assert_eq!(take(), 543);
        assert_eq!(take(), 0, "take reads each later count once");
        add_later(Box::new(|| 7));
        enable(true);
        assert_eq!(take(), 0, "enable clears queued counts");
        enable(false);
        add_later(Box::new(|| {
            unreachable!("not queued while counting is off")
        }));
        assert_eq!(take(), 0);
    }
}
