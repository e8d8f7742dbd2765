//! Label remaps (SemanticKITTI learning map and its inverse) and label-grid downsampling
//! (docs/formats.md §2.4 and §2.6).

use crate::error::DataError;

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
            if *v == 0 {
                *v = 255;
            }
        }
        lut[0] = 0;
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

fn check_grid(labels_len: usize, dims: [usize; 3]) -> Result<usize, DataError> {
    let n = dims[0]
        .checked_mul(dims[1])
        .and_then(|v| v.checked_mul(dims[2]))
        .ok_or_else(|| DataError::InvalidArgument(format!("grid dims {dims:?} overflow")))?;
    if n != labels_len {
        return Err(DataError::InvalidArgument(format!(
            "label grid has {labels_len} values but dims {dims:?} need {n}"
        )));
    }
    Ok(n)
}

/// Downsample a label grid by `factor` with the MonoScene / SparseOcc / VoxFormer
/// `_downsample_label` rule (docs/formats.md §2.6), per `factor³` block:
/// if `n0 + n255 > 0.95·factor³` the label is 0 when `n0 > n255`, else 255 (so a tie gives
/// 255); otherwise it is the most frequent label in `1..=254`, ties to the smaller id.
///
/// `labels` is flat C order `[x][y][z]`; every dim must be divisible by `factor`.
pub fn downsample_labels(
    labels: &[u8],
    dims: [usize; 3],
    factor: usize,
) -> Result<Vec<u8>, DataError> {
    check_grid(labels.len(), dims)?;
    if factor == 0 || dims.iter().any(|d| d % factor != 0) {
        return Err(DataError::InvalidArgument(format!(
            "dims {dims:?} are not divisible by downsampling factor {factor}"
        )));
    }
    if factor == 1 {
        return Ok(labels.to_vec());
    }
    let out_dims = [dims[0] / factor, dims[1] / factor, dims[2] / factor];
    let block = factor * factor * factor;
    let empty_threshold = 0.95 * block as f64;
    let mut out = Vec::with_capacity(out_dims[0] * out_dims[1] * out_dims[2]);
    let mut counts = [0u32; 256];
    for ox in 0..out_dims[0] {
        for oy in 0..out_dims[1] {
            for oz in 0..out_dims[2] {
                counts.iter_mut().for_each(|c| *c = 0);
                for x in ox * factor..(ox + 1) * factor {
                    for y in oy * factor..(oy + 1) * factor {
                        let base = (x * dims[1] + y) * dims[2] + oz * factor;
                        for &l in &labels[base..base + factor] {
                            counts[l as usize] += 1;
                        }
                    }
                }
                let n0 = counts[0];
                let n255 = counts[255];
                let label = if (n0 + n255) as f64 > empty_threshold {
                    if n0 > n255 {
                        0
                    } else {
                        255
                    }
                } else {
                    // argmax over 1..=254, first (smallest) on ties
                    let mut best = 1usize;
                    for c in 2..255 {
                        if counts[c] > counts[best] {
                            best = c;
                        }
                    }
                    best as u8
                };
                out.push(label);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

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

    fn reference_downsample(labels: &[u8], dims: [usize; 3], f: usize) -> Vec<u8> {
        // direct transcription of the rule, block by block, with an explicit sort-based mode
        let od = [dims[0] / f, dims[1] / f, dims[2] / f];
        let mut out = vec![0u8; od[0] * od[1] * od[2]];
        for ox in 0..od[0] {
            for oy in 0..od[1] {
                for oz in 0..od[2] {
                    let mut blk = vec![];
                    for x in 0..f {
                        for y in 0..f {
                            for z in 0..f {
                                blk.push(
                                    labels[((ox * f + x) * dims[1] + oy * f + y) * dims[2]
                                        + oz * f
                                        + z],
                                );
                            }
                        }
                    }
                    let n0 = blk.iter().filter(|&&v| v == 0).count();
                    let n255 = blk.iter().filter(|&&v| v == 255).count();
                    let v = if (n0 + n255) as f64 > 0.95 * (f * f * f) as f64 {
                        if n0 > n255 {
                            0
                        } else {
                            255
                        }
                    } else {
                        let mut sem: Vec<u8> =
                            blk.into_iter().filter(|&v| v > 0 && v < 255).collect();
                        sem.sort();
                        let mut best = (0usize, 0u8);
                        let mut i = 0;
                        while i < sem.len() {
                            let j = sem[i..].iter().take_while(|&&v| v == sem[i]).count();
                            if j > best.0 {
                                best = (j, sem[i]);
                            }
                            i += j;
                        }
                        best.1
                    };
                    out[(ox * od[1] + oy) * od[2] + oz] = v;
                }
            }
        }
        out
    }

    #[test]
    fn downsample_matches_reference_on_random_grids() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for f in [2usize, 4] {
            for _ in 0..5 {
                let dims = [8 * f, 4 * f, 2 * f];
                let n = dims.iter().product();
                let labels: Vec<u8> = (0..n)
                    .map(|_| match rng.random_range(0..10) {
                        0..=4 => 0,
                        5 => 255,
                        _ => rng.random_range(1..4),
                    })
                    .collect();
                assert_eq!(
                    downsample_labels(&labels, dims, f).unwrap(),
                    reference_downsample(&labels, dims, f)
                );
            }
        }
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
