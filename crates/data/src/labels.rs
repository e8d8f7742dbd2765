//! Label remaps (SemanticKITTI learning map and its inverse) and label-grid downsampling
//! (docs/formats.md §2.4 and §2.6).

use crate::error::DataError;
use occ_labels::{downsample_monoscene, EMPTY, IGNORE};

/// A lookup table from raw 16-bit dataset ids to training classes, and back.
///
/// Built like the official lut trick (SemanticKITTI `evaluate_completion.py`, MonoScene
/// `get_remap_lut`): every raw id not in the map, and every raw id that the map sends to 0,
/// becomes 255 (ignore), except raw 0 which stays 0 (empty). The table covers all 65,536 raw
/// ids, so any `u16` is a valid input.
#[derive(Clone, Debug, PartialEq)]
pub struct LearningMap {
    lut: Vec<u8>,
    /// Raw ids the map lists (whatever class they get).
    listed: Vec<bool>,
    inv: [u16; 256],
    num_classes: usize,
}

/// SemanticKITTI `learning_map` (raw id -> class), docs/formats.md §2.4. Raw ids mapping to 0 in the yaml
/// (1 outlier, 52 other-structure, 99 other-object) are listed as 0 and become 255.
const SEMANTIC_KITTI_LEARNING_MAP: [(u16, u8); 34] = [
    (0, 0),
    (1, 0),
    (10, 1),
    (11, 2),
    (13, 5),
    (15, 3),
    (16, 5),
    (18, 4),
    (20, 5),
    (30, 6),
    (31, 7),
    (32, 8),
    (40, 9),
    (44, 10),
    (48, 11),
    (49, 12),
    (50, 13),
    (51, 14),
    (52, 0),
    (60, 9),
    (70, 15),
    (71, 16),
    (72, 17),
    (80, 18),
    (81, 19),
    (99, 0),
    (252, 1),
    (253, 7),
    (254, 6),
    (255, 8),
    (256, 5),
    (257, 5),
    (258, 4),
    (259, 5),
];

/// SemanticKITTI `learning_map_inv` (class -> raw id), docs/formats.md §2.4.
const SEMANTIC_KITTI_LEARNING_MAP_INV: [u16; 20] = [
    0, 10, 11, 15, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 70, 71, 72, 80, 81,
];

impl LearningMap {
    /// Build from `(raw, class)` pairs and the inverse table `class -> raw`, with the lut rule
    /// (unlisted or class-0 raw ids -> 255, raw 0 -> 0).
    pub fn from_pairs(pairs: &[(u16, u8)], inverse: &[u16]) -> Self {
        let mut lut = vec![0u8; 65536];
        let mut listed = vec![false; 65536];
        for &(raw, class) in pairs {
            lut[raw as usize] = class;
            listed[raw as usize] = true;
        }
        for v in lut.iter_mut() {
            if *v == EMPTY {
                *v = IGNORE;
            }
        }
        lut[0] = EMPTY;
        let mut inv = [0u16; 256];
        for (c, &raw) in inverse.iter().enumerate().take(256) {
            inv[c] = raw;
        }
        LearningMap {
            lut,
            listed,
            inv,
            num_classes: inverse.len(),
        }
    }

    /// The SemanticKITTI SSC map: 20 classes (0 empty .. 19 traffic-sign), 255 ignore.
    pub fn semantic_kitti() -> Self {
        Self::from_pairs(
            &SEMANTIC_KITTI_LEARNING_MAP,
            &SEMANTIC_KITTI_LEARNING_MAP_INV,
        )
    }

    /// Number of training classes (20 for SemanticKITTI).
    pub fn num_classes(&self) -> usize {
        self.num_classes
    }

    /// True for a raw id the map lists (raw 0 always): ids it does not list are not labels of this
    /// dataset (a corrupted or foreign label file).
    pub fn is_listed(&self, raw: u16) -> bool {
        raw == 0 || self.listed[raw as usize]
    }

    /// Training class of a raw id (0..num_classes, or 255 = ignore).
    pub fn to_class(&self, raw: u16) -> u8 {
        self.lut[raw as usize]
    }

    /// Raw id of a training class (`learning_map_inv`). Classes outside `0..num_classes`
    /// (including 255) map to raw 0 (unlabeled), so a submission never holds an unknown id.
    pub fn to_raw(&self, class: u8) -> u16 {
        if (class as usize) < self.num_classes {
            self.inv[class as usize]
        } else {
            0
        }
    }

