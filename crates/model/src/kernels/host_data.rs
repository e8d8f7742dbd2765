//! Zero-copy access to tensors of the CPU inference backend (burn-ndarray without autodiff) for the
//! fused host kernels ([`crate::kernels::conv2d_host`], the DCA host loop in [`crate::sparseocc_pp::dca`]).
//!
//! `Tensor::into_data` iterates element by element when the array is shared (a parameter, a tensor
//! also kept for a residual connection): about 35 ns per value, more than the GEMM it feeds. The host
//! kernels borrow the array's memory instead.

use burn::backend::ndarray::NdArrayTensor;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
use occ_sparse::host::HostFloat;

/// Whether `B` is the CPU inference backend (burn-ndarray f32 or f64, no autodiff).
pub(crate) fn is_host_backend<B: Backend>() -> bool {
    use std::any::TypeId;
    let t = TypeId::of::<B>();
    t == TypeId::of::<burn::backend::NdArray<f32>>()
        || t == TypeId::of::<burn::backend::NdArray<f64>>()
}

/// Whether `B` is burn-ndarray f32 (host kernels then compute in f32, otherwise in f64).
pub(crate) fn is_host_f32<B: Backend>() -> bool {
    std::any::TypeId::of::<B>() == std::any::TypeId::of::<burn::backend::NdArray<f32>>()
}

/// Float types of the host path: [`HostFloat`] plus conversion from the f64 the folding is done in,
/// and zero-copy access to a burn-ndarray tensor of that type.
pub(crate) trait Elem:
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

impl Elem for f32 {
    /// From f64 (rounded for f32).
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
    /// From f64 (rounded for f32).
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

/// `f(values)` of a tensor of the burn-ndarray backend without going through `TensorData` (whose
/// conversion iterates element by element when the array is shared, e.g. a parameter or a tensor
/// also kept for a residual connection).
pub(crate) fn with_host_slice<B: Backend, const D: usize, T: Elem, R>(
    x: &Tensor<B, D>,
    f: impl FnOnce(&[T]) -> R,
) -> Option<R> {
    let prim = x.clone().into_primitive().tensor();
    let nd = (&prim as &dyn std::any::Any).downcast_ref::<NdArrayTensor>()?;
    T::with_slice(nd, f)
}

/// The values of a burn-ndarray tensor of element type `T`, row-major (a copy).
pub(crate) fn read<B: Backend, const D: usize, T: Elem>(t: &Tensor<B, D>) -> Option<Vec<T>> {
    with_host_slice(t, |s: &[T]| s.to_vec())
}

/// Whether `B` is the CPU training backend `Autodiff<NdArray<f32 | f64>>` (the host autodiff ops of
/// [`crate::kernels::dca_host`] and [`crate::kernels::conv2d_host`] then replace burn's generic kernels).
pub(crate) fn is_host_autodiff<B: Backend>() -> bool {
    use burn::backend::{Autodiff, NdArray};
    use std::any::TypeId;
    let t = TypeId::of::<B>();
    t == TypeId::of::<Autodiff<NdArray<f32>>>() || t == TypeId::of::<Autodiff<NdArray<f64>>>()
}

/// The primitive of the CPU training backend with element type `T`.
pub(crate) type AdTensor<T> =
    burn::tensor::ops::FloatTensor<burn::backend::Autodiff<burn::backend::NdArray<T>>>;

/// The autodiff primitive of `t` when `B` is `Autodiff<NdArray<T>>`, else `None`.
pub(crate) fn to_ad<B: Backend, const D: usize, T>(t: Tensor<B, D>) -> Option<AdTensor<T>>
where
    T: burn::backend::ndarray::FloatNdArrayElement,
    NdArrayTensor: From<burn::backend::ndarray::SharedArray<T>>,
{
    let prim = t.into_primitive().tensor();
    let any: Box<dyn std::any::Any> = Box::new(prim);
    any.downcast::<AdTensor<T>>().ok().map(|b| *b)
}

/// Back from [`to_ad`]: `None` when `B` is not `Autodiff<NdArray<T>>`.
pub(crate) fn from_ad<B: Backend, const D: usize, T>(t: AdTensor<T>) -> Option<Tensor<B, D>>
where
    T: burn::backend::ndarray::FloatNdArrayElement,
    NdArrayTensor: From<burn::backend::ndarray::SharedArray<T>>,
{
    let any: Box<dyn std::any::Any> = Box::new(t);
    let prim = any.downcast::<B::FloatTensorPrimitive>().ok()?;
    Some(Tensor::from_primitive(
        burn::tensor::TensorPrimitive::Float(*prim),
    ))
}

/// A copy of the values of a burn-ndarray primitive of element type `T`.
pub(crate) fn host_vec<T: Elem>(t: &NdArrayTensor) -> Option<Vec<T>> {
    T::with_slice(t, |s| s.to_vec())
}
