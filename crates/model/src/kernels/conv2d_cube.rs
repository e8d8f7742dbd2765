//! The image encoder's convolutions on the cubecl backends, in inference and training, as an
//! im2col `#[cube]` kernel and cubecl's matrix product; in training their backward as matrix
//! products and a col2im `#[cube]` kernel.
//!
//! burn-cubecl 0.21 computes `conv2d` with its direct kernel when autotune is off (this project's
//! build: docs/gpu.md), one output value per unit looping over `C_in · k_h · k_w` products, and its
//! `unfold4d` is that same convolution with an identity weight. Here [`kernel::im2col_kernel`]
//! writes the unfolded input `[C_in·k_h·k_w, N·L]` (`L = H_out·W_out` output positions, in
//! column blocks of at most [`MAX_COLS_ELEMS`] values), one unit per value, and the convolution is
//! one matrix product `[C_out, C_in·k_h·k_w] x [C_in·k_h·k_w, N·L]`: cubecl's tiled matmul,
//! tensor cores where the device has them. A pointwise stride-1 convolution needs no
//! unfolding (its input already is that matrix). Every size is a runtime value, so the kernel
//! compiles once.
//!
//! In training ([`conv2d_train`], [`crate::kernels::ModelBackend::conv2d_autodiff`]) the
//! convolution is one autodiff op with the same forward; its backward is `dW = dY · colᵀ` and
//! `dX = col2im(Wᵀ · dY)` per column block (the unfolding recomputed from the saved input, not
//! kept) and `db` as blocked column sums. [`kernel::col2im_kernel`] sums, for every input value,
//! the taps that read it, in a fixed order (no atomics). burn-cubecl 0.21's own backward without
//! autotune runs its direct kernel as the weight gradient (one unit per weight value, looping
//! over all output positions) and gets the input gradient of strided 1x1 convolutions wrong.
//! `SPARSEOCC_CUBE_CONV2D=direct` keeps burn's convolution in inference and training (the peer on
//! a GPU).

use crate::kernels::conv2d_host::{padding_of, Geometry};
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::Autodiff;
use burn::nn::conv::Conv2d;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Shape, Tensor, TensorPrimitive};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{BoolElement, CubeBackend, CubeRuntime, FloatElement, IntElement};
use burn_fusion::{Fusion, FusionTensor};
use cubecl::prelude::AddressType;
use cubecl::{calculate_cube_count_elemwise, CubeCount, CubeDim};
use occ_sparse::cube::{address_type_of, inputs_of, register_one};

mod kernel {
    use cubecl::prelude::*;

    /// Sizes of one unfolding (all runtime values).
    #[derive(CubeLaunch, CubeType)]
    pub struct Im2colDims {
        /// Images, input channels, height, width.
        pub n: usize,
        pub c: usize,
        pub h: usize,
        pub w: usize,
        /// Kernel, stride, padding (top, left) and dilation per axis (y, x).
        pub kh: usize,
        pub kw: usize,
        pub sh: usize,
        pub sw: usize,
        pub ph: usize,
        pub pw: usize,
        pub dh: usize,
        pub dw: usize,
        /// Output height and width.
        pub ho: usize,
        pub wo: usize,
        /// First output position of the column block, and its length.
        pub l0: usize,
        pub lc: usize,
    }

