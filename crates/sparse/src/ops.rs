//! Structural operations: union/add of tensors with different sites, adding zero-featured sites, prune by
//! mask, gather rows, top-k by score, channel concatenation.

use crate::backend::index_tensor;
use crate::coords::{pack, Coord, CoordSet};
use crate::error::{Result, SparseError};
use crate::rows::{scatter_add_rows, RowPlan};
use crate::tensor::SparseTensor;
use crate::SparseConvBackend;
use burn::prelude::*;
use std::sync::Arc;

fn check_frame<B: Backend>(a: &SparseTensor<B>, b: &SparseTensor<B>) -> Result<()> {
    if a.spatial_shape() != b.spatial_shape()
        || a.batch_size() != b.batch_size()
        || a.tensor_stride() != b.tensor_stride()
    {
        return Err(SparseError::Incompatible(format!(
            "shape {:?}/{:?}, batch {}/{}, stride {:?}/{:?}",
            a.spatial_shape(),
            b.spatial_shape(),
            a.batch_size(),
            b.batch_size(),
            a.tensor_stride(),
            b.tensor_stride()
        )));
    }
    Ok(())
}

/// Sorted union of two sites lists with the row of every input site in the union.
fn union_sets(a: &CoordSet, b: &CoordSet) -> (Vec<Coord>, Vec<u32>, Vec<u32>) {
    let mut keys: Vec<u64> = a
        .coords()
        .iter()
        .chain(b.coords())
        .map(|&c| pack(c))
        .collect();
    keys.sort_unstable();
    keys.dedup();
    let row = |c: Coord| keys.binary_search(&pack(c)).map(|r| r as u32).unwrap_or(0);
    let ia: Vec<u32> = a.coords().iter().map(|&c| row(c)).collect();
    let ib: Vec<u32> = b.coords().iter().map(|&c| row(c)).collect();
    let coords = keys.into_iter().map(crate::coords::unpack).collect();
    (coords, ia, ib)
}

/// Sum of two sparse tensors over the union of their sites (spconv `sparse_add`); a site present in only
/// one tensor keeps that tensor's features. When both share the same coordinate set, this is a plain add.
pub fn add<B: SparseConvBackend>(
    a: &SparseTensor<B>,
    b: &SparseTensor<B>,
) -> Result<SparseTensor<B>> {
    if a.channels() != b.channels() {
        return Err(SparseError::Shape(format!(
            "add: {} vs {} channels",
            a.channels(),
            b.channels()
        )));
    }
    if Arc::ptr_eq(a.coord_set(), b.coord_set()) {
        return a.with_feats(a.feats().clone() + b.feats().clone());
    }
    check_frame(a, b)?;
    let (coords, ia, ib) = union_sets(a.coord_set(), b.coord_set());
    let n = coords.len();
    let feats = scatter_add_rows(a.feats().clone(), &Arc::new(RowPlan::new(ia, n)?))
        + scatter_add_rows(b.feats().clone(), &Arc::new(RowPlan::new(ib, n)?));
    let set =
        CoordSet::from_valid_unique(coords, a.spatial_shape(), a.batch_size(), a.tensor_stride());
    SparseTensor::from_parts(Arc::new(set), feats)
}

/// Adds new sites with zero features (sites already present are ignored). The original sites keep
/// their features. Used by geometry-guided propagation (new voxels are zero-initialised).
pub fn extend_zero<B: SparseConvBackend>(
    t: &SparseTensor<B>,
    extra: &[Coord],
) -> Result<SparseTensor<B>> {
    let set = t.coord_set();
    let shape = t.spatial_shape();
    for (row, &c) in extra.iter().enumerate() {
        let ok = c[0] >= 0
            && (c[0] as usize) < t.batch_size()
            && (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < shape[a]);
        if !ok {
            return Err(SparseError::OutOfRange {
                row,
                coord: c,
                shape,
                batch_size: t.batch_size(),
            });
        }
    }
    let mut keys: Vec<u64> = t.coords().iter().chain(extra).map(|&c| pack(c)).collect();
    keys.sort_unstable();
    keys.dedup();
    if keys.len() == t.num_active() {
        return Ok(t.clone());
    }
    let rows: Vec<u32> = t
        .coords()
        .iter()
        .map(|&c| keys.binary_search(&pack(c)).map(|r| r as u32).unwrap_or(0))
        .collect();
    let coords: Vec<Coord> = keys.into_iter().map(crate::coords::unpack).collect();
    let feats = scatter_add_rows(
        t.feats().clone(),
        &Arc::new(RowPlan::new(rows, coords.len())?),
    );
    let new_set = CoordSet::from_valid_unique(coords, shape, set.batch_size(), set.tensor_stride());
    SparseTensor::from_parts(Arc::new(new_set), feats)
}

