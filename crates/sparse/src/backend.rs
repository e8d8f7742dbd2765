//! The sparse-convolution compute op, as a burn backend extension with its own backward pass.
//!
//! `SparseConvBackend` has a portable default implementation built from burn tensor ops that runs on
//! every backend (CUDA included): an implicit GEMM (one gather of the K neighbour rows of every output,
//! one matrix product), or per kernel offset gather, matmul and index-add for maps without a gather
//! table. The `NdArray` backend overrides it with the
//! blocked host GEMM of [`crate::host`], and `Autodiff<B>` wraps either with an explicit backward pass:
//! `dx = conv(dy, w, map^T, transposed weight)` and `dw = weight_grad(x, dy, map)`.

use crate::host::{self, HostFloat, WeightView};
use crate::kernel_map::KernelMap;
use crate::rows::{self, RowPlan};
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::NodeId;
use burn::backend::Autodiff;
use burn::prelude::*;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, TensorData, TensorMetadata, TensorPrimitive};
use std::sync::Arc;

fn wrap<B: Backend, const D: usize>(p: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(p))
}

fn unwrap<B: Backend, const D: usize>(t: Tensor<B, D>) -> FloatTensor<B> {
    t.into_primitive().tensor()
}

/// Index tensor on a device from host row indices.
/// Built directly in the backend's integer type when it is 32-bit (CUDA), to upload half the bytes and
/// skip a conversion pass.
pub fn index_tensor<B: Backend>(idx: &[u32], device: &B::Device) -> Tensor<B, 1, Int> {
    use burn::tensor::Element;
    let data = if <B::IntElem as Element>::dtype() == DType::I32 {
        let v: Vec<i32> = idx.iter().map(|&i| i as i32).collect();
        TensorData::new(v, [idx.len()])
    } else {
        let v: Vec<i64> = idx.iter().map(|&i| i as i64).collect();
        TensorData::new(v, [idx.len()])
    };
    Tensor::from_data(data, device)
}

/// Most elements of one gathered `[rows, K·C_in]` block of the implicit GEMM (512 MiB of f32);
/// larger outputs are processed in row chunks.
const IMPLICIT_GEMM_MAX_ELEMS: usize = 1 << 27;

/// The weight as one `[K·C_in, C_out]` matrix (offset-major rows), the right operand of the
/// implicit GEMM.
pub(crate) fn weight_matrix<B: Backend>(w: Tensor<B, 3>, transposed: bool) -> Tensor<B, 2> {
    let [d0, kv, d2] = w.dims();
    if transposed {
        // [C_in, K, C_out] -> [K, C_in, C_out]
        w.swap_dims(0, 1).reshape([kv * d0, d2])
    } else {
        // [C_out, K, C_in] -> [K, C_in, C_out]
        w.permute([1, 2, 0]).reshape([kv * d2, d0])
    }
}

/// Row buckets of the portable path's matrix products. cubecl compiles a kernel per configuration,
/// not per shape, but cubek-matmul 0.2 derives part of the configuration from the row count `M`:
/// its unit selector's partition grows with `M` (2, 4, 8, 16 rows for `M` below 512, 1,024,
/// 1,536 and above) and its cube order is swizzled only when the count of row tiles (`M / 128` at
/// the largest partition) is a multiple of 4. A voxel count as `M` would so compile new kernels
/// on later frames. Padded to at least [`RowBucket::min`] rows and a multiple of
/// [`RowBucket::multiple`], every frame gets the same configurations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RowBucket {
    /// Row counts are padded to a multiple of this.
    pub multiple: usize,
    /// ... and to at least this.
    pub min: usize,
}

impl RowBucket {
    /// No padding (the CPU backends, whose kernels take any row count).
    pub const NONE: Self = Self {
        multiple: 1,
        min: 0,
    };
    /// The cubecl backends: a multiple of 512 rows, at least 1,536 (see the type's documentation).
    pub const CUBECL: Self = Self {
        multiple: 512,
        min: 1536,
    };

    /// The padded count for `rows`: `rows` itself without padding, otherwise the smallest allowed
    /// count above `rows` (always at least one padding row, so that every frame runs the same
    /// operations, a pad and a slice, whatever its count).
    pub fn padded(self, rows: usize) -> usize {
        if self.multiple <= 1 && self.min == 0 {
            return rows;
        }
        let m = self.multiple.max(1);
        ((rows / m + 1) * m).max(self.min.max(rows + 1))
    }

    /// `x` with zero rows appended up to [`RowBucket::padded`] rows (`x` itself without padding).
    ///
    /// # Shapes
    /// - x: `[rows, c]` -> `[self.padded(rows), c]`
    pub fn pad<B: SparseConvBackend>(self, x: Tensor<B, 2>) -> Tensor<B, 2> {
        let [rows, _] = x.dims();
        rows::pad_rows(x, self.padded(rows))
    }

