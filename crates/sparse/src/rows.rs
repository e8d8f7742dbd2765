//! Row gather and row scatter-add with a plan built once on the host, as spconv and torchsparse
//! keep their gather/scatter tables apart from the compute.
//!
//! A [`RowPlan`] is an index list `dest` (`dest[h]` = the output row of input row `h`) over
//! `n_out` rows, with its inverse in compressed-row form: the input rows sorted by destination
//! (`order`) and each output row's segment of them (`offsets`). It serves two adjoint ops:
//!
//! - scatter-add `out[r] = Σ_{h : dest[h] = r} v[h]` ([`scatter_add_rows`]), whose gradient is the
//!   gather `dv = dout[dest]`;
//! - gather `out[h] = x[dest[h]]` ([`gather_rows`]), whose gradient is the scatter-add of `dout`.
//!
//! burn's `select_assign` (the portable scatter-add, also burn's backward of `select`) runs one
//! thread per column on the cubecl backends, each looping over every index: a few threads for a
//! whole frame of voxels on a GPU, and wrong on lavapipe past 65,532 rows (its shader loop limit,
//! measured: `docs/gpu.md`). On those backends the scatter-add is a segment sum instead, one
//! thread per output value looping over its own segment ([`crate::cube`]), deterministic (no float
//! atomics). The NdArray backend keeps `select_assign`, which is serial and fast on the host.

use crate::backend::{index_tensor, SparseConvBackend};
use crate::error::{Result, SparseError};
use burn::prelude::*;
use burn::tensor::ops::FloatTensor;
use burn::tensor::TensorPrimitive;
use std::sync::Arc;

/// An index list and its inverse (input rows grouped by output row).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RowPlan {
    n_out: usize,
    dest: Vec<u32>,
    order: Vec<u32>,
    offsets: Vec<u32>,
    max_segment: usize,
}

impl RowPlan {
    /// Plan for `dest` (`dest[h] < n_out`). Errors when an index is out of range or a count does
    /// not fit the 32-bit indices of the device kernels.
    pub fn new(dest: Vec<u32>, n_out: usize) -> Result<Self> {
        if dest.len() >= u32::MAX as usize || n_out >= u32::MAX as usize {
            return Err(SparseError::Shape(format!(
                "row plan: {} rows into {n_out} exceeds 32-bit indices",
                dest.len()
            )));
        }
        if let Some((h, &r)) = dest.iter().enumerate().find(|(_, &r)| r as usize >= n_out) {
            return Err(SparseError::Shape(format!(
                "row plan: index {r} at position {h} is out of range for {n_out} rows"
            )));
        }
        // Counting sort by destination (stable: rows of one segment keep their input order).
        let mut offsets = vec![0u32; n_out + 1];
        for &r in &dest {
            offsets[r as usize + 1] += 1;
        }
        let max_segment = offsets.iter().copied().max().unwrap_or(0) as usize;
        for r in 0..n_out {
            offsets[r + 1] += offsets[r];
        }
        let mut next = offsets.clone();
        let mut order = vec![0u32; dest.len()];
        for (h, &r) in dest.iter().enumerate() {
            order[next[r as usize] as usize] = h as u32;
            next[r as usize] += 1;
        }
        Ok(Self {
            n_out,
            dest,
            order,
            offsets,
            max_segment,
        })
    }

    /// Number of output rows of the scatter (input rows of the gather).
    pub fn n_out(&self) -> usize {
        self.n_out
    }

    /// Number of indices (input rows of the scatter, output rows of the gather).
    pub fn n_in(&self) -> usize {
        self.dest.len()
    }

    /// `dest[h]`: the output row of input row `h`.
    pub fn dest(&self) -> &[u32] {
        &self.dest
    }

    /// The input rows sorted by output row (stable).
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// `offsets[r]..offsets[r + 1]`: output row `r`'s part of [`Self::order`]; `n_out + 1` values.
    pub fn offsets(&self) -> &[u32] {
        &self.offsets
    }

    /// Most input rows that share one output row.
    pub fn max_segment(&self) -> usize {
        self.max_segment
    }
}

/// The portable scatter-add (burn `select_assign` into zeros): the default of
/// [`SparseConvBackend::scatter_add_rows`].
pub fn scatter_add_rows_portable<B: Backend>(values: Tensor<B, 2>, plan: &RowPlan) -> Tensor<B, 2> {
    let device = values.device();
    let [_, c] = values.dims();
    Tensor::<B, 2>::zeros([plan.n_out(), c], &device).select_assign(
        0,
        index_tensor::<B>(plan.dest(), &device),
        values,
        burn::tensor::IndexingUpdateOp::Add,
    )
}

/// Scatter-add of rows: `out[r] = Σ_{h : dest[h] = r} values[h]`. Differentiable.
///
/// # Shapes
/// - values: `[plan.n_in(), C]` -> `[plan.n_out(), C]`
pub fn scatter_add_rows<B: SparseConvBackend>(
    values: Tensor<B, 2>,
    plan: &Arc<RowPlan>,
) -> Tensor<B, 2> {
    Tensor::from_primitive(TensorPrimitive::Float(B::scatter_add_rows(
        values.into_primitive().tensor(),
        plan.clone(),
    )))
}

