//! Label-grid downsampling: the two rules of the reference codebases (docs/formats.md §2.6), on one
//! block walk.
//!
//! - [`downsample_monoscene`] (per block [`monoscene_block_label`]): the MonoScene / VoxFormer / SSC
//!   `_downsample_label` rule. The SparseOcc preprocessing writes the 1/2-resolution SemanticKITTI
//!   labels with it (`occ_data::labels::downsample_labels`, `prepare`), and SparseOcc++ takes its
//!   1/2-resolution and anchor-level targets with it (`occ_model::sparseocc_pp`).
//! - [`downsample_mode`]: the official SparseOcc in-network mode rule (its `loss_voxel`), used by
//!   SparseOcc and the dense baseline for their 1/2-resolution targets (`occ_model::targets`).
//!
//! The rules differ where a block is mostly empty: the SSC rule gives [`EMPTY`] or [`IGNORE`] once
//! these are more than 95 % of it, the mode rule takes the most frequent non-empty label (where
//! [`IGNORE`] counts as a label) as soon as the block has one that occurs twice.
//!
//! Grids are flat C order `[x][y][z]` (z fastest); the output has `dims / factor` (integer division)
//! blocks per axis, so the voxels of incomplete blocks at the upper borders are dropped.

use crate::{EMPTY, IGNORE};
use std::fmt;

/// A label grid or factor that cannot be downsampled: the grid's length does not match its dims, or
/// the factor is 0.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DownsampleError(String);

impl fmt::Display for DownsampleError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for DownsampleError {}

/// Label of a `ds³` block by the MonoScene / SSC rule (`_downsample_label`): if empty ([`EMPTY`]) and
/// ignored ([`IGNORE`]) voxels are more than 95 % of the `ds³` cells, the block is [`EMPTY`] when there
/// are more of them than ignored ones and [`IGNORE`] otherwise (ties → [`IGNORE`]); else the most
/// frequent label in `1..=254` (ties → the smaller id). `labels` yields the block's labels.
pub fn monoscene_block_label(labels: impl Iterator<Item = u8>, ds: usize) -> u8 {
    let mut counts = [0u32; 256];
    for l in labels {
        counts[l as usize] += 1;
    }
    monoscene_rule(&counts, ds * ds * ds)
}

/// The SSC rule on a block's label counts (`cells`: the block's size).
fn monoscene_rule(counts: &[u32; 256], cells: usize) -> u8 {
    let (n0, n255) = (counts[EMPTY as usize], counts[IGNORE as usize]);
    if f64::from(n0 + n255) > 0.95 * cells as f64 {
        return if n0 > n255 { EMPTY } else { IGNORE };
    }
    most_frequent(counts, 1..IGNORE as usize).0
}

/// The SparseOcc mode rule on a block's label counts: all [`EMPTY`] → [`EMPTY`]; otherwise the mode of
/// the block where each 0 is replaced by a unique negative number and a negative mode becomes
/// [`IGNORE`] (`torch.mode`, ties to the smallest value). In effect the most frequent non-zero label
/// ([`IGNORE`] counts as a label), ties to the smaller id, and [`IGNORE`] when no label occurs twice
/// while the block holds a 0.
fn mode_rule(counts: &[u32; 256]) -> u8 {
    match most_frequent(counts, 1..256) {
        (_, 0) => EMPTY,
        (_, 1) if counts[EMPTY as usize] > 0 => IGNORE,
        (label, _) => label,
    }
}

/// The label of `range` with the highest count (the smallest on ties) and its count; `(EMPTY, 0)`
/// when none occurs.
fn most_frequent(counts: &[u32; 256], range: std::ops::Range<usize>) -> (u8, u32) {
    let (mut best, mut best_n) = (EMPTY, 0);
    for c in range {
        if counts[c] > best_n {
            (best, best_n) = (c as u8, counts[c]);
        }
    }
    (best, best_n)
}

/// `labels` downsampled by `factor` with the MonoScene / SSC rule ([`monoscene_block_label`]).
pub fn downsample_monoscene(
    labels: &[u8],
    dims: [usize; 3],
    factor: usize,
) -> Result<Vec<u8>, DownsampleError> {
    let cells = factor.saturating_mul(factor).saturating_mul(factor);
    downsample_by(labels, dims, factor, |counts| monoscene_rule(counts, cells))
}