    /// `cols[(c·k_h + ky)·k_w + kx, n, l] = x[n, c, oy·s_h - p_h + ky·d_h, ox·s_w - p_w + kx·d_w]`
    /// (0 off the image) for the output positions `l0 + l = oy · W_out + ox` of the block. One unit
    /// per value; adjacent units write adjacent positions.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub fn im2col_kernel<F: Float>(
        x: &Tensor<F>,
        cols: &mut Tensor<F>,
        dims: &Im2colDims,
        #[define(F)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= cols.len() {
            terminate!();
        }
        let l = ABSOLUTE_POS % dims.lc;
        let rest = ABSOLUTE_POS / dims.lc;
        let n = rest % dims.n;
        let row = rest / dims.n;
        let taps = dims.kh * dims.kw;
        let c = row / taps;
        let ky = (row / dims.kw) % dims.kh;
        let kx = row % dims.kw;
        let p = dims.l0 + l;
        let oy = p / dims.wo;
        let ox = p % dims.wo;
        let iy = i32::cast_from(oy * dims.sh + ky * dims.dh) - i32::cast_from(dims.ph);
        let ix = i32::cast_from(ox * dims.sw + kx * dims.dw) - i32::cast_from(dims.pw);
        let inside =
            iy >= 0 && ix >= 0 && iy < i32::cast_from(dims.h) && ix < i32::cast_from(dims.w);
        let mut v = F::from_int(0);
        if inside {
            let at =
                ((n * dims.c + c) * dims.h + usize::cast_from(iy)) * dims.w + usize::cast_from(ix);
            v = x[at];
        }
        cols[ABSOLUTE_POS] = v;
    }

    /// The adjoint of [`im2col_kernel`] over one column block: `dx[n, c, iy, ix]` is the sum of
    /// `dcols[(c·k_h + ky)·k_w + kx, n, l]` over the taps `(ky, kx)` whose output position
    /// `l0 + l = oy · W_out + ox` lies in the block and reads that input value
    /// (`iy = oy·s_h - p_h + ky·d_h`, same in x). One unit per input value, taps in a fixed order:
    /// no atomics, the same sums every run.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub fn col2im_kernel<F: Float>(
        dcols: &Tensor<F>,
        dx: &mut Tensor<F>,
        dims: &Im2colDims,
        #[define(F)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= dx.len() {
            terminate!();
        }
        let ix = ABSOLUTE_POS % dims.w;
        let iy = (ABSOLUTE_POS / dims.w) % dims.h;
        let c = (ABSOLUTE_POS / (dims.w * dims.h)) % dims.c;
        let n = ABSOLUTE_POS / (dims.w * dims.h * dims.c);
        let width = dims.n * dims.lc;
        let mut acc = F::from_int(0);
        for ky in 0..dims.kh {
            let ty = i32::cast_from(iy + dims.ph) - i32::cast_from(ky * dims.dh);
            let sh = i32::cast_from(dims.sh);
            if ty >= 0 && ty % sh == 0 && ty / sh < i32::cast_from(dims.ho) {
                let oy = usize::cast_from(ty / sh);
                for kx in 0..dims.kw {
                    let tx = i32::cast_from(ix + dims.pw) - i32::cast_from(kx * dims.dw);
                    let sw = i32::cast_from(dims.sw);
                    if tx >= 0 && tx % sw == 0 && tx / sw < i32::cast_from(dims.wo) {
                        let p = oy * dims.wo + usize::cast_from(tx / sw);
                        if p >= dims.l0 && p < dims.l0 + dims.lc {
                            let row = (c * dims.kh + ky) * dims.kw + kx;
                            acc += dcols[row * width + n * dims.lc + (p - dims.l0)];
                        }
                    }
                }
            }
        }
        dx[ABSOLUTE_POS] = acc;
    }
}

/// Most values of one unfolded column block (128 MiB of f32: WebGPU's default largest storage
/// binding); a larger unfolding runs block by block.
pub const MAX_COLS_ELEMS: usize = 1 << 25;

occ_sparse::env_switch! {
    /// How the cubecl backends compute the image encoder's convolutions.
    pub enum CubeConv2d: "SPARSEOCC_CUBE_CONV2D" {
        /// `im2col` (the default): [`kernel::im2col_kernel`] and cubecl's matrix product; in
        /// training [`conv2d_train`].
        Im2col = "im2col",
        /// `direct`: burn's `conv2d` and its backward (burn-cubecl's direct kernels without
        /// autotune; a strided 1x1 convolution in training as a subsampling and a stride-1 one).
        Direct = "direct",
    }
}

/// A fused cubecl backend.
type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;

/// An output of `shape` in `input`'s dtype on its device, and the launch of one unit per output
/// value (cube count, cube size, address type over both tensors).
fn one_unit_per_value<R: CubeRuntime, const D: usize>(
    input: &CubeTensor<R>,
    shape: [usize; D],
) -> (CubeTensor<R>, CubeCount, CubeDim, AddressType) {
    let units = shape.iter().product();
    let out = empty_device_dtype(
        input.client.clone(),
        input.device.clone(),
        Shape::new(shape),
        input.dtype,
    );
    let dim = CubeDim::new(&input.client, units);
    let count = calculate_cube_count_elemwise(&input.client, units, dim);
    let address = address_type_of(&[input, &out]);
    (out, count, dim, address)
}
type FusedTensor<R> = FusionTensor<FusionCubeRuntime<R>>;

/// One unfolding's geometry on the host.
#[derive(Clone, Copy, Debug)]
struct Unfold {
    n: usize,
    c: usize,
    g: Geometry,
}

impl Unfold {
    fn rows(self) -> usize {
        self.c * self.g.kh * self.g.kw
    }

