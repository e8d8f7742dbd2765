//! Zero-copy access to the tensors of burn-ndarray (with and without autodiff) for the host kernels
//! ([`crate::kernels::conv2d_host`], [`crate::kernels::dca_host`]).
//!
//! `Tensor::into_data` iterates element by element when the array is shared (a parameter, a tensor
//! also kept for a residual connection): about 35 ns per value, more than the GEMM it feeds. The host
//! kernels borrow the array's memory instead. Every function here is typed on the backend
//! (`NdArray<T>` or `Autodiff<NdArray<T>, C>`), so the primitive is known at compile time; a tensor
//! whose element type is not `T` (burn 0.21 fixes a device's float dtype at the first tensor of the
//! process, so an `NdArray<f64>` tensor can hold f32 values) gives `None`.

use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::ndarray::{FloatNdArrayElement, NdArrayTensor, SharedArray};
use burn::backend::{Autodiff, NdArray};
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};
use occ_sparse::host::HostFloat;

/// Float types of the host kernels (f32 and f64): [`HostFloat`] plus conversion from the f64 the
/// BatchNorm folding and the bilinear weights are computed in, and zero-copy access to a
/// burn-ndarray tensor of that type.
pub trait Elem:
    HostFloat
    + std::ops::Mul<Output = Self>
    + std::ops::Add<Output = Self>
    + PartialOrd
    + burn::tensor::Element
{
    /// From f64 (rounded for f32).
    fn from_f64(v: f64) -> Self;
    /// `f(values)` in row-major order, borrowed when the array is already in standard layout; `None`
    /// when the tensor holds another element type.
    fn with_slice<R>(t: &NdArrayTensor, f: impl FnOnce(&[Self]) -> R) -> Option<R>;
}

/// An [`Elem`] that is also burn-ndarray's float element, so that `NdArray<T>` is a backend.
pub trait NdElem: Elem + FloatNdArrayElement {}

impl NdElem for f32 {}
impl NdElem for f64 {}

impl Elem for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn with_slice<R>(t: &NdArrayTensor, f: impl FnOnce(&[Self]) -> R) -> Option<R> {
        match t {
            NdArrayTensor::F32(s) => Some(f(s.view().as_standard_layout().as_slice()?)),
            _ => None,
        }
    }
}

impl Elem for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
    fn with_slice<R>(t: &NdArrayTensor, f: impl FnOnce(&[Self]) -> R) -> Option<R> {
        match t {
            NdArrayTensor::F64(s) => Some(f(s.view().as_standard_layout().as_slice()?)),
            _ => None,
        }
    }
}

/// `f(values)` of a burn-ndarray tensor without going through `TensorData` (whose conversion
/// iterates element by element when the array is shared, e.g. a parameter or a tensor also kept for
/// a residual connection); `None` when it holds another element type than `T`.
pub(crate) fn with_host_slice<T: NdElem, const D: usize, R>(
    x: &Tensor<NdArray<T>, D>,
    f: impl FnOnce(&[T]) -> R,
) -> Option<R>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let prim: NdArrayTensor = x.clone().into_primitive().tensor();
    T::with_slice(&prim, f)
}

/// The values of a burn-ndarray tensor of element type `T`, row-major (a copy).
pub(crate) fn read<T: NdElem, const D: usize>(t: &Tensor<NdArray<T>, D>) -> Option<Vec<T>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    with_host_slice(t, |s: &[T]| s.to_vec())
}

/// The primitive of the CPU training backend with element type `T` and checkpointing `C`.
pub(crate) type AdTensor<T, C> = FloatTensor<Autodiff<NdArray<T>, C>>;

/// The autodiff primitive of a tensor of the CPU training backend.
pub(crate) fn to_ad<T, C: CheckpointStrategy, const D: usize>(
    t: Tensor<Autodiff<NdArray<T>, C>, D>,
) -> AdTensor<T, C>
where
    T: NdElem,
    NdArrayTensor: From<SharedArray<T>>,
{
    t.into_primitive().tensor()
}

/// Back from [`to_ad`].
pub(crate) fn from_ad<T, C: CheckpointStrategy, const D: usize>(
    t: AdTensor<T, C>,
) -> Tensor<Autodiff<NdArray<T>, C>, D>
where
    T: NdElem,
    NdArrayTensor: From<SharedArray<T>>,
{
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

/// A copy of the values of a burn-ndarray primitive of element type `T`.
pub(crate) fn host_vec<T: Elem>(t: &NdArrayTensor) -> Option<Vec<T>> {
    T::with_slice(t, |s| s.to_vec())
}
