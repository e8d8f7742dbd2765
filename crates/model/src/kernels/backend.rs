//! The model's own compute kernels as a burn backend extension, the way occ-sparse's
//! [`SparseConvBackend`] is done: a trait whose default methods run the portable burn ops (every
//! backend, CUDA included), overridden for `NdArray<f32 | f64>` by the host kernels and, through the
//! inner backend's `*_autodiff` methods, for `Autodiff<NdArray<f32 | f64>>` by autodiff ops with an
//! explicit backward pass. Model code is generic over `B: ModelBackend` and calls the kernels through
//! it; nothing checks types at run time.
//!
//! | kernel | portable default | `NdArray<T>` | `Autodiff<NdArray<T>, C>` |
//! |---|---|---|---|
//! | [`ModelBackend::conv2d_bn`] | burn's `Conv2d`, `BatchNorm`, `relu` (on the cubecl backends `conv2d_cube`: im2col + matmul, in training with a col2im backward) | [`conv_bn_host`] (BN folded, im2col + GEMM) | [`conv_autodiff`] (im2col + GEMM, GEMM backward), then burn's `BatchNorm`, `relu` |
//! | [`ModelBackend::dca_sample`] | [`dca::sample_tensor_ops`] (`grid_sample`) | host loop | host loop as one autodiff op |
//! | [`ModelBackend::row_linear`], [`ModelBackend::row_layer_norm`], [`ModelBackend::row_softmax`] | burn's `Linear` (+ `relu`), `LayerNorm`, `softmax` | row-wise host loops (`rows_host`: bias and ReLU fused into the GEMM output, one pass per row) | burn's (portable) |
//!
//! Where a host kernel does not apply (a grouped convolution, tensors whose float type is not the
//! backend's), the override falls back to the portable path, as the type-checking code before it did.

use crate::kernels::conv2d_host::{
    bn_relu, conv_autodiff, conv_bn_host, conv_bn_portable, conv_forward_portable,
};
use crate::kernels::dca::{self, DcaSample};
use crate::kernels::host_data::NdElem;
use crate::kernels::{dca_host, rows_host};
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::{Autodiff, NdArray};
use burn::nn::conv::Conv2d;
use burn::nn::{BatchNorm, LayerNorm, Linear};
use burn::tensor::activation::softmax;
use burn::tensor::Tensor;
use occ_sparse::{RowBucket, SparseConvBackend};

/// Backends the models run on: sparse convolution ([`SparseConvBackend`]) plus the model's own
/// kernels, each with a portable default (see the module documentation).
pub trait ModelBackend: SparseConvBackend {
    /// `relu?(bn?(conv(x)))`, the image-side convolution with its BatchNorm (see
    /// [`crate::kernels::conv2d_host::conv_bn`], the entry point that also counts the multiply-adds).
    ///
    /// # Shapes
    /// - x: `[N, C_in, H, W]` -> `[N, C_out, H_out, W_out]`
    fn conv2d_bn(
        conv: &Conv2d<Self>,
        bn: Option<&BatchNorm<Self>>,
        x: Tensor<Self, 4>,
        apply_relu: bool,
    ) -> Tensor<Self, 4> {
        conv_bn_portable(conv, bn, x, apply_relu)
    }

    /// `relu?(lin.forward(x))` over the last axis.
    ///
    /// # Shapes
    /// - x: `[..., d_in]` -> `[..., d_out]`
    fn row_linear<const D: usize>(
        lin: &Linear<Self>,
        x: Tensor<Self, D>,
        relu: bool,
    ) -> Tensor<Self, D> {
        linear_portable(lin, x, relu, Self::ROW_BUCKET)
    }

    /// `ln.forward(x)` for a LayerNorm made with epsilon [`LAYER_NORM_EPSILON`] (burn's module
    /// does not expose its epsilon, so the models build theirs with this constant). The default
    /// pads the rows to [`SparseConvBackend::ROW_BUCKET`] (see [`rows_bucketed`]).
    ///
    /// # Shapes
    /// - x: `[..., d]` -> `[..., d]`
    fn row_layer_norm<const D: usize>(ln: &LayerNorm<Self>, x: Tensor<Self, D>) -> Tensor<Self, D> {
        rows_bucketed(x, Self::ROW_BUCKET, |x| ln.forward(x))
    }

    /// Softmax over the last axis. The default pads the rows to
    /// [`SparseConvBackend::ROW_BUCKET`] (see [`rows_bucketed`]).
    ///
    /// # Shapes
    /// - x: `[..., d]` -> `[..., d]`
    fn row_softmax<const D: usize>(x: Tensor<Self, D>) -> Tensor<Self, D> {
        rows_bucketed(x, Self::ROW_BUCKET, |x| softmax(x, 1))
    }

    /// The DCA sampling step (see [`dca`]).
    ///
    /// # Shapes
    /// see [`DcaSample`]; returns `[N, D]`
    fn dca_sample(s: DcaSample<'_, Self>) -> Tensor<Self, 2> {
        dca::sample_tensor_ops(s)
    }