    /// `f` on `x`'s rows padded to the bucket, its result cut back to `x`'s rows: for row-wise `f`
    /// (a matrix product with a weight), the same values as `f(x)`.
    ///
    /// # Shapes
    /// - x: `[rows, c]`, f: `[r, c] -> [r, d]` -> `[rows, d]`
    pub fn map<B: SparseConvBackend>(
        self,
        x: Tensor<B, 2>,
        f: impl FnOnce(Tensor<B, 2>) -> Tensor<B, 2>,
    ) -> Tensor<B, 2> {
        let [rows, _] = x.dims();
        if self.padded(rows) == rows {
            return f(x);
        }
        f(self.pad(x)).narrow(0, 0, rows)
    }
}

/// Row chunks `(start, end)` of an implicit GEMM over `rows` outputs with `width = K·C_in`.
fn row_chunks(rows: usize, width: usize, max_elems: usize) -> impl Iterator<Item = (usize, usize)> {
    let step = (max_elems / width.max(1)).max(1);
    (0..rows)
        .step_by(step)
        .map(move |a| (a, (a + step).min(rows)))
}

/// `x` with one zero row appended (row `n_in`, the target of absent neighbours in the gather table).
fn with_zero_row<B: Backend>(x: Tensor<B, 2>) -> Tensor<B, 2> {
    let [_, c] = x.dims();
    let device = x.device();
    Tensor::cat(vec![x, Tensor::zeros([1, c], &device)], 0)
}

/// The `[rows.len(), K·C_in]` implicit-GEMM block of output rows `rows`: their K neighbour rows of
/// `xp` (the input with its zero row) side by side, read through the gather table.
/// With a row bucket, the block has [`RowBucket::padded`] rows, the rows past `rows.len()` all
/// read the zero row.
fn gather_rows<B: Backend>(
    xp: &Tensor<B, 2>,
    table: &[u32],
    kv: usize,
    rows: std::ops::Range<usize>,
    bucket: RowBucket,
) -> Tensor<B, 2> {
    let [n_in_with_zero, cin] = xp.dims();
    let padded = bucket.padded(rows.len());
    let part = &table[rows.start * kv..rows.end * kv];
    let idx = if padded == rows.len() {
        index_tensor::<B>(part, &xp.device())
    } else {
        let zero_row = (n_in_with_zero - 1) as u32;
        let mut v = Vec::with_capacity(padded * kv);
        v.extend_from_slice(part);
        v.resize(padded * kv, zero_row);
        index_tensor::<B>(&v, &xp.device())
    };
    xp.clone().select(0, idx).reshape([padded, kv * cin])
}

/// Portable forward (any backend; the one GPU backends use). As an implicit GEMM when the map has a
/// [`KernelMap::gather_table`]: one gather of every output row's K neighbour rows into
/// `[n_out, K·C_in]` (absent neighbours read a zero row) and one matrix product with the
/// `[K·C_in, C_out]` weight, in row chunks of at most 2^27 gathered values — a handful of launches
/// per layer whatever the kernel volume, no scatter. Otherwise [`conv_forward_per_offset`].
pub fn conv_forward_portable<B: Backend>(
    x: Tensor<B, 2>,
    w: Tensor<B, 3>,
    map: &KernelMap,
    transposed: bool,
) -> Tensor<B, 2> {
    conv_forward_portable_chunked(
        x,
        w,
        map,
        transposed,
        IMPLICIT_GEMM_MAX_ELEMS,
        RowBucket::NONE,
    )
}

/// [`conv_forward_portable`] with gathered blocks of at most `max_elems` values (before padding),
/// each block's rows padded to `bucket`.
pub fn conv_forward_portable_chunked<B: Backend>(
    x: Tensor<B, 2>,
    w: Tensor<B, 3>,
    map: &KernelMap,
    transposed: bool,
    max_elems: usize,
    bucket: RowBucket,
) -> Tensor<B, 2> {
    let Some(table) = map.gather_table() else {
        return conv_forward_per_offset(x, w, map, transposed);
    };
    let device = x.device();
    let [_, cin] = x.dims();
    let kv = map.kernel_volume();
    let wm = weight_matrix(w, transposed);
    let [_, cout] = wm.dims();
    let n_out = map.n_out();
    if n_out == 0 || map.num_pairs() == 0 {
        return Tensor::zeros([n_out, cout], &device);
    }
    let xp = with_zero_row(x);
    let mut parts = Vec::new();
    for (a, b) in row_chunks(n_out, kv * cin, max_elems) {
        let y = gather_rows(&xp, table, kv, a..b, bucket).matmul(wm.clone());
        parts.push(if bucket.padded(b - a) == b - a {
            y
        } else {
            y.narrow(0, 0, b - a)
        });
    }
    if parts.len() == 1 {
        parts.pop().expect("one part")
    } else {
        Tensor::cat(parts, 0)
    }
}