/// Keeps the rows at `indices` (in that order). Errors on out-of-range or repeated indices.
pub fn gather<B: Backend>(t: &SparseTensor<B>, indices: &[usize]) -> Result<SparseTensor<B>> {
    let n = t.num_active();
    let mut seen = vec![false; n];
    for &i in indices {
        if i >= n {
            return Err(SparseError::Shape(format!("gather: row {i} >= {n}")));
        }
        if seen[i] {
            return Err(SparseError::Shape(format!("gather: row {i} repeated")));
        }
        seen[i] = true;
    }
    let coords: Vec<Coord> = indices.iter().map(|&i| t.coords()[i]).collect();
    let idx: Vec<u32> = indices.iter().map(|&i| i as u32).collect();
    let device = t.device();
    let feats = if idx.is_empty() {
        Tensor::zeros([0, t.channels()], &device)
    } else {
        t.feats()
            .clone()
            .select(0, index_tensor::<B>(&idx, &device))
    };
    let set =
        CoordSet::from_valid_unique(coords, t.spatial_shape(), t.batch_size(), t.tensor_stride());
    SparseTensor::from_parts(Arc::new(set), feats)
}

/// Keeps the rows where `mask` is true (order preserved).
pub fn prune<B: Backend>(t: &SparseTensor<B>, mask: &[bool]) -> Result<SparseTensor<B>> {
    if mask.len() != t.num_active() {
        return Err(SparseError::Shape(format!(
            "prune: mask of {} for {} sites",
            mask.len(),
            t.num_active()
        )));
    }
    let idx: Vec<usize> = mask
        .iter()
        .enumerate()
        .filter_map(|(i, &m)| m.then_some(i))
        .collect();
    gather(t, &idx)
}

/// Rows of the `k` highest scores, in descending score order (ties: lower row first), computed per batch
/// item when `per_batch` is true (k each), over all sites otherwise. NaN scores rank lowest.
pub fn topk_indices(scores: &[f32], coords: &[Coord], k: usize, per_batch: bool) -> Vec<usize> {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    let key = |i: usize| {
        if scores[i].is_nan() {
            f32::NEG_INFINITY
        } else {
            scores[i]
        }
    };
    order.sort_by(|&a, &b| key(b).total_cmp(&key(a)).then(a.cmp(&b)));
    if !per_batch {
        order.truncate(k);
        return order;
    }
    let mut taken = std::collections::HashMap::<i32, usize>::new();
    order
        .into_iter()
        .filter(|&i| {
            let n = taken.entry(coords[i][0]).or_insert(0);
            *n += 1;
            *n <= k
        })
        .collect()
}

/// Top-k selection of sites by a per-site score `[N]`: returns the kept tensor (sites in descending
/// score order) and the kept row indices.
pub fn topk<B: Backend>(
    t: &SparseTensor<B>,
    scores: &Tensor<B, 1>,
    k: usize,
    per_batch: bool,
) -> Result<(SparseTensor<B>, Vec<usize>)> {
    if scores.dims()[0] != t.num_active() {
        return Err(SparseError::Shape(format!(
            "topk: {} scores for {} sites",
            scores.dims()[0],
            t.num_active()
        )));
    }
    let s: Vec<f32> = scores
        .clone()
        .into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .map_err(|e| SparseError::Shape(format!("topk scores: {e:?}")))?;
    let idx = topk_indices(&s, t.coords(), k, per_batch);
    Ok((gather(t, &idx)?, idx))
}

/// Concatenates the channels of tensors on the same sites.
pub fn cat_feats<B: Backend>(parts: &[SparseTensor<B>]) -> Result<SparseTensor<B>> {
    let first = parts
        .first()
        .ok_or_else(|| SparseError::Shape("cat_feats: no tensor".into()))?;
    for p in parts {
        if !Arc::ptr_eq(p.coord_set(), first.coord_set()) && p.coords() != first.coords() {
            return Err(SparseError::Incompatible(
                "cat_feats: different sites".into(),
            ));
        }
    }
    let feats = Tensor::cat(parts.iter().map(|p| p.feats().clone()).collect(), 1);
    first.with_feats(feats)
}