    /// `conv.forward(x)` on `Autodiff<Self, C>`, the convolution of
    /// [`ModelBackend::conv2d_bn`] in training (the BatchNorm and ReLU stay burn's). Default:
    /// burn's `Conv2d::forward` through burn's autodiff ([`conv_forward_portable`]: a strided 1x1
    /// convolution as a subsampling and a stride-1 one, whose input gradient burn-cubecl 0.21
    /// gets wrong).
    fn conv2d_autodiff<C: CheckpointStrategy>(
        conv: &Conv2d<Autodiff<Self, C>>,
        x: Tensor<Autodiff<Self, C>, 4>,
    ) -> Tensor<Autodiff<Self, C>, 4> {
        conv_forward_portable(conv, x)
    }

    /// [`ModelBackend::dca_sample`] on `Autodiff<Self, C>`. Default: the tensor-op composition
    /// through burn's autodiff.
    fn dca_sample_autodiff<C: CheckpointStrategy>(
        s: DcaSample<'_, Autodiff<Self, C>>,
    ) -> Tensor<Autodiff<Self, C>, 2> {
        dca::sample_tensor_ops(s)
    }
}

/// The epsilon of the models' LayerNorms (burn's default), known to [`ModelBackend::row_layer_norm`].
pub const LAYER_NORM_EPSILON: f64 = 1e-5;

/// burn's `Linear`, then ReLU if asked.
fn linear_portable<B: SparseConvBackend, const D: usize>(
    lin: &Linear<B>,
    x: Tensor<B, D>,
    relu: bool,
    bucket: RowBucket,
) -> Tensor<B, D> {
    let y = linear_bucketed(lin, x, bucket);
    if relu {
        burn::tensor::activation::relu(y)
    } else {
        y
    }
}

/// `lin.forward(x)` with `x`'s rows (all axes but the last) padded to `bucket` for the matrix
/// product (see [`RowBucket`]: on the cubecl backends a voxel count as the row count would compile
/// new kernels on later frames); the same values.
///
/// # Shapes
/// - x: `[..., d_in]` -> `[..., d_out]`
pub fn linear_bucketed<B: SparseConvBackend, const D: usize>(
    lin: &Linear<B>,
    x: Tensor<B, D>,
    bucket: RowBucket,
) -> Tensor<B, D> {
    rows_bucketed(x, bucket, |x2| lin.forward(x2))
}

/// `f` applied to `x` seen as rows `[rows, d]` (all axes but the last), the rows padded with zeros
/// to `bucket` and cut back after: for row-wise ops whose kernels a row count can configure (a
/// matrix product's partition; a reduction over each row, whose idle-unit variant follows the
/// number of rows; see [`RowBucket`]). `f` must be row-wise (row `r` of its output depends on
/// row `r` of its input only). Without padding (the CPU backends), `f` gets `x` reshaped.
///
/// # Shapes
/// - x: `[..., d]` -> `[..., d_out]` (`f`: `[rows, d]` -> `[rows, d_out]`)
pub fn rows_bucketed<B: SparseConvBackend, const D: usize>(
    x: Tensor<B, D>,
    bucket: RowBucket,
    f: impl FnOnce(Tensor<B, 2>) -> Tensor<B, 2>,
) -> Tensor<B, D> {
    let dims = x.dims();
    let d_in = dims[D - 1];
    let rows = x.shape().num_elements() / d_in.max(1);
    let y = bucket.map(x.reshape([rows, d_in]), f);
    let mut out = dims;
    out[D - 1] = y.dims()[1];
    y.reshape(out)
}

/// The CPU backend: the host kernels, in inference and (through `Autodiff<NdArray<T>>`) in training.
impl<T: NdElem> ModelBackend for NdArray<T>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    fn conv2d_bn(
        conv: &Conv2d<Self>,
        bn: Option<&BatchNorm<Self>>,
        x: Tensor<Self, 4>,
        apply_relu: bool,
    ) -> Tensor<Self, 4> {
        match conv_bn_host(conv, bn, &x, apply_relu) {
            Some(out) => out,
            None => conv_bn_portable(conv, bn, x, apply_relu),
        }
    }

    fn dca_sample(s: DcaSample<'_, Self>) -> Tensor<Self, 2> {
        dca_host::sample_host(s).unwrap_or_else(dca::sample_tensor_ops)
    }

    fn row_linear<const D: usize>(
        lin: &Linear<Self>,
        x: Tensor<Self, D>,
        relu: bool,
    ) -> Tensor<Self, D> {
        rows_host::linear_host(lin, &x, relu)
            .unwrap_or_else(|| linear_portable(lin, x, relu, Self::ROW_BUCKET))
    }

    fn row_layer_norm<const D: usize>(ln: &LayerNorm<Self>, x: Tensor<Self, D>) -> Tensor<Self, D> {
        rows_host::layer_norm_host(ln, &x, LAYER_NORM_EPSILON).unwrap_or_else(|| ln.forward(x))
    }

    fn row_softmax<const D: usize>(x: Tensor<Self, D>) -> Tensor<Self, D> {
        rows_host::softmax_host(&x).unwrap_or_else(|| softmax(x, D - 1))
    }

    fn conv2d_autodiff<C: CheckpointStrategy>(
        conv: &Conv2d<Autodiff<Self, C>>,
        x: Tensor<Autodiff<Self, C>, 4>,
    ) -> Tensor<Autodiff<Self, C>, 4> {
        conv_autodiff(conv, x.clone()).unwrap_or_else(|| conv_forward_portable(conv, x))
    }

    fn dca_sample_autodiff<C: CheckpointStrategy>(
        s: DcaSample<'_, Autodiff<Self, C>>,
    ) -> Tensor<Autodiff<Self, C>, 2> {
        dca_host::sample_autodiff(s).unwrap_or_else(dca::sample_tensor_ops)
    }
}