/// Portable forward, one gather, matrix product and index-add per kernel offset (the fallback for
/// maps without a gather table).
pub fn conv_forward_per_offset<B: Backend>(
    x: Tensor<B, 2>,
    w: Tensor<B, 3>,
    map: &KernelMap,
    transposed: bool,
) -> Tensor<B, 2> {
    let device = x.device();
    let [d0, kv, d2] = w.dims();
    let cout = if transposed { d2 } else { d0 };
    let mut y = Tensor::<B, 2>::zeros([map.n_out(), cout], &device);
    for k in 0..kv {
        let (ins, outs) = map.pairs(k);
        if ins.is_empty() {
            continue;
        }
        let wk = w.clone().slice([0..d0, k..k + 1, 0..d2]).reshape([d0, d2]);
        let wk = if transposed { wk } else { wk.transpose() }; // [cin, cout]
        let g = x.clone().select(0, index_tensor::<B>(ins, &device));
        y = y.select_assign(
            0,
            index_tensor::<B>(outs, &device),
            g.matmul(wk),
            burn::tensor::IndexingUpdateOp::Add,
        );
    }
    y
}

/// Portable weight gradient, `[d0, K, d2]`: with a gather table, `Σ_chunks G^T dy` over the same
/// `[rows, K·C_in]` gathers as [`conv_forward_portable`] (one product per chunk); otherwise
/// [`conv_weight_grad_per_offset`].
pub fn conv_weight_grad_portable<B: Backend>(
    x: Tensor<B, 2>,
    dy: Tensor<B, 2>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
) -> Tensor<B, 3> {
    conv_weight_grad_portable_chunked(x, dy, map, wshape, transposed, IMPLICIT_GEMM_MAX_ELEMS)
}

/// [`conv_weight_grad_portable`] with gathered blocks of at most `max_elems` values.
pub fn conv_weight_grad_portable_chunked<B: Backend>(
    x: Tensor<B, 2>,
    dy: Tensor<B, 2>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
    max_elems: usize,
) -> Tensor<B, 3> {
    let Some(table) = map.gather_table() else {
        return conv_weight_grad_per_offset(x, dy, map, wshape, transposed);
    };
    let device = x.device();
    let [_, kv, _] = wshape;
    let [_, cin] = x.dims();
    let [_, cout] = dy.dims();
    let n_out = map.n_out();
    if n_out == 0 || map.num_pairs() == 0 {
        return Tensor::zeros(wshape, &device);
    }
    let xp = with_zero_row(x);
    let mut dw: Option<Tensor<B, 2>> = None;
    for (a, b) in row_chunks(n_out, kv * cin, max_elems) {
        let g = gather_rows(&xp, table, kv, a..b, RowBucket::NONE);
        let part = g.transpose().matmul(dy.clone().slice([a..b, 0..cout]));
        dw = Some(match dw {
            Some(acc) => acc + part,
            None => part,
        });
    }
    weight_from_matrix(dw.expect("n_out > 0"), wshape, transposed)
}

/// The weight `[D0, K, D2]` of a `[K·C_in, C_out]` matrix (offset-major rows): the inverse of
/// [`weight_matrix`], for weight gradients computed in the implicit GEMM's layout.
pub(crate) fn weight_from_matrix<B: Backend>(
    dw: Tensor<B, 2>,
    wshape: [usize; 3],
    transposed: bool,
) -> Tensor<B, 3> {
    let [d0, kv, d2] = wshape;
    let [rows, cout] = dw.dims();
    let dw = dw.reshape([kv, rows / kv.max(1), cout]);
    if transposed {
        dw.swap_dims(0, 1).reshape([d0, kv, d2]) // [C_in, K, C_out]
    } else {
        dw.permute([2, 0, 1]).reshape([d0, kv, d2]) // [C_out, K, C_in]
    }
}

/// Portable weight gradient, one pair of gathers and a product per kernel offset, `[d0, K, d2]`.
pub fn conv_weight_grad_per_offset<B: Backend>(
    x: Tensor<B, 2>,
    dy: Tensor<B, 2>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
) -> Tensor<B, 3> {
    let device = x.device();
    let [d0, kv, d2] = wshape;
    let mut slices = Vec::with_capacity(kv);
    for k in 0..kv {
        let (ins, outs) = map.pairs(k);
        if ins.is_empty() {
            slices.push(Tensor::<B, 3>::zeros([d0, 1, d2], &device));
            continue;
        }
        let gx = x.clone().select(0, index_tensor::<B>(ins, &device));
        let gy = dy.clone().select(0, index_tensor::<B>(outs, &device));
        let s = if transposed {
            gx.transpose().matmul(gy)
        } else {
            gy.transpose().matmul(gx)
        };
        slices.push(s.reshape([d0, 1, d2]));
    }
    Tensor::cat(slices, 1)
}

