//! Image-side 2D convolutions (backbone, FPN, LSS depth net) with their inference BatchNorm folded in,
//! computed on the CPU inference backend as im2col + one GEMM per image.
//!
//! burn-ndarray's `conv2d` is a direct convolution: the ResNet-50 + FPN encoder of the SemanticKITTI
//! setting (1280x384) took 11-12 s on this project's 2-core reference machine, against 2.0 s here (the
//! GEMM reaches 35-45 GFLOP/s). The encoder is shared by the three models, so it bounded every
//! end-to-end ratio of the benchmark (issue 8). [`conv_bn`] keeps burn's modules and weights as
//! they are and only changes how the forward pass is computed: it calls the backend's
//! [`ModelBackend::conv2d_bn`], whose burn-ndarray override (inference, [`conv_bn_host`]) folds the BN's `gamma / sqrt(var + eps)` is folded into the convolution
//! weight and its shift into the bias (the standard inference-time fusion), the input is unfolded into
//! a `[C_in·k_h·k_w, H_out·W_out]` matrix (skipped for 1x1 stride-1 convolutions, whose input already
//! is that matrix) and multiplied by the `[C_out, C_in·k_h·k_w]` weight with the host GEMM (`occ_sparse::host::HostFloat::gemm`) on all
//! cores.
//!
//! On the CPU training backend (`Autodiff<NdArray>`) the convolution alone (BatchNorm stays burn's,
//! with batch statistics) is one autodiff op computed the same way, with its backward as two GEMMs
//! and a col2im per image ([`conv_autodiff`]); with the DCA op of [`crate::kernels::dca_host`] it made the
//! demo's training step 3.4x faster. GPU backends take the trait's portable default, burn's own
//! `Conv2d` and `BatchNorm` ([`conv_bn_portable`]).

use crate::kernels::host_data::{from_ad, host_vec, read, to_ad, with_host_slice, Elem, NdElem};
use crate::kernels::ModelBackend;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::{Autodiff, NdArray};
use burn::nn::conv::Conv2d;
use burn::nn::{BatchNorm, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::backend::Backend;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Int, Tensor, TensorData};
use rayon::prelude::*;

/// `relu?(bn?(conv(x)))` — the composition of burn's `Conv2d::forward`, `BatchNorm::forward` and `relu`,
/// computed by the backend's [`ModelBackend::conv2d_bn`] (fused on the CPU inference backend, one
/// autodiff op for the convolution on the CPU training backend; see the module documentation).
///
/// # Shapes
/// - x: `[N, C_in, H, W]`
/// - returns `[N, C_out, H_out, W_out]` (burn's output-size rule)
pub fn conv_bn<B: ModelBackend>(
    conv: &Conv2d<B>,
    bn: Option<&BatchNorm<B>>,
    x: Tensor<B, 4>,
    apply_relu: bool,
) -> Tensor<B, 4> {
    let out = B::conv2d_bn(conv, bn, x, apply_relu);
    if crate::profile::counting() {
        crate::profile::add_conv2d(conv.weight.dims(), out.shape().num_elements());
    }
    out
}

/// [`conv_bn`] with burn's own modules: `Conv2d::forward`, then `BatchNorm::forward`, then `relu`
/// (the portable path, any backend).
pub fn conv_bn_portable<B: occ_sparse::SparseConvBackend>(
    conv: &Conv2d<B>,
    bn: Option<&BatchNorm<B>>,
    x: Tensor<B, 4>,
    apply_relu: bool,
) -> Tensor<B, 4> {
    bn_relu(conv_forward_portable(conv, x), bn, apply_relu)
}