/// Training: the inner backend's `*_autodiff` kernels.
impl<B: ModelBackend, C: CheckpointStrategy> ModelBackend for Autodiff<B, C> {
    fn conv2d_bn(
        conv: &Conv2d<Self>,
        bn: Option<&BatchNorm<Self>>,
        x: Tensor<Self, 4>,
        apply_relu: bool,
    ) -> Tensor<Self, 4> {
        bn_relu(B::conv2d_autodiff(conv, x), bn, apply_relu)
    }

    fn dca_sample(s: DcaSample<'_, Self>) -> Tensor<Self, 2> {
        B::dca_sample_autodiff(s)
    }
}

/// The cubecl backends: the image-side convolutions as im2col + matrix product, in training with
/// a col2im backward ([`crate::kernels::conv2d_cube`]; `SPARSEOCC_CUBE_CONV2D=direct` keeps
/// burn's), the DCA
/// sampling as `#[cube]` kernels in inference and training (see
/// [`crate::kernels::dca_cube::CubeDca`]), the rest portable.
#[cfg(feature = "cube")]
macro_rules! cube_model_backend {
    ($runtime:ty, $f:ty, $i:ty, $b:ty) => {
        fn conv2d_bn(
            conv: &Conv2d<Self>,
            bn: Option<&BatchNorm<Self>>,
            x: Tensor<Self, 4>,
            apply_relu: bool,
        ) -> Tensor<Self, 4> {
            use crate::kernels::conv2d_cube::{conv2d, CubeConv2d};
            if CubeConv2d::current() == CubeConv2d::Im2col {
                if let Some(y) = conv2d::<$runtime, $f, $i, $b>(conv, x.clone()) {
                    return bn_relu(y, bn, apply_relu);
                }
            }
            conv_bn_portable(conv, bn, x, apply_relu)
        }

        fn conv2d_autodiff<C: CheckpointStrategy>(
            conv: &Conv2d<Autodiff<Self, C>>,
            x: Tensor<Autodiff<Self, C>, 4>,
        ) -> Tensor<Autodiff<Self, C>, 4> {
            match crate::kernels::conv2d_cube::conv2d_train::<$runtime, $f, $i, $b, C>(conv, x) {
                Ok(y) => y,
                Err(x) => conv_forward_portable(conv, x),
            }
        }

        fn dca_sample(s: DcaSample<'_, Self>) -> Tensor<Self, 2> {
            use crate::kernels::dca_cube::CubeDca;
            if CubeDca::current() != CubeDca::TensorOps {
                crate::kernels::dca_cube::sample::<$runtime, $f, $i, $b>(s)
            } else {
                dca::sample_tensor_ops(s)
            }
        }

        fn dca_sample_autodiff<C: CheckpointStrategy>(
            s: DcaSample<'_, Autodiff<Self, C>>,
        ) -> Tensor<Autodiff<Self, C>, 2> {
            use crate::kernels::dca_cube::CubeDca;
            if CubeDca::current() == CubeDca::InferenceAndTraining {
                crate::kernels::dca_cube::sample_autodiff::<$runtime, $f, $i, $b, C>(s)
            } else {
                dca::sample_tensor_ops(s)
            }
        }
    };
}

/// CUDA: the DCA kernels, otherwise the portable defaults (burn's ops, run by cubecl kernels).
#[cfg(feature = "cuda")]
impl ModelBackend for burn_cuda::Cuda {
    cube_model_backend!(cubecl::cuda::CudaRuntime, f32, i32, u8);
}

/// WebGPU (WGSL; lavapipe on a machine without a GPU): as CUDA.
#[cfg(feature = "wgpu")]
impl ModelBackend for burn_wgpu::Wgpu {
    cube_model_backend!(burn_wgpu::WgpuRuntime, f32, i32, u32);
}