/// The portable forward on a backend's primitives, with its gather limit and row bucket (the
/// default of [`SparseConvBackend::sparse_conv`]).
fn portable_sparse_conv<B: SparseConvBackend>(
    x: FloatTensor<B>,
    w: FloatTensor<B>,
    map: &KernelMap,
    transposed: bool,
) -> FloatTensor<B> {
    unwrap(conv_forward_portable_chunked::<B>(
        wrap(x),
        wrap(w),
        map,
        transposed,
        B::MAX_GATHER_ELEMS,
        B::ROW_BUCKET,
    ))
}

/// The portable weight gradient on a backend's primitives, with its gather limit (the default of
/// [`SparseConvBackend::sparse_conv_weight_grad`]).
fn portable_sparse_conv_weight_grad<B: SparseConvBackend>(
    x: FloatTensor<B>,
    dy: FloatTensor<B>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
) -> FloatTensor<B> {
    unwrap(conv_weight_grad_portable_chunked::<B>(
        wrap(x),
        wrap(dy),
        map,
        wshape,
        transposed,
        B::MAX_GATHER_ELEMS,
    ))
}

/// Backends that can run sparse convolution.
///
/// Weight `w` is `[D0, K, D2]` (the layer's `[Cout, kx, ky, kz, Cin]` flattened); see
/// [`host::WeightView`] for the meaning of `transposed`.
pub trait SparseConvBackend: Backend {
    /// Most values in one gathered `[rows, K·C_in]` block of the portable implicit GEMM: the
    /// backend's largest buffer bounds it (a block beyond it fails to allocate).
    const MAX_GATHER_ELEMS: usize = IMPLICIT_GEMM_MAX_ELEMS;

    /// Row padding of the portable path's matrix products (see [`RowBucket`]): the cubecl
    /// backends' by default, none on the CPU.
    const ROW_BUCKET: RowBucket = RowBucket::CUBECL;

    /// Whether this backend builds kernel-map tables on its own device from the maps' sites
    /// ([`crate::kernel_map::conv_map_deferred`]), so that the host builds no pairs. The host
    /// builds them by default.
    fn builds_maps_on_device() -> bool {
        false
    }

    /// The gather table this backend computes `map` with on `device`, read back to the host: the
    /// check of device-built tables (`sparseocc check-backend`). `None` for a backend that has no
    /// device table of its own (the default).
    fn device_gather_table(
        map: &KernelMap,
        device: &burn::tensor::Device<Self>,
    ) -> Option<Vec<u32>> {
        let _ = (map, device);
        None
    }

    /// The pair count of `map` from its table on `device`, as a count to read later (after the
    /// caller synchronises: [`crate::flops::add_later`]), for a map without host pairs whose table
    /// this backend builds on its device. `None` (the default) where there is no such table: the
    /// caller then counts the host pairs.
    fn device_pair_count(
        map: &KernelMap,
        device: &burn::tensor::Device<Self>,
    ) -> Option<Box<dyn FnOnce() -> usize>> {
        let _ = (map, device);
        None
    }

    /// `y[o] += W_k x[i]` over the pairs of `map`.
    ///
    /// # Shapes
    /// - x: `[map.n_in(), cin]`, w: `[D0, K, D2]` -> `[map.n_out(), cout]`
    fn sparse_conv(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        map: Arc<KernelMap>,
        transposed: bool,
    ) -> FloatTensor<Self> {
        portable_sparse_conv::<Self>(x, w, &map, transposed)
    }

    /// Gradient of [`SparseConvBackend::sparse_conv`] with respect to the weight.
    ///
    /// # Shapes
    /// - x: `[n_in, cin]`, dy: `[n_out, cout]` -> `[D0, K, D2]`
    fn sparse_conv_weight_grad(
        x: FloatTensor<Self>,
        dy: FloatTensor<Self>,
        map: Arc<KernelMap>,
        wshape: [usize; 3],
        transposed: bool,
    ) -> FloatTensor<Self> {
        portable_sparse_conv_weight_grad::<Self>(x, dy, &map, wshape, transposed)
    }