/// Gather of rows: `out[h] = x[dest[h]]`, whose backward is [`scatter_add_rows`]. Differentiable.
///
/// # Shapes
/// - x: `[plan.n_out(), C]` -> `[plan.n_in(), C]`
pub fn gather_rows<B: SparseConvBackend>(x: Tensor<B, 2>, plan: &Arc<RowPlan>) -> Tensor<B, 2> {
    Tensor::from_primitive(TensorPrimitive::Float(B::gather_rows(
        x.into_primitive().tensor(),
        plan.clone(),
    )))
}

/// The portable gather (burn `select`): the default of [`SparseConvBackend::gather_rows`].
pub fn gather_rows_portable<B: Backend>(x: FloatTensor<B>, plan: &RowPlan) -> FloatTensor<B> {
    let x = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(x));
    let device = x.device();
    x.select(0, index_tensor::<B>(plan.dest(), &device))
        .into_primitive()
        .tensor()
}

/// `x` with zero rows appended up to `rows` rows, whose backward keeps the output gradient's
/// first rows. One kernel on the cubecl backends ([`SparseConvBackend::pad_rows`]); how
/// [`crate::RowBucket::pad`] pads. Differentiable.
///
/// # Shapes
/// - x: `[n, C]` (`n <= rows`) -> `[rows, C]`
pub fn pad_rows<B: SparseConvBackend>(x: Tensor<B, 2>, rows: usize) -> Tensor<B, 2> {
    let [n, _] = x.dims();
    assert!(n <= rows, "pad_rows: {n} rows do not fit in {rows}");
    if n == rows {
        return x;
    }
    Tensor::from_primitive(TensorPrimitive::Float(B::pad_rows(
        x.into_primitive().tensor(),
        rows,
    )))
}

/// The portable pad (burn `cat` with a block of zeros in `x`'s float type): the default of
/// [`SparseConvBackend::pad_rows`].
pub fn pad_rows_portable<B: Backend>(x: FloatTensor<B>, rows: usize) -> FloatTensor<B> {
    let x = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(x));
    let [n, c] = x.dims();
    if n == rows {
        return x.into_primitive().tensor();
    }
    let zeros = Tensor::<B, 2>::zeros([rows - n, c], (&x.device(), x.dtype()));
    Tensor::cat(vec![x, zeros], 0).into_primitive().tensor()
}

/// Rows summed per block in [`sum_rows`].
const SUM_BLOCK_ROWS: usize = 256;

/// Column sums over a long row axis, in two levels: blocks of 256 rows, then the block sums.
/// burn's `sum_dim(0)` (with autotune off, as this project builds the cubecl backends) gives each
/// column to one thread, which loops over every row: a few threads for a frame of voxels on a GPU,
/// and on lavapipe only the first 65,532 rows are summed (measured: docs/gpu.md). Here each level
/// loops over at most `max(256, N / 256)` rows and the first uses `N / 256 · C` threads.
/// Differentiable (zero rows pad `N` to a whole number of blocks, [`pad_rows`]).
///
/// # Shapes
/// - x: `[N, C]` -> `[1, C]`
pub fn sum_rows<B: SparseConvBackend>(x: Tensor<B, 2>) -> Tensor<B, 2> {
    sum_rows_padded_with(x, B::pad_rows)
}