/// `conv.forward(x)` (burn's `Conv2d`), except for a strided 1x1 convolution without padding (the
/// ResNet shortcut's downsampling), which is computed as the subsampled input `x[:, :, ::s_h, ::s_w]`
/// (a `select` of rows and columns) through a stride-1 1x1 convolution: the same values, and a
/// backward that avoids burn-cubecl 0.21's input gradient of strided convolutions. That gradient is
/// a transposed convolution whose direct kernel bounds its loop over input rows by
/// `kernel · dilation − stride`, an empty range when the kernel is smaller than the stride, so a
/// 1x1 stride-2 convolution gets an all-zero input gradient on the cubecl backends (measured with
/// `check-backend`'s `burn_conv2d_1x1_s2_*` cases on lavapipe; docs/gpu.md).
///
/// # Shapes
/// - x: `[N, C_in, H, W]` → `[N, C_out, H_out, W_out]` (burn's output-size rule)
pub fn conv_forward_portable<B: Backend>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [_, _, kh, kw] = conv.weight.dims();
    if kh != 1 || kw != 1 || conv.stride == [1, 1] || padding_of(conv) != Some([0; 4]) {
        return conv.forward(x);
    }
    let device = x.device();
    let every = |x: Tensor<B, 4>, dim: usize, step: usize| {
        let n = x.dims()[dim];
        if step == 1 || n == 0 {
            return x;
        }
        let idx: Vec<i64> = (0..n).step_by(step).map(|i| i as i64).collect();
        let len = idx.len();
        x.select(
            dim,
            Tensor::<B, 1, Int>::from_data(TensorData::new(idx, [len]), &device),
        )
    };
    let x = every(every(x, 2, conv.stride[0]), 3, conv.stride[1]);
    burn::tensor::module::conv2d(
        x,
        conv.weight.val(),
        conv.bias.as_ref().map(|b| b.val()),
        ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
    )
}

/// `relu?(bn?(y))` with burn's `BatchNorm` (its training statistics summed in two levels:
/// [`occ_sparse::norm::batch_norm`]) and `relu`.
pub(crate) fn bn_relu<B: occ_sparse::SparseConvBackend>(
    y: Tensor<B, 4>,
    bn: Option<&BatchNorm<B>>,
    apply_relu: bool,
) -> Tensor<B, 4> {
    let y = match bn {
        Some(bn) => occ_sparse::norm::batch_norm(bn, y),
        None => y,
    };
    if apply_relu {
        relu(y)
    } else {
        y
    }
}

/// The fused host path of [`conv_bn`] on the CPU inference backend (`NdArray<f32 | f64>`): `None`
/// where it does not apply (grouped or non-explicit padding, sizes burn should report, or tensors
/// whose dtype is not the backend's, since burn 0.21 fixes a device's float dtype at the first
/// tensor of the process); [`ModelBackend::conv2d_bn`] then falls back to burn's ops.
///
/// # Shapes
/// - x: `[N, C_in, H, W]`
/// - returns `[N, C_out, H_out, W_out]`
pub fn conv_bn_host<T: NdElem>(
    conv: &Conv2d<NdArray<T>>,
    bn: Option<&BatchNorm<NdArray<T>>>,
    x: &Tensor<NdArray<T>, 4>,
    apply_relu: bool,
) -> Option<Tensor<NdArray<T>, 4>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let pads = padding_of(conv)?;
    let out = host_forward(conv, bn, x, pads, apply_relu)?;
    super::count(|c| c.conv2d += 1);
    Some(out)
}

/// Padding `(top, left, bottom, right)` of an ungrouped convolution with explicit or no padding.
pub(crate) fn padding_of<B: Backend>(conv: &Conv2d<B>) -> Option<[usize; 4]> {
    if conv.groups != 1 {
        return None;
    }
    match conv.padding {
        PaddingConfig2d::Valid => Some([0; 4]),
        PaddingConfig2d::Explicit(t, l, b, r) => Some([t, l, b, r]),
        PaddingConfig2d::Same => None,
    }
}

/// Geometry of one convolution.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Geometry {
    pub(crate) h: usize,
    pub(crate) w: usize,
    pub(crate) kh: usize,
    pub(crate) kw: usize,
    pub(crate) stride: [usize; 2],
    pub(crate) dilation: [usize; 2],
    /// `(top, left)`.
    pub(crate) pad: [usize; 2],
    pub(crate) ho: usize,
    pub(crate) wo: usize,
}