    /// Scatter-add of rows over a plan: `out[r] = Σ_{h : dest[h] = r} values[h]`
    /// ([`crate::rows`]). The default is burn's `select_assign` into zeros.
    ///
    /// # Shapes
    /// - values: `[plan.n_in(), C]` -> `[plan.n_out(), C]`
    fn scatter_add_rows(values: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        unwrap(rows::scatter_add_rows_portable::<Self>(wrap(values), &plan))
    }

    /// Gather of rows over a plan: `out[h] = x[dest[h]]` ([`crate::rows`]); under `Autodiff`
    /// its backward is [`SparseConvBackend::scatter_add_rows`]. The default is burn's `select`.
    ///
    /// # Shapes
    /// - x: `[plan.n_out(), C]` -> `[plan.n_in(), C]`
    fn gather_rows(x: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        rows::gather_rows_portable::<Self>(x, &plan)
    }

    /// `x` with zero rows appended up to `rows` rows ([`crate::pad_rows`], [`RowBucket::pad`]);
    /// under `Autodiff` its backward is the output gradient's first rows. The default is burn's
    /// `cat` with a block of zeros (a fill and a copy of each part on the cubecl backends, which
    /// pad in one kernel instead).
    ///
    /// # Shapes
    /// - x: `[n, C]` (`n <= rows`) -> `[rows, C]`
    fn pad_rows(x: FloatTensor<Self>, rows: usize) -> FloatTensor<Self> {
        rows::pad_rows_portable::<Self>(x, rows)
    }
}

fn host_forward<B: Backend>(
    x: FloatTensor<B>,
    w: FloatTensor<B>,
    map: &KernelMap,
    transposed: bool,
) -> FloatTensor<B> {
    let xt: Tensor<B, 2> = wrap(x);
    let wt: Tensor<B, 3> = wrap(w);
    let device = xt.device();
    let [d0, k, d2] = wt.dims();
    let wv = WeightView {
        d0,
        k,
        d2,
        transposed,
    };
    let cout = if transposed { d2 } else { d0 };
    let xd = xt.into_data();
    let wd = wt.into_data();
    let data = match (xd.dtype, wd.dtype) {
        (DType::F32, DType::F32) => run_fwd::<f32>(&xd, &wd, wv, map, cout),
        (DType::F64, DType::F64) => run_fwd::<f64>(&xd, &wd, wv, map, cout),
        _ => {
            return unwrap(conv_forward_portable::<B>(
                Tensor::from_data(xd, &device),
                Tensor::from_data(wd, &device),
                map,
                transposed,
            ))
        }
    };
    unwrap(Tensor::<B, 2>::from_data(data, &device))
}

fn run_fwd<F: HostFloat + burn::tensor::Element>(
    xd: &TensorData,
    wd: &TensorData,
    wv: WeightView,
    map: &KernelMap,
    cout: usize,
) -> TensorData {
    let x = xd.as_slice::<F>().expect("dtype checked");
    let w = wd.as_slice::<F>().expect("dtype checked");
    TensorData::new(host::conv_forward(x, w, wv, map), [map.n_out(), cout])
}

fn host_weight_grad<B: Backend>(
    x: FloatTensor<B>,
    dy: FloatTensor<B>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
) -> FloatTensor<B> {
    let xt: Tensor<B, 2> = wrap(x);
    let dyt: Tensor<B, 2> = wrap(dy);
    let device = xt.device();
    let wv = WeightView {
        d0: wshape[0],
        k: wshape[1],
        d2: wshape[2],
        transposed,
    };
    let xd = xt.into_data();
    let dd = dyt.into_data();
    let data = match (xd.dtype, dd.dtype) {
        (DType::F32, DType::F32) => TensorData::new(
            host::conv_weight_grad::<f32>(
                xd.as_slice().expect("dtype checked"),
                dd.as_slice().expect("dtype checked"),
                wv,
                map,
            ),
            wshape,
        ),
        (DType::F64, DType::F64) => TensorData::new(
            host::conv_weight_grad::<f64>(
                xd.as_slice().expect("dtype checked"),
                dd.as_slice().expect("dtype checked"),
                wv,
                map,
            ),
            wshape,
        ),
        _ => {
            return unwrap(conv_weight_grad_portable::<B>(
                Tensor::from_data(xd, &device),
                Tensor::from_data(dd, &device),
                map,
                wshape,
                transposed,
            ))
        }
    };
    unwrap(Tensor::<B, 3>::from_data(data, &device))
}

/// Zero-copy access to the host buffers of the `NdArray` backend.
mod nd {

    use burn::backend::ndarray::NdArrayTensor;
    use ndarray::{ArcArray, IxDyn};