    /// Remap raw ids to classes.
    pub fn remap(&self, raw: &[u16]) -> Vec<u8> {
        raw.iter().map(|&r| self.lut[r as usize]).collect()
    }

    /// Remap per-point uint32 labels (low 16 bits = semantic raw id, high 16 = instance).
    pub fn remap_point_labels(&self, labels: &[u32]) -> Vec<u8> {
        labels
            .iter()
            .map(|&l| self.lut[(l & 0xFFFF) as usize])
            .collect()
    }

    /// Classes to raw ids (for submission files).
    pub fn inverse_remap(&self, classes: &[u8]) -> Vec<u16> {
        classes.iter().map(|&c| self.to_raw(c)).collect()
    }
}

/// Downsample a SemanticKITTI-style label grid by `factor` with the MonoScene / SparseOcc / VoxFormer
/// `_downsample_label` rule ([`occ_labels::downsample_monoscene`], docs/formats.md §2.6), as the
/// preprocessing writes the 1/2-resolution labels: every dim must be divisible by `factor`.
///
/// `labels` is flat C order `[x][y][z]`.
pub fn downsample_labels(
    labels: &[u8],
    dims: [usize; 3],
    factor: usize,
) -> Result<Vec<u8>, DataError> {
    if factor == 0 || dims.iter().any(|d| d % factor != 0) {
        return Err(DataError::InvalidArgument(format!(
            "dims {dims:?} are not divisible by downsampling factor {factor}"
        )));
    }
    downsample_monoscene(labels, dims, factor)
        .map_err(|e| DataError::InvalidArgument(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learning_map_table_from_facts() {
        let m = LearningMap::semantic_kitti();
        let expect: &[(&[u16], u8)] = &[
            (&[10, 252], 1),
            (&[11], 2),
            (&[15], 3),
            (&[18, 258], 4),
            (&[13, 16, 20, 256, 257, 259], 5),
            (&[30, 254], 6),
            (&[31, 253], 7),
            (&[32, 255], 8),
            (&[40, 60], 9),
            (&[44], 10),
            (&[48], 11),
            (&[49], 12),
            (&[50], 13),
            (&[51], 14),
            (&[70], 15),
            (&[71], 16),
            (&[72], 17),
            (&[80], 18),
            (&[81], 19),
        ];
        let mut listed = vec![false; 65536];
        for (raws, c) in expect {
            for &r in *raws {
                assert_eq!(m.to_class(r), *c, "raw {r}");
                listed[r as usize] = true;
            }
        }
        assert_eq!(m.to_class(0), 0);
        for raw in 1..=65535u16 {
            if !listed[raw as usize] {
                assert_eq!(m.to_class(raw), 255, "raw {raw}");
            }
        }
        let inv = [
            0u16, 10, 11, 15, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 70, 71, 72, 80, 81,
        ];
        for (c, &r) in inv.iter().enumerate() {
            assert_eq!(m.to_raw(c as u8), r);
            assert_eq!(m.to_class(r), c as u8, "inverse map must round trip");
        }
        assert_eq!(m.to_raw(255), 0);
        assert_eq!(m.to_raw(20), 0);
        assert_eq!(
            m.remap_point_labels(&[(7 << 16) | 10, 0xFFFF_FFFF]),
            vec![1, 255]
        );
    }

    #[test]
    fn downsample_special_cases() {
        // 4 zeros + 4 ignores -> 255 (tie), 5 zeros + 3 ignores -> 0
        let mut a = vec![0u8; 8];
        a[4..].fill(255);
        assert_eq!(downsample_labels(&a, [2, 2, 2], 2).unwrap(), vec![255]);
        a[4] = 0;
        assert_eq!(downsample_labels(&a, [2, 2, 2], 2).unwrap(), vec![0]);
        // one semantic voxel among 7 zeros: 7 > 7.6 is false -> semantic wins
        let mut b = vec![0u8; 8];
        b[3] = 9;
        assert_eq!(downsample_labels(&b, [2, 2, 2], 2).unwrap(), vec![9]);
        // tie between 3 and 5 -> 3
        let c = [5u8, 5, 3, 3, 0, 0, 0, 0];
        assert_eq!(downsample_labels(&c, [2, 2, 2], 2).unwrap(), vec![3]);
        assert!(downsample_labels(&c, [2, 2, 3], 2).is_err());
        assert!(downsample_labels(&c, [2, 2, 2], 0).is_err());
        assert!(downsample_labels(&c[..7], [2, 2, 2], 2).is_err());
    }
}