impl Geometry {
    /// The geometry of `conv` on an input of `x_dims` with padding `(top, left, bottom, right)`;
    /// `None` when the sizes do not fit (burn then reports the error).
    pub(crate) fn of<B: Backend>(
        conv: &Conv2d<B>,
        x_dims: [usize; 4],
        [top, left, bottom, right]: [usize; 4],
    ) -> Option<Self> {
        let [_, cin, h, w] = x_dims;
        let [_, wcin, kh, kw] = conv.weight.dims();
        let (stride, dilation) = (conv.stride, conv.dilation);
        let span = |k: usize, d: usize| d * (k - 1) + 1;
        if wcin != cin
            || kh == 0
            || kw == 0
            || h + top + bottom < span(kh, dilation[0])
            || w + left + right < span(kw, dilation[1])
            || stride.contains(&0)
        {
            return None;
        }
        Some(Geometry {
            h,
            w,
            kh,
            kw,
            stride,
            dilation,
            pad: [top, left],
            ho: (h + top + bottom - span(kh, dilation[0])) / stride[0] + 1,
            wo: (w + left + right - span(kw, dilation[1])) / stride[1] + 1,
        })
    }

    /// Scratch for [`Self::unfolded`]: `[C_in·k_h·k_w, H_out·W_out]`, empty for pointwise convolutions.
    fn col_buffer<T: Elem>(&self, cin: usize) -> Vec<T> {
        if self.is_pointwise() {
            Vec::new()
        } else {
            vec![T::zero(); cin * self.kh * self.kw * self.ho * self.wo]
        }
    }

    /// The unfolded image `[C_in·k_h·k_w, H_out·W_out]`: `img` itself for pointwise convolutions,
    /// else written into `col` (from [`Self::col_buffer`]).
    fn unfolded<'a, T: Elem>(&self, img: &'a [T], col: &'a mut [T]) -> &'a [T] {
        if self.is_pointwise() {
            img
        } else {
            self.im2col(img, col);
            col
        }
    }

    /// `dst [C_out, H_out·W_out] = weight [C_out, k] · unfolded(img)`.
    fn gemm_image<T: Elem>(
        &self,
        weight: &[T],
        cout: usize,
        img: &[T],
        col: &mut [T],
        dst: &mut [T],
    ) {
        let hw = self.ho * self.wo;
        let k = weight.len() / cout.max(1);
        let b_mat = self.unfolded(img, col);
        // Checked in release too (once per image): the GEMM below reads and writes through raw pointers.
        assert!(
            weight.len() == cout * k && b_mat.len() == k * hw && dst.len() == cout * hw,
            "conv2d_host: GEMM operand sizes do not match the geometry"
        );
        // SAFETY: weight [cout, k], b_mat [k, hw], dst [cout, hw], all row-major and of those sizes.
        unsafe {
            T::gemm(
                cout,
                k,
                hw,
                weight.as_ptr(),
                k as isize,
                1,
                b_mat.as_ptr(),
                hw as isize,
                1,
                T::zero(),
                dst.as_mut_ptr(),
                hw as isize,
                1,
            );
        }
    }

    /// The adjoint of [`Self::im2col`]: adds `col [C_in·k_h·k_w, H_out·W_out]` back onto the image
    /// `[C_in, H, W]` it was unfolded from.
    fn col2im_add<T: Elem>(&self, col: &[T], img: &mut [T]) {
        let (hw_out, kk) = (self.ho * self.wo, self.kh * self.kw);
        img.par_chunks_mut(self.h * self.w)
            .enumerate()
            .for_each(|(ci, dst)| {
                for ky in 0..self.kh {
                    for kx in 0..self.kw {
                        let src = &col[(ci * kk + ky * self.kw + kx) * hw_out..][..hw_out];
                        let dx = (kx * self.dilation[1]) as isize - self.pad[1] as isize;
                        for oy in 0..self.ho {
                            let iy = (oy * self.stride[0] + ky * self.dilation[0]) as isize
                                - self.pad[0] as isize;
                            if iy < 0 || iy >= self.h as isize {
                                continue;
                            }
                            let line = &mut dst[iy as usize * self.w..(iy as usize + 1) * self.w];
                            for (ox, &v) in src[oy * self.wo..(oy + 1) * self.wo].iter().enumerate()
                            {
                                let ix = (ox * self.stride[1]) as isize + dx;
                                if ix >= 0 && ix < self.w as isize {
                                    line[ix as usize] += v;
                                }
                            }
                        }
                    }
                }
            });
    }

