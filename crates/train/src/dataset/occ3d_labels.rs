//! Occ3D classes (free = 17) to training ids (empty = 0, outside `mask_camera` ignored) and back.

use occ_data::formats::occ3d::{self, Occ3dLabels};
use occ_labels::{EMPTY, IGNORE};

/// Occ3D labels to training ids: free (17) -> 0, class `c` -> `c + 1`, outside `mask_camera` -> 255.
pub fn occ3d_training_labels(l: &Occ3dLabels) -> Vec<u8> {
    l.semantics
        .iter()
        .zip(&l.mask_camera)
        .map(|(&s, &m)| match (m, s) {
            (0, _) => IGNORE,
            (_, occ3d::FREE) => EMPTY,
            (_, c) => c + 1,
        })
        .collect()
}

/// Training ids back to Occ3D classes: 0 -> free (17), `k` -> `k - 1` (255 stays invalid).
pub fn occ3d_from_training(classes: &[u8]) -> Vec<u8> {
    classes
        .iter()
        .map(|&k| match k {
            EMPTY => occ3d::FREE,
            IGNORE => IGNORE,
            k => k - 1,
        })
        .collect()
}