    pub(super) enum Host<'a> {
        F32(std::borrow::Cow<'a, [f32]>),
        F64(std::borrow::Cow<'a, [f64]>),
    }

    fn slice<E: Clone>(v: ndarray::ArrayView<'_, E, IxDyn>) -> std::borrow::Cow<'_, [E]> {
        match v.to_slice() {
            Some(s) => std::borrow::Cow::Borrowed(s),
            None => std::borrow::Cow::Owned(v.iter().cloned().collect()),
        }
    }

    pub(super) fn host(t: &NdArrayTensor) -> Option<Host<'_>> {
        match t {
            NdArrayTensor::F32(s) => Some(Host::F32(slice(s.view()))),
            NdArrayTensor::F64(s) => Some(Host::F64(slice(s.view()))),
            _ => None,
        }
    }

    pub(super) fn tensor<E>(v: Vec<E>, shape: &[usize]) -> NdArrayTensor
    where
        NdArrayTensor: From<ArcArray<E, IxDyn>>,
    {
        let a = ArcArray::from_shape_vec(IxDyn(shape), v).expect("length matches shape");
        NdArrayTensor::from(a)
    }
}

impl<E, I, Q> SparseConvBackend for burn::backend::NdArray<E, I, Q>
where
    E: burn::backend::ndarray::FloatNdArrayElement,
    I: burn::backend::ndarray::IntNdArrayElement,
    Q: burn::backend::ndarray::QuantElement,
    burn::backend::ndarray::NdArrayTensor: From<burn::backend::ndarray::SharedArray<E>>,
    burn::backend::ndarray::NdArrayTensor: From<burn::backend::ndarray::SharedArray<I>>,
{
    const ROW_BUCKET: RowBucket = RowBucket::NONE;

    fn sparse_conv(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        map: Arc<KernelMap>,
        transposed: bool,
    ) -> FloatTensor<Self> {
        let ws = w.shape();
        let wv = WeightView {
            d0: ws[0],
            k: ws[1],
            d2: ws[2],
            transposed,
        };
        let cout = if transposed { ws[2] } else { ws[0] };
        let shape = [map.n_out(), cout];
        match (nd::host(&x), nd::host(&w)) {
            (Some(nd::Host::F32(xs)), Some(nd::Host::F32(wsl))) => {
                nd::tensor(host::conv_forward::<f32>(&xs, &wsl, wv, &map), &shape)
            }
            (Some(nd::Host::F64(xs)), Some(nd::Host::F64(wsl))) => {
                nd::tensor(host::conv_forward::<f64>(&xs, &wsl, wv, &map), &shape)
            }
            _ => host_forward::<Self>(x, w, &map, transposed),
        }
    }

    fn sparse_conv_weight_grad(
        x: FloatTensor<Self>,
        dy: FloatTensor<Self>,
        map: Arc<KernelMap>,
        wshape: [usize; 3],
        transposed: bool,
    ) -> FloatTensor<Self> {
        let wv = WeightView {
            d0: wshape[0],
            k: wshape[1],
            d2: wshape[2],
            transposed,
        };
        match (nd::host(&x), nd::host(&dy)) {
            (Some(nd::Host::F32(xs)), Some(nd::Host::F32(ds))) => {
                nd::tensor(host::conv_weight_grad::<f32>(&xs, &ds, wv, &map), &wshape)
            }
            (Some(nd::Host::F64(xs)), Some(nd::Host::F64(ds))) => {
                nd::tensor(host::conv_weight_grad::<f64>(&xs, &ds, wv, &map), &wshape)
            }
            _ => host_weight_grad::<Self>(x, dy, &map, wshape, transposed),
        }
    }
}

/// The cubecl backends' sparse convolution and its weight gradient: the `#[cube]` kernels of
/// [`crate::cube`] where the map has a gather table (and [`crate::cube::CubeConv`] is `fetch`), the
/// portable defaults otherwise.
#[cfg(feature = "cube")]
macro_rules! cube_sparse_conv {
    ($runtime:ty, $f:ty, $i:ty, $b:ty) => {
        fn builds_maps_on_device() -> bool {
            crate::cube::CubeConv::current() == crate::cube::CubeConv::Fetch
                && crate::cube::CubeMaps::current() == crate::cube::CubeMaps::Device
        }

        fn device_gather_table(
            map: &KernelMap,
            device: &burn::tensor::Device<Self>,
        ) -> Option<Vec<u32>> {
            crate::cube::read_device_gather_table::<$runtime, $f, $i, $b>(map, device)
        }

        fn device_pair_count(
            map: &KernelMap,
            device: &burn::tensor::Device<Self>,
        ) -> Option<Box<dyn FnOnce() -> usize>> {
            crate::cube::device_pair_count::<$runtime, $f, $i, $b>(map, device)
        }

        fn pad_rows(x: FloatTensor<Self>, rows: usize) -> FloatTensor<Self> {
            crate::cube::fusion_pad_rows::<$runtime, $f, $i, $b>(x, rows)
        }

        fn sparse_conv(
            x: FloatTensor<Self>,
            w: FloatTensor<Self>,
            map: Arc<KernelMap>,
            transposed: bool,
        ) -> FloatTensor<Self> {
            match crate::cube::fusion_sparse_conv::<$runtime, $f, $i, $b>(x, w, &map, transposed) {
                Ok(y) => y,
                Err((x, w)) => portable_sparse_conv::<Self>(x, w, &map, transposed),
            }
        }

        fn sparse_conv_weight_grad(
            x: FloatTensor<Self>,
            dy: FloatTensor<Self>,
            map: Arc<KernelMap>,
            wshape: [usize; 3],
            transposed: bool,
        ) -> FloatTensor<Self> {
            match crate::cube::fusion_sparse_conv_weight_grad::<$runtime, $f, $i, $b>(
                x, dy, &map, wshape, transposed,
            ) {
                Ok(dw) => dw,
                Err((x, dy)) => {
                    portable_sparse_conv_weight_grad::<Self>(x, dy, &map, wshape, transposed)
                }
            }
        }
    };
}

/// CUDA: the sparse convolution as `#[cube]` kernels, the row scatter-add as a cubecl segment sum
/// ([`crate::cube`]).
#[cfg(feature = "cuda")]
impl SparseConvBackend for burn_cuda::Cuda {
    cube_sparse_conv!(cubecl::cuda::CudaRuntime, f32, i32, u8);

