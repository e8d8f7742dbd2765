//! The image encoder's convolutions on the cubecl backends, in inference, as an im2col `#[cube]`
//! kernel and cubecl's matrix product.
//!
//! burn-cubecl 0.21 computes `conv2d` with its direct kernel when autotune is off (this project's
//! build: docs/gpu.md), one output value per unit looping over `C_in · k_h · k_w` products, and its
//! `unfold4d` is that same convolution with an identity weight. Here [`kernel::im2col_kernel`]
//! writes the unfolded input `[C_in·k_h·k_w, N·L]` (`L = H_out·W_out` output positions, in
//! column blocks of at most [`MAX_COLS_ELEMS`] values), one unit per value, and the convolution is
//! one matrix product `[C_out, C_in·k_h·k_w] x [C_in·k_h·k_w, N·L]`: cubecl's tiled matmul,
//! tensor cores where the device has them. A pointwise stride-1 convolution needs no
//! unfolding (its input already is that matrix). Every size is a runtime value, so the kernel
//! compiles once. Training keeps burn's convolution ([`crate::kernels::ModelBackend::conv2d_autodiff`]).
//! `SPARSEOCC_CUBE_CONV2D=direct` keeps burn's convolution in inference too (the peer on a GPU).

use crate::kernels::conv2d_host::{padding_of, Geometry};
use burn::nn::conv::Conv2d;
use burn::tensor::{Shape, Tensor, TensorPrimitive};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{BoolElement, CubeBackend, CubeRuntime, FloatElement, IntElement};
use burn_fusion::Fusion;
use cubecl::{calculate_cube_count_elemwise, CubeDim};
use occ_sparse::cube::{address_type_of, inputs_of, register_cube_op};
use std::sync::Arc;

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
        /// Output width.
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
}

/// Most values of one unfolded column block (128 MiB of f32: WebGPU's default largest storage
/// binding); a larger unfolding runs block by block.
pub const MAX_COLS_ELEMS: usize = 1 << 25;

occ_sparse::env_switch! {
    /// How the cubecl backends compute the image encoder's convolutions in inference.
    pub enum CubeConv2d: "SPARSEOCC_CUBE_CONV2D" {
        /// `im2col` (the default): [`kernel::im2col_kernel`] and cubecl's matrix product.
        Im2col = "im2col",
        /// `direct`: burn's `conv2d` (burn-cubecl's direct kernel without autotune).
        Direct = "direct",
    }
}

/// A fused cubecl backend.
type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;

/// One unfolding's geometry on the host.
#[derive(Clone, Copy, Debug)]
struct Unfold {
    n: usize,
    c: usize,
    g: Geometry,
}

impl Unfold {
    fn launch<R: CubeRuntime>(self, x: CubeTensor<R>, l0: usize, lc: usize) -> CubeTensor<R> {
        let x = into_contiguous(x);
        let g = self.g;
        let rows = self.c * g.kh * g.kw;
        let cols = empty_device_dtype(
            x.client.clone(),
            x.device.clone(),
            Shape::new([rows, self.n * lc]),
            x.dtype,
        );
        let units = self.n * rows * lc;
        let client = x.client.clone();
        let dim = CubeDim::new(&client, units);
        let count = calculate_cube_count_elemwise(&client, units, dim);
        let address = address_type_of(&[&x, &cols]);
        let dims = kernel::Im2colDimsLaunch::new(
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
            g.wo,
            l0,
            lc,
        );
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
    let rows = c * g.kh * g.kw;
    let positions = g.ho * g.wo;
    let weight = conv.weight.val().reshape([cout, rows]);
    // `[C_out, N, L]`, in column blocks.
    let y = if g.is_pointwise() {
        let x = x
            .reshape([n, c, positions])
            .swap_dims(0, 1)
            .reshape([c, n * positions]);
        weight.matmul(x).reshape([cout, n, positions])
    } else {
        let unfold = Unfold { n, c, g };
        let block = (MAX_COLS_ELEMS / (n * rows).max(1)).clamp(1, positions);
        let x = x.into_primitive().tensor();
        let mut parts = Vec::with_capacity(positions.div_ceil(block));
        for l0 in (0..positions).step_by(block) {
            let lc = block.min(positions - l0);
            let cols = register_cube_op::<R, F, I, BT>(
                "occ_model::im2col",
                vec![x.clone()],
                &[(Shape::new([rows, n * lc]), x.dtype)],
                Arc::new(move |t| {
                    let [x] = inputs_of(t);
                    vec![unfold.launch(x, l0, lc)]
                }),
            )
            .pop()
            .expect("one output");
            let cols =
                Tensor::<Fused<R, F, I, BT>, 2>::from_primitive(TensorPrimitive::Float(cols));
            parts.push(weight.clone().matmul(cols).reshape([cout, n, lc]));
        }
        Tensor::cat(parts, 2)
    };
    let y = y.swap_dims(0, 1);
    let y = y.reshape([n, cout, g.ho, g.wo]);
    Some(match &conv.bias {
        Some(b) => y + b.val().reshape([1, cout, 1, 1]),
        None => y,
    })
}
