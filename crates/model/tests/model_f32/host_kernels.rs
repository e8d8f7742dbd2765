//! The production CPU backends (`NdArray<f32>` for inference, `Autodiff<NdArray<f32>>` for
//! training) take the host kernels (see `common/kernel_checks`).

use crate::kernel_checks::{inference_calls, training_calls, RESNET18_CONVS};
use occ_model::kernels::HostKernelCalls;

#[test]
fn cpu_backends_take_the_host_kernels_f32() {
    type B = burn::backend::NdArray<f32>;
    let expected = HostKernelCalls {
        conv2d: RESNET18_CONVS + 1,
        dca: 1,
        ..Default::default()
    };
    assert_eq!(inference_calls::<B>(), expected);
    let expected = HostKernelCalls {
        conv2d_autodiff: RESNET18_CONVS,
        dca_autodiff: 1,
        ..Default::default()
    };
    assert_eq!(training_calls::<burn::backend::Autodiff<B>>(), expected);
}