    fn scatter_add_rows(values: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        crate::cube::fusion_scatter_add_rows::<cubecl::cuda::CudaRuntime, f32, i32, u8>(
            values, &plan,
        )
    }
}

/// WebGPU (WGSL; lavapipe on a machine without a GPU): the `#[cube]` kernels as on CUDA; the
/// portable path, where it runs, in gathered blocks of 64 MiB: WebGPU's default storage-buffer
/// binding limit is 128 MiB (lavapipe refused a 219 MiB block of the 2^27-value default).
#[cfg(feature = "wgpu")]
impl SparseConvBackend for burn_wgpu::Wgpu {
    const MAX_GATHER_ELEMS: usize = 1 << 24;

    cube_sparse_conv!(burn_wgpu::WgpuRuntime, f32, i32, u32);

    fn scatter_add_rows(values: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        crate::cube::fusion_scatter_add_rows::<burn_wgpu::WgpuRuntime, f32, i32, u32>(values, &plan)
    }
}

#[derive(Debug)]
struct SparseConvBackwardOp;

impl<B: SparseConvBackend> Backward<B, 2> for SparseConvBackwardOp {
    type State = (NodeId, NodeId, Arc<KernelMap>, [usize; 3], bool);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let [node_x, node_w] = ops.parents;
        let dy = grads.consume::<B>(&ops.node);
        let (x_id, w_id, map, wshape, transposed) = ops.state;
        let x: FloatTensor<B> = checkpointer.retrieve_node_output(x_id);
        let w: FloatTensor<B> = checkpointer.retrieve_node_output(w_id);
        if let Some(node) = node_w {
            let dw = B::sparse_conv_weight_grad(x, dy.clone(), map.clone(), wshape, transposed);
            grads.register::<B>(node.id, dw);
        }
        if let Some(node) = node_x {
            let dx = B::sparse_conv(dy, w, map.transposed(), !transposed);
            grads.register::<B>(node.id, dx);
        }
    }
}

/// The two row ops of [`RowPlan`], each the adjoint of the other.
#[derive(Debug, Clone, Copy)]
enum RowOp {
    /// `out[r] = Σ_{h : dest[h] = r} x[h]`
    ScatterAdd,
    /// `out[h] = x[dest[h]]`
    Gather,
}

impl RowOp {
    fn apply<B: SparseConvBackend>(self, x: FloatTensor<B>, plan: Arc<RowPlan>) -> FloatTensor<B> {
        match self {
            RowOp::ScatterAdd => B::scatter_add_rows(x, plan),
            RowOp::Gather => B::gather_rows(x, plan),
        }
    }

    fn adjoint(self) -> Self {
        match self {
            RowOp::ScatterAdd => RowOp::Gather,
            RowOp::Gather => RowOp::ScatterAdd,
        }
    }
}

/// Backward of a row op: its adjoint applied to the output gradient (the scatter's backward is
/// `dv = dout[dest]`, the gather's `dx = scatter_add(dout)`).
#[derive(Debug)]
struct RowOpBackward(RowOp);

impl<B: SparseConvBackend> Backward<B, 1> for RowOpBackward {
    type State = Arc<RowPlan>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dout = grads.consume::<B>(&ops.node);
        if let Some(node) = &ops.parents[0] {
            grads.register::<B>(node.id, self.0.adjoint().apply::<B>(dout, ops.state));
        }
    }
}