    /// `true` when the input matrix `[C_in, H·W]` already is the unfolded one.
    pub(crate) fn is_pointwise(&self) -> bool {
        self.kh == 1 && self.kw == 1 && self.stride == [1, 1] && self.pad == [0, 0]
    }

    /// Unfold one image `[C_in, H, W]` into `col [C_in·k_h·k_w, H_out·W_out]` (zeros outside).
    fn im2col<T: Elem>(&self, img: &[T], col: &mut [T]) {
        let (hw_out, kk) = (self.ho * self.wo, self.kh * self.kw);
        col.par_chunks_mut(hw_out)
            .enumerate()
            .for_each(|(row, dst)| {
                let (ci, ky, kx) = (row / kk, (row % kk) / self.kw, row % self.kw);
                let src = &img[ci * self.h * self.w..(ci + 1) * self.h * self.w];
                let dx = (kx * self.dilation[1]) as isize - self.pad[1] as isize;
                for oy in 0..self.ho {
                    let iy = (oy * self.stride[0] + ky * self.dilation[0]) as isize
                        - self.pad[0] as isize;
                    let out = &mut dst[oy * self.wo..(oy + 1) * self.wo];
                    if iy < 0 || iy >= self.h as isize {
                        out.fill(T::zero());
                        continue;
                    }
                    let line = &src[iy as usize * self.w..(iy as usize + 1) * self.w];
                    if self.stride[1] == 1 {
                        // Contiguous copy between the zero borders.
                        let lo = (-dx).clamp(0, self.wo as isize) as usize;
                        let hi =
                            (self.w as isize - dx).clamp(lo as isize, self.wo as isize) as usize;
                        out[..lo].fill(T::zero());
                        let start = (lo as isize + dx) as usize;
                        out[lo..hi].copy_from_slice(&line[start..start + (hi - lo)]);
                        out[hi..].fill(T::zero());
                    } else {
                        for (ox, o) in out.iter_mut().enumerate() {
                            let ix = (ox * self.stride[1]) as isize + dx;
                            *o = if ix < 0 || ix >= self.w as isize {
                                T::zero()
                            } else {
                                line[ix as usize]
                            };
                        }
                    }
                }
            });
    }
}

/// The fused host forward; `None` (caller falls back to burn) if a tensor's element type is not `T`.
fn host_forward<T: NdElem>(
    conv: &Conv2d<NdArray<T>>,
    bn: Option<&BatchNorm<NdArray<T>>>,
    x: &Tensor<NdArray<T>, 4>,
    pads: [usize; 4],
    apply_relu: bool,
) -> Option<Tensor<NdArray<T>, 4>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let [n, cin, _, _] = x.dims();
    let [cout, ..] = conv.weight.dims();
    let geo = Geometry::of(conv, x.dims(), pads)?;
    let weight: Vec<T> = read(&conv.weight.val())?;
    let bias: Option<Vec<T>> = match &conv.bias {
        Some(b) => Some(read(&b.val())?),
        None => None,
    };
    let bn = match bn {
        Some(bn) => Some(BnStats {
            gamma: read(&bn.gamma.val())?,
            beta: read(&bn.beta.val())?,
            mean: read(&bn.running_mean.value())?,
            var: read(&bn.running_var.value())?,
            epsilon: bn.epsilon,
        }),
        None => None,
    };
    let (weight, shift) = fold_bn(weight, cout, bias, bn);
    let out = with_host_slice(x, |input: &[T]| {
        fused_forward(&geo, n, cin, cout, &weight, &shift, input, apply_relu)
    })?;
    Some(Tensor::from_data(
        TensorData::new(out, [n, cout, geo.ho, geo.wo]),
        &x.device(),
    ))
}

/// A BatchNorm's affine parameters and inference statistics, per channel.
struct BnStats<T> {
    gamma: Vec<T>,
    beta: Vec<T>,
    mean: Vec<T>,
    var: Vec<T>,
    epsilon: f64,
}