    fn positions(self) -> usize {
        self.g.ho * self.g.wo
    }

    /// Output positions per column block (at most [`MAX_COLS_ELEMS`] values a block).
    fn block(self) -> usize {
        (MAX_COLS_ELEMS / (self.n * self.rows()).max(1)).clamp(1, self.positions().max(1))
    }

    /// The column blocks `(l0, lc)`.
    fn blocks(self) -> impl Iterator<Item = (usize, usize)> {
        let (positions, block) = (self.positions(), self.block());
        (0..positions)
            .step_by(block)
            .map(move |l0| (l0, block.min(positions - l0)))
    }

    fn dims<R: CubeRuntime>(self, l0: usize, lc: usize) -> kernel::Im2colDimsLaunch<R> {
        let g = self.g;
        kernel::Im2colDimsLaunch::new(
            self.n,
            self.c,
            g.h,
            g.w,
            g.kh,
            g.kw,
            g.stride[0],
            g.stride[1],
            g.pad[0],
            g.pad[1],
            g.dilation[0],
            g.dilation[1],
            g.ho,
            g.wo,
            l0,
            lc,
        )
    }

    fn launch<R: CubeRuntime>(self, x: CubeTensor<R>, l0: usize, lc: usize) -> CubeTensor<R> {
        let x = into_contiguous(x);
        let (cols, count, dim, address) = one_unit_per_value(&x, [self.rows(), self.n * lc]);
        let client = x.client.clone();
        let dims = self.dims(l0, lc);
        let dtype = x.dtype;
        // SAFETY: an input value is read only at `(n, c, iy, ix)` inside the image (checked), and
        // the output position is bounds-checked.
        unsafe {
            kernel::im2col_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                x.into_tensor_arg(),
                cols.clone().into_tensor_arg(),
                dims,
                dtype.into(),
            )
        };
        cols
    }

    /// [`kernel::col2im_kernel`]: the input gradient `[N, C, H, W]` of one column block's
    /// `dcols [C·k_h·k_w, N·lc]`.
    fn launch_col2im<R: CubeRuntime>(
        self,
        dcols: CubeTensor<R>,
        l0: usize,
        lc: usize,
    ) -> CubeTensor<R> {
        let dcols = into_contiguous(dcols);
        let shape = [self.n, self.c, self.g.h, self.g.w];
        let (dx, count, dim, address) = one_unit_per_value(&dcols, shape);
        let client = dcols.client.clone();
        let dims = self.dims(l0, lc);
        let dtype = dcols.dtype;
        // SAFETY: `dcols` is read at `row < C·k_h·k_w`, `n < N`, `p - l0 < lc` (checked), inside
        // its `[C·k_h·k_w, N·lc]`; the output position is bounds-checked.
        unsafe {
            kernel::col2im_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                dcols.into_tensor_arg(),
                dx.clone().into_tensor_arg(),
                dims,
                dtype.into(),
            )
        };
        dx
    }

    /// One column block of the unfolded input as a fusion op: `[C·k_h·k_w, N·lc]`.
    fn cols<R, F, I, BT>(
        self,
        x: &FusedTensor<R>,
        l0: usize,
        lc: usize,
    ) -> Tensor<Fused<R, F, I, BT>, 2>
    where
        R: CubeRuntime,
        F: FloatElement,
        I: IntElement,
        BT: BoolElement,
    {
        let shape = Shape::new([self.rows(), self.n * lc]);
        let cols =
            register_one::<R, F, I, BT>("occ_model::im2col", vec![x.clone()], shape, move |t| {
                let [x] = inputs_of(t);
                self.launch(x, l0, lc)
            });
        Tensor::from_primitive(TensorPrimitive::Float(cols))
    }

    /// The input gradient of one column block as a fusion op: `[N, C, H, W]`.
    fn col2im<R, F, I, BT>(
        self,
        dcols: Tensor<Fused<R, F, I, BT>, 2>,
        l0: usize,
        lc: usize,
    ) -> Tensor<Fused<R, F, I, BT>, 4>
    where
        R: CubeRuntime,
        F: FloatElement,
        I: IntElement,
        BT: BoolElement,
    {
        let shape = Shape::new([self.n, self.c, self.g.h, self.g.w]);
        let dcols = vec![dcols.into_primitive().tensor()];
        let dx = register_one::<R, F, I, BT>("occ_model::col2im", dcols, shape, move |t| {
            let [dcols] = inputs_of(t);
            self.launch_col2im(dcols, l0, lc)
        });
        Tensor::from_primitive(TensorPrimitive::Float(dx))
    }

    /// `W · col(x) (+ bias)`: the convolution with weight `[C_out, C·k_h·k_w]`.
    ///
    /// # Shapes
    /// - x: `[N, C, H, W]` -> `[N, C_out, H_out, W_out]`
    fn forward<R, F, I, BT>(
        self,
        x: Tensor<Fused<R, F, I, BT>, 4>,
        weight: Tensor<Fused<R, F, I, BT>, 2>,
        bias: Option<Tensor<Fused<R, F, I, BT>, 1>>,
    ) -> Tensor<Fused<R, F, I, BT>, 4>
    where
        R: CubeRuntime,
        F: FloatElement,
        I: IntElement,
        BT: BoolElement,
    {
        let (n, c, g) = (self.n, self.c, self.g);
        let cout = weight.dims()[0];
        let positions = self.positions();
        // `[C_out, N, L]`, in column blocks.
        // With one image, `[N, C, L]` and `[C, N, L]` are the same memory: a reshape, where the
        // swap of the first two axes would copy the tensor (a launch and a pass over it).
        let y = if g.is_pointwise() {
            let x = match n {
                1 => x.reshape([c, positions]),
                _ => x
                    .reshape([n, c, positions])
                    .swap_dims(0, 1)
                    .reshape([c, n * positions]),
            };
            weight.matmul(x).reshape([cout, n, positions])
        } else {
            let x = x.into_primitive().tensor();
            let mut parts: Vec<_> = self
                .blocks()
                .map(|(l0, lc)| {
                    let cols = self.cols::<R, F, I, BT>(&x, l0, lc);
                    weight.clone().matmul(cols).reshape([cout, n, lc])
                })
                .collect();
            // One block (the common case) needs no concatenation: a cat of one tensor would
            // still copy it (a launch and a pass over the output).
            match parts.len() {
                1 => parts.pop().expect("one block"),
                _ => Tensor::cat(parts, 2),
            }
        };
        let y = match n {
            1 => y.reshape([n, cout, g.ho, g.wo]),
            _ => y.swap_dims(0, 1).reshape([n, cout, g.ho, g.wo]),
        };
        match bias {
            Some(b) => y + b.reshape([1, cout, 1, 1]),
            None => y,
        }
    }

    /// `(dX, dW, db)` of [`Self::forward`] for the output gradient `dy`: `dW = Σ_blocks dY · colᵀ`,
    /// `dX = Σ_blocks col2im(Wᵀ · dY)` (only when `need_dx`), `db = Σ dY`.
    ///
    /// # Shapes
    /// - x: `[N, C, H, W]`, weight: `[C_out, C·k_h·k_w]`, dy: `[N, C_out, H_out, W_out]`
    ///   -> (`[N, C, H, W]`, `[C_out, C·k_h·k_w]`, `[C_out]`)
    #[allow(clippy::type_complexity)]
    fn backward<R, F, I, BT>(
        self,
        x: Tensor<Fused<R, F, I, BT>, 4>,
        weight: Tensor<Fused<R, F, I, BT>, 2>,
        dy: Tensor<Fused<R, F, I, BT>, 4>,
        need_dx: bool,
    ) -> (
        Option<Tensor<Fused<R, F, I, BT>, 4>>,
        Tensor<Fused<R, F, I, BT>, 2>,
        Tensor<Fused<R, F, I, BT>, 1>,
    )
    where
        R: CubeRuntime,
        F: FloatElement,
        I: IntElement,
        BT: BoolElement,
    {
        let (n, c, g) = (self.n, self.c, self.g);
        let cout = weight.dims()[0];
        let positions = self.positions();
        // `[C_out, N, L]`.
        let dy = dy.reshape([n, cout, positions]).swap_dims(0, 1);
        // The bias gradient as column sums over the `N·L` positions (a long axis: occ_sparse's
        // blocked sums, not one unit a column, padded in one kernel).
        let db = occ_sparse::rows::sum_rows_padded_with(
            dy.clone().swap_dims(0, 2).reshape([positions * n, cout]),
            occ_sparse::cube::fusion_pad_rows::<R, F, I, BT>,
        )
        .reshape([cout]);
        let wt = weight.clone().transpose();
        if g.is_pointwise() {
            let dy = dy.reshape([cout, n * positions]);
            let xm = x
                .reshape([n, c, positions])
                .swap_dims(0, 1)
                .reshape([c, n * positions]);
            let dw = dy.clone().matmul(xm.transpose());
            let dx = need_dx.then(|| {
                wt.matmul(dy)
                    .reshape([c, n, positions])
                    .swap_dims(0, 1)
                    .reshape([n, c, g.h, g.w])
            });
            return (dx, dw, db);
        }
        let x = x.into_primitive().tensor();
        let (mut dx, mut dw) = (None::<Tensor<Fused<R, F, I, BT>, 4>>, None);
        for (l0, lc) in self.blocks() {
            let dyb = dy.clone().narrow(2, l0, lc).reshape([cout, n * lc]);
            let cols = self.cols::<R, F, I, BT>(&x, l0, lc);
            let part = dyb.clone().matmul(cols.transpose());
            dw = Some(match dw {
                Some(d) => d + part,
                None => part,
            });
            if need_dx {
                let part = self.col2im(wt.clone().matmul(dyb), l0, lc);
                dx = Some(match dx {
                    Some(d) => d + part,
                    None => part,
                });
            }
        }
        let dw = dw.unwrap_or_else(|| weight.zeros_like());
        (dx, dw, db)
    }
}