/// [`sum_rows`] on a backend without [`SparseConvBackend`] (the raw fused cubecl backend of a
/// kernel's backward), padding with `pad` (`[n, C]`, rows -> `[rows, C]`: such a backend's
/// [`crate::cube::fusion_pad_rows`], or [`pad_rows_portable`]).
///
/// # Shapes
/// - x: `[N, C]` -> `[1, C]`
pub fn sum_rows_padded_with<B: Backend>(
    x: Tensor<B, 2>,
    pad: fn(FloatTensor<B>, usize) -> FloatTensor<B>,
) -> Tensor<B, 2> {
    let [n, c] = x.dims();
    if n <= SUM_BLOCK_ROWS {
        return x.sum_dim(0);
    }
    let blocks = n.div_ceil(SUM_BLOCK_ROWS);
    let x = if blocks * SUM_BLOCK_ROWS > n {
        Tensor::from_primitive(TensorPrimitive::Float(pad(
            x.into_primitive().tensor(),
            blocks * SUM_BLOCK_ROWS,
        )))
    } else {
        x
    };
    let partial = x
        .reshape([blocks, SUM_BLOCK_ROWS, c])
        .sum_dim(1)
        .reshape([blocks, c]);
    sum_rows_padded_with(partial, pad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, NdArray};

    // f32, as every other test in this binary: burn 0.21 keeps one default float type per device
    // (`NdArrayDevice::Cpu` for NdArray<f32> and NdArray<f64> alike), fixed by whichever test
    // creates a tensor first, so f32 and f64 tests must not share a binary. The values below
    // are small integers and halves: their sums are exact in f32.
    type B = NdArray<f32>;

    #[test]
    fn sum_rows_equals_the_plain_column_sum() {
        let dev = Default::default();
        for n in [1usize, 255, 256, 257, 70_000] {
            let v: Vec<f32> = (0..n * 3).map(|i| ((i * 37) % 101) as f32 - 50.0).collect();
            let x = Tensor::<B, 2>::from_data(TensorData::new(v, [n, 3]), &dev);
            let got = sum_rows(x.clone()).to_data().to_vec::<f32>().unwrap();
            let want = x.sum_dim(0).to_data().to_vec::<f32>().unwrap();
            assert_eq!(got, want, "n = {n}");
        }
    }

    #[test]
    fn pad_rows_appends_zeros_and_keeps_the_first_rows_of_its_gradient() {
        let dev = Default::default();
        let v: Vec<f32> = (0..6).map(|i| i as f32 - 2.5).collect();
        let x = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(v.clone(), [3, 2]), &dev)
            .require_grad();
        let p = pad_rows(x.clone(), 5);
        assert_eq!(p.dims(), [5, 2]);
        let mut want = v.clone();
        want.extend([0.0; 4]);
        assert_eq!(p.to_data().to_vec::<f32>().unwrap(), want);
        // d/dx Σ (p ⊙ w) = w's first three rows.
        let w: Vec<f32> = (0..10).map(|i| i as f32 + 1.0).collect();
        let wt = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(w.clone(), [5, 2]), &dev);
        let grads = (p * wt).sum().backward();
        let gx = x.grad(&grads).unwrap().to_data().to_vec::<f32>().unwrap();
        assert_eq!(gx, w[..6]);
        // Already the size: the tensor itself.
        let same = pad_rows(
            Tensor::<B, 2>::from_data(TensorData::new(v.clone(), [3, 2]), &dev),
            3,
        );
        assert_eq!(same.to_data().to_vec::<f32>().unwrap(), v);
    }

    #[test]
    fn plan_groups_rows_by_destination() {
        let p = RowPlan::new(vec![2, 0, 2, 1, 2], 4).unwrap();
        assert_eq!(p.offsets(), &[0, 1, 2, 5, 5]);
        assert_eq!(p.order(), &[1, 3, 0, 2, 4]);
        assert_eq!(p.max_segment(), 3);
        assert!(RowPlan::new(vec![0, 4], 4).is_err());
    }

    #[test]
    fn scatter_and_gather_match_hand_sums_and_are_adjoint() {
        let dev = Default::default();
        let plan = Arc::new(RowPlan::new(vec![2, 0, 2, 1, 2], 4).unwrap());
        let v: Vec<f32> = (0..10).map(|i| i as f32 * 0.5 - 1.0).collect();
        let vt = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(v.clone(), [5, 2]), &dev)
            .require_grad();
        let out = scatter_add_rows(vt.clone(), &plan);
        let got = out.to_data().to_vec::<f32>().unwrap();
        // Row 2 = v[0] + v[2] + v[4], row 3 empty.
        let want = [
            v[2],
            v[3],
            v[6],
            v[7],
            v[0] + v[4] + v[8],
            v[1] + v[5] + v[9],
            0.0,
            0.0,
        ];
        assert_eq!(got, want);
        // d/dv Σ (out ⊙ w) = w[dest].
        let w: Vec<f32> = (0..8).map(|i| i as f32 + 1.0).collect();
        let wt = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(w.clone(), [4, 2]), &dev);
        let grads = (out * wt.clone()).sum().backward();
        let gv = vt.grad(&grads).unwrap().to_data().to_vec::<f32>().unwrap();
        let dest = [2usize, 0, 2, 1, 2];
        for h in 0..5 {
            for c in 0..2 {
                assert_eq!(gv[h * 2 + c], w[dest[h] * 2 + c]);
            }
        }
        // The gather is the adjoint: <gather(x), u> = <x, scatter(u)>.
        let xt = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(w.clone(), [4, 2]), &dev)
            .require_grad();
        let ut = Tensor::<Autodiff<B>, 2>::from_data(TensorData::new(v.clone(), [5, 2]), &dev);
        let g = gather_rows(xt.clone(), &plan);
        let lhs: f32 = (g * ut.clone()).sum().into_scalar();
        let rhs: f32 = (xt.clone() * scatter_add_rows(ut.clone(), &plan))
            .sum()
            .into_scalar();
        assert!((lhs - rhs).abs() < 1e-6);
        let grads = (gather_rows(xt.clone(), &plan) * ut).sum().backward();
        let gx = xt.grad(&grads).unwrap().to_data().to_vec::<f32>().unwrap();
        let sc = scatter_add_rows(
            Tensor::<B, 2>::from_data(TensorData::new(v, [5, 2]), &dev),
            &plan,
        );
        assert_eq!(gx, sc.to_data().to_vec::<f32>().unwrap());
    }
}