/// A row op on the autodiff backend: the inner backend's op, tracked with its adjoint.
fn autodiff_row_op<B: SparseConvBackend, C: CheckpointStrategy>(
    op: RowOp,
    x: FloatTensor<Autodiff<B, C>>,
    plan: Arc<RowPlan>,
) -> FloatTensor<Autodiff<B, C>> {
    match RowOpBackward(op)
        .prepare::<C>([x.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = op.apply::<B>(x.primitive, plan.clone());
            prep.finish(plan, out)
        }
        OpsKind::UnTracked(prep) => prep.finish(op.apply::<B>(x.primitive, plan)),
    }
}

/// Backward of [`SparseConvBackend::pad_rows`]: the output gradient's first rows (the input's).
#[derive(Debug)]
struct PadRowsBackward;

impl<B: SparseConvBackend> Backward<B, 1> for PadRowsBackward {
    /// The input's row count.
    type State = usize;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dout = grads.consume::<B>(&ops.node);
        if let Some(node) = &ops.parents[0] {
            let dx = wrap::<B, 2>(dout).narrow(0, 0, ops.state);
            grads.register::<B>(node.id, unwrap(dx));
        }
    }
}

impl<B: SparseConvBackend, C: CheckpointStrategy> SparseConvBackend for Autodiff<B, C> {
    const MAX_GATHER_ELEMS: usize = B::MAX_GATHER_ELEMS;
    const ROW_BUCKET: RowBucket = B::ROW_BUCKET;

    fn builds_maps_on_device() -> bool {
        B::builds_maps_on_device()
    }

    fn device_gather_table(
        map: &KernelMap,
        device: &burn::tensor::Device<Self>,
    ) -> Option<Vec<u32>> {
        B::device_gather_table(map, device)
    }

    fn device_pair_count(
        map: &KernelMap,
        device: &burn::tensor::Device<Self>,
    ) -> Option<Box<dyn FnOnce() -> usize>> {
        B::device_pair_count(map, device)
    }

    fn scatter_add_rows(values: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        autodiff_row_op::<B, C>(RowOp::ScatterAdd, values, plan)
    }

    fn gather_rows(x: FloatTensor<Self>, plan: Arc<RowPlan>) -> FloatTensor<Self> {
        autodiff_row_op::<B, C>(RowOp::Gather, x, plan)
    }

    fn pad_rows(x: FloatTensor<Self>, rows: usize) -> FloatTensor<Self> {
        let n = TensorMetadata::shape(&x.primitive)[0];
        match PadRowsBackward
            .prepare::<C>([x.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(n, B::pad_rows(x.primitive, rows)),
            OpsKind::UnTracked(prep) => prep.finish(B::pad_rows(x.primitive, rows)),
        }
    }

    fn sparse_conv(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        map: Arc<KernelMap>,
        transposed: bool,
    ) -> FloatTensor<Self> {
        let wshape: [usize; 3] = {
            let s = burn::tensor::TensorMetadata::shape(&w.primitive);
            [s[0], s[1], s[2]]
        };
        match SparseConvBackwardOp
            .prepare::<C>([x.node.clone(), w.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let x_id = prep.checkpoint(&x);
                let w_id = prep.checkpoint(&w);
                let out = B::sparse_conv(x.primitive, w.primitive, map.clone(), transposed);
                prep.finish((x_id, w_id, map, wshape, transposed), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::sparse_conv(x.primitive, w.primitive, map, transposed))
            }
        }
    }

    fn sparse_conv_weight_grad(
        x: FloatTensor<Self>,
        dy: FloatTensor<Self>,
        map: Arc<KernelMap>,
        wshape: [usize; 3],
        transposed: bool,
    ) -> FloatTensor<Self> {
        // Second-order gradients are not needed by any model here; the result is not tracked.
        let x_inner = <Self as burn::tensor::backend::AutodiffBackend>::inner(x);
        let dy_inner = <Self as burn::tensor::backend::AutodiffBackend>::inner(dy);
        <Self as burn::tensor::backend::AutodiffBackend>::from_inner(B::sparse_conv_weight_grad(
            x_inner, dy_inner, map, wshape, transposed,
        ))
    }
}

/// Tensor-level entry point: sparse convolution of row features with a `[D0, K, D2]` weight.
pub fn sparse_conv<B: SparseConvBackend>(
    x: Tensor<B, 2>,
    w: Tensor<B, 3>,
    map: Arc<KernelMap>,
    transposed: bool,
) -> Tensor<B, 2> {
    wrap(B::sparse_conv(unwrap(x), unwrap(w), map, transposed))
}