/// `conv.forward(x)` as im2col + matrix product on a fused cubecl backend; `None` where it does
/// not apply (grouped or `Same`-padded convolutions, no image, sizes burn should report), and the
/// caller runs burn's convolution.
///
/// # Shapes
/// - x: `[N, C_in, H, W]` -> `[N, C_out, H_out, W_out]`
pub fn conv2d<R, F, I, BT>(
    conv: &Conv2d<Fused<R, F, I, BT>>,
    x: Tensor<Fused<R, F, I, BT>, 4>,
) -> Option<Tensor<Fused<R, F, I, BT>, 4>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    let [n, c, _, _] = x.dims();
    if n == 0 {
        return None;
    }
    let g = Geometry::of(conv, x.dims(), padding_of(conv)?)?;
    let cout = conv.weight.dims()[0];
    let weight = conv.weight.val().reshape([cout, c * g.kh * g.kw]);
    Some(Unfold { n, c, g }.forward(x, weight, conv.bias.as_ref().map(|b| b.val())))
}

/// An autodiff backend over a fused cubecl backend.
type Ad<R, F, I, BT, C> = Autodiff<Fused<R, F, I, BT>, C>;

/// `conv.forward(x)` in training on a fused cubecl backend, as one autodiff op computed like
/// inference (im2col + matrix product) whose backward is matrix products and the col2im
/// `#[cube]` kernel ([`Unfold::backward`]); burn-cubecl 0.21's own backward without autotune is its
/// direct convolution kernel run as a weight gradient (one unit per weight value, looping over
/// every output position) and a direct transposed convolution. `Err(x)` where it does not apply
/// (as [`conv2d`], or `SPARSEOCC_CUBE_CONV2D=direct`): the caller runs burn's.
///
/// # Shapes
/// - x: `[N, C_in, H, W]` -> `[N, C_out, H_out, W_out]`
#[allow(clippy::result_large_err, clippy::type_complexity)]
pub fn conv2d_train<R, F, I, BT, C>(
    conv: &Conv2d<Ad<R, F, I, BT, C>>,
    x: Tensor<Ad<R, F, I, BT, C>, 4>,
) -> Result<Tensor<Ad<R, F, I, BT, C>, 4>, Tensor<Ad<R, F, I, BT, C>, 4>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
    C: CheckpointStrategy,
{
    let [n, c, _, _] = x.dims();
    let geometry = padding_of(conv).and_then(|p| Geometry::of(conv, x.dims(), p));
    let (Some(g), true) = (
        geometry,
        n > 0 && CubeConv2d::current() == CubeConv2d::Im2col,
    ) else {
        return Err(x);
    };
    let unfold = Unfold { n, c, g };
    let cout = conv.weight.dims()[0];
    let device = x.device();
    let bias = match &conv.bias {
        Some(b) => b.val(),
        None => Tensor::zeros([cout], &device),
    };
    let weight = conv.weight.val().reshape([cout, unfold.rows()]);
    let (x, weight, bias) = (
        x.into_primitive().tensor(),
        weight.into_primitive().tensor(),
        bias.into_primitive().tensor(),
    );
    let inner = |t: &FusedTensor<R>| t.clone();
    let y = unfold.forward::<R, F, I, BT>(
        Tensor::from_primitive(TensorPrimitive::Float(inner(&x.primitive))),
        Tensor::from_primitive(TensorPrimitive::Float(inner(&weight.primitive))),
        Some(Tensor::from_primitive(TensorPrimitive::Float(inner(
            &bias.primitive,
        )))),
    );
    let y = y.into_primitive().tensor();
    let nodes = [x.node.clone(), weight.node.clone(), bias.node.clone()];
    let out: FloatTensor<Ad<R, F, I, BT, C>> = match Conv2dIm2colBackward
        .prepare::<C>(nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(
            ConvSaved {
                x: x.primitive,
                weight: weight.primitive,
                unfold,
            },
            y,
        ),
        OpsKind::UnTracked(prep) => prep.finish(y),
    };
    Ok(Tensor::from_primitive(TensorPrimitive::Float(out)))
}