/// `labels` downsampled by `factor` with the SparseOcc in-network mode rule (see the module docs).
pub fn downsample_mode(
    labels: &[u8],
    dims: [usize; 3],
    factor: usize,
) -> Result<Vec<u8>, DownsampleError> {
    downsample_by(labels, dims, factor, mode_rule)
}

/// Every whole `factor³` block of `labels` counted and labelled by `rule`; a copy for `factor` 1.
fn downsample_by(
    labels: &[u8],
    dims: [usize; 3],
    factor: usize,
    rule: impl Fn(&[u32; 256]) -> u8,
) -> Result<Vec<u8>, DownsampleError> {
    let n = dims
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(d))
        .ok_or_else(|| DownsampleError(format!("grid dims {dims:?} overflow")))?;
    if n != labels.len() {
        return Err(DownsampleError(format!(
            "label grid has {} values but dims {dims:?} need {n}",
            labels.len()
        )));
    }
    if factor == 0 {
        return Err(DownsampleError("downsampling factor 0".into()));
    }
    if factor == 1 {
        return Ok(labels.to_vec());
    }
    let out_dims = dims.map(|d| d / factor);
    let mut out = Vec::with_capacity(out_dims.iter().product());
    let mut counts = [0u32; 256];
    for ox in 0..out_dims[0] {
        for oy in 0..out_dims[1] {
            for oz in 0..out_dims[2] {
                counts.fill(0);
                for x in ox * factor..(ox + 1) * factor {
                    for y in oy * factor..(oy + 1) * factor {
                        let base = (x * dims[1] + y) * dims[2] + oz * factor;
                        for &l in &labels[base..base + factor] {
                            counts[l as usize] += 1;
                        }
                    }
                }
                out.push(rule(&counts));
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (this crate has no dependencies).
    struct Lcg(u64);
    impl Lcg {
        fn below(&mut self, n: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 33) % n
        }
    }

    /// The blocks of a grid, each as its list of labels, in output order.
    fn blocks(labels: &[u8], dims: [usize; 3], f: usize) -> Vec<Vec<u8>> {
        let od = dims.map(|d| d / f);
        let mut out = vec![];
        for ox in 0..od[0] {
            for oy in 0..od[1] {
                for oz in 0..od[2] {
                    let mut blk = vec![];
                    for x in 0..f {
                        for y in 0..f {
                            for z in 0..f {
                                let i =
                                    ((ox * f + x) * dims[1] + oy * f + y) * dims[2] + oz * f + z;
                                blk.push(labels[i]);
                            }
                        }
                    }
                    out.push(blk);
                }
            }
        }
        out
    }

    /// The SSC rule transcribed block by block, with a sort-based mode.
    fn reference_monoscene(blk: &[u8]) -> u8 {
        let n0 = blk.iter().filter(|&&v| v == 0).count();
        let n255 = blk.iter().filter(|&&v| v == 255).count();
        if (n0 + n255) as f64 > 0.95 * blk.len() as f64 {
            return if n0 > n255 { 0 } else { 255 };
        }
        let mut sem: Vec<u8> = blk.iter().copied().filter(|&v| v > 0 && v < 255).collect();
        sem.sort();
        sorted_mode(&sem)
    }

    /// The mode rule as the reference computes it: zeros replaced by distinct negative numbers, the
    /// smallest most frequent value, a negative mode becoming 255.
    fn reference_mode(blk: &[u8]) -> u8 {
        if blk.iter().all(|&v| v == 0) {
            return 0;
        }
        let mut vals: Vec<i32> = blk
            .iter()
            .enumerate()
            .map(|(i, &v)| if v == 0 { -1 - i as i32 } else { i32::from(v) })
            .collect();
        vals.sort();
        let best = sorted_mode(&vals);
        if best < 0 {
            255
        } else {
            best as u8
        }
    }

    /// The first (smallest) most frequent value of a sorted slice.
    fn sorted_mode<T: Copy + Default + PartialEq>(sorted: &[T]) -> T {
        let (mut best, mut best_n, mut i) = (T::default(), 0usize, 0usize);
        while i < sorted.len() {
            let j = sorted[i..].iter().take_while(|&&v| v == sorted[i]).count();
            if j > best_n {
                (best, best_n) = (sorted[i], j);
            }
            i += j;
        }
        best
    }

    #[test]
    fn both_rules_match_their_references_on_random_grids() {
        let mut rng = Lcg(11);
        for f in [2usize, 4] {
            for _ in 0..5 {
                let dims = [8 * f, 4 * f, 2 * f];
                let n = dims.iter().product();
                let labels: Vec<u8> = (0..n)
                    .map(|_| match rng.below(10) {
                        0..=4 => 0,
                        5 => 255,
                        _ => 1 + rng.below(3) as u8,
                    })
                    .collect();
                let blks = blocks(&labels, dims, f);
                let ssc: Vec<u8> = blks.iter().map(|b| reference_monoscene(b)).collect();
                let mode: Vec<u8> = blks.iter().map(|b| reference_mode(b)).collect();
                assert_eq!(downsample_monoscene(&labels, dims, f).unwrap(), ssc);
                assert_eq!(downsample_mode(&labels, dims, f).unwrap(), mode);
                for (b, &want) in blks.iter().zip(&ssc) {
                    assert_eq!(monoscene_block_label(b.iter().copied(), f), want);
                }
            }
        }
    }

    #[test]
    fn hand_made_blocks_under_both_rules() {
        let both = |b: [u8; 8]| {
            (
                downsample_monoscene(&b, [2, 2, 2], 2).unwrap()[0],
                downsample_mode(&b, [2, 2, 2], 2).unwrap()[0],
            )
        };
        // all empty: empty under both
        assert_eq!(both([0; 8]), (0, 0));
        // 4 zeros + 4 ignores: a tie gives 255 (SSC); 255 is the mode
        assert_eq!(both([0, 0, 0, 0, 255, 255, 255, 255]), (255, 255));
        // 5 zeros + 3 ignores: more zeros (SSC); 255 occurs more than once (mode)
        assert_eq!(both([0, 0, 0, 0, 0, 255, 255, 255]), (0, 255));
        // one semantic voxel among 7 zeros: 7 > 7.6 is false so it wins (SSC); occurs once (mode)
        assert_eq!(both([0, 0, 0, 9, 0, 0, 0, 0]), (9, 255));
        // tie between 3 and 5: the smaller under both
        assert_eq!(both([5, 5, 3, 3, 0, 0, 0, 0]), (3, 3));
        // 255 outnumbers the class: the class (SSC); 255 (mode)
        assert_eq!(both([255, 255, 255, 7, 7, 0, 0, 0]), (7, 255));
        // a full block of one class
        assert_eq!(both([4; 8]), (4, 4));
        // no zero, every label once: the smallest (mode), the smallest class (SSC)
        assert_eq!(both([1, 2, 3, 4, 5, 6, 7, 255]), (1, 1));
    }

    #[test]
    fn incomplete_border_blocks_are_dropped_and_bad_grids_refused() {
        // dims [3, 2, 2] by 2: one block (x = 0..2), the x = 2 slab dropped
        let mut l = vec![0u8; 12];
        l[8..].fill(6);
        assert_eq!(downsample_monoscene(&l, [3, 2, 2], 2).unwrap(), vec![0]);
        assert_eq!(downsample_mode(&l, [3, 2, 2], 2).unwrap(), vec![0]);
        assert_eq!(downsample_mode(&l, [3, 2, 2], 1).unwrap(), l);
        assert!(downsample_monoscene(&l[..11], [3, 2, 2], 2).is_err());
        assert!(downsample_mode(&l, [3, 2, 2], 0).is_err());
        assert!(downsample_monoscene(&l, [usize::MAX, 2, 2], 2).is_err());
        // the 95 % threshold on a 4³ block: 61 zeros + 3 semantic → 0; 60 + 4 → the class
        let mut b = [0u8; 64];
        b[..3].fill(5);
        assert_eq!(monoscene_block_label(b.iter().copied(), 4), 0);
        b[3] = 5;
        assert_eq!(monoscene_block_label(b.iter().copied(), 4), 5);
    }
}