/// The weight `[C_out, k]` with the BN's `gamma / sqrt(var + eps)` folded into its rows, and the
/// per-channel shift `(bias - mean)·scale + beta` (the bias alone without BN); folded in f64.
fn fold_bn<T: Elem>(
    weight: Vec<T>,
    cout: usize,
    bias: Option<Vec<T>>,
    bn: Option<BnStats<T>>,
) -> (Vec<T>, Vec<T>) {
    let bias: Vec<f64> = match bias {
        Some(b) => b.iter().map(|v| v.to_f64()).collect(),
        None => vec![0.0; cout],
    };
    let (scale, shift) = match bn {
        Some(BnStats {
            gamma: g,
            beta: b,
            mean: m,
            var: v,
            epsilon,
        }) => {
            let scale: Vec<f64> = (0..cout)
                .map(|o| g[o].to_f64() / (v[o].to_f64() + epsilon).sqrt())
                .collect();
            let shift = (0..cout)
                .map(|o| (bias[o] - m[o].to_f64()) * scale[o] + b[o].to_f64())
                .collect();
            (Some(scale), shift)
        }
        None => (None, bias),
    };
    let k = weight.len() / cout.max(1);
    let weight: Vec<T> = match &scale {
        Some(s) => weight
            .chunks(k)
            .zip(s)
            .flat_map(|(row, &s)| row.iter().map(move |&v| T::from_f64(v.to_f64() * s)))
            .collect(),
        None => weight,
    };
    (weight, shift.into_iter().map(T::from_f64).collect())
}

/// `relu?(weight · unfolded(x_n) + shift)` per image of `input [N, C_in, H, W]`:
/// `[N, C_out, H_out·W_out]`.
#[allow(clippy::too_many_arguments)]
fn fused_forward<T: Elem>(
    geo: &Geometry,
    n: usize,
    cin: usize,
    cout: usize,
    weight: &[T],
    shift: &[T],
    input: &[T],
    apply_relu: bool,
) -> Vec<T> {
    let hw_out = geo.ho * geo.wo;
    let mut out = vec![T::zero(); n * cout * hw_out];
    let mut col = geo.col_buffer::<T>(cin);
    for (img, dst) in input
        .chunks(cin * geo.h * geo.w)
        .zip(out.chunks_mut(cout * hw_out))
    {
        geo.gemm_image(weight, cout, img, &mut col, dst);
        dst.par_chunks_mut(hw_out)
            .zip(shift.par_iter())
            .for_each(|(row, &s)| {
                for v in row.iter_mut() {
                    let y = *v + s;
                    *v = if apply_relu && y < T::zero() {
                        T::zero()
                    } else {
                        y
                    };
                }
            });
    }
    out
}

/// `conv.forward(x)` on the CPU training backend (`Autodiff<NdArray<f32 | f64>>`) as one autodiff
/// op computed like the inference path: im2col + GEMM forward; backward `dW = Σ_n dY_n · col_nᵀ`,
/// `db = Σ dY`, `dX_n = col2im(Wᵀ · dY_n)` (burn-ndarray's own `conv2d` and its backward are direct
/// loops). `None` for grouped or `Same`-padded convolutions, sizes burn should report, or tensors
/// whose element type is not the backend's (burn 0.21 fixes a device's float dtype at the first
/// tensor of the process); [`ModelBackend::conv2d_autodiff`] then falls back to `Conv2d::forward`.
pub fn conv_autodiff<T: NdElem, C: CheckpointStrategy>(
    conv: &Conv2d<Autodiff<NdArray<T>, C>>,
    x: Tensor<Autodiff<NdArray<T>, C>, 4>,
) -> Option<Tensor<Autodiff<NdArray<T>, C>, 4>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    use burn::backend::autodiff::ops::{Backward, OpsKind};
    use burn::tensor::ops::FloatTensorOps;
    let pads = padding_of(conv)?;
    let geo = Geometry::of(conv, x.dims(), pads)?;
    let [n, cin, _, _] = x.dims();
    let [cout, ..] = conv.weight.dims();
    let bias = match &conv.bias {
        Some(b) => b.val(),
        None => Tensor::zeros([cout], &x.device()),
    };
    let x = to_ad(x);
    let weight = to_ad(conv.weight.val());
    let bias = to_ad(bias);
    let saved = ConvSaved {
        geo,
        n,
        cin,
        cout,
        x: host_vec(&x.primitive)?,
        weight: host_vec(&weight.primitive)?,
    };
    let out = saved.forward(&host_vec::<T>(&bias.primitive)?);
    let out = NdArray::<T>::float_from_data(
        TensorData::new(out, [n, cout, geo.ho, geo.wo]),
        &Default::default(),
    );
    let nodes = [x.node.clone(), weight.node.clone(), bias.node.clone()];
    let result = match ConvBackward.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => prep.finish(std::sync::Arc::new(saved), out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    super::count(|c| c.conv2d_autodiff += 1);
    Some(from_ad(result))
}