/// What the backward of [`conv2d_train`] keeps: the input and the weight matrix.
#[derive(Debug)]
struct ConvSaved<R: CubeRuntime> {
    x: FusedTensor<R>,
    weight: FusedTensor<R>,
    unfold: Unfold,
}

impl<R: CubeRuntime> Clone for ConvSaved<R> {
    fn clone(&self) -> Self {
        Self {
            x: self.x.clone(),
            weight: self.weight.clone(),
            unfold: self.unfold,
        }
    }
}

/// The backward step of [`conv2d_train`].
#[derive(Debug)]
struct Conv2dIm2colBackward;

impl<R, F, I, BT> Backward<Fused<R, F, I, BT>, 3> for Conv2dIm2colBackward
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type State = ConvSaved<R>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let Ops {
            parents: [px, pw, pb],
            node,
            state: ConvSaved { x, weight, unfold },
        } = ops;
        let dy = grads.consume::<Fused<R, F, I, BT>>(&node);
        let wrap4 = |t| Tensor::<Fused<R, F, I, BT>, 4>::from_primitive(TensorPrimitive::Float(t));
        let (dx, dw, db) = unfold.backward(
            wrap4(x),
            Tensor::from_primitive(TensorPrimitive::Float(weight)),
            wrap4(dy),
            px.is_some(),
        );
        if let (Some(p), Some(dx)) = (px, dx) {
            grads.register::<Fused<R, F, I, BT>>(p.id, dx.into_primitive().tensor());
        }
        if let Some(p) = pw {
            grads.register::<Fused<R, F, I, BT>>(p.id, dw.into_primitive().tensor());
        }
        if let Some(p) = pb {
            grads.register::<Fused<R, F, I, BT>>(p.id, db.into_primitive().tensor());
        }
    }
}

