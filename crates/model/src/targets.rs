//! Targets shared by the three models: the full-resolution labels of a batch checked and downsampled
//! to a prediction grid, by the two downsampling rules the papers' codebases use (docs/formats.md
//! §2.6): the official SparseOcc in-network mode rule ([`downsample_labels_mode`], SparseOcc and the
//! dense baseline) and the MonoScene / SSC rule ([`monoscene_block_label`], [`downsample_labels`],
//! SparseOcc++). Label conventions: [`crate::loss::EMPTY_CLASS`] (0) and [`crate::loss::IGNORE_LABEL`]
//! (255).

use crate::batch::Batch;
use crate::error::ModelError;
use burn::prelude::*;

pub(crate) fn check_input<B: Backend>(
    feats: &Tensor<B, 4>,
    batch: &Batch<B>,
    feat_channels: usize,
    full_dims: [usize; 3],
) -> Result<(), ModelError> {
    let c = feats.dims()[1];
    if c != feat_channels {
        return Err(ModelError::Input(format!(
            "feature map has {c} channels, the model was configured for {feat_channels}"
        )));
    }
    if batch.grid.dims != full_dims {
        return Err(ModelError::Input(format!(
            "batch grid {:?} differs from the configured full_dims {full_dims:?}",
            batch.grid.dims
        )));
    }
    Ok(())
}

/// Full-resolution targets of a batch downsampled to the prediction grid, one vector per item.
pub(crate) fn targets_at<B: Backend>(
    batch: &Batch<B>,
    full_dims: [usize; 3],
    ratio: usize,
) -> Result<Vec<Vec<u8>>, ModelError> {
    let target = batch.target.as_ref().ok_or_else(|| {
        ModelError::Input("losses need batch.target (the full-resolution labels)".into())
    })?;
    if target.len() != batch.batch_size() {
        return Err(ModelError::Input(format!(
            "batch.target has {} items, the batch has {}",
            target.len(),
            batch.batch_size()
        )));
    }
    target
        .iter()
        .map(|t| downsample_labels_mode(t, full_dims, ratio))
        .collect()
}

/// The official in-network label downsampling (SparseOcc `loss_voxel`, docs/formats.md §2.6): per `r³` block,
/// all-zero → 0; otherwise the mode of the block where each 0 is replaced by a unique negative number
/// and a negative mode becomes 255 — i.e. the most frequent non-zero label (255 counts as a label),
/// ties to the smallest value (`torch.mode`), and when no label occurs twice while the block contains a
/// zero, a negative number wins the tie, giving 255.
///
/// `labels`: flat C order over `dims`; output flat C order over `dims / r` (integer division).
pub fn downsample_labels_mode(
    labels: &[u8],
    dims: [usize; 3],
    r: usize,
) -> Result<Vec<u8>, ModelError> {
    let [x, y, z] = dims;
    if labels.len() != x * y * z || r == 0 {
        return Err(ModelError::Input(format!(
            "downsample_labels_mode: {} labels for a {dims:?} grid, ratio {r}",
            labels.len()
        )));
    }
    if r == 1 {
        return Ok(labels.to_vec());
    }
    let [ox, oy, oz] = [x / r, y / r, z / r];
    let mut out = vec![0u8; ox * oy * oz];
    let mut counts = [0u32; 256];
    for i in 0..ox {
        for j in 0..oy {
            for k in 0..oz {
                counts.iter_mut().for_each(|c| *c = 0);
                let mut zeros = 0u32;
                for a in 0..r {
                    for b in 0..r {
                        for c in 0..r {
                            let l = labels[((i * r + a) * y + j * r + b) * z + k * r + c];
                            if l == 0 {
                                zeros += 1;
                            } else {
                                counts[l as usize] += 1;
                            }
                        }
                    }
                }
                let best = (1..256).max_by(|&p, &q| counts[p].cmp(&counts[q]).then(q.cmp(&p)));
                let v = match best {
                    Some(l) if counts[l] == 0 => 0,
                    Some(l) if counts[l] == 1 && zeros > 0 => 255,
                    Some(l) => l as u8,
                    None => 0,
                };
                out[(i * oy + j) * oz + k] = v;
            }
        }
    }
    Ok(out)
}

/// Label of a `ds³` block by the MonoScene / SSC downsampling rule (docs/formats.md §2.6, `_downsample_label`):
/// if empty (0) and ignore (255) voxels are more than 95 % of the block, the block is 0 when there are
/// more 0s than 255s and 255 otherwise (ties → 255); else the most frequent label in `1..=254` (ties →
/// the smaller id). `labels` yields the block's labels.
pub fn monoscene_block_label(labels: impl Iterator<Item = u8>, ds: usize) -> u8 {
    let mut counts = [0u32; 256];
    for l in labels {
        counts[l as usize] += 1;
    }
    let (n0, n255) = (counts[0] as f64, counts[255] as f64);
    let cells = (ds * ds * ds) as f64;
    if n0 + n255 > 0.95 * cells {
        return if n0 > n255 { 0 } else { 255 };
    }
    let (mut best, mut best_n) = (0usize, 0u32);
    for (c, &n) in counts.iter().enumerate().take(255).skip(1) {
        if n > best_n {
            best = c;
            best_n = n;
        }
    }
    best as u8
}

/// The whole full-resolution grid downsampled by `ds` with [`monoscene_block_label`] (flat
/// `[X/ds][Y/ds][Z/ds]`). Voxels of incomplete blocks at the upper border are dropped (dims must be
/// multiples of `ds` for an exact result).
pub fn downsample_labels(full: &[u8], full_dims: [usize; 3], ds: usize) -> Vec<u8> {
    let ds = ds.max(1);
    let d = full_dims.map(|n| n / ds);
    let [fy, fz] = [full_dims[1], full_dims[2]];
    let mut out = Vec::with_capacity(d[0] * d[1] * d[2]);
    for x in 0..d[0] {
        for y in 0..d[1] {
            for z in 0..d[2] {
                let it = (0..ds).flat_map(move |dx| {
                    (0..ds).flat_map(move |dy| {
                        (0..ds).map(move |dz| {
                            ((x * ds + dx) * fy + (y * ds + dy)) * fz + (z * ds + dz)
                        })
                    })
                });
                out.push(monoscene_block_label(
                    it.map(|i| full.get(i).copied().unwrap_or(255)),
                    ds,
                ));
            }
        }
    }
    out
}