/// What the backward pass of [`conv_autodiff`] needs.
#[derive(Debug)]
struct ConvSaved<T> {
    geo: Geometry,
    n: usize,
    cin: usize,
    cout: usize,
    x: Vec<T>,
    weight: Vec<T>,
}

impl<T: Elem> ConvSaved<T> {
    fn k(&self) -> usize {
        self.cin * self.geo.kh * self.geo.kw
    }

    /// `[C_out, H_out·W_out]` per image: `W · col(x_n) + bias`.
    fn forward(&self, bias: &[T]) -> Vec<T> {
        let (geo, hw) = (&self.geo, self.geo.ho * self.geo.wo);
        let mut out = vec![T::zero(); self.n * self.cout * hw];
        let mut col = geo.col_buffer::<T>(self.cin);
        let img_len = self.cin * geo.h * geo.w;
        for (img, dst) in self.x.chunks(img_len).zip(out.chunks_mut(self.cout * hw)) {
            geo.gemm_image(&self.weight, self.cout, img, &mut col, dst);
            dst.par_chunks_mut(hw)
                .zip(bias.par_iter())
                .for_each(|(row, &b)| row.iter_mut().for_each(|v| *v += b));
        }
        out
    }

    /// `(dX, dW, db)` for the output gradient `dy [N, C_out, H_out·W_out]`.
    fn backward(&self, dy: &[T]) -> (Vec<T>, Vec<T>, Vec<T>) {
        let (geo, k, hw) = (&self.geo, self.k(), self.geo.ho * self.geo.wo);
        let img_len = self.cin * geo.h * geo.w;
        let mut dx = vec![T::zero(); self.n * img_len];
        let mut dw = vec![T::zero(); self.cout * k];
        let mut db = vec![T::zero(); self.cout];
        let mut col = geo.col_buffer::<T>(self.cin);
        let mut dcol = geo.col_buffer::<T>(self.cin);
        for ((img, dyn_), dxn) in self
            .x
            .chunks(img_len)
            .zip(dy.chunks(self.cout * hw))
            .zip(dx.chunks_mut(img_len))
        {
            for (b, row) in db.iter_mut().zip(dyn_.chunks(hw)) {
                for &v in row {
                    *b += v;
                }
            }
            let b_mat = geo.unfolded(img, &mut col);
            let dcol_out: &mut [T] = if geo.is_pointwise() {
                &mut dxn[..]
            } else {
                &mut dcol[..]
            };
            // SAFETY: dy_n [cout, hw]; b_mat read as its transpose [hw, k]; dw [cout, k];
            // weight read as its transpose [k, cout]; dcol_out [k, hw]; all row-major buffers.
            unsafe {
                T::gemm(
                    self.cout,
                    hw,
                    k,
                    dyn_.as_ptr(),
                    hw as isize,
                    1,
                    b_mat.as_ptr(),
                    1,
                    hw as isize,
                    T::one(),
                    dw.as_mut_ptr(),
                    k as isize,
                    1,
                );
                T::gemm(
                    k,
                    self.cout,
                    hw,
                    self.weight.as_ptr(),
                    1,
                    k as isize,
                    dyn_.as_ptr(),
                    hw as isize,
                    1,
                    T::zero(),
                    dcol_out.as_mut_ptr(),
                    hw as isize,
                    1,
                );
            }
            if !geo.is_pointwise() {
                geo.col2im_add(&dcol, dxn);
            }
        }
        (dx, dw, db)
    }
}

/// The backward step of [`conv_autodiff`].
#[derive(Debug)]
struct ConvBackward;