/// This file's text, for `check-cuda-source` to find every launchable kernel declared here in
/// [`cuda_source_kernels`] (`occ_sparse::cuda_source::launchable_kernels`).
#[cfg(feature = "cuda-source")]
pub const KERNEL_SOURCE: &str = include_str!("conv2d_cube.rs");

/// Every configuration of this file's kernels that a CUDA launch can compile, for
/// `sparseocc check-cuda-source` (`occ_sparse::cuda_source`): each kernel with the backend's
/// float type, both address types and the cube shapes `CubeDim::new` gives one unit per value.
#[cfg(feature = "cuda-source")]
pub fn cuda_source_kernels(
    client: &cubecl::prelude::ComputeClient<occ_sparse::cuda_source::OfflineCuda>,
    float: cubecl::ir::StorageType,
) -> Vec<Box<dyn cubecl::prelude::CubeKernel>> {
    use cubecl::prelude::{CubeKernel, TensorCompilationArg};
    use kernel::*;
    use occ_sparse::cuda_source::{elementwise_cube_dims, launch_settings, OfflineCuda as R};
    let t = || TensorCompilationArg { inplace: None };
    let dims = || Im2colDimsCompilationArg {
        n: (),
        c: (),
        h: (),
        w: (),
        kh: (),
        kw: (),
        sh: (),
        sw: (),
        ph: (),
        pw: (),
        dh: (),
        dw: (),
        ho: (),
        wo: (),
        l0: (),
        lc: (),
    };
    let mut k: Vec<Box<dyn CubeKernel>> = Vec::new();
    for s in launch_settings(&elementwise_cube_dims(client)) {
        k.push(Box::new(im2col_kernel::Im2colKernel::<R>::new(
            s.clone(),
            client.clone(),
            t(),
            t(),
            dims(),
            float,
        )));
        k.push(Box::new(col2im_kernel::Col2imKernel::<R>::new(
            s,
            client.clone(),
            t(),
            t(),
            dims(),
            float,
        )));
    }
    k
}
