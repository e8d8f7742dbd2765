//! cubecl kernels of the sparse library, for the cubecl backends (CUDA, WebGPU) behind burn's
//! fusion layer: each kernel has a launcher on the raw `CubeBackend` tensors and a fusion custom
//! op that runs it inside the fused stream (as burn's backend-extension example does for
//! `Fusion<CubeBackend>`). Tested against the NdArray reference by `sparseocc check-backend`
//! (lavapipe when there is no GPU: docs/gpu.md).

use crate::backend::index_tensor;
use crate::rows::RowPlan;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Shape, Tensor as BurnTensor, TensorPrimitive};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{BoolElement, CubeBackend, CubeRuntime, FloatElement, IntElement};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::{Fusion, FusionRuntime};
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, OperationOutput, TensorIr};
use cubecl::{calculate_cube_count_elemwise, CubeDim};
use kernel::segment_sum_kernel;
use std::marker::PhantomData;

mod kernel {
    use cubecl::prelude::*;

    /// Segment sum over a grouped index list: output value `(r, c)` is the sum of
    /// `values[order[j], c]` for `j` in `offsets[r]..offsets[r + 1]`, in that order. One thread per
    /// output value; no atomics, so the result does not depend on scheduling.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn segment_sum_kernel<F: Numeric, I: Numeric>(
        values: &Tensor<F>,
        order: &Tensor<I>,
        offsets: &Tensor<I>,
        output: &mut Tensor<F>,
        channels: usize,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        if ABSOLUTE_POS >= output.len() {
            terminate!();
        }
        let row = ABSOLUTE_POS / channels;
        let col = ABSOLUTE_POS % channels;
        let start = usize::cast_from(offsets[row]);
        let end = usize::cast_from(offsets[row + 1]);
        let mut acc = F::from_int(0);
        for j in start..end {
            let h = usize::cast_from(order[j]);
            acc += values[h * channels + col];
        }
        output[ABSOLUTE_POS] = acc;
    }
}

/// Launches [`segment_sum_kernel`] on raw cubecl tensors.
///
/// # Shapes
/// - values: `[H, C]`, order: `[H]`, offsets: `[n_out + 1]` -> `[n_out, C]`
pub fn segment_sum<R: CubeRuntime>(
    values: CubeTensor<R>,
    order: CubeTensor<R>,
    offsets: CubeTensor<R>,
    n_out: usize,
) -> CubeTensor<R> {
    let values = into_contiguous(values);
    let order = into_contiguous(order);
    let offsets = into_contiguous(offsets);
    let channels = values.meta.shape()[1];
    let output = empty_device_dtype(
        values.client.clone(),
        values.device.clone(),
        Shape::new([n_out, channels]),
        values.dtype,
    );
    let working_units = n_out * channels;
    if working_units == 0 {
        return output;
    }
    let client = values.client.clone();
    let cube_dim = CubeDim::new(&client, working_units);
    let cube_count = calculate_cube_count_elemwise(&client, working_units, cube_dim);
    let address_type = [&values, &order, &offsets, &output]
        .iter()
        .map(|t| t.required_address_type())
        .max()
        .unwrap_or_default();
    let dtypes = [values.dtype.into(), order.dtype.into()];
    // SAFETY: every index is in range: `RowPlan` checks `dest < n_out`, so `order` holds input
    // rows `< H` and `offsets` is non-decreasing up to `H`; the output position is bounds-checked.
    unsafe {
        segment_sum_kernel::launch_unchecked(
            &client,
            cube_count,
            cube_dim,
            address_type,
            values.into_tensor_arg(),
            order.into_tensor_arg(),
            offsets.into_tensor_arg(),
            output.clone().into_tensor_arg(),
            channels,
            dtypes,
        )
    };
    output
}

/// Marks the runtime and element types an op is for, without holding any.
type TypesOf<R, F, I, BT> = PhantomData<fn() -> (R, F, I, BT)>;

/// The fusion custom op running [`segment_sum`].
struct SegmentSumOp<R, F, I, BT> {
    desc: CustomOpIr,
    n_out: usize,
    _backend: TypesOf<R, F, I, BT>,
}

impl<R, F, I, BT> std::fmt::Debug for SegmentSumOp<R, F, I, BT> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SegmentSumOp")
            .field("desc", &self.desc)
            .field("n_out", &self.n_out)
            .finish()
    }
}

impl<R, F, I, BT> Operation<FusionCubeRuntime<R>> for SegmentSumOp<R, F, I, BT>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    fn execute(
        &self,
        handles: &mut HandleContainer<<FusionCubeRuntime<R> as FusionRuntime>::FusionHandle>,
    ) {
        type Raw<R, F, I, BT> = CubeBackend<R, F, I, BT>;
        let ([values, order, offsets], [out]) = self.desc.as_fixed();
        let values = handles.get_float_tensor::<Raw<R, F, I, BT>>(values);
        let order = handles.get_int_tensor::<Raw<R, F, I, BT>>(order);
        let offsets = handles.get_int_tensor::<Raw<R, F, I, BT>>(offsets);
        let result = segment_sum::<R>(values, order, offsets, self.n_out);
        handles.register_float_tensor::<Raw<R, F, I, BT>>(&out.id, result);
    }
}

/// Row scatter-add ([`crate::rows`]) on a fused cubecl backend, as a [`segment_sum`] over the
/// plan's grouped rows.
pub fn fusion_scatter_add_rows<R, F, I, BT>(
    values: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    plan: &RowPlan,
) -> FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
    let values =
        BurnTensor::<Fused<R, F, I, BT>, 2>::from_primitive(TensorPrimitive::Float(values));
    let device = values.device();
    let order = index_tensor::<Fused<R, F, I, BT>>(plan.order(), &device).into_primitive();
    let offsets = index_tensor::<Fused<R, F, I, BT>>(plan.offsets(), &device).into_primitive();
    let values = values.into_primitive().tensor();
    let client = values.client.clone();
    let streams = OperationStreams::with_inputs([&values, &order, &offsets]);
    let out = TensorIr::uninit(
        client.create_empty_handle(),
        Shape::new([plan.n_out(), values.shape[1]]),
        values.dtype,
    );
    let desc = CustomOpIr::new(
        "occ_sparse::segment_sum",
        &[values.into_ir(), order.into_ir(), offsets.into_ir()],
        &[out],
    );
    client
        .register(
            streams,
            OperationIr::Custom(desc.clone()),
            SegmentSumOp::<R, F, I, BT> {
                desc,
                n_out: plan.n_out(),
                _backend: PhantomData,
            },
        )
        .output()
}
