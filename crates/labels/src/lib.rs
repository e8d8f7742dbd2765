//! The label conventions of the whole project, in one place (docs/formats.md §1, §2.6, §2.10).
//!
//! Ground-truth and predicted grids hold one `u8` training class per voxel. Every dataset's training
//! ids follow the same two conventions: [`EMPTY`] (0) is empty space, [`IGNORE`] (255) a voxel without
//! ground truth (invalid, unknown, outside the camera mask, noise), which losses and metrics skip.
//! Occ3D's own files keep their "free" class 17; the training pipeline maps it to [`EMPTY`].
//!
//! - [`downsample`]: the two label-downsampling rules of the reference codebases (the MonoScene / SSC
//!   rule and the SparseOcc in-network mode rule).
//! - [`SEMANTIC_KITTI_CLASS_FREQUENCIES`]: the voxel counts the class weights are derived from.
//!
//! This crate depends on nothing; every other crate of the workspace may use it.

pub mod downsample;

pub use downsample::{
    downsample_mode, downsample_monoscene, monoscene_block_label, DownsampleError,
};

/// Class id of empty space (docs/formats.md §1).
pub const EMPTY: u8 = 0;

/// Label of voxels that are not supervised and not scored (docs/formats.md §2.4-§2.5: invalid /
/// unknown voxels); also what a reader makes of a prediction value that is no class.
pub const IGNORE: u8 = 255;

/// True for a label that is a class of something (neither [`EMPTY`] nor [`IGNORE`]).
pub fn is_occupied(label: u8) -> bool {
    label != EMPTY && label != IGNORE
}

/// SemanticKITTI voxel class frequencies, in class order empty, car, …, traffic-sign (docs/formats.md
/// §2.10; MonoScene `data/semantic_kitti/params.py`, SparseOcc `utils/semkitti.py`).
pub const SEMANTIC_KITTI_CLASS_FREQUENCIES: [f64; 20] = [
    5.41773033e9,
    1.57835390e7,
    1.25136e5,
    1.18809e5,
    6.46799e5,
    8.21951e5,
    2.62978e5,
    2.83696e5,
    2.0475e5,
    6.16887030e7,
    4.502961e6,
    4.488365e7,
    2.269923e6,
    5.68402180e7,
    1.57196520e7,
    1.58442623e8,
    2.061623e6,
    3.69705220e7,
    1.151988e6,
    3.34146e5,
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn occupied_is_neither_empty_nor_ignore() {
        assert!(!is_occupied(EMPTY));
        assert!(!is_occupied(IGNORE));
        assert!((1..=254).all(is_occupied));
    }

    #[test]
    fn empty_is_the_most_frequent_class() {
        let f = SEMANTIC_KITTI_CLASS_FREQUENCIES;
        assert!(f[1..].iter().all(|&c| c < f[0]));
    }
}