impl<T: NdElem> burn::backend::autodiff::ops::Backward<NdArray<T>, 3> for ConvBackward
where
    NdArrayTensor: From<SharedArray<T>>,
{
    type State = std::sync::Arc<ConvSaved<T>>;

    fn backward(
        self,
        ops: burn::backend::autodiff::ops::Ops<Self::State, 3>,
        grads: &mut burn::backend::autodiff::grads::Gradients,
        _checkpointer: &mut burn::backend::autodiff::checkpoint::base::Checkpointer,
    ) {
        use burn::backend::NdArray;
        use burn::tensor::ops::FloatTensorOps;
        let burn::backend::autodiff::ops::Ops {
            parents,
            node,
            state: saved,
        } = ops;
        let dy = grads.consume::<NdArray<T>>(&node);
        let dy: Vec<T> = host_vec(&dy).expect("the output gradient of an NdArray<T> op");
        let (dx, dw, db) = saved.backward(&dy);
        let g = &saved.geo;
        let outs = [
            (dx, vec![saved.n, saved.cin, g.h, g.w]),
            (dw, vec![saved.cout, saved.cin, g.kh, g.kw]),
            (db, vec![saved.cout]),
        ];
        for (parent, (v, shape)) in parents.into_iter().zip(outs) {
            if let Some(parent) = parent {
                let t =
                    NdArray::<T>::float_from_data(TensorData::new(v, shape), &Default::default());
                grads.register::<NdArray<T>>(parent.id, t);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Param;
    use burn::nn::conv::Conv2dConfig;

    type Ad = Autodiff<NdArray<f32>>;

    /// [`conv_forward_portable`]'s strided 1x1 path against burn's `Conv2d` on NdArray (whose
    /// backward is right on the CPU): forward and the gradients of input, weight and bias, at even
    /// and odd sizes and unequal strides.
    #[test]
    fn strided_pointwise_conv_matches_burn_forward_and_backward() {
        let device = Default::default();
        let seq = |n: usize, a: f32| -> Vec<f32> {
            (0..n)
                .map(|i| ((i as f32 * a).sin() * 5.0).round() / 8.0)
                .collect()
        };
        for (h, w, stride) in [
            (8usize, 6usize, [2usize, 2usize]),
            (7, 9, [2, 2]),
            (7, 10, [2, 3]),
        ] {
            let run = |ours: bool| {
                let mut conv = Conv2dConfig::new([3, 4], [1, 1])
                    .with_stride(stride)
                    .init::<Ad>(&device);
                conv.weight = Param::from_tensor(Tensor::from_data(
                    TensorData::new(seq(12, 0.9), [4, 3, 1, 1]),
                    &device,
                ));
                conv.bias = Some(Param::from_tensor(Tensor::from_data(
                    TensorData::new(seq(4, 1.7), [4]),
                    &device,
                )));
                let x = Tensor::<Ad, 4>::from_data(
                    TensorData::new(seq(2 * 3 * h * w, 0.3), [2, 3, h, w]),
                    &device,
                )
                .require_grad();
                let y = if ours {
                    conv_forward_portable(&conv, x.clone())
                } else {
                    conv.forward(x.clone())
                };
                let r = Tensor::<Ad, 4>::from_data(
                    TensorData::new(seq(y.shape().num_elements(), 1.1), y.dims()),
                    &device,
                );
                let grads = (y.clone() * r).sum().backward();
                let v = |t: Option<Tensor<NdArray<f32>, 4>>| {
                    t.unwrap().into_data().to_vec::<f32>().unwrap()
                };
                (
                    y.into_data().to_vec::<f32>().unwrap(),
                    v(x.grad(&grads)),
                    v(conv.weight.val().grad(&grads)),
                    conv.bias
                        .as_ref()
                        .unwrap()
                        .val()
                        .grad(&grads)
                        .unwrap()
                        .into_data()
                        .to_vec::<f32>()
                        .unwrap(),
                )
            };
            let (a, b) = (run(true), run(false));
            let close = |p: &[f32], q: &[f32], what: &str| {
                assert_eq!(p.len(), q.len(), "{what} {h}x{w} {stride:?}");
                for (u, v) in p.iter().zip(q) {
                    assert!(
                        (u - v).abs() < 1e-5,
                        "{what} {h}x{w} {stride:?}: {u} vs {v}"
                    );
                }
            };
            close(&a.0, &b.0, "forward");
            close(&a.1, &b.1, "dx");
            close(&a.2, &b.2, "dw");
            close(&a.3, &b.3, "db");
        }
    }
}
